//! Behaviour and accuracy of the shape engine on the built-in families.
//! Thresholds sit above the figures measured by `graspd eval transfer`
//! (see the issue notes), so a regression fails here.

use super::builtin;
use super::cpd::{self, EmOptions, RigidOptions};
use super::register::RegisterError;
use super::space::ShapeSpace;
use super::{RegisterOptions, Registrar};
use crate::eval::transfer::Placement;
use crate::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use crate::geometry::sample_points;
use crate::tools::{self, Category, Split};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::SeedableRng;
use std::sync::OnceLock;

fn mug_space() -> &'static ShapeSpace {
    static SPACE: OnceLock<ShapeSpace> = OnceLock::new();
    SPACE.get_or_init(|| {
        builtin::build(Category::Mug, &builtin::options(Category::Mug), |_, _| {}).expect("mug space builds").0
    })
}

pub(super) fn mug_registrar() -> &'static Registrar {
    static REG: OnceLock<Registrar> = OnceLock::new();
    REG.get_or_init(|| Registrar::new(mug_space().clone()))
}

fn hammer_registrar() -> &'static Registrar {
    static REG: OnceLock<Registrar> = OnceLock::new();
    REG.get_or_init(|| {
        Registrar::new(
            builtin::build(Category::Hammer, &builtin::options(Category::Hammer), |_, _| {})
                .expect("hammer space builds")
                .0,
        )
    })
}

/// A tool standing on the table at `yaw`, off the origin.
fn on_table(yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(0.05, -0.03, 0.0), UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw))
}

/// `mesh` lying on its side (turned 90° about its x axis) at `yaw`, its
/// lowest point on the table (z = 0).
fn on_side(mesh: &crate::geometry::TriMesh, yaw: f64) -> Isometry3<f64> {
    let side = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2);
    let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * side;
    let zmin = mesh.vertices.iter().map(|p| (rot * p).z).fold(f64::INFINITY, f64::min);
    Isometry3::from_parts(Translation3::new(0.02, 0.04, -zmin), rot)
}

/// The middle value (the upper of the two for an even count).
fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// One noisy view of `mesh` placed at `yaw` on a table.
pub(super) fn view_of(mesh: &crate::geometry::TriMesh, yaw: f64, view: usize) -> (Vec<Point3<f64>>, Isometry3<f64>) {
    let pose = on_table(yaw);
    (capture(mesh, &pose, pose * Point3::new(0.0, 0.0, 0.05), view, 3).0, pose)
}

/// A noisy view (`view` of 8 around `centre`) of `mesh` at `pose` on a table,
/// and the camera's pose.
fn capture(
    mesh: &crate::geometry::TriMesh,
    pose: &Isometry3<f64>,
    centre: Point3<f64>,
    view: usize,
    seed: u64,
) -> (Vec<Point3<f64>>, Isometry3<f64>) {
    capture_with(mesh, pose, centre, view, seed, DepthNoise::default())
}

/// As `capture`, with the camera's noise given.
fn capture_with(
    mesh: &crate::geometry::TriMesh,
    pose: &Isometry3<f64>,
    centre: Point3<f64>,
    view: usize,
    seed: u64,
    noise: DepthNoise,
) -> (Vec<Point3<f64>>, Isometry3<f64>) {
    let scene = Scene::new(mesh, *pose, Some(0.0)).unwrap();
    let cam_pose = standard_view(view, 8, centre, mesh.diagonal(), Intrinsics::default()).unwrap();
    let cam = DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: cam_pose, noise };
    (cam.capture(&scene, seed).unwrap().points_world, cam_pose)
}

#[test]
fn shape_space_is_compact_and_reproduces_training_keypoints() {
    let space = mug_space();
    // At most one mode fewer than training instances; kept by explained variance.
    assert!((2..space.instances.len()).contains(&space.modes()), "{} modes", space.modes());
    let ev = &space.explained_variance;
    assert!(ev.windows(2).all(|w| w[0] <= w[1]) && ev.len() == space.modes(), "explained variance {ev:?}");
    assert!(space.explained_variance[0] > 0.5, "first mode explains {:?}", space.explained_variance);
    let family = tools::family(Category::Mug).unwrap();
    let kp: Vec<[f64; 3]> = space.keypoints.iter().map(|k| k.position).collect();
    let mut errs = Vec::new();
    for (inst, latent) in family.iter().filter(|i| i.split == Split::Train).zip(&space.train_latents) {
        for (a, b) in space.deform(&kp, latent).iter().zip(&inst.keypoints) {
            errs.push(super::estep::dist2(a, &b.position).sqrt() * 1e3);
        }
    }
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    assert!(median < 5.0, "median keypoint error at the training latents {median:.1} mm");
}

#[test]
fn artefact_round_trips_and_refuses_corruption() {
    let space = mug_space();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mug.gspace");
    space.save(&path).unwrap();
    let back = ShapeSpace::load(&path).unwrap();
    assert_eq!(back.mean, space.mean);
    assert_eq!(back.modes, space.modes);

    let bytes = std::fs::read(&path).unwrap();
    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x20;
    assert!(ShapeSpace::from_bytes(&flipped).unwrap_err().contains("checksum"));
    assert!(ShapeSpace::from_bytes(&bytes[..bytes.len() - 10]).unwrap_err().contains("truncated"));
    let mut version = bytes.clone();
    version[8] = 99;
    assert!(ShapeSpace::from_bytes(&version).unwrap_err().contains("version 99"));
    assert!(ShapeSpace::from_bytes(b"not an artefact at all, clearly").unwrap_err().contains("magic"));
}

#[test]
fn registers_a_partial_view_of_an_unseen_mug() {
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let mut errs = Vec::new();
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let (cloud, pose) = view_of(&test.mesh, *yaw, k * 2 + 1);
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        let rot_err = (r.rotation_cloud_from_canonical * pose.rotation.inverse()).angle().to_degrees();
        assert!(r.fit.confident, "view {k}: {:?}", r.fit);
        assert!(rot_err < 15.0, "view {k}: rotation error {rot_err:.1}°");
        for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
            let truth = pose * Point3::from(t.position);
            errs.push((Vector3::from(p.position) - truth.coords).norm() * 1e3);
        }
    }
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    assert!(median < 10.0, "median keypoint error {median:.1} mm over {errs:?}");
}

/// No step of a registration computes a subnormal number (an f32 or f64
/// below the normal range, or an underflow to zero): Intel cores take a
/// microcode assist for each, about a hundred cycles. An AVX-512 exponential
/// that scaled its cut lanes before masking them made the race 6× slower on
/// a Xeon (27.8 → 4.1 ms, mug) while the Zen 5 this was written on did not
/// show it. The flags are the processor's own, raised on AMD as on Intel.
#[cfg(target_arch = "x86_64")]
#[test]
fn a_registration_computes_no_subnormal_numbers() {
    use crate::simd::{sticky_fp_flags, SUBNORMAL_FLAGS};
    let registrar = mug_registrar(); // built outside the flags' watch
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    for (k, yaw) in [0.4f64, 2.0].iter().enumerate() {
        let pose = on_table(*yaw);
        let (cloud, cam) = capture(&test.mesh, &pose, pose * Point3::new(0.0, 0.0, 0.05), k * 3 + 1, 3);
        for viewpoint in [None, Some(cam.translation.vector.into())] {
            let opts = RegisterOptions { viewpoint, ..RegisterOptions::default() };
            let (r, flags) = sticky_fp_flags(|| {
                // GRASPD_TRAP_SUBNORMALS=1 unmasks the denormal-operand
                // exception: under a debugger the test then stops (SIGFPE)
                // at the instruction that read one.
                let trap = std::env::var_os("GRASPD_TRAP_SUBNORMALS").is_some();
                crate::simd::trap_subnormal_operands(trap);
                let r = registrar.register(&cloud, &opts);
                crate::simd::trap_subnormal_operands(false);
                r
            });
            assert!(r.is_ok());
            assert_eq!(flags & SUBNORMAL_FLAGS, 0, "view {k}, viewpoint {viewpoint:?}: MXCSR flags {flags:#x}");
        }
    }
}

/// A noisy sensor's view of the right tool (2 mm depth noise, 10 %
/// scattered outliers) is a confident fit: the inlier fraction is counted
/// on a uniform sample of the view, not on the fit's even subsample, which
/// takes the scattered points out of proportion (measured on these views:
/// 0.80-0.84; on the fit's subsample 0.62-0.64, none confident).
#[test]
fn a_noisy_view_of_the_right_tool_is_confident() {
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let noise = DepthNoise { sigma_m: 0.002, ..DepthNoise::default() };
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let pose = on_table(*yaw);
        let (mut cloud, _) = capture_with(&test.mesh, &pose, pose * Point3::new(0.0, 0.0, 0.05), k * 2 + 1, 3, noise);
        crate::eval::transfer::add_outliers(&mut cloud, 0.1, &mut rand_chacha::ChaCha8Rng::seed_from_u64(k as u64));
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        assert!(r.fit.confident, "view {k}: {:?}", r.fit);
        assert!(r.fit.stray_points > 0, "view {k}: no stray point set aside: {:?}", r.fit);
    }
}

#[test]
fn another_category_is_a_poor_fit_not_a_confident_one() {
    let reg = mug_registrar();
    let hammer = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let (cloud, _) = view_of(&hammer.mesh, 0.7, 1);
    let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
    assert!(!r.fit.confident, "a hammer fitted as a mug: {:?}", r.fit);
    // A flat patch of table.
    let table: Vec<Point3<f64>> =
        (0..2000).map(|i| Point3::new((i % 50) as f64 * 0.004, (i / 50) as f64 * 0.004, 0.0)).collect();
    let r = reg.register(&table, &RegisterOptions::default()).unwrap();
    assert!(!r.fit.confident, "a table fitted as a mug: {:?}", r.fit);
}

/// Clouds that lie on the surface of almost any shape (every point an
/// inlier) but show nothing of a tool: a line, a blob a few millimetres
/// wide, a few distinct points repeated, one point repeated with 5 %
/// scattered about it (with 0.5 % it has no extent: `bad_clouds_...`).
/// Measured before the coverage and latent rules: all confident, inlier
/// fraction 0.96-1.
#[test]
fn degenerate_clouds_are_not_confident() {
    use rand::{Rng, SeedableRng};
    let reg = mug_registrar();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let mut jitter = |s: f64| (rng.random::<f64>() - 0.5) * s;
    let line: Vec<Point3<f64>> = (0..300).map(|i| Point3::new(i as f64 * 1e-3, 0.0, 0.0)).collect();
    let blob: Vec<Point3<f64>> = (0..500).map(|_| Point3::new(jitter(0.006), jitter(0.006), jitter(0.006))).collect();
    let two: Vec<Point3<f64>> = (0..1000).map(|i| Point3::new(0.1 * (i % 2) as f64, 0.0, 0.0)).collect();
    let clump: Vec<Point3<f64>> =
        (0..2000)
            .map(|i| {
                if i < 1900 {
                    Point3::new(0.05, 0.05, 0.05)
                } else {
                    Point3::new(jitter(0.1), jitter(0.1), jitter(0.1))
                }
            })
            .collect();
    for (name, cloud) in [("line", line), ("blob", blob), ("two points", two), ("clump", clump)] {
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        assert!(!r.fit.confident, "{name}: {:?}", r.fit);
    }
}

#[test]
fn bad_clouds_are_clear_errors() {
    let reg = mug_registrar();
    let opts = RegisterOptions::default();
    assert_eq!(reg.register(&[], &opts).unwrap_err(), RegisterError::Empty);
    let mut nan = vec![Point3::new(0.0, 0.0, 0.01); 100];
    nan.iter_mut().enumerate().for_each(|(i, p)| p.x = i as f64 * 1e-3);
    nan[42].y = f64::INFINITY;
    assert_eq!(reg.register(&nan, &opts).unwrap_err(), RegisterError::NonFinite(42));
    assert!(matches!(reg.register(&nan[..5], &opts).unwrap_err(), RegisterError::TooFewPoints { got: 5, .. }));
    assert_eq!(reg.register(&vec![Point3::new(1.0, 2.0, 3.0); 500], &opts).unwrap_err(), RegisterError::Degenerate);
    // One point repeated but for 0.5 % scattered 10 cm about it.
    let mut clump = vec![Point3::new(0.05, 0.05, 0.05); 1990];
    clump.extend((0..10).map(|i| Point3::new(0.01 * i as f64, 0.1 - 0.01 * i as f64, 0.03)));
    assert_eq!(reg.register(&clump, &opts).unwrap_err(), RegisterError::Degenerate);
    let km: Vec<Point3<f64>> = (0..500).map(|i| Point3::new(i as f64 * 10.0, (i % 7) as f64 * 30.0, 0.0)).collect();
    let e = reg.register(&km, &opts).unwrap_err();
    assert!(matches!(e, RegisterError::AbsurdScale { .. }), "{e}");
    assert!(e.to_string().contains("units"));
}

/// Points far from the tool (a flying pixel on the wall behind it, a leak
/// of the segmentation into the floor, a garbage coordinate) are set aside
/// as strays and change nothing else: the fit is the one of the view
/// without them, to the bit. One point 6 m off made the cloud 6 m across
/// and the request was refused as not a hand-held tool's. A cloud in
/// millimetres is refused whatever its strays.
#[test]
fn far_points_are_strays_not_the_clouds_extent() {
    let reg = mug_registrar();
    let mug = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let (view, _) = view_of(&mug.mesh, 0.7, 1);
    let opts = RegisterOptions::default();
    let plain = reg.register(&view, &opts).unwrap();
    let mut far = view.clone();
    far.extend([
        Point3::new(6.0, 0.5, 1.0),
        Point3::new(0.02, 0.01, -0.3),
        Point3::new(-1e6, 3.0, 0.0),
        Point3::new(0.0, 0.0, -1e30),
    ]);
    let r = reg.register(&far, &opts).unwrap();
    assert_eq!(r.latent, plain.latent);
    assert_eq!(r.rotation_cloud_from_canonical, plain.rotation_cloud_from_canonical);
    assert_eq!(r.translation_cloud_from_canonical, plain.translation_cloud_from_canonical);
    assert_eq!(r.scale, plain.scale);
    assert_eq!(r.fit.stray_points, plain.fit.stray_points + 4);
    assert_eq!(r.lowest_kept_z, plain.lowest_kept_z);
    assert!(plain.fit.confident && r.fit.confident);
    // The view stands on the table z = 0; its lowest points are depth noise.
    assert!(plain.lowest_kept_z.abs() < 0.005, "{}", plain.lowest_kept_z);
    let mm: Vec<Point3<f64>> = far.iter().map(|p| Point3::from(p.coords * 1e3)).collect();
    let e = reg.register(&mm, &opts).unwrap_err();
    assert!(matches!(e, RegisterError::AbsurdScale { extent_m, .. } if extent_m > 100.0), "{e}");
}

#[test]
fn cpd_handles_200k_points_in_linear_memory() {
    let mug = tools::family(Category::Mug).unwrap().remove(0);
    let source = sample_points(&mug.mesh, 1000, 1).unwrap();
    let target = sample_points(&mug.mesh, 200_000, 2).unwrap();
    // The dense M×N posterior alone would be 1.6 GB; ours holds O(M + N).
    let r =
        cpd::rigid(&source, &target, &RigidOptions { em: EmOptions { w: 0.1, max_iters: 60, tol: 1e-6 }, scale: true })
            .unwrap();
    assert!((r.scale - 1.0).abs() < 0.02, "scale {}", r.scale);
    assert!((r.rotation - nalgebra::Matrix3::identity()).norm() < 0.02, "rotation {}", r.rotation);
    assert!(r.translation.norm() < 2e-3, "translation {}", r.translation);
}

#[test]
fn jacobian_determinant_matches_finite_differences() {
    let space = mug_space();
    let latent = &space.train_latents[3];
    let h = 1e-5;
    for p in space.surface.iter().step_by(97) {
        // Central differences: the field is smooth at the kernel's scale.
        let mut probes = Vec::new();
        for d in 0..3 {
            for sign in [1.0, -1.0] {
                let mut q = *p;
                q[d] += sign * h;
                probes.push(q);
            }
        }
        let y = space.deform(&probes, latent);
        let col = |d: usize| {
            let (a, b) = (y[2 * d], y[2 * d + 1]);
            Vector3::new(a[0] - b[0], a[1] - b[1], a[2] - b[2]) / (2.0 * h)
        };
        let fd = nalgebra::Matrix3::from_columns(&[col(0), col(1), col(2)]).determinant();
        let exact = space.jacobian_determinants(&[*p], latent)[0];
        assert!((fd - exact).abs() < 1e-6 * (1.0 + exact.abs()), "finite differences {fd}, exact {exact}");
    }
}

/// A fold (det J ≤ 0) turns part of a tool inside out: invisible to a surface
/// fit, but it flings keypoints beside the surface to the wrong side (a
/// mirrored hammer handle moved a thumb keypoint 62 mm). No built-in space
/// may fold at its training latents, nor two standard deviations out along
/// any mode (where registration's latent prior still lets a fit go).
#[test]
fn built_in_spaces_do_not_fold() {
    for category in Category::ALL {
        let (space, report) = builtin::build(category, &builtin::options(category), |_, _| {}).unwrap();
        let worst = report.min_jacobian_determinant.iter().copied().fold(f64::INFINITY, f64::min);
        assert!(
            worst > 0.05,
            "{}: training latents fold (min det J per instance {:?})",
            category.name(),
            report.min_jacobian_determinant
        );
        for (j, var) in space.variances.iter().enumerate() {
            for sign in [-2.0, 2.0] {
                let mut latent = vec![0.0; space.modes()];
                latent[j] = sign * var.sqrt();
                let det =
                    space.jacobian_determinants(&space.surface, &latent).into_iter().fold(f64::INFINITY, f64::min);
                assert!(det > 0.0, "{}: mode {j} at {sign}σ folds (min det J {det:.2})", category.name());
            }
        }
    }
}

#[test]
fn folding_fits_are_refitted_stiffer() {
    // λ = 3 folds most hammers (measured: 7 of 10 training handles mirrored).
    let mut opts = builtin::options(Category::Hammer);
    opts.cpd.lambda = 3.0;
    let (_, report) = builtin::build(Category::Hammer, &opts, |_, _| {}).unwrap();
    assert!(report.stiffened.len() >= 3, "stiffened {:?}", report.stiffened);
    let worst = report.min_jacobian_determinant.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(worst > 0.0, "still folds after refits: {:?}", report.min_jacobian_determinant);
}

/// 10 % of a view's points scattered through its bounding box (flying
/// pixels, speckle): a hammer's views are sparse (8 points a subsample cell),
/// and before stray points were dropped they won half of the subsample
/// (measured: 25 mm median keypoint error, 3 of 8 views turned round).
#[test]
fn a_hammer_view_with_ten_percent_outliers_registers() {
    use rand::SeedableRng;
    let reg = hammer_registrar();
    let test = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let mut errs = Vec::new();
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let (mut cloud, pose) = view_of(&test.mesh, *yaw, k * 3);
        let clean = cloud.len();
        crate::eval::transfer::add_outliers(&mut cloud, 0.1, &mut rng);
        assert!(cloud.len() > clean + clean / 20);
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        let rot_err = (r.rotation_cloud_from_canonical * pose.rotation.inverse()).angle().to_degrees();
        assert!(r.fit.confident, "view {k}: {:?}", r.fit);
        assert!(rot_err < 10.0, "view {k}: rotation error {rot_err:.1}°");
        assert!((r.scale - 1.0).abs() < 0.1, "view {k}: scale {:.3}", r.scale);
        for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
            let truth = pose * Point3::from(t.position);
            errs.push((Vector3::from(p.position) - truth.coords).norm() * 1e3);
        }
    }
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    assert!(median < 6.0, "median keypoint error {median:.1} mm over {errs:?}");
}

/// A segmentation that leaks onto the table (the mask dilated by 3 pixels:
/// a third to a half more points, a ring of table round the hammer's foot
/// and a patch behind it) is set aside as the table's, whether the table's
/// height is given or found from the leak (which then holds the hammer on
/// it as a given one would); a clean view sets nothing aside.
/// Measured before: the leak's points kept, hammer keypoint median 12 mm
/// at 2 pixels (`eval transfer --mask-leak-px 2`), 16 mm at 4.
#[test]
fn a_mask_leaking_onto_the_table_is_set_aside() {
    let reg = hammer_registrar();
    let test = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let leaky = DepthNoise { mask_leak_px: 3, ..DepthNoise::default() };
    for table in [Some(0.0), None] {
        let opts = RegisterOptions { support_height: table, ..RegisterOptions::default() };
        let (mut errs, mut clean_errs) = (Vec::new(), Vec::new());
        let err = |r: &super::Registration, pose: &Isometry3<f64>, out: &mut Vec<f64>| {
            for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
                let truth = pose * Point3::from(t.position);
                out.push((Vector3::from(p.position) - truth.coords).norm() * 1e3);
            }
        };
        for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
            let pose = on_table(*yaw);
            let centre = pose * Point3::new(0.0, 0.0, 0.05);
            let (clean, _) = capture(&test.mesh, &pose, centre, k * 3, 3);
            let (cloud, _) = capture_with(&test.mesh, &pose, centre, k * 3, 3, leaky);
            let leaked = cloud.len() - clean.len();
            assert!(leaked > clean.len() / 5, "view {k}: {leaked} table points of {}", cloud.len());
            let plain = reg.register(&clean, &opts).unwrap();
            assert_eq!(plain.fit.table_points, 0, "view {k}, table {table:?}");
            err(&plain, &pose, &mut clean_errs);
            let r = reg.register(&cloud, &opts).unwrap();
            assert!(r.fit.confident, "view {k}, table {table:?}: {:?}", r.fit);
            // The leak's points, less those at the tool's very foot.
            assert!(r.fit.table_points > leaked * 4 / 5 && r.fit.table_points <= r.fit.stray_points, "{:?}", r.fit);
            // Not given, the table is found from the leak (z = 0, 1 mm depth noise).
            match table {
                Some(_) => assert_eq!(r.found_table_height, None),
                None => assert!(r.found_table_height.is_some_and(|h| h.abs() < 1e-3), "{:?}", r.found_table_height),
            }
            assert_eq!(plain.found_table_height, None, "view {k}: a table found in a clean view");
            err(&r, &pose, &mut errs);
        }
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let (leaky, clean) = (median(&mut errs), median(&mut clean_errs));
        assert!(
            leaky < 4.0 && leaky < clean + 1.0,
            "table {table:?}: median keypoint error {leaky:.1} mm (clean view {clean:.1}) over {errs:?}"
        );
    }
}

/// Something in front of the tool (a bar hiding 30 % of the mug's image
/// width) leaves a band of the fitted mug's camera-facing surface where the
/// camera saw nothing: `FitQuality::contradicted_fraction` says so. Measured,
/// `eval transfer --views 8 --seed 11` (test and train, camera given): views
/// without an occluder at most 0.06 where the fit was right (0.08-0.10 only
/// where it was wrong), with one 0.14-0.45 (mug, seeds 7 and 11), 0.09-0.57 (drill).
#[test]
fn a_view_with_something_in_front_contradicts_its_fit() {
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let pose = on_table(*yaw);
        let centre = pose * Point3::new(0.0, 0.0, 0.05);
        for share in [0.0, 0.3] {
            let noise = DepthNoise { occluder_share: share, ..DepthNoise::default() };
            let (cloud, cam) = capture_with(&test.mesh, &pose, centre, k * 3, 3, noise);
            let v = cam.translation.vector;
            let opts = RegisterOptions {
                viewpoint: Some([v.x, v.y, v.z]),
                support_height: Some(0.0),
                ..RegisterOptions::default()
            };
            let r = reg.register(&cloud, &opts).unwrap();
            let c = r.fit.contradicted_fraction.expect("a camera position, a free-space test");
            if share == 0.0 {
                assert!(c < 0.05, "view {k}, nothing in front: {c:.3} contradicted");
            } else {
                assert!(c > 0.1, "view {k}, 30 % hidden: only {c:.3} contradicted");
            }
        }
    }
}

/// A hammer on its side, off its category's rest pose: the race ranks poses
/// on the mean shape, and a hammer whose head differs from it lost its true
/// pose to one turned half round (claw and face swapped, 130-200 mm off).
/// Finished with its latent, the runner-up is compared fairly
/// (`RegisterOptions::recheck_runner_up`). Measured here (the training
/// hammers, 40 views): turned half round 7 → 3, of which called sure of it
/// (confident, not ambiguous) 2 → 2.
#[test]
fn a_hammer_on_its_side_is_seldom_turned_half_round() {
    let reg = hammer_registrar();
    let train: Vec<_> =
        tools::family(Category::Hammer).unwrap().into_iter().filter(|i| i.split == Split::Train).collect();
    let (mut turned, mut misled) = ([0usize; 2], [0usize; 2]);
    for inst in &train {
        for (k, yaw) in [0.3f64, 1.9, 3.5, 5.1].iter().enumerate() {
            let pose = on_side(&inst.mesh, *yaw);
            let (cloud, cam) = capture(&inst.mesh, &pose, pose * Point3::origin(), k * 2 + 1, 5);
            let v = cam.translation.vector;
            for (m, recheck) in [None, Some(1.0)].into_iter().enumerate() {
                let opts = RegisterOptions {
                    viewpoint: Some([v.x, v.y, v.z]),
                    support_height: Some(0.0),
                    recheck_runner_up: recheck,
                    ..RegisterOptions::default()
                };
                let r = reg.register(&cloud, &opts).unwrap();
                let rot_err = (r.rotation_cloud_from_canonical * pose.rotation.inverse()).angle().to_degrees();
                if rot_err > 90.0 {
                    turned[m] += 1;
                    misled[m] += usize::from(r.fit.confident && !r.fit.ambiguous_pose);
                }
            }
        }
    }
    assert_eq!(RegisterOptions::default().recheck_runner_up, Some(1.0));
    assert!(
        turned[1] <= 3 && turned[1] < turned[0],
        "turned half round: race alone {}, rechecked {}",
        turned[0],
        turned[1]
    );
    assert!(misled[1] <= misled[0], "sure and turned: race alone {}, rechecked {}", misled[0], misled[1]);
}

/// The coarse stage ranks poses on the mean shape at 80 points, and a
/// training mug far from the mean shape can leave its true pose out of the
/// race's four; the race's best then contradicts the view, and two more
/// coarse hypotheses race (`RegisterOptions::keep_contradicted`). The views
/// are `eval transfer --category mug --views 12` views (seeds 7 and 23,
/// from `GRASPD_EVAL_TRACE`'s "to reproduce") where the four alone lost it.
#[test]
fn a_mug_whose_true_pose_ranked_fifth_is_raced_when_the_best_contradicts_the_view() {
    #[rustfmt::skip]
    let views: [EvalView; 6] = [
        ("mug_train_00", 8, 3.7957610010830356, [-0.04091859389462889, -0.08564368711067459], 4807025220587635530, 15724615175267181746),
        ("mug_train_07", 1, 1.573116278199607, [-0.03928120813862299, -0.08017621696636967], 15725432089916840804, 9780663794412164592),
        ("mug_train_04", 3, 0.6932742061656395, [-0.03559692546268813, 0.07362352482152738], 11982674491983804604, 2855417265271327470),
        ("mug_train_07", 0, 2.3323180793006397, [-0.03848001548507862, -0.05875905877363896], 17231047740177485114, 6712630502953962110),
        ("mug_train_07", 9, 4.5556255656907245, [0.09881502153424933, 0.09154542977309943], 4671387726428440840, 17074805204754930496),
        ("mug_train_08", 9, 3.499519735185996, [-0.040452736900519315, -0.013247725422026214], 6876564083239952663, 10237491224835594987),
    ];
    let mut right = [0usize; 2];
    for view in &views {
        for (m, keep_contradicted) in [0, 2].into_iter().enumerate() {
            // The sweep's challenger off: it finds four of these six too
            // (five with the reserve; see the next test).
            let opts =
                RegisterOptions { keep_contradicted, sweep_challenger_margin: None, ..RegisterOptions::default() };
            right[m] += usize::from(mug_eval_view_rotation_error(view, opts).0 < 15.0);
        }
    }
    assert_eq!(RegisterOptions::default().keep_contradicted, 2);
    // Two of the six reserves lead by less than the ambiguity margin and are not taken.
    assert!(
        right[1] >= 4 && right[1] > right[0],
        "poses found of 6: the race's four {}, with the reserve {}",
        right[0],
        right[1]
    );
}

/// A view of `eval transfer --category mug --views 12`, from the fields its
/// trace prints under "to reproduce" (`GRASPD_EVAL_TRACE`): instance, view
/// of 12, yaw (rad), place on the table, capture seed, register seed.
type EvalView = (&'static str, usize, f64, [f64; 2], u64, u64);

/// The rotation error (degrees) of the eval's registration of `view`, and
/// whether it is flagged `ambiguous_pose`: `opts` with the view's register
/// seed, the camera's position and the table.
fn mug_eval_view_rotation_error(view: &EvalView, opts: RegisterOptions) -> (f64, bool) {
    let &(name, view, yaw, at, capture_seed, seed) = view;
    let inst = tools::instance(Category::Mug, name).unwrap();
    let placed = Placement::upright(yaw, at).place(&inst.mesh, view, 12, DepthNoise::default()).unwrap();
    let cloud = placed.capture(capture_seed).unwrap();
    let opts = RegisterOptions { seed, viewpoint: Some(placed.viewpoint()), support_height: Some(0.0), ..opts };
    let r = mug_registrar().register(&cloud, &opts).unwrap();
    let rot = placed.world_from_tool.rotation;
    ((r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees(), r.fit.ambiguous_pose)
}

/// A view that hides the mug's handle leaves its turn open, and the
/// registration says so; a second camera a quarter turn round the tool sees
/// the handle, and the two views merged in one frame register at the true
/// turn, no longer flagged, with the first camera's position given, and
/// with both cameras'. The views are `eval transfer --category mug --views
/// 12 --seed 7` test views that ended 20-51° off, flagged (`--second-view`
/// is the eval of this over every view).
#[test]
fn a_second_view_settles_the_turn_a_view_hiding_the_handle_leaves_open() {
    #[rustfmt::skip]
    let views: [EvalView; 3] = [
        ("mug_test_01", 1, 3.3466569965873756, [0.05900630029360761, 0.010377743495624215], 7694806594164826800, 15309659868891968803),
        ("mug_test_01", 3, 4.1301575055604705, [-0.09544787794777031, 0.022787981670855984], 3033484725971336444, 17238574751080881951),
        ("mug_test_02", 8, 0.4009085801779778, [0.05208012276988947, -0.09664661914678017], 7002309302245813876, 5323640489058749303),
    ];
    for view in &views {
        let (one_view_deg, one_view_ambiguous) = mug_eval_view_rotation_error(view, RegisterOptions::default());
        assert!(
            one_view_ambiguous && one_view_deg > 10.0,
            "{view:?}: one view {one_view_deg:.1}° off, flagged {one_view_ambiguous}"
        );
        let &(name, k, yaw, at, capture_seed, seed) = view;
        let inst = tools::instance(Category::Mug, name).unwrap();
        let placement = Placement::upright(yaw, at);
        let first = placement.place(&inst.mesh, k, 12, DepthNoise::default()).unwrap();
        let second = placement.second_view(&inst.mesh, k, 12, DepthNoise::default()).unwrap();
        let mut cloud = first.capture(capture_seed).unwrap();
        cloud.extend(second.capture(capture_seed ^ 1).unwrap());
        // Told the first camera, and told both.
        for second_viewpoint in [None, Some(second.viewpoint())] {
            let opts = RegisterOptions {
                seed,
                viewpoint: Some(first.viewpoint()),
                second_viewpoint,
                support_height: Some(0.0),
                ..RegisterOptions::default()
            };
            let r = mug_registrar().register(&cloud, &opts).unwrap();
            let deg = (r.rotation_cloud_from_canonical * first.world_from_tool.rotation.inverse()).angle().to_degrees();
            let flagged = r.fit.ambiguous_pose;
            assert!(
                deg < 5.0 && !flagged,
                "{view:?}, {second_viewpoint:?}: two views {deg:.1}° off, flagged {flagged}"
            );
            assert!(r.fit.confident);
        }
    }
}

/// The race poses the mean shape, whose handle can overhang a mug's own:
/// with the handle turned to the camera the free-space penalty then
/// outweighs a clearly better likelihood at the true turn, and the lead
/// ends half a turn off (`mug_test_01`, 173°). The yaw sweep names the turn
/// the likelihood prefers and it is raced (`sweep_challenger_margin`). The
/// views are `eval transfer --category mug --views 12` views (seeds 23, 31
/// and 47) that ended 40-173° off without.
#[test]
fn the_sweep_races_a_turn_the_likelihood_prefers_to_the_arc_the_penalty_chose() {
    #[rustfmt::skip]
    let views: [EvalView; 6] = [
        ("mug_test_01", 3, 1.8249705610870155, [-0.08734043676366128, 0.07529573836732087], 17276483145886802676, 14909025304967615899),
        ("mug_train_04", 3, 0.6932742061656395, [-0.03559692546268813, 0.07362352482152738], 11982674491983804604, 2855417265271327470),
        ("mug_train_06", 10, 4.7848778768518905, [-0.08658589114495847, -0.08217325287326044], 17375619305682195069, 12181962909173877628),
        ("mug_train_04", 10, 3.3816619223141573, [-0.03695744849501919, -0.007046566560975443], 4000983975265459439, 12933732995060772462),
        ("mug_train_04", 0, 1.9141801989361944, [0.07005235199685565, -0.0895579495173259], 14118070968053101817, 15182391654566357288),
        ("mug_train_04", 10, 4.238810639789291, [-0.09615861924382987, 0.0007657575759900004], 17211163749902323178, 11276791088310240851),
    ];
    let mut right = [0usize; 2];
    for view in &views {
        for (m, sweep_challenger_margin) in
            [None, RegisterOptions::default().sweep_challenger_margin].into_iter().enumerate()
        {
            let opts = RegisterOptions { sweep_challenger_margin, ..RegisterOptions::default() };
            right[m] += usize::from(mug_eval_view_rotation_error(view, opts).0 < 15.0);
        }
    }
    assert!(
        right[1] >= 5 && right[0] <= 1,
        "poses found of 6: without the challenger {}, with it {}",
        right[0],
        right[1]
    );
}

/// Where the handle peeks past the body (10-30 of 15,000 points), the yaw
/// sweep's averaged scores leave an arc open that the image settles; the
/// finished fit, turned across it, leaves those points unexplained but at
/// the true turn (`RegisterOptions::narrow_by_unexplained`). The views are
/// `eval transfer --category mug --views 12` training views (seeds 23, 31
/// and 47) that ended 31-54° off without. Three are narrowed to one run of
/// turns under 30° wide, the race's rivals at turns the counts refute, and
/// are then no longer flagged ambiguous (`narrowing_settles_ambiguity`).
#[test]
fn a_handle_peeking_past_the_body_narrows_the_open_arc_to_the_true_turn() {
    #[rustfmt::skip]
    let views: [EvalView; 5] = [
        ("mug_train_01", 5, 5.00765231751928, [-0.018435882512626622, -0.008897861771284954], 6507295192169113639, 15275386548063726255),
        ("mug_train_07", 0, 2.3323180793006397, [-0.03848001548507862, -0.05875905877363896], 17231047740177485114, 6712630502953962110),
        ("mug_train_05", 9, 1.1095100430463438, [-0.054899099814625665, 0.004279066122259901], 17563844483134779273, 16935032180110242511),
        ("mug_train_05", 9, 1.1875224986477737, [-0.03200492673047537, 0.05148404183814399], 14564016925231336979, 3337734056604290159),
        ("mug_train_07", 5, 0.1976216374178657, [-0.09605341770521288, 0.05327518786074135], 3642224853077777694, 15360001767057248982),
    ];
    let (mut right, mut settled) = ([0usize; 2], [0usize; 2]);
    for view in &views {
        for (m, narrow_by_unexplained) in [false, true].into_iter().enumerate() {
            let opts = RegisterOptions { narrow_by_unexplained, ..RegisterOptions::default() };
            let (error_deg, ambiguous) = mug_eval_view_rotation_error(view, opts);
            right[m] += usize::from(error_deg < 10.0);
            settled[m] += usize::from(error_deg < 10.0 && !ambiguous);
        }
        // The flag as the sweep left it.
        let opts = RegisterOptions { narrowing_settles_ambiguity: false, ..RegisterOptions::default() };
        assert!(mug_eval_view_rotation_error(view, opts).1, "{view:?}: the sweep's arc was open");
    }
    let d = RegisterOptions::default();
    assert!(d.narrow_by_unexplained && d.narrowing_settles_ambiguity);
    assert!(right[1] >= 4 && right[0] == 0, "poses within 10° of 5: without {}, narrowed {}", right[0], right[1]);
    assert!(
        settled[1] >= 3 && settled[0] == 0,
        "within 10° and settled of 5: without {}, narrowed {}",
        settled[0],
        settled[1]
    );
}

/// The hammers' registration holds the scale near 1 (their sizes lie in the
/// latent: see `default_scale_prior_std`), yet a hammer 30 % larger than
/// the family still registers at its size, the latent and the scale
/// sharing the growth; the options can loosen the prior.
#[test]
fn a_hammer_larger_than_the_family_registers_despite_the_tight_scale_prior() {
    use crate::shape::register::{default_scale_prior_std, LOOSE_SCALE_PRIOR_STD};
    assert!(default_scale_prior_std("hammer") < 0.05 && default_scale_prior_std("mug") == LOOSE_SCALE_PRIOR_STD);
    let reg = hammer_registrar();
    let test = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let grow = 1.3;
    let mut big = test.mesh.clone();
    big.vertices.iter_mut().for_each(|v| *v = Point3::from(grow * v.coords));
    let loose = RegisterOptions { scale_prior_std: Some(LOOSE_SCALE_PRIOR_STD), ..RegisterOptions::default() };
    let mut errs = [Vec::new(), Vec::new()];
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let (cloud, pose) = view_of(&big, *yaw, k * 3);
        for (e, opts) in errs.iter_mut().zip([RegisterOptions::default(), loose]) {
            let r = reg.register(&cloud, &opts).unwrap();
            for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
                let truth = pose * Point3::from(grow * Vector3::from(t.position));
                e.push((Vector3::from(p.position) - truth.coords).norm() * 1e3);
            }
        }
    }
    let [tight, loose] = errs.map(|mut e| {
        e.sort_by(f64::total_cmp);
        e[e.len() / 2]
    });
    // Here: 5.8 mm with the hammers' prior, 4.9 mm with the loose one.
    assert!(tight < 7.0 && tight < loose + 2.0, "median keypoint error {tight:.1} mm (loose prior: {loose:.1} mm)");
}

#[test]
fn registered_keypoints_are_not_pulled_toward_the_camera() {
    // A partial view sees one side; the model's hidden side must not drag the
    // fit onto it. Measured median bias on these 4 mugs x 8 views: -1.48 mm with
    // back-face culling alone, -0.67 mm with the range image's occlusion and the
    // lower fine-stage hidden weight (all ten training mugs: -1.73 / -0.88 mm).
    use crate::eval::transfer::{evaluate, TransferEvalOptions};
    let family = tools::family(Category::Mug).unwrap();
    let train: Vec<_> = family.iter().filter(|i| i.split == Split::Train).take(4).collect();
    let report = evaluate(mug_registrar(), &train, Split::Train, &[], &TransferEvalOptions::default(), || {});
    let bias = report.keypoint_depth_bias_mm.median;
    assert!(bias.abs() < 1.2, "registered keypoints sit {bias:+.2} mm along the view (median)");
    assert!(report.ours.keypoint_error_mm.median < 5.0, "{:?}", report.ours.keypoint_error_mm);
}

#[test]
fn surfels_take_the_fit_nearer_the_observed_surface() {
    // A polish whose Gaussians are flat along the surface (σ_n along the
    // normal, σ_t across) is not blurred along the view by the model's point
    // spacing. Measured on these 4 mugs x 8 views: depth bias median −0.87 →
    // −0.54 mm, keypoint error median 1.81 → 1.50 mm.
    use crate::eval::transfer::{evaluate, TransferEvalOptions};
    let family = tools::family(Category::Mug).unwrap();
    let train: Vec<_> = family.iter().filter(|i| i.split == Split::Train).take(4).collect();
    let run = |surfels: bool| {
        let register = RegisterOptions { surfels, ..RegisterOptions::default() };
        let opts = TransferEvalOptions { register, ..TransferEvalOptions::default() };
        evaluate(mug_registrar(), &train, Split::Train, &[], &opts, || {})
    };
    let (iso, flat) = (run(false), run(true));
    let bias = |r: &crate::eval::transfer::SplitReport| r.keypoint_depth_bias_mm.median;
    let err = |r: &crate::eval::transfer::SplitReport| r.ours.keypoint_error_mm.median;
    assert!(
        bias(&flat).abs() < bias(&iso).abs() - 0.15,
        "depth bias {:+.2} mm with surfels, {:+.2} without",
        bias(&flat),
        bias(&iso)
    );
    assert!(err(&flat) < err(&iso), "keypoint error {:.2} mm with surfels, {:.2} without", err(&flat), err(&iso));
}

#[test]
fn a_mug_on_its_side_registers_the_right_way_round() {
    // Its principal axes are too alike to settle the pose, so the registrar
    // also starts from the mug lying on its side (measured, 8 views: keypoint
    // error p90 115 mm without those starts, its opening reversed; 9.2 mm with).
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let mut errs = Vec::new();
    for (k, yaw) in [0.3f64, 1.9, 3.5, 5.1].iter().enumerate() {
        let pose = on_side(&test.mesh, *yaw);
        let rot = pose.rotation;
        let (cloud, cam_pose) = capture(&test.mesh, &pose, pose * Point3::origin(), k * 2, k as u64);
        let opts = RegisterOptions { viewpoint: Some(cam_pose.translation.vector.into()), ..Default::default() };
        let r = reg.register(&cloud, &opts).unwrap();
        let rot_err = (r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees();
        assert!(rot_err < 25.0, "view {k}: rotation error {rot_err:.1}°");
        // The view does not look upright, so every start was tried.
        let every = reg.register(&cloud, &RegisterOptions { lying_hypotheses: Some(true), ..opts }).unwrap();
        assert_eq!(r.hypotheses, every.hypotheses, "view {k}: lying starts skipped for a mug on its side");
        // Lying on its flank, not as mugs were modelled: a known table does
        // not hold it (`REST_POSE_COS`; held there, its keypoints got worse).
        let on_table = reg.register(&cloud, &RegisterOptions { support_height: Some(0.0), ..opts }).unwrap();
        assert_eq!(on_table.keypoints, r.keypoints, "view {k}: the table held a mug on its side");
        for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
            errs.push((Vector3::from(p.position) - (pose * Point3::from(t.position)).coords).norm() * 1e3);
        }
    }
    errs.sort_by(f64::total_cmp);
    assert!(errs[errs.len() / 2] < 8.0, "median keypoint error {:.1} mm over {errs:?}", errs[errs.len() / 2]);
}

#[test]
fn an_upright_mug_is_not_started_lying() {
    // A view of a standing mug shows mostly its sides (`UPRIGHT_SIDE_FACING`):
    // the lying starts, which a mug on its side needs, would only cost time,
    // and the principal-axis starts only win a wrong pose now and then. It
    // starts upright only, once per yaw.
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    for (k, yaw) in [0.4f64, 2.0, 3.6, 5.2].iter().enumerate() {
        let (cloud, cam_pose) =
            capture(&test.mesh, &on_table(*yaw), on_table(*yaw) * Point3::new(0.0, 0.0, 0.05), k * 2 + 1, 9);
        let opts = RegisterOptions { viewpoint: Some(cam_pose.translation.vector.into()), ..Default::default() };
        let fewer = reg.register(&cloud, &opts).unwrap();
        let every = reg.register(&cloud, &RegisterOptions { lying_hypotheses: Some(true), ..opts }).unwrap();
        assert_eq!(
            fewer.hypotheses, opts.yaws,
            "view {k}: {} starts, {} with every kind",
            fewer.hypotheses, every.hypotheses
        );
        assert!(every.hypotheses > 3 * opts.yaws, "view {k}: {} starts with every kind", every.hypotheses);
        // Standing, whichever way its handle turned (a hidden handle leaves the yaw open).
        let tilt = (fewer.rotation_cloud_from_canonical * Vector3::z()).angle(&Vector3::z()).to_degrees();
        assert!(tilt < 10.0, "view {k}: registered {tilt:.1}° off upright");
    }
}

#[test]
fn the_polish_tightens_a_partial_view_fit() {
    // The polish (an 800-point model, 800 observed points) takes σ from the
    // refine's point spacing toward the sensor's noise, and the keypoints
    // with it (eval transfer, 8 views: mug test median 3.7 → 3.0 mm).
    // Measured here: σ 2.4-2.5 mm against 3.0-3.2 without, median keypoint
    // error 3.95 against 4.82 mm. With isotropic components, whose one σ
    // says it (a surfel polish's σ_n and σ_t: `surfels_take_...`).
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let iso = RegisterOptions { surfels: false, ..RegisterOptions::default() };
    let without = RegisterOptions { polish_points: 0, ..iso };
    let (mut errs, mut errs_without) = (Vec::new(), Vec::new());
    for (k, yaw) in [0.4f64, 2.0, 4.4, 5.5].iter().enumerate() {
        let (cloud, pose) = view_of(&test.mesh, *yaw, k * 2 + 1);
        let mut sigma = [0.0; 2];
        for (i, (opts, errs)) in [(iso, &mut errs), (without, &mut errs_without)].into_iter().enumerate() {
            let r = reg.register(&cloud, &opts).unwrap();
            for (p, t) in r.keypoints.iter().zip(&test.keypoints) {
                errs.push((Vector3::from(p.position) - (pose * Point3::from(t.position)).coords).norm() * 1e3);
            }
            sigma[i] = r.sigma2.sqrt() * 1e3;
        }
        assert!(sigma[0] < 0.9 * sigma[1], "view {k}: σ {:.2} mm with the polish, {:.2} without", sigma[0], sigma[1]);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (with, without) = (median(&mut errs), median(&mut errs_without));
    assert!(with < without && with < 4.5, "median keypoint error {with:.2} mm with the polish, {without:.2} without");
}

#[test]
fn a_view_without_its_camera_position_gets_one_estimated() {
    // The camera's direction from the view and a first fit, used only when
    // it settles; a cloud of the whole surface is no one camera's view and
    // gets none.
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let mut angles = Vec::new();
    for (k, yaw) in [0.4f64, 2.0, 4.4, 5.5].iter().enumerate() {
        let pose = on_table(*yaw);
        let (cloud, cam_pose) = capture(&test.mesh, &pose, pose * Point3::new(0.0, 0.0, 0.05), k * 2 + 1, k as u64);
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        let centroid = cloud.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / cloud.len() as f64;
        let truth = (cam_pose.translation.vector - centroid).normalize();
        if let Some(vp) = r.estimated_viewpoint {
            angles.push((Vector3::from(vp) - centroid).normalize().angle(&truth).to_degrees());
        }
        // A given camera position is used as it is, not estimated.
        let given = RegisterOptions { viewpoint: Some(cam_pose.translation.vector.into()), ..Default::default() };
        assert!(reg.register(&cloud, &given).unwrap().estimated_viewpoint.is_none());
    }
    // Two of these four settle (the other two, seen from 45° above, leave
    // directions 50° apart equally plausible and are fitted without one).
    assert!(angles.len() >= 2, "estimated on {} of 4 views", angles.len());
    assert!(angles.iter().all(|a| *a < 30.0), "estimated directions off by {angles:?}°");

    let whole: Vec<Point3<f64>> = sample_points(&test.mesh, 3000, 5).unwrap();
    let r = reg.register(&whole, &RegisterOptions::default()).unwrap();
    assert!(r.estimated_viewpoint.is_none(), "a whole surface seen from {:?}", r.estimated_viewpoint);
}

#[test]
fn a_flat_tool_without_its_camera_position_gets_a_camera_above_it() {
    // A hammer lying flat looks alike from a wide cone of directions above
    // it; the estimate then takes the cone's mean (near straight down) rather
    // than none (as before: all 8 views refused), and the fit weighs the
    // model by what a camera there would see.
    let reg = hammer_registrar();
    let test = tools::family(Category::Hammer).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let middle = test.mesh.aabb().map(|(lo, hi)| Point3::from((lo.coords + hi.coords) / 2.0)).unwrap();
    let (mut above, mut errs, mut worst_view) = (0, Vec::new(), 0.0f64);
    for (k, yaw) in [0.3f64, 1.1, 1.9, 2.7, 3.5, 4.3, 5.1, 5.9].iter().enumerate() {
        // Framed on the hammer's middle, as `eval transfer` frames its views.
        let pose = on_table(*yaw);
        let (cloud, _) = capture(&test.mesh, &pose, pose * middle, k, k as u64);
        let r = reg.register(&cloud, &RegisterOptions::default()).unwrap();
        let centroid = cloud.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / cloud.len() as f64;
        if let Some(vp) = r.estimated_viewpoint {
            above += ((Vector3::from(vp) - centroid).normalize().z > 25f64.to_radians().cos()) as usize;
        }
        let view: Vec<f64> = r
            .keypoints
            .iter()
            .zip(&test.keypoints)
            .map(|(p, t)| (Vector3::from(p.position) - (pose * Point3::from(t.position)).coords).norm() * 1e3)
            .collect();
        worst_view = worst_view.max(view.iter().sum::<f64>() / view.len() as f64);
        errs.extend(view);
    }
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    // Measured: 8 of 8 above, median 4.3 mm, worst view 5.6 mm. Without the
    // estimate 3.8 and 5.1: on these 8 views it costs a little, where over
    // `eval transfer`'s 3 × 24 test views it gains (see VIEWPOINT_ABOVE_WITHIN).
    assert!(above >= 6, "a camera above the hammer on {above} of 8 views");
    assert!(median < 5.0 && worst_view < 7.0, "keypoint median {median:.2} mm, worst view's mean {worst_view:.2} mm");
}

#[test]
fn a_half_hidden_handle_is_not_placed_on_the_mirror_side() {
    // A handle turned 130-160° away from the camera shows only an edge at the
    // body's silhouette; its mirror image about the line of sight hides it as
    // well but sticks out of the silhouette on the other side. The yaw sweep
    // once scored turns on the race's sparse model and about the world's up,
    // and chose the mirror, unflagged (eval transfer mug_test_00 view 5: 95°
    // off). Fits left unflagged should have the handle on its side; flagged
    // fits may sit anywhere in the arc the view allows. Measured on these 192
    // views (3 test mugs, 8 cameras, 8 turns): before, 11 of 70 unflagged fits
    // more than 30° off and an unflagged keypoint error p90 of 38.5 mm; with
    // the sweep on the polish model about the tool's axis, 5 of 60 and 10.7
    // mm; with its margin 0.05 → 0.08 nats a point, 1 of 53 and 7.3 mm.
    let reg = mug_registrar();
    let t = Translation3::new(0.03, -0.02, 0.0);
    let centre = Point3::new(t.x, t.y, 0.05);
    let (mut wrong, mut flagged, mut fits, mut errs) = (Vec::new(), 0, 0, Vec::new());
    for test in tools::family(Category::Mug).unwrap().into_iter().filter(|i| i.split == Split::Test) {
        for view in 0..8 {
            // The camera looks at `centre` whatever the turn: its azimuth is the turns' zero.
            let cam = standard_view(view, 8, centre, test.mesh.diagonal(), Intrinsics::default()).unwrap();
            let eye = cam.translation.vector;
            let azimuth = (eye.y - t.y).atan2(eye.x - t.x);
            for offset_deg in [-160.0f64, -150.0, -140.0, -130.0, 130.0, 140.0, 150.0, 160.0] {
                let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), azimuth + offset_deg.to_radians());
                let pose = Isometry3::from_parts(t, rot);
                let (cloud, _) = capture(&test.mesh, &pose, centre, view, 11 + view as u64);
                let opts = RegisterOptions { viewpoint: Some(eye.into()), ..Default::default() };
                let r = reg.register(&cloud, &opts).unwrap();
                let rot_err = (r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees();
                fits += 1;
                if r.fit.ambiguous_pose {
                    flagged += 1;
                    continue;
                }
                if rot_err > 30.0 {
                    wrong.push((test.name.clone(), view, offset_deg, rot_err.round()));
                }
                for (p, kp) in r.keypoints.iter().zip(&test.keypoints) {
                    errs.push((Vector3::from(p.position) - (pose * Point3::from(kp.position)).coords).norm() * 1e3);
                }
            }
        }
    }
    errs.sort_by(f64::total_cmp);
    let p90 = errs[errs.len() * 9 / 10];
    eprintln!(
        "{fits} fits, {flagged} flagged, unflagged more than 30° off: {wrong:?}; unflagged keypoint p90 {p90:.1} mm"
    );
    assert!(wrong.len() <= 4, "unflagged fits off by more than 30° (instance, view, offset°, error°): {wrong:?}");
    assert!(p90 < 15.0, "unflagged keypoint error p90 {p90:.1} mm");
}

#[test]
fn the_sweep_screen_keeps_the_turns_the_dense_scores_choose() {
    // The yaw sweep scores its turns on the race's sparse model first and only
    // the promising ones on the dense model; on views where the handle is half
    // hidden (flat scores, the hard case for the screen) and where it shows,
    // the fits must come out as without the screen.
    let reg = mug_registrar();
    let t = Translation3::new(0.03, -0.02, 0.0);
    let centre = Point3::new(t.x, t.y, 0.05);
    let screened = RegisterOptions::default();
    assert!(screened.yaw_sweep_screen, "the screen is on by default");
    let unscreened = RegisterOptions { yaw_sweep_screen: false, ..screened };
    let mut fits = 0;
    for test in tools::family(Category::Mug).unwrap().into_iter().filter(|i| i.split == Split::Test) {
        for view in [1, 4, 6] {
            let cam = standard_view(view, 8, centre, test.mesh.diagonal(), Intrinsics::default()).unwrap();
            let eye = cam.translation.vector;
            let azimuth = (eye.y - t.y).atan2(eye.x - t.x);
            for offset_deg in [-150.0f64, 0.0, 90.0, 140.0] {
                let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), azimuth + offset_deg.to_radians());
                let (cloud, _) = capture(&test.mesh, &Isometry3::from_parts(t, rot), centre, view, 5 + view as u64);
                let [a, b] = [screened, unscreened]
                    .map(|o| reg.register(&cloud, &RegisterOptions { viewpoint: Some(eye.into()), ..o }).unwrap());
                let angle = (a.rotation_cloud_from_canonical * b.rotation_cloud_from_canonical.inverse()).angle();
                assert!(
                    angle < 1e-6 && a.fit.ambiguous_pose == b.fit.ambiguous_pose,
                    "{} view {view} turned {offset_deg}°: {:.1}° apart with and without the screen",
                    test.name,
                    angle.to_degrees()
                );
                fits += 1;
            }
        }
    }
    assert_eq!(fits, 36);
}

#[test]
fn squarem_brings_the_latent_fit_nearer_convergence_in_the_same_iterations() {
    // The refine's latent drifts a little further each EM iteration; SQUAREM
    // jumps along that path. Against a long plain fit (400 iterations, the
    // latent EM converges to), 40 accelerated iterations should end much
    // nearer than 40 plain ones. Measured, summed over the three views:
    // 0.76 against 1.87 before the fine stages counted grazing model points
    // hidden (`GRAZING_COS`), 1.34 against 2.18 since: points crossing the
    // grazing angle flip their weight as the pose moves, which moves the
    // long fit's end too (the fits' iterations in `bench_register` did not
    // change: mug 76.0 → 74.9 a fit, drill 48.3 → 49.2, hammer 50.7 → 47.0).
    // With the 20-draw space (2026-12-06): 1.40 against 2.11 at its 9 modes,
    // 1.57 against 1.88 at 12; at 12 it still paid (eval transfer, seeds 7 /
    // 11 / 23, without it: hammer test median 1.45 -> 1.49 mm, mug p90 8.73
    // -> 9.18, fits 0.4-0.6 ms longer).
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let refine_only = RegisterOptions { polish_points: 0, tol: 1e-12, ..RegisterOptions::default() };
    let (mut plain_gap, mut fast_gap) = (0.0, 0.0);
    for (k, yaw) in [0.4f64, 2.0, 4.4].iter().enumerate() {
        let (cloud, _) = view_of(&test.mesh, *yaw, k * 3 + 1);
        let fit = |accelerate: bool, fine_iters: usize| {
            reg.register(&cloud, &RegisterOptions { accelerate, fine_iters, ..refine_only }).unwrap().latent
        };
        let converged = fit(false, 400);
        let gap = |l: Vec<f64>| l.iter().zip(&converged).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
        plain_gap += gap(fit(false, 40));
        fast_gap += gap(fit(true, 40));
    }
    eprintln!("latent distance to the converged fit after 40 iterations: plain {plain_gap:.3}, SQUAREM {fast_gap:.3}");
    assert!(fast_gap < 0.75 * plain_gap, "plain {plain_gap:.3}, SQUAREM {fast_gap:.3}");
}

/// A hammer whose handle is much longer than the mean shape's (the family's
/// longest, 53 mm beyond the canonical's end): its handle end is in view, so
/// the fit must reach it. From the race's σ² alone the refine settled with
/// the handle 17-37 mm short (the observed end taken for outliers); it
/// re-anneals from the shape space's own spread (`refine_shape_sigma2`).
#[test]
fn a_long_handle_in_view_is_fitted_to_its_end() {
    let reg = hammer_registrar();
    let family = tools::family(Category::Hammer).unwrap();
    let train: Vec<_> = family.iter().filter(|i| i.split == Split::Train).collect();
    // The training hammer furthest along the first mode (the handle's length: the longest handle).
    let (inst, _) =
        train.iter().zip(&reg.space.train_latents).max_by(|a, b| a.1[0].abs().total_cmp(&b.1[0].abs())).unwrap();
    let end = inst.keypoints.iter().position(|k| k.name == "handle_end").unwrap();
    let mut errs = [Vec::new(), Vec::new()];
    let without = RegisterOptions { refine_shape_sigma2: 0.0, ..RegisterOptions::default() };
    let (lo, hi) = inst.mesh.aabb().unwrap();
    for (k, yaw) in [0.3f64, 1.3, 2.3, 3.3, 4.3, 5.3].iter().enumerate() {
        let pose = on_table(*yaw);
        let (cloud, camera) = capture(&inst.mesh, &pose, pose * Point3::from((lo.coords + hi.coords) / 2.0), k, 5);
        let viewpoint = Some(camera.translation.vector.into());
        for (e, opts) in errs.iter_mut().zip([RegisterOptions::default(), without]) {
            let r = reg.register(&cloud, &RegisterOptions { viewpoint, ..opts }).unwrap();
            let truth = pose * Point3::from(inst.keypoints[end].position);
            e.push((Vector3::from(r.keypoints[end].position) - truth.coords).norm() * 1e3);
        }
    }
    eprintln!("handle end error per view, mm: {:.1?}, without re-annealing {:.1?}", errs[0], errs[1]);
    let [annealed, settled] = errs.map(|mut e| {
        e.sort_by(f64::total_cmp);
        e[e.len() / 2]
    });
    // Here: 10.3 mm (views 10.3 / 11.1 / 1.6 / 10.0 / 12.8 / 0.9); 30.8 mm
    // without re-annealing. With the 10-draw space (9 modes) it was 4.0 and
    // 29.7, with the 20-draw space at 12 modes 8.0 and 28.4: that space fits
    // this, the family's longest handle, at scale 0.95 with its first mode
    // at about 2.2 of the true 4.1, the rest of the length taken off the
    // scale. A weaker latent prior (1, 0.5; 12 modes) reaches further here
    // (7.7, 3.7 mm) but not on the test tools (eval transfer, seeds 7 / 11 /
    // 23, weight 1: hammer 1.45 -> 1.50 mm). Measured and left; the bound
    // checks what re-annealing is for.
    assert!(annealed < 12.0, "handle end {annealed:.1} mm off (median; {settled:.1} mm without re-annealing)");
}

#[test]
fn a_known_table_holds_the_tool_on_it() {
    // A view from above shows nothing of a tool's underside: without the
    // table's height the completed shape's lowest point floats or sinks by
    // the latent's and the scale's play; with it (`support_height`) the
    // lowest point touches the table and the keypoints follow.
    let reg = hammer_registrar();
    let family = tools::family(Category::Hammer).unwrap();
    let (mut gap, mut errs) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
    for (k, inst) in family.iter().filter(|i| i.split == Split::Test).enumerate() {
        let (lo, hi) = inst.mesh.aabb().unwrap();
        for (v, yaw) in [0.7f64, 2.9, 5.0].iter().enumerate() {
            let pose = on_table(*yaw);
            let centre = pose * Point3::from((lo.coords + hi.coords) / 2.0);
            let (cloud, camera) = capture(&inst.mesh, &pose, centre, 3 * k + v, 11);
            let viewpoint = Some(camera.translation.vector.into());
            for (i, support_height) in [None, Some(0.0)].into_iter().enumerate() {
                let r =
                    reg.register(&cloud, &RegisterOptions { viewpoint, support_height, ..Default::default() }).unwrap();
                let lowest = reg.completed_shape(&r).iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
                gap[i].push(lowest.abs() * 1e3);
                for (p, t) in r.keypoints.iter().zip(&inst.keypoints) {
                    errs[i].push((Vector3::from(p.position) - (pose * Point3::from(t.position)).coords).norm() * 1e3);
                }
            }
        }
    }
    let largest = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    eprintln!(
        "lowest point off the table, median / largest: {:.2} / {:.2} mm without, {:.2} / {:.2} with; keypoints median {:.2} / {:.2} mm",
        median(&gap[0]),
        largest(&gap[0]),
        median(&gap[1]),
        largest(&gap[1]),
        median(&errs[0]),
        median(&errs[1])
    );
    assert!(largest(&gap[1]) < 0.8, "with the table, the lowest point {:?} mm off it", gap[1]);
    assert!(median(&gap[1]) < 0.5 * median(&gap[0]), "lowest point off the table: {:?} → {:?} mm", gap[0], gap[1]);
    assert!(
        median(&errs[1]) < median(&errs[0]),
        "keypoint median {:.2} → {:.2} mm",
        median(&errs[0]),
        median(&errs[1])
    );
}

/// A cloud far denser than a camera view of a tool (each point of a mug
/// view taken 14 times, about 200,000 points, with 5 % outliers) registers
/// from a seeded subsample of `WORKING_POINTS`: as accurately as the view
/// itself with the same share of outliers, the same answer twice, and its
/// strays counted for the whole cloud. (The stray test and even subsamples
/// passed over every point before: 26 ms a fit at this size against 11 now,
/// `DENSE_VIEWS=13 bench_register mug`.)
///
/// Accuracy is compared as the median over seven views: on one view either
/// cloud may land a few millimetres off by its sample alone (measured,
/// keypoint median per view, view / dense, 2026-12-06, the 20-draw space at
/// 12 modes: 1.0 / 1.7, 1.1 /
/// 5.1, 1.5 / 2.3, 1.3 / 1.9, 1.8 / 1.6, 1.2 / 2.7, 1.5 / 1.8 mm). Until
/// then the test took one view and compared it without outliers, which
/// held by luck of the view: the 20-draw shape space moved it to 4.1 mm.
#[test]
fn a_200k_point_view_registers_from_its_working_subsample() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let reg = mug_registrar();
    let test = tools::family(Category::Mug).unwrap().into_iter().find(|i| i.split == Split::Test).unwrap();
    let opts = RegisterOptions::default();
    let jitter = Normal::new(0.0, 0.0005).unwrap();
    let (mut view_errors, mut dense_errors) = (Vec::new(), Vec::new());
    for (k, yaw) in [0.4f64, 1.2, 2.0, 2.8, 3.6, 4.4, 5.2].into_iter().enumerate() {
        let (mut view, pose) = view_of(&test.mesh, yaw, k);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let mut dense: Vec<Point3<f64>> = view
            .iter()
            .flat_map(|p| (0..14).map(|_| p + Vector3::from_fn(|_, _| jitter.sample(&mut rng))).collect::<Vec<_>>())
            .collect();
        let clean = dense.len();
        crate::eval::transfer::add_outliers(&mut dense, 0.05, &mut rng);
        crate::eval::transfer::add_outliers(&mut view, 0.05, &mut rng);
        assert!(dense.len() > 150_000 && clean > 4 * super::register::WORKING_POINTS, "{} points", dense.len());
        let error = |r: &super::Registration| -> f64 {
            let mut errs: Vec<f64> = r
                .keypoints
                .iter()
                .zip(&test.keypoints)
                .map(|(p, t)| (Vector3::from(p.position) - (pose * Point3::from(t.position)).coords).norm() * 1e3)
                .collect();
            errs.sort_by(f64::total_cmp);
            errs[errs.len() / 2]
        };
        let (r_view, r_dense) = (reg.register(&view, &opts).unwrap(), reg.register(&dense, &opts).unwrap());
        view_errors.push(error(&r_view));
        dense_errors.push(error(&r_dense));
        if k > 0 {
            continue;
        }
        assert!(r_dense.fit.confident, "{:?}", r_dense.fit);
        let again = reg.register(&dense, &opts).unwrap();
        assert_eq!(again.keypoints, r_dense.keypoints);
        // The outliers are 1/21 of the cloud; each point of the working subsample stands for ~6 of the cloud.
        let outliers = (dense.len() - clean) as f64 / dense.len() as f64;
        assert!(
            (r_dense.fit.stray_fraction - outliers).abs() < 0.02,
            "stray fraction {:.3}, outliers {outliers:.3}",
            r_dense.fit.stray_fraction
        );
        let counted = r_dense.fit.stray_fraction * dense.len() as f64;
        assert!(
            (r_dense.fit.stray_points as f64 - counted).abs() <= 1.0,
            "{} strays against {counted:.0}",
            r_dense.fit.stray_points
        );
    }
    let (v, d) = (median(&view_errors), median(&dense_errors));
    assert!(d < v.max(2.0) + 1.0, "keypoint median over the views {d:.2} mm, the views alone {v:.2}: {dense_errors:.1?} against {view_errors:.1?}");
}

#[test]
fn a_hidden_handle_leaves_a_yaw_arc_that_holds_the_truth() {
    // Handle straight behind the mug: every turn that keeps it hidden fits,
    // and the registration reports the arc, the true turn inside it, and a
    // spread on the handle's keypoint but none on the base centre (on the
    // axis). Handle towards the camera: the view settles the turn.
    let reg = mug_registrar();
    let t = Translation3::new(0.03, -0.02, 0.0);
    let centre = Point3::new(t.x, t.y, 0.05);
    let step = std::f64::consts::TAU / RegisterOptions::default().yaw_sweep_steps as f64;
    let index = |name: &str| reg.space.keypoints.iter().position(|k| k.name == name).unwrap();
    let (handle, base) = (index("handle_middle"), index("base_centre"));
    let mut report = Vec::new();
    for test in tools::family(Category::Mug).unwrap().into_iter().filter(|i| i.split == Split::Test) {
        for view in [1, 4] {
            let cam = standard_view(view, 8, centre, test.mesh.diagonal(), Intrinsics::default()).unwrap();
            let eye = cam.translation.vector;
            let azimuth = (eye.y - t.y).atan2(eye.x - t.x);
            for offset_deg in [0.0f64, 180.0] {
                let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), azimuth + offset_deg.to_radians());
                let (cloud, _) = capture(&test.mesh, &Isometry3::from_parts(t, rot), centre, view, 5 + view as u64);
                let r = reg
                    .register(&cloud, &RegisterOptions { viewpoint: Some(eye.into()), ..Default::default() })
                    .unwrap();
                let arc = r.yaw_arc.expect("a sweep ran: the up direction is given");
                let spread = r.keypoint_spread_m().unwrap();
                let error = (r.rotation_cloud_from_canonical * rot.inverse()).angle();
                report.push(format!(
                    "{} view {view} handle at {offset_deg}°: arc ±{:.0}°, error {:.0}°, spread handle {:.0} base {:.1} mm",
                    test.name,
                    arc.half_width_rad.to_degrees(),
                    error.to_degrees(),
                    spread[handle] * 1e3,
                    spread[base] * 1e3
                ));
                let a = Vector3::from(arc.axis_cloud);
                assert!(
                    (a.norm() - 1.0).abs() < 1e-9 && a.z > 0.98,
                    "{}: the mug's axis, upright",
                    report.last().unwrap()
                );
                assert!(spread[base] < 0.003, "{}", report.last().unwrap());
                if offset_deg == 0.0 {
                    assert!(arc.half_width_rad < 1.5 * step, "{}", report.last().unwrap());
                } else {
                    assert!(arc.half_width_rad >= step, "{}", report.last().unwrap());
                    assert!(error <= arc.half_width_rad + step / 2.0, "{}", report.last().unwrap());
                    assert!(spread[handle] > 0.01, "{}", report.last().unwrap());
                }
            }
        }
    }
    eprintln!("{}", report.join("\n"));
}

#[test]
fn a_noisy_standing_mug_is_still_told_standing() {
    // Under 2 mm depth noise and 10 % outliers the gate's normals scatter:
    // from 12 neighbours 15 of these 24 views passed, from 24 (`side_facing`) all.
    let reg = mug_registrar();
    let mut kept_every_start = Vec::new();
    for inst in tools::family(Category::Mug).unwrap().iter().filter(|i| i.split == Split::Test) {
        for view in 0..8 {
            let yaw = 0.7 * view as f64;
            let noise = DepthNoise { sigma_m: 0.002, ..DepthNoise::default() };
            let centre = on_table(yaw) * Point3::new(0.0, 0.0, 0.05);
            let (mut cloud, cam) = capture_with(&inst.mesh, &on_table(yaw), centre, view, 9, noise);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(view as u64);
            crate::eval::transfer::add_outliers(&mut cloud, 0.1, &mut rng);
            let opts = RegisterOptions { viewpoint: Some(cam.translation.vector.into()), ..Default::default() };
            let r = reg.register(&cloud, &opts).unwrap();
            if r.hypotheses != opts.yaws {
                kept_every_start.push((inst.name.clone(), view, r.hypotheses));
            }
        }
    }
    assert!(kept_every_start.is_empty(), "views not told standing (tool, view, starts): {kept_every_start:?}");
}

#[test]
fn a_mug_on_its_side_fitted_end_over_end_is_called_ambiguous() {
    // Seen across its body, neither its inside nor its base in view, a mug
    // on its side fits almost as well either end first, and the race now and
    // then picks the wrong end (rim and base swapped, the handle kept). Such
    // a pose must not be reported as certain: the end-over-end turn of the
    // race's winner is raced too (`RegisterOptions::flip_check`). Measured
    // on these 24 views, the race alone (no `recheck_runner_up`): 9 end over
    // end, 7 of them unflagged without the check; with the recheck 4.
    let reg = mug_registrar();
    let family = tools::family(Category::Mug).unwrap();
    let (mut end_over_end, mut alone_end_over_end, mut unflagged_without) = (0, 0, 0);
    for name in ["mug_train_01", "mug_train_04", "mug_train_05"] {
        let inst = family.iter().find(|i| i.name == name).unwrap();
        for (k, yaw) in [0.3f64, 1.1, 1.9, 2.7, 3.5, 4.3, 5.1, 5.9].iter().enumerate() {
            let pose = on_side(&inst.mesh, *yaw);
            let rot = pose.rotation;
            let (cloud, cam_pose) = capture(&inst.mesh, &pose, pose * Point3::origin(), k, k as u64);
            let opts = RegisterOptions { viewpoint: Some(cam_pose.translation.vector.into()), ..Default::default() };
            let r = reg.register(&cloud, &opts).unwrap();
            let rot_err = (r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees();
            if rot_err > 90.0 {
                end_over_end += 1;
                assert!(r.fit.ambiguous_pose, "{name} view {k}: {rot_err:.0}° off, not called ambiguous");
            }
            let alone = RegisterOptions { recheck_runner_up: None, ..opts };
            let r = reg.register(&cloud, &alone).unwrap();
            if (r.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees() > 90.0 {
                alone_end_over_end += 1;
                assert!(r.fit.ambiguous_pose, "{name} view {k}: race alone, end over end, not called ambiguous");
                let without = reg.register(&cloud, &RegisterOptions { flip_check: false, ..alone }).unwrap();
                unflagged_without += usize::from(!without.fit.ambiguous_pose);
            }
        }
    }
    // The views still show what the check is for.
    assert!(
        alone_end_over_end >= 5 && unflagged_without >= 3 && end_over_end <= alone_end_over_end,
        "race alone {alone_end_over_end} end over end, {unflagged_without} unflagged without the check; rechecked {end_over_end}"
    );
}
