//! `mpiflow models`: the named scene models (`list`), fetching one into the hub cache (`fetch`),
//! and checking a model on this machine (`check`: its contract, its time per photo, a depth or
//! mask preview).

use std::path::PathBuf;
use std::time::Instant;

use clap::{Args, Subcommand};
use mpiflow::io::image::{load_rgb, ImageLimits, RgbImage};
use mpiflow::raster::{Grid, InstanceMasks};
use mpiflow::scene::hub::{sha256_file, Hub};
use mpiflow::scene::registry::{self, Contract, Role};

use super::CliError;

#[derive(Subcommand, Debug)]
pub enum ModelsCommand {
    /// The named models: name, role, licence, hub file, and whether it is in the cache.
    List,
    /// Download a named model into the hub cache (verified by its SHA-256) and print its path.
    Fetch {
        /// A name from `mpiflow models list`.
        name: String,
    },
    /// Load a depth or segmentation model (NAME or FILE), print the contract it runs with, time
    /// it on a photo and write the photo's depth preview (PNG, white = near) or mask preview (the
    /// photo dimmed, each object found in its own colour).
    Check(CheckArgs),
}

#[derive(Args, Debug)]
pub struct CheckArgs {
    /// A name from `mpiflow models list`, or an ONNX file (with its optional FILE.toml manifest).
    model: PathBuf,
    /// The photo (default: a 640x480 grey image).
    #[arg(long, value_name = "PHOTO")]
    image: Option<PathBuf>,
    /// Timed runs after the first (warm-up) run.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..=100))]
    runs: u64,
    /// The preview (default: depth-preview.png for a depth model, mask-preview.png for a
    /// segmenter).
    #[arg(long, value_name = "FILE.png")]
    out: Option<PathBuf>,
}

pub fn run(c: ModelsCommand) -> Result<(), CliError> {
    let hub = Hub::from_env();
    match c {
        ModelsCommand::List => {
            for e in registry::registry()? {
                let file = e.hub_file();
                let cached = hub.cached_path(&file);
                let state =
                    if cached.is_file() { format!("cached at {}", cached.display()) } else { "not cached".into() };
                println!("{}  ({}, {})  {}", e.name, e.role, e.licence, e.description);
                println!("    {} -> {state}", hub.url(&file));
                println!("    sha256 {}; {}", e.sha256, e.contract.describe(e.role));
            }
            println!(
                "hub cache: {}{}",
                hub.cache.display(),
                if hub.offline { " (HF_HUB_OFFLINE: cache only)" } else { "" }
            );
            Ok(())
        }
        ModelsCommand::Fetch { name } => {
            let r = registry::resolve(std::path::Path::new(&name), role_of(&name)?, &hub, true)?;
            println!("{}", r.path.display());
            Ok(())
        }
        ModelsCommand::Check(a) => check(&a, &hub),
    }
}

/// The role of a registry name (an unknown name is an error listing the names).
fn role_of(name: &str) -> Result<Role, CliError> {
    match registry::find(name)? {
        Some(e) => Ok(e.role),
        None => {
            let names: Vec<String> = registry::registry()?.into_iter().map(|e| e.name).collect();
            Err(CliError(format!("{name}: no model of that name (named models: {})", names.join(", "))))
        }
    }
}

/// The role a FILE's contract describes: its `output_kind`'s, else segmentation when it names
/// segmentation outputs, else depth.
fn file_role(c: &Contract) -> Role {
    match c.output_kind {
        Some(kind) => kind.role(),
        None if c.masks_output.is_some() || c.scores_output.is_some() || c.logits_output.is_some() => Role::Segment,
        None => Role::Depth,
    }
}

fn check(a: &CheckArgs, hub: &Hub) -> Result<(), CliError> {
    let role = if a.model.is_file() {
        file_role(&registry::resolve(&a.model, Role::Depth, hub, false)?.contract)
    } else {
        role_of(&a.model.to_string_lossy())?
    };
    let r = registry::resolve(&a.model, role, hub, true)?;
    println!(
        "model: {} ({} bytes, sha256 {})",
        r.path.display(),
        std::fs::metadata(&r.path)?.len(),
        sha256_file(&r.path)?
    );
    match &r.entry {
        Some(e) => println!("registry: {} ({}), {}@{} {}", e.name, e.licence, e.repo, e.revision, e.file),
        None if registry::manifest_path(&r.path).is_file() => {
            println!("manifest: {}", registry::manifest_path(&r.path).display());
        }
        None => println!("manifest: none (the default contract)"),
    }
    println!("contract: {}", r.contract.describe(role));
    if role == Role::Segment {
        return check_segmenter(a, &r);
    }
    let t = Instant::now();
    let model = registry::load_depth(&r)?;
    println!("loaded and warmed up in {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let image = photo(a)?;
    // a first run (allocations, caches), then the timed ones
    let mut disparity = model.estimate(&image)?;
    let t = Instant::now();
    for _ in 0..a.runs {
        disparity = model.estimate(&image)?;
    }
    print_time(t, a, &image);
    let pixels: Vec<u8> = disparity.data.iter().map(|&d| (d.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    let preview = image::GrayImage::from_raw(disparity.width as u32, disparity.height as u32, pixels)
        .ok_or_else(|| CliError("the depth map has the wrong size".into()))?;
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("depth-preview.png"));
    preview.save(&out).map_err(|e| CliError(format!("{}: {e}", out.display())))?;
    println!("depth preview: {} (white = near)", out.display());
    Ok(())
}

/// `--image`, or a 640x480 grey image.
fn photo(a: &CheckArgs) -> Result<RgbImage, CliError> {
    match &a.image {
        Some(p) => load_rgb(p, &ImageLimits::default()).map_err(|e| CliError(format!("--image: {e}"))),
        None => Ok(RgbImage { width: 640, height: 480, data: vec![0.5; 640 * 480 * 3] }),
    }
}

fn print_time(t: Instant, a: &CheckArgs, image: &RgbImage) {
    let ms = t.elapsed().as_secs_f64() * 1e3 / a.runs as f64;
    println!(
        "{ms:.0} ms per photo ({}x{} photo, mean of {} runs after one untimed run, {} threads available)",
        image.width,
        image.height,
        a.runs,
        std::thread::available_parallelism().map_or(1, usize::from)
    );
}

/// A segmenter's check: the instances it finds on the photo, its time, the mask preview.
fn check_segmenter(a: &CheckArgs, r: &registry::Resolved) -> Result<(), CliError> {
    let t = Instant::now();
    let model = registry::load_segmenter(r)?;
    println!("loaded and warmed up in {:.0} ms", t.elapsed().as_secs_f64() * 1e3);
    let image = photo(a)?;
    let mut masks = model.segment(&image)?;
    let t = Instant::now();
    for _ in 0..a.runs {
        masks = model.segment(&image)?;
    }
    print_time(t, a, &image);
    if masks.masks.is_empty() {
        println!("objects: none found (the photo's samples move the camera only)");
    }
    for m in &masks.masks {
        let class = m.category.map_or("-".to_string(), |c| c.to_string());
        println!("object {}: class {class}, score {:.3}, {} pixels", m.id, m.score, m.area);
    }
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("mask-preview.png"));
    mask_preview(&image, &masks).save(&out).map_err(|e| CliError(format!("{}: {e}", out.display())))?;
    println!("mask preview: {} (the photo dimmed, each object in its own colour)", out.display());
    Ok(())
}

/// The photo at half brightness with each instance's pixels (mask >= 0.5) blended half with its
/// colour.
fn mask_preview(image: &RgbImage, masks: &InstanceMasks) -> image::RgbImage {
    const COLOURS: [[f32; 3]; 6] =
        [[1.0, 0.2, 0.2], [0.2, 1.0, 0.2], [0.2, 0.4, 1.0], [1.0, 1.0, 0.2], [1.0, 0.2, 1.0], [0.2, 1.0, 1.0]];
    let g = Grid::new(image.width, image.height);
    image::RgbImage::from_fn(image.width as u32, image.height as u32, |x, y| {
        let i = g.index(x as usize, y as usize);
        let mut px = [0.0f32; 3];
        for (c, v) in px.iter_mut().enumerate() {
            *v = image.data[i * 3 + c] * 0.5;
        }
        if let Some((k, _)) = masks.masks.iter().enumerate().find(|(_, m)| m.mask[i] >= 0.5) {
            for (c, v) in px.iter_mut().enumerate() {
                *v += COLOURS[k % COLOURS.len()][c] * 0.5;
            }
        }
        image::Rgb(px.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
    })
}
