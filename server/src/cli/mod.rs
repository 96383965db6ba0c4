//! Command-line front end of the engine.

mod assets;
mod cloud;
mod cpd;
mod demo;
mod eval;
mod grasp;
mod hand;
mod register;
mod serve;
mod space;

use clap::{Parser, Subcommand};

pub type CliResult = Result<(), Box<dyn std::error::Error>>;

#[derive(Parser)]
#[command(name = "graspd", version, about = "One-shot grasp transfer for multi-fingered hands")]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The built-in procedural tool families.
    #[command(subcommand)]
    Assets(assets::AssetsCommand),
    /// Renders a segmented partial view of a mesh with the virtual depth camera.
    Cloud(cloud::CloudArgs),
    /// Coherent Point Drift of one cloud onto another.
    Cpd(cpd::CpdArgs),
    /// Category shape spaces.
    #[command(subcommand)]
    Space(space::SpaceCommand),
    /// Registers a partial cloud to a category: latent shape, pose, keypoints.
    Register(register::RegisterArgs),
    /// Evaluations that print the figures of the issues.
    #[command(subcommand)]
    Eval(eval::EvalCommand),
    /// The hand model: joints, couplings, keypoints; random reachable keypoint sets.
    #[command(subcommand)]
    Hand(hand::HandCommand),
    /// Wrist pose and joints whose keypoints best match target keypoints.
    Retarget(grasp::RetargetArgs),
    /// Registration, grasp and pre-grasp from a partial cloud of a tool.
    Grasp(grasp::GraspArgs),
    /// Demonstrations on the canonical tools: author one, check an imported one.
    #[command(subcommand)]
    Demo(demo::DemoCommand),
    /// Runs the daemon: serves the engine to local clients over shared memory (iceoryx2).
    Serve(serve::ServeArgs),
}

pub fn run(cli: Cli) -> CliResult {
    match cli.command {
        Command::Assets(c) => assets::run(c),
        Command::Cloud(a) => cloud::run(a),
        Command::Cpd(a) => cpd::run(a),
        Command::Space(c) => space::run(c),
        Command::Register(a) => register::run(a),
        Command::Eval(c) => eval::run(c),
        Command::Hand(c) => hand::run(c),
        Command::Retarget(a) => grasp::run_retarget(a),
        Command::Grasp(a) => grasp::run_grasp(a),
        Command::Demo(c) => demo::run(c),
        Command::Serve(a) => serve::run(a, std::time::Instant::now()),
    }
}

/// Prints `value` as pretty JSON on stdout.
pub fn print_json(value: &impl serde::Serialize) -> CliResult {
    println!("{}", serde_json::to_string_pretty(value)?);
    Ok(())
}

/// A progress bar on stderr for work a person waits on (hidden when not a terminal).
pub fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg:>12} [{bar:30}] {pos}/{len} {elapsed}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// The repository's assets directory (next to the server crate).
pub fn assets_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets")
}

/// `base` with the fields of the JSON object `json` laid over it (nested
/// objects merge field by field); an unknown field is an error naming it.
pub fn overlay_json<T: serde::Serialize + serde::de::DeserializeOwned>(
    base: T,
    json: &str,
    flag: &str,
) -> Result<T, Box<dyn std::error::Error>> {
    fn merge(base: &mut serde_json::Value, over: serde_json::Value, path: &str) -> Result<(), String> {
        match (base, over) {
            (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
                for (k, v) in o {
                    let slot = b.get_mut(&k).ok_or_else(|| format!("unknown field {path}{k}"))?;
                    merge(slot, v, &format!("{path}{k}."))?;
                }
                Ok(())
            }
            (slot, v) => {
                *slot = v;
                Ok(())
            }
        }
    }
    let over: serde_json::Value = serde_json::from_str(json).map_err(|e| format!("{flag} is not JSON: {e}"))?;
    if !over.is_object() {
        return Err(format!("{flag} must be a JSON object").into());
    }
    let mut value = serde_json::to_value(base)?;
    merge(&mut value, over, "").map_err(|e| format!("{flag}: {e}"))?;
    Ok(serde_json::from_value(value).map_err(|e| format!("{flag}: {e}"))?)
}
