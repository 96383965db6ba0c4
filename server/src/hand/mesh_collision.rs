//! A collision mesh as the capsule that encloses it.
//!
//! The hand model collides primitives only (the penetration and clearance
//! terms fill them with spheres), and many published hand URDFs give a
//! link's collision as a mesh. Such a mesh becomes the capsule round its
//! vertices along their principal axis: conservative (no vertex lies
//! outside it, so no part of the link passes through a tool unnoticed),
//! and close for a phalanx, whose shape a capsule is. A palm or a blob
//! gets a fatter capsule, or a sphere; a URDF that wants it tighter can
//! still say its shape in primitives.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// The smallest radius given to a capsule (a mesh of one point, or of
/// collinear points, encloses nothing).
const MIN_RADIUS_M: f64 = 1e-4;

/// A capsule: the points within `radius` of the segment from −`half_length`
/// to +`half_length` along the z axis of `frame`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Capsule {
    pub frame: Isometry3<f64>,
    pub radius: f64,
    pub half_length: f64,
}

impl Capsule {
    /// Distance from `p` (the points' frame) to the capsule's surface; ≤ 0 inside.
    pub fn distance(&self, p: &Vector3<f64>) -> f64 {
        let local = self.frame.inverse_transform_vector(&(p - self.frame.translation.vector));
        let z = local.z.clamp(-self.half_length, self.half_length);
        (local - Vector3::new(0.0, 0.0, z)).norm() - self.radius
    }
}

/// The capsule along the points' principal axis that encloses them all,
/// with the smallest radius about that axis and, for it, the shortest
/// segment; None for no points or a non-finite one.
pub fn enclosing_capsule(points: &[Vector3<f64>]) -> Option<Capsule> {
    if points.is_empty() || !points.iter().all(|p| p.iter().all(|v| v.is_finite())) {
        return None;
    }
    let n = points.len() as f64;
    let centre = points.iter().sum::<Vector3<f64>>() / n;
    let cov = points.iter().fold(nalgebra::Matrix3::zeros(), |a, p| a + (p - centre) * (p - centre).transpose());
    let eigen = cov.symmetric_eigen();
    let largest = eigen.eigenvalues.imax();
    let axis = eigen.eigenvectors.column(largest).into_owned().try_normalize(1e-12).unwrap_or_else(Vector3::z);
    // Each point's place along the axis and distance from it.
    let along: Vec<(f64, f64)> = points
        .iter()
        .map(|p| {
            let d = p - centre;
            let t = d.dot(&axis);
            (t, (d - t * axis).norm())
        })
        .collect();
    let radius = along.iter().map(|&(_, r)| r).fold(MIN_RADIUS_M, f64::max);
    // A point beyond the segment's end lies in the end's half sphere when
    // the end is within √(r² − d²) of it along the axis: the segment must
    // reach max(t − h) and min(t + h). Where those cross, every point is
    // within r of any place between them: a sphere.
    let reach = |&(_, d): &(f64, f64)| (radius * radius - d * d).max(0.0).sqrt();
    let top = along.iter().map(|a| a.0 - reach(a)).fold(f64::NEG_INFINITY, f64::max);
    let bottom = along.iter().map(|a| a.0 + reach(a)).fold(f64::INFINITY, f64::min);
    let (middle, half_length) = ((top + bottom) / 2.0, (top - bottom).max(0.0) / 2.0);
    let rotation = UnitQuaternion::rotation_between(&Vector3::z(), &axis)
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    Some(Capsule {
        frame: Isometry3::from_parts(Translation3::from(centre + middle * axis), rotation),
        radius,
        half_length,
    })
}

/// Where a URDF's mesh file is: `file://` stripped; `package://PKG/REST`
/// as REST under a directory named PKG at or above `dir` (the URDF's
/// directory; ROS's package path is not known here), else under `dir`
/// itself; a relative path under `dir`.
pub fn resolve_mesh_path(filename: &str, dir: Option<&Path>) -> PathBuf {
    let base = dir.unwrap_or(Path::new("."));
    let name = filename.strip_prefix("file://").unwrap_or(filename);
    if let Some(rest) = name.strip_prefix("package://") {
        let (package, relative) = rest.split_once('/').unwrap_or((rest, ""));
        for above in base.ancestors() {
            if above.file_name().is_some_and(|f| f == package) {
                return above.join(relative);
            }
            let beside = above.join(package).join(relative);
            if beside.exists() {
                return beside;
            }
        }
        return base.join(relative);
    }
    let path = Path::new(name);
    if path.is_absolute() {
        path.to_path_buf()
    } else {
        base.join(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn encloses(c: &Capsule, points: &[Vector3<f64>]) -> bool {
        points.iter().all(|p| c.distance(p) <= 1e-12)
    }

    #[test]
    fn a_finger_shaped_cloud_gets_a_tight_capsule_along_its_length() {
        // Points on a capsule of radius 8 mm, segment 40 mm, turned and moved.
        let truth = Capsule {
            frame: Isometry3::new(Vector3::new(0.01, -0.02, 0.05), Vector3::new(0.3, -0.5, 0.2)),
            radius: 0.008,
            half_length: 0.02,
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let points: Vec<Vector3<f64>> = (0..2000)
            .map(|_| {
                let z: f64 = rng.random_range(-0.028..0.028);
                let phi: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                // On the surface: the cylinder, or a cap beyond the segment.
                let over = (z.abs() - 0.02).max(0.0);
                let r = (0.008f64 * 0.008 - over * over).max(0.0).sqrt();
                truth.frame * nalgebra::Point3::new(r * phi.cos(), r * phi.sin(), z)
            })
            .map(|p| p.coords)
            .collect();
        let c = enclosing_capsule(&points).unwrap();
        assert!(encloses(&c, &points));
        assert!((c.radius - 0.008).abs() < 5e-4, "radius {}", c.radius);
        assert!((c.half_length - 0.02).abs() < 1e-3, "half length {}", c.half_length);
        let axis = c.frame.rotation * Vector3::z();
        assert!(axis.dot(&(truth.frame.rotation * Vector3::z())).abs() > 0.999);
    }

    #[test]
    fn blobs_lines_and_single_points_are_enclosed() {
        let cube: Vec<Vector3<f64>> =
            (0..8).map(|i| Vector3::new((i & 1) as f64, ((i >> 1) & 1) as f64, (i >> 2) as f64) * 0.02).collect();
        let c = enclosing_capsule(&cube).unwrap();
        assert!(encloses(&c, &cube));
        // Within the cube's diagonal of its centre.
        assert!(c.radius + c.half_length <= 0.02 * 3f64.sqrt(), "{c:?}");
        let line: Vec<Vector3<f64>> = (0..5).map(|i| Vector3::new(0.0, 0.0, 0.01 * i as f64)).collect();
        let c = enclosing_capsule(&line).unwrap();
        assert!(encloses(&c, &line) && c.radius == MIN_RADIUS_M);
        let one = [Vector3::new(0.1, 0.2, 0.3)];
        let c = enclosing_capsule(&one).unwrap();
        assert!(encloses(&c, &one) && c.half_length == 0.0);
        assert!(enclosing_capsule(&[]).is_none());
        assert!(enclosing_capsule(&[Vector3::new(f64::NAN, 0.0, 0.0)]).is_none());
    }

    #[test]
    fn mesh_paths_resolve_as_a_urdf_means_them() {
        let dir = tempfile::tempdir().unwrap();
        let urdf_dir = dir.path().join("my_hand_description/urdf");
        std::fs::create_dir_all(&urdf_dir).unwrap();
        let pkg = dir.path().join("my_hand_description");
        assert_eq!(
            resolve_mesh_path("package://my_hand_description/meshes/a.stl", Some(&urdf_dir)),
            pkg.join("meshes/a.stl")
        );
        assert_eq!(resolve_mesh_path("../meshes/a.stl", Some(&urdf_dir)), urdf_dir.join("../meshes/a.stl"));
        assert_eq!(resolve_mesh_path("file:///abs/a.obj", Some(&urdf_dir)), PathBuf::from("/abs/a.obj"));
        // A package beside an ancestor (a workspace's src/ layout).
        let other = dir.path().join("other_meshes/m");
        std::fs::create_dir_all(&other).unwrap();
        std::fs::write(other.join("b.obj"), "").unwrap();
        assert_eq!(
            resolve_mesh_path("package://other_meshes/m/b.obj", Some(&urdf_dir)),
            dir.path().join("other_meshes/m/b.obj")
        );
    }
}
