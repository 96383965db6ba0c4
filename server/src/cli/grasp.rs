//! `graspd retarget` (keypoints → wrist pose and joints), `graspd grasp`
//! (cloud → registration → grasp → pre-grasp) and `graspd eval grasp`
//! (the paper's Table I on the training instances).

use super::hand::HandArgs;
use super::register::ViewArgs;
use super::space::spaces_dir;
use super::{print_json, progress_bar, CliResult};
use clap::Args;
use graspd::eval::grasp::{evaluate_grasps, percentile, GraspEvalOptions};
use graspd::grasp::transfer::{is_z_up, solve_transferred, TransferModel, TransferredTool};
use graspd::grasp::{Demonstration, Grasp, GraspSolver, GraspTargets, PoseFile, PreGraspOptions, Scene, SolveOptions};
use graspd::hand::HandModel;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::{self, Category, Split};
use nalgebra::Point3;
use std::path::PathBuf;
use std::time::Instant;

type AnyError = Box<dyn std::error::Error>;

#[derive(Args)]
pub struct RetargetArgs {
    /// Target keypoints, world frame, metres: a JSON array of 12 [x, y, z] (hand keypoint order)
    /// or of {"name", "position"}; or {"keypoints": [...], "weights": [...]}; or {"sets": [...]} of those.
    #[arg(long)]
    keypoints: PathBuf,
    /// Starts in all (the first from the open hand fitted rigidly to the targets).
    #[arg(long, default_value_t = SolveOptions::default().starts)]
    starts: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A table plane z = this (world) the hand must stay above.
    #[arg(long, allow_hyphen_values = true)]
    table_z: Option<f64>,
    #[command(flatten)]
    hand: HandArgs,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct GraspArgs {
    #[arg(long)]
    category: String,
    /// Segmented partial cloud of one tool (.ply, .pcd, .xyz, .npy), metres.
    #[arg(long)]
    cloud: PathBuf,
    #[command(flatten)]
    view: ViewArgs,
    /// Table top height in the cloud's frame (z up); the registration then also
    /// holds the tool's lowest point on it. Default: the table a segmentation
    /// leaking onto it shows, else the lowest point of the cloud (stray
    /// points set aside) or of the registered shape, whichever is lower
    /// (grasp only).
    #[arg(long, allow_hyphen_values = true)]
    table_z: Option<f64>,
    /// No table plane.
    #[arg(long)]
    no_table: bool,
    /// Demonstration file (default: the bundled one of the category, assets/demos/).
    #[arg(long)]
    demo: Option<PathBuf>,
    /// Pre-grasp: distance backed off along the palm normal, metres.
    #[arg(long, default_value_t = PreGraspOptions::default().backoff_m)]
    backoff_m: f64,
    /// Pre-grasp joints: share of the way from the open hand to the grasp.
    #[arg(long, default_value_t = PreGraspOptions::default().joint_fraction)]
    joint_fraction: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    hand: HandArgs,
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
pub struct EvalGraspArgs {
    #[arg(long)]
    category: String,
    /// Demonstration file (default: the bundled one of the category).
    #[arg(long)]
    demo: Option<PathBuf>,
    /// Timed solves per instance.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Solver starts per grasp.
    #[arg(long, default_value_t = SolveOptions::default().starts)]
    starts: usize,
    /// No table under the tools.
    #[arg(long)]
    no_table: bool,
    /// Solve without the penetration term (keypoints only, as eq. 6 alone).
    #[arg(long)]
    no_penetration: bool,
    /// Clearance the penetration term keeps from the registered shape, mm
    /// (default: the demonstration's `penetration_margin_m`, else 0).
    #[arg(long)]
    margin_mm: Option<f64>,
    /// A shape-space artefact to evaluate (default: the category's built-in
    /// space, cached in assets/spaces and built there when missing).
    #[arg(long)]
    space: Option<PathBuf>,
    #[command(flatten)]
    hand: HandArgs,
    #[arg(long)]
    json: bool,
}

/// One set of targets read from a keypoints file.
struct TargetSet {
    targets: GraspTargets,
}

fn point_of(v: &serde_json::Value, what: &str) -> Result<(Option<String>, Point3<f64>), String> {
    let xyz = |a: &serde_json::Value| -> Result<Point3<f64>, String> {
        let arr = a.as_array().filter(|a| a.len() == 3).ok_or_else(|| format!("{what}: expected [x, y, z]"))?;
        let mut p = [0.0; 3];
        for (k, c) in arr.iter().enumerate() {
            p[k] = c.as_f64().ok_or_else(|| format!("{what}: coordinate {k} is not a number ({c})"))?;
        }
        Ok(Point3::from(p))
    };
    match v {
        serde_json::Value::Array(_) => Ok((None, xyz(v)?)),
        serde_json::Value::Object(o) => {
            let name = o.get("name").and_then(|n| n.as_str()).map(str::to_owned);
            let pos = o.get("position").ok_or_else(|| format!("{what}: an object needs \"position\""))?;
            Ok((name, xyz(pos)?))
        }
        _ => Err(format!("{what}: expected [x, y, z] or {{\"name\", \"position\"}}")),
    }
}

fn target_set(hand: &HandModel, v: &serde_json::Value, what: &str) -> Result<TargetSet, String> {
    let (list, weights) = match v {
        serde_json::Value::Array(a) => (a.clone(), None),
        serde_json::Value::Object(o) => {
            let kps = o
                .get("keypoints")
                .and_then(|k| k.as_array())
                .ok_or_else(|| format!("{what}: expected a \"keypoints\" array"))?;
            let weights = match o.get("weights") {
                None | Some(serde_json::Value::Null) => None,
                Some(w) => Some(
                    w.as_array()
                        .ok_or_else(|| format!("{what}: \"weights\" must be an array"))?
                        .iter()
                        .enumerate()
                        .map(|(i, x)| x.as_f64().ok_or_else(|| format!("{what}: weight {i} is not a number")))
                        .collect::<Result<Vec<f64>, String>>()?,
                ),
            };
            (kps.clone(), weights)
        }
        _ => return Err(format!("{what}: expected an array of keypoints or an object")),
    };
    let points: Vec<(Option<String>, Point3<f64>)> = list
        .iter()
        .enumerate()
        .map(|(i, p)| point_of(p, &format!("{what}, keypoint {i}")))
        .collect::<Result<_, _>>()?;
    let expected = hand.keypoints().len();
    if points.len() != expected {
        return Err(format!(
            "{what}: expected {expected} keypoints (one per hand keypoint: {}), got {}",
            hand.keypoints().iter().map(|k| k.name.as_str()).collect::<Vec<_>>().join(", "),
            points.len()
        ));
    }
    let named = points.iter().filter(|(n, _)| n.is_some()).count();
    let ordered: Vec<Point3<f64>> = if named == 0 {
        points.iter().map(|(_, p)| *p).collect()
    } else if named == points.len() {
        hand.keypoints()
            .iter()
            .map(|k| {
                points
                    .iter()
                    .find(|(n, _)| n.as_deref() == Some(k.name.as_str()))
                    .map(|(_, p)| *p)
                    .ok_or_else(|| format!("{what}: no keypoint named `{}`", k.name))
            })
            .collect::<Result<_, _>>()?
    } else {
        return Err(format!("{what}: name all keypoints or none"));
    };
    let targets = match weights {
        Some(w) => GraspTargets { keypoints_world: ordered, weights: w },
        None => GraspTargets::uniform(ordered),
    };
    targets.validate(hand).map_err(|e| format!("{what}: {e}"))?;
    Ok(TargetSet { targets })
}

/// Reads a keypoints file: one set, or a batch ("sets"). Returns the sets and whether it was a batch.
fn read_targets(hand: &HandModel, path: &PathBuf) -> Result<(Vec<TargetSet>, bool), AnyError> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("{} is not JSON: {e}", path.display()))?;
    let what = path.display().to_string();
    if let Some(sets) = v.get("sets") {
        let sets = sets.as_array().ok_or_else(|| format!("{what}: \"sets\" must be an array"))?;
        let out = sets
            .iter()
            .enumerate()
            .map(|(i, s)| target_set(hand, s, &format!("{what}, set {i}")))
            .collect::<Result<Vec<_>, _>>()?;
        return Ok((out, true));
    }
    Ok((vec![target_set(hand, &v, &what)?], false))
}

pub fn pose_json(pose: &nalgebra::Isometry3<f64>) -> serde_json::Value {
    serde_json::json!(PoseFile::from_isometry(pose))
}

/// {"wrist_pose", "joints" (every moving joint), "actuated"} of a grasp.
pub fn grasp_json(hand: &HandModel, g: &Grasp) -> serde_json::Value {
    let joints: serde_json::Map<String, serde_json::Value> = hand
        .moving_joints()
        .iter()
        .zip(&g.joints)
        .map(|(&j, q)| (hand.joints()[j].name.clone(), serde_json::json!(q)))
        .collect();
    let actuated: serde_json::Map<String, serde_json::Value> =
        hand.actuated_names().zip(&g.actuated).map(|(n, q)| (n.to_owned(), serde_json::json!(q))).collect();
    serde_json::json!({"wrist_pose": pose_json(&g.wrist_pose_world), "joints": joints, "actuated": actuated})
}

pub fn run_retarget(a: RetargetArgs) -> CliResult {
    let hand = a.hand.load()?;
    let (sets, batch) = read_targets(&hand, &a.keypoints)?;
    let opts = SolveOptions { starts: a.starts.max(1), seed: a.seed, ..SolveOptions::default() };
    let mut solver = GraspSolver::new(&hand, opts);
    let scene = Scene { tool: None, table_height_world: a.table_z };
    let mut results = Vec::new();
    let (mut times, mut means, mut maxes) = (Vec::new(), Vec::new(), Vec::new());
    for set in &sets {
        let t0 = Instant::now();
        let cold = solver.cold_start(&set.targets)?;
        let (grasp, report) = solver.solve(&set.targets, &cold, &scene)?;
        let elapsed_ms = 1e3 * t0.elapsed().as_secs_f64();
        times.push(elapsed_ms);
        means.push(report.residual_mm.mean);
        maxes.push(report.residual_mm.max);
        let mut v = grasp_json(&hand, &grasp);
        v["residual_mm"] = serde_json::json!(report.residual_mm);
        v["penetration_mm"] = serde_json::json!(report.penetration_mm);
        v["elapsed_ms"] = serde_json::json!(elapsed_ms);
        v["iterations"] = serde_json::json!(report.iterations);
        v["starts"] = serde_json::json!(report.starts);
        v["abandoned_starts"] = serde_json::json!(report.abandoned_starts);
        v["converged"] = serde_json::json!(report.converged);
        results.push(v);
    }
    let summary = serde_json::json!({
        "sets": sets.len(),
        "elapsed_ms": {"p50": percentile(&times, 0.5), "p99": percentile(&times, 0.99), "mean": times.iter().sum::<f64>() / times.len() as f64},
        "residual_mm": {"mean": means.iter().sum::<f64>() / means.len() as f64, "max": maxes.iter().cloned().fold(0.0, f64::max),
                        "p50_of_means": percentile(&means, 0.5)},
    });
    if a.json {
        if batch {
            print_json(&serde_json::json!({"results": results, "summary": summary}))?;
        } else {
            print_json(&results[0])?;
        }
    } else {
        for (i, r) in results.iter().enumerate() {
            println!(
                "set {i}: residual mean {:.3} mm max {:.3} mm, {:.3} ms",
                r["residual_mm"]["mean"].as_f64().unwrap_or(f64::NAN),
                r["residual_mm"]["max"].as_f64().unwrap_or(f64::NAN),
                r["elapsed_ms"].as_f64().unwrap_or(f64::NAN)
            );
        }
        if batch {
            println!("summary: {summary}");
        }
    }
    Ok(())
}

fn load_demo(path: Option<&PathBuf>, category: Category) -> Result<Demonstration, AnyError> {
    Ok(match path {
        Some(p) => Demonstration::load(p)?,
        None => Demonstration::builtin(category)
            .map_err(|e| format!("{e} (author one with `graspd demo author --category {}`)", category.name()))?,
    })
}

fn canonical_instance(category: Category) -> Result<tools::Instance, AnyError> {
    Ok(tools::family(category)?
        .into_iter()
        .find(|i| i.split == Split::Canonical)
        .ok_or("the family has no canonical instance")?)
}

pub fn run_grasp(a: GraspArgs) -> CliResult {
    let t_total = Instant::now();
    let category: Category = a.category.parse()?;
    let hand = a.hand.load()?;
    let demo = load_demo(a.demo.as_ref(), category)?;
    let demo_keypoints = demo.checked_keypoints(&hand)?;
    let canonical = canonical_instance(category)?;
    let cloud = graspd::io::read_cloud(&a.cloud)?;
    let super::register::SetUp { up, viewpoint, second_viewpoint } = a.view.parse()?;

    let t_load = Instant::now();
    let space = builtin::load_or_build(category, &spaces_dir(), |_, _| {})?;
    let registrar = Registrar::new(space);
    let model = TransferModel::new(&registrar.space, &demo_keypoints, &canonical.mesh);
    let load_ms = 1e3 * t_load.elapsed().as_secs_f64();

    // A given table is also the registration's support (in a z-up frame).
    let support_height = if a.no_table { None } else { super::register::support_height(up, a.table_z).ok().flatten() };
    let reg = registrar.register(
        &cloud,
        &RegisterOptions { up, viewpoint, second_viewpoint, support_height, seed: a.seed, ..Default::default() },
    )?;
    let tool = TransferredTool::from_registration(&registrar, &reg, &model)?;

    let mut warnings = Vec::new();
    if !reg.fit.confident {
        warnings.push("the registration is not confident: the cloud may not be a tool of this category".to_owned());
    }
    let table_z = if a.no_table {
        None
    } else if let Some(z) = a.table_z {
        Some(z)
    } else if is_z_up(up) {
        Some(tool.table_z_under(&reg))
    } else {
        warnings.push("no table: the cloud's frame is not z-up (give --table-z for one)".to_owned());
        None
    };
    if let Some(z) = table_z {
        if !z.is_finite() {
            return Err(format!("--table-z {z} is not finite").into());
        }
    }
    let pre = PreGraspOptions { backoff_m: a.backoff_m, joint_fraction: a.joint_fraction, ..Default::default() };
    let mut solver = GraspSolver::new(&hand, SolveOptions { seed: a.seed, ..SolveOptions::default() });
    let out = solve_transferred(&mut solver, &demo, &tool, table_z, &pre)?;
    if !out.pregrasp.collision_free {
        warnings.push(format!(
            "no clear pre-grasp near the grasp; the preferred one touches the scene ({:.1} mm)",
            -1e3 * out.pregrasp.min_clearance_m
        ));
    }
    let total_ms = 1e3 * t_total.elapsed().as_secs_f64();

    let q = reg.rotation_cloud_from_canonical.coords;
    let mut pregrasp = grasp_json(&hand, &out.pregrasp.grasp);
    pregrasp["collision_free"] = serde_json::json!(out.pregrasp.collision_free);
    pregrasp["min_clearance_mm"] = serde_json::json!(1e3 * out.pregrasp.min_clearance_m);
    pregrasp["backoff_m"] = serde_json::json!(out.pregrasp.backoff_m);
    pregrasp["approach_tilt_rad"] = serde_json::json!(out.pregrasp.approach_tilt_rad);
    pregrasp["joint_fraction"] = serde_json::json!(out.pregrasp.joint_fraction);
    let targets: Vec<serde_json::Value> = hand
        .keypoints()
        .iter()
        .zip(&tool.targets)
        .map(|(k, p)| serde_json::json!({"name": k.name, "position": [p.x, p.y, p.z]}))
        .collect();
    let v = serde_json::json!({
        "category": category.name(),
        "points": cloud.len(),
        "registration": {
            "latent": reg.latent,
            "pose": {
                "frame": "cloud_from_canonical",
                "translation": reg.translation_cloud_from_canonical.as_slice(),
                "rotation_xyzw": [q.x, q.y, q.z, q.w],
            },
            "scale": reg.scale,
            "fit": reg.fit,
            "keypoints": reg.keypoints,
            // As `graspd register`: the camera position assumed when none was given (null: none used).
            "estimated_viewpoint": reg.estimated_viewpoint,
            "yaw_arc": super::register::yaw_arc_json(&reg),
        },
        "targets": targets,
        "grasp": grasp_json(&hand, &out.grasp),
        "pregrasp": pregrasp,
        "task_space_distance_cm": out.task_space_distance_cm,
        "residual_mm": out.report.residual_mm,
        "penetration_mm": out.report.penetration_mm,
        "baselines": {
            "cg": {"task_space_distance_cm": out.cg.task_space_distance_cm},
            "wp": {"task_space_distance_cm": out.wp.task_space_distance_cm},
        },
        "table_z": table_z,
        "solver": {
            "iterations": out.report.iterations,
            "starts": out.report.starts,
            "abandoned_starts": out.report.abandoned_starts,
            "best_start": out.report.best_start,
            "converged": out.report.converged,
        },
        "elapsed_ms": total_ms,
        "stage_ms": {
            "load_space": load_ms,
            "registration": reg.elapsed_ms,
            "transfer": tool.elapsed_ms,
            "solve": out.report.elapsed_ms,
            "pregrasp": out.pregrasp_ms,
        },
        "warnings": warnings,
    });
    if a.json {
        print_json(&v)?;
    } else {
        let t = out.grasp.wrist_pose_world.translation.vector;
        println!(
            "{}: registration scale {:.3}, residual {:.2} mm ({:.1} ms)",
            category.name(),
            reg.scale,
            reg.fit.residual_mm,
            reg.elapsed_ms
        );
        println!(
            "grasp: wrist at ({:.4}, {:.4}, {:.4}), joints {:?}",
            t.x,
            t.y,
            t.z,
            out.grasp.actuated.iter().map(|q| (q * 1e3).round() / 1e3).collect::<Vec<_>>()
        );
        println!(
            "task-space distance {:.3} cm (CG {:.3}, WP {:.3}), penetration {:.2} mm, solve {:.2} ms, total {:.1} ms",
            out.task_space_distance_cm,
            out.cg.task_space_distance_cm,
            out.wp.task_space_distance_cm,
            out.report.penetration_mm,
            out.report.elapsed_ms,
            total_ms
        );
        println!("pre-grasp collision free: {}", out.pregrasp.collision_free);
        for w in &warnings {
            println!("warning: {w}");
        }
    }
    Ok(())
}

pub fn run_eval(a: EvalGraspArgs) -> CliResult {
    let category: Category = a.category.parse()?;
    let hand = a.hand.load()?;
    let mut demo = load_demo(a.demo.as_ref(), category)?;
    demo.checked_keypoints(&hand)?;
    if let Some(mm) = a.margin_mm {
        demo.penetration_margin_m = Some(1e-3 * mm);
    }
    let space = super::space::load_space(category, a.space.as_deref())?;
    let family = tools::family(category)?;
    let canonical = family.iter().find(|i| i.split == Split::Canonical).ok_or("no canonical instance")?;
    let training: Vec<&tools::Instance> = family.iter().filter(|i| i.split == Split::Train).collect();
    let mut solve = SolveOptions { starts: a.starts.max(1), ..SolveOptions::default() };
    solve.penetration.enabled = !a.no_penetration;
    // A demonstration made without a table is evaluated without one.
    let opts = GraspEvalOptions { solve, repeats: a.repeats, table: demo.table && !a.no_table };
    let bar = progress_bar(training.len() as u64, "instances");
    let report = evaluate_grasps(&hand, &space, &demo, canonical, &training, &opts, || bar.inc(1))?;
    bar.finish_and_clear();
    if a.json {
        print_json(&report)?;
    } else {
        let t = &report.task_space_distance_cm;
        println!("{} (Table I, {} training instances): task-space distance, cm", report.category, report.instances);
        println!("  ours {:.3} ± {:.3}", t.ours.mean, t.ours.std);
        println!("  WP   {:.3} ± {:.3}", t.wp.mean, t.wp.std);
        println!("  CG   {:.3} ± {:.3}", t.cg.mean, t.cg.std);
        println!(
            "  ours/CG {:.2}; penetration mean {:.2} mm max {:.2} mm (WP max {:.1}, CG max {:.1}; ours on the true mesh max {:.2} mm); solve p50 {:.2} ms p99 {:.2} ms",
            report.ours_over_cg,
            report.penetration_mm.ours.mean,
            report.penetration_mm.ours.max,
            report.penetration_mm.wp.max,
            report.penetration_mm.cg.max,
            report.penetration_true_mesh_mm.ours.max,
            report.solve_ms.p50,
            report.solve_ms.p99
        );
        println!(
            "  targets: ours ≤ 0.5 cm {}, ≤ 0.3×CG {}, penetration ≤ 2 mm {}",
            if t.ours.mean <= 0.5 { "met" } else { "MISSED" },
            if report.ours_over_cg <= 0.3 { "met" } else { "MISSED" },
            if report.penetration_mm.ours.max <= 2.0 { "met" } else { "MISSED" }
        );
    }
    Ok(())
}
