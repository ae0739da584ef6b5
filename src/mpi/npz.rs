//! Import of an MPI from `.npz` in the public reference layout: `mpi_rgb` [1?,N,3,H,W],
//! `mpi_sigma` [1?,N,1,H,W], `disparity` [1?,N] (near to far), optional `K` [1?,3,3],
//! optional `G` [4,4] (X_tgt = R X_src + t) and optional `mask_in` [1?,1,H,W] (one 2-D mask
//! shared by all planes, as the reference uses it) or [1?,N,C,H,W] (per-plane channels).

use super::{Mpi, MpiError};
use crate::geometry::{Intrinsics, Pose};
use crate::io::npy::{read_array, Array};
use std::path::Path;

/// Loads an MPI. Values are not sanitised here; call [`Mpi::sanitize`].
pub fn load_npz(path: &Path) -> Result<Mpi, MpiError> {
    load_npz_limited(path, u64::MAX)
}

/// [`load_npz`] refusing arrays of more than `max_values` values in all, by the shapes in their
/// headers before their data is read (an `.npz` is a zip: a small file can hold huge arrays of
/// zeros).
pub fn load_npz_limited(path: &Path, max_values: u64) -> Result<Mpi, MpiError> {
    let p = path.display().to_string();
    let file = std::fs::File::open(path).map_err(|e| MpiError::Io { path: p.clone(), source: e })?;
    load_npz_from(std::io::BufReader::new(file), &p, max_values)
}

/// [`load_npz_limited`] of an `.npz` held in memory (a shard member); `name` is what errors call
/// it.
pub fn load_npz_bytes_limited(bytes: &[u8], name: &str, max_values: u64) -> Result<Mpi, MpiError> {
    load_npz_from(std::io::Cursor::new(bytes), name, max_values)
}

/// [`load_npz_limited`] of any seekable reader; `p` names it in errors.
fn load_npz_from<R: std::io::Read + std::io::Seek>(reader: R, p: &str, max_values: u64) -> Result<Mpi, MpiError> {
    let p = p.to_string();
    // the archive's and parser's messages as one printable line
    let reason = |e: &dyn std::fmt::Display| crate::failure::printable(&e.to_string(), 300);
    let mut npz = npyz::npz::NpzArchive::new(reader).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound | std::io::ErrorKind::PermissionDenied => {
            MpiError::Io { path: p.clone(), source: e }
        }
        _ => MpiError::BadArchive { path: p.clone(), reason: reason(&e) },
    })?;
    let mut values = 0u64;
    let mut get = |key: &'static str| -> Result<Option<Array>, MpiError> {
        let bad = |e: &dyn std::fmt::Display| MpiError::BadArchive {
            path: p.clone(),
            reason: format!("array `{key}`: {}", reason(e)),
        };
        // the member's npy header length, checked against its size before the parser allocates it
        let member = npyz::npz::file_name_from_array_name(key);
        if let Ok(mut z) = npz.zip_archive().by_name(&member) {
            let size = z.size();
            crate::io::npy::check_header(&mut z, size).map_err(|e| bad(&e))?;
        }
        match npz.by_name(key) {
            Ok(Some(f)) => {
                let n = f.shape().iter().try_fold(1u64, |a, &d| a.checked_mul(d)).unwrap_or(u64::MAX);
                values = values.saturating_add(n);
                if values > max_values {
                    let m = format!("shape {:?} brings the arrays over the limit of {max_values} values", f.shape());
                    return Err(bad(&m));
                }
                read_array(f).map(Some).map_err(|e| bad(&e))
            }
            Ok(None) => Ok(None),
            Err(e) => Err(bad(&e)),
        }
    };
    let need = |a: Option<Array>, key: &'static str| a.ok_or(MpiError::MissingKey { path: p.clone(), key });
    let rgb = need(get("mpi_rgb")?, "mpi_rgb")?.squeeze_leading(4);
    let sigma = need(get("mpi_sigma")?, "mpi_sigma")?.squeeze_leading(4);
    let disp = need(get("disparity")?, "disparity")?.squeeze_leading(1);
    let k = get("K")?.map(|a| a.squeeze_leading(2));
    let g = get("G")?.map(|a| a.squeeze_leading(2));
    let mask = get("mask_in")?;
    let shape_err = |key: &str, a: &Array, expected: &str| MpiError::BadShape {
        path: p.clone(),
        key: key.to_string(),
        shape: a.shape.clone(),
        expected: expected.to_string(),
    };

    if rgb.shape.len() != 4 || rgb.shape[1] != 3 {
        return Err(shape_err("mpi_rgb", &rgb, "[1?, N, 3, H, W]"));
    }
    let (n, h, w) = (rgb.shape[0] as usize, rgb.shape[2] as usize, rgb.shape[3] as usize);
    if sigma.shape != [n as u64, 1, h as u64, w as u64] {
        return Err(shape_err("mpi_sigma", &sigma, &format!("[1?, {n}, 1, {h}, {w}]")));
    }
    if disp.shape != [n as u64] {
        return Err(shape_err("disparity", &disp, &format!("[1?, {n}]")));
    }
    let mut mpi = Mpi::new(w, h, disp.data.clone(), 0);
    let hw = w * h;
    for i in 0..n {
        let plane = mpi.plane_rgba_mut(i);
        for c in 0..3 {
            let src = &rgb.data[(i * 3 + c) * hw..(i * 3 + c + 1) * hw];
            for (j, &v) in src.iter().enumerate() {
                plane[4 * j + c] = v as f32;
            }
        }
        for (j, &v) in sigma.data[i * hw..(i + 1) * hw].iter().enumerate() {
            plane[4 * j + 3] = v as f32;
        }
    }
    if let Some(m) = mask {
        attach_mask(&mut mpi, &m, (n, h, w), &p)?;
    }
    if let Some(k) = k {
        let arr: [f64; 9] = k.data.as_slice().try_into().map_err(|_| shape_err("K", &k, "[1?, 3, 3]"))?;
        mpi.intrinsics = Some(
            Intrinsics::from_row_major(&arr)
                .ok_or_else(|| MpiError::Invalid(format!("{p}: `K` is not a pinhole intrinsics matrix: {arr:?}")))?,
        );
    }
    if let Some(g) = g {
        let arr: [f64; 16] = g.data.as_slice().try_into().map_err(|_| shape_err("G", &g, "[4, 4]"))?;
        let pose = Pose::from_row_major_4x4(&arr);
        if !pose.is_finite() {
            return Err(MpiError::Invalid(format!("{p}: `G` is not finite")));
        }
        mpi.pose = Some(pose);
    }
    mpi.validate().map_err(|e| MpiError::Invalid(format!("{p}: {e}")))?;
    Ok(mpi)
}

/// `mask_in` as the MPI's extra channels (`n` planes of `h` x `w`): one 2-D mask shared by all
/// planes, or per-plane channels; `p` names the file in errors.
fn attach_mask(mpi: &mut Mpi, m: &Array, (n, h, w): (usize, usize, usize), p: &str) -> Result<(), MpiError> {
    let hw = w * h;
    let dims = m.shape.len();
    let (per_plane, channels) = match (dims, m.shape.as_slice()) {
        (2, [mh, mw]) if (*mh as usize, *mw as usize) == (h, w) => (false, 1),
        (3, [1, mh, mw]) if (*mh as usize, *mw as usize) == (h, w) => (false, 1),
        (4, [1, 1, mh, mw]) if (*mh as usize, *mw as usize) == (h, w) => (false, 1),
        (4, [mn, c, mh, mw]) if (*mn as usize, *mh as usize, *mw as usize) == (n, h, w) => (true, *c as usize),
        (5, [1, mn, c, mh, mw]) if (*mn as usize, *mh as usize, *mw as usize) == (n, h, w) => (true, *c as usize),
        _ => {
            return Err(MpiError::BadShape {
                path: p.to_string(),
                key: "mask_in".to_string(),
                shape: m.shape.clone(),
                expected: format!("[1?, 1, {h}, {w}] or [1?, {n}, C, {h}, {w}]"),
            })
        }
    };
    mpi.extra_channels = channels;
    mpi.extras = vec![0.0; n * hw * channels];
    for i in 0..n {
        for c in 0..channels {
            let src =
                if per_plane { &m.data[(i * channels + c) * hw..(i * channels + c + 1) * hw] } else { &m.data[..hw] };
            for (j, &v) in src.iter().enumerate() {
                mpi.extras[(i * hw + j) * channels + c] = v as f32;
            }
        }
    }
    Ok(())
}

/// The element type of the colour and density arrays an `.npz` is written with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MpiDtype {
    /// float32: lossless.
    F32,
    /// float16 (half the bytes): colours rounded to 11 significant bits, densities too and
    /// capped at 65504 (the largest finite f16; an opacity of 1 - exp(-65504 d) is 1 for any
    /// plane spacing d the layerings make). The cost: `mpiflow bench accuracy`, "MPI stored as
    /// f16".
    F16,
}

impl MpiDtype {
    /// The name `bake.json` records (`f32` / `f16`).
    pub fn as_str(self) -> &'static str {
        match self {
            MpiDtype::F32 => "f32",
            MpiDtype::F16 => "f16",
        }
    }
}

/// Writes `mpi` as an `.npz` in the layout [`load_npz`] reads (and the reference writes):
/// `mpi_rgb` and `mpi_sigma` in `dtype` (`[N, 3, H, W]`, `[N, 1, H, W]`), `disparity` f64 `[N]`
/// (near to far, exactly as held), `K` f64 `[3, 3]` when the MPI has intrinsics, `G` f64 `[4, 4]`
/// when it has a pose, and `mask_in` f32 `[N, C, H, W]` when it has extra channels. Lossless in
/// f32: loading the file gives back the same values bit for bit. Members are deflated, as NumPy's
/// `savez_compressed`, and dated 1980-01-01: the bytes depend on the MPI only, not on when it was
/// written. A packed MPI is written densely ([`Mpi::unpacked`]).
pub fn save_npz_as<W: std::io::Write + std::io::Seek>(mpi: &Mpi, writer: W, dtype: MpiDtype) -> std::io::Result<W> {
    use npyz::WriterBuilder;
    let mpi = &*mpi.unpacked();
    fn member<T: npyz::AutoSerialize + Copy, W: std::io::Write + std::io::Seek>(
        npz: &mut npyz::npz::NpzWriter<W>,
        name: &str,
        shape: &[u64],
        data: impl IntoIterator<Item = T>,
    ) -> std::io::Result<()> {
        // a fixed member time (1980-01-01, zip's epoch), not the clock: the same MPI gives the
        // same bytes at any time
        let options = npyz::zip::write::FileOptions::default().last_modified_time(npyz::zip::DateTime::default());
        let mut w = npz.array::<T>(name, options)?.default_dtype().shape(shape).begin_nd()?;
        w.extend(data)?;
        w.finish()
    }
    let (n, h, w, hw) = (mpi.planes(), mpi.height, mpi.width, mpi.plane_len());
    let (n64, h64, w64) = (n as u64, h as u64, w as u64);
    let mut npz = npyz::npz::NpzWriter::new(writer);
    let rgb = (0..n).flat_map(|i| (0..3).flat_map(move |c| (0..hw).map(move |j| mpi.plane_rgba(i)[4 * j + c])));
    let sigma = (0..n).flat_map(|i| (0..hw).map(move |j| mpi.plane_rgba(i)[4 * j + 3]));
    let (rgb_shape, sigma_shape) = ([n64, 3, h64, w64], [n64, 1, h64, w64]);
    match dtype {
        MpiDtype::F32 => {
            member(&mut npz, "mpi_rgb", &rgb_shape, rgb)?;
            member(&mut npz, "mpi_sigma", &sigma_shape, sigma)?;
        }
        MpiDtype::F16 => {
            // a sanitised MPI holds finite values; NaN would stay NaN, so it is made 0 here too
            let half = |v: f32, cap: f32| half::f16::from_f32(if v.is_nan() { 0.0 } else { v.clamp(-cap, cap) });
            let max = half::f16::MAX.to_f32();
            member(&mut npz, "mpi_rgb", &rgb_shape, rgb.map(|v| half(v, max)))?;
            member(&mut npz, "mpi_sigma", &sigma_shape, sigma.map(|v| half(v, max)))?;
        }
    }
    member(&mut npz, "disparity", &[n64], mpi.disparity.iter().copied())?;
    if let Some(k) = mpi.intrinsics {
        member(&mut npz, "K", &[3, 3], [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0])?;
    }
    if let Some(p) = mpi.pose {
        let (r, t) = (p.rotation, p.translation);
        let row = |i: usize| [r.col(0)[i], r.col(1)[i], r.col(2)[i], t[i]];
        let g = [row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]];
        member(&mut npz, "G", &[4, 4], g.into_iter().flatten())?;
    }
    let c = mpi.extra_channels;
    if c > 0 {
        let extras =
            (0..n).flat_map(|i| (0..c).flat_map(move |ch| (0..hw).map(move |j| mpi.extras[(i * hw + j) * c + ch])));
        member(&mut npz, "mask_in", &[n64, c as u64, h64, w64], extras)?;
    }
    npz.zip_writer().finish().map_err(std::io::Error::other)
}
