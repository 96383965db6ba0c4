//! The Place-mug episode with the scripted controller: pre-grasp → close →
//! lift → move to the goal → lower → release → retreat, 10 s at 30 Hz, the
//! reward of [`crate::task`] summed every control step.
//!
//! The first five phases are the lift script, then the controller carries
//! the tool ([`CarryController`]): a desired tool pose moves from where the
//! tool is at the end of the lift to above the goal (keeping its height),
//! then down to [`PlaceScript::place_clearance_m`] above it, and is held
//! there while the correction converges. Then the fingers open to the
//! pre-grasp's joints and the wrist backs off along the pre-grasp's offset
//! and up.
//!
//! Success is the paper's rule (d < 3 cm, θ < 0.2 rad) on the tool's pose at
//! the end of the episode, with the hand gone: the mug must rest there.

use graspd::hand::HandModel;
use graspd::tools::Instance;
use mujoco_rs::prelude::MjData;
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Point3, Translation3};
use serde::Serialize;

use crate::carry::{CarryController, EpisodeStepper, Steering, TaskRig};
use crate::engine::SimError;
use crate::episode::{ease, lerp_pose, warnings, LiftScript, LiftSetup};
use crate::hand::HandAsset;
use crate::plan::{GraspInfo, GraspPlan, GraspPlanner};
use crate::scene::Scene;
use crate::task::{self, pose_reward, PlaceRanges, PoseEpisode, PoseReward, PoseState};

/// Timings of the phases after the lift, and the controller's settings.
#[derive(Clone, Debug, PartialEq)]
pub struct PlaceScript {
    /// Approach, close, settle and lift; its `hold_s` is the pause before moving.
    pub lift: LiftScript,
    pub move_s: f64,
    pub lower_s: f64,
    /// Held still just above the goal, letting the correction converge.
    pub align_s: f64,
    pub release_s: f64,
    pub retreat_s: f64,
    /// Height of the tool's base above the goal when the fingers open, metres.
    pub place_clearance_m: f64,
    /// Rise of the wrist while it backs off, metres.
    pub retreat_up_m: f64,
    pub steering: Steering,
}

impl Default for PlaceScript {
    fn default() -> Self {
        Self {
            // The press: a mug is hooked by its handle from the side, and a
            // grasp placed where the solver put it (the palm 2 mm off the
            // registered handle) held only at the edge of its basin: shifts
            // of 2-3 mm or 2° dropped it. 8 mm past it, the palm against the
            // handle, is the middle of a plateau (`sim place --press-mm`, 10
            // training mugs, seeds 100-109, from the camera: 0 / 4 / 6 / 8 /
            // 10 mm → 64 / 84 / 94 / 96 / 95 of 100). Position drill gains
            // nothing and Drive nail loses (its palm presses the handle into
            // the table), so they keep 0.
            lift: LiftScript { hold_s: 0.3, press_m: 0.008, ..LiftScript::default() },
            move_s: 2.0,
            lower_s: 1.2,
            align_s: 0.8,
            release_s: 0.6,
            retreat_s: 0.8,
            place_clearance_m: 0.004,
            retreat_up_m: 0.06,
            steering: Steering::default(),
        }
    }
}

/// The scripted Place-mug controller. Stateful (it carries a
/// [`CarryController`]); one per episode, or [`Self::reset`].
#[derive(Clone, Debug)]
pub struct PlaceController {
    carry: CarryController,
    goal: Isometry3<f64>,
    /// The pre-grasp's offset from the grasp, palm frame (the back-off).
    backoff: Isometry3<f64>,
    q_open: Vec<f64>,
    script: PlaceScript,
    /// End times of move, lower, align, release, retreat.
    ends: [f64; 5],
}

impl PlaceController {
    pub fn new(hand: &HandModel, plan: &GraspPlan, goal: Isometry3<f64>, script: &PlaceScript) -> Self {
        let carry = CarryController::new(hand, plan, &script.lift, &script.steering);
        let mut ends = [script.move_s, script.lower_s, script.align_s, script.release_s, script.retreat_s];
        ends[0] += carry.lift_duration();
        for k in 1..ends.len() {
            ends[k] += ends[k - 1];
        }
        Self {
            carry,
            goal,
            backoff: plan.grasp.wrist_pose_world.inverse() * plan.pregrasp.wrist_pose_world,
            q_open: plan.pregrasp.actuated.clone(),
            script: script.clone(),
            ends,
        }
    }

    pub fn reset(&mut self) {
        self.carry.reset();
    }

    /// End of the lift script, seconds.
    pub fn lift_duration(&self) -> f64 {
        self.carry.lift_duration()
    }

    /// End of the whole script, seconds (the episode may run on).
    pub fn duration(&self) -> f64 {
        self.ends[4]
    }

    /// When the fingers start to open, seconds.
    pub fn release_at(&self) -> f64 {
        self.ends[2]
    }

    /// The desired tool pose at time `t` of the move, lower and align phases.
    fn desired_tool(&self, t: f64, from: &Isometry3<f64>) -> Isometry3<f64> {
        let start = self.carry.lift_duration();
        let [moved, lowered, ..] = self.ends;
        let mut above = self.goal;
        above.translation.vector.z = from.translation.vector.z;
        let mut placed = self.goal;
        placed.translation.vector.z += self.script.place_clearance_m;
        if t <= moved {
            lerp_pose(from, &above, ease((t - start) / self.script.move_s))
        } else if t <= lowered {
            lerp_pose(&above, &placed, ease((t - moved) / self.script.lower_s))
        } else {
            placed
        }
    }

    /// Wrist and joint targets (into `q`) for the control interval ending at
    /// `t`, given the tool's current pose.
    pub fn targets(&mut self, t: f64, tool_pose: &Isometry3<f64>, q: &mut [f64]) -> Isometry3<f64> {
        if t <= self.carry.lift_duration() {
            return self.carry.lift_targets(t, q);
        }
        let from = self.carry.carry_start(tool_pose);
        let [_, _, aligned, released, retreated] = self.ends;
        if t <= aligned {
            let desired = self.desired_tool(t, &from);
            return self.carry.steer(&desired, tool_pose, q);
        }
        let placed = self.carry.last_wrist();
        let q_squeeze = self.carry.q_squeeze();
        if t <= released {
            let s = ease((t - aligned) / self.script.release_s);
            for ((q, a), b) in q.iter_mut().zip(q_squeeze).zip(&self.q_open) {
                *q = a + s * (b - a);
            }
            return placed;
        }
        q.copy_from_slice(&self.q_open);
        let away = Translation3::new(0.0, 0.0, self.script.retreat_up_m) * placed * self.backoff;
        lerp_pose(&placed, &away, ease((t - released) / (retreated - released)))
    }
}

/// How an episode of a goal-pose task (Place mug, Position drill) went.
#[derive(Clone, Debug, Serialize)]
pub struct PoseOutcome {
    pub seed: u64,
    /// The paper's rule at the end of the episode.
    pub success: bool,
    /// First time the rule held, seconds (the tool may pass through the goal).
    pub first_reached_s: Option<f64>,
    pub final_distance_m: f64,
    pub final_angle_rad: f64,
    /// The tool's lowest point above the table when the lift ended, metres (the grasp held).
    pub clearance_after_lift_m: f64,
    /// Sum of the per-step rewards, and its terms.
    pub episode_return: f64,
    pub return_terms: PoseReward,
    pub control_steps: usize,
    pub physics_us_per_step: f64,
    pub warnings: Vec<String>,
    /// Where the grasp came from, the start mode, the daemon's round trip.
    pub grasp: GraspInfo,
}

/// A scripted controller of a goal-pose task.
pub trait PoseController {
    /// End of its lift script, seconds.
    fn lift_duration(&self) -> f64;
    /// Wrist and joint targets (into `q`) for the control interval ending at `t`.
    fn targets(&mut self, t: f64, tool_pose: &Isometry3<f64>, q: &mut [f64]) -> Isometry3<f64>;
}

impl PoseController for PlaceController {
    fn lift_duration(&self) -> f64 {
        PlaceController::lift_duration(self)
    }
    fn targets(&mut self, t: f64, tool_pose: &Isometry3<f64>, q: &mut [f64]) -> Isometry3<f64> {
        PlaceController::targets(self, t, tool_pose, q)
    }
}

/// One episode of a goal-pose task: `plan` made with the tool frame at the
/// origin and carried here to the episode's start, `height_points` on the
/// tool's mesh (tool frame), the controller made from the carried plan by
/// `controller`. Success is judged at the end of the episode.
#[allow(clippy::too_many_arguments)]
pub fn run_pose_episode<M: ModelType, C: PoseController>(
    scene: &Scene,
    data: &mut MjData<M>,
    hand_model: &HandModel,
    plan: &GraspPlan,
    height_points: &[Point3<f64>],
    episode: &PoseEpisode,
    control_hz: f64,
    controller: impl FnOnce(&GraspPlan) -> C,
) -> Result<PoseOutcome, SimError> {
    let plan = plan.carried(hand_model, &episode.start);
    let mut stepper = EpisodeStepper::start(scene, data, hand_model, &plan, &episode.start, control_hz)?;
    let table_z = scene.table.map_or(0.0, |(_, z)| z);
    let mut controller = controller(&plan);
    let n_control = (task::EPISODE_S * control_hz).round() as usize;
    let mut q = plan.pregrasp.actuated.clone();
    let mut sum = PoseReward::default();
    let mut first_reached = None;
    let mut clearance_after_lift = f64::NAN;
    let lifted_at = controller.lift_duration();
    for k in 0..n_control {
        let t = (k + 1) as f64 / control_hz;
        let pose = stepper.tool.pose(data);
        let wrist = controller.targets(t, &pose, &mut q);
        stepper.step(data, &wrist, &q);
        let pose = stepper.tool.pose(data);
        let trace = stepper.trace;
        let grasp = stepper.grasp_state(data, &pose, height_points, table_z);
        let clear = grasp.clearance_m;
        let r = pose_reward(&PoseState { tool_pose: pose, goal: episode.goal, grasp });
        sum.accumulate(&r);
        if r.success > 0.0 && first_reached.is_none() {
            first_reached = Some(t);
        }
        if clearance_after_lift.is_nan() && t >= lifted_at - 0.5 / control_hz {
            clearance_after_lift = clear;
        }
        if trace && k % 3 == 2 {
            eprintln!(
                "t {t:5.2} tool ({:7.4} {:7.4} {:7.4}) d {:6.1} mm θ {:5.3} rad clear {:6.1} mm Δk {:5.1} mm r {:7.3}",
                pose.translation.x,
                pose.translation.y,
                pose.translation.z,
                1e3 * r.distance_m,
                r.angle_rad,
                1e3 * clear,
                1e3 * r.keypoint_distance_m,
                r.total
            );
        }
    }
    let end = stepper.tool.pose(data);
    let (d, theta) = task::pose_error(&end, &episode.goal);
    Ok(PoseOutcome {
        seed: episode.seed,
        success: task::reached(&end, &episode.goal),
        first_reached_s: first_reached,
        final_distance_m: d,
        final_angle_rad: theta,
        clearance_after_lift_m: clearance_after_lift,
        episode_return: sum.total,
        return_terms: PoseReward { distance_m: d, angle_rad: theta, ..sum },
        control_steps: n_control,
        physics_us_per_step: stepper.physics_us_per_step(),
        warnings: warnings(data),
        grasp: GraspInfo::default(),
    })
}

/// One Place-mug episode: `plan` made with the tool frame at the origin,
/// `height_points` on the tool's mesh (tool frame).
#[allow(clippy::too_many_arguments)]
pub fn run_place<M: ModelType>(
    scene: &Scene,
    data: &mut MjData<M>,
    hand_model: &HandModel,
    plan: &GraspPlan,
    height_points: &[Point3<f64>],
    episode: &PoseEpisode,
    script: &PlaceScript,
    control_hz: f64,
) -> Result<PoseOutcome, SimError> {
    run_pose_episode(scene, data, hand_model, plan, height_points, episode, control_hz, |plan| {
        PlaceController::new(hand_model, plan, episode.goal, script)
    })
}

/// Everything that sets up Place-mug episodes besides the tool.
#[derive(Clone, Debug, Default)]
pub struct PlaceSetup {
    pub base: LiftSetup,
    pub script: PlaceScript,
    pub ranges: PlaceRanges,
}

/// Builds one instance's scene once and runs `episodes` episodes (seeds
/// `first_seed`, `first_seed + 1`, ...), each with the planner's grasp for
/// the mug where it starts.
pub fn place_instance(
    asset: &HandAsset,
    planner: &mut GraspPlanner,
    instance: &Instance,
    setup: &PlaceSetup,
    first_seed: u64,
    episodes: usize,
) -> Result<Vec<PoseOutcome>, SimError> {
    setup.ranges.validate()?;
    pose_task_instance(
        asset,
        planner,
        instance,
        &setup.base,
        "place",
        (first_seed, episodes),
        |seed, table_z| setup.ranges.sample(seed, table_z),
        |plan, episode| PlaceController::new(asset.model(), plan, episode.goal, &setup.script),
    )
}

/// One tool's goal-pose episodes (Place mug, Position drill): its scene
/// built once, then `episodes` episodes (seeds `first_seed`,
/// `first_seed + 1`, ...) drawn by `sample`, each with the planner's grasp
/// for the tool where it starts and the task's controller.
#[allow(clippy::too_many_arguments)]
pub(crate) fn pose_task_instance<C: PoseController>(
    asset: &HandAsset,
    planner: &mut GraspPlanner,
    instance: &Instance,
    base: &LiftSetup,
    task: &str,
    (first_seed, episodes): (u64, usize),
    sample: impl Fn(u64, f64) -> PoseEpisode,
    controller: impl Fn(&GraspPlan, &PoseEpisode) -> C,
) -> Result<Vec<PoseOutcome>, SimError> {
    let mut rig = TaskRig::build(asset, planner, instance, base, task, Vec::new(), Vec::new())?;
    let runs = rig.run_seeded(
        planner,
        first_seed,
        episodes,
        sample,
        |episode| episode.start,
        |rig, plan, episode| {
            run_pose_episode(
                &rig.scene,
                &mut rig.data,
                asset.model(),
                plan,
                &rig.height_points,
                episode,
                base.physics.control_hz,
                |plan| controller(plan, episode),
            )
        },
    )?;
    Ok(runs.into_iter().map(|(o, grasp)| PoseOutcome { grasp, ..o }).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::carry::{HEIGHT_POINTS, HEIGHT_POINTS_SEED};
    use crate::scene::{SceneSpec, Table};
    use crate::tool::{ToolBody, ToolMaterial};
    use graspd::geometry::sample::sample_points;
    use graspd::tools::{self, Category};

    fn canonical_setup() -> (HandAsset, GraspPlanner, Instance) {
        let asset = HandAsset::default_sih().unwrap();
        let planner = GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        (asset, planner, mug)
    }

    /// The demonstrated grasp on the canonical mug carries it from random
    /// starts to random goals: every episode ends with the mug resting
    /// within the paper's thresholds, having been lifted on the way.
    #[test]
    fn the_scripted_controller_places_the_canonical_mug() {
        let (asset, mut planner, mug) = canonical_setup();
        let outs = place_instance(&asset, &mut planner, &mug, &PlaceSetup::default(), 100, 3).unwrap();
        for o in &outs {
            assert!(o.success, "{o:?}");
            assert!(o.clearance_after_lift_m > 0.05, "{o:?}");
            assert!(o.first_reached_s.is_some_and(|t| t > 3.0), "{o:?}");
            // Reaching the goal is worth 100 per step: the return says so.
            assert!(o.return_terms.success >= 100.0 * 30.0, "{o:?}");
        }
        // Different seeds, different goals: the episodes are not copies.
        assert_ne!(outs[0].final_distance_m, outs[1].final_distance_m);
    }

    /// A training mug whose transferred grasp held only at the edge of its
    /// basin (the palm stopped 2 mm off the handle, and the mug dropped out
    /// of the hand on the way to the goal in 10 of 10 episodes): with the
    /// approach pressing the palm on, it is placed.
    #[test]
    fn the_press_places_a_mug_that_the_solved_wrist_pose_dropped() {
        let (asset, mut planner, _) = canonical_setup();
        let mug = tools::instance(Category::Mug, "mug_train_00").unwrap();
        let setup = PlaceSetup::default();
        assert!(setup.script.lift.press_m > 0.0);
        let outs = place_instance(&asset, &mut planner, &mug, &setup, 100, 2).unwrap();
        for o in &outs {
            assert!(o.success, "{o:?}");
        }
    }

    /// The same episode with a hand that never closes: the mug stays where it
    /// started, 10-20 cm from the goal; no success and no success reward.
    #[test]
    fn an_open_hand_places_nothing() {
        let (asset, mut planner, mug) = canonical_setup();
        let hand = asset.model();
        let mut plan = planner.plan(&mug).unwrap();
        plan.grasp.actuated = hand.open_hand().to_vec();
        plan.pregrasp.actuated = hand.open_hand().to_vec();
        let setup = PlaceSetup::default();
        let tool =
            ToolBody::from_mesh("mug", &mug.mesh, ToolMaterial::for_category(Category::Mug), &setup.base.decomposition)
                .unwrap();
        let spec = SceneSpec {
            name: "open".into(),
            physics: setup.base.physics.clone(),
            table: Some(Table::default()),
            tools: vec![(&tool, Isometry3::identity())],
            hand: Some((&asset, setup.base.hand.clone(), plan.pregrasp.wrist_pose_world)),
            ..Default::default()
        };
        let scene = spec.build().unwrap();
        let mut data = MjData::new(scene.model.clone());
        let points = sample_points(&mug.mesh, HEIGHT_POINTS, HEIGHT_POINTS_SEED).unwrap();
        let mut script = setup.script.clone();
        script.lift.squeeze_rad = 0.0;
        let episode = setup.ranges.sample(100, 0.0);
        let o = run_place(&scene, &mut data, hand, &plan, &points, &episode, &script, 30.0).unwrap();
        assert!(!o.success, "{o:?}");
        assert!(o.final_distance_m > 0.08, "{o:?}");
        assert!(o.clearance_after_lift_m < 0.01, "{o:?}");
        assert_eq!(o.return_terms.success, 0.0);
    }
}
