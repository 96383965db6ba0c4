//! One view of `graspd eval transfer`, again, from the fields its trace
//! prints under "to reproduce" (`GRASPD_EVAL_TRACE=1`), registered with the
//! eval's options and `GRASPD_REGISTER_TRACE` honoured:
//! `cargo run --release --example repro_view -- CATEGORY INSTANCE VIEW VIEWS
//! YAW X Y CAPTURE_SEED REGISTER_SEED [REGISTER_OPTIONS_JSON]`, the JSON
//! laid over the default options.
//! Upright tools, scale 1, the camera's position known (the eval's defaults).
//! `SECOND_VIEW_SEED=N`: merged with the second view of `--second-view`,
//! captured with seed N (the trace's "second view's capture seed").
use graspd::eval::transfer::Placement;
use graspd::geometry::camera::DepthNoise;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::{self, Category};
use nalgebra::Point3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    if a.len() < 9 {
        return Err(
            "usage: repro_view CATEGORY INSTANCE VIEW VIEWS YAW X Y CAPTURE_SEED REGISTER_SEED [OPTIONS_JSON]".into()
        );
    }
    let category: Category = a[0].parse()?;
    let (view, views): (usize, usize) = (a[2].parse()?, a[3].parse()?);
    let (yaw, x, y): (f64, f64, f64) = (a[4].parse()?, a[5].parse()?, a[6].parse()?);
    let (capture_seed, register_seed): (u64, u64) = (a[7].parse()?, a[8].parse()?);
    // Laid over the defaults, field by field.
    let mut base = serde_json::to_value(RegisterOptions::default())?;
    if let Some(json) = a.get(9) {
        let over: serde_json::Map<String, serde_json::Value> = serde_json::from_str(json)?;
        for (k, v) in over {
            base[k] = v;
        }
    }
    let base: RegisterOptions = serde_json::from_value(base)?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let registrar = Registrar::new(builtin::load_or_build(category, &root, |_, _| {})?);
    let inst = tools::instance(category, &a[1])?;
    let placed = Placement::upright(yaw, [x, y])
        .place(&inst.mesh, view, views, DepthNoise::default())
        .ok_or("the view cannot be placed")?;
    let mut cloud = placed.capture(capture_seed).ok_or("the camera sees nothing")?;
    if let Ok(seed) = std::env::var("SECOND_VIEW_SEED") {
        let second = Placement::upright(yaw, [x, y])
            .second_view(&inst.mesh, view, views, DepthNoise::default())
            .ok_or("the second view cannot be placed")?;
        cloud.extend(second.capture(seed.parse()?).ok_or("the second camera sees nothing")?);
    }
    let (pose, rot) = (placed.world_from_tool, placed.world_from_tool.rotation);
    let opts =
        RegisterOptions { seed: register_seed, viewpoint: Some(placed.viewpoint()), support_height: Some(0.0), ..base };
    let r = registrar.register(&cloud, &opts)?;
    let rot_err = (r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees();
    let kp_err: Vec<f64> = r
        .keypoints
        .iter()
        .zip(&inst.keypoints)
        .map(|(k, truth)| {
            let t = pose * Point3::from(truth.position);
            (Point3::from(k.position) - t).norm() * 1e3
        })
        .collect();
    println!(
        "{} points, rotation error {rot_err:.1}°, yaw arc {:?}, ambiguous {}, keypoint errors {:.1?} mm",
        cloud.len(),
        r.yaw_arc.map(|a| a.half_width_rad.to_degrees()),
        r.fit.ambiguous_pose,
        kp_err
    );
    Ok(())
}
