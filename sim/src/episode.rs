//! A scripted grasp-and-lift episode: the check that the physics and the
//! transferred grasps are good enough for a policy to learn on (issue 6's
//! scripted controller; moving to a goal pose comes with the tasks).
//!
//! At the 30 Hz control rate, from the pre-grasp:
//! 0. reach, only when the hand starts elsewhere (the neutral start, w/o PG:
//!    [`crate::plan::HandStart::Fixed`]): the wrist moves in a straight line
//!    to a stand-off on the pre-grasp's line ([`LiftScript::reach_standoff_m`]
//!    further back than the pre-grasp), the joints from where they are to
//!    the pre-grasp's; the approach then starts there, so the hand comes in
//!    along the pre-grasp direction through the pre-grasp;
//! 1. approach: the wrist moves in a straight line to the grasp's wrist pose
//!    (pushed `press_m` further along the palm normal: the solver places the
//!    palm on, or a margin off, the registered surface, and the wrist's weld
//!    is a spring, so a command at the surface presses with no force; the
//!    wrist's counterpart of the squeeze), joints held at the pre-grasp's;
//! 2. close: the joint targets ramp to the grasp's joints plus a squeeze
//!    (each joint that closes from the open hand to the grasp is commanded
//!    further by `squeeze_rad`, so the servos press on the tool rather than
//!    stop at first touch);
//! 3. settle, with the hand still;
//! 4. lift: the wrist rises by `lift_m`;
//! 5. hold: the wrist stays, for `hold_s`.
//!
//! The tool is held when, at the end of the hold, it touches the hand and
//! not the table, and its lowest point is at least [`HELD_CLEARANCE_M`] above
//! the table top (the paper's lift term measures the same lowest point). A
//! tool held but swung round in the hand (a mug hanging from its handle)
//! counts as held and is reported by its tilt; `upright` says it stayed
//! within [`UPRIGHT_TILT_RAD`] of its start orientation.

use std::time::Instant;

use graspd::grasp::Grasp;
use graspd::hand::HandModel;
use mujoco_rs::prelude::MjData;
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Translation3, Vector3};
use serde::Serialize;

use crate::engine::SimError;
use crate::hand::{HandAsset, HandMjcfOptions};
use crate::mjcf::PhysicsOptions;
use crate::plan::{GraspPlan, GraspPlanner, HandStart};
use crate::scene::Scene;
use crate::scene::{SceneSpec, Table};
use crate::tool::{DecompositionOptions, ToolBody};
use graspd::tools::Instance;

/// Lowest tool point above the table for a tool to count as held, metres.
pub const HELD_CLEARANCE_M: f64 = 0.01;
/// Largest tilt of a held tool's z axis from its start for `upright`, radians (30°).
pub const UPRIGHT_TILT_RAD: f64 = std::f64::consts::PI / 6.0;

/// Timings and amplitudes of the script.
#[derive(Clone, Debug, PartialEq)]
pub struct LiftScript {
    pub approach_s: f64,
    pub close_s: f64,
    pub settle_s: f64,
    pub lift_s: f64,
    /// Wrist rise, metres (the 10 cm).
    pub lift_m: f64,
    pub hold_s: f64,
    /// Extra closing commanded beyond the grasp's joints, radians.
    pub squeeze_rad: f64,
    /// How far past the grasp's wrist pose the approach goes, along the palm
    /// normal, metres: the palm presses on the tool instead of stopping where
    /// the solver put it (module docs, step 1).
    pub press_m: f64,
    /// The reach from a fixed start (module docs), seconds; 0 s when the hand starts at the pre-grasp.
    pub reach_s: f64,
    /// How much further back than the pre-grasp the reach ends, along the
    /// pre-grasp's line, metres (the approach then passes through the pre-grasp).
    pub reach_standoff_m: f64,
}

impl Default for LiftScript {
    fn default() -> Self {
        Self {
            approach_s: 1.0,
            close_s: 0.8,
            settle_s: 0.3,
            lift_s: 1.0,
            lift_m: 0.10,
            hold_s: 2.0,
            squeeze_rad: 0.3,
            press_m: 0.0,
            // 1 s fits the task scripts in the 10 s episode (Place mug's retreat ends at 10.0 s).
            reach_s: 1.0,
            reach_standoff_m: 0.05,
        }
    }
}

/// How an episode went.
#[derive(Clone, Debug, Serialize)]
pub struct LiftOutcome {
    /// In the hand, off the table, at the end of the hold (module docs).
    pub held: bool,
    /// Held, and tilted less than [`UPRIGHT_TILT_RAD`].
    pub upright: bool,
    /// The tool's lowest point above the table top at the end of the lift and of the hold, metres.
    pub clearance_after_lift_m: f64,
    pub clearance_after_hold_m: f64,
    /// How far the tool moved in the palm frame during the hold, metres (slip).
    pub slip_during_hold_m: f64,
    /// Tilt of the tool's z axis from its start at the end, radians.
    pub tilt_rad: f64,
    pub control_steps: usize,
    pub physics_steps: usize,
    /// Wall time of the physics steps alone, microseconds per step.
    pub physics_us_per_step: f64,
    /// Hand links touching the tool when the hand has closed (end of the settle phase).
    pub links_touching_at_grasp: Vec<String>,
    /// MuJoCo's warnings raised during the episode (instability, too many contacts), by name.
    pub warnings: Vec<String>,
}

/// Linear interpolation of poses (translation linear, rotation slerp).
pub(crate) fn lerp_pose(a: &Isometry3<f64>, b: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let s = s.clamp(0.0, 1.0);
    Isometry3::from_parts(
        Translation3::from(a.translation.vector.lerp(&b.translation.vector, s)),
        a.rotation.slerp(&b.rotation, s),
    )
}

/// Smooth 0 → 1 ramp (zero velocity at both ends) over [0, 1].
pub(crate) fn ease(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

/// The squeezed joint targets: further along each joint's closing direction.
pub fn squeezed(hand: &HandModel, grasp: &Grasp, squeeze_rad: f64) -> Vec<f64> {
    let mut q: Vec<f64> = grasp
        .actuated
        .iter()
        .zip(hand.open_hand())
        .map(|(&g, &o)| {
            let closing = g - o;
            // A joint the grasp barely moves is not a closing joint.
            if closing.abs() < 0.05 {
                g
            } else {
                g + squeeze_rad * closing.signum()
            }
        })
        .collect();
    hand.clamp_actuated(&mut q);
    q
}

/// The script as a function of time: wrist and joint targets for any
/// instant of the episode (no state, so many environments can share one).
#[derive(Clone, Debug)]
pub struct LiftController {
    /// The fixed start (wrist, joints) when the hand does not start at the pre-grasp.
    reach_from: Option<(Isometry3<f64>, Vec<f64>)>,
    /// Where the approach starts: the pre-grasp, or the stand-off behind it after a reach.
    approach_from: Isometry3<f64>,
    grasp_wrist: Isometry3<f64>,
    lifted_wrist: Isometry3<f64>,
    q_pre: Vec<f64>,
    q_squeeze: Vec<f64>,
    /// Length of the reach (0 s without one); the other phases start after it.
    reach_s: f64,
    /// End times of approach, close, settle, lift, hold.
    ends: [f64; 5],
    script: LiftScript,
}

impl LiftController {
    pub fn new(hand: &HandModel, plan: &GraspPlan, script: &LiftScript) -> Self {
        let grasp_wrist =
            plan.grasp.wrist_pose_world * Translation3::from(script.press_m * hand.palm_normal().into_inner());
        let pre_wrist = plan.pregrasp.wrist_pose_world;
        let (reach_from, approach_from, reach_s) = match &plan.start {
            HandStart::PreGrasp => (None, pre_wrist, 0.0),
            HandStart::Fixed { wrist_world, actuated } => {
                // Further out along the line from the grasp through the pre-grasp.
                let back = pre_wrist.translation.vector - grasp_wrist.translation.vector;
                let dir = back.try_normalize(1e-9).unwrap_or_else(Vector3::z);
                let standoff = Translation3::from(script.reach_standoff_m * dir) * pre_wrist;
                (Some((*wrist_world, actuated.clone())), standoff, script.reach_s.max(0.0))
            }
        };
        let mut ends = [script.approach_s, script.close_s, script.settle_s, script.lift_s, script.hold_s];
        ends[0] += reach_s;
        for k in 1..ends.len() {
            ends[k] += ends[k - 1];
        }
        Self {
            reach_from,
            approach_from,
            reach_s,
            grasp_wrist,
            lifted_wrist: Translation3::new(0.0, 0.0, script.lift_m) * grasp_wrist,
            q_pre: plan.pregrasp.actuated.clone(),
            q_squeeze: squeezed(hand, &plan.grasp, script.squeeze_rad),
            ends,
            script: script.clone(),
        }
    }

    /// Length of the whole script, seconds.
    pub fn duration(&self) -> f64 {
        self.ends[4]
    }

    /// The wrist command once lifted (the lift and hold phases' end).
    pub fn lifted_wrist(&self) -> Isometry3<f64> {
        self.lifted_wrist
    }

    /// End of the settle phase (the hand closed) and of the lift, seconds.
    pub fn closed_at(&self) -> f64 {
        self.ends[2]
    }
    pub fn lifted_at(&self) -> f64 {
        self.ends[3]
    }

    /// Wrist target and actuated joint targets (written into `q`) at time `t`.
    pub fn targets(&self, t: f64, q: &mut [f64]) -> Isometry3<f64> {
        let [approach, close, settle, lift, _] = self.ends;
        let sc = &self.script;
        if let Some((from, q_from)) = &self.reach_from {
            if t <= self.reach_s {
                let s = ease(t / self.reach_s);
                for ((q, a), b) in q.iter_mut().zip(q_from).zip(&self.q_pre) {
                    *q = a + s * (b - a);
                }
                return lerp_pose(from, &self.approach_from, s);
            }
        }
        if t <= approach {
            q.copy_from_slice(&self.q_pre);
            lerp_pose(&self.approach_from, &self.grasp_wrist, ease((t - self.reach_s) / sc.approach_s))
        } else if t <= close {
            let s = ease((t - approach) / sc.close_s);
            for ((q, a), b) in q.iter_mut().zip(&self.q_pre).zip(&self.q_squeeze) {
                *q = a + s * (b - a);
            }
            self.grasp_wrist
        } else if t <= settle {
            q.copy_from_slice(&self.q_squeeze);
            self.grasp_wrist
        } else if t <= lift {
            q.copy_from_slice(&self.q_squeeze);
            lerp_pose(&self.grasp_wrist, &self.lifted_wrist, ease((t - settle) / sc.lift_s))
        } else {
            q.copy_from_slice(&self.q_squeeze);
            self.lifted_wrist
        }
    }
}

/// Puts the scene at the episode's start: the tool at `tool_pose`, the hand
/// at the plan's start (its pre-grasp unless the plan says otherwise),
/// everything at rest.
pub fn reset_to_pregrasp<M: ModelType>(
    scene: &Scene,
    data: &mut MjData<M>,
    hand_model: &HandModel,
    plan: &GraspPlan,
    tool_pose: &Isometry3<f64>,
) -> Result<(), SimError> {
    let hand = scene.hand.as_ref().ok_or(SimError::MissingElement { kind: "hand", name: "hand".into() })?;
    let tool = scene.tools.first().ok_or(SimError::MissingElement { kind: "tool", name: "tool".into() })?;
    data.reset();
    tool.set_pose(data, tool_pose);
    let (wrist, q) = plan.start_configuration();
    hand.set_configuration(data, hand_model, &wrist, q);
    data.forward();
    Ok(())
}

/// Physics steps per control step of a scene at `control_hz`.
pub fn substeps(scene: &Scene, control_hz: f64) -> usize {
    (1.0 / (control_hz * scene.model.opt().timestep)).round().max(1.0) as usize
}

/// Runs the script from the plan's pre-grasp. `data` is reset first; the
/// tool starts at `tool_pose`, the plan must already be carried to it.
pub fn run_lift<M: ModelType>(
    scene: &Scene,
    data: &mut MjData<M>,
    hand_model: &HandModel,
    plan: &GraspPlan,
    tool_pose: &Isometry3<f64>,
    script: &LiftScript,
    control_hz: f64,
) -> Result<LiftOutcome, SimError> {
    reset_to_pregrasp(scene, data, hand_model, plan, tool_pose)?;
    let hand = scene.hand.as_ref().ok_or(SimError::MissingElement { kind: "hand", name: "hand".into() })?;
    let tool = scene.tools.first().ok_or(SimError::MissingElement { kind: "tool", name: "tool".into() })?;
    let substeps = substeps(scene, control_hz);
    // Diagnostics on stderr every 0.1 s, as graspd's GRASPD_EVAL_TRACE.
    let trace = std::env::var_os("GRASPD_SIM_TRACE").is_some_and(|v| v != "0");
    let table_z = scene.table.map_or(0.0, |(_, z)| z);
    let start_up = tool.pose(data).rotation * Vector3::z();
    let controller = LiftController::new(hand_model, plan, script);
    let n_control = (controller.duration() * control_hz).round() as usize;
    let mut clearance_after_lift = f64::NAN;
    let mut palm_from_tool_at_hold: Option<Isometry3<f64>> = None;
    let mut physics_time = 0.0;
    let mut q_target = plan.pregrasp.actuated.clone();
    let mut touching = Vec::new();
    for k in 0..n_control {
        // Targets for the control interval that ends at t.
        let t = (k + 1) as f64 / control_hz;
        let wrist = controller.targets(t, &mut q_target);
        hand.set_wrist_target(data, &wrist);
        hand.set_joint_targets(data, &q_target);
        let t0 = Instant::now();
        for _ in 0..substeps {
            data.step();
        }
        physics_time += t0.elapsed().as_secs_f64();
        if trace && k % 3 == 2 {
            let pose = tool.pose(data);
            let q = hand.actuated_positions(data, hand_model);
            let wrist_err = (hand.wrist_pose(data).translation.vector - wrist.translation.vector).norm();
            eprintln!(
                "t {t:5.2} tool ({:7.4} {:7.4} {:7.4}) tilt {:5.1}° clear {:6.1} mm  wrist err {:4.1} mm  q-q* [{}]  touching [{}]",
                pose.translation.x,
                pose.translation.y,
                pose.translation.z,
                (pose.rotation * Vector3::z()).dot(&start_up).clamp(-1.0, 1.0).acos().to_degrees(),
                1e3 * (tool.lowest_z(data) - table_z),
                1e3 * wrist_err,
                q.iter().zip(&q_target).map(|(a, b)| format!("{:+.2}", a - b)).collect::<Vec<_>>().join(" "),
                touching_links(scene, data, hand_model, tool.body).join(" ")
            );
        }
        if touching.is_empty() && t > controller.closed_at() - 0.5 / control_hz {
            touching = touching_links(scene, data, hand_model, tool.body);
        }
        if palm_from_tool_at_hold.is_none() && t > controller.lifted_at() - 0.5 / control_hz {
            clearance_after_lift = tool.lowest_z(data) - table_z;
            palm_from_tool_at_hold = Some(hand.wrist_pose(data).inverse() * tool.pose(data));
        }
    }
    let end_pose = tool.pose(data);
    let clearance_after_hold = tool.lowest_z(data) - table_z;
    let on_table = scene.in_contact(data, tool.body, 0);
    let in_hand = hand.link_bodies.iter().any(|&b| scene.in_contact(data, tool.body, b));
    let held = in_hand && !on_table && clearance_after_hold >= HELD_CLEARANCE_M;
    let slip = palm_from_tool_at_hold
        .map(|p| ((hand.wrist_pose(data).inverse() * end_pose).translation.vector - p.translation.vector).norm())
        .unwrap_or(f64::NAN);
    let up = end_pose.rotation * Vector3::z();
    let tilt = up.dot(&start_up).clamp(-1.0, 1.0).acos();
    let physics_steps = n_control * substeps;
    Ok(LiftOutcome {
        held,
        upright: held && tilt < UPRIGHT_TILT_RAD,
        clearance_after_lift_m: clearance_after_lift,
        clearance_after_hold_m: clearance_after_hold,
        slip_during_hold_m: slip,
        tilt_rad: tilt,
        control_steps: n_control,
        physics_steps,
        physics_us_per_step: 1e6 * physics_time / physics_steps.max(1) as f64,
        links_touching_at_grasp: touching,
        warnings: warnings(data),
    })
}

/// Names of the hand links in contact with `tool_body`, in link order.
pub fn touching_links<M: ModelType>(
    scene: &Scene,
    data: &MjData<M>,
    hand_model: &HandModel,
    tool_body: usize,
) -> Vec<String> {
    let Some(hand) = &scene.hand else { return Vec::new() };
    let body_of = |g: i32| usize::try_from(g).ok().map(|g| scene.model.geom_bodyid()[g] as usize);
    let mut touching = vec![false; hand.link_bodies.len()];
    for c in data.contact() {
        let (Some(a), Some(b)) = (body_of(c.geom[0]), body_of(c.geom[1])) else { continue };
        let other = if a == tool_body {
            b
        } else if b == tool_body {
            a
        } else {
            continue;
        };
        if let Some(l) = hand.link_bodies.iter().position(|&lb| lb == other) {
            touching[l] = true;
        }
    }
    hand_model.links().iter().zip(touching).filter(|(_, t)| *t).map(|(l, _)| l.name.clone()).collect()
}

/// Names of MuJoCo warnings raised since the last reset.
pub fn warnings<M: ModelType>(data: &MjData<M>) -> Vec<String> {
    // MuJoCo 3.17's mjtWarning order.
    const NAMES: [&str; 7] = ["inertia", "contactfull", "constraintfull", "badqpos", "badqvel", "badqacc", "badctrl"];
    data.warning().iter().zip(NAMES).filter(|(w, _)| w.number > 0).map(|(_, n)| n.to_owned()).collect()
}

/// Everything that sets up a lift episode besides the tool.
#[derive(Clone, Debug, Default)]
pub struct LiftSetup {
    pub physics: PhysicsOptions,
    pub hand: HandMjcfOptions,
    pub decomposition: DecompositionOptions,
    pub script: LiftScript,
}

/// Plans the grasp of one instance of a family, builds its scene (table,
/// the instance's own mesh at its canonical pose, the hand at the
/// pre-grasp) and runs the scripted lift.
pub fn lift_instance(
    asset: &HandAsset,
    planner: &mut GraspPlanner,
    instance: &Instance,
    setup: &LiftSetup,
) -> Result<(GraspPlan, LiftOutcome), SimError> {
    let plan = planner.plan(instance)?;
    let tool = ToolBody::from_instance(instance, &setup.decomposition)?;
    let tool_pose = Isometry3::identity();
    let plan = plan.carried(asset.model(), &tool_pose);
    let spec = SceneSpec {
        name: format!("lift_{}", instance.name),
        physics: setup.physics.clone(),
        table: Some(Table::default()),
        tools: vec![(&tool, tool_pose)],
        hand: Some((asset, setup.hand.clone(), plan.pregrasp.wrist_pose_world)),
        ..Default::default()
    };
    let scene = spec.build()?;
    let mut data = MjData::new(scene.model.clone());
    let outcome =
        run_lift(&scene, &mut data, asset.model(), &plan, &tool_pose, &setup.script, setup.physics.control_hz)?;
    Ok((plan, outcome))
}

#[cfg(test)]
mod tests {
    use super::*;
    use graspd::tools::{self, Category, Split};

    fn planner(asset: &HandAsset) -> GraspPlanner {
        GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap()
    }

    /// The demonstrated grasp on the canonical mug: closed, lifted 10 cm and
    /// held for 2 s, upright, by the thumb against the fingers.
    #[test]
    fn canonical_mug_is_lifted_and_held() {
        let asset = HandAsset::default_sih().unwrap();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let (plan, out) = lift_instance(&asset, &mut planner(&asset), &mug, &LiftSetup::default()).unwrap();
        assert_eq!(plan.source, "demonstration");
        assert!(out.held && out.upright, "{out:?}");
        assert!(out.clearance_after_hold_m > 0.05, "{out:?}");
        assert!(out.links_touching_at_grasp.iter().any(|l| l.starts_with("th_")), "{out:?}");
        assert!(out.links_touching_at_grasp.iter().any(|l| l.starts_with("if_") || l.starts_with("mf_")), "{out:?}");
        assert!(out.warnings.is_empty(), "{out:?}");
    }

    /// The approach ends `press_m` past the grasp's wrist, along the palm
    /// normal, with the grasp's orientation; the lift rises from there.
    #[test]
    fn the_approach_presses_past_the_grasp_along_the_palm_normal() {
        let asset = HandAsset::default_sih().unwrap();
        let hand = asset.model();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let plan = planner(&asset).plan(&mug).unwrap();
        let script = LiftScript { press_m: 0.006, ..LiftScript::default() };
        let lift = LiftController::new(hand, &plan, &script);
        let mut q = vec![0.0; hand.actuated_joints().len()];
        let at_grasp = lift.targets(script.approach_s, &mut q);
        let grasp = plan.grasp.wrist_pose_world;
        let normal = grasp.rotation * hand.palm_normal().into_inner();
        let shift = at_grasp.translation.vector - grasp.translation.vector;
        assert!((shift - 0.006 * normal).norm() < 1e-12, "{shift:?} vs {normal:?}");
        assert!(at_grasp.rotation.angle_to(&grasp.rotation) < 1e-12);
        let lifted = lift.lifted_wrist().translation.vector - at_grasp.translation.vector;
        assert!((lifted - Vector3::new(0.0, 0.0, script.lift_m)).norm() < 1e-12, "{lifted:?}");
    }

    /// The same episode with a hand that never closes (grasp joints = the
    /// open hand, no squeeze): the mug stays on the table. The criterion
    /// needs the grasp, not just the lift of the wrist.
    #[test]
    fn an_open_hand_lifts_nothing() {
        let asset = HandAsset::default_sih().unwrap();
        let hand = asset.model();
        let (mug, tool) = crate::tool::canonical_mug();
        let mut plan = planner(&asset).plan(&mug).unwrap();
        plan.grasp.actuated = hand.open_hand().to_vec();
        plan.pregrasp.actuated = hand.open_hand().to_vec();
        let setup = LiftSetup::default();
        let spec = SceneSpec {
            name: "open_hand".into(),
            physics: setup.physics.clone(),
            table: Some(Table::default()),
            tools: vec![(&tool, Isometry3::identity())],
            hand: Some((&asset, setup.hand.clone(), plan.pregrasp.wrist_pose_world)),
            ..Default::default()
        };
        let scene = spec.build().unwrap();
        let mut data = MjData::new(scene.model.clone());
        let script = LiftScript { squeeze_rad: 0.0, ..LiftScript::default() };
        let out = run_lift(&scene, &mut data, hand, &plan, &Isometry3::identity(), &script, 30.0).unwrap();
        assert!(!out.held, "{out:?}");
        assert!(out.clearance_after_hold_m < HELD_CLEARANCE_M, "{out:?}");
    }

    /// Transferred grasps on the training mugs (shape-space latents, as
    /// Table I): most are held. Measured 8 of 10 with the default settings
    /// (`sim lift --instances train`); the floor leaves one of margin.
    #[test]
    fn most_training_mugs_are_held() {
        let asset = HandAsset::default_sih().unwrap();
        let mut planner = planner(&asset);
        let family = tools::family(Category::Mug).unwrap();
        let mut held = Vec::new();
        for mug in family.iter().filter(|i| i.split == Split::Train) {
            let (_, out) = lift_instance(&asset, &mut planner, mug, &LiftSetup::default()).unwrap();
            if out.held {
                held.push(mug.name.clone());
            }
        }
        assert!(held.len() >= 7, "held only {held:?}");
    }
}
