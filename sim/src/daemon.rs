//! Grasps from a running graspd daemon (`graspd serve`), the simulator as a
//! co-located client: the scene's depth camera takes the tool's partial
//! cloud at its pose in the episode ([`crate::camera`]), the cloud goes to
//! the daemon's Grasp method in the lab frame (graspd-client, shared
//! memory), and the answer (registration, grasp, pre-grasp, all in the lab
//! frame) is converted into the tool's frame, where the simulator's plans
//! live ([`crate::plan::GraspPlan`]: carried to each episode's start).
//!
//! What the daemon is told besides the cloud, as a lab would tell it: the
//! cloud's frame is z up (`up`), the camera's origin in it (`viewpoint`:
//! visibility weights and the free-space check of the registration), the
//! table's height in it when the category's demonstration was authored with
//! a table (as the in-process plan and `graspd eval grasp`: the hammer's is
//! not), and a seed (the episode's).

use std::time::{Duration, Instant};

use graspd::grasp::transfer::{is_z_up, solve_transferred, Similarity, TransferredTool};
use graspd::grasp::{Grasp, GraspSolver, PreGraspOptions, SolveOptions};
use graspd::hand::HandModel;
use graspd::service::engine::GraspAssets;
use graspd::shape::{RegisterOptions, Registrar, ShapeSpace};
use graspd::tools::Category;
use graspd_client::{Client, ClientOptions, CloudOptions, StatusCode, Table};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::camera::{LabFrame, SceneCamera};
use crate::engine::SimError;

/// Fewer points than this and the view is refused before it reaches the
/// daemon (a tool out of the frame, or hidden): the registration needs a
/// surface, not a handful of pixels.
pub const MIN_CLOUD_POINTS: usize = 200;

/// How to reach the daemon.
#[derive(Clone, Debug)]
pub struct DaemonOptions {
    /// The daemon's `service_prefix`.
    pub prefix: String,
    /// Deadline of one Grasp call (registration, solve, pre-grasp).
    pub timeout: Duration,
    /// How long to wait for a daemon to appear when connecting.
    pub connect_timeout: Duration,
}

impl Default for DaemonOptions {
    fn default() -> Self {
        Self {
            prefix: graspd_client::protocol::DEFAULT_PREFIX.to_owned(),
            // A Grasp takes tens of milliseconds on an idle core; the generous
            // deadline is for a loaded, shared machine.
            timeout: Duration::from_secs(10),
            connect_timeout: Duration::from_secs(2),
        }
    }
}

/// A daemon's grasp, in the tool's frame, and what the call cost.
#[derive(Clone, Debug)]
pub struct DaemonGrasp {
    pub grasp: Grasp,
    pub pregrasp: Grasp,
    /// The registered pose: the category's canonical frame in the tool's
    /// frame, with the registration's scale (identity for a perfect fit of
    /// the canonical tool).
    pub tool_from_canonical: Similarity,
    pub latent: Vec<f64>,
    pub task_space_distance_cm: f64,
    pub pregrasp_collision_free: bool,
    pub registration_confident: bool,
    pub ambiguous_pose: bool,
    /// The turns about the tool's upright axis the view left open (half
    /// width, rad; 0: settled; None: not assessed).
    pub yaw_half_width_rad: Option<f64>,
    /// Share of the fitted shape's camera-facing surface the view
    /// contradicts (something in front of the tool raises it; None: not assessed).
    pub contradicted_fraction: Option<f64>,
    /// The daemon's warnings (e.g. `registration_not_confident`).
    pub warnings: Vec<String>,
    pub cloud_points: usize,
    /// The whole call as the client sees it: the cloud written into shared
    /// memory, sent, answered, ms.
    pub latency_ms: f64,
    /// The daemon's engine time (registration, solve, pre-grasp), ms.
    pub engine_ms: f64,
}

/// Who answers a camera view: a running daemon, or graspd's engine in this
/// process doing what the daemon's Grasp does (`--grasp-from register`: the
/// same registration, transfer, solve and pre-grasp, without the transport;
/// it tells the registration's part in a grasp from the daemon's).
enum Backend {
    Client(Box<Client>),
    Engine(Box<EngineBackend>),
}

/// The daemon's Grasp done in this process (graspd's `service::engine`).
struct EngineBackend {
    registrar: Registrar,
    /// The demonstration and its transfer model, as the daemon loads them.
    assets: GraspAssets,
}

/// A connected client of one daemon (or the engine in-process), with the camera and frame it uses.
pub struct DaemonGrasper {
    backend: Backend,
    options: DaemonOptions,
    pub camera: SceneCamera,
    pub lab: LabFrame,
}

impl DaemonGrasper {
    /// Connects to the daemon of `options.prefix` and checks that it can
    /// serve Grasp for `category` with a shape space of `latent_dim` modes
    /// (the simulator reads the daemon's latent in its own copy of the
    /// space, for the generalised demonstration the reward measures).
    pub fn connect(
        options: DaemonOptions,
        category: Category,
        latent_dim: usize,
        camera: SceneCamera,
        lab: LabFrame,
    ) -> Result<Self, SimError> {
        let err = |reason: String| SimError::Daemon { prefix: options.prefix.clone(), reason };
        let mut client = Client::connect(ClientOptions {
            prefix: options.prefix.clone(),
            connect_timeout: options.connect_timeout,
            ..ClientOptions::default()
        })
        .map_err(|e| err(call_error(&e)))?;
        let health = client.health().map_err(|e| err(call_error(&e)))?;
        if !health.grasp_available {
            return Err(err("it does not serve Grasp (no hand model or demonstration loaded)".into()));
        }
        let categories = client.categories().map_err(|e| err(call_error(&e)))?;
        let Some(info) = categories.iter().find(|c| c.name == category.name()) else {
            let served: Vec<&str> = categories.iter().map(|c| c.name.as_str()).collect();
            return Err(err(format!("it does not serve the {category} category (it serves {served:?})")));
        };
        if info.latent_dim as usize != latent_dim {
            return Err(err(format!(
                "its {category} shape space has {} modes, the simulator's {latent_dim}: both must load the same artefact (assets/spaces)",
                info.latent_dim
            )));
        }
        tracing::info!(prefix = %options.prefix, pid = health.pid, version = %health.server_version, "connected to graspd");
        Ok(Self { backend: Backend::Client(Box::new(client)), options, camera, lab })
    }

    /// No daemon: the camera's views are registered and grasped by graspd's
    /// engine in this process, in `space` (the simulator's copy), exactly as
    /// the daemon's Grasp does (same options, the cloud rounded to f32 as on
    /// the wire). `prefix()` is `in-process`.
    pub fn in_process(
        hand: &HandModel,
        category: Category,
        space: ShapeSpace,
        camera: SceneCamera,
        lab: LabFrame,
    ) -> Result<Self, SimError> {
        let assets = GraspAssets::load(category, hand, &space, None).map_err(|reason| SimError::Plan { reason })?;
        let backend = EngineBackend { registrar: Registrar::new(space), assets };
        Ok(Self {
            backend: Backend::Engine(Box::new(backend)),
            options: DaemonOptions { prefix: "in-process".into(), ..DaemonOptions::default() },
            camera,
            lab,
        })
    }

    /// Whether the daemon answers (false: the engine in this process).
    pub fn is_daemon(&self) -> bool {
        matches!(self.backend, Backend::Client(_))
    }

    pub fn prefix(&self) -> &str {
        &self.options.prefix
    }

    /// The daemon's grasp of the tool whose mesh (tool frame) is `mesh`,
    /// standing at `tool_pose_sim` on a table at `table_z`: the camera's view
    /// (noise from `seed`), a Grasp call, the answer in the tool's frame.
    #[allow(clippy::too_many_arguments)]
    pub fn grasp(
        &mut self,
        hand: &HandModel,
        category: Category,
        mesh: &graspd::geometry::TriMesh,
        tool_pose_sim: &Isometry3<f64>,
        table_z: f64,
        with_table: bool,
        seed: u64,
    ) -> Result<DaemonGrasp, SimError> {
        let cloud_sim = self.camera.capture(mesh, tool_pose_sim, table_z, seed)?;
        if cloud_sim.len() < MIN_CLOUD_POINTS {
            return Err(SimError::Camera {
                reason: format!(
                    "the camera sees {} points of the tool (fewer than {MIN_CLOUD_POINTS}): is it in the view?",
                    cloud_sim.len()
                ),
            });
        }
        let lab_from_sim = self.lab.lab_from_sim();
        let cloud: Vec<[f32; 3]> = cloud_sim
            .iter()
            .map(|p| {
                let q = lab_from_sim * p;
                [q.x as f32, q.y as f32, q.z as f32]
            })
            .collect();
        let up = lab_from_sim * Vector3::z();
        let eye = lab_from_sim * self.camera.eye_sim;
        let table = lab_from_sim * Point3::new(0.0, 0.0, table_z);
        let opts = CloudOptions {
            cloud_frame: "lab".into(),
            up: Some([up.x as f32, up.y as f32, up.z as f32]),
            viewpoint: Some([eye.x as f32, eye.y as f32, eye.z as f32]),
            seed,
            table: Some(if with_table { Table::At(table.z as f32) } else { Table::None }),
            ..CloudOptions::default()
        };
        let tool_from_lab = tool_pose_sim.inverse() * self.lab.sim_from_lab();
        let client = match &mut self.backend {
            Backend::Client(client) => client,
            Backend::Engine(engine) => {
                let t0 = Instant::now();
                let mut out = engine.grasp(hand, &cloud, &opts, &tool_from_lab)?;
                out.latency_ms = 1e3 * t0.elapsed().as_secs_f64();
                out.engine_ms = out.latency_ms;
                return Ok(out);
            }
        };
        let t0 = Instant::now();
        let answer = client
            .grasp_with(category.name(), &cloud, &opts, self.options.timeout)
            .map_err(|e| SimError::Daemon { prefix: self.options.prefix.clone(), reason: call_error(&e) })?;
        let latency_ms = 1e3 * t0.elapsed().as_secs_f64();
        let timing = client.last_call();
        let (grasp, pregrasp, tool_from_canonical) = grasp_in_tool_frame(hand, &answer, &tool_from_lab)?;
        Ok(DaemonGrasp {
            grasp,
            pregrasp,
            tool_from_canonical,
            latent: answer.registration.latent.clone(),
            task_space_distance_cm: 100.0 * answer.task_space_distance_m,
            pregrasp_collision_free: answer.pregrasp_collision_free,
            registration_confident: answer.registration.fit.confident,
            ambiguous_pose: answer.registration.fit.ambiguous_pose,
            yaw_half_width_rad: answer.registration.fit.yaw_half_width_rad,
            contradicted_fraction: answer.registration.fit.contradicted_fraction,
            warnings: answer.warnings.iter().map(|w| (*w).to_owned()).collect(),
            cloud_points: cloud.len(),
            latency_ms,
            engine_ms: timing.compute_ns as f64 * 1e-6,
        })
    }
}

impl EngineBackend {
    /// What the daemon's Grasp does with `cloud` (lab frame) and `opts`
    /// (graspd `service::engine::Engine::grasp`), the answer moved into the
    /// tool's frame by `tool_from_lab`. Times are left at zero.
    fn grasp(
        &self,
        hand: &HandModel,
        cloud: &[[f32; 3]],
        opts: &CloudOptions,
        tool_from_lab: &Isometry3<f64>,
    ) -> Result<DaemonGrasp, SimError> {
        let err = |what: &str, e: &dyn std::fmt::Display| SimError::Plan { reason: format!("{what}: {e}") };
        let points: Vec<Point3<f64>> =
            cloud.iter().map(|p| Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)).collect();
        // What the daemon makes of the request's header (`engine::register_options`):
        // a given table in a z-up frame is also the registration's support.
        let up = opts.up.map(|u| u.map(f64::from));
        let support_height = match opts.table {
            Some(Table::At(z)) if is_z_up(up) => Some(z as f64),
            _ => None,
        };
        let register = RegisterOptions {
            up,
            viewpoint: opts.viewpoint.map(|u| u.map(f64::from)),
            second_viewpoint: opts.second_viewpoint.map(|u| u.map(f64::from)),
            support_height,
            seed: opts.seed,
            ..RegisterOptions::default()
        };
        let reg = self.registrar.register(&points, &register).map_err(|e| err("cannot register the cloud", &e))?;
        let tool = TransferredTool::from_registration(&self.registrar, &reg, &self.assets.transfer)
            .map_err(|e| err("cannot carry the demonstration onto the registered shape", &e))?;
        let table_z = match opts.table {
            Some(Table::At(z)) => Some(z as f64),
            _ => None,
        };
        let mut solver = GraspSolver::new(hand, SolveOptions { seed: opts.seed, ..SolveOptions::default() });
        let out = solve_transferred(&mut solver, &self.assets.demo, &tool, table_z, &PreGraspOptions::default())
            .map_err(|e| err("cannot solve the grasp", &e))?;
        let carry = |g: &Grasp| Grasp::new(hand, tool_from_lab * g.wrist_pose_world, g.actuated.clone());
        let pose = Similarity::of_registration(&reg);
        let tool_from_canonical = tool_from_lab * pose.rigid();
        let mut warnings = Vec::new();
        if !reg.fit.confident {
            warnings.push("registration_not_confident".to_owned());
        }
        if !out.pregrasp.collision_free {
            warnings.push("pregrasp_in_collision".to_owned());
        }
        Ok(DaemonGrasp {
            grasp: carry(&out.grasp),
            pregrasp: carry(&out.pregrasp.grasp),
            tool_from_canonical: Similarity {
                rotation: tool_from_canonical.rotation,
                translation: tool_from_canonical.translation.vector,
                scale: reg.scale,
            },
            latent: reg.latent.clone(),
            task_space_distance_cm: out.task_space_distance_cm,
            pregrasp_collision_free: out.pregrasp.collision_free,
            registration_confident: reg.fit.confident,
            ambiguous_pose: reg.fit.ambiguous_pose,
            yaw_half_width_rad: reg.yaw_arc.map(|a| a.half_width_rad),
            contradicted_fraction: reg.fit.contradicted_fraction,
            warnings,
            cloud_points: cloud.len(),
            latency_ms: 0.0,
            engine_ms: 0.0,
        })
    }
}

/// A client error in words, with the way out when no daemon is there.
fn call_error(e: &graspd_client::Error) -> String {
    if e.code == StatusCode::Unavailable {
        format!("{e} (is `graspd serve` running with this service_prefix?)")
    } else {
        e.to_string()
    }
}

/// A wire pose (`target_from_source`, quaternion x, y, z, w) as an isometry; refuses non-finite or zero rotations.
pub fn isometry_of(pose: &graspd_client::Pose) -> Result<Isometry3<f64>, SimError> {
    let [x, y, z, w] = pose.rotation_xyzw;
    let t = pose.translation;
    if !t.iter().chain(&pose.rotation_xyzw).all(|v| v.is_finite()) {
        return Err(SimError::Plan { reason: format!("the daemon's {} pose is not finite", pose.frame) });
    }
    let q = Quaternion::new(w, x, y, z);
    if q.norm() < 1e-9 {
        return Err(SimError::Plan { reason: format!("the daemon's {} rotation is a zero quaternion", pose.frame) });
    }
    Ok(Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_quaternion(q)))
}

/// A daemon's hand configuration as a [`Grasp`] in the frame of
/// `to_frame_from_cloud` (joints matched to the hand by name).
fn configuration(
    hand: &HandModel,
    c: &graspd_client::HandConfiguration,
    to_frame_from_cloud: &Isometry3<f64>,
    what: &str,
) -> Result<Grasp, SimError> {
    let mut q = Vec::with_capacity(hand.num_actuated());
    for name in hand.actuated_names() {
        let v = c.actuated.iter().find(|(n, _)| n == name).map(|(_, v)| *v).ok_or_else(|| SimError::Plan {
            reason: format!("the daemon's {what} has no value for the actuated joint `{name}`"),
        })?;
        q.push(v);
    }
    let grasp = Grasp::new(hand, to_frame_from_cloud * isometry_of(&c.wrist_pose)?, q);
    grasp.validate(hand).map_err(|e| SimError::Plan { reason: format!("the daemon's {what}: {e}") })?;
    Ok(grasp)
}

/// The daemon's answer (in the cloud's frame) moved into another frame:
/// `to_from_cloud` is that frame from the cloud's (for the simulator: the
/// tool's frame from the lab's). Returns the grasp, the pre-grasp and the
/// registered pose (canonical frame → that frame, with the scale).
pub fn grasp_in_tool_frame(
    hand: &HandModel,
    answer: &graspd_client::Grasp,
    to_from_cloud: &Isometry3<f64>,
) -> Result<(Grasp, Grasp, Similarity), SimError> {
    let grasp = configuration(hand, &answer.grasp, to_from_cloud, "grasp")?;
    let pregrasp = configuration(hand, &answer.pregrasp, to_from_cloud, "pre-grasp")?;
    let reg = &answer.registration;
    if !(reg.scale.is_finite() && reg.scale > 0.0) {
        return Err(SimError::Plan {
            reason: format!("the daemon's registration scale {} is not positive", reg.scale),
        });
    }
    // cloud_from_canonical (x = s·R·z + t) composed with the rigid frame change.
    let cloud_from_canonical = isometry_of(&reg.pose)?;
    let to_from_canonical = to_from_cloud * cloud_from_canonical;
    let similarity = Similarity {
        rotation: to_from_canonical.rotation,
        translation: to_from_canonical.translation.vector,
        scale: reg.scale,
    };
    Ok((grasp, pregrasp, similarity))
}

#[cfg(test)]
mod tests {
    use super::*;
    use graspd_client::{Fit, HandConfiguration, Pose, Registration};

    fn wire_pose(frame: &str, p: &Isometry3<f64>) -> Pose {
        let q = p.rotation.coords;
        Pose {
            frame: frame.into(),
            translation: [p.translation.x, p.translation.y, p.translation.z],
            rotation_xyzw: [q.x, q.y, q.z, q.w],
        }
    }

    fn wire_hand(hand: &HandModel, g: &Grasp, cloud_from_frame: &Isometry3<f64>) -> HandConfiguration {
        // Names in reverse order: the conversion must match by name, not position.
        let mut actuated: Vec<(String, f64)> =
            hand.actuated_names().map(str::to_owned).zip(g.actuated.iter().copied()).collect();
        actuated.reverse();
        HandConfiguration {
            wrist_pose: wire_pose("cloud_from_wrist", &(cloud_from_frame * g.wrist_pose_world)),
            actuated,
            joints: Vec::new(),
        }
    }

    fn answer(
        hand: &HandModel,
        grasp: &Grasp,
        pre: &Grasp,
        cloud_from_tool: &Isometry3<f64>,
        scale: f64,
    ) -> graspd_client::Grasp {
        graspd_client::Grasp {
            registration: Registration {
                category: "mug".into(),
                cloud_frame: "lab".into(),
                points: 1000,
                latent: vec![0.1, -0.2],
                pose: wire_pose("cloud_from_canonical", cloud_from_tool),
                scale,
                sigma2_m2: 1e-6,
                fit: Fit {
                    inlier_fraction: 1.0,
                    residual_m: 0.001,
                    inlier_threshold_m: 0.005,
                    confident: true,
                    ambiguous_pose: false,
                    stray_points: 0,
                    table_points: 0,
                    coverage: 0.4,
                    view_width_m: 0.08,
                    latent_mahalanobis: 1.0,
                    contradicted_fraction: Some(0.01),
                    yaw_half_width_rad: Some(0.0),
                },
                keypoints: Vec::new(),
                viewpoint: graspd_client::Viewpoint::None,
            },
            grasp: wire_hand(hand, grasp, cloud_from_tool),
            pregrasp: wire_hand(hand, pre, cloud_from_tool),
            task_space_distance_m: 0.003,
            residual_mean_m: 0.003,
            residual_max_m: 0.005,
            penetration_m: 0.0,
            pregrasp_min_clearance_m: 0.01,
            pregrasp_collision_free: true,
            table_z_m: Some(0.0),
            warnings: Vec::new(),
        }
    }

    /// A grasp known in the tool's frame, sent through the lab frame as the
    /// daemon would answer it, comes back where it was: the tool stands at a
    /// start turned and shifted in the simulator, the lab frame is turned a
    /// quarter about z and shifted. The carried plan then puts the wrist where
    /// the daemon said in the simulator's frame.
    #[test]
    fn a_daemon_grasp_comes_back_in_the_tool_frame() {
        let hand = HandModel::default_sih().unwrap();
        let demo = graspd::grasp::Demonstration::builtin(Category::Mug).unwrap();
        let grasp_tool = demo.grasp_at(&hand, &Isometry3::identity()).unwrap();
        let mut q = grasp_tool.actuated.clone();
        q[0] += 0.1;
        let pre_tool = Grasp::new(&hand, Isometry3::translation(-0.08, 0.0, 0.02) * grasp_tool.wrist_pose_world, q);
        let start = Isometry3::from_parts(
            Translation3::new(0.03, -0.04, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7),
        );
        let lab = LabFrame::default();
        let lab_from_tool = lab.lab_from_sim() * start;
        let a = answer(&hand, &grasp_tool, &pre_tool, &lab_from_tool, 1.1);
        let tool_from_lab = start.inverse() * lab.sim_from_lab();
        let (g, p, s) = grasp_in_tool_frame(&hand, &a, &tool_from_lab).unwrap();
        let close = |a: &Isometry3<f64>, b: &Isometry3<f64>| {
            (a.translation.vector - b.translation.vector).norm() < 1e-9 && a.rotation.angle_to(&b.rotation) < 1e-9
        };
        assert!(close(&g.wrist_pose_world, &grasp_tool.wrist_pose_world), "{g:?}");
        assert!(close(&p.wrist_pose_world, &pre_tool.wrist_pose_world), "{p:?}");
        assert_eq!(g.actuated, grasp_tool.actuated);
        assert_eq!(p.actuated, pre_tool.actuated);
        // The registered pose of a perfectly seen tool is the identity in its own frame, scale kept.
        assert!(s.translation.norm() < 1e-9 && s.rotation.angle() < 1e-9, "{s:?}");
        assert_eq!(s.scale, 1.1);
        // In the simulator's frame: the daemon's lab pose moved by sim_from_lab.
        let sim_wrist = start * g.wrist_pose_world;
        let lab_wrist = isometry_of(&a.grasp.wrist_pose).unwrap();
        assert!(close(&sim_wrist, &(lab.sim_from_lab() * lab_wrist)));
        // Ignoring the frame change (the lab taken for the simulator) would turn the wrist a quarter.
        assert!(lab_wrist.rotation.angle_to(&sim_wrist.rotation) > 1.0);
    }

    /// Answers the hand cannot take are errors, not panics.
    #[test]
    fn a_bad_answer_is_an_error() {
        let hand = HandModel::default_sih().unwrap();
        let demo = graspd::grasp::Demonstration::builtin(Category::Mug).unwrap();
        let g = demo.grasp_at(&hand, &Isometry3::identity()).unwrap();
        let good = answer(&hand, &g, &g, &Isometry3::identity(), 1.0);
        let mut missing = good.clone();
        missing.grasp.actuated.pop();
        assert!(grasp_in_tool_frame(&hand, &missing, &Isometry3::identity()).is_err());
        let mut nan = good.clone();
        nan.pregrasp.wrist_pose.translation[1] = f64::NAN;
        assert!(grasp_in_tool_frame(&hand, &nan, &Isometry3::identity()).is_err());
        let mut zero = good.clone();
        zero.registration.pose.rotation_xyzw = [0.0; 4];
        assert!(grasp_in_tool_frame(&hand, &zero, &Isometry3::identity()).is_err());
        let mut scale = good;
        scale.registration.scale = -1.0;
        assert!(grasp_in_tool_frame(&hand, &scale, &Isometry3::identity()).is_err());
    }

    /// No daemon under a prefix: a clear error naming the prefix and the way out.
    #[test]
    fn no_daemon_is_a_clear_error() {
        let options = DaemonOptions {
            prefix: format!("graspd_sim_nobody_{}", std::process::id()),
            connect_timeout: Duration::ZERO,
            ..DaemonOptions::default()
        };
        let err = DaemonGrasper::connect(options, Category::Mug, 8, SceneCamera::default(), LabFrame::default())
            .err()
            .expect("no daemon");
        let text = err.to_string();
        assert!(text.contains("graspd_sim_nobody_") && text.contains("graspd serve"), "{text}");
    }
}
