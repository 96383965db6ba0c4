//! Calibration of the fit-quality rule: the inlier fraction, at several
//! radii, of real YCB scans and of the procedural test tools registered to
//! their own category and to the other two, and the share of views called
//! confident. `cargo run --release --example confidence_scan [VIEWS]`;
//! NOISY=1 takes the views with 2 mm depth noise and 10 % outliers.
use graspd::eval::transfer::add_outliers;
use graspd::eval::ycb::ycb_mesh_path;
use graspd::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use graspd::geometry::TriMesh;
use graspd::shape::cpd::to_p3;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::{Category, Split};
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Isometry3, Point3};
use rand::SeedableRng;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let views: usize = std::env::args().nth(1).map_or(Ok(8), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    let cats = [Category::Mug, Category::Drill, Category::Hammer];
    let registrars: Vec<Registrar> = cats
        .iter()
        .map(|&c| builtin::load_or_build(c, &root, |_, _| {}).map(Registrar::new))
        .collect::<Result<_, _>>()?;
    let noisy = std::env::var("NOISY").is_ok_and(|v| v == "1");
    let noise = if noisy { DepthNoise { sigma_m: 0.002, ..DepthNoise::default() } } else { DepthNoise::default() };
    let mut objects: Vec<(String, Category, TriMesh)> = Vec::new();
    for &c in &cats {
        match graspd::io::read_mesh(ycb_mesh_path(&data, c)) {
            Ok(m) => objects.push((format!("YCB {}", c.name()), c, m.mesh)),
            Err(e) => eprintln!("skipping the YCB {} scan: {e}", c.name()),
        }
    }
    for &c in &cats {
        for inst in graspd::tools::family(c)?.into_iter().filter(|i| i.split == Split::Test) {
            objects.push((inst.name.clone(), c, inst.mesh));
        }
    }
    let radii = [0.004, 0.006, 0.008, 0.010];
    for (name, object, mesh) in &objects {
        let (lo, hi) = mesh.aabb().ok_or("empty mesh")?;
        let centre = Point3::from((lo.coords + hi.coords) / 2.0);
        let scene = Scene::new(mesh, Isometry3::identity(), Some(lo.z))?;
        for (ci, &category) in cats.iter().enumerate() {
            let mut rows: Vec<Vec<f64>> = Vec::new();
            let (mut base, mut confident) = (Vec::new(), 0);
            for view in 0..views {
                let pose = standard_view(view, views, centre, mesh.diagonal(), Intrinsics::default())?;
                let cam = DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise };
                let mut cloud = cam.capture(&scene, view as u64)?.points_world;
                if noisy {
                    add_outliers(&mut cloud, 0.1, &mut rand_chacha::ChaCha8Rng::seed_from_u64(view as u64));
                }
                let reg =
                    registrars[ci].register(&cloud, &RegisterOptions { seed: view as u64, ..Default::default() })?;
                base.push(reg.fit.inlier_fraction);
                confident += reg.fit.confident as usize;
                let shape = to_p3(&registrars[ci].completed_shape(&reg));
                let tree: ImmutableKdTree<f64, u32, 3, 32> = ImmutableKdTree::new_from_slice(&shape);
                let d: Vec<f64> = cloud
                    .iter()
                    .map(|p| tree.nearest_one::<SquaredEuclidean>(&[p.x, p.y, p.z]).distance.sqrt())
                    .collect();
                rows.push(
                    radii.iter().map(|r| d.iter().filter(|&&x| x <= *r).count() as f64 / d.len() as f64).collect(),
                );
            }
            let mean = |i: usize| rows.iter().map(|r| r[i]).sum::<f64>() / rows.len() as f64;
            let min = |i: usize| rows.iter().map(|r| r[i]).fold(1.0, f64::min);
            let max = |i: usize| rows.iter().map(|r| r[i]).fold(0.0, f64::max);
            let (lo_b, hi_b) = (base.iter().copied().fold(1.0, f64::min), base.iter().copied().fold(0.0, f64::max));
            print!(
                "{:>14} {} as {:>6}: reported {:.2} [{lo_b:.2}, {hi_b:.2}], confident {confident}/{views}",
                name,
                if *object == category { "(own)  " } else { "(other)" },
                category.name(),
                base.iter().sum::<f64>() / base.len() as f64
            );
            for (i, r) in radii.iter().enumerate() {
                print!(" | {:.0} mm {:.2} [{:.2}, {:.2}]", r * 1e3, mean(i), min(i), max(i));
            }
            println!();
        }
    }
    Ok(())
}
