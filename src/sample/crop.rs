//! The crop: what a request asks ([`CropSpec`]), its window (centre, or a position from the
//! sample's own random stream) and the cut of every field of a sample.

use crate::geometry::Intrinsics;
use crate::rng::{Purpose, SampleRng};
use crate::sample::augment::clear_valid_outside;
pub use crate::sample::error::CropTooLarge;
use crate::sample::types::{ClipFrame, LinkFields, Sample, SampleAddress};

/// How to cut samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CropSpec {
    /// 0 = the rendered width.
    pub width: u32,
    /// 0 = the rendered height.
    pub height: u32,
    pub random: bool,
}

/// The random stream of a sample's crop position: `Purpose::Other(CROP_PURPOSE)` of its address.
pub const CROP_PURPOSE: u32 = 0x6372_6f70; // "crop"

/// The crop window `(x0, y0, width, height)` of a `w` x `h` frame; a crop larger than the frame
/// in either side is an error (0 = the rendered side).
/// Centre: `(w - cw) / 2`; random: `x0 = below(w - cw + 1)`, then `y0 = below(h - ch + 1)`, from
/// the address's crop stream.
pub fn crop_window(
    spec: &CropSpec,
    w: usize,
    h: usize,
    address: SampleAddress,
) -> Result<(usize, usize, usize, usize), CropTooLarge> {
    let cw = if spec.width == 0 { w } else { spec.width as usize };
    let ch = if spec.height == 0 { h } else { spec.height as usize };
    if cw > w || ch > h {
        return Err(CropTooLarge { want_w: cw, want_h: ch, w, h });
    }
    if spec.random {
        let mut rng = SampleRng::new(address.dataset, address.seed, address.index, Purpose::Other(CROP_PURPOSE));
        let x0 = rng.below((w - cw + 1) as u64) as usize;
        let y0 = rng.below((h - ch + 1) as u64) as usize;
        Ok((x0, y0, cw, ch))
    } else {
        Ok(((w - cw) / 2, (h - ch) / 2, cw, ch))
    }
}

/// The intrinsics of the window at (x0, y0) of a frame with intrinsics `k`.
pub fn window_intrinsics(k: Intrinsics, x0: usize, y0: usize) -> Intrinsics {
    Intrinsics::new(k.fx, k.fy, k.cx - x0 as f64, k.cy - y0 as f64)
}

/// Clears `valid` and `occlusion` (either may be empty) where the flow target leaves the `w` x
/// `h` window: what lies outside it is not the sample's, so a pixel that moves there is neither
/// valid nor called occluded.
pub fn clear_outside(flow: &[f32], valid: &mut [u8], occlusion: &mut [u8], w: usize, h: usize) {
    for m in [valid, occlusion] {
        if !m.is_empty() {
            clear_valid_outside(flow, m, w, h);
        }
    }
}

/// The `cw` x `ch` window at (x0, y0) of a `w`-wide plane of `channels` values per pixel (empty stays empty).
pub(crate) fn crop_plane<T: Copy>(
    data: &[T],
    w: usize,
    channels: usize,
    x0: usize,
    y0: usize,
    cw: usize,
    ch: usize,
) -> Vec<T> {
    if data.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(cw * ch * channels);
    for y in y0..y0 + ch {
        out.extend_from_slice(&data[(y * w + x0) * channels..(y * w + x0 + cw) * channels]);
    }
    out
}

/// A flow with its masks cut to the window (`valid` and the occlusion cleared where the target leaves it).
fn crop_link(l: &LinkFields, w: usize, x0: usize, y0: usize, cw: usize, ch: usize) -> LinkFields {
    let flow = crop_plane(&l.flow, w, 2, x0, y0, cw, ch);
    let mut valid = crop_plane(&l.valid, w, 1, x0, y0, cw, ch);
    let mut occlusion = crop_plane(&l.occlusion, w, 1, x0, y0, cw, ch);
    clear_outside(&flow, &mut valid, &mut occlusion, cw, ch);
    LinkFields { flow, valid, occlusion }
}

/// Cuts every field of `s` to the window; the flow values stay (a displacement does not change
/// when both images are cut alike), and `valid` and the occlusion are cleared where the flow
/// target leaves the crop (the renderer's rule: target inside `[0, cw - 1] x [0, ch - 1]`;
/// [`clear_outside`]).
pub fn crop_sample(s: &Sample, x0: usize, y0: usize, cw: usize, ch: usize) -> Sample {
    let w = s.width;
    let flow = crop_plane(&s.flow, w, 2, x0, y0, cw, ch);
    let mut valid = crop_plane(&s.valid, w, 1, x0, y0, cw, ch);
    let mut occlusion = crop_plane(&s.occlusion, w, 1, x0, y0, cw, ch);
    clear_outside(&flow, &mut valid, &mut occlusion, cw, ch);
    Sample {
        address: s.address,
        source_id: s.source_id.clone(),
        width: cw,
        height: ch,
        image1: crop_plane(&s.image1, w, 3, x0, y0, cw, ch),
        image2: crop_plane(&s.image2, w, 3, x0, y0, cw, ch),
        flow,
        valid,
        occlusion,
        mask1: crop_plane(&s.mask1, w, 1, x0, y0, cw, ch),
        mask2: crop_plane(&s.mask2, w, 1, x0, y0, cw, ch),
        camera: s.camera.clone(),
        objects: s.objects.clone(),
        depth1: crop_plane(&s.depth1, w, 1, x0, y0, cw, ch),
        depth2: crop_plane(&s.depth2, w, 1, x0, y0, cw, ch),
        holes: crop_plane(&s.holes, w, 1, x0, y0, cw, ch),
        inpainted_pixels: s.inpainted_pixels,
        backward: crop_link(&s.backward, w, x0, y0, cw, ch),
        clip: s
            .clip
            .iter()
            .map(|f| ClipFrame {
                image: crop_plane(&f.image, w, 3, x0, y0, cw, ch),
                forward: crop_link(&f.forward, w, x0, y0, cw, ch),
                backward: crop_link(&f.backward, w, x0, y0, cw, ch),
                mask: crop_plane(&f.mask, w, 1, x0, y0, cw, ch),
                depth: crop_plane(&f.depth, w, 1, x0, y0, cw, ch),
                holes: crop_plane(&f.holes, w, 1, x0, y0, cw, ch),
            })
            .collect(),
        skipped_sources: s.skipped_sources,
        provenance: s.provenance.clone(),
        intrinsics: window_intrinsics(s.intrinsics, x0, y0),
        timings: s.timings,
    }
}
