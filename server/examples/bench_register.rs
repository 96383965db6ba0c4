//! Registration time per stage on the test views of one category (the
//! 2,000-point target of the shape-engine issue is a subsample of these).
//! `cargo run --release --example bench_register -- mug [repeats]`; set
//! VIEWPOINT=known or VIEWPOINT=unknown to time one of the two cases only;
//! REGISTER_OPTIONS='{"race_points": 300}' lays options over the defaults.
use graspd::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::{self, Category, Split};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let category: Category = args.get(1).map_or("mug", |s| s.as_str()).parse()?;
    let repeats: usize = args.get(2).map_or(Ok(20), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let registrar = Registrar::new(builtin::load_or_build(category, &root, |_, _| {})?);
    let family = tools::family(category)?;
    let mut views = Vec::new();
    for inst in family.iter().filter(|i| i.split == Split::Test) {
        for view in 0..8 {
            let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7 * view as f64);
            let zmin = inst.mesh.vertices.iter().map(|p| (rot * p).z).fold(f64::INFINITY, f64::min);
            let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, -zmin), rot);
            let scene = Scene::new(&inst.mesh, pose, Some(0.0))?;
            let (lo, hi) = inst.mesh.aabb().ok_or("empty mesh")?;
            let centre = pose * Point3::from((lo.coords + hi.coords) / 2.0);
            let intrinsics = Intrinsics::default();
            let cam_pose = standard_view(view, 8, centre, inst.mesh.diagonal(), intrinsics)?;
            let cam = DepthCamera { intrinsics, world_from_camera: cam_pose, noise: DepthNoise::default() };
            let cloud = cam.capture(&scene, view as u64)?.points_world;
            // The target is stated for 2,000-point views.
            let cloud: Vec<_> = cloud.iter().step_by((cloud.len() / 2000).max(1)).copied().collect();
            let t = cam_pose.translation.vector;
            views.push((cloud, [t.x, t.y, t.z]));
        }
    }
    let mut base = serde_json::to_value(RegisterOptions::default())?;
    if let Ok(over) = std::env::var("REGISTER_OPTIONS") {
        let over: serde_json::Map<String, serde_json::Value> = serde_json::from_str(&over)?;
        for (k, v) in over {
            base[k] = v;
        }
    }
    let base: RegisterOptions = serde_json::from_value(base)?;
    let modes: &[bool] = match std::env::var("VIEWPOINT").as_deref() {
        Ok("known") => &[true],
        Ok("unknown") => &[false],
        _ => &[false, true],
    };
    for &known_viewpoint in modes {
        let mut total = Vec::new();
        let mut iterations = 0usize;
        let mut stages = [Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new()];
        for _ in 0..repeats {
            for (cloud, vp) in &views {
                let opts = RegisterOptions { viewpoint: known_viewpoint.then_some(*vp), ..base };
                let t0 = std::time::Instant::now();
                let r = registrar.register(cloud, &opts)?;
                total.push(t0.elapsed().as_secs_f64() * 1e3);
                iterations += r.iterations;
                let s = r.stage_ms;
                for (v, x) in stages.iter_mut().zip([s.coarse, s.race, s.refine, s.polish, s.quality]) {
                    v.push(x);
                }
            }
        }
        let pct = |v: &mut Vec<f64>, q: f64| {
            v.sort_by(f64::total_cmp);
            v[((v.len() - 1) as f64 * q).round() as usize]
        };
        println!(
            "{} viewpoint {}: {} fits, total p50 {:.2} ms p99 {:.2} ms; stage p50 coarse {:.2} race {:.2} refine {:.2} polish {:.2} quality {:.2} ms; {:.1} EM iterations a fit",
            category.name(),
            if known_viewpoint { "known  " } else { "unknown" },
            total.len(),
            pct(&mut total.clone(), 0.5),
            pct(&mut total, 0.99),
            pct(&mut stages[0], 0.5),
            pct(&mut stages[1], 0.5),
            pct(&mut stages[2], 0.5),
            pct(&mut stages[3], 0.5),
            pct(&mut stages[4], 0.5),
            iterations as f64 / (repeats * views.len()) as f64,
        );
    }
    Ok(())
}
