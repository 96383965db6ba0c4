//! graspd's side of the registration peer benchmark (`bench/register_peer.sh`):
//! writes a category's shape model as a plain statistical shape model (mean
//! points, modes, prior variances, in the canonical frame, metres) and the
//! test views of `bench_register` (2,000 points each, with their ground-truth
//! keypoints), and times graspd's registration on those views, so that a peer
//! fits the same model to the same clouds in the same run.
//!
//! `cargo run --release --example register_peer -- CATEGORY OUT_DIR [REPEATS]`
//! writes OUT_DIR/CATEGORY.json.
#[path = "common/views.rs"]
mod views;

use graspd::geometry::farthest_point_order;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::Category;
use serde_json::json;

/// The model the peer fits: the densest level of graspd's own fit (its
/// polish: 800 farthest-point samples of the canonical surface).
const MODEL_POINTS: usize = 800;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(category), Some(out_dir)) = (args.get(1), args.get(2)) else {
        return Err("usage: register_peer CATEGORY OUT_DIR [REPEATS]".into());
    };
    let category: Category = category.parse()?;
    let repeats: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let registrar = Registrar::new(builtin::load_or_build(category, &root, |_, _| {})?);
    let space = &registrar.space;
    let norm = space.norm;

    // y(ℓ) = mean + Σ ℓ_j mode_j in the canonical frame (metres); the prior of
    // ℓ_j is N(0, variances_j), as in graspd's own fit.
    let canonical: Vec<[f64; 3]> = space.surface.iter().map(|p| norm.forward(p)).collect();
    let points: Vec<[f64; 3]> =
        farthest_point_order(&canonical, MODEL_POINTS).into_iter().map(|i| space.surface[i]).collect();
    let metres = |z: &[[f64; 3]]| {
        let m = space.linear_model(z);
        let mean: Vec<[f64; 3]> = m.base.iter().map(|p| norm.inverse(p)).collect();
        let modes: Vec<Vec<f64>> =
            m.basis.iter().map(|b| b.iter().flat_map(|d| d.map(|v| v * norm.scale)).collect()).collect();
        (mean, modes)
    };
    let (mean, modes) = metres(&points);
    let kp: Vec<[f64; 3]> = space.keypoints.iter().map(|k| k.position).collect();
    let (kp_mean, kp_modes) = metres(&kp);

    let views = views::test_views(category)?;
    let mut ours = serde_json::Map::new();
    for known_viewpoint in [false, true] {
        let mut fits = Vec::new();
        for view in &views {
            let opts =
                RegisterOptions { viewpoint: known_viewpoint.then_some(view.viewpoint), ..RegisterOptions::default() };
            let mut elapsed_ms = Vec::with_capacity(repeats);
            let mut last = None;
            for _ in 0..repeats.max(1) {
                let t0 = std::time::Instant::now();
                let r = registrar.register(&view.cloud, &opts)?;
                elapsed_ms.push(t0.elapsed().as_secs_f64() * 1e3);
                last = Some(r);
            }
            let r = last.expect("at least one repeat");
            let keypoints: Vec<[f64; 3]> = r.keypoints.iter().map(|k| k.position).collect();
            fits.push(json!({
                "elapsed_ms": elapsed_ms,
                "keypoints": keypoints,
                "confident": r.fit.confident,
                "ambiguous_pose": r.fit.ambiguous_pose,
            }));
        }
        ours.insert(if known_viewpoint { "viewpoint_known" } else { "viewpoint_unknown" }.into(), fits.into());
    }

    let out = json!({
        "category": category.name(),
        "model": {
            "mean": mean,
            "modes": modes,
            "eigenvalues": space.variances,
            "keypoint_names": space.keypoints.iter().map(|k| k.name.clone()).collect::<Vec<_>>(),
            "keypoint_mean": kp_mean,
            "keypoint_modes": kp_modes,
        },
        "views": views.iter().map(|v| json!({
            "cloud": v.cloud.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
            "viewpoint": v.viewpoint,
            "keypoints": v.keypoints_world,
        })).collect::<Vec<_>>(),
        "ours": ours,
    });
    std::fs::create_dir_all(out_dir)?;
    let path = std::path::Path::new(out_dir).join(format!("{}.json", category.name()));
    std::fs::write(&path, serde_json::to_vec(&out)?)?;
    eprintln!("wrote {}", path.display());
    Ok(())
}
