//! The bundled default source: a handful of RGB-D scenes composed procedurally from the bundled
//! photos (`examples/photos/`, CC0 / public domain), with **exact** depth and instance masks, so
//! that the service and `mpiflow generate` work with no model files and no `--source`.
//!
//! This is a stand-in, not photographs with real depth: the geometry is invented and the photos
//! are pasted onto it. Real use wants a depth model or depth given with the source.
//!
//! # Composition of scene `i`
//!
//! All random numbers come from [`SampleRng`] keyed by (`BUILTIN_KEY`, seed, i), using only the
//! documented primitives and IEEE `+ - * / sqrt`, so the scenes are the same on every run and
//! machine of one architecture. The camera is the reference default (`fx = 0.58 W`,
//! `fy = 0.58 H`, centre), looking along +z with y pointing down.
//!
//! 1. **Background**: photo `i mod P` (photos sorted by name), randomly cropped to the scene's
//!    aspect ratio (zoom 1 to 1.25, random position, random horizontal flip) and resized to
//!    `W x H`. Its geometry is a room corner: a ground plane `Y = h` (camera height `h` in
//!    [1.2, 1.8]) and a back wall slanted about the vertical axis, `z = z_w + s X` (`z_w` in
//!    [6, 10], slope `s` in [-0.35, 0.35]). A pixel's depth is the nearer of the two surfaces
//!    along its ray: wall `z_w / (1 - s a)` with `a = (x - cx) / fx`, ground `h fy / (y - cy)` for
//!    rows below the horizon ([`BackgroundGeometry::depth`]).
//! 2. **Objects**: 2 or 3 cut-outs (ellipses or rounded rectangles) of the *other* photos, each a
//!    fronto-parallel billboard standing on the ground at depth `z_o` in
//!    `[1.02 z_bottom, min(0.6 z_w, 5)]` (`z_bottom` = the ground's depth on the bottom row, so its
//!    foot `y = cy + fy h / z_o` is inside the image), world height `(0.7..1.4) h`, aspect
//!    0.6 to 1.4, at a random column. A soft contact shadow darkens the ground under each
//!    (colour only). Objects are drawn far to near; each visible pixel of object `k` has depth
//!    exactly `z_o` and instance id `k + 1` in the masks (0 = background).
//!
//! The item carries the exact depth ([`GivenDepth::Depth`]), the masks and the intrinsics; the
//! scene stage brings the depth to the scene scale (`disparity = d_min / d`, nearest content at 1).

use super::dir::resize_rgb;
use super::{FailureKind, Fnv64, GivenDepth, Source, SourceError, SourceItem};
use crate::geometry::Intrinsics;
use crate::io::image::{load_rgb, ImageLimits, RgbImage};
use crate::raster::grid::pixel_values;
use crate::raster::{Grid, InstanceMasks};
use crate::rng::{Purpose, SampleRng};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// The dataset word of the composition's random streams.
pub const BUILTIN_KEY: u64 = 0x6d70_6966_6c6f_7762; // "mpiflowb"

/// The environment variable that overrides the default photo folder.
pub const PHOTOS_ENV: &str = "MPIFLOW_PHOTOS";

/// The bundled photos: `$MPIFLOW_PHOTOS` if set, else `examples/photos` of the crate checkout.
pub fn default_photos_dir() -> PathBuf {
    match std::env::var_os(PHOTOS_ENV) {
        Some(p) if !p.is_empty() => PathBuf::from(p),
        _ => Path::new(env!("CARGO_MANIFEST_DIR")).join("examples").join("photos"),
    }
}

/// How the built-in scenes are made.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltinOptions {
    /// Folder of `.png`/`.jpg`/`.jpeg` photos (at least one).
    pub photos_dir: PathBuf,
    /// Number of scenes.
    pub count: usize,
    pub width: usize,
    pub height: usize,
    /// Seed of the composition (not of the samples).
    pub seed: u64,
    /// Limits for decoding the photos.
    pub limits: ImageLimits,
}

impl Default for BuiltinOptions {
    /// 8 scenes of 640 x 480 from [`default_photos_dir`], seed 0.
    fn default() -> Self {
        BuiltinOptions {
            photos_dir: default_photos_dir(),
            count: 8,
            width: 640,
            height: 480,
            seed: 0,
            limits: ImageLimits::default(),
        }
    }
}

/// The background geometry of a scene (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BackgroundGeometry {
    /// Height of the camera above the ground plane `Y = camera_height` (y down).
    pub camera_height: f64,
    /// Depth of the back wall on the optical axis.
    pub wall_depth: f64,
    /// The wall is `z = wall_depth + wall_slope * X`.
    pub wall_slope: f64,
}

impl BackgroundGeometry {
    /// The exact depth (z) of the background at pixel (x, y) for intrinsics `k`: the nearer of
    /// wall and ground along the pixel's ray.
    pub fn depth(&self, k: &Intrinsics, x: f64, y: f64) -> f64 {
        let a = (x - k.cx) / k.fx;
        let wall = self.wall_depth / (1.0 - self.wall_slope * a);
        let b = (y - k.cy) / k.fy;
        if b > 0.0 {
            let ground = self.camera_height / b;
            if ground < wall {
                return ground;
            }
        }
        wall
    }
}

/// The outline of a cut-out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Shape {
    Ellipse,
    /// A rectangle with corners rounded by a quarter of its smaller side.
    RoundedRect,
}

/// One pasted cut-out.
#[derive(Clone, Debug, PartialEq)]
pub struct PlacedObject {
    /// Its id in the masks.
    pub id: u32,
    /// The photo it was cut from.
    pub photo: String,
    pub shape: Shape,
    /// Its exact depth (a fronto-parallel billboard).
    pub depth: f64,
    /// Bounding box in pixels, `[x0, y0, x1, y1)` clipped to the image.
    pub bbox: [usize; 4],
    /// Visible pixels (after nearer objects are drawn).
    pub visible_pixels: usize,
}

/// A composed scene with everything the composition knows.
#[derive(Clone, Debug)]
pub struct Composition {
    pub id: String,
    pub image: RgbImage,
    /// Exact depth, H x W, all finite and > 0.
    pub depth: Vec<f32>,
    /// Instance ids, H x W (0 = background).
    pub ids: Vec<u32>,
    pub intrinsics: Intrinsics,
    pub background_photo: String,
    pub background: BackgroundGeometry,
    /// In drawing order (far to near).
    pub objects: Vec<PlacedObject>,
}

type PhotoSlot = OnceLock<Result<Arc<RgbImage>, (String, FailureKind, String)>>;

/// The bundled default source (see the module documentation).
#[derive(Debug)]
pub struct BuiltinSource {
    options: BuiltinOptions,
    /// (file name, size in bytes), sorted by name.
    photos: Vec<(String, u64)>,
    decoded: Vec<PhotoSlot>,
    fingerprint: u64,
}

impl BuiltinSource {
    /// The default: 8 scenes of 640 x 480 from the bundled photos.
    pub fn open_default() -> Result<Self, SourceError> {
        Self::open(&BuiltinOptions::default())
    }

    /// Lists the photo folder (names and sizes only; photos are decoded on first use). An
    /// unreadable folder, one without photos, zero scenes or an empty size is an error.
    pub fn open(options: &BuiltinOptions) -> Result<Self, SourceError> {
        let dir = &options.photos_dir;
        if options.count == 0 || options.width < 16 || options.height < 16 {
            return Err(SourceError::Invalid(format!(
                "builtin source: {} scenes of {} x {} requested; need at least one scene of 16 x 16 or more",
                options.count, options.width, options.height
            )));
        }
        let not_found = |m: String| {
            SourceError::file(
                dir.display().to_string(),
                FailureKind::Decode,
                format!("{m} (the bundled photos live in examples/photos of the repository; set {PHOTOS_ENV} to another folder)"),
            )
        };
        let rd = std::fs::read_dir(dir).map_err(|e| not_found(format!("cannot list the photo folder: {e}")))?;
        let mut photos = Vec::new();
        for ent in rd.flatten() {
            let Ok(name) = ent.file_name().into_string() else { continue };
            let ext = Path::new(&name).extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
            if !matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
                continue;
            }
            if let Ok(meta) = std::fs::metadata(ent.path()) {
                if meta.is_file() {
                    photos.push((name, meta.len()));
                }
            }
        }
        photos.sort();
        if photos.is_empty() {
            return Err(not_found("no .png or .jpg photos".into()));
        }
        let mut h = Fnv64::new();
        h.str("mpiflow builtin scenes v1")
            .u64(options.count as u64)
            .u64(options.width as u64)
            .u64(options.height as u64)
            .u64(options.seed);
        for (name, size) in &photos {
            h.str(name).u64(*size);
        }
        let decoded = (0..photos.len()).map(|_| OnceLock::new()).collect();
        Ok(BuiltinSource { options: options.clone(), photos, decoded, fingerprint: h.finish() })
    }

    pub fn options(&self) -> &BuiltinOptions {
        &self.options
    }

    /// The photo file names, sorted.
    pub fn photos(&self) -> Vec<String> {
        self.photos.iter().map(|(n, _)| n.clone()).collect()
    }

    fn photo(&self, k: usize) -> Result<Arc<RgbImage>, SourceError> {
        let slot = self.decoded[k].get_or_init(|| {
            let p = self.options.photos_dir.join(&self.photos[k].0);
            load_rgb(&p, &self.options.limits).map(Arc::new).map_err(|e| {
                let ps = p.display().to_string();
                let m = e.to_string();
                let m = m.strip_prefix(&format!("{ps}: ")).map(str::to_string).unwrap_or(m);
                (ps, e.failure_kind(), m)
            })
        });
        slot.clone().map_err(|(path, kind, message)| SourceError::File { path, kind, message })
    }

    fn stem(&self, k: usize) -> String {
        let n = &self.photos[k].0;
        Path::new(n).file_stem().and_then(|s| s.to_str()).unwrap_or(n).to_string()
    }

    /// Composes scene `i` (see the module documentation).
    pub fn compose(&self, i: usize) -> Result<Composition, SourceError> {
        if i >= self.options.count {
            return Err(SourceError::Invalid(format!(
                "builtin scene {i} is out of range (there are {})",
                self.options.count
            )));
        }
        let (w, h) = (self.options.width, self.options.height);
        let k = Intrinsics::reference_default(w, h);
        let mut rng = SampleRng::new(BUILTIN_KEY, self.options.seed, i as u64, Purpose::Other(0));
        // the stages draw from the one stream in this order: background, geometry, objects
        let bg_k = i % self.photos.len();
        let mut image = self.background(&mut rng, bg_k)?;
        let geo = BackgroundGeometry {
            camera_height: rng.uniform(1.2, 1.8),
            wall_depth: rng.uniform(6.0, 10.0),
            wall_slope: rng.uniform(-0.35, 0.35),
        };
        let mut depth: Vec<f64> = (0..w * h).map(|j| geo.depth(&k, (j % w) as f64, (j / w) as f64)).collect();
        let mut ids = vec![0u32; w * h];
        let plans = self.plan_objects(&mut rng, &k, &geo, bg_k)?;
        contact_shadows(&mut image, &plans);
        let mut canvas = Canvas { image: &mut image, depth: &mut depth, ids: &mut ids };
        let objects = self.paste_objects(&plans, &mut canvas)?;
        Ok(Composition {
            id: format!("builtin-{i:02}-{}", self.stem(bg_k)),
            image,
            depth: depth.into_iter().map(|d| d as f32).collect(),
            ids,
            intrinsics: k,
            background_photo: self.photos[bg_k].0.clone(),
            background: geo,
            objects,
        })
    }

    /// The background photo `bg_k`: cover-cropped to the scene's aspect ratio, zoomed, maybe
    /// flipped, at the scene's size.
    fn background(&self, rng: &mut SampleRng, bg_k: usize) -> Result<RgbImage, SourceError> {
        let (w, h) = (self.options.width, self.options.height);
        let bg = self.photo(bg_k)?;
        let zoom = rng.uniform(1.0, 1.25);
        let aspect = w as f64 / h as f64;
        let (mut cw, mut ch) = (bg.width as f64, bg.width as f64 / aspect);
        if ch > bg.height as f64 {
            ch = bg.height as f64;
            cw = ch * aspect;
        }
        let (cw, ch) = (((cw / zoom) as usize).max(1), ((ch / zoom) as usize).max(1));
        let cx0 = rng.below((bg.width - cw + 1) as u64) as usize;
        let cy0 = rng.below((bg.height - ch + 1) as u64) as usize;
        let flip = rng.sign() < 0.0;
        Ok(resize_rgb(crop(&bg, cx0, cy0, cw, ch, flip), w, h))
    }

    /// The objects to paste, chosen all first (photo, shape, depth on the ground, size, crop of
    /// their photo), in the order drawn.
    fn plan_objects(
        &self,
        rng: &mut SampleRng,
        k: &Intrinsics,
        geo: &BackgroundGeometry,
        bg_k: usize,
    ) -> Result<Vec<Plan>, SourceError> {
        let (w, h) = (self.options.width, self.options.height);
        let np = self.photos.len();
        let n_obj = 2 + rng.below(2) as usize;
        let z_bottom = geo.camera_height * k.fy / ((h - 1) as f64 - k.cy);
        let z_lo = 1.02 * z_bottom;
        let z_hi = (0.6 * geo.wall_depth).min(5.0).max(z_lo * 1.1);
        let mut plans: Vec<Plan> = Vec::with_capacity(n_obj);
        for _ in 0..n_obj {
            let photo = if np > 1 { (bg_k + 1 + rng.below((np - 1) as u64) as usize) % np } else { bg_k };
            let shape = if rng.below(2) == 0 { Shape::Ellipse } else { Shape::RoundedRect };
            let z = rng.uniform(z_lo, z_hi);
            let ph = (k.fy * rng.uniform(0.7, 1.4) * geo.camera_height / z).max(8.0);
            // at most 0.45 W, and at least 8 px where the frame allows it (a frame under 18 px
            // wide takes objects narrower than 8 px)
            let pw_max = 0.45 * w as f64;
            let pw = (ph * rng.uniform(0.6, 1.4)).clamp(8.0f64.min(pw_max), pw_max);
            let foot = k.cy + k.fy * geo.camera_height / z;
            let x0 = rng.uniform(0.0, w as f64 - pw);
            let src = self.photo(photo)?;
            // a crop of the photo with the cut-out's aspect ratio, around the photo's centre
            let frac = rng.uniform(0.35, 0.7);
            let (mut sw, mut sh) = (frac * src.width as f64, frac * src.width as f64 * ph / pw);
            if sh > 0.9 * src.height as f64 {
                let s = 0.9 * src.height as f64 / sh;
                sw *= s;
                sh *= s;
            }
            let (sw, sh) = ((sw as usize).clamp(1, src.width), (sh as usize).clamp(1, src.height));
            let jx = rng.uniform(-0.15, 0.15);
            let jy = rng.uniform(-0.15, 0.15);
            let sx0 = ((src.width - sw) as f64 * (0.5 + jx)) as usize;
            let sy0 = ((src.height - sh) as f64 * (0.5 + jy)) as usize;
            let flip = rng.sign() < 0.0;
            plans.push(Plan { photo, shape, z, x0, y0: foot - ph, pw, ph, crop: (sx0, sy0, sw, sh), flip });
        }
        Ok(plans)
    }

    /// The planned objects pasted far to near: their depth, id and texture written into the
    /// canvas; each object's bounding box and visible pixels.
    fn paste_objects(&self, plans: &[Plan], canvas: &mut Canvas<'_>) -> Result<Vec<PlacedObject>, SourceError> {
        let (w, h) = (self.options.width, self.options.height);
        let frame = Grid::new(w, h);
        let mut order: Vec<usize> = (0..plans.len()).collect();
        order.sort_by(|&a, &b| plans[b].z.total_cmp(&plans[a].z).then(a.cmp(&b)));
        let mut objects = Vec::with_capacity(plans.len());
        for &o in &order {
            let p = &plans[o];
            let id = o as u32 + 1;
            let src = self.photo(p.photo)?;
            let (sx0, sy0, sw, sh) = p.crop;
            let pwi = (p.pw.round() as usize).max(1);
            let phi = (p.ph.round() as usize).max(1);
            let tex = resize_rgb(crop(&src, sx0, sy0, sw, sh, p.flip), pwi, phi);
            let (bx0, by0) = (p.x0.round() as i64, p.y0.round() as i64);
            let r = 0.25 * pwi.min(phi) as f64;
            let mut bbox = [usize::MAX, usize::MAX, 0, 0];
            for ty in 0..phi {
                let y = by0 + ty as i64;
                if y < 0 || y >= h as i64 {
                    continue;
                }
                for tx in 0..pwi {
                    let x = bx0 + tx as i64;
                    if x < 0
                        || x >= w as i64
                        || !inside(p.shape, tx as f64 + 0.5, ty as f64 + 0.5, pwi as f64, phi as f64, r)
                    {
                        continue;
                    }
                    let j = frame.index(x as usize, y as usize);
                    canvas.depth[j] = p.z;
                    canvas.ids[j] = id;
                    let t = Grid::new(pwi, phi).index(tx, ty);
                    canvas.image.data[pixel_values(j, 3)].copy_from_slice(&tex.data[pixel_values(t, 3)]);
                    bbox = [
                        bbox[0].min(x as usize),
                        bbox[1].min(y as usize),
                        bbox[2].max(x as usize + 1),
                        bbox[3].max(y as usize + 1),
                    ];
                }
            }
            if bbox[0] == usize::MAX {
                bbox = [0, 0, 0, 0];
            }
            objects.push(PlacedObject {
                id,
                photo: self.photos[p.photo].0.clone(),
                shape: p.shape,
                depth: p.z,
                bbox,
                visible_pixels: 0,
            });
        }
        for obj in &mut objects {
            obj.visible_pixels = canvas.ids.iter().filter(|&&v| v == obj.id).count();
        }
        Ok(objects)
    }
}

/// An object chosen for a scene, before it is pasted.
struct Plan {
    photo: usize,
    shape: Shape,
    z: f64,
    x0: f64,
    y0: f64,
    pw: f64,
    ph: f64,
    crop: (usize, usize, usize, usize),
    flip: bool,
}

/// What the pasted objects write: colour, depth and instance ids, row-major at the scene's size.
struct Canvas<'a> {
    image: &'a mut RgbImage,
    depth: &'a mut [f64],
    ids: &'a mut [u32],
}

/// Contact shadows of the planned objects on the background (colour only).
fn contact_shadows(image: &mut RgbImage, plans: &[Plan]) {
    let (w, h) = (image.width, image.height);
    let g = Grid::new(w, h);
    for p in plans {
        let (xc, yc) = (p.x0 + 0.5 * p.pw, p.y0 + p.ph);
        let (rx, ry) = (0.6 * p.pw, 0.06 * p.ph + 3.0);
        let ys = ((yc - ry).floor().max(0.0) as usize).min(h);
        let ye = ((yc + ry).ceil().max(0.0) as usize + 1).min(h);
        let xs = ((xc - rx).floor().max(0.0) as usize).min(w);
        let xe = ((xc + rx).ceil().max(0.0) as usize + 1).min(w);
        for y in ys..ye {
            for x in xs..xe {
                let (dx, dy) = ((x as f64 - xc) / rx, (y as f64 - yc) / ry);
                let r2 = dx * dx + dy * dy;
                if r2 < 1.0 {
                    let f = (1.0 - 0.35 * (1.0 - r2)) as f32;
                    for c in &mut image.data[pixel_values(g.index(x, y), 3)] {
                        *c *= f;
                    }
                }
            }
        }
    }
}

/// Whether the point (u, v) of a `w x h` box lies inside the shape.
fn inside(shape: Shape, u: f64, v: f64, w: f64, h: f64, r: f64) -> bool {
    match shape {
        Shape::Ellipse => {
            let (dx, dy) = ((u - 0.5 * w) / (0.5 * w), (v - 0.5 * h) / (0.5 * h));
            dx * dx + dy * dy <= 1.0
        }
        Shape::RoundedRect => {
            let qx = (u - 0.5 * w).abs() - (0.5 * w - r);
            let qy = (v - 0.5 * h).abs() - (0.5 * h - r);
            if qx <= 0.0 || qy <= 0.0 {
                true
            } else {
                qx * qx + qy * qy <= r * r
            }
        }
    }
}

/// A `cw x ch` crop at (x0, y0), optionally mirrored left-right.
fn crop(img: &RgbImage, x0: usize, y0: usize, cw: usize, ch: usize, flip: bool) -> RgbImage {
    let g = Grid::new(img.width, img.height);
    let mut data = Vec::with_capacity(cw * ch * 3);
    for y in y0..y0 + ch {
        for xi in 0..cw {
            let x = if flip { x0 + cw - 1 - xi } else { x0 + xi };
            data.extend_from_slice(&img.data[pixel_values(g.index(x, y), 3)]);
        }
    }
    RgbImage { width: cw, height: ch, data }
}

impl Source for BuiltinSource {
    fn len(&self) -> usize {
        self.options.count
    }

    fn id(&self, i: usize) -> String {
        if i < self.options.count {
            format!("builtin-{i:02}-{}", self.stem(i % self.photos.len()))
        } else {
            String::new()
        }
    }

    fn load(&self, i: usize) -> Result<SourceItem, SourceError> {
        let c = self.compose(i)?;
        let masks = InstanceMasks::from_index_map(&c.ids, c.image.width, c.image.height)
            .map_err(|e| SourceError::Invalid(format!("builtin scene {i}: {e}")))?;
        Ok(SourceItem {
            id: c.id,
            image: c.image,
            depth: Some(GivenDepth::Depth(c.depth)),
            masks: Some(masks),
            mpi: None,
            intrinsics: Some(c.intrinsics),
        })
    }

    fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    fn describe(&self) -> String {
        format!(
            "builtin:{} procedural scenes of {} x {} from {} photos in {}",
            self.options.count,
            self.options.width,
            self.options.height,
            self.photos.len(),
            self.options.photos_dir.display()
        )
    }
}
