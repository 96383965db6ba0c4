use super::space::spaces_dir;
use super::{print_json, progress_bar, CliResult};
use clap::Subcommand;
use graspd::eval::transfer::{evaluate, TransferEvalOptions};
use graspd::geometry::DepthNoise;
use graspd::shape::{builtin, Registrar};
use graspd::tools::{self, Category, Split};

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Keypoint transfer and shape completion from single partial views.
    Transfer {
        #[arg(long)]
        category: String,
        /// Viewpoints per instance.
        #[arg(long, default_value_t = 8)]
        views: usize,
        /// Constant axial depth noise σ, millimetres.
        #[arg(long, default_value_t = 1.0)]
        noise_mm: f64,
        /// Fraction of outlier points added to each view.
        #[arg(long, default_value_t = 0.0)]
        outliers: f64,
        /// Random uniform scale of each placed tool, ± this fraction.
        #[arg(long, default_value_t = 0.0)]
        scale_jitter: f64,
        /// Lay the tools on their side.
        #[arg(long)]
        on_side: bool,
        #[arg(long, default_value_t = 7)]
        seed: u64,
        #[arg(long)]
        json: bool,
    },
    /// Grasps on the training instances: the paper's Table I (ours, WP, CG).
    Grasp(super::grasp::EvalGraspArgs),
}

pub fn run(cmd: EvalCommand) -> CliResult {
    match cmd {
        EvalCommand::Grasp(a) => return super::grasp::run_eval(a),
        EvalCommand::Transfer { category, views, noise_mm, outliers, scale_jitter, on_side, seed, json } => {
            let category: Category = category.parse()?;
            let space = builtin::load_or_build(category, &spaces_dir(), |_, _| {})?;
            let registrar = Registrar::new(space);
            let family = tools::family(category)?;
            let opts = TransferEvalOptions {
                views,
                noise: DepthNoise { sigma_m: noise_mm.max(0.0) * 1e-3, ..DepthNoise::default() },
                outliers,
                scale_jitter,
                on_side,
                seed,
                ..Default::default()
            };
            let mut opts = opts;
            if std::env::var_os("GRASPD_NOSCALE").is_some() { opts.register.estimate_scale = false; }
            if let Ok(k) = std::env::var("GRASPD_KEEP") { opts.register.keep = k.parse().unwrap_or(2); }
            let mut reports = Vec::new();
            for split in [Split::Test, Split::Train] {
                let insts: Vec<_> = family.iter().filter(|i| i.split == split).collect();
                let bar = progress_bar((insts.len() * views) as u64, split.name());
                reports.push(evaluate(&registrar, &insts, split, &opts, || bar.inc(1)));
                bar.finish_and_clear();
            }
            let out = serde_json::json!({
                "category": category.name(),
                "views": views,
                "noise_mm": noise_mm, "outliers": outliers, "scale_jitter": scale_jitter, "on_side": on_side,
                "test": reports[0],
                "train": reports[1],
            });
            if json {
                print_json(&out)?;
            } else {
                for r in &reports {
                    println!(
                        "{} {}: keypoint error median {:.1} mm p90 {:.1} mm (canonical {:.1}/{:.1}, cpd_partial {:.1}/{:.1}); chamfer {:.1} mm; fit p50 {:.1} ms p99 {:.1} ms",
                        category.name(), r.split, r.ours.keypoint_error_mm.median, r.ours.keypoint_error_mm.p90,
                        r.canonical.keypoint_error_mm.median, r.canonical.keypoint_error_mm.p90,
                        r.cpd_partial.keypoint_error_mm.median, r.cpd_partial.keypoint_error_mm.p90,
                        r.ours.chamfer_mm.median, r.fit_ms.p50, r.fit_ms.p99
                    );
                }
            }
        }
    }
    Ok(())
}
