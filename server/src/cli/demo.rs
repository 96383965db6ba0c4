//! `graspd demo`: author a demonstration on a canonical tool (close until
//! contact) and check a demonstration file made elsewhere.

use super::hand::HandArgs;
use super::{print_json, CliResult};
use clap::Subcommand;
use graspd::grasp::{
    check_demonstration, close_until_contact, CloseOptions, DemoCheck, DemoCheckOptions, Demonstration, Grasp,
    PoseFile, Scene, ToolCollider,
};
use graspd::hand::HandModel;
use graspd::tools::{self, Category, Split};
use nalgebra::Isometry3;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum DemoCommand {
    /// Closes the open hand at a wrist pose onto the canonical tool until every
    /// finger touches it, checks contact and penetration, and writes the demonstration.
    Author {
        #[arg(long)]
        category: String,
        /// Wrist (palm) pose in the canonical tool frame: "x y z qx qy qz qw" (metres, unit quaternion).
        #[arg(long, allow_hyphen_values = true)]
        wrist: String,
        /// Where to write it (default: assets/demos/CATEGORY.json).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Actuated joints to close toward, "q0 q1 ..." (default: each joint's limit away from the open hand).
        #[arg(long, allow_hyphen_values = true)]
        closed: Option<String>,
        /// Fingers allowed to stay off the tool, comma separated (e.g. "lf").
        #[arg(long, value_delimiter = ',')]
        free: Vec<String>,
        /// Contact threshold, millimetres.
        #[arg(long, default_value_t = 3.0)]
        contact_mm: f64,
        /// Largest allowed penetration, millimetres.
        #[arg(long, default_value_t = 1.0)]
        max_penetration_mm: f64,
        /// No table: by default the tool rests on the plane z = 0 of its canonical frame.
        #[arg(long)]
        no_table: bool,
        /// Check and print, but write nothing.
        #[arg(long)]
        dry_run: bool,
        #[command(flatten)]
        hand: HandArgs,
        #[arg(long)]
        json: bool,
    },
    /// Validates a demonstration file (e.g. recorded with a data glove): format,
    /// hand, joint limits, keypoints against its own grasp, contact and penetration on the canonical tool.
    Check {
        #[arg(long)]
        file: PathBuf,
        /// Tool category (default: the part of the file's "tool" before '/').
        #[arg(long)]
        category: Option<String>,
        /// Fingers allowed to stay off the tool, comma separated (default: the file's `free_fingers`).
        #[arg(long, value_delimiter = ',')]
        free: Vec<String>,
        #[arg(long, default_value_t = 3.0)]
        contact_mm: f64,
        #[arg(long, default_value_t = 1.0)]
        max_penetration_mm: f64,
        /// Largest allowed distance of the file's keypoints to its grasp's own, millimetres.
        #[arg(long, default_value_t = 1.0)]
        max_keypoint_mismatch_mm: f64,
        /// No table, even where the file says it was made with one (`"table": true`, the default).
        #[arg(long)]
        no_table: bool,
        #[command(flatten)]
        hand: HandArgs,
        #[arg(long)]
        json: bool,
    },
}

/// Parses "x y z qx qy qz qw" (spaces or commas) into a pose.
pub fn parse_pose(s: &str) -> Result<Isometry3<f64>, String> {
    let v = parse_numbers(s)?;
    let [x, y, z, qx, qy, qz, qw] = v[..] else {
        return Err(format!("pose {s:?}: expected 7 numbers \"x y z qx qy qz qw\", got {}", v.len()));
    };
    PoseFile { translation: [x, y, z], rotation_xyzw: [qx, qy, qz, qw] }
        .to_isometry()
        .map_err(|e| format!("pose {s:?}: {e}"))
}

/// Numbers separated by spaces and/or commas.
pub fn parse_numbers(s: &str) -> Result<Vec<f64>, String> {
    s.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .map(|t| t.parse::<f64>().map_err(|e| format!("{t:?} in {s:?}: {e}")))
        .collect()
}

/// The canonical instance's mesh and the scene (tool at the canonical pose,
/// table at z = 0 unless disabled).
fn canonical_collider(category: Category) -> Result<ToolCollider, Box<dyn std::error::Error>> {
    let canonical = tools::family(category)?
        .into_iter()
        .find(|i| i.split == Split::Canonical)
        .ok_or("the family has no canonical instance")?;
    Ok(ToolCollider::new(&canonical.mesh, Isometry3::identity())?)
}

fn check_json(check: &DemoCheck) -> serde_json::Value {
    serde_json::json!({
        "ok": check.ok(),
        "problems": check.problems,
        "fingers": check.fingers,
        "palm_clearance_mm": check.palm_clearance_mm,
        "table_clearance_mm": check.table_clearance_mm,
        "penetration_mm": check.penetration_mm,
        "keypoint_mismatch_mm": check.keypoint_mismatch_mm,
    })
}

fn print_check(check: &DemoCheck) {
    for f in &check.fingers {
        println!(
            "  {:<3} clearance {:>7.2} mm (tip {:>7.2} mm) {}",
            f.finger,
            f.clearance_mm,
            f.tip_clearance_mm,
            if f.contact { "contact" } else { "free" }
        );
    }
    println!("  palm clearance {:.2} mm, penetration {:.2} mm", check.palm_clearance_mm, check.penetration_mm);
    if let Some(t) = check.table_clearance_mm {
        println!("  table clearance {t:.2} mm");
    }
    for p in &check.problems {
        println!("  problem: {p}");
    }
}

fn joints_json(hand: &HandModel, grasp: &Grasp) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    for (name, q) in hand.actuated_names().zip(&grasp.actuated) {
        m.insert(name.to_owned(), serde_json::json!(q));
    }
    serde_json::Value::Object(m)
}

pub fn run(cmd: DemoCommand) -> CliResult {
    let hand = match &cmd {
        DemoCommand::Author { hand, .. } | DemoCommand::Check { hand, .. } => hand.load()?,
    };
    match cmd {
        DemoCommand::Author {
            category,
            wrist,
            out,
            closed,
            free,
            contact_mm,
            max_penetration_mm,
            no_table,
            dry_run,
            hand: _,
            json,
        } => {
            let category: Category = category.parse()?;
            let wrist = parse_pose(&wrist)?;
            let collider = canonical_collider(category)?;
            let scene = Scene { tool: Some(&collider), table_height_world: (!no_table).then_some(0.0) };
            let close_opts =
                CloseOptions { closed: closed.as_deref().map(parse_numbers).transpose()?, ..CloseOptions::default() };
            let closed = close_until_contact(&hand, &wrist, &scene, &close_opts)?;
            let mut demo = Demonstration::new(
                &hand,
                &format!("{}/canonical", category.name()),
                &closed.grasp,
                &Isometry3::identity(),
            );
            demo.table = !no_table;
            demo.free_fingers = free.clone();
            let check_opts =
                DemoCheckOptions { contact_mm, max_penetration_mm, free_fingers: free, ..Default::default() };
            let keypoints = demo.keypoints(&hand)?;
            let check = check_demonstration(&hand, &closed.grasp, &keypoints, &scene, &check_opts)?;
            let path = out.unwrap_or_else(|| Demonstration::builtin_path(category));
            let written = check.ok() && !dry_run;
            if written {
                if let Some(dir) = path.parent() {
                    std::fs::create_dir_all(dir)?;
                }
                std::fs::write(&path, serde_json::to_string_pretty(&demo)? + "\n")?;
            }
            if json {
                let mut v = check_json(&check);
                v["category"] = serde_json::json!(category.name());
                v["wrist_pose"] = serde_json::json!(demo.wrist_pose_tool);
                v["actuated"] = joints_json(&hand, &closed.grasp);
                v["in_contact"] = serde_json::json!(hand
                    .actuated_names()
                    .zip(&closed.in_contact)
                    .map(|(n, c)| (n.to_owned(), *c))
                    .collect::<std::collections::BTreeMap<_, _>>());
                v["out"] = serde_json::json!(written.then(|| path.display().to_string()));
                print_json(&v)?;
            } else {
                println!("{} demonstration, joints {:?}", category.name(), closed.grasp.actuated);
                print_check(&check);
                if written {
                    println!("wrote {}", path.display());
                }
            }
            if !check.ok() {
                return Err(format!("demonstration refused: {}", check.problems.join("; ")).into());
            }
        }
        DemoCommand::Check {
            file,
            category,
            free,
            contact_mm,
            max_penetration_mm,
            max_keypoint_mismatch_mm,
            no_table,
            hand: _,
            json,
        } => {
            let demo = Demonstration::load(&file)?;
            let category: Category = match category {
                Some(c) => c.parse()?,
                None => demo.tool.split('/').next().unwrap_or_default().parse().map_err(|e| {
                    format!("{e}; the file's tool is {:?}: name the category with --category", demo.tool)
                })?,
            };
            if demo.hand != hand.name() {
                return Err(
                    format!("the demonstration was made with hand `{}`, not `{}`", demo.hand, hand.name()).into()
                );
            }
            let grasp = demo.grasp_at(&hand, &Isometry3::identity())?;
            let keypoints = demo.keypoints(&hand)?;
            let collider = canonical_collider(category)?;
            // The file's own scene and free fingers, unless the command line says more.
            let table = demo.table && !no_table;
            let scene = Scene { tool: Some(&collider), table_height_world: table.then_some(0.0) };
            let free = if free.is_empty() { demo.free_fingers.clone() } else { free };
            let check_opts = DemoCheckOptions {
                contact_mm,
                max_penetration_mm,
                free_fingers: free,
                max_keypoint_mismatch_mm,
                ..Default::default()
            };
            let check = check_demonstration(&hand, &grasp, &keypoints, &scene, &check_opts)?;
            if json {
                let mut v = check_json(&check);
                v["category"] = serde_json::json!(category.name());
                v["file"] = serde_json::json!(file.display().to_string());
                print_json(&v)?;
            } else {
                println!("{}: {} demonstration", file.display(), category.name());
                print_check(&check);
                println!("{}", if check.ok() { "ok" } else { "REFUSED" });
            }
            if !check.ok() {
                return Err(format!("demonstration refused: {}", check.problems.join("; ")).into());
            }
        }
    }
    Ok(())
}
