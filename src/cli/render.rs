//! `mpiflow render`: one novel view from an MPI (.npz) or an RGB-D pair, written as PNG, .flo
//! and optionally .npy files.

use super::{parse_floats, CliError};
use clap::Args;
use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::io::image::{load_rgb, save_gray_png, save_rgb_png, ImageLimits, RgbImage};
use mpiflow::io::{colorwheel, flo, npy};
use mpiflow::mpi::layering::{build_mpi, Layering, LayeringOptions};
use mpiflow::mpi::npz::load_npz;
use mpiflow::mpi::Mpi;
use mpiflow::render::{render, Fields, Mode, Occupancy, RenderParams, Resample, Skip};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// An MPI in the reference .npz layout (mpi_rgb, mpi_sigma, disparity, optional K, G, mask_in).
    #[arg(long, value_name = "FILE.npz", conflicts_with_all = ["image", "depth"])]
    mpi: Option<PathBuf>,
    /// Source photo (PNG or JPEG); needs --depth.
    #[arg(long, value_name = "FILE", requires = "depth")]
    image: Option<PathBuf>,
    /// Depth of the source photo: float32 H x W .npy in the unit of the translation;
    /// non-finite or <= 0 means unknown.
    #[arg(long, value_name = "FILE.npy", requires = "image")]
    depth: Option<PathBuf>,
    /// Number of MPI planes built from RGB-D input (default: the scene models' default).
    #[arg(long, default_value_t = mpiflow::scene::models::ModelConfig::default().planes as u32, value_parser = clap::value_parser!(u32).range(1..=256))]
    planes: u32,
    /// How RGB-D pixels are assigned to planes: true-depth, soft or hard (default: the scene
    /// models' default, soft).
    #[arg(long, value_name = "KIND")]
    layering: Option<Layering>,
    /// Where the planes go in disparity: uniform or content (dense where the photo's depths are;
    /// default: the scene models' default, uniform).
    #[arg(long, value_name = "KIND")]
    placement: Option<mpiflow::mpi::layering::Placement>,
    /// Complete the background beside depth steps (default: the scene models' default, off).
    #[arg(long, value_name = "BOOL", num_args = 0..=1, default_missing_value = "true")]
    backdrop: Option<bool>,
    /// Source intrinsics fx,fy,cx,cy in pixels (default: K of the npz, else 0.58W,0.58H,0.5W,0.5H).
    #[arg(long, value_name = "FX,FY,CX,CY", value_parser = parse_floats::<4>, allow_hyphen_values = true)]
    intrinsics: Option<[f64; 4]>,
    /// Target intrinsics fx,fy,cx,cy (default: the source intrinsics).
    #[arg(long, value_name = "FX,FY,CX,CY", value_parser = parse_floats::<4>, allow_hyphen_values = true)]
    target_intrinsics: Option<[f64; 4]>,
    /// Rotation as an axis-angle vector in radians (X_tgt = R X_src + t).
    #[arg(long, value_name = "RX,RY,RZ", value_parser = parse_floats::<3>, allow_hyphen_values = true)]
    rotation: Option<[f64; 3]>,
    /// Translation (X_tgt = R X_src + t); a camera moving forward has negative tz.
    #[arg(long, value_name = "TX,TY,TZ", value_parser = parse_floats::<3>, allow_hyphen_values = true)]
    translation: Option<[f64; 3]>,
    /// `reference` reproduces the public implementation; `exact` ray-casts (coverage, validity, skipping).
    #[arg(long, default_value = "exact")]
    mode: Mode,
    /// Colour kernel of the exact-mode target view (density and masks stay bilinear; the
    /// reference mode is always bilinear).
    #[arg(long, value_name = "KERNEL", default_value_t = Resample::default(),
          value_parser = super::kernels::resample_parser())]
    resample: Resample,
    /// Alias-free minification of the exact-mode target view (planes the view shrinks are
    /// sampled from prefiltered levels).
    #[arg(long)]
    minify: bool,
    /// Output directory (created if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Also write image2.npy, flow.npy, depth2.npy, valid.npy (and mask2.npy with a mask channel).
    #[arg(long)]
    npy: bool,
}

fn intrinsics(v: [f64; 4], which: &str) -> Result<Intrinsics, CliError> {
    let k = Intrinsics::new(v[0], v[1], v[2], v[3]);
    if !k.is_valid() {
        return Err(CliError(format!("--{which}: focal lengths must be non-zero")));
    }
    Ok(k)
}

/// Loads an H x W depth map (also 1 x H x W or H x W x 1) matching the image size.
fn load_depth(path: &Path, w: usize, h: usize) -> Result<Vec<f32>, CliError> {
    let a = npy::read_npy_file(path).map_err(|e| CliError(format!("{}: {e}", path.display())))?;
    let dims: Vec<u64> = a.shape.iter().copied().filter(|&d| d != 1).collect();
    let ok = a.shape.len() >= 2
        && a.shape.len() <= 3
        && a.data.len() == w * h
        && (dims == [h as u64, w as u64] || (w == 1 || h == 1));
    if !ok {
        return Err(CliError(format!(
            "{}: depth has shape {:?}, expected [{h}, {w}] to match the image",
            path.display(),
            a.shape
        )));
    }
    Ok(a.data.iter().map(|&v| v as f32).collect())
}

pub fn run(a: RenderArgs) -> Result<(), CliError> {
    let (mut mpi, image1): (Mpi, Option<RgbImage>) = match (&a.mpi, &a.image, &a.depth) {
        (Some(path), _, _) => (load_npz(path)?, None),
        (None, Some(img), Some(dep)) => {
            let rgb = load_rgb(img, &ImageLimits::default())?;
            let depth = load_depth(dep, rgb.width, rgb.height)?;
            let d = mpiflow::scene::models::ModelConfig::default().layering_options();
            let opts = LayeringOptions {
                planes: a.planes as usize,
                layering: a.layering.unwrap_or(d.layering),
                placement: a.placement.unwrap_or(d.placement),
                backdrop: a.backdrop.unwrap_or(d.backdrop),
                ..d
            };
            let mpi = build_mpi(&rgb.data, &depth, rgb.width, rgb.height, &opts)
                .map_err(|e| CliError(format!("{}: {e}", dep.display())))?;
            (mpi, Some(rgb))
        }
        _ => return Err(CliError("give either --mpi FILE.npz, or --image FILE with --depth FILE.npy".into())),
    };
    let repaired = mpi.sanitize();
    if repaired.total() > 0 {
        eprintln!(
            "warning: repaired {} non-finite colour values and {} invalid densities in the MPI",
            repaired.nonfinite_color, repaired.bad_sigma
        );
    }
    let (w, h) = (mpi.width, mpi.height);
    let k_src = match a.intrinsics {
        Some(v) => intrinsics(v, "intrinsics")?,
        None => mpi.intrinsics.unwrap_or_else(|| Intrinsics::reference_default(w, h)),
    };
    let k_tgt = match a.target_intrinsics {
        Some(v) => intrinsics(v, "target-intrinsics")?,
        None => k_src,
    };
    let pose = match (a.rotation, a.translation) {
        (None, None) => mpi.pose.unwrap_or_default(),
        (r, t) => Pose::from_axis_angle(r.unwrap_or_default(), t.unwrap_or_default()),
    };
    let params = RenderParams {
        k_src,
        k_tgt,
        pose,
        mode: a.mode,
        fields: Fields::default(),
        skip: if a.mode == Mode::Exact { Skip::DEFAULT } else { Skip::NONE },
        links: [None, None],
        resample: a.resample,
        minify: a.minify,
    };
    // tile skipping as the pipeline skips (the same output; the plane samples below show it)
    let occ = (a.mode == Mode::Exact).then(|| Occupancy::build(&mpi, params.skip.tile_sigma_eps));
    let out = render::<f32>(&mpi, &params, occ.as_ref())?;
    if out.stats.repaired > 0 {
        eprintln!("warning: {} non-finite output values were replaced by 0", out.stats.repaired);
    }
    let image1 = match image1 {
        Some(img) => img,
        None => {
            // the MPI's own view: the same renderer under the identity motion
            let p = RenderParams {
                k_tgt: k_src,
                pose: Pose::identity(),
                fields: Fields { target: true, flow: false, occlusion: false },
                ..params
            };
            RgbImage { width: w, height: h, data: render::<f32>(&mpi, &p, None)?.image }
        }
    };
    write_outputs(&a.out, &image1, &out, a.npy)?;
    let valid = out.valid.iter().filter(|&&v| v == 1).count() as f64 / (w * h) as f64;
    let occluded = out.occlusion.iter().filter(|&&v| v == 1).count() as f64 / (w * h) as f64;
    println!(
        "rendered {w}x{h}, {} planes, mode {:?}: valid {:.1}%, occluded {:.1}% -> {}",
        mpi.planes(),
        a.mode,
        100.0 * valid,
        100.0 * occluded,
        a.out.display()
    );
    let st = &out.stats;
    println!(
        "target view: {} plane samples ({:.2} per pixel), {} left out by tile skipping, {} by early ray termination",
        st.samples,
        st.samples as f64 / (w * h) as f64,
        st.skipped_tile,
        st.skipped_early
    );
    Ok(())
}

fn write_outputs(
    dir: &Path,
    image1: &RgbImage,
    out: &mpiflow::render::RenderOutput,
    with_npy: bool,
) -> Result<(), CliError> {
    let (w, h) = (out.width, out.height);
    std::fs::create_dir_all(dir).map_err(|e| CliError(format!("cannot create {}: {e}", dir.display())))?;
    let ctx = |name: &str| {
        let p = dir.join(name);
        move |e: std::io::Error| CliError(format!("cannot write {}: {e}", p.display()))
    };
    let image2 = RgbImage { width: w, height: h, data: out.image.clone() };
    save_rgb_png(&dir.join("image1.png"), image1)?;
    save_rgb_png(&dir.join("image2.png"), &image2)?;
    flo::write_flo(&dir.join("flow.flo"), w, h, &out.flow).map_err(ctx("flow.flo"))?;
    let wheel = colorwheel::flow_to_color(&out.flow, w, h, None);
    save_rgb_png(
        &dir.join("flow.png"),
        &RgbImage { width: w, height: h, data: wheel.iter().map(|&v| v as f32 / 255.0).collect() },
    )?;
    let to255 = |m: &[u8]| m.iter().map(|&v| v * 255).collect::<Vec<u8>>();
    save_gray_png(&dir.join("valid.png"), w, h, &to255(&out.valid))?;
    save_gray_png(&dir.join("occlusion.png"), w, h, &to255(&out.occlusion))?;
    if with_npy {
        let (hu, wu) = (h as u64, w as u64);
        npy::write_f32(&dir.join("image2.npy"), &[hu, wu, 3], &out.image).map_err(ctx("image2.npy"))?;
        npy::write_f32(&dir.join("flow.npy"), &[hu, wu, 2], &out.flow).map_err(ctx("flow.npy"))?;
        npy::write_f32(&dir.join("depth2.npy"), &[hu, wu], &out.depth).map_err(ctx("depth2.npy"))?;
        npy::write_u8(&dir.join("valid.npy"), &[hu, wu], &out.valid).map_err(ctx("valid.npy"))?;
        if out.extra_channels > 0 {
            let mask: Vec<f32> = out.extras.iter().step_by(out.extra_channels).copied().collect();
            npy::write_f32(&dir.join("mask2.npy"), &[hu, wu], &mask).map_err(ctx("mask2.npy"))?;
        }
    }
    Ok(())
}
