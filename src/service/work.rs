//! The work of one sample before it is made, in work units: the pixels the renderer makes x the
//! frames x the taps of the resampling kernel (the texels read per output pixel and plane). The
//! dispatch charges a request's first samples this many units at the rate the samples made so far
//! have set (`pool::meter`; later samples by what the stream's latest took), and a request whose
//! largest sample is over `max_sample_work` is refused before any work. Planes and objects are
//! left to the measure: they are known only once the scene is built.

use super::config::ServiceConfig;
use super::encode::OutputSpec;
use super::error::{Reason, ServiceError};
use super::validate::sample_pixels_bound;
use crate::render::Resample;

/// Bytes a sample takes while it is made, per rendered pixel and frame, besides the raw
/// tensors of its fields: the renderer's and the merge's buffers of each view (colour, depth,
/// flow, weights and masks in f32). From the RSS an 8-frame clip of every field at 640x480 adds
/// per worker, about 220 MiB: 89 bytes per pixel-frame, 26 of them its raw fields.
pub const WORKSPACE_PER_PIXEL_FRAME: u64 = 64;

/// The bytes a sample of the request (`out`, `frames`) takes on its worker while it is made,
/// besides its encoded bytes: what the byte budget reserves for it from dispatch until it is
/// done (`pool::Produce::workspace`).
pub fn workspace(out: &OutputSpec, frames: usize, config: &ServiceConfig) -> u64 {
    let pixels = rendered_pixels(out, config);
    let raw: u64 = super::encode::bytes_per_pixel(&out.fields, frames, out.flow_f16).iter().map(|(_, b)| b).sum();
    pixels.saturating_mul((frames as u64).saturating_mul(WORKSPACE_PER_PIXEL_FRAME).saturating_add(raw))
}

/// The pixels the renderer makes for a sample of the request: the whole frame for an
/// augmentation (it renders, then crops), else the sample's own bound.
fn rendered_pixels(out: &OutputSpec, config: &ServiceConfig) -> u64 {
    if out.augment.is_some() {
        config.max_sample_pixels()
    } else {
        sample_pixels_bound(out, config)
    }
}

/// Work units in one unit of `max_sample_work`.
pub const UNITS_PER_MWORK: u64 = 1_000_000;

/// The texels a kernel reads per output pixel and plane.
pub fn taps(r: Resample) -> u64 {
    match r {
        Resample::Bilinear => 4,
        Resample::Bicubic | Resample::Bspline3 | Resample::Omoms3 => 16,
        Resample::Bspline5 | Resample::Lanczos3 => 36,
    }
}

/// The work units of a sample of `pixels` x `frames` with kernel `r`.
pub fn units(pixels: u64, frames: usize, r: Resample) -> u64 {
    pixels.saturating_mul(frames as u64).saturating_mul(taps(r))
}

/// The work units of the largest sample of a request (`out`, `frames`, kernel `r`), or
/// RESOURCE_EXHAUSTED naming `max_sample_work` when it is over it. An augmentation renders the
/// whole frame before it crops, a plain crop only its window.
pub fn admit(out: &OutputSpec, frames: usize, r: Resample, config: &ServiceConfig) -> Result<u64, ServiceError> {
    let pixels = rendered_pixels(out, config);
    let work = units(pixels, frames, r);
    let limit = config.max_sample_work.saturating_mul(UNITS_PER_MWORK);
    if work <= limit {
        return Ok(work);
    }
    Err(ServiceError::LimitExceeded(
        Reason::SampleTooLarge,
        format!(
            "sample too much work: up to {pixels} pixels x {frames} frames x {} taps ({r}) is {:.1} million work units, \
             over max_sample_work = {}; ask for fewer frames, a smaller crop or a kernel of fewer taps (bilinear 4, \
             bicubic and bspline3 16)",
            taps(r),
            work as f64 / UNITS_PER_MWORK as f64,
            config.max_sample_work
        ),
    ))
}

/// The workspace of the request's largest sample (`workspace`), or RESOURCE_EXHAUSTED naming
/// `max_buffered_mb` when it and the sample's encoded `bound` together are over the byte
/// `budget`: such a sample could never start within it.
pub fn admit_workspace(
    out: &OutputSpec,
    frames: usize,
    bound: u64,
    config: &ServiceConfig,
    budget: u64,
) -> Result<u64, ServiceError> {
    let ws = workspace(out, frames, config);
    if bound.saturating_add(ws) <= budget {
        return Ok(ws);
    }
    let mb = |b: u64| b as f64 / 1e6;
    Err(ServiceError::LimitExceeded(
        Reason::SampleTooLarge,
        format!(
            "sample too large: up to {} pixels x {frames} frames takes about {:.1} MB while it is made and up to \
             {:.1} MB sent, over the byte budget of samples being made and unsent (max_buffered_mb) of {:.1} MB; ask \
             for fewer fields or frames, a smaller crop, or a server with a larger max_buffered_mb",
            rendered_pixels(out, config),
            mb(ws),
            mb(bound),
            mb(budget)
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A clip of lanczos3 at 1920x1080 is over a bound that a pair at 640x480 is well within,
    /// and the refusal names the key and the kernel.
    #[test]
    fn a_sample_over_the_work_bound_is_refused_naming_it() {
        let c = ServiceConfig { size: Some("1920x1080".into()), max_sample_work: 64, ..ServiceConfig::default() };
        let out = OutputSpec::default();
        let e = admit(&out, 8, Resample::Lanczos3, &c).unwrap_err();
        let m = e.to_string();
        assert!(m.contains("max_sample_work = 64") && m.contains("lanczos3"), "{m}");
        let c = ServiceConfig { size: Some("640x480".into()), ..c };
        assert_eq!(admit(&out, 2, Resample::Bspline3, &c).unwrap(), 640 * 480 * 2 * 16);
    }
}
