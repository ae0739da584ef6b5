//! Object instances of an image: [`InstanceMasks`] from index PNGs, COCO JSON or models, and
//! their selection.

#[allow(clippy::wildcard_imports)]
use super::*;

// ---------------------------------------------------------------------------------------------
// instances

/// One object instance.
#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    /// The instance id (the value in an index PNG, the annotation id in COCO JSON).
    pub id: u32,
    /// Detection confidence (1.0 for given masks).
    pub score: f32,
    /// `H x W` values in [0, 1], row-major.
    pub mask: Vec<f32>,
    /// Pixels with mask value >= 0.5.
    pub area: f64,
    /// The COCO `category_id`, where known.
    pub category: Option<u32>,
}

impl Instance {
    /// An instance with its area computed from `mask`.
    pub fn new(id: u32, score: f32, mask: Vec<f32>) -> Self {
        let area = binary_area(&mask);
        Instance { id, score, mask, area, category: None }
    }
}

/// The number of values >= 0.5.
pub fn binary_area(mask: &[f32]) -> f64 {
    mask.iter().filter(|&&v| v >= 0.5).count() as f64
}

/// The object instances of one image.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct InstanceMasks {
    pub width: usize,
    pub height: usize,
    pub masks: Vec<Instance>,
}

/// The PNG file signature.
const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];

impl InstanceMasks {
    /// No instances.
    pub fn new(width: usize, height: usize) -> Self {
        InstanceMasks { width, height, masks: Vec::new() }
    }

    /// One instance per distinct non-zero id of a row-major `width x height` index map (0 =
    /// background), in increasing id order, with score 1.0 and area = its pixel count.
    pub fn from_index_map(ids: &[u32], width: usize, height: usize) -> Result<Self, MaskError> {
        Self::from_index_map_within(ids, width, height, usize::MAX).map_err(|e| match e {
            Err(e) => e,
            Ok(n) => size_err("index map", format!("{n} instances")), // no budget: never
        })
    }

    /// [`from_index_map`](Self::from_index_map) refusing, before the masks are allocated, an
    /// index map whose instances x pixels exceed `max_values` (`Err(Ok(instances))`).
    fn from_index_map_within(
        ids: &[u32],
        width: usize,
        height: usize,
        max_values: usize,
    ) -> Result<Self, Result<usize, MaskError>> {
        if Some(ids.len()) != width.checked_mul(height) {
            return Err(Err(size_err("index map", format!("{} values for {width} x {height} pixels", ids.len()))));
        }
        let mut counts: BTreeMap<u32, usize> = BTreeMap::new();
        for &id in ids.iter().filter(|&&id| id != 0) {
            *counts.entry(id).or_insert(0) += 1;
            if counts.len() > MAX_INSTANCES {
                return Err(Err(size_err(
                    "index map",
                    format!("more than {MAX_INSTANCES} distinct instance ids (MAX_INSTANCES)"),
                )));
            }
        }
        if counts.len().saturating_mul(ids.len()) > max_values {
            return Err(Ok(counts.len()));
        }
        let mut slot: BTreeMap<u32, usize> = BTreeMap::new();
        let mut masks: Vec<Instance> = Vec::with_capacity(counts.len());
        for (k, (&id, &count)) in counts.iter().enumerate() {
            slot.insert(id, k);
            masks.push(Instance { id, score: 1.0, mask: vec![0.0; ids.len()], area: count as f64, category: None });
        }
        let mut last: Option<(u32, usize)> = None;
        for (i, &id) in ids.iter().enumerate().filter(|(_, &id)| id != 0) {
            let k = match last {
                Some((lid, k)) if lid == id => k,
                _ => slot[&id],
            };
            last = Some((id, k));
            masks[k].mask[i] = 1.0;
        }
        Ok(InstanceMasks { width, height, masks })
    }

    /// Reads an instance-index PNG (the reference's `masks/NAME.png`) with the default limits;
    /// see [`from_index_png_with_limits`](Self::from_index_png_with_limits).
    pub fn from_index_png(path: &Path) -> Result<Self, MaskError> {
        Self::from_index_png_with_limits(path, &ImageLimits::default())
    }

    /// Reads an instance-index PNG: each distinct non-zero value is one instance (0 =
    /// background), as [`from_index_map`](Self::from_index_map).
    ///
    /// - 8- or 16-bit grey: the value is the id.
    /// - Grey with alpha: the value where alpha > 0, else background.
    /// - 8-bit RGB(A) (also palette PNGs, which the decoder expands to RGB): if every pixel has
    ///   R = G = B (grey saved as colour) the value R is the id; otherwise each colour is one
    ///   instance with id `R << 16 | G << 8 | B` (black = background); pixels with alpha 0 are
    ///   background.
    /// - 16-bit RGB(A) that is not grey, and anything that is not a PNG: refused.
    pub fn from_index_png_with_limits(path: &Path, limits: &ImageLimits) -> Result<Self, MaskError> {
        let mut sig = [0u8; 8];
        let is_png = std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut sig)).map(|_| sig == PNG_SIGNATURE);
        if let Ok(false) = is_png {
            return Err(MaskError::IndexPng {
                path: path.to_path_buf(),
                reason: "not a PNG file (instance masks must be lossless PNGs)".into(),
            });
        }
        // other failures (missing file, short file) are reported by the decoder
        let img = decode_file(path, limits)?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let ids = index_ids(&img).map_err(|reason| MaskError::IndexPng { path: path.to_path_buf(), reason })?;
        Self::from_index_png_ids(&ids, w, h, path, limits)
    }

    /// [`from_index_png_with_limits`](Self::from_index_png_with_limits) for a PNG held in memory
    /// (a shard member, an upload), named `name` in errors.
    pub fn from_index_png_bytes(bytes: &[u8], name: &str, limits: &ImageLimits) -> Result<Self, MaskError> {
        let path = Path::new(name);
        if !bytes.starts_with(&PNG_SIGNATURE) {
            return Err(MaskError::IndexPng {
                path: path.to_path_buf(),
                reason: "not a PNG file (instance masks must be lossless PNGs)".into(),
            });
        }
        let img = crate::io::image::decode_bytes(bytes, path, limits)?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let ids = index_ids(&img).map_err(|reason| MaskError::IndexPng { path: path.to_path_buf(), reason })?;
        Self::from_index_png_ids(&ids, w, h, path, limits)
    }

    /// The instances of an index PNG's ids within the mask budget: at most
    /// [`MAX_MASK_FRAMES`] x `limits.max_pixels` mask values (each instance is a full-frame f32
    /// mask), refused as [`MaskError::TooLarge`] before they are allocated.
    fn from_index_png_ids(
        ids: &[u32],
        w: usize,
        h: usize,
        path: &Path,
        limits: &ImageLimits,
    ) -> Result<Self, MaskError> {
        let budget = usize::try_from(limits.max_pixels).unwrap_or(usize::MAX).saturating_mul(MAX_MASK_FRAMES);
        Self::from_index_map_within(ids, w, h, budget).map_err(|e| match e {
            Err(e) => e.prefixed(&path.display().to_string()),
            Ok(n) => MaskError::TooLarge {
                path: path.to_path_buf(),
                reason: format!(
                    "{n} instances of {w} x {h} pixels are more mask values than the budget of {budget} \
                     ({MAX_MASK_FRAMES} frames of the pixel limit)"
                ),
            },
        })
    }

    /// The index map of the instances: each pixel gets the id of the instance with the largest
    /// mask value `>= threshold` there (ties: the earlier instance), 0 where none reaches it.
    pub fn to_index_map(&self, threshold: f32) -> Vec<u32> {
        let n = self.width * self.height;
        let mut ids = vec![0u32; n];
        let mut best = vec![f32::NEG_INFINITY; n];
        for inst in &self.masks {
            for (i, &v) in inst.mask.iter().enumerate().take(n) {
                if v >= threshold && v > best[i] {
                    best[i] = v;
                    ids[i] = inst.id;
                }
            }
        }
        ids
    }

    /// Writes [`to_index_map`](Self::to_index_map)`(0.5)` as a grey PNG: 8-bit when every id is
    /// at most 255, 16-bit when at most 65535; larger ids, an id 0, or an empty image are errors.
    pub fn save_index_png(&self, path: &Path) -> Result<(), MaskError> {
        let what = path.display().to_string();
        if self.masks.iter().any(|m| m.id == 0) {
            return Err(size_err(&what, "instance id 0 cannot be told from the background"));
        }
        let max_id = self.masks.iter().map(|m| m.id).max().unwrap_or(0);
        let ids = self.to_index_map(0.5);
        if max_id <= 255 {
            let bytes: Vec<u8> = ids.iter().map(|&v| v as u8).collect();
            save_gray_png(path, self.width, self.height, &bytes)?;
        } else if max_id <= 65535 {
            let words: Vec<u16> = ids.iter().map(|&v| v as u16).collect();
            save_gray16_png(path, self.width, self.height, &words)?;
        } else {
            return Err(size_err(&what, format!("instance id {max_id} does not fit in a 16-bit PNG")));
        }
        Ok(())
    }

    /// Instances from COCO annotations: a JSON list of annotation objects, or an object with
    /// such a list under `"annotations"`. Each annotation needs `"segmentation"`: an RLE object
    /// `{"counts": string | [int], "size": [h, w]}` (the size must equal `h, w`), or a list of
    /// polygons `[[x0, y0, ...], ...]` (a flat `[x0, y0, ...]` is one polygon; polygons of fewer
    /// than 3 points are skipped, where pycocotools would read a 4-number one as a box).
    /// Optional: `"score"` (default 1.0), `"id"` (default: position + 1), `"category_id"`.
    /// Errors name the field, e.g. `annotations[3].segmentation.counts`.
    pub fn from_coco_json(value: &Value, h: usize, w: usize) -> Result<Self, MaskError> {
        pixel_count(h, w)?;
        let list = match value {
            Value::Array(a) => a,
            Value::Object(o) => match o.get("annotations") {
                Some(Value::Array(a)) => a,
                _ => return Err(json_err("annotations", "expected a list of annotations or {\"annotations\": [...]}")),
            },
            _ => return Err(json_err("annotations", "expected a list of annotations or {\"annotations\": [...]}")),
        };
        if list.len() > MAX_INSTANCES {
            return Err(size_err("annotations", format!("{} annotations, more than {MAX_INSTANCES}", list.len())));
        }
        let mut masks = Vec::with_capacity(list.len());
        for (i, ann) in list.iter().enumerate() {
            let field = format!("annotations[{i}]");
            masks.push(annotation(ann, &field, i, h, w)?);
        }
        Ok(InstanceMasks { width: w, height: h, masks })
    }

    /// [`from_coco_json`](Self::from_coco_json) of a JSON file; errors name the file.
    pub fn from_coco_json_file(path: &Path, h: usize, w: usize) -> Result<Self, MaskError> {
        let name = path.display().to_string();
        let text = std::fs::read(path).map_err(|e| {
            MaskError::Image(if e.kind() == std::io::ErrorKind::NotFound {
                ImageError::NotFound { path: path.to_path_buf() }
            } else {
                ImageError::Io { path: path.to_path_buf(), source: e }
            })
        })?;
        let value: Value = serde_json::from_slice(&text).map_err(|e| json_err(&name, format!("invalid JSON: {e}")))?;
        Self::from_coco_json(&value, h, w).map_err(|e| e.prefixed(&name))
    }

    /// Up to `k` instances to move: those with an area of at least `min_area_fraction` of the
    /// image (and not empty), by decreasing score (NaN last), then decreasing area, then
    /// increasing id, then position. Returns indices into [`masks`](Self::masks).
    pub fn select_objects(&self, k: usize, min_area_fraction: f64) -> Vec<usize> {
        let min_area = min_area_fraction * (self.width * self.height) as f64;
        let mut idx: Vec<usize> =
            (0..self.masks.len()).filter(|&i| self.masks[i].area > 0.0 && self.masks[i].area >= min_area).collect();
        let score = |i: usize| {
            let s = self.masks[i].score;
            if s.is_nan() {
                f32::NEG_INFINITY
            } else {
                s
            }
        };
        idx.sort_by(|&a, &b| {
            score(b)
                .total_cmp(&score(a))
                .then(self.masks[b].area.total_cmp(&self.masks[a].area))
                .then(self.masks[a].id.cmp(&self.masks[b].id))
                .then(a.cmp(&b))
        });
        idx.truncate(k);
        idx
    }

    /// Every mask resized with [`resize_nearest`], areas recomputed.
    pub fn resize_nearest(&self, new_width: usize, new_height: usize) -> Self {
        self.resized(new_width, new_height, resize_nearest)
    }

    /// The `cw x ch` window at `(x0, y0)` of every mask ([`crop`](super::resize::crop)), areas
    /// recomputed.
    pub fn cropped(&self, x0: usize, y0: usize, cw: usize, ch: usize) -> Self {
        let masks = self
            .masks
            .iter()
            .map(|m| {
                let mask = super::resize::crop(&m.mask, self.width, 1, x0, y0, cw, ch);
                Instance { area: binary_area(&mask), mask, ..m.clone() }
            })
            .collect();
        InstanceMasks { width: cw, height: ch, masks }
    }

    /// Every mask resized with [`resize_bilinear`], areas recomputed.
    pub fn resize_bilinear(&self, new_width: usize, new_height: usize) -> Self {
        self.resized(new_width, new_height, resize_bilinear)
    }

    fn resized(&self, nw: usize, nh: usize, f: fn(&[f32], usize, usize, usize, usize) -> Vec<f32>) -> Self {
        let masks = self
            .masks
            .iter()
            .map(|m| {
                let mask = f(&m.mask, self.width, self.height, nw, nh);
                Instance { area: binary_area(&mask), mask, ..m.clone() }
            })
            .collect();
        InstanceMasks { width: nw, height: nh, masks }
    }
}

/// Instance ids of the pixels of a decoded index PNG (see `from_index_png_with_limits`).
fn index_ids(img: &DynamicImage) -> Result<Vec<u32>, String> {
    fn colour<T: Copy + Into<u32>>(raw: &[T], ch: usize, wide: bool) -> Result<Vec<u32>, String> {
        let px = || raw.chunks_exact(ch).map(|p| (p[0].into(), p[1].into(), p[2].into(), ch == 4 && p[3].into() == 0));
        let grey = px().all(|(r, g, b, transparent)| transparent || (r == g && g == b));
        if grey {
            return Ok(px().map(|(r, _, _, transparent)| if transparent { 0 } else { r }).collect());
        }
        if wide {
            return Err("a 16-bit colour PNG cannot be read as instance ids (use 8- or 16-bit grey)".into());
        }
        Ok(px().map(|(r, g, b, transparent)| if transparent { 0 } else { (r << 16) | (g << 8) | b }).collect())
    }
    fn grey_alpha<T: Copy + Into<u32>>(raw: &[T]) -> Vec<u32> {
        raw.chunks_exact(2).map(|p| if p[1].into() == 0 { 0 } else { p[0].into() }).collect()
    }
    match img {
        DynamicImage::ImageLuma8(b) => Ok(b.as_raw().iter().map(|&v| u32::from(v)).collect()),
        DynamicImage::ImageLuma16(b) => Ok(b.as_raw().iter().map(|&v| u32::from(v)).collect()),
        DynamicImage::ImageLumaA8(b) => Ok(grey_alpha(b.as_raw())),
        DynamicImage::ImageLumaA16(b) => Ok(grey_alpha(b.as_raw())),
        DynamicImage::ImageRgb8(b) => colour(b.as_raw(), 3, false),
        DynamicImage::ImageRgba8(b) => colour(b.as_raw(), 4, false),
        DynamicImage::ImageRgb16(b) => colour(b.as_raw(), 3, true),
        DynamicImage::ImageRgba16(b) => colour(b.as_raw(), 4, true),
        other => Err(format!("a {:?} image cannot be read as instance ids (use 8- or 16-bit grey)", other.color())),
    }
}

fn as_u32(v: &Value, what: &str) -> Result<u32, MaskError> {
    v.as_u64()
        .and_then(|x| u32::try_from(x).ok())
        .ok_or_else(|| json_err(what, format!("expected an integer in 0..=4294967295, found {v}")))
}

fn as_coords(v: &Value, what: &str) -> Result<Vec<f64>, MaskError> {
    let Value::Array(a) = v else {
        return Err(json_err(what, format!("expected a list of coordinates, found {}", kind(v))));
    };
    a.iter()
        .enumerate()
        .map(|(j, c)| {
            c.as_f64().ok_or_else(|| json_err(&format!("{what}[{j}]"), format!("expected a number, found {c}")))
        })
        .collect()
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
}

/// One COCO annotation object.
fn annotation(ann: &Value, field: &str, i: usize, h: usize, w: usize) -> Result<Instance, MaskError> {
    let Value::Object(o) = ann else {
        return Err(json_err(field, format!("expected an annotation object, found {}", kind(ann))));
    };
    let seg_field = format!("{field}.segmentation");
    let seg = o.get("segmentation").ok_or_else(|| json_err(field, "no \"segmentation\""))?;
    let mask: Vec<u8> = match seg {
        Value::Object(r) => {
            let size_field = format!("{seg_field}.size");
            let size = match r.get("size") {
                Some(Value::Array(s)) if s.len() == 2 => [as_u32(&s[0], &size_field)?, as_u32(&s[1], &size_field)?],
                _ => return Err(json_err(&size_field, "expected [height, width]")),
            };
            if (size[0] as usize, size[1] as usize) != (h, w) {
                return Err(size_err(
                    &size_field,
                    format!("RLE of {} x {} for an image of {h} x {w}", size[0], size[1]),
                ));
            }
            let counts_field = format!("{seg_field}.counts");
            let counts = match r.get("counts") {
                Some(Value::String(s)) => RleCounts::Compressed(s.clone()),
                Some(Value::Array(a)) => RleCounts::Uncompressed(
                    a.iter()
                        .enumerate()
                        .map(|(j, c)| as_u32(c, &format!("{counts_field}[{j}]")))
                        .collect::<Result<_, _>>()?,
                ),
                _ => return Err(json_err(&counts_field, "expected a compressed RLE string or a list of counts")),
            };
            rle_decode(&counts, h, w).map_err(|e| e.in_field(&counts_field))?
        }
        Value::Array(a) => {
            let polys: Vec<Vec<f64>> = if a.first().is_some_and(Value::is_number) {
                vec![as_coords(seg, &seg_field)?]
            } else {
                a.iter()
                    .enumerate()
                    .map(|(j, p)| as_coords(p, &format!("{seg_field}[{j}]")))
                    .collect::<Result<_, _>>()?
            };
            let mut mask = vec![0u8; h * w];
            for (j, p) in polys.iter().enumerate().filter(|(_, p)| p.len() >= 6 || p.len() % 2 != 0) {
                let pf = format!("{seg_field}[{j}]");
                let rle = polygon_to_rle(p, h, w).map_err(|e| e.in_field(&pf))?;
                let m = rle_decode_counts(&rle, h, w).map_err(|e| e.in_field(&pf))?;
                mask.iter_mut().zip(&m).for_each(|(a, &b)| *a |= b);
            }
            mask
        }
        other => {
            return Err(json_err(
                &seg_field,
                format!("expected an RLE object or a list of polygons, found {}", kind(other)),
            ))
        }
    };
    let score = match o.get("score") {
        None | Some(Value::Null) => 1.0,
        Some(v) => {
            v.as_f64().ok_or_else(|| json_err(&format!("{field}.score"), format!("expected a number, found {v}")))?
                as f32
        }
    };
    let id = match o.get("id") {
        None | Some(Value::Null) => u32::try_from(i + 1).unwrap_or(u32::MAX),
        Some(v) => as_u32(v, &format!("{field}.id"))?,
    };
    let category = match o.get("category_id") {
        None | Some(Value::Null) => None,
        Some(v) => Some(as_u32(v, &format!("{field}.category_id"))?),
    };
    let area = mask.iter().filter(|&&v| v != 0).count() as f64;
    Ok(Instance { id, score, mask: mask.into_iter().map(f32::from).collect(), area, category })
}
