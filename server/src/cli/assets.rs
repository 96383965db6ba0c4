use super::{assets_dir, print_json, CliResult};
use clap::Subcommand;
use graspd::tools::{self, Category};
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum AssetsCommand {
    /// Categories, instances, splits and paths of the built-in families.
    List {
        #[arg(long)]
        json: bool,
    },
    /// Regenerates the families deterministically (same seed, same bytes).
    Generate {
        /// Output directory (default: assets/tools of the repository).
        #[arg(long)]
        out: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: AssetsCommand) -> CliResult {
    match cmd {
        AssetsCommand::Generate { out, json } => {
            let out = out.unwrap_or_else(|| assets_dir().join("tools"));
            let t0 = std::time::Instant::now();
            let manifest = tools::generate(&out)?;
            if json {
                print_json(&manifest)?;
            } else {
                let n: usize = Category::ALL.len();
                println!(
                    "wrote {} instances of {n} categories to {} in {:.2} s",
                    manifest.instances.len(),
                    out.display(),
                    t0.elapsed().as_secs_f64()
                );
            }
        }
        AssetsCommand::List { json } => {
            let dir = assets_dir().join("tools");
            let mut rows = Vec::new();
            for c in Category::ALL {
                for inst in tools::family(c)? {
                    rows.push(serde_json::json!({
                        "category": c.name(),
                        "instance": inst.name,
                        "split": inst.split.name(),
                        "path": dir.join(c.name()).join(format!("{}.obj", inst.name)),
                        "triangles": inst.mesh.triangles.len(),
                        "keypoints": inst.keypoints.iter().map(|k| k.name.clone()).collect::<Vec<_>>(),
                    }));
                }
            }
            if json {
                print_json(&serde_json::json!({
                    "categories": Category::ALL.iter().map(|c| serde_json::json!({"name": c.name(), "canonical_frame": c.canonical_frame()})).collect::<Vec<_>>(),
                    "instances": rows,
                }))?;
            } else {
                for r in rows {
                    println!(
                        "{:<8} {:<20} {:<10} {}",
                        r["category"].as_str().unwrap_or(""),
                        r["instance"].as_str().unwrap_or(""),
                        r["split"].as_str().unwrap_or(""),
                        r["path"].as_str().unwrap_or("")
                    );
                }
            }
        }
    }
    Ok(())
}
