//! The engine behind the service: loaded categories, and the conversion of
//! wire requests into engine calls and of engine results into wire bodies.

use crate::grasp::transfer::{is_z_up, solve_transferred, TransferModel, TransferredTool};
use crate::grasp::{Demonstration, GraspError, GraspSolver, PreGraspOptions, SolveOptions};
use crate::hand::HandModel;
use crate::shape::{builtin, RegisterOptions, Registrar, ShapeSpace};
use crate::tools::{Category, Split};
use graspd_proto::{self as proto, StatusCode};
use nalgebra::Point3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A status code with its message: what every failed request is answered with.
#[derive(Clone, Debug, PartialEq)]
pub struct Status {
    pub code: StatusCode,
    pub message: String,
}

impl Status {
    pub fn new(code: StatusCode, message: impl Into<String>) -> Self {
        Self { code, message: message.into() }
    }
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::new(StatusCode::InvalidArgument, message)
    }
}

/// What Grasp needs of a category beyond its shape space: the demonstration
/// (canonical frame), and its keypoints and the canonical mesh as models
/// of the latent (made once here, evaluated per request).
pub struct GraspAssets {
    pub demo: Demonstration,
    pub transfer: TransferModel,
}

pub struct LoadedCategory {
    pub category: Category,
    pub registrar: Registrar,
    pub info: proto::CategoryInfo,
    /// Err: why Grasp is not served for this category (answered FAILED_PRECONDITION).
    pub grasp: Result<GraspAssets, String>,
}

pub struct Engine {
    pub categories: Vec<LoadedCategory>,
    /// The hand Grasp solves for; Err: why Grasp is not served at all.
    pub hand: Result<HandModel, String>,
    actuated_names: Vec<proto::Name>,
    joint_names: Vec<proto::Name>,
}

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("category {name}: {reason}")]
    Category { name: String, reason: String },
    #[error("hand: {0}")]
    Hand(String),
}

/// Where Grasp's hand and demonstrations come from: the bundled SIH-like
/// hand and `assets/demos/<category>.json` unless the configuration names
/// others. A hand or demonstration the configuration names must load and
/// fit (the daemon does not start otherwise); the bundled ones, if they
/// fail, leave Grasp unserved with the reason.
#[derive(Clone, Debug, Default)]
pub struct GraspSources {
    /// URDF and keypoints file of the hand.
    pub hand: Option<(PathBuf, PathBuf)>,
    /// A demonstration file per category name.
    pub demos: BTreeMap<String, PathBuf>,
}

impl Engine {
    /// Loads (or builds and caches) the shape space of every category; returns
    /// the load time of each, milliseconds.
    pub fn load(
        names: &[String],
        cache_dir: &Path,
        sources: &GraspSources,
    ) -> Result<(Engine, Vec<(String, f64)>), EngineError> {
        let mut categories = Vec::new();
        let mut times = Vec::new();
        let hand = match &sources.hand {
            Some((urdf, keypoints)) => HandModel::from_urdf_file(urdf, keypoints),
            None => HandModel::default_sih(),
        };
        let hand = hand.map_err(|e| format!("hand model: {e}")).and_then(|h| {
            if h.num_actuated() > proto::MAX_JOINTS || h.moving_joints().len() > proto::MAX_JOINTS {
                Err(format!(
                    "the hand has more than {} joints; the protocol carries {}",
                    proto::MAX_JOINTS,
                    proto::MAX_JOINTS
                ))
            } else {
                Ok(h)
            }
        });
        match (&hand, &sources.hand) {
            (Err(e), Some(_)) => return Err(EngineError::Hand(e.clone())),
            (Err(e), None) => tracing::warn!("Grasp will not be served: {e}"),
            (Ok(h), _) => tracing::info!(
                "hand {} ({} actuated joints, {} keypoints)",
                h.name(),
                h.num_actuated(),
                h.keypoints().len()
            ),
        }
        let (actuated_names, joint_names) = match &hand {
            Ok(h) => (
                h.actuated_names().map(proto::str_to_text).collect(),
                h.moving_joints().iter().map(|&j| proto::str_to_text(&h.joints()[j].name)).collect(),
            ),
            Err(_) => (Vec::new(), Vec::new()),
        };
        for name in names {
            let t0 = Instant::now();
            let err = |reason: String| EngineError::Category { name: name.clone(), reason };
            let category: Category = name.parse().map_err(|e: crate::tools::ToolsError| err(e.to_string()))?;
            let space = builtin::load_or_build(category, cache_dir, |_, _| {}).map_err(|e| err(e.to_string()))?;
            if space.modes() > proto::MAX_LATENT {
                return Err(err(format!(
                    "{} latent modes; the protocol carries at most {}",
                    space.modes(),
                    proto::MAX_LATENT
                )));
            }
            if space.keypoints.len() > proto::MAX_KEYPOINTS {
                return Err(err(format!(
                    "{} keypoints; the protocol carries at most {}",
                    space.keypoints.len(),
                    proto::MAX_KEYPOINTS
                )));
            }
            let mut info = proto::CategoryInfo::zeroed();
            info.name = proto::str_to_name(category.name()).map_err(|e| err(e.to_string()))?;
            info.latent_dim = space.modes() as u32;
            info.keypoint_count = space.keypoints.len() as u32;
            for (slot, k) in info.keypoint_names.iter_mut().zip(&space.keypoints) {
                *slot = proto::str_to_text(&k.name);
            }
            info.canonical_frame = proto::str_to_text(category.canonical_frame());
            let registrar = Registrar::new(space);
            let demo = sources.demos.get(name).map(PathBuf::as_path);
            let grasp = match &hand {
                Ok(h) => GraspAssets::load(category, h, &registrar.space, demo),
                Err(e) => Err(e.clone()),
            };
            match (&grasp, demo) {
                (Err(e), Some(_)) => return Err(err(e.clone())),
                (Err(e), None) => tracing::warn!("Grasp will not be served for {name}: {e}"),
                (Ok(_), _) => {}
            }
            info.grasp_available = (hand.is_ok() && grasp.is_ok()) as u32;
            times.push((name.clone(), 1e3 * t0.elapsed().as_secs_f64()));
            categories.push(LoadedCategory { category, registrar, info, grasp });
        }
        Ok((Engine { categories, hand, actuated_names, joint_names }, times))
    }

    /// The hand Grasp solves for: its name and actuated joints (None when it did not load).
    pub fn hand(&self) -> Option<(&str, usize)> {
        self.hand.as_ref().ok().map(|h| (h.name(), h.num_actuated()))
    }

    /// Whether any category is served by Grasp.
    pub fn grasp_available(&self) -> bool {
        self.hand.is_ok() && self.categories.iter().any(|c| c.grasp.is_ok())
    }

    pub fn find(&self, name: &str) -> Option<usize> {
        self.categories.iter().position(|c| c.category.name() == name)
    }

    pub fn names(&self) -> Vec<&'static str> {
        self.categories.iter().map(|c| c.category.name()).collect()
    }

    /// Register: the cloud (read once from the caller's memory, converted and
    /// checked here) → latent, pose, fit, keypoints.
    pub fn register(
        &self,
        category: usize,
        points: &[proto::Point],
        header: &proto::RequestHeader,
    ) -> Result<proto::RegisterResponse, Status> {
        let c = self
            .categories
            .get(category)
            .ok_or_else(|| Status::new(StatusCode::Internal, "category index out of range"))?;
        let cloud = convert_cloud(points)?;
        let opts = register_options(header)?;
        let reg = c
            .registrar
            .register(&cloud, &opts)
            .map_err(|e| Status::invalid(format!("cannot register the cloud: {e}")))?;
        Ok(proto::RegisterResponse { registration: registration_to_wire(&reg, points.len(), opts.viewpoint) })
    }

    /// Grasp: registration, the category's demonstration carried onto the
    /// registered shape, the hand solved onto it, and the pre-grasp (what
    /// `graspd grasp` does, in one call).
    pub fn grasp(
        &self,
        category: usize,
        points: &[proto::Point],
        header: &proto::RequestHeader,
    ) -> Result<proto::GraspResponse, Status> {
        let c = self
            .categories
            .get(category)
            .ok_or_else(|| Status::new(StatusCode::Internal, "category index out of range"))?;
        let hand = self
            .hand
            .as_ref()
            .map_err(|e| Status::new(StatusCode::FailedPrecondition, format!("grasp not available: {e}")))?;
        let assets = c.grasp.as_ref().map_err(|e| {
            Status::new(StatusCode::FailedPrecondition, format!("grasp not available for {}: {e}", c.category.name()))
        })?;
        let cloud = convert_cloud(points)?;
        let opts = register_options(header)?;
        let pre = pregrasp_options(header)?;
        let reg = c
            .registrar
            .register(&cloud, &opts)
            .map_err(|e| Status::invalid(format!("cannot register the cloud: {e}")))?;
        let tool = TransferredTool::from_registration(&c.registrar, &reg, &assets.transfer)
            .map_err(|e| Status::invalid(format!("cannot carry the demonstration onto the registered shape: {e}")))?;
        let mut warnings = 0;
        if !reg.fit.confident {
            warnings |= proto::grasp_warning::REGISTRATION_NOT_CONFIDENT;
        }
        let table_z = match header.table_mode {
            proto::table_mode::NONE => None,
            proto::table_mode::GIVEN => Some(header.table_z_m as f64),
            _ if is_z_up(opts.up) => Some(tool.table_z_under(&reg)),
            _ => {
                warnings |= proto::grasp_warning::NO_TABLE_FRAME_NOT_Z_UP;
                None
            }
        };
        let mut solver = GraspSolver::new(hand, SolveOptions { seed: header.seed, ..SolveOptions::default() });
        let out = solve_transferred(&mut solver, &assets.demo, &tool, table_z, &pre)
            .map_err(|e| Status::invalid(format!("cannot solve the grasp: {e}")))?;
        if !out.pregrasp.collision_free {
            warnings |= proto::grasp_warning::PREGRASP_IN_COLLISION;
        }
        let mut r = proto::GraspResponse::zeroed();
        r.registration = registration_to_wire(&reg, points.len(), opts.viewpoint);
        r.grasp = hand_to_wire(&out.grasp);
        r.pregrasp = hand_to_wire(&out.pregrasp.grasp);
        for (slot, n) in r.actuated_names.iter_mut().zip(&self.actuated_names) {
            *slot = *n;
        }
        for (slot, n) in r.joint_names.iter_mut().zip(&self.joint_names) {
            *slot = *n;
        }
        r.actuated_count = self.actuated_names.len() as u32;
        r.joint_count = self.joint_names.len() as u32;
        r.task_space_distance_m = out.task_space_distance_cm * 1e-2;
        r.residual_mean_m = out.report.residual_mm.mean * 1e-3;
        r.residual_max_m = out.report.residual_mm.max * 1e-3;
        r.penetration_m = out.report.penetration_mm * 1e-3;
        r.pregrasp_min_clearance_m =
            if out.pregrasp.min_clearance_m.is_finite() { out.pregrasp.min_clearance_m } else { f64::MAX };
        r.pregrasp_collision_free = out.pregrasp.collision_free as u32;
        r.table_used = table_z.is_some() as u32;
        r.table_z_m = table_z.unwrap_or(0.0);
        r.warnings = warnings;
        Ok(r)
    }
}

impl GraspAssets {
    /// The category's demonstration (the file at `demo`, else the bundled
    /// one) for `hand`, carried by `space` (the category's shape space).
    /// The demonstration must have been made with `hand`: its name, actuated
    /// joints, limits and keypoints are checked here, not at the first
    /// request. Err: why Grasp cannot be served.
    pub fn load(category: Category, hand: &HandModel, space: &ShapeSpace, demo: Option<&Path>) -> Result<Self, String> {
        let demo = match demo {
            Some(path) => Demonstration::load(path),
            None => Demonstration::builtin(category),
        }
        .map_err(|e| format!("demonstration: {e}"))?;
        let demo_keypoints = demo.checked_keypoints(hand).map_err(|e| match e {
            GraspError::DemonstrationOfAnotherHand { .. } => e.to_string(),
            e => format!("demonstration: {e}"),
        })?;
        let canonical_mesh = crate::tools::family(category)
            .map_err(|e| e.to_string())?
            .into_iter()
            .find(|i| i.split == Split::Canonical)
            .ok_or("the family has no canonical instance")?
            .mesh;
        let transfer = TransferModel::new(space, &demo_keypoints, &canonical_mesh);
        Ok(GraspAssets { demo, transfer })
    }
}

fn hand_to_wire(g: &crate::grasp::Grasp) -> proto::HandConfiguration {
    let mut h = proto::HandConfiguration::zeroed();
    let q = g.wrist_pose_world.rotation.coords;
    h.rotation_cloud_from_wrist_xyzw = [q.x, q.y, q.z, q.w];
    let t = g.wrist_pose_world.translation.vector;
    h.translation_cloud_from_wrist_m = [t.x, t.y, t.z];
    for (slot, v) in h.actuated.iter_mut().zip(&g.actuated) {
        *slot = *v;
    }
    for (slot, v) in h.joints.iter_mut().zip(&g.joints) {
        *slot = *v;
    }
    h
}

/// Pre-grasp options from the header (0 = the engine's default).
pub fn pregrasp_options(h: &proto::RequestHeader) -> Result<PreGraspOptions, Status> {
    let d = PreGraspOptions::default();
    let (b, f) = (h.pregrasp_backoff_m, h.pregrasp_joint_fraction);
    if !(b.is_finite() && (0.0..=0.5).contains(&b)) {
        return Err(Status::invalid(format!("pregrasp_backoff_m {b}: 0 (default) to 0.5 m")));
    }
    if !(f.is_finite() && (0.0..=1.0).contains(&f)) {
        return Err(Status::invalid(format!("pregrasp_joint_fraction {f}: 0 (default) to 1")));
    }
    Ok(PreGraspOptions {
        backoff_m: if b == 0.0 { d.backoff_m } else { b as f64 },
        joint_fraction: if f == 0.0 { d.joint_fraction } else { f as f64 },
        ..d
    })
}

/// f32 wire points → f64 engine points; rejects NaN/Inf. The caller's memory
/// is read exactly once (a client writing into it meanwhile cannot make the
/// checked and the used values differ).
pub fn convert_cloud(points: &[proto::Point]) -> Result<Vec<Point3<f64>>, Status> {
    if points.is_empty() {
        return Err(Status::invalid("empty cloud"));
    }
    let mut out = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let [x, y, z] = p.0;
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(Status::invalid(format!("point {i} has a non-finite coordinate ({x}, {y}, {z})")));
        }
        out.push(Point3::new(x as f64, y as f64, z as f64));
    }
    Ok(out)
}

/// Registration options from the request header (the rest: the engine's defaults).
pub fn register_options(h: &proto::RequestHeader) -> Result<RegisterOptions, Status> {
    let [x, y, z] = h.up_in_cloud;
    if !(x.is_finite() && y.is_finite() && z.is_finite()) {
        return Err(Status::invalid(format!("up_in_cloud ({x}, {y}, {z}) is not finite")));
    }
    let n2 = (x as f64).powi(2) + (y as f64).powi(2) + (z as f64).powi(2);
    let up = if n2 == 0.0 {
        None
    } else if n2 < 1e-12 {
        return Err(Status::invalid("up_in_cloud is too short to give a direction (all zero means unknown)"));
    } else {
        Some([x as f64, y as f64, z as f64])
    };
    if h.flags & !proto::flags::ALL != 0 {
        return Err(Status::invalid(format!("flags {:#x}: unknown bits", h.flags)));
    }
    let point = |flag: u32, name: &str, [x, y, z]: [f32; 3]| -> Result<Option<[f64; 3]>, Status> {
        if h.flags & flag == 0 {
            return Ok(None);
        }
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(Status::invalid(format!("{name} is not finite")));
        }
        Ok(Some([x as f64, y as f64, z as f64]))
    };
    let viewpoint = point(proto::flags::VIEWPOINT, "viewpoint_in_cloud_m", h.viewpoint_in_cloud_m)?;
    let second_viewpoint =
        point(proto::flags::SECOND_VIEWPOINT, "second_viewpoint_in_cloud_m", h.second_viewpoint_in_cloud_m)?;
    if second_viewpoint.is_some() && viewpoint.is_none() {
        return Err(Status::invalid("flag SECOND_VIEWPOINT needs VIEWPOINT (the first camera's position)"));
    }
    // A table given in a z-up frame is the plane the tool rests on: the
    // registration holds the tool's lowest point on it (`support_height`).
    let support_height = match h.table_mode {
        proto::table_mode::GIVEN if is_z_up(up) => {
            if !h.table_z_m.is_finite() {
                return Err(Status::invalid(format!("table_z_m {} is not finite", h.table_z_m)));
            }
            Some(h.table_z_m as f64)
        }
        _ => None,
    };
    Ok(RegisterOptions { up, viewpoint, second_viewpoint, support_height, seed: h.seed, ..Default::default() })
}

/// The wire's Registration of `reg`, a fit of `points` points given the
/// camera position `given` (the request's, if any).
pub fn registration_to_wire(
    reg: &crate::shape::Registration,
    points: usize,
    given: Option<[f64; 3]>,
) -> proto::Registration {
    let mut r = proto::Registration::zeroed();
    for (slot, v) in r.latent.iter_mut().zip(&reg.latent) {
        *slot = *v;
    }
    let q = reg.rotation_cloud_from_canonical.coords;
    r.rotation_cloud_from_canonical_xyzw = [q.x, q.y, q.z, q.w];
    let t = reg.translation_cloud_from_canonical;
    r.translation_cloud_from_canonical_m = [t.x, t.y, t.z];
    r.scale = reg.scale;
    r.sigma2_m2 = reg.sigma2;
    r.inlier_fraction = reg.fit.inlier_fraction;
    r.residual_m = reg.fit.residual_mm * 1e-3;
    r.inlier_threshold_m = reg.fit.inlier_mm * 1e-3;
    r.latent_dim = reg.latent.len().min(proto::MAX_LATENT) as u32;
    r.keypoint_count = reg.keypoints.len().min(proto::MAX_KEYPOINTS) as u32;
    r.confident = reg.fit.confident as u32;
    r.ambiguous_pose = reg.fit.ambiguous_pose as u32;
    r.stray_points = reg.fit.stray_points.min(u32::MAX as usize) as u32;
    r.table_points = reg.fit.table_points.min(u32::MAX as usize) as u32;
    r.coverage = reg.fit.coverage;
    r.view_width_m = reg.fit.view_width_mm * 1e-3;
    r.latent_mahalanobis = reg.fit.latent_mahalanobis;
    r.contradicted_fraction = reg.fit.contradicted_fraction.unwrap_or(-1.0);
    r.yaw_half_width_rad = reg.yaw_arc.map_or(-1.0, |a| a.half_width_rad as f32);
    r.points = points.min(u32::MAX as usize) as u32;
    (r.viewpoint_source, r.viewpoint_cloud_m) = match (given, reg.estimated_viewpoint) {
        (Some(v), _) => (proto::viewpoint_source::GIVEN, v),
        (None, Some(v)) => (proto::viewpoint_source::ESTIMATED, v),
        (None, None) => (proto::viewpoint_source::NONE, [0.0; 3]),
    };
    for (slot, k) in r.keypoints.iter_mut().zip(&reg.keypoints) {
        slot.name = proto::str_to_text(&k.name);
        slot.position_cloud_m = k.position;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clouds_with_nan_inf_or_nothing_are_invalid_arguments() {
        assert_eq!(convert_cloud(&[]).unwrap_err().code, StatusCode::InvalidArgument);
        let e = convert_cloud(&[proto::Point([0.0, 0.0, 0.0]), proto::Point([f32::NAN, 0.0, 0.0])]).unwrap_err();
        assert!(e.message.contains("point 1"), "{}", e.message);
        assert!(convert_cloud(&[proto::Point([f32::INFINITY, 0.0, 0.0])]).is_err());
        assert_eq!(convert_cloud(&[proto::Point([1.0, 2.0, 3.0])]).unwrap()[0], Point3::new(1.0, 2.0, 3.0));
    }

    #[test]
    fn up_in_cloud_zero_is_unknown_and_nan_is_invalid() {
        let mut h = proto::RequestHeader::zeroed();
        assert_eq!(register_options(&h).unwrap().up, None);
        h.up_in_cloud = [0.0, 0.0, 2.0];
        assert_eq!(register_options(&h).unwrap().up, Some([0.0, 0.0, 2.0]));
        h.up_in_cloud = [f32::NAN, 0.0, 1.0];
        assert_eq!(register_options(&h).unwrap_err().code, StatusCode::InvalidArgument);
    }

    #[test]
    fn a_given_table_in_a_z_up_frame_supports_the_tool() {
        let mut h = proto::RequestHeader::zeroed();
        h.up_in_cloud = [0.0, 0.0, 1.0];
        h.table_z_m = 0.75;
        assert_eq!(register_options(&h).unwrap().support_height, None, "AUTO: the cloud's lowest point is no support");
        h.table_mode = proto::table_mode::GIVEN;
        assert_eq!(register_options(&h).unwrap().support_height, Some(0.75));
        h.up_in_cloud = [3e-7, 0.0, 1.0];
        assert_eq!(register_options(&h).unwrap().support_height, Some(0.75), "+z to an f32 extrinsic's rounding");
        h.up_in_cloud = [0.0, 1.0, 0.0];
        assert_eq!(register_options(&h).unwrap().support_height, None, "the plane z = 0.75 is not across this up");
        h.up_in_cloud = [0.0, 0.02, 1.0];
        assert_eq!(register_options(&h).unwrap().support_height, None, "1° off z: not a plane z = const");
        h.up_in_cloud = [0.0, 0.0, 1.0];
        h.table_z_m = f32::NAN;
        assert_eq!(register_options(&h).unwrap_err().code, StatusCode::InvalidArgument);
    }

    /// The bundled hand under other names (`hand::renamed`) and, when
    /// `demo`, its mug demonstration.
    fn renamed_hand(dir: &Path, demo: bool) -> GraspSources {
        let h = crate::hand::renamed::write(dir).unwrap();
        let mut sources = GraspSources { hand: Some((h.urdf, h.keypoints)), demos: BTreeMap::new() };
        if demo {
            sources.demos.insert("mug".into(), h.mug_demo);
        }
        sources
    }

    fn mug_view() -> Vec<proto::Point> {
        mug_view_and_camera().0
    }

    /// A test mug's view and the camera's position (world frame).
    fn mug_view_and_camera() -> (Vec<proto::Point>, [f32; 3]) {
        use crate::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
        let mesh =
            crate::tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap().mesh;
        let (lo, hi) = mesh.aabb().unwrap();
        let scene = Scene::new(&mesh, nalgebra::Isometry3::identity(), Some(lo.z)).unwrap();
        let centre = Point3::from((lo.coords + hi.coords) / 2.0);
        let pose = standard_view(0, 8, centre, mesh.diagonal(), Intrinsics::default()).unwrap();
        let cam =
            DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise: DepthNoise::default() };
        let view = cam.capture(&scene, 1).unwrap();
        let points = view.points_world.iter().map(|p| proto::Point([p.x as f32, p.y as f32, p.z as f32])).collect();
        let c = pose.translation.vector;
        (points, [c.x as f32, c.y as f32, c.z as f32])
    }

    /// The built-in shape spaces' cache (assets/spaces).
    fn bundled_spaces() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces")
    }

    fn grasp_header() -> proto::RequestHeader {
        let mut h = proto::RequestHeader::zeroed();
        h.protocol_version = proto::PROTOCOL_VERSION;
        h.up_in_cloud = [0.0, 0.0, 1.0];
        h
    }

    /// Grasp's table when none is given lies under the points the fit kept:
    /// a flying pixel under the mug (far, or near enough for the stray test)
    /// neither lowers it nor changes the grasp; before, the lowest point of
    /// the whole cloud was the table.
    #[test]
    fn a_stray_point_under_the_tool_is_not_the_table() {
        let cache = bundled_spaces();
        let (engine, _) = Engine::load(&["mug".to_string()], &cache, &GraspSources::default()).unwrap();
        let (cloud, h) = (mug_view(), grasp_header());
        let plain = engine.grasp(0, &cloud, &h).unwrap();
        assert_eq!(plain.table_used, 1);
        let lowest = cloud.iter().map(|p| p.0[2]).fold(f32::INFINITY, f32::min) as f64;
        assert!((plain.table_z_m - lowest).abs() < 0.003, "table {} under a view down to {lowest}", plain.table_z_m);
        let centre = cloud.iter().fold([0.0f32; 3], |c, p| [c[0] + p.0[0], c[1] + p.0[1], c[2] + p.0[2]]);
        let [x, y] = [centre[0], centre[1]].map(|v| v / cloud.len() as f32);
        for (below_m, same) in [(0.3, true), (0.04, false)] {
            let mut stray = cloud.clone();
            stray.push(proto::Point([x, y, lowest as f32 - below_m]));
            let r = engine.grasp(0, &stray, &h).unwrap();
            assert!((r.table_z_m - plain.table_z_m).abs() < 1e-3, "{below_m}: {} vs {}", r.table_z_m, plain.table_z_m);
            if same {
                assert_eq!(r.registration.stray_points, plain.registration.stray_points + 1);
                assert_eq!(r.table_z_m, plain.table_z_m);
                assert_eq!(r.grasp.actuated, plain.grasp.actuated);
                assert_eq!(r.grasp.translation_cloud_from_wrist_m, plain.grasp.translation_cloud_from_wrist_m);
            }
        }
    }

    /// The wire carries the fit's verdicts as `graspd register --json` gives
    /// them (in metres where the CLI says mm); a fit with no camera position
    /// has no contradicted fraction (−1), one with a camera has one.
    #[test]
    fn the_wire_carries_every_verdict_of_the_fit() {
        let (engine, _) = Engine::load(&["mug".to_string()], &bundled_spaces(), &GraspSources::default()).unwrap();
        let (cloud, camera) = mug_view_and_camera();
        let mut h = grasp_header();
        h.flags = proto::flags::VIEWPOINT;
        h.viewpoint_in_cloud_m = camera;
        let c = &engine.categories[0];
        let points = convert_cloud(&cloud).unwrap();
        let direct = c.registrar.register(&points, &register_options(&h).unwrap()).unwrap();
        let wire = engine.register(0, &cloud, &h).unwrap().registration;
        assert_eq!(wire.coverage, direct.fit.coverage);
        assert_eq!(wire.latent_mahalanobis, direct.fit.latent_mahalanobis);
        assert_eq!(wire.view_width_m, direct.fit.view_width_mm * 1e-3);
        assert_eq!(wire.table_points as usize, direct.fit.table_points);
        assert_eq!(Some(wire.contradicted_fraction), direct.fit.contradicted_fraction.or(Some(-1.0)));
        assert!(wire.coverage > 0.2 && wire.view_width_m > 0.03, "a mug view: {wire:?}");
        assert!((0.0..0.06).contains(&wire.contradicted_fraction), "a right fit, the camera given: {wire:?}");
        // No camera given and none estimated (no up direction): nothing to contradict.
        (h.flags, h.up_in_cloud) = (0, [0.0; 3]);
        let direct = c.registrar.register(&points, &register_options(&h).unwrap()).unwrap();
        let wire = engine.register(0, &cloud, &h).unwrap().registration;
        assert_eq!((direct.fit.contradicted_fraction, wire.contradicted_fraction), (None, -1.0));
    }

    /// A second camera's position travels to the registration with the
    /// first's; alone, or not finite, it is refused.
    #[test]
    fn the_header_gives_a_second_cameras_position_with_the_first() {
        let mut h = grasp_header();
        (h.viewpoint_in_cloud_m, h.second_viewpoint_in_cloud_m) = ([0.5, 0.0, 0.375], [0.0, 0.5, 0.25]);
        h.flags = proto::flags::VIEWPOINT | proto::flags::SECOND_VIEWPOINT;
        let o = register_options(&h).unwrap();
        assert_eq!((o.viewpoint, o.second_viewpoint), (Some([0.5, 0.0, 0.375]), Some([0.0, 0.5, 0.25])));
        h.flags = proto::flags::VIEWPOINT;
        assert_eq!(register_options(&h).unwrap().second_viewpoint, None);
        h.flags = proto::flags::SECOND_VIEWPOINT;
        let e = register_options(&h).unwrap_err();
        assert!(e.code == StatusCode::InvalidArgument && e.message.contains("needs VIEWPOINT"), "{e:?}");
        h.flags = proto::flags::ALL;
        h.second_viewpoint_in_cloud_m[1] = f32::INFINITY;
        let e = register_options(&h).unwrap_err();
        assert!(e.message.contains("second_viewpoint_in_cloud_m is not finite"), "{e:?}");
    }

    /// A hand and demonstration named by the configuration are the ones
    /// Grasp solves for: the bundled hand under other names gives the same
    /// grasp, named as the configured hand names its joints.
    #[test]
    fn a_configured_hand_and_demonstration_serve_grasp() {
        let cache = bundled_spaces();
        let dir = tempfile::tempdir().unwrap();
        let names = vec!["mug".to_string()];
        let (bundled, _) = Engine::load(&names, &cache, &GraspSources::default()).unwrap();
        let (renamed, _) = Engine::load(&names, &cache, &renamed_hand(dir.path(), true)).unwrap();
        assert_eq!(renamed.hand(), Some(("sih_renamed", 5)));
        assert_eq!(renamed.categories[0].info.grasp_available, 1);
        let (cloud, h) = (mug_view(), grasp_header());
        let a = bundled.grasp(0, &cloud, &h).unwrap();
        let b = renamed.grasp(0, &cloud, &h).unwrap();
        let names_of = |r: &proto::GraspResponse| -> Vec<String> {
            r.actuated_names[..r.actuated_count as usize].iter().map(|n| proto::text_lossy(n)).collect()
        };
        assert!(names_of(&a).iter().any(|n| n == "palm_to_if_proximal"));
        assert!(names_of(&b).iter().any(|n| n == "palm_to_index_base"), "{:?}", names_of(&b));
        assert!(!names_of(&b).iter().any(|n| n == "palm_to_if_proximal"));
        assert_eq!(a.grasp.actuated, b.grasp.actuated);
        assert_eq!(a.grasp.translation_cloud_from_wrist_m, b.grasp.translation_cloud_from_wrist_m);
    }

    /// Another hand without a demonstration of its own: Register still
    /// serves, Grasp is refused with the reason; a configured demonstration
    /// or hand that does not fit or load stops the start.
    #[test]
    fn a_hand_without_its_demonstration_is_refused_clearly() {
        let cache = bundled_spaces();
        let dir = tempfile::tempdir().unwrap();
        let names = vec!["mug".to_string()];
        let (engine, _) = Engine::load(&names, &cache, &renamed_hand(dir.path(), false)).unwrap();
        let (cloud, h) = (mug_view(), grasp_header());
        assert!(engine.register(0, &cloud, &h).is_ok());
        // ListCategories says so; Health still names the hand that loaded.
        assert_eq!(engine.categories[0].info.grasp_available, 0);
        assert!(!engine.grasp_available());
        assert_eq!(engine.hand().map(|(name, _)| name), Some("sih_renamed"));
        let e = engine.grasp(0, &cloud, &h).unwrap_err();
        assert_eq!(e.code, StatusCode::FailedPrecondition);
        assert!(e.message.contains("made with hand `sih_right`, not `sih_renamed`"), "{}", e.message);
        // The bundled (sih_right) demonstration named for the renamed hand.
        let mut sources = renamed_hand(dir.path(), false);
        sources.demos.insert("mug".into(), Demonstration::builtin_path(Category::Mug));
        let e = Engine::load(&names, &cache, &sources).err().unwrap().to_string();
        assert!(e.contains("mug") && e.contains("made with hand `sih_right`"), "{e}");
        // A demonstration file that is not there.
        sources.demos.insert("mug".into(), dir.path().join("missing.json"));
        let e = Engine::load(&names, &cache, &sources).err().unwrap().to_string();
        assert!(e.contains("missing.json"), "{e}");
        // A hand whose URDF is not there.
        let sources =
            GraspSources { hand: Some((dir.path().join("no.urdf"), dir.path().join("k.json"))), ..Default::default() };
        let e = Engine::load(&names, &cache, &sources).err().unwrap().to_string();
        assert!(e.starts_with("hand:") && e.contains("no.urdf"), "{e}");
    }
}
