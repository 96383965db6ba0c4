use super::{print_json, CliResult};
use clap::Args;
use graspd::service::{self, Config, Waiting};
use std::path::PathBuf;

#[derive(Args)]
pub struct ServeArgs {
    /// Configuration file (TOML; every option: deploy/graspd.toml). Default: built-in defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Spin instead of sleeping between requests (lowest latency; keeps a core busy).
    #[arg(long)]
    poll: bool,
    /// Log a metrics line (per-method counts and latency percentiles) every SECONDS.
    #[arg(long, value_name = "SECONDS")]
    metrics: Option<f64>,
    /// Print one JSON line on stdout when serving starts, and a JSON report on exit.
    #[arg(long)]
    json: bool,
}

pub fn run(a: ServeArgs, process_start: std::time::Instant) -> CliResult {
    let mut config = match &a.config {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    if a.poll {
        config.waiting = Waiting::Poll;
    }
    if let Some(m) = a.metrics {
        config.metrics_interval_s = m;
    }
    config.validate()?;
    let report =
        service::serve(config, service::ServeOptions { process_start: Some(process_start), ready_line: a.json })?;
    if a.json {
        print_json(&report)?;
    }
    Ok(())
}
