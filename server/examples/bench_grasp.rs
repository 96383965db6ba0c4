//! Grasp latency per stage, the daemon's Grasp path in-process: register the
//! test views of one category, carry the demonstration onto the registered
//! shape, solve the hand onto it (table at z = 0) and find the pre-grasp.
//! `cargo run --release --example bench_grasp -- mug [repeats]`.
#[path = "common/views.rs"]
mod views;

use graspd::eval::grasp::percentile;
use graspd::grasp::transfer::{solve_transferred, TransferModel, TransferredTool};
use graspd::grasp::{Demonstration, GraspSolver, PreGraspOptions, SolveOptions};
use graspd::hand::HandModel;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::{self, Category, Split};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let category: Category = args.get(1).map_or("mug", |s| s.as_str()).parse()?;
    let repeats: usize = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let registrar = Registrar::new(builtin::load_or_build(category, &root, |_, _| {})?);
    let hand = HandModel::default_sih()?;
    let demo = Demonstration::builtin(category)?;
    let keypoints = demo.keypoints(&hand)?;
    let canonical =
        tools::family(category)?.into_iter().find(|i| i.split == Split::Canonical).ok_or("no canonical")?.mesh;
    let views = views::test_views(category)?;
    let model = TransferModel::new(&registrar.space, &keypoints, &canonical);
    let mut stages: [Vec<f64>; 5] = Default::default();
    let mut penetration = Vec::new();
    let mut tsd = Vec::new();
    let mut best_start = [0usize; 16];
    let mut iterations = 0usize;
    let starts: usize = std::env::var("STARTS").map_or(Ok(SolveOptions::default().starts), |s| s.parse())?;
    for _ in 0..repeats {
        for (k, view) in views.iter().enumerate() {
            let t0 = std::time::Instant::now();
            let opts = RegisterOptions { viewpoint: Some(view.viewpoint), ..Default::default() };
            let reg = registrar.register(&view.cloud, &opts)?;
            let t_reg = t0.elapsed().as_secs_f64() * 1e3;
            let tool = TransferredTool::from_registration(&registrar, &reg, &model)?;
            let mut solver = GraspSolver::new(&hand, SolveOptions { seed: k as u64, starts, ..Default::default() });
            let out = solve_transferred(&mut solver, &demo, &tool, Some(0.0), &PreGraspOptions::default())?;
            let total = t0.elapsed().as_secs_f64() * 1e3;
            for (v, x) in stages.iter_mut().zip([t_reg, tool.elapsed_ms, out.report.elapsed_ms, out.pregrasp_ms, total])
            {
                v.push(x);
            }
            penetration.push(out.report.penetration_mm);
            best_start[out.report.best_start.min(15)] += 1;
            iterations += out.report.iterations;
            tsd.push(out.task_space_distance_cm);
        }
    }
    let p = |v: &[f64]| (percentile(v, 0.5), percentile(v, 0.99));
    let names = ["register", "transfer", "solve", "pre-grasp", "total"];
    print!("{} grasp: {} views;", category.name(), stages[4].len());
    for (name, v) in names.iter().zip(&stages) {
        let (a, b) = p(v);
        print!(" {name} {a:.2}/{b:.2}");
    }
    println!(" ms (p50/p99); penetration max {:.2} mm", penetration.iter().cloned().fold(0.0, f64::max));
    let n = stages[4].len();
    println!(
        "  task-space distance mean {:.3} cm; {:.0} LM iterations a solve; best start {:?}",
        tsd.iter().sum::<f64>() / n as f64,
        iterations as f64 / n as f64,
        &best_start[..starts.min(16)]
    );
    Ok(())
}
