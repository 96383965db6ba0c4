use super::{print_json, CliResult};
use clap::Args;
use graspd::shape::cpd::{self, EmOptions, NonRigidOptions, RigidOptions};
use std::path::PathBuf;

#[derive(Args)]
pub struct CpdArgs {
    /// Moving cloud (Y).
    #[arg(long)]
    source: PathBuf,
    /// Fixed cloud (X).
    #[arg(long)]
    target: PathBuf,
    /// Rigid with scale instead of non-rigid.
    #[arg(long)]
    rigid: bool,
    /// Kernel width relative to the source's RMS radius.
    #[arg(long, default_value_t = 0.5)]
    beta: f64,
    #[arg(long, default_value_t = 2.0)]
    lambda: f64,
    /// Outlier weight in [0, 1).
    #[arg(long, default_value_t = 0.1)]
    w: f64,
    #[arg(long, default_value_t = 150)]
    iters: usize,
    /// Relative change of the objective that ends the run (0: run all iterations).
    #[arg(long, default_value_t = 1e-5)]
    tol: f64,
    /// Largest kernel rank (low-rank factor).
    #[arg(long, default_value_t = 1024)]
    max_rank: usize,
    /// Kernel eigenvalues below this fraction of the largest are dropped. 1e-8
    /// matches full-rank CPD within 0.04% of the object's size (bench/README.md);
    /// 1e-6 keeps fewer ranks (234 against 369 on the 1,024-point mug), within 2%.
    #[arg(long, default_value_t = 1e-8)]
    rank_tol: f64,
    /// Moved source written here.
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    json: bool,
}

pub fn run(a: CpdArgs) -> CliResult {
    let src = graspd::io::read_cloud(&a.source)?;
    let dst = graspd::io::read_cloud(&a.target)?;
    let em = EmOptions { w: a.w, max_iters: a.iters, tol: a.tol };
    let out = if a.rigid {
        let bar = super::progress_bar(a.iters as u64, "iterations");
        let r =
            cpd::rigid_reporting(&src, &dst, &RigidOptions { em, scale: true }, &mut |i| bar.set_position(i as u64));
        bar.finish_and_clear();
        let r = r?;
        graspd::io::write_cloud(&a.out, &r.moved)?;
        serde_json::json!({
            "mode": "rigid", "iterations": r.report.iterations, "converged": r.report.converged,
            "sigma2": r.report.sigma2, "elapsed_ms": r.report.elapsed_ms, "scale": r.scale,
            "rotation": r.rotation.as_slice(), "translation": r.translation.as_slice(),
            "source_points": src.len(), "target_points": dst.len(),
        })
    } else {
        let opts = NonRigidOptions { em, beta: a.beta, lambda: a.lambda, max_rank: a.max_rank, rank_tol: a.rank_tol };
        // The kernel factor comes first (seconds at tens of thousands of points).
        let bar = super::progress_bar(a.iters as u64, "kernel");
        bar.tick();
        let r = cpd::non_rigid_reporting(&src, &dst, &opts, &mut |i| {
            if i == 1 {
                bar.set_message("iterations");
            }
            bar.set_position(i as u64)
        });
        bar.finish_and_clear();
        let r = r?;
        graspd::io::write_cloud(&a.out, &r.moved)?;
        serde_json::json!({
            "mode": "nonrigid", "iterations": r.report.iterations, "converged": r.report.converged,
            "sigma2": r.report.sigma2, "elapsed_ms": r.report.elapsed_ms, "kernel_rank": r.kernel_rank,
            "kernel_tail_ratio": r.kernel_tail_ratio,
            "source_points": src.len(), "target_points": dst.len(),
        })
    };
    if a.json {
        print_json(&out)?;
    } else {
        println!(
            "{} iterations, sigma2 {:.3e} m², {:.1} ms -> {}",
            out["iterations"],
            out["sigma2"].as_f64().unwrap_or(f64::NAN),
            out["elapsed_ms"].as_f64().unwrap_or(f64::NAN),
            a.out.display()
        );
    }
    Ok(())
}
