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
        /// The segmentation leaks onto the table: the tool's mask dilated by
        /// this many pixels.
        #[arg(long, default_value_t = 0)]
        mask_leak_px: u32,
        /// Something in front of each tool (a pole, the robot's arm) hides
        /// this share of its image width; the cloud does not say where.
        #[arg(long, default_value_t = 0.0)]
        occluder_share: f64,
        /// Random uniform scale of each placed tool, ± this fraction.
        #[arg(long, default_value_t = 0.0)]
        scale_jitter: f64,
        /// Lay the tools on their side.
        #[arg(long)]
        on_side: bool,
        /// Register whole-surface samples instead of camera views (diagnostic).
        #[arg(long)]
        full_surface: bool,
        /// Merge each view with a second camera's, a quarter turn round the
        /// tool and 25° up (a robot's second look); the registration is told
        /// both cameras, or neither with --unknown-viewpoint.
        #[arg(long)]
        second_view: bool,
        /// With --second-view: the second camera's calibration error, its
        /// points moved by this many millimetres and turned by this many
        /// degrees about their centroid (directions drawn per view).
        #[arg(long, value_name = "MM,DEG", value_delimiter = ',')]
        second_view_misalign: Option<Vec<f64>>,
        /// Do not tell the registration where the camera is.
        #[arg(long)]
        unknown_viewpoint: bool,
        /// Do not tell the registration the table's height (the tool resting on it).
        #[arg(long)]
        unknown_table: bool,
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Registration options as a JSON object laid over the defaults
        /// (e.g. '{"race_points": 300}'; field names as in `RegisterOptions`).
        #[arg(long)]
        register_options: Option<String>,
        /// Evaluate one split only (test or train).
        #[arg(long)]
        split: Option<String>,
        /// A shape-space artefact to evaluate (default: the category's built-in
        /// space, cached in assets/spaces and built there when missing).
        #[arg(long)]
        space: Option<std::path::PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Real scanned YCB tools (from ../shared/data/ycb) registered to their categories.
    Ycb {
        /// Categories to evaluate (default: all three).
        #[arg(long)]
        category: Option<String>,
        #[arg(long, default_value_t = 8)]
        views: usize,
        /// The shared data folder (default: ../shared/data beside the repository).
        #[arg(long)]
        data: Option<std::path::PathBuf>,
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Tell the registration where the camera is (a calibrated camera, as
        /// `eval transfer` does by default); without it the viewpoint is estimated.
        #[arg(long)]
        known_viewpoint: bool,
        /// Tell the registration the table's height (the scan rests on it).
        #[arg(long)]
        known_table: bool,
        /// Merge each view with a second camera's, a quarter turn round the
        /// scan (with --known-viewpoint the registration is told both).
        #[arg(long)]
        second_view: bool,
        /// Registration options as a JSON object laid over the defaults (as for `eval transfer`).
        #[arg(long)]
        register_options: Option<String>,
        #[arg(long)]
        json: bool,
    },
    /// Grasps on the training instances: the paper's Table I (ours, WP, CG).
    Grasp(super::grasp::EvalGraspArgs),
}

pub fn run(cmd: EvalCommand) -> CliResult {
    match cmd {
        EvalCommand::Ycb {
            category,
            views,
            data,
            seed,
            known_viewpoint,
            known_table,
            second_view,
            register_options,
            json,
        } => {
            let register = match register_options {
                Some(j) => super::overlay_json(graspd::shape::RegisterOptions::default(), &j, "--register-options")?,
                None => graspd::shape::RegisterOptions::default(),
            };
            let data = data.unwrap_or_else(|| super::assets_dir().join("../../shared/data"));
            let cats: Vec<Category> = match category {
                Some(c) => vec![c.parse()?],
                None => Category::ALL.to_vec(),
            };
            let mut reports = Vec::new();
            for c in cats {
                let path = graspd::eval::ycb::ycb_mesh_path(&data, c);
                if !path.exists() {
                    eprintln!("skipping {}: {} is absent", c.name(), path.display());
                    continue;
                }
                let registrar = Registrar::new(builtin::load_or_build(c, &spaces_dir(), |_, _| {})?);
                let protocol =
                    graspd::eval::ycb::YcbProtocol { views, seed, known_viewpoint, known_table, second_view };
                reports.push(graspd::eval::ycb::evaluate(&registrar, c, &path, protocol, &register)?);
            }
            if json {
                print_json(&reports)?;
            } else {
                for r in &reports {
                    println!(
                        "{} ({} viewpoint{}{}): chamfer median {:.1} mm (p90 {:.1}), inliers median {:.2}, confident {:.0}%, scale median {:.2}, fit p50 {:.1} ms",
                        r.category, if r.known_viewpoint { "known" } else { "estimated" }, if r.known_table { ", table known" } else { "" }, if r.second_view { ", two views" } else { "" }, r.chamfer_mm.median, r.chamfer_mm.p90, r.inlier_fraction.median, r.confident_fraction * 100.0, r.scale.median, r.fit_ms.median
                    );
                }
            }
        }
        EvalCommand::Grasp(a) => return super::grasp::run_eval(a),
        EvalCommand::Transfer {
            category,
            views,
            noise_mm,
            outliers,
            mask_leak_px,
            occluder_share,
            scale_jitter,
            on_side,
            full_surface,
            second_view,
            second_view_misalign,
            unknown_viewpoint,
            unknown_table,
            seed,
            register_options,
            split,
            space,
            json,
        } => {
            let second_view_misalign = match second_view_misalign.as_deref() {
                None => [0.0; 2],
                Some(&[mm, deg]) if second_view && mm.is_finite() && deg.is_finite() && mm >= 0.0 && deg >= 0.0 => {
                    [mm * 1e-3, deg.to_radians()]
                }
                Some(_) if !second_view => return Err("--second-view-misalign needs --second-view".into()),
                Some(v) => return Err(format!("--second-view-misalign {v:?}: two non-negative numbers, MM,DEG").into()),
            };
            if !(0.0..1.0).contains(&occluder_share) {
                return Err(format!("--occluder-share {occluder_share}: from 0 up to 1").into());
            }
            let register = match register_options {
                Some(j) => super::overlay_json(graspd::shape::RegisterOptions::default(), &j, "--register-options")?,
                None => graspd::shape::RegisterOptions::default(),
            };
            let splits: Vec<Split> = match split.as_deref() {
                None => vec![Split::Test, Split::Train],
                Some("test") => vec![Split::Test],
                Some("train") => vec![Split::Train],
                Some(other) => return Err(format!("unknown split {other:?} (test or train)").into()),
            };
            let category: Category = category.parse()?;
            let space = super::space::load_space(category, space.as_deref())?;
            let registrar = Registrar::new(space);
            let family = tools::family(category)?;
            let opts = TransferEvalOptions {
                views,
                noise: DepthNoise {
                    sigma_m: noise_mm.max(0.0) * 1e-3,
                    mask_leak_px,
                    occluder_share,
                    ..DepthNoise::default()
                },
                outliers,
                scale_jitter,
                on_side,
                full_surface,
                second_view,
                second_view_misalign,
                known_viewpoint: !unknown_viewpoint,
                known_table: !unknown_table,
                seed,
                register,
            };

            // The demonstration's hand keypoints, whose transfer a grasp depends on.
            let hand = graspd::hand::HandModel::default_sih()?;
            let demo = graspd::grasp::Demonstration::builtin(category)?;
            let grasp_targets: Vec<[f64; 3]> = demo.keypoints(&hand)?.iter().map(|p| [p.x, p.y, p.z]).collect();
            let mut reports = Vec::new();
            for &split in &splits {
                let insts: Vec<_> = family.iter().filter(|i| i.split == split).collect();
                let bar = progress_bar((insts.len() * views) as u64, split.name());
                reports.push(evaluate(&registrar, &insts, split, &grasp_targets, &opts, || bar.inc(1)));
                bar.finish_and_clear();
            }
            let out = serde_json::json!({
                "category": category.name(),
                "views": views,
                "noise_mm": noise_mm, "outliers": outliers, "mask_leak_px": mask_leak_px, "occluder_share": occluder_share, "scale_jitter": scale_jitter, "on_side": on_side, "full_surface": full_surface, "second_view": second_view, "second_view_misalign_mm_deg": [second_view_misalign[0] * 1e3, second_view_misalign[1].to_degrees()], "known_viewpoint": !unknown_viewpoint, "known_table": !unknown_table,
                "test": splits.iter().position(|s| *s == Split::Test).map(|i| &reports[i]),
                "train": splits.iter().position(|s| *s == Split::Train).map(|i| &reports[i]),
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
                    if let (Some(o), Some(c)) = (&r.ours.grasp_target_error_mm, &r.canonical.grasp_target_error_mm) {
                        println!(
                            "  grasp targets (the demonstration's hand keypoints carried onto the tool): median {:.1} mm p90 {:.1} mm (canonical {:.1}/{:.1})",
                            o.median, o.p90, c.median, c.p90
                        );
                    }
                    println!(
                        "  keypoint depth bias (along the view; negative: toward the camera): median {:+.2} mm",
                        r.keypoint_depth_bias_mm.median
                    );
                    println!(
                        "  confident {:.0}%, ambiguous {:.0}%, misled {:.1}% (confident, not ambiguous, a keypoint over {} mm off)",
                        r.confident_fraction * 100.0,
                        r.ambiguous_fraction * 100.0,
                        r.misled_fraction * 100.0,
                        graspd::eval::transfer::MISLED_MM
                    );
                    if let Some(v) = &r.view_ambiguity {
                        println!(
                            "  the views themselves: {:.0}% leave the tool's turn open{}; the floor under any method (the true shape, the middle of each view's unseen turns) median {:.1} mm p90 {:.1} mm",
                            v.open_fraction * 100.0,
                            if v.open_fraction > 0.0 {
                                format!(" (half width median {:.0}°)", v.half_width_deg.median)
                            } else {
                                String::new()
                            },
                            v.keypoint_error_floor_mm.median,
                            v.keypoint_error_floor_mm.p90,
                        );
                        if v.open_fraction > 0.0 {
                            println!(
                                "    on the open views: ours median {:.1} p90 {:.1} mm, the floor {:.1} / {:.1}",
                                v.open_keypoint_error_mm.median,
                                v.open_keypoint_error_mm.p90,
                                v.open_keypoint_error_floor_mm.median,
                                v.open_keypoint_error_floor_mm.p90
                            );
                        }
                    }
                    if r.skipped_views > 0 {
                        println!("  {} views not scored (fewer than 50 points of the tool seen)", r.skipped_views);
                    }
                }
            }
        }
    }
    Ok(())
}
