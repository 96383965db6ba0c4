//! Small dense helpers the solver needs without allocating: a weighted
//! rigid fit (Kabsch) and an in-place Cholesky solve.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// The rigid transform T minimising Σ wᵢ‖T·srcᵢ − dstᵢ‖² (weighted Kabsch,
/// reflections excluded). Degenerate inputs (fewer than three non-collinear
/// weighted points) still give a transform mapping the weighted centroids.
pub fn fit_rigid(src: &[Point3<f64>], dst: &[Point3<f64>], weights: &[f64]) -> Isometry3<f64> {
    assert!(src.len() == dst.len() && src.len() == weights.len(), "fit_rigid: lengths");
    let total: f64 = weights.iter().sum();
    if total.is_nan() || total <= 0.0 {
        return Isometry3::identity();
    }
    let mut cs = Vector3::zeros();
    let mut cd = Vector3::zeros();
    for ((s, d), &w) in src.iter().zip(dst).zip(weights) {
        cs += w * s.coords;
        cd += w * d.coords;
    }
    cs /= total;
    cd /= total;
    let mut h = Matrix3::zeros();
    for ((s, d), &w) in src.iter().zip(dst).zip(weights) {
        h += w * (s.coords - cs) * (d.coords - cd).transpose();
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Isometry3::translation(cd.x - cs.x, cd.y - cs.y, cd.z - cs.z);
    };
    let v = v_t.transpose();
    let d = (v * u.transpose()).determinant().signum();
    let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, if d == 0.0 { 1.0 } else { d })) * u.transpose();
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let t = cd - rot * cs;
    Isometry3::from_parts(Translation3::from(t), rot)
}

/// Solves A·x = b for a symmetric positive definite A (row-major n × n,
/// only the lower triangle read; overwritten by its Cholesky factor). `b`
/// becomes x. Returns false, leaving garbage, if A is not positive definite.
pub fn cholesky_solve_in_place(a: &mut [f64], n: usize, b: &mut [f64]) -> bool {
    debug_assert!(a.len() >= n * n && b.len() >= n);
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d.is_nan() || d <= 0.0 || !d.is_finite() {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    // L·y = b, then Lᵀ·x = y.
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i * n + k] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    true
}
