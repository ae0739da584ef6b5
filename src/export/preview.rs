//! Preview contact sheets: `OUT/previews/preview-I.png`, one row per sample, each row five
//! panels of `panel_width` pixels: image1 | image2 | flow colour (Middlebury wheel, normalised by
//! the sample's largest flow) | object labels (coloured over a dimmed image1) | validity
//! (light grey = valid, red = valid but occluded in image2, black = invalid).
//!
//! A clip (more than two frames) draws one row per consecutive pair: frame k | frame k + 1 |
//! flow k -> k + 1 | frame k's labels | validity of that flow.
//!
//! A sheet starts at the first sample written and at every sample whose index is a multiple of
//! `every`, and takes that sample and the following ones until it holds `rows` rows (or the run
//! ends, or the next sheet starts). `I` is the index of its first row.

use std::path::{Path, PathBuf};

use ::image::imageops::{self, FilterType};
use ::image::{ExtendedColorType, ImageBuffer, Rgb};

use super::fields::{encode_png, sample_key};
use super::layout::write_atomic;
use super::ExportError;
use crate::io::colorwheel;
use crate::sample::Sample;

/// Panels per row.
pub const PANELS: usize = 5;
/// Pixels between panels, rows and around the sheet.
pub const GAP: usize = 2;
/// Sheet background.
const BACKGROUND: [u8; 3] = [24, 24, 24];

/// Colours of object labels 1, 2, ... (cycled): matplotlib's tab10.
pub const LABEL_COLORS: [[u8; 3]; 10] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
];
const VALID_COLOR: [u8; 3] = [220, 220, 220];
const OCCLUDED_COLOR: [u8; 3] = [230, 40, 40];
const INVALID_COLOR: [u8; 3] = [0, 0, 0];

/// When and how previews are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreviewOptions {
    /// A sheet starts at every index that is a multiple of this (and at the first sample); 0
    /// turns previews off.
    pub every: u64,
    /// Rows (samples) per sheet, >= 1.
    pub rows: usize,
    /// Width of one panel in pixels, >= 8; panel height keeps the sample's aspect ratio.
    pub panel_width: usize,
}

impl Default for PreviewOptions {
    fn default() -> Self {
        Self { every: 100, rows: 4, panel_width: 160 }
    }
}

/// Size of one panel for a `width` x `height` sample.
pub fn panel_size(width: usize, height: usize, panel_width: usize) -> (usize, usize) {
    let h = ((height as f64) * (panel_width as f64) / (width.max(1) as f64)).round() as usize;
    (panel_width, h.max(1))
}

/// Size of a sheet whose rows come from samples of these (width, height).
pub fn sheet_size(samples: &[(usize, usize)], panel_width: usize) -> (usize, usize) {
    let width = GAP + PANELS * (panel_width + GAP);
    let height = GAP + samples.iter().map(|&(w, h)| panel_size(w, h, panel_width).1 + GAP).sum::<usize>();
    (width, height)
}

type Rgb8 = ImageBuffer<Rgb<u8>, Vec<u8>>;

fn to_buffer(width: usize, height: usize, rgb: Vec<u8>) -> Rgb8 {
    ImageBuffer::from_raw(width as u32, height as u32, rgb).expect("buffer size checked by the caller")
}

/// Resizes to the panel size: a triangle filter when shrinking a photo-like panel, nearest
/// neighbour for label panels and when enlarging.
fn fit(img: &Rgb8, pw: usize, ph: usize, smooth: bool) -> Rgb8 {
    if img.width() as usize == pw && img.height() as usize == ph {
        return img.clone();
    }
    let shrinking = (img.width() as usize) > pw;
    let filter = if smooth && shrinking { FilterType::Triangle } else { FilterType::Nearest };
    imageops::resize(img, pw as u32, ph as u32, filter)
}

fn label_color(label: u8) -> [u8; 3] {
    LABEL_COLORS[(usize::from(label) + LABEL_COLORS.len() - 1) % LABEL_COLORS.len()]
}

/// Object labels over image1 dimmed to a third.
fn objects_panel(s: &Sample) -> Vec<u8> {
    let mut out = Vec::with_capacity(s.width * s.height * 3);
    for (px, &label) in s.image1.chunks_exact(3).zip(&s.mask1) {
        if label == 0 {
            out.extend(px.iter().map(|&c| c / 3));
        } else {
            let col = label_color(label);
            out.extend(px.iter().zip(col).map(|(&c, k)| ((u16::from(c) / 3 + u16::from(k) * 2) / 3) as u8));
        }
    }
    out
}

fn validity_panel(s: &Sample) -> Vec<u8> {
    let mut out = Vec::with_capacity(s.width * s.height * 3);
    for (&v, &o) in s.valid.iter().zip(&s.occlusion) {
        let c = if v == 0 {
            INVALID_COLOR
        } else if o != 0 {
            OCCLUDED_COLOR
        } else {
            VALID_COLOR
        };
        out.extend_from_slice(&c);
    }
    out
}

/// One row of a sheet.
#[derive(Clone, Debug)]
pub struct PreviewRow {
    pub index: u64,
    panels: Vec<Rgb8>,
    pub panel_height: usize,
}

/// Draws the row of one sample (the sample must have consistent buffers, see
/// [`super::fields::check_sample`]).
pub fn preview_row(index: u64, s: &Sample, panel_width: usize) -> PreviewRow {
    let (w, h) = (s.width, s.height);
    let (pw, ph) = panel_size(w, h, panel_width);
    let flow_rgb = colorwheel::flow_to_color(&s.flow, w, h, None);
    let panels = vec![
        fit(&to_buffer(w, h, s.image1.clone()), pw, ph, true),
        fit(&to_buffer(w, h, s.image2.clone()), pw, ph, true),
        fit(&to_buffer(w, h, flow_rgb), pw, ph, true),
        fit(&to_buffer(w, h, objects_panel(s)), pw, ph, false),
        fit(&to_buffer(w, h, validity_panel(s)), pw, ph, false),
    ];
    PreviewRow { index, panels, panel_height: ph }
}

/// The pairs of a sample as pair samples: itself for a pair; for a clip of K frames the K - 1
/// consecutive pairs (frame k, frame k + 1, the flow k -> k + 1 and its masks, frame k's labels).
pub fn pairs_of(s: &Sample) -> Vec<Sample> {
    let mut out = vec![Sample { clip: Vec::new(), ..s.clone() }];
    let mut prev = (s.image2.clone(), s.mask2.clone());
    for c in &s.clip {
        out.push(Sample {
            image1: prev.0.clone(),
            image2: c.image.clone(),
            flow: c.forward.flow.clone(),
            valid: c.forward.valid.clone(),
            occlusion: c.forward.occlusion.clone(),
            mask1: prev.1.clone(),
            mask2: c.mask.clone(),
            clip: Vec::new(),
            ..s.clone()
        });
        prev = (c.image.clone(), c.mask.clone());
    }
    out
}

/// Lays rows out into one sheet; returns (width, height, RGB bytes).
pub fn compose_sheet(rows: &[PreviewRow], panel_width: usize) -> (usize, usize, Vec<u8>) {
    let width = GAP + PANELS * (panel_width + GAP);
    let height = GAP + rows.iter().map(|r| r.panel_height + GAP).sum::<usize>();
    let mut sheet: Rgb8 = ImageBuffer::from_pixel(width as u32, height as u32, Rgb(BACKGROUND));
    let mut y = GAP;
    for row in rows {
        for (i, panel) in row.panels.iter().enumerate() {
            let x = GAP + i * (panel_width + GAP);
            imageops::replace(&mut sheet, panel, x as i64, y as i64);
        }
        y += row.panel_height + GAP;
    }
    (width, height, sheet.into_raw())
}

/// `DIR/preview-I.png`.
pub fn preview_path(dir: &Path, first_index: u64) -> PathBuf {
    dir.join(format!("preview-{}.png", sample_key(first_index)))
}

/// Collects rows and writes a sheet whenever one is complete.
pub struct PreviewCollector {
    dir: PathBuf,
    options: PreviewOptions,
    current: Vec<PreviewRow>,
    /// Samples in `current` (a clip draws one row per pair).
    current_samples: usize,
    seen_any: bool,
    written: Vec<PathBuf>,
}

impl PreviewCollector {
    /// Sheets go to `dir` (created on the first sheet).
    pub fn new(dir: &Path, options: PreviewOptions) -> Result<Self, ExportError> {
        if options.every > 0 && (options.rows == 0 || options.panel_width < 8) {
            return Err(ExportError::Invalid(format!(
                "preview sheets need at least 1 row and panels at least 8 pixels wide (rows {}, panel width {})",
                options.rows, options.panel_width
            )));
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            options,
            current: Vec::new(),
            current_samples: 0,
            seen_any: false,
            written: Vec::new(),
        })
    }

    fn starts_sheet(&self, index: u64) -> bool {
        !self.seen_any || index.is_multiple_of(self.options.every)
    }

    /// Offers the next sample written (in writing order).
    pub fn add(&mut self, index: u64, s: &Sample) -> Result<(), ExportError> {
        if self.options.every == 0 {
            return Ok(());
        }
        let starts = self.starts_sheet(index);
        if starts {
            self.flush()?;
        }
        if starts || !self.current.is_empty() {
            let rows: Vec<PreviewRow> = if s.clip.is_empty() {
                vec![preview_row(index, s, self.options.panel_width)]
            } else {
                pairs_of(s).iter().map(|p| preview_row(index, p, self.options.panel_width)).collect()
            };
            self.current.extend(rows);
            self.current_samples += 1;
        }
        self.seen_any = true;
        if self.current_samples >= self.options.rows {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), ExportError> {
        if self.current.is_empty() {
            return Ok(());
        }
        std::fs::create_dir_all(&self.dir).map_err(|source| ExportError::Io { path: self.dir.clone(), source })?;
        let (w, h, rgb) = compose_sheet(&self.current, self.options.panel_width);
        let png = encode_png(w, h, &rgb, ExtendedColorType::Rgb8)?;
        let path = preview_path(&self.dir, self.current[0].index);
        write_atomic(&path, &png)?;
        self.written.push(path);
        self.current.clear();
        self.current_samples = 0;
        Ok(())
    }

    /// Writes the sheet in progress; returns every sheet written.
    pub fn finish(mut self) -> Result<Vec<PathBuf>, ExportError> {
        self.flush()?;
        Ok(std::mem::take(&mut self.written))
    }
}
