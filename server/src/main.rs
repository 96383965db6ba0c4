//! `graspd`: the daemon and the offline tools (assets, clouds, CPD, shape
//! spaces, registration, evaluations). Every command whose output a script
//! would read takes --json.

mod cli;

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    // `graspd ... | head` must end quietly, not panic in println!: restore the
    // default SIGPIPE disposition that Rust's runtime replaces.
    // SAFETY: called first thing in main, before any thread exists.
    #[cfg(unix)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let args = cli::Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("GRASPD_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    // Single-threaded numerics unless asked: figures are quoted per core, and
    // the daemon decides its own parallelism.
    faer::set_global_parallelism(faer::Par::Seq);
    match cli::run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
