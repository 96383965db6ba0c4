use super::space::spaces_dir;
use super::{print_json, CliResult};
use clap::Args;
use graspd::grasp::transfer::is_z_up;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::Category;
use std::path::PathBuf;

#[derive(Args)]
pub struct RegisterArgs {
    #[arg(long)]
    category: String,
    /// Segmented partial cloud of one tool (.ply, .pcd, .xyz, .npy), metres.
    #[arg(long)]
    cloud: PathBuf,
    #[command(flatten)]
    view: ViewArgs,
    /// The tool rests on a table whose top is at this z (cloud frame, z up,
    /// metres): the registration holds the tool's lowest point on it.
    #[arg(long, allow_hyphen_values = true)]
    table_z: Option<f64>,
    /// Write the completed shape (cloud frame) here.
    #[arg(long)]
    shape_out: Option<PathBuf>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    json: bool,
}

/// Where the cloud was seen from: the priors a registration takes from the set-up.
#[derive(Args)]
pub struct ViewArgs {
    /// World up in the cloud's frame, "x,y,z" (default: z up); "none" when unknown
    /// (`graspd grasp` then puts no table under the tool).
    #[arg(long, default_value = "0,0,1")]
    up: String,
    /// The camera's position in the cloud's frame, "x,y,z" ("0,0,0" for a cloud in
    /// the camera frame): model points facing away from it are not expected in the view.
    /// Without it one is estimated from the view when the view settles it
    /// (`estimated_viewpoint` in the JSON); giving it is more accurate.
    #[arg(long, allow_hyphen_values = true)]
    viewpoint: Option<String>,
    /// With --viewpoint, a second camera's position in the cloud's frame,
    /// "x,y,z", when the cloud merges two cameras' views (a second look at
    /// the tool): model points facing it are expected in the view too.
    #[arg(long, allow_hyphen_values = true, requires = "viewpoint")]
    second_viewpoint: Option<String>,
}

/// The up direction and the cameras' positions, each when known.
pub struct SetUp {
    pub up: Option<[f64; 3]>,
    pub viewpoint: Option<[f64; 3]>,
    pub second_viewpoint: Option<[f64; 3]>,
}

impl ViewArgs {
    /// The set-up, parsed.
    pub fn parse(&self) -> Result<SetUp, String> {
        let vec3 = |flag: &str, v: &Option<String>| v.as_deref().map(|v| parse_vec3(flag, v)).transpose();
        Ok(SetUp {
            up: parse_up(&self.up)?,
            viewpoint: vec3("--viewpoint", &self.viewpoint)?,
            second_viewpoint: vec3("--second-viewpoint", &self.second_viewpoint)?,
        })
    }
}

/// The registration's support plane from `--table-z`: a table top at z in
/// a z-up cloud frame (the plane across `up`).
pub fn support_height(up: Option<[f64; 3]>, table_z: Option<f64>) -> Result<Option<f64>, String> {
    let Some(z) = table_z else { return Ok(None) };
    if !z.is_finite() {
        return Err(format!("--table-z {z} is not finite"));
    }
    if is_z_up(up) {
        Ok(Some(z))
    } else {
        Err("--table-z needs a z-up cloud frame (--up 0,0,1)".to_owned())
    }
}

fn parse_up(s: &str) -> Result<Option<[f64; 3]>, String> {
    if s.eq_ignore_ascii_case("none") {
        return Ok(None);
    }
    let v = parse_vec3("--up", s)?;
    if v.iter().map(|a| a * a).sum::<f64>() <= 1e-12 {
        return Err(format!("--up {s:?}: a direction cannot be zero (or say \"none\")"));
    }
    Ok(Some(v))
}

/// Three finite numbers separated by commas and/or spaces.
fn parse_vec3(flag: &str, s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|x| !x.is_empty())
        .map(|x| x.parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{flag} {s:?}: {e}"))?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|a| a.is_finite()) => Ok([*x, *y, *z]),
        _ => Err(format!("{flag} {s:?}: expected three finite numbers")),
    }
}

pub fn run(a: RegisterArgs) -> CliResult {
    let category: Category = a.category.parse()?;
    let cloud = graspd::io::read_cloud(&a.cloud)?;
    let space = builtin::load_or_build(category, &spaces_dir(), |_, _| {})?;
    let registrar = Registrar::new(space);
    let SetUp { up, viewpoint, second_viewpoint } = a.view.parse()?;
    let support_height = support_height(up, a.table_z)?;
    let opts = RegisterOptions { up, viewpoint, second_viewpoint, support_height, seed: a.seed, ..Default::default() };
    let reg = registrar.register(&cloud, &opts)?;
    if let Some(p) = &a.shape_out {
        graspd::io::write_cloud(p, &registrar.completed_shape(&reg))?;
    }
    let q = reg.rotation_cloud_from_canonical.coords;
    let out = serde_json::json!({
        "category": category.name(),
        "points": cloud.len(),
        "latent": reg.latent,
        "pose": {
            "frame": "cloud_from_canonical",
            "translation": reg.translation_cloud_from_canonical.as_slice(),
            "rotation_xyzw": [q.x, q.y, q.z, q.w],
        },
        "scale": reg.scale,
        "sigma2": reg.sigma2,
        "fit": reg.fit,
        "keypoints": reg.keypoints,
        "hypotheses": reg.hypotheses,
        "iterations": reg.iterations,
        "elapsed_ms": reg.elapsed_ms,
        "stage_ms": reg.stage_ms,
        // The camera position assumed when --viewpoint was not given (null: none used).
        "estimated_viewpoint": reg.estimated_viewpoint,
        // The table a leaking segmentation showed, when none was given (null: none found).
        "found_table_height": reg.found_table_height,
        "yaw_arc": yaw_arc_json(&reg),
    });
    if a.json {
        print_json(&out)?;
    } else {
        println!(
            "{}: scale {:.3}, inliers {:.1}%, residual {:.2} mm, {}{} ({:.1} ms)",
            category.name(),
            reg.scale,
            reg.fit.inlier_fraction * 100.0,
            reg.fit.residual_mm,
            if reg.fit.confident { "confident" } else { "POOR FIT" },
            if reg.fit.ambiguous_pose { ", AMBIGUOUS POSE" } else { "" },
            reg.elapsed_ms
        );
        if let Some(c) = reg.fit.contradicted_fraction {
            // Clean views of a right fit: a few percent (see `FitQuality::contradicted_fraction`).
            println!(
                "  the view contradicts {:.1}% of the fitted shape's camera-facing surface{}",
                c * 100.0,
                if c > 0.08 { ": something in front of the tool hid part of it, or the fit is wrong" } else { "" }
            );
        }
        let spread = reg.keypoint_spread_m().unwrap_or_default();
        if let Some(arc) = reg.yaw_arc.filter(|a| a.half_width_rad > 0.0) {
            println!(
                "  the view leaves the turn about the tool's axis open by ±{:.0}°: spread per keypoint below",
                arc.half_width_rad.to_degrees()
            );
        }
        for (i, k) in reg.keypoints.iter().enumerate() {
            let s = spread.get(i).filter(|s| **s > 0.0).map_or(String::new(), |s| format!("  ±{:.0} mm", s * 1e3));
            println!("  {:<16} {:>9.4} {:>9.4} {:>9.4}{s}", k.name, k.position[0], k.position[1], k.position[2]);
        }
    }
    Ok(())
}

/// The registration's yaw arc for the JSON: the axis, the half width and how
/// far each keypoint moves across it (`keypoints` order); null without one.
pub(crate) fn yaw_arc_json(reg: &graspd::shape::Registration) -> serde_json::Value {
    match (reg.yaw_arc, reg.keypoint_spread_m()) {
        (Some(arc), Some(spread)) => serde_json::json!({
            "axis_cloud": arc.axis_cloud,
            "half_width_rad": arc.half_width_rad,
            "keypoint_spread_m": spread,
        }),
        _ => serde_json::Value::Null,
    }
}
