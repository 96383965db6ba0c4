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
    /// Place-mug episodes with the scripted controller (pre-grasp, close, lift, move to the goal, place, release).
    Place(PoseTaskArgs),
    /// Position-drill episodes with the scripted controller (pre-grasp, close, lift, carry to the goal pose in the air, hold).
    Position(PoseTaskArgs),
    /// Drive-nail episodes with the scripted controller (pre-grasp, close, lift, face down over the nail, strike).
    Nail(NailArgs),
    /// Throughput of N mug-lift environments stepped in parallel.
    Bench(BenchArgs),
    /// Episodes of a task stepped by actions (the trainer's interface,
    /// sim::env): N environments in parallel, a policy's actions in, success
    /// per tool and control steps per second out.
    Rollout(RolloutArgs),
    /// Writes a lift scene's MJCF (table, tool, hand at the pre-grasp), for MuJoCo's own tools.
    Scene(SceneArgs),
    /// One seeded episode drawn offscreen: K frames evenly spaced over it and a strip of them (PNG).
    Strip(StripArgs),
}

#[derive(clap::Args)]
struct StripArgs {
    /// `place` (Place mug), `position` (Position drill) or `nail` (Drive nail).
    #[arg(long)]
    task: String,
    /// An instance of the task's category (default: the canonical tool).
    #[arg(long)]
    instance: Option<String>,
    /// The episode's seed (start, goal; also the grasp solver's).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// `pregrasp`, `canonical` or `neutral` (as the task commands' --start).
    #[arg(long, default_value = "pregrasp")]
    start: String,
    /// `inprocess` (the tool's training latent) or `register` (the scene
    /// camera's view registered in this process, as the daemon does; test tools need it).
    #[arg(long, default_value = "inprocess")]
    grasp_from: String,
    #[arg(long, default_value_t = 6)]
    frames: usize,
    /// Size of one frame, pixels.
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// Camera azimuth about z from +x and elevation (negative: looking down), degrees.
    #[arg(long, allow_negative_numbers = true)]
    azimuth: Option<f64>,
    #[arg(long, allow_negative_numbers = true)]
    elevation: Option<f64>,
    /// Camera distance from the middle of the tool's path, m (default: from the path's extent).
    #[arg(long)]
    distance: Option<f64>,
    /// Output folder (frame_NN.png, strip.png), made if missing.
    #[arg(long)]
    out: std::path::PathBuf,
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct RolloutArgs {
    /// `place` (Place mug), `position` (Position drill) or `nail` (Drive nail).
    #[arg(long)]
    task: String,
    /// `canonical`, `train`, `all` (canonical and train), `test` (with
    /// `--grasp-from register` or `daemon`) or one instance name; the
    /// environments are dealt round the tools.
    #[arg(long, default_value = "all")]
    instances: String,
    #[command(flatten)]
    grasp: GraspArgs,
    /// `expert` (the task's scripted controller, as actions) or `hold`
    /// (zero wrist deltas, the start's joint targets).
    #[arg(long, default_value = "expert")]
    policy: String,
    /// Environments stepped in parallel.
    #[arg(long, default_value_t = 16)]
    envs: usize,
    /// Worker threads (default: the cores available to this process).
    #[arg(long)]
    threads: Option<usize>,
    /// Episodes to finish in all (seeds `seed`, `seed + 1`, ... in the order they start).
    #[arg(long, default_value_t = 32)]
    episodes: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct SceneArgs {
    #[arg(long, default_value = "mug")]
    category: String,
    #[arg(long, default_value = "mug_canonical")]
    instance: String,
    /// Output MJCF file (self-contained: meshes inline).
    #[arg(long)]
    out: std::path::PathBuf,
}

#[derive(clap::Args)]
struct BenchArgs {
    #[arg(long, default_value_t = 16)]
    envs: usize,
    /// Wall-clock seconds to measure (after a warm-up that staggers the episodes).
    #[arg(long, default_value_t = 30.0)]
    seconds: f64,
    /// Worker threads (default: the cores available to this process).
    #[arg(long)]
    threads: Option<usize>,
    /// `scripted` (approach, close, lift, hold; contact-rich) or `hold` (the
    /// pre-grasp's targets held: the zero action).
    #[arg(long, default_value = "scripted")]
    actions: String,
    /// Physics steps per 30 Hz control step.
    #[arg(long)]
    substeps: Option<usize>,
    #[arg(long)]
    json: bool,
}

/// Where a task's grasps come from and where its hand starts (sim/src/plan.rs).
#[derive(clap::Args)]
struct GraspArgs {
    /// `inprocess` (graspd's engine in this process, the tool's training
    /// latent), `daemon` (a running `graspd serve`, from the scene
    /// camera's view of the tool; needed for test instances) or `register`
    /// (the camera's view registered and grasped in this process as the
    /// daemon does it: no daemon, no transport).
    #[arg(long, default_value = "inprocess")]
    grasp_from: String,
    /// `pregrasp` (the generalised grasp's pre-grasp), `canonical` (w/o GG:
    /// the demonstration carried by the tool's pose) or `neutral` (w/o PG:
    /// the open hand above the table, the script reaches the grasp).
    #[arg(long, default_value = "pregrasp")]
    start: String,
    /// The daemon's service prefix (its configuration's `service_prefix`).
    #[arg(long, default_value = "graspd")]
    daemon_prefix: String,
    /// Deadline of one Grasp call to the daemon, ms.
    #[arg(long, default_value_t = 10_000)]
    daemon_timeout_ms: u64,
    /// Multiplies the scene camera's depth noise (0: a noiseless camera), for
    /// telling the registration's errors from the sensor's.
    #[arg(long, default_value_t = 1.0)]
    camera_noise_scale: f64,
    /// The scene camera's segmentation leaks onto the table: the tool's
    /// mask dilated by this many pixels (`--grasp-from register|daemon`).
    #[arg(long, default_value_t = 0)]
    camera_mask_leak_px: u32,
    /// Something in front of the tool hides this share of its image width
    /// in the scene camera (`--grasp-from register|daemon`).
    #[arg(long, default_value_t = 0.0)]
    camera_occluder_share: f64,
    /// URDF of another hand than the bundled SIH-like one (with
    /// --hand-keypoints; its servos take the bundled hand's gains unless
    /// --kp / --force-limit say otherwise).
    #[arg(long, requires = "hand_keypoints")]
    hand_urdf: Option<std::path::PathBuf>,
    /// The keypoints file of the --hand-urdf hand.
    #[arg(long, requires = "hand_urdf")]
    hand_keypoints: Option<std::path::PathBuf>,
    /// The task's demonstration file (default: the category's bundled one,
    /// made with the bundled hand; another hand needs its own).
    #[arg(long)]
    demo: Option<std::path::PathBuf>,
    /// Finger servo stiffness, N·m/rad (default: 4, tuned on the bundled
    /// hand; another hand's fingers may want their own).
    #[arg(long)]
    kp: Option<f64>,
    /// Finger servo torque limit, N·m (default: 2).
    #[arg(long)]
    force_limit: Option<f64>,
}

impl GraspArgs {
    /// The finger servos' gains, the defaults with --kp / --force-limit laid over them.
    fn servo(&self, hand: &mut graspd_sim::hand::HandMjcfOptions) -> Result<(), String> {
        for (flag, v) in [("--kp", self.kp), ("--force-limit", self.force_limit)] {
            if v.is_some_and(|v| !(v.is_finite() && v > 0.0)) {
                return Err(format!("{flag} {}: must be a positive number", v.unwrap_or_default()));
            }
        }
        hand.kp = self.kp.unwrap_or(hand.kp);
        hand.force_limit = self.force_limit.unwrap_or(hand.force_limit);
        Ok(())
    }

    /// The hand of the episodes: --hand-urdf and --hand-keypoints, else the bundled one.
    fn hand_asset(&self) -> Result<graspd_sim::hand::HandAsset, Box<dyn std::error::Error>> {
        Ok(match (&self.hand_urdf, &self.hand_keypoints) {
            (Some(u), Some(k)) => graspd_sim::hand::HandAsset::from_files(u, k)?,
            _ => graspd_sim::hand::HandAsset::default_sih()?,
        })
    }
}

#[derive(clap::Args)]
struct NailArgs {
    /// The task's category (hammer), the only one it takes.
    #[arg(long, default_value = "hammer")]
    category: String,
    /// `canonical`, `train`, `all` (canonical and train), `test` (with
    /// `--grasp-from daemon`) or one instance name.
    #[arg(long, default_value = "all")]
    instances: String,
    #[command(flatten)]
    grasp: GraspArgs,
    /// Episodes per instance (random hammer start, seeds `seed`, `seed + 1`, ...).
    #[arg(long, default_value_t = 5)]
    episodes: usize,
    /// First episode seed (also the grasp solver's seed).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Coulomb friction of the nail's slide, N (default: the fixture's).
    #[arg(long)]
    frictionloss: Option<f64>,
    /// Damping of the nail's slide, N·s/m (default: the fixture's).
    #[arg(long)]
    damping: Option<f64>,
    /// Height of the face above the head before a strike, m (default: the script's).
    #[arg(long)]
    raise_m: Option<f64>,
    /// How far below the head a strike aims, m (default: the script's).
    #[arg(long)]
    overshoot_m: Option<f64>,
    /// Duration of a strike's downswing, s (default: the script's).
    #[arg(long)]
    down_s: Option<f64>,
    /// Closing commanded beyond the grasp's joints, rad (default: the script's).
    #[arg(long)]
    squeeze_rad: Option<f64>,
    /// How far past the grasp the approach presses the palm, mm (default: the script's).
    #[arg(long)]
    press_mm: Option<f64>,
    /// MuJoCo no-slip solver iterations (0: off).
    #[arg(long)]
    noslip_iterations: Option<usize>,
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct PoseTaskArgs {
    /// The task's category (place: mug; position: drill), the only one it takes.
    #[arg(long)]
    category: Option<String>,
    /// `canonical`, `train`, `all` (canonical and train), `test` (with
    /// `--grasp-from daemon`) or one instance name.
    #[arg(long, default_value = "all")]
    instances: String,
    #[command(flatten)]
    grasp: GraspArgs,
    /// Episodes per instance (random start and goal, seeds `seed`, `seed + 1`, ...).
    #[arg(long, default_value_t = 5)]
    episodes: usize,
    /// First episode seed (also the grasp solver's seed).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// MuJoCo no-slip solver iterations (0: off).
    #[arg(long)]
    noslip_iterations: Option<usize>,
    /// How far past the grasp the approach presses the palm, mm (default: the task's).
    #[arg(long)]
    press_mm: Option<f64>,
    #[arg(long)]
    json: bool,
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
    /// How far past the grasp the approach presses the palm, mm (default: 0).
    #[arg(long)]
    press_mm: Option<f64>,
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
    // `... | head` must end quietly, not panic in println!: restore the
    // default SIGPIPE disposition that Rust's runtime replaces.
    // SAFETY: called first thing in main, before any thread exists.
    #[cfg(unix)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
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
        Command::Place(a) => run_pose_task(a, PoseTask::PlaceMug),
        Command::Position(a) => run_pose_task(a, PoseTask::PositionDrill),
        Command::Nail(a) => run_nail(a),
        Command::Bench(a) => run_bench(a),
        Command::Rollout(a) => run_rollout(a),
        Command::Scene(a) => run_scene(a),
        Command::Strip(a) => run_strip(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The instances an `--instances` argument names.
fn choose_instances<'a>(
    family: &'a [graspd::tools::Instance],
    category: graspd::tools::Category,
    which: &str,
) -> Result<Vec<&'a graspd::tools::Instance>, Box<dyn std::error::Error>> {
    Ok(graspd_sim::plan::choose_instances(family, category, which)?)
}

/// The grasp planner the grasp arguments ask for: in-process, or connected
/// to the daemon (an error naming the prefix when none serves it).
fn make_planner(
    asset: &graspd_sim::hand::HandAsset,
    category: graspd::tools::Category,
    seed: u64,
    a: &GraspArgs,
) -> Result<graspd_sim::plan::GraspPlanner, Box<dyn std::error::Error>> {
    use graspd_sim::plan::{GraspFrom, GraspPlanner, StartMode};
    let from: GraspFrom = a.grasp_from.parse()?;
    let start: StartMode = a.start.parse()?;
    let mut planner = match &a.demo {
        Some(path) => {
            GraspPlanner::with_demonstration(asset.model(), category, seed, graspd::grasp::Demonstration::load(path)?)?
        }
        None => GraspPlanner::new(asset.model(), category, seed).map_err(|e| {
            let hint = if a.hand_urdf.is_some() { " (give that hand's demonstration with --demo)" } else { "" };
            format!("{e}{hint}")
        })?,
    };
    planner = planner.with_start(start);
    if !(a.camera_noise_scale.is_finite() && a.camera_noise_scale >= 0.0) {
        return Err(format!("--camera-noise-scale {}: 0 or more", a.camera_noise_scale).into());
    }
    if !(0.0..1.0).contains(&a.camera_occluder_share) {
        return Err(format!("--camera-occluder-share {}: from 0 up to 1", a.camera_occluder_share).into());
    }
    let mut camera = graspd_sim::camera::SceneCamera::default();
    camera.noise.sigma_m *= a.camera_noise_scale;
    camera.noise.quadratic_per_m *= a.camera_noise_scale;
    camera.noise.mask_leak_px = a.camera_mask_leak_px;
    camera.noise.occluder_share = a.camera_occluder_share;
    Ok(match from {
        GraspFrom::InProcess => planner,
        GraspFrom::Register => planner.with_engine_camera(camera, graspd_sim::camera::LabFrame::default())?,
        GraspFrom::Daemon => {
            let options = graspd_sim::daemon::DaemonOptions {
                prefix: a.daemon_prefix.clone(),
                timeout: std::time::Duration::from_millis(a.daemon_timeout_ms),
                ..Default::default()
            };
            let daemon = graspd_sim::daemon::DaemonGrasper::connect(
                options,
                category,
                planner.latent_dim(),
                camera,
                graspd_sim::camera::LabFrame::default(),
            )?;
            planner.with_daemon(daemon)
        }
    })
}

/// Median of the finite values (NaN when none).
fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// One row of the per-tool summary table.
struct SummaryRow {
    tool: String,
    split: &'static str,
    grasp_from: &'static str,
    source: &'static str,
    start: &'static str,
    successes: usize,
    episodes: usize,
    /// The task's final error(s), already in words (e.g. "d 8.1 mm  θ 0.031 rad").
    errors: String,
    latency_ms: f64,
}

/// The summary table of a run, one row per tool (medians over its episodes).
fn print_summary(rows: &[SummaryRow]) {
    println!(
        "{:<18} {:<9} {:<9} {:<13} {:<9} {:>9}  {:<32} {:>11}",
        "tool", "split", "grasp", "source", "start", "success", "final error (median)", "grasp ms"
    );
    for r in rows {
        println!(
            "{:<18} {:<9} {:<9} {:<13} {:<9} {:>9}  {:<32} {:>11}",
            r.tool,
            r.split,
            r.grasp_from,
            r.source,
            r.start,
            format!("{}/{}", r.successes, r.episodes),
            r.errors,
            if r.latency_ms.is_finite() { format!("{:.1}", r.latency_ms) } else { "-".to_owned() }
        );
    }
}

/// What a task command reports: per tool, its episodes (JSON) and a summary
/// row; over all tools, the successes. Shared by `sim place`, `position`, `nail`.
#[derive(Default)]
struct TaskReport {
    rows: Vec<serde_json::Value>,
    summary: Vec<SummaryRow>,
    successes: usize,
    total: usize,
}

impl TaskReport {
    /// One tool's episodes, with their successes, grasp info and the final
    /// error(s) in words for the summary table.
    fn add<O: serde::Serialize>(
        &mut self,
        inst: &graspd::tools::Instance,
        outs: &[O],
        success: impl Fn(&O) -> bool,
        grasp: impl Fn(&O) -> &graspd_sim::plan::GraspInfo,
        errors: String,
    ) {
        let ok = outs.iter().filter(|o| success(o)).count();
        self.successes += ok;
        self.total += outs.len();
        let first = outs.first().map(|o| grasp(o).clone()).unwrap_or_default();
        self.summary.push(SummaryRow {
            tool: inst.name.clone(),
            split: inst.split.name(),
            grasp_from: first.grasp_from,
            source: first.source,
            start: first.start,
            successes: ok,
            episodes: outs.len(),
            errors,
            latency_ms: median(outs.iter().filter_map(|o| grasp(o).latency_ms).collect()),
        });
        self.rows.push(serde_json::json!({
            "instance": inst.name,
            "split": inst.split.name(),
            "grasp_from": first.grasp_from,
            "grasp_source": first.source,
            "start": first.start,
            "successes": ok,
            "episodes": outs,
        }));
    }

    /// Prints the report: `extra` (the task's own fields: ranges, fixture)
    /// joined with the common ones as JSON, or the summary table.
    fn print(
        self,
        json: bool,
        task: &str,
        category: graspd::tools::Category,
        asset: &graspd_sim::hand::HandAsset,
        planner: &graspd_sim::plan::GraspPlanner,
        mut extra: serde_json::Value,
    ) -> Result<(), Box<dyn std::error::Error>> {
        if !json {
            print_summary(&self.summary);
            println!("success {} of {}", self.successes, self.total);
            return Ok(());
        }
        let common = serde_json::json!({
            "category": category.name(),
            "task": task,
            "grasp_from": planner.grasp_from(),
            "start": planner.start_mode(),
            // The policy interface these episodes would be driven through (sim/src/obs.rs).
            "observation_layout": graspd_sim::obs::ObservationLayout {
                keypoints: asset.model().keypoints().len(),
                latent_dim: planner.latent_dim(),
            }
            .segments(),
            "action_layout": graspd_sim::obs::ActionLayout { actuated: asset.model().actuated_joints().len() }.segments(),
            "episodes": self.total,
            "successes": self.successes,
            "success_rate": self.successes as f64 / self.total.max(1) as f64,
            "results": self.rows,
        });
        if let (Some(e), serde_json::Value::Object(c)) = (extra.as_object_mut(), common) {
            e.extend(c);
        }
        println!("{}", serde_json::to_string_pretty(&extra)?);
        Ok(())
    }
}

#[derive(Clone, Copy, PartialEq)]
enum PoseTask {
    PlaceMug,
    PositionDrill,
}

/// `sim place` and `sim position`: the goal-pose tasks, one report format.
fn run_pose_task(a: PoseTaskArgs, task: PoseTask) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category};
    use graspd_sim::place::{place_instance, PlaceSetup};
    use graspd_sim::position::{position_instance, DrillSetup};
    let (task_name, own) = match task {
        PoseTask::PlaceMug => ("place_mug", Category::Mug),
        PoseTask::PositionDrill => ("position_drill", Category::Drill),
    };
    let category: Category = match &a.category {
        Some(c) => c.parse()?,
        None => own,
    };
    if category != own {
        return Err(format!("{task_name} takes the {own} category, not {category}").into());
    }
    let family = tools::family(category)?;
    let chosen = choose_instances(&family, category, &a.instances)?;
    let asset = a.grasp.hand_asset()?;
    let mut planner = make_planner(&asset, category, a.seed, &a.grasp)?;
    let mut place = PlaceSetup::default();
    let mut position = DrillSetup::default();
    a.grasp.servo(&mut place.base.hand)?;
    a.grasp.servo(&mut position.base.hand)?;
    if let Some(n) = a.noslip_iterations {
        place.base.physics.noslip_iterations = n;
        position.base.physics.noslip_iterations = n;
    }
    if let Some(mm) = a.press_mm {
        place.script.lift.press_m = 1e-3 * mm;
        position.script.lift.press_m = 1e-3 * mm;
    }
    let ranges = match task {
        PoseTask::PlaceMug => serde_json::to_value(&place.ranges)?,
        PoseTask::PositionDrill => serde_json::to_value(&position.ranges)?,
    };
    let mut report = TaskReport::default();
    for inst in chosen {
        let outs = match task {
            PoseTask::PlaceMug => place_instance(&asset, &mut planner, inst, &place, a.seed, a.episodes)?,
            PoseTask::PositionDrill => position_instance(&asset, &mut planner, inst, &position, a.seed, a.episodes)?,
        };
        if !a.json {
            for o in &outs {
                println!(
                    "{:<18} seed {:<4} success {:<5} d {:6.1} mm  θ {:5.3} rad  first reached {:>6}  lift clear {:6.1} mm  return {:8.1}  grasp {}{}{}",
                    inst.name,
                    o.seed,
                    o.success,
                    1e3 * o.final_distance_m,
                    o.final_angle_rad,
                    o.first_reached_s.map_or("-".to_owned(), |t| format!("{t:.2} s")),
                    1e3 * o.clearance_after_lift_m,
                    o.episode_return,
                    o.grasp.source,
                    o.grasp.latency_ms.map_or(String::new(), |ms| format!(" {ms:.1} ms")),
                    if o.warnings.is_empty() { String::new() } else { format!("  warnings: {}", o.warnings.join(", ")) }
                );
            }
        }
        let errors = format!(
            "d {:.1} mm  θ {:.3} rad",
            1e3 * median(outs.iter().map(|o| o.final_distance_m).collect()),
            median(outs.iter().map(|o| o.final_angle_rad).collect())
        );
        report.add(inst, &outs, |o| o.success, |o| &o.grasp, errors);
    }
    let servo = match task {
        PoseTask::PlaceMug => &place.base.hand,
        PoseTask::PositionDrill => &position.base.hand,
    };
    let servo = serde_json::json!({ "kp": servo.kp, "force_limit": servo.force_limit });
    report.print(a.json, task_name, category, &asset, &planner, serde_json::json!({ "ranges": ranges, "servo": servo }))
}

fn run_nail(a: NailArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category};
    use graspd_sim::nail::{nail_instance, NailSetup};
    let category: Category = a.category.parse()?;
    if category != Category::Hammer {
        return Err(format!("drive_nail takes the hammer category, not {category}").into());
    }
    let family = tools::family(category)?;
    let chosen = choose_instances(&family, category, &a.instances)?;
    let asset = a.grasp.hand_asset()?;
    let mut planner = make_planner(&asset, category, a.seed, &a.grasp)?;
    let mut setup = NailSetup::default();
    a.grasp.servo(&mut setup.base.hand)?;
    if let Some(n) = a.noslip_iterations {
        setup.base.physics.noslip_iterations = n;
    }
    if let Some(f) = a.frictionloss {
        setup.fixture.frictionloss_n = f;
    }
    if let Some(d) = a.damping {
        setup.fixture.damping_ns_per_m = d;
    }
    if let Some(v) = a.raise_m {
        setup.script.raise_m = v;
    }
    if let Some(v) = a.overshoot_m {
        setup.script.overshoot_m = v;
    }
    if let Some(v) = a.down_s {
        setup.script.down_s = v;
    }
    if let Some(v) = a.squeeze_rad {
        setup.script.lift.squeeze_rad = v;
    }
    if let Some(mm) = a.press_mm {
        setup.script.lift.press_m = 1e-3 * mm;
    }
    let mut report = TaskReport::default();
    for inst in chosen {
        let outs = nail_instance(&asset, &mut planner, inst, &setup, a.seed, a.episodes)?;
        if !a.json {
            for o in &outs {
                println!(
                    "{:<18} seed {:<4} success {:<5} depth {:5.1} mm  strikes {:2}  first driven {:>6}  lift clear {:6.1} mm  aim {:5.1} mm  held {:<5}  return {:8.1}  grasp {}{}{}",
                    inst.name,
                    o.seed,
                    o.success,
                    1e3 * o.depth_m,
                    o.strikes,
                    o.first_driven_s.map_or("-".to_owned(), |t| format!("{t:.2} s")),
                    1e3 * o.clearance_after_lift_m,
                    1e3 * o.face_distance_at_first_strike_m,
                    o.held_at_end,
                    o.episode_return,
                    o.grasp.source,
                    o.grasp.latency_ms.map_or(String::new(), |ms| format!(" {ms:.1} ms")),
                    if o.warnings.is_empty() { String::new() } else { format!("  warnings: {}", o.warnings.join(", ")) }
                );
            }
        }
        let errors = format!("depth {:.1} mm", 1e3 * median(outs.iter().map(|o| o.depth_m).collect()));
        report.add(inst, &outs, |o| o.success, |o| &o.grasp, errors);
    }
    // The goal segment of the observation layout is the nail's head.
    let servo = serde_json::json!({ "kp": setup.base.hand.kp, "force_limit": setup.base.hand.force_limit });
    let extra = serde_json::json!({ "ranges": setup.ranges, "fixture": setup.fixture, "servo": servo });
    report.print(a.json, "drive_nail", category, &asset, &planner, extra)
}

fn run_lift(a: LiftArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category};
    use graspd_sim::episode::{lift_instance, LiftSetup};
    let category: Category = a.category.parse()?;
    let family = tools::family(category)?;
    let chosen = choose_instances(&family, category, &a.instances)?;
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
    if let Some(mm) = a.press_mm {
        setup.script.press_m = 1e-3 * mm;
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

fn run_bench(a: BenchArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category};
    use graspd_sim::episode::LiftSetup;
    use graspd_sim::scene::{SceneSpec, Table};
    use graspd_sim::tool::{ToolBody, ToolMaterial};
    use graspd_sim::vecenv::{ActionStream, VecLift};
    use nalgebra::Isometry3;
    use std::time::Instant;

    let actions = match a.actions.as_str() {
        "scripted" => ActionStream::Scripted,
        "hold" => ActionStream::Hold,
        other => return Err(format!("--actions {other}: expected `scripted` or `hold`").into()),
    };
    if !(a.seconds.is_finite() && a.seconds > 0.0) {
        return Err(format!("--seconds {} must be positive", a.seconds).into());
    }
    let threads = a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let mut setup = LiftSetup::default();
    if let Some(n) = a.substeps {
        setup.physics.substeps = n.max(1);
    }
    let asset = graspd_sim::hand::HandAsset::default_sih()?;
    let hand = asset.model();
    let mug = tools::instance(Category::Mug, "mug_canonical")?;
    let plan = graspd_sim::plan::GraspPlanner::new(hand, Category::Mug, 0)?.plan(&mug)?;
    let tool = ToolBody::from_mesh("mug", &mug.mesh, ToolMaterial::for_category(Category::Mug), &setup.decomposition)?;
    let spec = SceneSpec {
        name: "bench_mug".into(),
        physics: setup.physics.clone(),
        table: Some(Table::default()),
        tools: vec![(&tool, Isometry3::identity())],
        hand: Some((&asset, setup.hand.clone(), plan.pregrasp.wrist_pose_world)),
        ..Default::default()
    };
    let mut envs = VecLift::new(
        spec.build()?,
        hand,
        plan,
        Isometry3::identity(),
        &setup.script,
        actions,
        setup.physics.control_hz,
        a.envs,
        threads,
    )?;
    tracing::info!(envs = a.envs, threads, "stepping for {} s", a.seconds);
    let t0 = Instant::now();
    let mut batches = 0u64;
    while t0.elapsed().as_secs_f64() < a.seconds {
        envs.step();
        batches += 1;
    }
    let wall = t0.elapsed().as_secs_f64();
    let (physics_s, episodes) = envs.physics_stats();
    let control_steps = batches * envs.len() as u64;
    let physics_steps = control_steps * envs.substeps() as u64;
    let v = serde_json::json!({
        "scene": "mug_canonical lift",
        "actions": a.actions,
        "envs": envs.len(),
        "threads": threads,
        "substeps": envs.substeps(),
        "control_hz": setup.physics.control_hz,
        "seconds": wall,
        "control_steps": control_steps,
        "control_steps_per_s": control_steps as f64 / wall,
        "physics_steps_per_s": physics_steps as f64 / wall,
        // Time inside MuJoCo's step per physics step, each thread's own time (not divided by threads).
        "physics_us_per_step": 1e6 * physics_s / physics_steps.max(1) as f64,
        "episodes_completed": episodes,
        "simulated_seconds_per_s": control_steps as f64 / setup.physics.control_hz / wall,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{} envs on {} threads, {}: {:.0} control steps/s ({} physics steps each), {:.1} µs per physics step, {:.0}× real time",
            envs.len(),
            threads,
            a.actions,
            v["control_steps_per_s"].as_f64().unwrap_or(0.0),
            envs.substeps(),
            v["physics_us_per_step"].as_f64().unwrap_or(0.0),
            v["simulated_seconds_per_s"].as_f64().unwrap_or(0.0)
        );
    }
    Ok(())
}

fn run_rollout(a: RolloutArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools;
    use graspd_sim::env::{EnvSetup, Expert, Task, VecTaskEnv};
    use graspd_sim::obs::Action;
    use std::time::Instant;

    let task: Task = a.task.parse()?;
    let expert = match a.policy.as_str() {
        "expert" => true,
        "hold" => false,
        other => return Err(format!("--policy {other}: expected `expert` or `hold`").into()),
    };
    if a.episodes == 0 {
        return Err("--episodes must be at least 1".into());
    }
    let category = task.category();
    let family = tools::family(category)?;
    let instances: Vec<tools::Instance> =
        choose_instances(&family, category, &a.instances)?.into_iter().cloned().collect();
    let asset = a.grasp.hand_asset()?;
    let planner = make_planner(&asset, category, a.seed, &a.grasp)?;
    let threads = a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let t_build = Instant::now();
    let mut setup = EnvSetup::new(task);
    a.grasp.servo(&mut setup.task.base_mut().hand)?;
    let mut envs = VecTaskEnv::new(&asset, planner, &instances, setup, a.envs, threads, a.seed)?;
    let build_s = t_build.elapsed().as_secs_f64();
    let n = envs.len();
    let width = envs.action_layout().len();
    let mut actions = vec![0.0f32; n * width];
    let mut experts: Vec<Option<Expert>> = (0..n).map(|_| None).collect();
    let mut finished = Vec::new();
    let (mut steps, mut step_s, mut policy_s) = (0u64, 0.0, 0.0);
    let bar = indicatif::ProgressBar::new(a.episodes as u64);
    while finished.len() < a.episodes {
        let t0 = Instant::now();
        if expert {
            envs.expert_actions(&mut experts, &mut actions)?;
        } else {
            for (i, row) in actions.chunks_exact_mut(width).enumerate() {
                let env = envs.env(i).ok_or("environment missing")?;
                row.copy_from_slice(&Action::hold(env.command()?.1).to_vec());
            }
        }
        let t1 = Instant::now();
        envs.step(&actions)?;
        policy_s += (t1 - t0).as_secs_f64();
        step_s += t1.elapsed().as_secs_f64();
        steps += n as u64;
        let done = envs.drain_finished();
        bar.inc(done.len() as u64);
        finished.extend(done);
    }
    bar.finish_and_clear();
    finished.truncate(a.episodes);
    let mut per_tool: Vec<(String, usize, usize)> = Vec::new();
    for s in &finished {
        match per_tool.iter_mut().find(|(t, _, _)| *t == s.instance) {
            Some(row) => {
                row.1 += s.success as usize;
                row.2 += 1;
            }
            None => per_tool.push((s.instance.clone(), s.success as usize, 1)),
        }
    }
    let successes = finished.iter().filter(|s| s.success).count();
    let v = serde_json::json!({
        "task": task.name(),
        "policy": a.policy,
        "envs": n,
        "threads": threads,
        "episodes": finished.len(),
        "successes": successes,
        "success_rate": successes as f64 / finished.len() as f64,
        "per_tool": per_tool.iter().map(|(t, ok, all)| serde_json::json!({"instance": t, "successes": ok, "episodes": all})).collect::<Vec<_>>(),
        "control_steps": steps,
        // Stepping alone (physics, observations, rewards, resets with their grasp plans) and with the policy's time.
        "control_steps_per_s": steps as f64 / step_s,
        "control_steps_per_s_with_policy": steps as f64 / (step_s + policy_s),
        "build_s": build_s,
        "observation_layout": envs.observation_layout().segments(),
        "action_layout": envs.action_layout().segments(),
        "results": finished,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("{:<18} {:>9}", "tool", "success");
        for (t, ok, all) in &per_tool {
            println!("{t:<18} {:>9}", format!("{ok}/{all}"));
        }
        println!(
            "{} of {} episodes; {} envs on {} threads: {:.0} control steps/s stepping, {:.0} with the policy",
            successes,
            finished.len(),
            n,
            threads,
            v["control_steps_per_s"].as_f64().unwrap_or(0.0),
            v["control_steps_per_s_with_policy"].as_f64().unwrap_or(0.0)
        );
    }
    Ok(())
}

fn run_scene(a: SceneArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd::tools::{self, Category};
    use graspd_sim::episode::LiftSetup;
    use graspd_sim::scene::{SceneSpec, Table};
    use graspd_sim::tool::ToolBody;
    use nalgebra::Isometry3;

    let category: Category = a.category.parse()?;
    let instance = tools::instance(category, &a.instance)?;
    let asset = graspd_sim::hand::HandAsset::default_sih()?;
    let plan = graspd_sim::plan::GraspPlanner::new(asset.model(), category, 0)?.plan(&instance)?;
    let setup = LiftSetup::default();
    let tool = ToolBody::from_instance(&instance, &setup.decomposition)?;
    let spec = SceneSpec {
        name: format!("lift_{}", instance.name),
        physics: setup.physics.clone(),
        table: Some(Table::default()),
        tools: vec![(&tool, Isometry3::identity())],
        hand: Some((&asset, setup.hand.clone(), plan.pregrasp.wrist_pose_world)),
        ..Default::default()
    };
    let xml = spec.to_mjcf();
    // Compile it before writing, so a written file is a valid model.
    spec.build()?;
    std::fs::write(&a.out, xml).map_err(|e| format!("cannot write {}: {e}", a.out.display()))?;
    println!("{}: {} hulls, {:.3} kg", a.out.display(), tool.hulls.len(), tool.mass.mass);
    Ok(())
}

fn run_strip(a: StripArgs) -> Result<(), Box<dyn std::error::Error>> {
    use graspd_sim::render::{make_strip, RenderOptions, StripRequest};
    let request = StripRequest {
        task: a.task.parse()?,
        instance: a.instance,
        seed: a.seed,
        start: a.start.parse()?,
        from_camera: match a.grasp_from.parse()? {
            graspd_sim::plan::GraspFrom::InProcess => false,
            graspd_sim::plan::GraspFrom::Register => true,
            graspd_sim::plan::GraspFrom::Daemon => {
                return Err("sim strip takes --grasp-from inprocess or register, not daemon".into())
            }
        },
        frames: a.frames,
        render: {
            let d = RenderOptions::default();
            RenderOptions {
                width: a.width,
                height: a.height,
                azimuth_deg: a.azimuth.unwrap_or(d.azimuth_deg),
                elevation_deg: a.elevation.unwrap_or(d.elevation_deg),
                distance_m: a.distance,
                ..d
            }
        },
        gap: 4,
    };
    // Hidden when stderr is not a terminal.
    let bar = indicatif::ProgressBar::new(a.frames as u64 + 1);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg:>12} [{bar:30}] {pos}/{len} {elapsed}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_message("episode");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let out = make_strip(&request, &a.out, &mut |done, _| {
        bar.set_message("frames");
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let out = out?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        for f in &out.frames {
            println!("{}  t {:5.2} s", f.path.display(), f.t_s);
        }
        println!(
            "{}  {} × {} px, {} KB  ({} {} seed {}, success {}; episode {:.1} s, render {:.1} s)",
            out.strip.display(),
            out.strip_size[0],
            out.strip_size[1],
            out.strip_bytes / 1024,
            serde_json::to_value(out.task)?.as_str().unwrap_or(""),
            out.instance,
            out.seed,
            out.success,
            out.episode_s,
            out.render_s
        );
    }
    Ok(())
}
