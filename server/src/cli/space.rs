use super::{assets_dir, print_json, progress_bar, CliResult};
use clap::Subcommand;
use graspd::shape::builtin;
use graspd::shape::ShapeSpace;
use graspd::tools::Category;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum SpaceCommand {
    /// Builds (and caches) the shape space of a built-in category.
    Build {
        #[arg(long)]
        category: String,
        /// Artefact directory (default: assets/spaces).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Build options as a JSON object laid over the category's (e.g.
        /// '{"cpd": {"beta": 1.5}}'; field names as in `BuildOptions`).
        #[arg(long)]
        options: Option<String>,
        #[arg(long)]
        json: bool,
    },
}

pub fn spaces_dir() -> PathBuf {
    assets_dir().join("spaces")
}

/// The shape space of `category`: the artefact at `path` when given (refused
/// when it is another category's), else the built-in one (cached, built when missing).
pub fn load_space(
    category: Category,
    path: Option<&std::path::Path>,
) -> Result<ShapeSpace, Box<dyn std::error::Error>> {
    match path {
        Some(path) => {
            let s = ShapeSpace::load(path)?;
            if s.category != category.name() {
                return Err(format!("{}: a {} space, not {}", path.display(), s.category, category.name()).into());
            }
            Ok(s)
        }
        None => Ok(builtin::load_or_build(category, &spaces_dir(), |_, _| {})?),
    }
}

pub fn run(cmd: SpaceCommand) -> CliResult {
    match cmd {
        SpaceCommand::Build { category, out, options, json } => {
            let category: Category = category.parse()?;
            let opts = match options {
                Some(j) => super::overlay_json(builtin::options(category), &j, "--options")?,
                None => builtin::options(category),
            };
            let bar = progress_bar(10, "instances");
            let (space, report) = builtin::build(category, &opts, |i, n| {
                bar.set_length(n as u64);
                bar.set_position(i as u64);
            })?;
            bar.finish_and_clear();
            let dir = out.unwrap_or_else(spaces_dir);
            let path = builtin::artefact_path(&dir, category);
            space.save(&path)?;
            if json {
                let mut v = serde_json::to_value(&report)?;
                v["artefact"] = serde_json::json!(path);
                print_json(&v)?;
            } else {
                println!(
                    "{}: {} instances, {} points, {} modes (explained {:.3}), kernel rank {}, {:.2} s -> {}",
                    report.category,
                    report.instances,
                    report.points,
                    report.modes,
                    report.explained_variance.last().copied().unwrap_or(0.0),
                    report.kernel_rank,
                    report.build_s,
                    path.display()
                );
            }
        }
    }
    Ok(())
}
