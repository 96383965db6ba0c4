//! The paper's Table I: how close the solved grasps come to the generalised
//! demonstrations on the training instances, beside the WP and CG baselines.
//!
//! For each training instance of a category, the demonstration's keypoints
//! (canonical tool frame) are moved through the shape space with that
//! instance's latent (`ShapeSpace::train_latents`; the instances are in the
//! canonical frame, so the pose is the identity): these are the targets. The
//! canonical mesh deformed the same way is the registered shape the fingers
//! must not pierce, and the table is the plane under it. The grasp is solved
//! from the demonstration (warm start); CG keeps the demonstrated grasp, WP
//! moves its wrist by the best rigid fit of its keypoints to the targets.
//! Penetration is also measured against the instance's true mesh.

use serde::Serialize;

use crate::grasp::transfer::{solve_transferred, TransferModel, TransferredTool};
use crate::grasp::{Demonstration, GraspError, GraspSolver, PreGraspOptions, Scene, SolveOptions, ToolCollider};
use crate::hand::HandModel;
use crate::shape::ShapeSpace;
use crate::tools::Instance;
use nalgebra::Isometry3;

#[derive(Clone, Debug)]
pub struct GraspEvalOptions {
    pub solve: SolveOptions,
    /// Solves of each instance timed (the grasp is the same each time).
    pub repeats: usize,
    /// Put a table under the tool (the plane through its lowest point).
    pub table: bool,
}

impl Default for GraspEvalOptions {
    fn default() -> Self {
        Self { solve: SolveOptions::default(), repeats: 3, table: true }
    }
}

#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct MeanStd {
    pub mean: f64,
    /// Population standard deviation.
    pub std: f64,
}

#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct MeanMax {
    pub mean: f64,
    pub max: f64,
}

#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Methods<T> {
    pub ours: T,
    pub wp: T,
    pub cg: T,
}

#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct OursOnly<T> {
    pub ours: T,
}

#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Timing {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

/// One training instance.
#[derive(Clone, Debug, Serialize)]
pub struct InstanceRow {
    pub instance: String,
    pub task_space_distance_cm: Methods<f64>,
    pub residual_max_mm: f64,
    /// Against the registered (deformed canonical) shape and the table.
    pub penetration_mm: Methods<f64>,
    /// Against the instance's own mesh and the table.
    pub penetration_true_mesh_mm: f64,
    pub pregrasp_collision_free: bool,
    pub solve_ms: f64,
    pub iterations: usize,
    pub starts: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct GraspEvalReport {
    pub category: String,
    pub instances: usize,
    /// Paper Table I: mean keypoint-to-target distance, cm.
    pub task_space_distance_cm: Methods<MeanStd>,
    /// Against the registered shape and the table; the baselines keep the
    /// demonstrated joints and know nothing of the tool, so they pierce.
    pub penetration_mm: Methods<MeanMax>,
    pub penetration_true_mesh_mm: OursOnly<MeanMax>,
    /// Single-thread grasp solve (all starts), ms.
    pub solve_ms: Timing,
    /// ours / CG of the mean distances.
    pub ours_over_cg: f64,
    pub pregrasps_collision_free: usize,
    pub per_instance: Vec<InstanceRow>,
}

#[derive(Debug, thiserror::Error)]
pub enum GraspEvalError {
    #[error("grasp: {0}")]
    Grasp(#[from] GraspError),
    #[error("the shape space has no latent for training instance {0}")]
    NoLatent(String),
    #[error("no training instances")]
    Empty,
}

pub fn mean_std(v: &[f64]) -> MeanStd {
    if v.is_empty() {
        return MeanStd { mean: f64::NAN, std: f64::NAN };
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    MeanStd { mean, std: var.sqrt() }
}

/// Nearest-rank percentile of `v` (p in [0, 1]); NaN when empty.
pub fn percentile(v: &[f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let k = ((p * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    s[k]
}

/// Table I over `training` (instances of the space's category, in its
/// canonical frame). `progress` is called after each instance.
pub fn evaluate_grasps(
    hand: &HandModel,
    space: &ShapeSpace,
    demo: &Demonstration,
    canonical: &Instance,
    training: &[&Instance],
    opts: &GraspEvalOptions,
    mut progress: impl FnMut(),
) -> Result<GraspEvalReport, GraspEvalError> {
    if training.is_empty() {
        return Err(GraspEvalError::Empty);
    }
    let keypoints = demo.keypoints(hand)?;
    let mut solver = GraspSolver::new(hand, opts.solve.clone());
    let model = TransferModel::new(space, &keypoints, &canonical.mesh);
    let mut rows = Vec::new();
    let mut times = Vec::new();
    for inst in training {
        let k = space
            .instances
            .iter()
            .position(|n| n == &inst.name)
            .ok_or_else(|| GraspEvalError::NoLatent(inst.name.clone()))?;
        let tool = TransferredTool::from_latent(&model, &space.train_latents[k])?;
        let table = opts.table.then(|| tool.lowest_z());
        let mut out = solve_transferred(&mut solver, demo, &tool, table, &PreGraspOptions::default())?;
        times.push(out.report.elapsed_ms);
        for _ in 1..opts.repeats.max(1) {
            let again = solve_transferred(&mut solver, demo, &tool, table, &PreGraspOptions::default())?;
            times.push(again.report.elapsed_ms);
            out.report.elapsed_ms = out.report.elapsed_ms.min(again.report.elapsed_ms);
        }
        let scene = Scene { tool: Some(&tool.collider), table_height_world: table };
        let wp_pen = 1e3 * solver.clearance(&out.wp.grasp, &scene).penetration_m;
        let cg_pen = 1e3 * solver.clearance(&out.cg.grasp, &scene).penetration_m;
        let truth = ToolCollider::new(&inst.mesh, Isometry3::identity())?;
        let true_scene = Scene { tool: Some(&truth), table_height_world: opts.table.then_some(0.0) };
        let penetration_true_mesh_mm = 1e3 * solver.clearance(&out.grasp, &true_scene).penetration_m;
        rows.push(InstanceRow {
            instance: inst.name.clone(),
            task_space_distance_cm: Methods {
                ours: out.task_space_distance_cm,
                wp: out.wp.task_space_distance_cm,
                cg: out.cg.task_space_distance_cm,
            },
            residual_max_mm: out.report.residual_mm.max,
            penetration_mm: Methods { ours: out.report.penetration_mm, wp: wp_pen, cg: cg_pen },
            penetration_true_mesh_mm,
            pregrasp_collision_free: out.pregrasp.collision_free,
            solve_ms: out.report.elapsed_ms,
            iterations: out.report.iterations,
            starts: out.report.starts,
        });
        progress();
    }
    let col = |f: &dyn Fn(&InstanceRow) -> f64| rows.iter().map(f).collect::<Vec<f64>>();
    let ours = col(&|r| r.task_space_distance_cm.ours);
    let wp = col(&|r| r.task_space_distance_cm.wp);
    let cg = col(&|r| r.task_space_distance_cm.cg);
    let pen = col(&|r| r.penetration_mm.ours);
    let pen_wp = col(&|r| r.penetration_mm.wp);
    let pen_cg = col(&|r| r.penetration_mm.cg);
    let pen_true = col(&|r| r.penetration_true_mesh_mm);
    let mean_max = |v: &[f64]| MeanMax { mean: mean_std(v).mean, max: v.iter().cloned().fold(0.0, f64::max) };
    let task = Methods { ours: mean_std(&ours), wp: mean_std(&wp), cg: mean_std(&cg) };
    Ok(GraspEvalReport {
        category: space.category.clone(),
        instances: rows.len(),
        ours_over_cg: task.ours.mean / task.cg.mean,
        task_space_distance_cm: task,
        penetration_mm: Methods { ours: mean_max(&pen), wp: mean_max(&pen_wp), cg: mean_max(&pen_cg) },
        penetration_true_mesh_mm: OursOnly { ours: mean_max(&pen_true) },
        solve_ms: Timing {
            p50: percentile(&times, 0.5),
            p99: percentile(&times, 0.99),
            max: times.iter().cloned().fold(0.0, f64::max),
        },
        pregrasps_collision_free: rows.iter().filter(|r| r.pregrasp_collision_free).count(),
        per_instance: rows,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statistics() {
        let m = mean_std(&[1.0, 2.0, 3.0, 4.0]);
        assert!((m.mean - 2.5).abs() < 1e-12 && (m.std - 1.25f64.sqrt()).abs() < 1e-12);
        assert!(mean_std(&[]).mean.is_nan());
        let v: Vec<f64> = (1..=100).map(f64::from).rev().collect();
        assert_eq!(percentile(&v, 0.5), 50.0);
        assert_eq!(percentile(&v, 0.99), 99.0);
        assert_eq!(percentile(&v, 1.0), 100.0);
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert!(percentile(&[], 0.5).is_nan());
    }
}
