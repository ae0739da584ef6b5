//! Random camera and object motions: the configurable motion laws ([`MotionRanges`]), the five
//! presets (`reference`, `paper-kitti`, `depthstillation`, `mixed`, `stereo`) and the record of
//! one drawn motion ([`Motion`]) that goes into sample metadata.
//!
//! # Stereo
//!
//! Laws with `stereo = true` make rectified stereo pairs: image 1 is the left view, image 2 the
//! right view of a camera moved by a baseline `B` along its x axis, `X_tgt = X_src - (B, 0, 0)`,
//! so `t = (-B, 0, 0)`, no rotation, the same intrinsics and no moving objects. A point at depth
//! `Z` then has the disparity `d = x1 - x2 = fx B / Z >= 0` and the flow `(u, v) = (-d, 0)`.
//! [`MotionRanges::validate`] holds such laws to that form: translation x at most 0, every other
//! component exactly 0.
//!
//! # Conventions
//!
//! A drawn motion is a [`Pose`]: `X_tgt = R X_src + t` (docs/design.md, geometry conventions), the source camera (or, for an
//! object motion, the object's points) mapped into the target camera. The scene is scaled so that
//! the nearest content lies at depth ~1, so translations are in units of that depth.
//!
//! **Forward motion has negative `t_z`.** A camera that moves forward by a distance `d` along its
//! optical axis sees every point `d` closer: `Z_tgt = Z_src - d`, i.e. `t_z = -d`. The laws
//! therefore describe forward motion with [`Component::Forward`]`{ min, max }`: a *distance*
//! `d` uniform in `[min, max]` (both >= 0) and `t_z = -d`. The paper's KITTI setting "tz in
//! [0.1, 0.35]" (a forward distance) becomes `Forward { min: 0.1, max: 0.35 }`, i.e.
//! `t_z` in `[-0.35, -0.1]`; the reference script's "tz in [-(0.1 + ext_cz), -0.1]" becomes
//! `Forward { min: 0.1, max: 0.1 + ext_cz }`.
//!
//! Rotations are drawn either as an axis-angle vector ([`RotationKind::AxisAngle`]: the three
//! components are drawn independently; direction = axis, length = angle) or as Euler angles
//! ([`RotationKind::EulerZyx`]: angles `(a_x, a_y, a_z)` about the camera's x, y, z axes with
//! `R = Rz(a_z) · Ry(a_y) · Rx(a_x)`, each a right-handed rotation about a fixed axis, so `Rx` is
//! applied to the point first).
//!
//! # Draw order (part of the determinism contract)
//!
//! A rigid motion draws translation x, y, z, then rotation x, y, z, each component by its law:
//! [`Component::Uniform`] and [`Component::Forward`] take one [`SampleRng::uniform`];
//! [`Component::RandomSign`] and [`Component::LogUniform`] take one `uniform` for the magnitude,
//! then one [`SampleRng::sign`].
//! The camera and each object should use their own streams (`Purpose::CameraMotion`,
//! `Purpose::ObjectMotion(slot)`), so the two never shift each other's numbers.
//!
//! The drawn numbers (translation, angles) are bit-identical everywhere; the rotation matrix is
//! computed from them with `sin`/`cos`, which are bit-identical on one platform (same architecture
//! and math library).

use std::fmt;
use std::str::FromStr;

use glam::{DMat3, DQuat, DVec3};
use serde::{Deserialize, Serialize};

use crate::geometry::{rotation_from_axis_angle, Pose};
use crate::rng::SampleRng;

/// The public reference script's default `ext_cz` (extra forward distance of the camera).
pub const REFERENCE_EXT_CZ: f64 = 0.15;

/// A reveal budget for laws that opt in to one ([`MotionRanges::with_reveal_budget`]): uniform
/// in this range of the frame's share ([`MotionRanges::reveal_budget`]; docs/quality.md, "The
/// reveal budget"). The presets carry none: objects move by their law's draw, unscaled, and what
/// the motion uncovers is left to the completion.
pub const REVEAL_BUDGET: (f64, f64) = (0.001, 0.01);

/// Errors of motion configuration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MotionError {
    /// A range of a [`MotionRanges`] is unusable; `field` is its path, e.g. `camera.translation.z`.
    #[error("invalid motion range {field}: {reason}")]
    InvalidRange { field: String, reason: String },
    #[error("unknown motion preset {0:?} (expected one of: reference, paper-kitti, depthstillation, mixed, stereo)")]
    UnknownPreset(String),
}

/// The law of one scalar component (a translation along an axis or a rotation angle).
///
/// In JSON/TOML: `{ "law": "uniform", "lo": -0.2, "hi": 0.2 }`,
/// `{ "law": "random-sign", "min": 0.1, "max": 0.2 }`, `{ "law": "forward", "min": 0.1, "max": 0.35 }`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "law", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Component {
    /// Uniform in `[lo, hi]`.
    Uniform { lo: f64, hi: f64 },
    /// Magnitude uniform in `[min, max]` (`0 <= min <= max`), then a random sign (+ or -, 1/2 each).
    RandomSign { min: f64, max: f64 },
    /// Forward motion (translation z only): a distance `d` uniform in `[min, max]`
    /// (`0 <= min <= max`), and the value is `t_z = -d`.
    Forward { min: f64, max: f64 },
    /// Magnitude log-uniform in `[min, max]` (`0 < min <= max`: `min (max / min)^u`, `u`
    /// uniform in [0, 1]), then a random sign: as many small motions per octave as large ones.
    LogUniform { min: f64, max: f64 },
}

impl Component {
    /// Uniform in `[-a, a]`.
    pub fn symmetric(a: f64) -> Self {
        Component::Uniform { lo: -a, hi: a }
    }

    /// Always `v` (still consumes one draw).
    pub fn constant(v: f64) -> Self {
        Component::Uniform { lo: v, hi: v }
    }

    /// Draws a value (see the module documentation for how many numbers it consumes).
    pub fn draw(&self, rng: &mut SampleRng) -> f64 {
        match *self {
            Component::Uniform { lo, hi } => rng.uniform(lo, hi),
            Component::RandomSign { min, max } => {
                let magnitude = rng.uniform(min, max);
                let sign = rng.sign();
                magnitude * sign
            }
            Component::Forward { min, max } => -rng.uniform(min, max),
            Component::LogUniform { min, max } => {
                let u = rng.uniform(0.0, 1.0);
                let magnitude = (min * (max / min).powf(u)).clamp(min, max);
                let sign = rng.sign();
                magnitude * sign
            }
        }
    }

    /// The closed interval the drawn value lies in.
    pub fn bounds(&self) -> (f64, f64) {
        match *self {
            Component::Uniform { lo, hi } => (lo, hi),
            Component::RandomSign { max, .. } | Component::LogUniform { max, .. } => (-max, max),
            Component::Forward { min, max } => (-max, -min),
        }
    }

    /// The largest possible magnitude of the value.
    pub fn max_abs(&self) -> f64 {
        let (lo, hi) = self.bounds();
        lo.abs().max(hi.abs())
    }

    fn validate(&self, field: &str, allow_forward: bool) -> Result<(), MotionError> {
        let bad = |reason: String| Err(MotionError::InvalidRange { field: field.to_string(), reason });
        match *self {
            Component::Uniform { lo, hi } => {
                if !lo.is_finite() || !hi.is_finite() {
                    return bad(format!("bounds must be finite (lo = {lo}, hi = {hi})"));
                }
                if lo > hi {
                    return bad(format!("lo ({lo}) > hi ({hi})"));
                }
            }
            Component::RandomSign { min, max } | Component::Forward { min, max } => {
                if matches!(self, Component::Forward { .. }) && !allow_forward {
                    return bad("the forward law applies to the translation z component only".into());
                }
                if !min.is_finite() || !max.is_finite() {
                    return bad(format!("magnitudes must be finite (min = {min}, max = {max})"));
                }
                if min < 0.0 {
                    return bad(format!("magnitude min ({min}) must be >= 0"));
                }
                if min > max {
                    return bad(format!("min ({min}) > max ({max})"));
                }
            }
            Component::LogUniform { min, max } => {
                if !(min.is_finite() && max.is_finite() && min > 0.0 && min <= max) {
                    return bad(format!(
                        "log-uniform magnitudes need 0 < min <= max, finite (min = {min}, max = {max})"
                    ));
                }
            }
        }
        Ok(())
    }
}

/// One law per axis, drawn in the order x, y, z.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Axes {
    pub x: Component,
    pub y: Component,
    pub z: Component,
}

impl Axes {
    pub fn new(x: Component, y: Component, z: Component) -> Self {
        Self { x, y, z }
    }

    /// The same law on all three axes.
    pub fn splat(c: Component) -> Self {
        Self { x: c, y: c, z: c }
    }

    /// Draws x, then y, then z.
    pub fn draw(&self, rng: &mut SampleRng) -> [f64; 3] {
        let x = self.x.draw(rng);
        let y = self.y.draw(rng);
        let z = self.z.draw(rng);
        [x, y, z]
    }

    fn components(&self) -> [(&'static str, &Component); 3] {
        [("x", &self.x), ("y", &self.y), ("z", &self.z)]
    }
}

/// How the three rotation components are turned into a rotation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RotationKind {
    /// The components form an axis-angle vector (direction = axis, length = angle, radians).
    AxisAngle,
    /// The components are Euler angles `(a_x, a_y, a_z)` in radians, `R = Rz(a_z) Ry(a_y) Rx(a_x)`.
    EulerZyx,
}

impl RotationKind {
    /// The rotation matrix of drawn components.
    pub fn matrix(self, angles: [f64; 3]) -> DMat3 {
        match self {
            RotationKind::AxisAngle => rotation_from_axis_angle(DVec3::from(angles)),
            RotationKind::EulerZyx => euler_zyx_matrix(angles),
        }
    }
}

/// `R = Rz(a[2]) · Ry(a[1]) · Rx(a[0])`, right-handed rotations about the fixed x, y, z axes.
pub fn euler_zyx_matrix(a: [f64; 3]) -> DMat3 {
    DMat3::from_rotation_z(a[2]) * DMat3::from_rotation_y(a[1]) * DMat3::from_rotation_x(a[0])
}

/// The axis-angle vector (angle in [0, pi]) of a rotation matrix.
pub fn axis_angle_from_matrix(m: &DMat3) -> DVec3 {
    let mut q = DQuat::from_mat3(m).normalize();
    if q.w < 0.0 {
        q = -q;
    }
    let v = DVec3::new(q.x, q.y, q.z);
    let s = v.length();
    if s == 0.0 {
        return DVec3::ZERO;
    }
    v * (2.0 * s.atan2(q.w) / s)
}

/// The law of one rigid motion (the camera's, or an object's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigidLaw {
    /// Translation components (x right, y down, z forward; see the module doc for the sign of z).
    pub translation: Axes,
    /// How `rotation` is read: axis-angle vector or Euler angles.
    pub rotation_kind: RotationKind,
    /// Rotation components in radians.
    pub rotation: Axes,
}

impl RigidLaw {
    /// Draws translation x, y, z then rotation x, y, z. `law` names the ranges in the record.
    pub fn draw(&self, rng: &mut SampleRng, law: &str) -> Motion {
        let translation = self.translation.draw(rng);
        let angles = self.rotation.draw(rng);
        Motion::new(law, translation, self.rotation_kind, angles)
    }

    fn validate(&self, prefix: &str) -> Result<(), MotionError> {
        for (axis, c) in self.translation.components() {
            c.validate(&format!("{prefix}.translation.{axis}"), axis == "z")?;
        }
        for (axis, c) in self.rotation.components() {
            let field = format!("{prefix}.rotation.{axis}");
            c.validate(&field, false)?;
            if c.max_abs() >= std::f64::consts::PI {
                return Err(MotionError::InvalidRange {
                    field,
                    reason: format!("angles must stay below pi in magnitude (bounds {:?})", c.bounds()),
                });
            }
        }
        if self.rotation_kind == RotationKind::AxisAngle {
            let largest = DVec3::new(self.rotation.x.max_abs(), self.rotation.y.max_abs(), self.rotation.z.max_abs());
            if largest.length() >= std::f64::consts::PI {
                return Err(MotionError::InvalidRange {
                    field: format!("{prefix}.rotation"),
                    reason: format!(
                        "the largest axis-angle vector has length {} >= pi (its rotation would wrap around)",
                        largest.length()
                    ),
                });
            }
        }
        Ok(())
    }
}

fn default_name() -> String {
    "custom".to_string()
}

/// The complete motion laws of a sample: the camera's and the moving objects'. Serialisable so a
/// request or a TOML file can set them; [`MotionPreset::ranges`] gives the presets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionRanges {
    /// A name reported with every drawn motion (the preset's name, or "custom" when left out).
    #[serde(default = "default_name")]
    pub name: String,
    pub camera: RigidLaw,
    pub object: RigidLaw,
    /// Rectified stereo pairs (see the module documentation): the camera law is a pure baseline
    /// along x (`translation.x <= 0`, every other component 0) and no object moves. Left out of
    /// the JSON when false, so the laws of other presets keep their fingerprints.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stereo: bool,
    /// The most share of image2 (0 to 1) one object's motion relative to the scene may uncover,
    /// drawn per object after its motion (`{ "law": "uniform", "lo": 0.001, "hi": 0.01 }`); an
    /// object whose drawn motion would uncover more moves by less (applied by the recipe;
    /// docs/quality.md, "The reveal budget"). None: no budget (left out of the JSON, so laws
    /// without one keep their fingerprints).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reveal_budget: Option<Component>,
}

impl Default for MotionRanges {
    /// The `reference` preset.
    fn default() -> Self {
        MotionPreset::Reference.ranges()
    }
}

impl MotionRanges {
    /// These laws with the camera's replaced by a pure lateral translation: `tx` and `ty` of
    /// random sign and magnitude uniform in `[0, t]`, no forward part, no rotation (the sharpness
    /// and noise measurements of `mpiflow bench quality`); named `lateral-T`.
    #[must_use]
    pub fn with_lateral_camera(mut self, t: f64) -> Self {
        self.name = format!("lateral-{t}");
        let law = &mut self.camera;
        law.translation = Axes::new(
            Component::RandomSign { min: 0.0, max: t },
            Component::RandomSign { min: 0.0, max: t },
            Component::constant(0.0),
        );
        law.rotation = Axes::splat(Component::constant(0.0));
        self
    }

    /// These laws with the reveal budget [`REVEAL_BUDGET`] (an object whose motion would uncover
    /// more of the frame than its drawn share moves by less).
    #[must_use]
    pub fn with_reveal_budget(mut self) -> Self {
        self.reveal_budget = Some(Component::Uniform { lo: REVEAL_BUDGET.0, hi: REVEAL_BUDGET.1 });
        self
    }

    /// Checks every range: finite bounds, `lo <= hi`, magnitudes `0 <= min <= max`, the forward
    /// law on translation z only, rotation components below pi in magnitude, and for axis-angle
    /// laws the largest possible rotation vector shorter than pi.
    pub fn validate(&self) -> Result<(), MotionError> {
        self.camera.validate("camera")?;
        self.object.validate("object")?;
        if self.stereo {
            self.validate_stereo()?;
        }
        if let Some(b) = &self.reveal_budget {
            b.validate("reveal_budget", false)?;
            let (lo, hi) = b.bounds();
            if !(lo > 0.0 && hi <= 1.0) || matches!(b, Component::RandomSign { .. } | Component::LogUniform { .. }) {
                return Err(MotionError::InvalidRange {
                    field: "reveal_budget".into(),
                    reason: format!("a share of the frame: a uniform law with 0 < lo <= hi <= 1 (bounds {lo}, {hi})"),
                });
            }
        }
        Ok(())
    }

    /// Stereo laws: a baseline along x only (`t_x <= 0`: image 2 is the right view) and no
    /// rotation, so the pair is rectified.
    fn validate_stereo(&self) -> Result<(), MotionError> {
        let c = &self.camera;
        let bad = |field: String, reason: &str| Err(MotionError::InvalidRange { field, reason: reason.into() });
        let (_, hi) = c.translation.x.bounds();
        if hi > 0.0 {
            return bad(
                "camera.translation.x".into(),
                "stereo laws need translation x <= 0 (t = (-B, 0, 0): image 2 is the right view)",
            );
        }
        let rest = [("translation", "y", &c.translation.y), ("translation", "z", &c.translation.z)]
            .into_iter()
            .chain(c.rotation.components().map(|(axis, comp)| ("rotation", axis, comp)));
        for (part, axis, comp) in rest {
            if comp.bounds() != (0.0, 0.0) {
                let reason = "stereo laws allow no motion but the baseline along x (a rectified pair)";
                return bad(format!("camera.{part}.{axis}"), reason);
            }
        }
        Ok(())
    }

    /// A stereo preset's baseline law in the camera's translation x has a magnitude between
    /// these bounds; [`MotionPreset::Stereo`] uses them.
    pub const STEREO_BASELINE: (f64, f64) = (0.02, 0.2);

    /// Draws a camera motion (use a `Purpose::CameraMotion` stream).
    pub fn sample_camera_motion(&self, rng: &mut SampleRng) -> Motion {
        self.camera.draw(rng, &self.name)
    }

    /// Draws an object motion (use a `Purpose::ObjectMotion(slot)` stream).
    pub fn sample_object_motion(&self, rng: &mut SampleRng) -> Motion {
        self.object.draw(rng, &self.name)
    }

    /// Draws an object's reveal budget (from the object's stream, after its motion); None
    /// without one.
    pub fn sample_reveal_budget(&self, rng: &mut SampleRng) -> Option<f64> {
        self.reveal_budget.map(|b| b.draw(rng))
    }

    /// [`Self::sample_camera_motion`] as a pose.
    pub fn sample_camera(&self, rng: &mut SampleRng) -> Pose {
        self.sample_camera_motion(rng).to_pose()
    }

    /// [`Self::sample_object_motion`] as a pose.
    pub fn sample_object(&self, rng: &mut SampleRng) -> Pose {
        self.sample_object_motion(rng).to_pose()
    }
}

/// The named motion laws.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionPreset {
    /// The public reference script (Sharpiless/MPI-Flow): camera |tx|, |ty| in [0.1, 0.2] with
    /// random sign, forward distance in [0.1, 0.1 + ext_cz] (t_z in [-0.25, -0.1] with
    /// ext_cz = 0.15), axis-angle components uniform in ±0.4·pi/36. Objects: |tx|, |ty| in
    /// [0, 0.05] and |tz| in [0, 0.5·ext_cz], random signs, the same rotation law.
    #[default]
    Reference,
    /// The paper's KITTI setting: camera tx, ty uniform in [-0.2, 0.2], forward distance in
    /// [0.1, 0.35] (t_z in [-0.35, -0.1]), Euler angles (R = Rz Ry Rx) uniform in ±pi/90. The
    /// paper gives no separate object law; objects use the `reference` object law.
    PaperKitti,
    /// The Depthstillation law: camera |tx|, |ty|, |tz| in [0.1, 0.2] with random signs (so the
    /// camera moves forward or backward), Euler angles (R = Rz Ry Rx) of magnitude in
    /// [pi/36, pi/18] with random signs. Objects: |t| components in [0.05, 0.1] and angle
    /// magnitudes in [pi/72, pi/36], random signs, Euler angles. (The public code passes its
    /// "Euler" triplet to an axis-angle function; set `rotation_kind = "axis-angle"` for that
    /// reading. At these angles the two differ by second-order terms.)
    Depthstillation,
    /// Small and large motions together: every camera component log-uniform with a
    /// random sign, translations in [0.001, 0.3] (forward or backward along z), axis-angle
    /// components in [0.0002, 0.05] rad; objects: translations in [0.001, 0.1], axis-angle
    /// components in [0.0002, 0.03]. Flow magnitudes span sub-pixel motions to a tail past
    /// 100 px (percentiles in `docs/quality.md`), where `reference` has almost none under 5 px.
    Mixed,
    /// Rectified stereo pairs: image 2 is the right view at a baseline `B` uniform in
    /// [`MotionRanges::STEREO_BASELINE`] = [0.02, 0.2] scene units (the nearest content lies at
    /// depth ~1, so the largest disparity is ~`fx B`: 0.116 W px at B = 0.2 with the reference
    /// intrinsics `fx = 0.58 W`), `t = (-B, 0, 0)`, no rotation, no moving objects.
    Stereo,
}

impl MotionPreset {
    pub const ALL: [MotionPreset; 5] = [
        MotionPreset::Reference,
        MotionPreset::PaperKitti,
        MotionPreset::Depthstillation,
        MotionPreset::Mixed,
        MotionPreset::Stereo,
    ];

    /// The preset's name: `reference`, `paper-kitti`, `depthstillation`, `mixed` or `stereo`.
    pub fn name(self) -> &'static str {
        match self {
            MotionPreset::Reference => "reference",
            MotionPreset::PaperKitti => "paper-kitti",
            MotionPreset::Depthstillation => "depthstillation",
            MotionPreset::Mixed => "mixed",
            MotionPreset::Stereo => "stereo",
        }
    }

    /// The preset's laws (see each variant).
    pub fn ranges(self) -> MotionRanges {
        use std::f64::consts::PI;
        let reference_rotation = Axes::splat(Component::symmetric(0.4 * PI / 36.0));
        let reference_object = RigidLaw {
            translation: Axes::new(
                Component::RandomSign { min: 0.0, max: 0.05 },
                Component::RandomSign { min: 0.0, max: 0.05 },
                Component::RandomSign { min: 0.0, max: 0.5 * REFERENCE_EXT_CZ },
            ),
            rotation_kind: RotationKind::AxisAngle,
            rotation: reference_rotation,
        };
        let (camera, object) = match self {
            MotionPreset::Reference => (
                RigidLaw {
                    translation: Axes::new(
                        Component::RandomSign { min: 0.1, max: 0.2 },
                        Component::RandomSign { min: 0.1, max: 0.2 },
                        Component::Forward { min: 0.1, max: 0.1 + REFERENCE_EXT_CZ },
                    ),
                    rotation_kind: RotationKind::AxisAngle,
                    rotation: reference_rotation,
                },
                reference_object,
            ),
            MotionPreset::PaperKitti => (
                RigidLaw {
                    translation: Axes::new(
                        Component::symmetric(0.2),
                        Component::symmetric(0.2),
                        Component::Forward { min: 0.1, max: 0.35 },
                    ),
                    rotation_kind: RotationKind::EulerZyx,
                    rotation: Axes::splat(Component::symmetric(PI / 90.0)),
                },
                reference_object,
            ),
            MotionPreset::Depthstillation => (
                RigidLaw {
                    translation: Axes::splat(Component::RandomSign { min: 0.1, max: 0.2 }),
                    rotation_kind: RotationKind::EulerZyx,
                    rotation: Axes::splat(Component::RandomSign { min: PI / 36.0, max: PI / 18.0 }),
                },
                RigidLaw {
                    translation: Axes::splat(Component::RandomSign { min: 0.05, max: 0.1 }),
                    rotation_kind: RotationKind::EulerZyx,
                    rotation: Axes::splat(Component::RandomSign { min: PI / 72.0, max: PI / 36.0 }),
                },
            ),
            MotionPreset::Mixed => {
                let log = |min: f64, max: f64| Axes::splat(Component::LogUniform { min, max });
                (
                    RigidLaw {
                        translation: log(0.001, 0.3),
                        rotation_kind: RotationKind::AxisAngle,
                        rotation: log(0.0002, 0.05),
                    },
                    RigidLaw {
                        translation: log(0.001, 0.1),
                        rotation_kind: RotationKind::AxisAngle,
                        rotation: log(0.0002, 0.03),
                    },
                )
            }
            MotionPreset::Stereo => {
                let (min, max) = MotionRanges::STEREO_BASELINE;
                let still = RigidLaw {
                    translation: Axes::splat(Component::constant(0.0)),
                    rotation_kind: RotationKind::AxisAngle,
                    rotation: Axes::splat(Component::constant(0.0)),
                };
                let camera = RigidLaw {
                    translation: Axes::new(
                        Component::Uniform { lo: -max, hi: -min },
                        Component::constant(0.0),
                        Component::constant(0.0),
                    ),
                    ..still
                };
                return MotionRanges {
                    name: self.name().to_string(),
                    camera,
                    object: still,
                    stereo: true,
                    reveal_budget: None,
                };
            }
        };
        MotionRanges { name: self.name().to_string(), camera, object, stereo: false, reveal_budget: None }
    }
}

impl fmt::Display for MotionPreset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for MotionPreset {
    type Err = MotionError;

    /// `reference`, `paper-kitti`, `depthstillation`, `mixed` or `stereo` (ASCII case ignored).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        MotionPreset::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| MotionError::UnknownPreset(s.to_string()))
    }
}

/// What was drawn for one rigid motion, for sample metadata. `to_pose()` gives the motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Motion {
    /// The name of the [`MotionRanges`] it was drawn from (e.g. the preset name).
    pub law: String,
    /// `t` of `X_tgt = R X_src + t` (forward motion: `t[2] < 0`).
    pub translation: [f64; 3],
    /// How `angles` is read.
    pub rotation_kind: RotationKind,
    /// The rotation components as drawn (axis-angle vector or Euler angles `(a_x, a_y, a_z)`), radians.
    pub angles: [f64; 3],
    /// The rotation as an axis-angle vector (equal to `angles` for axis-angle laws).
    pub axis_angle: [f64; 3],
    /// The rotation matrix R, row-major.
    pub rotation: [[f64; 3]; 3],
}

impl Motion {
    /// The record of a motion given by its drawn components.
    pub fn new(law: &str, translation: [f64; 3], rotation_kind: RotationKind, angles: [f64; 3]) -> Self {
        let r = rotation_kind.matrix(angles);
        let axis_angle = match rotation_kind {
            RotationKind::AxisAngle => angles,
            RotationKind::EulerZyx => axis_angle_from_matrix(&r).to_array(),
        };
        Self {
            law: law.to_string(),
            translation,
            rotation_kind,
            angles,
            axis_angle,
            rotation: r.transpose().to_cols_array_2d(),
        }
    }

    /// The identity motion (no translation, no rotation).
    pub fn identity(law: &str) -> Self {
        Self::new(law, [0.0; 3], RotationKind::AxisAngle, [0.0; 3])
    }

    /// The pose: R from the stored matrix, t from the stored translation.
    pub fn to_pose(&self) -> Pose {
        Pose {
            rotation: DMat3::from_cols_array_2d(&self.rotation).transpose(),
            translation: DVec3::from(self.translation),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn euler_matrix_is_rz_ry_rx() {
        // a pure rotation about x by a: y -> (0, cos a, sin a)
        let a = 0.3;
        let r = euler_zyx_matrix([a, 0.0, 0.0]);
        assert!((r * DVec3::Y).abs_diff_eq(DVec3::new(0.0, a.cos(), a.sin()), 1e-15));
        // order: x first, then y, then z
        let ang = [0.1, -0.2, 0.3];
        let r = euler_zyx_matrix(ang);
        let p = DVec3::new(0.3, -0.7, 1.1);
        let step = DMat3::from_rotation_z(0.3) * (DMat3::from_rotation_y(-0.2) * (DMat3::from_rotation_x(0.1) * p));
        assert!((r * p).abs_diff_eq(step, 1e-15));
    }

    #[test]
    fn axis_angle_log_inverts_rodrigues() {
        for v in [DVec3::new(0.021, -0.013, 0.008), DVec3::new(0.0, 0.0, 3.0), DVec3::new(1e-9, 0.0, 0.0), DVec3::ZERO]
        {
            let back = axis_angle_from_matrix(&rotation_from_axis_angle(v));
            assert!(back.abs_diff_eq(v, 1e-12), "{v} -> {back}");
        }
    }

    #[test]
    fn identity_motion_is_identity_pose() {
        assert_eq!(Motion::identity("x").to_pose(), Pose::identity());
    }
}
