//! `sim`: the MuJoCo simulator's command line.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "sim", about = "graspd's MuJoCo simulator: scenes, scripted episodes, benchmarks")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The linked MuJoCo library.
    Info {
        #[arg(long)]
        json: bool,
    },
    /// Scripted grasp-and-lift episodes: pre-grasp, close, lift 10 cm, hold 2 s.
    Lift(LiftArgs),
}

#[derive(clap::Args)]
struct LiftArgs {
    #[arg(long, default_value = "mug")]
    category: String,
    /// `canonical`, `train`, `all` (canonical and train) or one instance name (e.g. mug_train_03).
    #[arg(long, default_value = "all")]
    instances: String,
    /// Seed of the grasp solver's restarts.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Finger servo stiffness, N·m/rad (default: the hand's).
    #[arg(long)]
    kp: Option<f64>,
    /// Finger servo torque limit, N·m (default: the hand's).
    #[arg(long)]
    force_limit: Option<f64>,
    /// Closing commanded beyond the grasp's joints, rad (default: the script's).
    #[arg(long)]
    squeeze_rad: Option<f64>,
    /// Physics steps per 30 Hz control step.
    #[arg(long)]
    substeps: Option<usize>,
    /// MuJoCo no-slip solver iterations (0: off).
    #[arg(long)]
    noslip_iterations: Option<usize>,
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result: Result<(), Box<dyn std::error::Error>> = match cli.command {
        Command::Info { json } => {
            let version = graspd_sim::mujoco_version();
            if json {
                println!(
                    "{}",
                    serde_json::json!({ "mujoco_version": version, "expected": graspd_sim::MUJOCO_VERSION })
                );
            } else {
                println!("MuJoCo {version} (built for {})", graspd_sim::MUJOCO_VERSION);
            }
            Ok(())
        }
        Command::Lift(a) => run_lift(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run_lift(a: LiftArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category, Split};
    use graspd_sim::episode::{lift_instance, LiftSetup};
    let category: Category = a.category.parse()?;
    let family = tools::family(category)?;
    let chosen: Vec<&tools::Instance> = match a.instances.as_str() {
        "canonical" => family.iter().filter(|i| i.split == Split::Canonical).collect(),
        "train" => family.iter().filter(|i| i.split == Split::Train).collect(),
        "all" => family.iter().filter(|i| i.split != Split::Test).collect(),
        name => {
            let found: Vec<_> = family.iter().filter(|i| i.name == name).collect();
            if found.is_empty() {
                return Err(format!("no {category} instance `{name}` (canonical, train, all, or a name)").into());
            }
            found
        }
    };
    let asset = graspd_sim::hand::HandAsset::default_sih()?;
    let mut planner = graspd_sim::plan::GraspPlanner::new(asset.model(), category, a.seed)?;
    let mut setup = LiftSetup::default();
    if let Some(kp) = a.kp {
        setup.hand.kp = kp;
    }
    if let Some(f) = a.force_limit {
        setup.hand.force_limit = f;
    }
    if let Some(s) = a.squeeze_rad {
        setup.script.squeeze_rad = s;
    }
    if let Some(n) = a.substeps {
        setup.physics.substeps = n.max(1);
    }
    if let Some(n) = a.noslip_iterations {
        setup.physics.noslip_iterations = n;
    }
    let mut rows = Vec::new();
    for inst in chosen {
        let (plan, out) = lift_instance(&asset, &mut planner, inst, &setup)?;
        if !a.json {
            println!(
                "{:<18} {:<13} tsd {:.2} cm  pre-grasp clear {:<5}  held {:<5}  upright {:<5}  clearance {:6.1} mm  slip {:5.1} mm  tilt {:5.1}°  {:.0} µs/step  touching [{}]{}",
                inst.name,
                plan.source,
                plan.task_space_distance_cm,
                plan.pregrasp_collision_free,
                out.held,
                out.upright,
                1e3 * out.clearance_after_hold_m,
                1e3 * out.slip_during_hold_m,
                out.tilt_rad.to_degrees(),
                out.physics_us_per_step,
                out.links_touching_at_grasp.join(" "),
                if out.warnings.is_empty() { String::new() } else { format!("  warnings: {}", out.warnings.join(", ")) }
            );
        }
        rows.push(serde_json::json!({
            "instance": inst.name,
            "split": inst.split.name(),
            "grasp_source": plan.source,
            "task_space_distance_cm": plan.task_space_distance_cm,
            "pregrasp_collision_free": plan.pregrasp_collision_free,
            "outcome": out,
        }));
    }
    let count = |key: &str| rows.iter().filter(|r| r["outcome"][key].as_bool() == Some(true)).count();
    let (held, upright) = (count("held"), count("upright"));
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "category": category.name(),
                "episodes": rows.len(),
                "held": held,
                "upright": upright,
                "results": rows,
            }))?
        );
    } else {
        println!("held {held} of {} ({upright} upright)", rows.len());
    }
    Ok(())
}
