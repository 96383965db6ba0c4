//! Tests of the hand model, its loader and its kinematics.

use nalgebra::{DMatrix, Isometry3, Matrix3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

const SIH_ACTUATED: [&str; 5] = [
    "palm_to_if_proximal",
    "palm_to_mf_proximal",
    "palm_to_rf_proximal",
    "palm_to_th_proximal",
    "th_proximal_to_th_inter",
];

fn sih() -> HandModel {
    HandModel::default_sih().expect("bundled SIH loads")
}

fn random_wrist(rng: &mut ChaCha8Rng) -> Isometry3<f64> {
    let t = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
    // Uniform rotation from a normalised 4-D Gaussian-ish draw (uniform cube,
    // rejected outside the ball, is uniform on the sphere after normalising).
    let q = loop {
        let v = nalgebra::Vector4::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n < 1.0 {
            break nalgebra::Quaternion::from(v / n);
        }
    };
    Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_quaternion(q))
}

fn random_actuated(model: &HandModel, rng: &mut ChaCha8Rng) -> Vec<f64> {
    model
        .actuated_limits()
        .iter()
        .map(|&[lo, hi]| {
            // Continuous joints: any angle in one turn each way.
            let (lo, hi) = (lo.max(-std::f64::consts::PI), hi.min(std::f64::consts::PI));
            rng.random_range(lo..hi)
        })
        .collect()
}

/// World positions of all keypoints then all fingertips.
fn points(model: &HandModel, kin: &mut HandKinematics, wrist: &Isometry3<f64>, q: &[f64]) -> Vec<Point3<f64>> {
    kin.update(model, wrist, q);
    kin.keypoints().iter().chain(kin.fingertips()).copied().collect()
}

/// Analytic Jacobian of keypoints then fingertips, (3·P) × (6 + n_a).
fn analytic_jacobian(model: &HandModel, kin: &mut HandKinematics, wrist: &Isometry3<f64>, q: &[f64]) -> DMatrix<f64> {
    kin.update(model, wrist, q);
    let n_kp = model.keypoints().len();
    let n_pts = n_kp + model.fingertips().len();
    let mut jac = DMatrix::zeros(3 * n_pts, WRIST_DOF + model.num_actuated());
    let stacked = kin.update_keypoint_jacobian(model).clone();
    jac.rows_mut(0, 3 * n_kp).copy_from(&stacked);
    for (i, tip) in model.fingertips().iter().enumerate() {
        let p = kin.fingertips()[i];
        let mut rows = jac.fixed_rows_mut::<3>(3 * (n_kp + i));
        kin.point_jacobian(model, tip.link, &p, &mut rows);
    }
    jac
}

/// Central differences through the same perturbation convention.
fn numeric_jacobian(model: &HandModel, kin: &mut HandKinematics, wrist: &Isometry3<f64>, q: &[f64]) -> DMatrix<f64> {
    let h = 1e-5;
    let n_pts = model.keypoints().len() + model.fingertips().len();
    let mut jac = DMatrix::zeros(3 * n_pts, WRIST_DOF + model.num_actuated());
    let mut column = |c: usize, plus: Vec<Point3<f64>>, minus: Vec<Point3<f64>>| {
        for (i, (a, b)) in plus.iter().zip(&minus).enumerate() {
            let d = (a - b) / (2.0 * h);
            jac.fixed_view_mut::<3, 1>(3 * i, c).copy_from(&d);
        }
    };
    for c in 0..WRIST_DOF {
        let mut delta = Vector6::zeros();
        delta[c] = h;
        let plus = points(model, kin, &perturb_wrist(wrist, &delta), q);
        let minus = points(model, kin, &perturb_wrist(wrist, &-delta), q);
        column(c, plus, minus);
    }
    for a in 0..model.num_actuated() {
        let (mut qp, mut qm) = (q.to_vec(), q.to_vec());
        qp[a] += h;
        qm[a] -= h;
        let plus = points(model, kin, wrist, &qp);
        let minus = points(model, kin, wrist, &qm);
        column(WRIST_DOF + a, plus, minus);
    }
    jac
}

/// Largest column error relative to the column's size (floored at 1 mm of
/// lever so exactly-zero columns compare absolutely).
fn max_relative_error(analytic: &DMatrix<f64>, numeric: &DMatrix<f64>) -> f64 {
    let mut worst: f64 = 0.0;
    for c in 0..analytic.ncols() {
        let a = analytic.column(c);
        let n = numeric.column(c);
        let err = (a - n).amax();
        let scale = a.amax().max(1e-3);
        worst = worst.max(err / scale);
    }
    worst
}

fn check_jacobians(model: &HandModel, seed: u64, trials: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut kin = HandKinematics::new(model);
    for trial in 0..trials {
        let wrist = random_wrist(&mut rng);
        let q = random_actuated(model, &mut rng);
        let analytic = analytic_jacobian(model, &mut kin, &wrist, &q);
        let numeric = numeric_jacobian(model, &mut kin, &wrist, &q);
        let wrist_err =
            max_relative_error(&analytic.columns(0, WRIST_DOF).into(), &numeric.columns(0, WRIST_DOF).into());
        let n_a = model.num_actuated();
        let joint_err =
            max_relative_error(&analytic.columns(WRIST_DOF, n_a).into(), &numeric.columns(WRIST_DOF, n_a).into());
        assert!(wrist_err < 1e-6, "trial {trial}: wrist Jacobian relative error {wrist_err:e}");
        assert!(joint_err < 1e-6, "trial {trial}: actuated Jacobian relative error {joint_err:e}");
    }
}

// ---------------------------------------------------------------- SIH model

#[test]
fn sih_structure() {
    let hand = sih();
    assert_eq!(hand.name(), "sih_right");
    assert_eq!(hand.links().len(), 12);
    let revolute = hand.joints().iter().filter(|j| j.kind == JointKind::Revolute).count();
    assert_eq!(revolute, 11);
    assert_eq!(hand.joints().len(), 11);
    assert_eq!(hand.moving_joints().len(), 11);
    assert_eq!(hand.num_actuated(), 5);
    assert_eq!(hand.actuated_names().collect::<Vec<_>>(), SIH_ACTUATED);
    let mimics: Vec<_> = hand.joints().iter().filter(|j| matches!(j.drive, JointDrive::Mimic { .. })).collect();
    assert_eq!(mimics.len(), 6);
    for j in &mimics {
        let JointDrive::Mimic { multiplier, offset, .. } = j.drive else { unreachable!() };
        assert_eq!((multiplier, offset), (1.0, 0.0), "{} is coupled 1:1", j.name);
    }
    let driver_of = |name: &str| match hand.joints()[hand.joint_index(name).unwrap()].drive {
        JointDrive::Mimic { driver, .. } => SIH_ACTUATED[driver],
        other => panic!("{name} is {other:?}"),
    };
    assert_eq!(driver_of("if_proximal_to_if_distal"), "palm_to_if_proximal");
    assert_eq!(driver_of("mf_proximal_to_mf_distal"), "palm_to_mf_proximal");
    assert_eq!(driver_of("rf_proximal_to_rf_distal"), "palm_to_rf_proximal");
    assert_eq!(driver_of("palm_to_lf_proximal"), "palm_to_rf_proximal");
    assert_eq!(driver_of("lf_proximal_to_lf_distal"), "palm_to_rf_proximal");
    assert_eq!(driver_of("th_inter_to_th_distal"), "th_proximal_to_th_inter");
    assert_eq!(hand.links()[hand.root_link()].name, "palm");
    let f = std::f64::consts::FRAC_PI_2;
    for [lo, hi] in &hand.actuated_limits()[..4] {
        assert!((lo + f).abs() < 1e-3 && *hi == 0.0);
    }
    let [lo, hi] = hand.actuated_limits()[4];
    assert!(lo == 0.0 && (hi - f).abs() < 1e-3);
}

#[test]
fn sih_keypoints_file() {
    let hand = sih();
    let names: Vec<_> = hand.keypoints().iter().map(|k| k.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "palm",
            "if_proximal",
            "if_distal",
            "mf_proximal",
            "mf_distal",
            "rf_proximal",
            "rf_distal",
            "lf_proximal",
            "lf_distal",
            "th_proximal",
            "th_inter",
            "th_distal"
        ]
    );
    assert_eq!(hand.fingertips().len(), 5);
    let palm = &hand.keypoints()[0];
    assert_eq!(hand.links()[palm.link].name, "palm");
    assert_eq!(palm.offset, Vector3::new(0.0, 0.018, 0.09));
    assert_eq!(hand.palm_normal().into_inner(), Vector3::y());
    assert_eq!(hand.open_hand().len(), 5);
    assert_eq!(&hand.open_hand()[..3], &[0.0, 0.0, 0.0], "fingers straight");
    assert!(hand.open_hand()[3] < 0.0, "thumb slightly opposed");
}

#[test]
fn sih_fingertips_at_zero() {
    let hand = sih();
    let mut kin = HandKinematics::new(&hand);
    kin.update(&hand, &Isometry3::identity(), &[0.0; 5]);
    let expected =
        [("if_tip", -0.0435, 0.241), ("mf_tip", -0.0187, 0.254), ("rf_tip", 0.0069, 0.234), ("lf_tip", 0.032, 0.211)];
    for (i, (name, x, z)) in expected.iter().enumerate() {
        assert_eq!(hand.fingertips()[i].name, *name);
        let p = kin.fingertips()[i];
        assert!((p.z - z).abs() < 5e-3, "{name} z = {}", p.z);
        assert!((p.x - x).abs() < 2e-3, "{name} x = {}", p.x);
        assert!(p.y.abs() < 1e-12, "{name} y = {}", p.y);
    }
    // The thumb is on the -x side, beyond the index finger.
    let thumb = kin.fingertips()[4];
    assert!(thumb.x < -0.1, "thumb tip x = {}", thumb.x);
    // The palmar keypoints face +y.
    for k in kin.keypoints().iter().take(9) {
        assert!(k.y > 0.0);
    }
}

#[test]
fn sih_flexion_is_toward_the_palm() {
    let hand = sih();
    let mut kin = HandKinematics::new(&hand);
    let half_pi = std::f64::consts::FRAC_PI_2;
    kin.update(&hand, &Isometry3::identity(), &[-half_pi, 0.0, 0.0, 0.0, 0.0]);
    // Proximal along +y (0.048), distal turned back along -z (0.052).
    let tip = kin.fingertips()[0];
    let expected = Point3::new(-0.0435, 0.048, 0.141 - 0.052);
    assert!((tip - expected).norm() < 1e-12, "index tip {tip}");
    // Opposed thumb (rotation -pi/2) points out of the palm, along +y.
    kin.update(&hand, &Isometry3::identity(), &[0.0, 0.0, 0.0, -half_pi, 0.0]);
    let thumb = kin.fingertips()[4];
    let base = Point3::new(-0.034, 0.019, 0.08);
    let d = thumb - base;
    assert!(d.y > 0.09 && d.x.abs() < 0.01, "opposed thumb offset {d}");
    // Its bend then curls it toward +z (the fingers).
    kin.update(&hand, &Isometry3::identity(), &[0.0, 0.0, 0.0, -half_pi, 0.8]);
    assert!(kin.fingertips()[4].z > thumb.z + 0.03);
}

#[test]
fn sih_mimic_expansion() {
    let hand = sih();
    let mut kin = HandKinematics::new(&hand);
    let q = [-0.3, -0.5, -0.7, -0.2, 0.9];
    kin.update(&hand, &Isometry3::identity(), &q);
    for (k, &j) in hand.moving_joints().iter().enumerate() {
        let expected = match hand.joints()[j].drive {
            JointDrive::Actuated { index } => q[index],
            JointDrive::Mimic { driver, multiplier, offset } => multiplier * q[driver] + offset,
            JointDrive::Fixed => unreachable!(),
        };
        assert_eq!(kin.joint_positions()[k], expected);
    }
}

#[test]
fn sih_jacobians_match_finite_differences() {
    check_jacobians(&sih(), 7, 25);
}

#[test]
fn sih_wrist_pose_moves_everything_rigidly() {
    let hand = sih();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut kin = HandKinematics::new(&hand);
    let q = random_actuated(&hand, &mut rng);
    kin.update(&hand, &Isometry3::identity(), &q);
    let local: Vec<_> = kin.keypoints().to_vec();
    let wrist = random_wrist(&mut rng);
    kin.update(&hand, &wrist, &q);
    for (a, b) in local.iter().zip(kin.keypoints()) {
        assert!((wrist * a - b).norm() < 1e-12);
    }
    let n = kin.palm_normal(&hand);
    assert!((n.into_inner() - wrist.rotation * Vector3::y()).norm() < 1e-12);
}

#[test]
fn sih_collision_primitives() {
    let hand = sih();
    // Palm: two boxes; 11 phalanges: one cylinder and two spheres each.
    let prims = hand.collision_primitives();
    assert_eq!(prims.len(), 2 + 11 * 3);
    let palm = &prims[0];
    let CollisionShape::Box { half_extents } = palm.shape else { panic!("palm plate is a box") };
    assert!((half_extents - Vector3::new(0.049, 0.015, 0.0425)).norm() < 1e-12);
    // Palm keypoint lies on the plate's palmar face.
    assert!((palm.origin.translation.y + half_extents.y - 0.018).abs() < 1e-12);

    // Each capsule's cylinder ends at its two spheres, in any configuration.
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut kin = HandKinematics::new(&hand);
    let wrist = random_wrist(&mut rng);
    let q = random_actuated(&hand, &mut rng);
    kin.update(&hand, &wrist, &q);
    let poses = kin.collision_poses();
    let mut capsules = 0;
    for (i, p) in prims.iter().enumerate() {
        if let CollisionShape::Cylinder { radius, half_length } = p.shape {
            let (CollisionShape::Sphere { radius: r0 }, CollisionShape::Sphere { radius: r1 }) =
                (prims[i + 1].shape, prims[i + 2].shape)
            else {
                panic!("cylinder {i} is followed by its two spheres")
            };
            assert_eq!((r0, r1), (radius, radius));
            let ends = [poses[i] * Point3::new(0.0, 0.0, -half_length), poses[i] * Point3::new(0.0, 0.0, half_length)];
            let caps = [poses[i + 1] * Point3::origin(), poses[i + 2] * Point3::origin()];
            let d = (ends[0] - caps[0]).norm().min((ends[0] - caps[1]).norm())
                + (ends[1] - caps[0]).norm().min((ends[1] - caps[1]).norm());
            assert!(d < 1e-9, "capsule {:?} ends off its caps by {d}", p.name);
            capsules += 1;
        }
        assert!((poses[i].to_homogeneous() - (kin.link_pose(p.link) * p.origin).to_homogeneous()).amax() < 1e-15);
    }
    assert_eq!(capsules, 11);
    // Palmar keypoints of the phalanges sit on their capsule surfaces.
    kin.update(&hand, &Isometry3::identity(), &[0.0; 5]);
    for k in &hand.keypoints()[1..] {
        let (i, r) = prims
            .iter()
            .enumerate()
            .find_map(|(i, p)| match p.shape {
                CollisionShape::Cylinder { radius, .. } if p.link == k.link => Some((i, radius)),
                _ => None,
            })
            .unwrap();
        let local = prims[i].origin.inverse() * Point3::from(k.offset);
        let radial = (local.x * local.x + local.y * local.y).sqrt();
        assert!((radial - r).abs() < 1e-6, "{} is {radial} from its capsule axis, radius {r}", k.name);
    }
}

#[test]
fn from_urdf_file_reports_a_missing_file() {
    let err = HandModel::from_urdf_file("/nonexistent/hand.urdf", "/nonexistent/kp.json").unwrap_err();
    assert!(matches!(err, HandModelError::Io { .. }));
    assert!(err.to_string().contains("/nonexistent/hand.urdf"));
}

// ---------------------------------------------------------- another hand

/// A 3-finger test gripper unlike the SIH: a fixed, tilted mount; a tilted
/// unnormalised axis; a mimic with multiplier -1 and offset 0.1 whose limits
/// narrow its driver; a continuous driver with a 0.5 / -0.2 follower; a
/// prismatic driver with a 20:1 revolute follower.
const GRIPPER_URDF: &str = r#"<?xml version="1.0"?>
<robot name="test_gripper">
  <link name="base"><collision><geometry><cylinder radius="0.04" length="0.02"/></geometry></collision></link>
  <link name="mount"/>
  <link name="a1"><collision><origin xyz="0 0 0.02"/><geometry><capsule radius="0.01" length="0.04"/></geometry></collision></link>
  <link name="a2"/>
  <link name="a_tip"/>
  <link name="b1"/>
  <link name="b2"><collision><origin xyz="0 0 0.01" rpy="0.2 0 0"/><geometry><box size="0.02 0.01 0.03"/></geometry></collision></link>
  <link name="c_slide"/>
  <link name="c1"/>
  <joint name="base_to_mount" type="fixed">
    <origin xyz="0 0 0.05" rpy="0.1 -0.2 0.3"/>
    <parent link="base"/><child link="mount"/>
  </joint>
  <joint name="mount_to_a1" type="revolute">
    <origin xyz="0.03 0 0.02" rpy="0 0.3 0"/>
    <parent link="mount"/><child link="a1"/>
    <axis xyz="0 1 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="a1_to_a2" type="revolute">
    <origin xyz="0 0 0.04"/>
    <parent link="a1"/><child link="a2"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.5" upper="1.0" effort="1" velocity="1"/>
    <mimic joint="mount_to_a1" multiplier="-1" offset="0.1"/>
  </joint>
  <joint name="a2_to_tip" type="fixed">
    <origin xyz="0 0.005 0.03" rpy="0 0 0.5"/>
    <parent link="a2"/><child link="a_tip"/>
  </joint>
  <joint name="mount_to_b1" type="continuous">
    <origin xyz="-0.03 0.01 0.02" rpy="0 0 2.0"/>
    <parent link="mount"/><child link="b1"/>
    <axis xyz="0 0 1"/>
  </joint>
  <joint name="b1_to_b2" type="revolute">
    <origin xyz="0 0.01 0.04"/>
    <parent link="b1"/><child link="b2"/>
    <axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>
    <mimic joint="mount_to_b1" multiplier="0.5" offset="-0.2"/>
  </joint>
  <joint name="mount_to_c_slide" type="prismatic">
    <origin xyz="0 -0.03 0.02"/>
    <parent link="mount"/><child link="c_slide"/>
    <axis xyz="0 0.6 0.8"/>
    <limit lower="0" upper="0.02" effort="1" velocity="1"/>
  </joint>
  <joint name="c_slide_to_c1" type="revolute">
    <origin xyz="0 0 0.01"/>
    <parent link="c_slide"/><child link="c1"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.5" upper="0.5" effort="1" velocity="1"/>
    <mimic joint="mount_to_c_slide" multiplier="20"/>
  </joint>
</robot>
"#;

const GRIPPER_KEYPOINTS: &str = r#"{
  "keypoints": [
    { "name": "base", "link": "base", "offset": [0, 0.01, 0.02] },
    { "name": "a1", "link": "a1", "offset": [0.005, 0.01, 0.02] },
    { "name": "a_tip", "link": "a_tip", "offset": [0, 0, 0.01] },
    { "name": "b2", "link": "b2", "offset": [0.01, 0.01, 0.03] },
    { "name": "c1", "link": "c1", "offset": [0, 0.01, 0.03] }
  ],
  "fingertips": [ { "name": "c_tip", "link": "c1", "offset": [0, 0, 0.05] } ],
  "palm_normal": [0, 0, 2],
  "open_hand": { "mount_to_a1": 0.1, "mount_to_b1": 0.0, "mount_to_c_slide": 0.01 }
}"#;

fn gripper() -> HandModel {
    HandModel::from_urdf_str(GRIPPER_URDF, GRIPPER_KEYPOINTS).expect("gripper loads")
}

#[test]
fn gripper_structure() {
    let g = gripper();
    assert_eq!(g.links().len(), 9);
    assert_eq!(g.joints().len(), 8);
    assert_eq!(g.moving_joints().len(), 6);
    assert_eq!(g.actuated_names().collect::<Vec<_>>(), ["mount_to_a1", "mount_to_b1", "mount_to_c_slide"]);
    assert_eq!(g.joints()[g.joint_index("mount_to_b1").unwrap()].kind, JointKind::Continuous);
    assert_eq!(g.joints()[g.joint_index("mount_to_c_slide").unwrap()].kind, JointKind::Prismatic);
    // a2 = -a1 + 0.1 within [-0.5, 1.0] narrows a1 to [-0.9, 0.6].
    let [lo, hi] = g.actuated_limits()[0];
    assert!((lo + 0.9).abs() < 1e-12 && (hi - 0.6).abs() < 1e-12, "a1 limits [{lo}, {hi}]");
    // b2 = 0.5 b1 - 0.2 within [-3, 3] bounds the continuous b1 to [-5.6, 6.4].
    let [lo, hi] = g.actuated_limits()[1];
    assert!((lo + 5.6).abs() < 1e-12 && (hi - 6.4).abs() < 1e-12, "b1 limits [{lo}, {hi}]");
    // c1 = 20 c within [-0.5, 0.5] leaves the slide's own [0, 0.02].
    assert_eq!(g.actuated_limits()[2], [0.0, 0.02]);
    assert_eq!(g.open_hand(), &[0.1, 0.0, 0.01]);
    assert!((g.palm_normal().into_inner() - Vector3::z()).norm() < 1e-15);
    // Cylinder + capsule (cylinder and two caps) + box.
    assert_eq!(g.collision_primitives().len(), 5);
    let mut q = [5.0, -9.0, 0.5];
    g.clamp_actuated(&mut q);
    assert_eq!(q, [0.6, -5.6, 0.02]);
}

/// URDF rpy by its definition, R = Rz(yaw)·Ry(pitch)·Rx(roll), written out.
fn rpy_matrix(r: f64, p: f64, y: f64) -> Matrix3<f64> {
    let (sr, cr, sp, cp, sy, cy) = (r.sin(), r.cos(), p.sin(), p.cos(), y.sin(), y.cos());
    let rx = Matrix3::new(1.0, 0.0, 0.0, 0.0, cr, -sr, 0.0, sr, cr);
    let ry = Matrix3::new(cp, 0.0, sp, 0.0, 1.0, 0.0, -sp, 0.0, cp);
    let rz = Matrix3::new(cy, -sy, 0.0, sy, cy, 0.0, 0.0, 0.0, 1.0);
    rz * ry * rx
}

/// Rotation about a unit axis by Rodrigues' formula.
fn rodrigues(axis: Vector3<f64>, angle: f64) -> Matrix3<f64> {
    let k = axis.cross_matrix();
    Matrix3::identity() + k * angle.sin() + k * k * (1.0 - angle.cos())
}

fn homogeneous(r: Matrix3<f64>, t: Vector3<f64>) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
    m
}

#[test]
fn gripper_forward_kinematics_by_hand() {
    let g = gripper();
    let mut kin = HandKinematics::new(&g);
    let wrist = Isometry3::from_parts(
        Translation3::new(0.3, -0.2, 0.5),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.7),
    );
    let q = [0.35, 1.2, 0.013];
    kin.update(&g, &wrist, &q);
    let w = wrist.to_homogeneous();
    let mount = w * homogeneous(rpy_matrix(0.1, -0.2, 0.3), Vector3::new(0.0, 0.0, 0.05));

    // Finger A, through the -1 / 0.1 mimic and the fixed tip frame.
    let a1 = mount
        * homogeneous(rpy_matrix(0.0, 0.3, 0.0), Vector3::new(0.03, 0.0, 0.02))
        * homogeneous(rodrigues(Vector3::new(0.0, 1.0, 1.0).normalize(), q[0]), Vector3::zeros());
    let a2 = a1 * homogeneous(rodrigues(Vector3::x(), -q[0] + 0.1), Vector3::new(0.0, 0.0, 0.04));
    let a_tip = a2 * homogeneous(rpy_matrix(0.0, 0.0, 0.5), Vector3::new(0.0, 0.005, 0.03));
    let expected = a_tip * nalgebra::Vector4::new(0.0, 0.0, 0.01, 1.0);
    assert!((kin.keypoints()[2].coords - expected.xyz()).norm() < 1e-12);

    // Finger B: continuous driver, 0.5 / -0.2 follower.
    let b1 = mount
        * homogeneous(rpy_matrix(0.0, 0.0, 2.0), Vector3::new(-0.03, 0.01, 0.02))
        * homogeneous(rodrigues(Vector3::z(), q[1]), Vector3::zeros());
    let b2 = b1 * homogeneous(rodrigues(Vector3::x(), 0.5 * q[1] - 0.2), Vector3::new(0.0, 0.01, 0.04));
    let expected = b2 * nalgebra::Vector4::new(0.01, 0.01, 0.03, 1.0);
    assert!((kin.keypoints()[3].coords - expected.xyz()).norm() < 1e-12);

    // Finger C: prismatic slide along (0, 0.6, 0.8), 20:1 follower.
    let slide =
        mount * homogeneous(Matrix3::identity(), Vector3::new(0.0, -0.03, 0.02) + Vector3::new(0.0, 0.6, 0.8) * q[2]);
    let c1 = slide * homogeneous(rodrigues(Vector3::x(), 20.0 * q[2]), Vector3::new(0.0, 0.0, 0.01));
    let expected = c1 * nalgebra::Vector4::new(0.0, 0.0, 0.05, 1.0);
    assert!((kin.fingertips()[0].coords - expected.xyz()).norm() < 1e-12);

    // The box collision primitive of b2, with its own rpy.
    let b2_box = b2 * homogeneous(rpy_matrix(0.2, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.01));
    assert!((kin.collision_poses()[4].to_homogeneous() - b2_box).amax() < 1e-12);
}

#[test]
fn gripper_jacobians_match_finite_differences() {
    check_jacobians(&gripper(), 19, 25);
}

#[test]
fn keypoint_jacobian_buffer_is_reused() {
    let g = sih();
    let mut kin = HandKinematics::new(&g);
    let ptr = kin.keypoint_jacobian().as_ptr();
    for q in [[-0.1; 5], [-0.2, -0.3, -0.4, -0.5, 0.6]] {
        kin.update(&g, &Isometry3::identity(), &q);
        let jac = kin.update_keypoint_jacobian(&g);
        assert_eq!(jac.shape(), (36, 11));
        assert_eq!(jac.as_ptr(), ptr);
    }
}

// -------------------------------------------------------- malformed input

/// A valid two-link robot with `joint` substituted in, plus any extra XML.
fn robot(extra: &str) -> String {
    format!(r#"<robot name="r"><link name="base"/><link name="f1"/><link name="f2"/>{extra}</robot>"#)
}

fn revolute(name: &str, parent: &str, child: &str, inner: &str) -> String {
    format!(
        r#"<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/><axis xyz="1 0 0"/>{inner}</joint>"#
    )
}

const LIMIT: &str = r#"<limit lower="-1" upper="1" effort="1" velocity="1"/>"#;
const KP: &str = r#"{ "keypoints": [], "palm_normal": [0, 1, 0] }"#;

fn load_err(urdf: &str) -> HandModelError {
    match HandModel::from_urdf_str(urdf, KP) {
        Ok(_) => panic!("accepted a bad URDF:\n{urdf}"),
        Err(e) => e,
    }
}

#[test]
fn the_test_template_is_valid() {
    let urdf = robot(&(revolute("j1", "base", "f1", LIMIT) + &revolute("j2", "f1", "f2", LIMIT)));
    let m = HandModel::from_urdf_str(&urdf, KP).unwrap();
    assert_eq!(m.num_actuated(), 2);
    assert_eq!(m.open_hand(), &[0.0, 0.0]);
}

#[test]
fn malformed_urdf_errors_name_the_element() {
    let two = |a: String| robot(&(revolute("j1", "base", "f1", LIMIT) + &a));
    // (what, URDF, expected variant, words the message must contain)
    type Case = (&'static str, String, fn(&HandModelError) -> bool, &'static [&'static str]);
    let cases: Vec<Case> = vec![
        (
            "missing parent link",
            two(revolute("j2", "ghost", "f2", LIMIT)),
            |e| matches!(e, HandModelError::MissingLink { role: "parent", .. }),
            &["j2", "ghost"],
        ),
        (
            "missing child link",
            two(revolute("j2", "f1", "ghost", LIMIT)),
            |e| matches!(e, HandModelError::MissingLink { role: "child", .. }),
            &["j2", "ghost"],
        ),
        (
            "multiple roots",
            robot(&revolute("j1", "base", "f1", LIMIT)),
            |e| matches!(e, HandModelError::MultipleRoots { .. }),
            &["base", "f2"],
        ),
        (
            "loop below the root",
            robot(&(revolute("j1", "f1", "f2", LIMIT) + &revolute("j2", "f2", "f1", LIMIT))),
            |e| matches!(e, HandModelError::KinematicLoop { .. }),
            &["loop", "f"],
        ),
        (
            "loop with no root",
            r#"<robot name="r"><link name="x"/><link name="y"/>"#.to_string()
                + &revolute("j1", "x", "y", LIMIT)
                + &revolute("j2", "y", "x", LIMIT)
                + "</robot>",
            |e| matches!(e, HandModelError::KinematicLoop { .. }),
            &["loop"],
        ),
        (
            "closed chain",
            two(revolute("j2", "base", "f1", LIMIT)),
            |e| matches!(e, HandModelError::MultipleParents { .. }),
            &["f1", "j1", "j2"],
        ),
        (
            "zero-width limits",
            two(revolute("j2", "f1", "f2", r#"<limit lower="0.5" upper="0.5" effort="1" velocity="1"/>"#)),
            |e| matches!(e, HandModelError::InvalidLimits { .. }),
            &["j2", "zero-width"],
        ),
        (
            "missing limits",
            two(revolute("j2", "f1", "f2", "")),
            |e| matches!(e, HandModelError::InvalidLimits { .. }),
            &["j2"],
        ),
        (
            "inverted limits",
            two(revolute("j2", "f1", "f2", r#"<limit lower="1" upper="-1" effort="1" velocity="1"/>"#)),
            |e| matches!(e, HandModelError::InvalidLimits { .. }),
            &["j2", "above"],
        ),
        (
            "mimic of an unknown joint",
            two(revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<mimic joint="ghost"/>"#))),
            |e| matches!(e, HandModelError::MimicUnknownJoint { .. }),
            &["j2", "ghost"],
        ),
        (
            "mimic of itself",
            two(revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<mimic joint="j2"/>"#))),
            |e| matches!(e, HandModelError::MimicSelf { .. }),
            &["j2"],
        ),
        (
            "mimic of a mimic",
            robot(
                &(revolute("j1", "base", "f1", &format!(r#"{LIMIT}<mimic joint="j2"/>"#))
                    + &revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<mimic joint="j1"/>"#))),
            ),
            |e| matches!(e, HandModelError::MimicOfMimic { .. }),
            &["j1", "j2"],
        ),
        (
            "mimic of a fixed joint",
            robot(
                &(r#"<joint name="j1" type="fixed"><parent link="base"/><child link="f1"/></joint>"#.to_string()
                    + &revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<mimic joint="j1"/>"#))),
            ),
            |e| matches!(e, HandModelError::MimicOfFixed { .. }),
            &["j2", "j1"],
        ),
        (
            "mimic limits that leave the driver no range",
            two(revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<mimic joint="j1" offset="5"/>"#))),
            |e| matches!(e, HandModelError::InconsistentMimicLimits { .. }),
            &["j1"],
        ),
        (
            "unsupported joint type",
            two(r#"<joint name="j2" type="floating"><parent link="f1"/><child link="f2"/></joint>"#.into()),
            |e| matches!(e, HandModelError::UnsupportedJointType { .. }),
            &["j2", "floating"],
        ),
        (
            "zero axis",
            two(r#"<joint name="j2" type="revolute"><parent link="f1"/><child link="f2"/><axis xyz="0 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>"#.into()),
            |e| matches!(e, HandModelError::InvalidAxis { .. }),
            &["j2", "axis"],
        ),
        (
            "non-finite origin",
            two(revolute("j2", "f1", "f2", &format!(r#"{LIMIT}<origin xyz="NaN 0 0"/>"#))),
            |e| matches!(e, HandModelError::NonFinite { .. }),
            &["j2", "origin"],
        ),
        (
            "duplicate joint",
            two(revolute("j1", "f1", "f2", LIMIT)),
            |e| matches!(e, HandModelError::DuplicateJoint { .. }),
            &["j1"],
        ),
        (
            "duplicate link",
            r#"<robot name="r"><link name="a"/><link name="a"/></robot>"#.into(),
            |e| matches!(e, HandModelError::DuplicateLink { .. }),
            &["`a`"],
        ),
        (
            "no links",
            r#"<robot name="empty"></robot>"#.into(),
            |e| matches!(e, HandModelError::NoLinks { .. }),
            &["empty"],
        ),
        (
            "collision mesh",
            r#"<robot name="r"><link name="base"><collision><geometry><mesh filename="palm.stl"/></geometry></collision></link></robot>"#.into(),
            |e| matches!(e, HandModelError::InvalidCollision { index: 0, .. }),
            &["base", "palm.stl"],
        ),
        (
            "negative sphere radius",
            r#"<robot name="r"><link name="base"><collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision><collision><geometry><sphere radius="-1"/></geometry></collision></link></robot>"#.into(),
            |e| matches!(e, HandModelError::InvalidCollision { index: 1, .. }),
            &["base", "collision 1", "radius"],
        ),
        (
            "unclosed tag",
            r#"<robot name="r"><link name="base"></robot>"#.into(),
            |e| matches!(e, HandModelError::MalformedUrdf { .. }),
            &["malformed URDF"],
        ),
        (
            "not XML",
            "this is not a URDF".into(),
            |e| matches!(e, HandModelError::MalformedUrdf { .. }),
            &["malformed URDF"],
        ),
        (
            "empty text",
            String::new(),
            |e| matches!(e, HandModelError::MalformedUrdf { .. }),
            &["malformed URDF"],
        ),
        (
            "joint without a child",
            two(r#"<joint name="j2" type="revolute"><parent link="f1"/></joint>"#.into()),
            |e| matches!(e, HandModelError::MalformedUrdf { .. }),
            &["child"],
        ),
        (
            "number that is not a number",
            two(revolute("j2", "f1", "f2", r#"<limit lower="minus one" upper="1" effort="1" velocity="1"/>"#)),
            |e| matches!(e, HandModelError::MalformedUrdf { .. }),
            &["malformed URDF"],
        ),
    ];
    for (what, urdf, is_expected, words) in cases {
        let err = load_err(&urdf);
        let msg = err.to_string();
        assert!(is_expected(&err), "{what}: unexpected error {err:?}");
        for w in words {
            assert!(msg.contains(w), "{what}: message `{msg}` does not name `{w}`");
        }
    }
}

#[test]
fn malformed_keypoints_errors_name_the_element() {
    let urdf = robot(&(revolute("j1", "base", "f1", LIMIT) + &revolute("j2", "f1", "f2", LIMIT)));
    let cases: [(&str, &str, &[&str]); 9] = [
        ("not JSON", "{ keypoints: ", &["malformed keypoints"]),
        ("unknown field", r#"{ "keypoints": [], "palm_normal": [0,1,0], "palm_norml": [0,1,0] }"#, &["palm_norml"]),
        (
            "keypoint on an unknown link",
            r#"{ "keypoints": [ {"name": "k1", "link": "nowhere", "offset": [0,0,0]} ], "palm_normal": [0,1,0] }"#,
            &["k1", "nowhere"],
        ),
        (
            "fingertip on an unknown link",
            r#"{ "keypoints": [], "fingertips": [ {"name": "t1", "link": "nowhere", "offset": [0,0,0]} ], "palm_normal": [0,1,0] }"#,
            &["fingertip", "t1", "nowhere"],
        ),
        (
            "duplicate keypoint",
            r#"{ "keypoints": [ {"name": "k", "link": "f1", "offset": [0,0,0]}, {"name": "k", "link": "f2", "offset": [0,0,0]} ], "palm_normal": [0,1,0] }"#,
            &["`k`"],
        ),
        ("zero palm normal", r#"{ "keypoints": [], "palm_normal": [0,0,0] }"#, &["palm_normal"]),
        (
            "open hand on a missing joint",
            r#"{ "keypoints": [], "palm_normal": [0,1,0], "open_hand": { "j1": 0, "j9": 0 } }"#,
            &["j9"],
        ),
        (
            "open hand incomplete",
            r#"{ "keypoints": [], "palm_normal": [0,1,0], "open_hand": { "j1": 0 } }"#,
            &["j2", "missing"],
        ),
        (
            "open hand out of range",
            r#"{ "keypoints": [], "palm_normal": [0,1,0], "open_hand": { "j1": 0, "j2": 2 } }"#,
            &["j2", "range"],
        ),
    ];
    for (what, json, words) in cases {
        let err = match HandModel::from_urdf_str(&urdf, json) {
            Ok(_) => panic!("{what}: accepted"),
            Err(e) => e,
        };
        let msg = err.to_string();
        for w in words {
            assert!(msg.contains(w), "{what}: message `{msg}` does not name `{w}`");
        }
    }
}

/// A collision given as a mesh (a 10 × 10 × 40 mm box, scaled, placed by
/// the collision's origin) becomes the capsule enclosing it, in the link's
/// frame; a mesh that cannot be read is an error naming it.
#[test]
fn a_collision_mesh_becomes_the_capsule_enclosing_it() {
    let dir = tempfile::tempdir().unwrap();
    let meshes = dir.path().join("meshes");
    std::fs::create_dir_all(&meshes).unwrap();
    let corners: Vec<[f64; 3]> =
        (0..8).map(|i| [(i & 1) as f64 * 0.01, ((i >> 1) & 1) as f64 * 0.01, (i >> 2) as f64 * 0.04]).collect();
    let mut obj: String = corners.iter().map(|c| format!("v {} {} {}\n", c[0], c[1], c[2])).collect();
    for f in [
        [1, 3, 2],
        [2, 3, 4],
        [5, 6, 8],
        [5, 8, 7],
        [1, 2, 6],
        [1, 6, 5],
        [3, 7, 8],
        [3, 8, 4],
        [1, 5, 7],
        [1, 7, 3],
        [2, 4, 8],
        [2, 8, 6],
    ] {
        obj += &format!("f {} {} {}\n", f[0], f[1], f[2]);
    }
    std::fs::write(meshes.join("phalanx.obj"), obj).unwrap();
    let urdf = r#"<robot name="r"><link name="base"><collision><origin xyz="0.1 0 0" rpy="0 0 1.5707963267948966"/><geometry><mesh filename="../meshes/phalanx.obj" scale="1 1 0.5"/></geometry></collision></link></robot>"#;
    let urdf_dir = dir.path().join("urdf");
    std::fs::create_dir_all(&urdf_dir).unwrap();
    std::fs::write(urdf_dir.join("r.urdf"), urdf).unwrap();
    std::fs::write(urdf_dir.join("k.json"), r#"{ "keypoints": [], "palm_normal": [0,1,0] }"#).unwrap();
    let hand = HandModel::from_urdf_file(urdf_dir.join("r.urdf"), urdf_dir.join("k.json")).unwrap();
    let prims = hand.collision_primitives();
    assert_eq!(prims.len(), 3, "a cylinder and its two caps: {prims:?}");
    let CollisionShape::Cylinder { radius, half_length } = prims[0].shape else { panic!("{prims:?}") };
    // The box scaled to 10 × 10 × 20 mm: radius its cross-section's half
    // diagonal, 7.1 mm; its corners on the cylinder's rims, 20 mm apart.
    assert!((radius - 0.005 * 2f64.sqrt()).abs() < 1e-9, "{radius} {prims:?}");
    assert!((half_length - 0.01).abs() < 1e-9, "{half_length}");
    // Every corner, scaled and placed by the collision's origin, lies in the capsule.
    let origin = Isometry3::from_parts(
        Translation3::new(0.1, 0.0, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
    );
    for c in &corners {
        let p = origin * Point3::new(c[0], c[1], 0.5 * c[2]);
        let inside = prims.iter().any(|prim| {
            let local = prim.origin.inverse_transform_point(&p);
            match prim.shape {
                CollisionShape::Sphere { radius } => local.coords.norm() <= radius + 1e-12,
                CollisionShape::Cylinder { radius, half_length } => {
                    local.z.abs() <= half_length + 1e-12 && local.coords.xy().norm() <= radius + 1e-12
                }
                CollisionShape::Box { .. } => false,
            }
        });
        assert!(inside, "corner {p:?} outside {prims:?}");
    }
    // A format that is not read, and a file that is not there.
    for (file, words) in [("hand.dae", &["hand.dae", "OBJ and STL"][..]), ("gone.obj", &["gone.obj"][..])] {
        let text = urdf.replace("../meshes/phalanx.obj", file);
        std::fs::write(urdf_dir.join("bad.urdf"), text).unwrap();
        let e = HandModel::from_urdf_file(urdf_dir.join("bad.urdf"), urdf_dir.join("k.json")).unwrap_err().to_string();
        for w in words {
            assert!(e.contains(w) && e.contains("base"), "{e}");
        }
    }
}
