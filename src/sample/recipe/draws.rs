//! The draws of a sample: the camera's motion, the moved objects and their motions, each from its
//! own random stream; an object's motion scaled down when it would uncover too much.

use crate::geometry::Pose;
use crate::rng::{Purpose, SampleRng};
use crate::sample::config::SampleConfig;
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::object::choose_objects;
use crate::sample::types::{ObjectRecord, SampleAddress};
use crate::scene::Scene;

/// The draws of a sample: the camera's motion, the chosen objects and their motions.
pub(super) struct Draws {
    pub(super) camera: Motion,
    pub(super) cam_pose: Pose,
    /// indices into the scene's instance masks, slot order
    pub(super) chosen: Vec<usize>,
    pub(super) records: Vec<ObjectRecord>,
    /// each chosen object's pose (composed with the camera's when objects follow it)
    pub(super) poses: Vec<Pose>,
}

/// Draws the camera motion, the moved objects and their motions, each from its own stream.
pub(super) fn draw_motions(scene: &Scene, address: SampleAddress, config: &SampleConfig) -> Draws {
    let ranges = config.motion.ranges();
    let rng = |p: Purpose| SampleRng::new(address.dataset, address.seed, address.index, p);
    let camera = ranges.sample_camera_motion(&mut rng(Purpose::CameraMotion));
    let cam_pose = camera.to_pose();
    // stereo laws move no object: a rectified pair is one rigid camera motion
    let chosen = if config.max_objects > 0 && !ranges.stereo && !scene.masks.masks.is_empty() {
        choose_objects(
            &scene.masks,
            config.max_objects,
            config.min_object_area_fraction,
            config.object_choice,
            &mut rng(Purpose::ObjectChoice),
        )
    } else {
        Vec::new()
    };
    let mut records = Vec::with_capacity(chosen.len());
    let mut poses = Vec::with_capacity(chosen.len());
    for (slot, &idx) in chosen.iter().enumerate() {
        let inst = &scene.masks.masks[idx];
        let mut stream = rng(Purpose::ObjectMotion(slot as u32));
        let mut motion = ranges.sample_object_motion(&mut stream);
        let mut pose = object_pose(&motion.to_pose(), &cam_pose, config.objects_follow_camera);
        if let Some(budget) = ranges.sample_reveal_budget(&mut stream) {
            (motion, pose) = within_budget(scene, &inst.mask, &cam_pose, (motion, pose), budget, config);
        }
        poses.push(pose);
        records.push(ObjectRecord {
            label: (slot + 1) as u8,
            instance: inst.id,
            score: inst.score,
            area: inst.area,
            motion,
        });
    }
    Draws { camera, cam_pose, chosen, records, poses }
}

/// The pose image2 shows an object under: its own motion, after the camera's when objects
/// follow it.
fn object_pose(own: &Pose, cam_pose: &Pose, follow: bool) -> Pose {
    if follow {
        cam_pose.compose(own)
    } else {
        *own
    }
}

/// An object's motion and pose moved by less when it would uncover more than `budget` of the
/// frame ([`crate::sample::reveal`]); the record is the motion applied (as an axis-angle law when
/// scaled).
fn within_budget(
    scene: &Scene,
    mask: &[f32],
    cam_pose: &Pose,
    (motion, pose): (Motion, Pose),
    budget: f64,
    config: &SampleConfig,
) -> (Motion, Pose) {
    use crate::sample::reveal::{fit_scale, scaled_pose, MaskSamples};
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    if scene.disparity.data.len() != w * h || mask.len() != w * h {
        return (motion, pose);
    }
    let samples = MaskSamples::new(mask, &scene.disparity.data, w, h, scene.intrinsics);
    let s = fit_scale(&samples, cam_pose, &pose, budget);
    if s == 1.0 {
        return (motion, pose);
    }
    let scaled = scaled_pose(cam_pose, &pose, s);
    let own = if config.objects_follow_camera { cam_pose.inverse().compose(&scaled) } else { scaled };
    let aa = crate::sample::motion::axis_angle_from_matrix(&own.rotation).to_array();
    let record = Motion::new(&motion.law, own.translation.to_array(), RotationKind::AxisAngle, aa);
    // the pose of the record, so that the sample's metadata reproduces the render exactly
    let applied = object_pose(&record.to_pose(), cam_pose, config.objects_follow_camera);
    (record, applied)
}
