//! The coarse stage's starting poses (paper §II-A: several rotation
//! hypotheses, as the pose is unknown): the view's principal axes onto the
//! canonical's, the tool upright at several yaws when `up` is known, and
//! lying on its side where the category needs it, unless the view itself
//! shows the tool standing (`side_facing`).

use super::{Pose, Registrar};
use crate::geometry::PointTree;
use crate::shape::estep::{dist2, P3};
use nalgebra::{Matrix3, Rotation3, SymmetricEigen, Vector3};

/// A view of a tool standing upright shows mostly its sides, facing all
/// round: with `up` known, at least this share of the view facing sideways
/// and those normals spread ([`UPRIGHT_ONE_WAY`]; `side_facing`), the view
/// is taken to show the tool standing: the lying starts are skipped even
/// where the category has them by default, and so are the principal-axis
/// starts (`Starts`). Only where the lying starts are the category's default
/// (the mug) and the options leave them open.
/// Measured (mug, `eval transfer --views 12`, seeds 7 / 11 / 23, test and
/// train views, 936 registrations each): upright share 0.81-1.00 and one-way
/// resultant 0.09-0.50, all 936 skipped; on its side (`--on-side`) share
/// 0.04-0.62, none skipped. Skipping the lying starts: upright test
/// keypoints identical, train p90 23.55 → 18.85 mm (a lying start had won
/// a few wrong poses), on-side identical; mug fit p50 8.6-8.9 → 7.8-7.9 ms
/// (`bench_register`, coarse stage 2.4 → 1.4 ms). For the principal-axis
/// starts see `Starts`. With 10 % outliers and 2 mm noise 207 of 312 upright
/// views passed with 12-neighbour normals, all 312 with 24 (see
/// `side_facing`; there train keypoint median / p90 2.20 / 20.80 → 2.18 /
/// 20.59 mm, means of seeds 7 / 11 / 23, test identical). A tilted or
/// top-down view falls outside and keeps every start.
pub(super) const UPRIGHT_SIDE_FACING: f64 = 0.75;
/// ... and at most this axial resultant of their azimuths: a flat face
/// turned sideways (a mug on its side seen against its base) is not a standing tool.
pub(super) const UPRIGHT_ONE_WAY: f64 = 0.7;
/// |normal · up| below this (about 20° from horizontal) counts as facing sideways.
const SIDE_FACING_MAX_UP: f64 = 0.34;

/// Which of the coarse stage's starts `Registrar::hypotheses` makes besides
/// the upright ones at each yaw (always made when `up` is known).
#[derive(Clone, Copy, Debug)]
pub(super) struct Starts {
    /// The view's principal axes onto the canonical's (4 sign choices). Made
    /// unless the view was measured standing (`UPRIGHT_SIDE_FACING`): then
    /// the upright starts cover them, and a tilted start only wins a wrong
    /// pose now and then. Always made without `up`. Measured, skipping them
    /// on standing views (mug, `eval transfer --views 12`, seeds 7 / 11 /
    /// 23, keypoint error median / p90): test identical (1.83 / 9.14 mm),
    /// train 1.84 / 18.85 → 1.81 / 14.92 mm; with `--unknown-viewpoint
    /// --unknown-table` test p90 22.45 → 21.30, train 2.41 / 27.03 → 2.39 /
    /// 25.11 mm; 2 mm noise and 10 % outliers (seed 7) test identical, train
    /// 2.22 / 20.95 → 2.15 / 20.40 mm. Mug fit p50 6.11-6.20 → 5.74-5.88 ms
    /// (`bench_register`, coarse stage 1.05 → 0.70 ms).
    pub(super) principal_axes: bool,
    /// The canonical lying on its side at each yaw (`lying_hypotheses`).
    pub(super) lying: bool,
}

impl Registrar {
    /// The coarse stage's starting poses for the view `x` (`Starts`), each
    /// with the mean shape's centroid on the view core's and the canonical scale.
    pub(super) fn hypotheses(&self, x: &[P3], up: Option<Vector3<f64>>, yaws: usize, starts: Starts) -> Vec<Pose> {
        // Axes and centre of the view's core: stray points (segmentation
        // leaks, flying pixels) would drag a plain centroid and tilt the axes.
        let (ax_o, mu_o) = principal_axes(&trimmed_core(x));
        let s0 = self.space.norm.scale;
        let mut rots = Vec::new();
        // Principal axes of the view onto the canonical's (4 proper sign choices).
        let signs = if starts.principal_axes || up.is_none() {
            &[(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)][..]
        } else {
            &[]
        };
        for &(s1, s2) in signs {
            let d = Matrix3::from_diagonal(&Vector3::new(s1, s2, 1.0));
            let mut r = ax_o * d * self.axes.transpose();
            if r.determinant() < 0.0 {
                let d = Matrix3::from_diagonal(&Vector3::new(s1, s2, -1.0));
                r = ax_o * d * self.axes.transpose();
            }
            rots.push(r);
        }
        match up {
            Some(up) => {
                // Upright at `yaws` yaws.
                let align = Rotation3::rotation_between(&Vector3::z(), &up)
                    .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
                for k in 0..yaws {
                    let yaw = Rotation3::from_axis_angle(
                        &nalgebra::Unit::new_normalize(up),
                        k as f64 * std::f64::consts::TAU / yaws as f64,
                    );
                    rots.push(*(yaw * align).matrix());
                    if starts.lying {
                        for a in [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2] {
                            let lie = Rotation3::from_axis_angle(&Vector3::x_axis(), a);
                            rots.push(*(yaw * align * lie).matrix());
                        }
                    }
                }
            }
            None => {
                // No prior: the 24 rotations of the cube.
                for r in cube_rotations() {
                    rots.push(r);
                }
            }
        }
        rots.into_iter()
            .map(|r| {
                let s = s0;
                // Model centroid onto the view's centroid.
                Pose { r, s, t: mu_o - s * (r * self.centroid) }
            })
            .collect()
    }
}

/// The points within 2.5× the median distance of the coordinate-wise median.
pub(super) fn trimmed_core(x: &[P3]) -> Vec<P3> {
    if x.len() < 10 {
        return x.to_vec();
    }
    let median = |mut v: Vec<f64>| {
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let m = [
        median(x.iter().map(|p| p[0]).collect()),
        median(x.iter().map(|p| p[1]).collect()),
        median(x.iter().map(|p| p[2]).collect()),
    ];
    let d: Vec<f64> = x.iter().map(|p| dist2(p, &m).sqrt()).collect();
    let limit = 2.5 * median(d.clone());
    let core: Vec<P3> = x.iter().zip(&d).filter(|(_, &di)| di <= limit).map(|(p, _)| *p).collect();
    if core.len() >= 10 {
        core
    } else {
        x.to_vec()
    }
}

/// Principal axes (columns, descending variance, right-handed) and centroid.
pub(super) fn principal_axes(x: &[P3]) -> (Matrix3<f64>, Vector3<f64>) {
    let (axes, _, mu) = principal_frame(x);
    (axes, mu)
}

/// Principal axes (columns, a proper rotation), their variances (descending) and the centroid.
pub(super) fn principal_frame(x: &[P3]) -> (Matrix3<f64>, [f64; 3], Vector3<f64>) {
    let n = x.len().max(1) as f64;
    let mu = x.iter().fold(Vector3::zeros(), |a, p| a + Vector3::from(*p)) / n;
    let mut cov = Matrix3::zeros();
    for p in x {
        let d = Vector3::from(*p) - mu;
        cov += d * d.transpose() / n;
    }
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let col = |k: usize| -> Vector3<f64> { eig.eigenvectors.column(order[k]).into_owned() };
    let mut axes = Matrix3::from_columns(&[col(0), col(1), col(2)]);
    if axes.determinant() < 0.0 {
        let c2 = -axes.column(2).into_owned();
        axes.set_column(2, &c2);
    }
    (axes, order.map(|k| eig.eigenvalues[k]), mu)
}

/// The 24 proper rotations mapping the coordinate axes onto themselves.
pub(super) fn cube_rotations() -> Vec<Matrix3<f64>> {
    let mut out = Vec::with_capacity(24);
    let axes: [Vector3<f64>; 6] =
        [Vector3::x(), Vector3::y(), Vector3::z(), -Vector3::x(), -Vector3::y(), -Vector3::z()];
    for a in &axes {
        for b in &axes {
            if a.dot(b).abs() > 0.5 {
                continue;
            }
            let c = a.cross(b);
            out.push(Matrix3::from_columns(&[*a, *b, c]));
        }
    }
    out
}

/// How much of the view faces sideways, and from how many sides: the share
/// of `x`'s points whose normal (the least principal axis of the point's 24
/// nearest neighbours in `x`) lies within about 20° of horizontal, and the
/// axial mean resultant length of those normals' azimuths (0: spread all
/// round, as over a standing body of revolution's visible half; 1: one
/// direction, as over a flat face). Written here rather than taken from a
/// point-cloud library: it is one k-d tree query and a 3×3 eigenproblem a point.
pub(super) fn side_facing(x: &[P3], up: &Vector3<f64>) -> (f64, f64) {
    // A normal from 24 neighbours, not 12: under 2 mm noise and 10 %
    // outliers the 12-point normals scattered and only 207 of 312 standing
    // mug views passed `UPRIGHT_SIDE_FACING` (seed 7; the rest kept every
    // start); with 24 all 312 of each of seeds 7 / 11 / 23 pass (share
    // 0.76-1.00, ±30 % size too), views on their side stay at 0.02-0.61
    // and clean standing ones at 0.89-1.00. A cylinder's normals stay
    // horizontal however wide the patch, so the wider patch costs no
    // separation; it costs about 0.03 ms (`bench_register` coarse stage).
    const NEIGHBOURS: usize = 24;
    const QUERY_STRIDE: usize = 4;
    if x.len() < 2 * NEIGHBOURS {
        return (0.0, 1.0);
    }
    let tree = PointTree::new_from_slice(x);
    let k = std::num::NonZeroUsize::new(NEIGHBOURS).expect("24 > 0");
    // Any two horizontal axes for the azimuth.
    let e1 = up.cross(&if up.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
    let e2 = up.cross(&e1);
    let (mut n_side, mut c2, mut s2) = (0usize, 0.0, 0.0);
    // Every 4th point asks (the fit's subsample is spread evenly or drawn at
    // random, so these still cover the view): all 400 took 0.7 ms, a third
    // of the coarse stage.
    let queries = x.len().div_ceil(QUERY_STRIDE);
    for p in x.iter().step_by(QUERY_STRIDE) {
        let nb = tree.nearest_n::<kiddo::SquaredEuclidean>(p, k);
        let mu = nb.iter().map(|n| Vector3::from(x[n.item as usize])).sum::<Vector3<f64>>() / NEIGHBOURS as f64;
        let cov = nb.iter().fold(Matrix3::zeros(), |c, n| {
            let d = Vector3::from(x[n.item as usize]) - mu;
            c + d * d.transpose()
        });
        let eig = cov.symmetric_eigen();
        let normal = eig.eigenvectors.column(eig.eigenvalues.imin()).into_owned();
        if normal.dot(up).abs() < SIDE_FACING_MAX_UP {
            n_side += 1;
            // Doubled angle: a normal's sign is not known.
            let (a, b) = (normal.dot(&e1), normal.dot(&e2));
            let r2 = a * a + b * b;
            c2 += (a * a - b * b) / r2;
            s2 += 2.0 * a * b / r2;
        }
    }
    let spread = if n_side > 0 { (c2 * c2 + s2 * s2).sqrt() / n_side as f64 } else { 1.0 };
    (n_side as f64 / queries as f64, spread)
}
