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
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
