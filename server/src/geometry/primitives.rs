//! Watertight primitive builders: the bricks the procedural tools are made of.
//!
//! Every builder returns one closed part (a [`TriMesh`] with `parts` empty):
//! each edge is shared by exactly two triangles, triangles are wound
//! counter-clockwise seen from outside, and the signed volume is positive.
//! Tools are assembled by [`TriMesh::append`]ing parts, which may overlap.
//!
//! The builders are pure functions of their arguments (no randomness, no
//! global state), so the same inputs give bit-identical meshes.

use super::TriMesh;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use std::f64::consts::{PI, TAU};

/// Radii at or below this are on the axis of revolution (a pole).
const POLE_EPS: f64 = 1e-12;
/// Consecutive points closer than this are one point.
const MERGE_EPS: f64 = 1e-12;

#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum PrimitiveError {
    #[error("{what}: needs at least {min} distinct points, got {got}")]
    TooFewPoints { what: &'static str, min: usize, got: usize },
    #[error("{what}: non-finite coordinate")]
    NonFinite { what: &'static str },
    #[error("revolve: profile point {index} has negative radius {r}")]
    NegativeRadius { index: usize, r: f64 },
    #[error("{what}: polygon encloses no area")]
    ZeroArea { what: &'static str },
    #[error("revolve: at least 3 segments around the axis are needed, got {0}")]
    TooFewSegments(usize),
    #[error("sweep: {0} scales given for {1} path points")]
    ScaleCount(usize, usize),
    #[error("sweep: scale {0:?} at path point {1} is not positive and finite")]
    BadScale([f64; 2], usize),
    #[error("sweep: the path folds back on itself at point {0}")]
    PathFoldsBack(usize),
    #[error("sweep: the up vector is parallel to the path's first tangent")]
    UpParallelToPath,
    #[error("{what}: dimension {value} must be positive and finite")]
    BadDimension { what: &'static str, value: f64 },
}

/// A closed 2D cross-section for [`sweep`] / [`tube`], in the sweep's local
/// (u, v) plane; centred on the path so the end caps can be fanned from it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CrossSection {
    /// Ellipse with half-axes along u and v. Vertex 0 lies on +u and, when
    /// `segments` is a multiple of 4, vertices also lie on +v, −u, −v, so
    /// points on the extreme lines of the tube are exactly on the mesh.
    Ellipse { half_u: f64, half_v: f64, segments: usize },
    /// Rectangle with circular corners (`corner_radius` 0 gives sharp corners).
    RoundedRect { half_u: f64, half_v: f64, corner_radius: f64, corner_segments: usize },
}

impl CrossSection {
    /// The section outline, counter-clockwise in (u, v).
    pub fn polygon(&self) -> Result<Vec<[f64; 2]>, PrimitiveError> {
        match *self {
            CrossSection::Ellipse { half_u, half_v, segments } => {
                positive("ellipse half_u", half_u)?;
                positive("ellipse half_v", half_v)?;
                if segments < 3 {
                    return Err(PrimitiveError::TooFewPoints { what: "ellipse", min: 3, got: segments });
                }
                Ok((0..segments)
                    .map(|k| {
                        let a = TAU * k as f64 / segments as f64;
                        [half_u * a.cos(), half_v * a.sin()]
                    })
                    .collect())
            }
            CrossSection::RoundedRect { half_u, half_v, corner_radius, corner_segments } => {
                positive("rect half_u", half_u)?;
                positive("rect half_v", half_v)?;
                if !(corner_radius.is_finite() && corner_radius >= 0.0) {
                    return Err(PrimitiveError::BadDimension { what: "rect corner_radius", value: corner_radius });
                }
                let r = corner_radius.min(half_u).min(half_v);
                let m = if r > 0.0 { corner_segments.max(1) } else { 0 };
                let centres = [
                    (half_u - r, half_v - r, 0.0),
                    (-(half_u - r), half_v - r, 0.5 * PI),
                    (-(half_u - r), -(half_v - r), PI),
                    (half_u - r, -(half_v - r), 1.5 * PI),
                ];
                let mut pts = Vec::with_capacity(4 * (m + 1));
                for (cu, cv, a0) in centres {
                    for k in 0..=m {
                        let a = a0 + 0.5 * PI * k as f64 / m.max(1) as f64;
                        pts.push([cu + r * a.cos(), cv + r * a.sin()]);
                    }
                }
                // A corner radius equal to a half-size makes neighbouring
                // arcs meet in one point; keep it once.
                Ok(dedup_closed(pts))
            }
        }
    }
}

fn positive(what: &'static str, value: f64) -> Result<(), PrimitiveError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(PrimitiveError::BadDimension { what, value })
    }
}

/// Drops consecutive duplicates, including last == first.
fn dedup_closed(mut pts: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    let close = |a: &[f64; 2], b: &[f64; 2]| (a[0] - b[0]).abs() <= MERGE_EPS && (a[1] - b[1]).abs() <= MERGE_EPS;
    pts.dedup_by(|b, a| close(a, b));
    while pts.len() > 1 && close(&pts[0], &pts[pts.len() - 1]) {
        pts.pop();
    }
    pts
}

/// Twice the signed area (shoelace); positive for counter-clockwise.
fn signed_area2(pts: &[[f64; 2]]) -> f64 {
    (0..pts.len())
        .map(|i| {
            let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum()
}

/// Validates a closed polygon and returns it counter-clockwise.
fn ccw_polygon(what: &'static str, pts: &[[f64; 2]]) -> Result<Vec<[f64; 2]>, PrimitiveError> {
    if pts.iter().any(|p| !(p[0].is_finite() && p[1].is_finite())) {
        return Err(PrimitiveError::NonFinite { what });
    }
    let mut pts = dedup_closed(pts.to_vec());
    if pts.len() < 3 {
        return Err(PrimitiveError::TooFewPoints { what, min: 3, got: pts.len() });
    }
    let a2 = signed_area2(&pts);
    let scale = pts.iter().fold(0.0f64, |m, p| m.max(p[0].abs()).max(p[1].abs()));
    if a2.abs() <= 1e-12 * scale * scale {
        return Err(PrimitiveError::ZeroArea { what });
    }
    if a2 < 0.0 {
        pts.reverse();
    }
    Ok(pts)
}

/// Surface of revolution about the z axis.
///
/// `profile` is a closed, simple polygon of (r, z) points with r ≥ 0 (either
/// orientation; the edge from the last point back to the first is implied).
/// Points with r = 0 become single pole vertices, and profile edges lying on
/// the axis produce no faces, so a solid (profile closed along the axis) or a
/// cup with a floor (outer wall, rim, inner wall, floor, back down the axis)
/// comes out closed. Vertex ring j lies at angle 2πj/`segments` from +x, so
/// with an even count there are meridians at ±x and (for multiples of 4) ±y.
pub fn revolve(profile: &[[f64; 2]], segments: usize) -> Result<TriMesh, PrimitiveError> {
    if segments < 3 {
        return Err(PrimitiveError::TooFewSegments(segments));
    }
    let mut pts = ccw_polygon("revolve profile", profile)?;
    for (index, p) in pts.iter_mut().enumerate() {
        if p[0] < -POLE_EPS {
            return Err(PrimitiveError::NegativeRadius { index, r: p[0] });
        }
        if p[0] <= POLE_EPS {
            p[0] = 0.0;
        }
    }
    let n = pts.len();
    let pole: Vec<bool> = pts.iter().map(|p| p[0] == 0.0).collect();
    let (cos, sin): (Vec<f64>, Vec<f64>) =
        (0..segments).map(|j| TAU * j as f64 / segments as f64).map(|a| (a.cos(), a.sin())).unzip();

    let mut vertices = Vec::new();
    let mut first = Vec::with_capacity(n);
    for (i, p) in pts.iter().enumerate() {
        first.push(vertices.len() as u32);
        if pole[i] {
            vertices.push(Point3::new(0.0, 0.0, p[1]));
        } else {
            vertices.extend((0..segments).map(|j| Point3::new(p[0] * cos[j], p[0] * sin[j], p[1])));
        }
    }
    let vid = |i: usize, j: usize| if pole[i] { first[i] } else { first[i] + (j % segments) as u32 };

    let mut triangles = Vec::with_capacity(2 * n * segments);
    for i in 0..n {
        let k = (i + 1) % n;
        if pole[i] && pole[k] {
            continue; // an edge on the axis sweeps no area
        }
        for j in 0..segments {
            let (a, b, c, d) = (vid(i, j), vid(k, j), vid(k, j + 1), vid(i, j + 1));
            // For a counter-clockwise profile the outward normal is
            // (angular tangent) × (profile tangent), hence this winding.
            // At a pole one triangle of the quad collapses and is dropped.
            for t in [[a, c, b], [a, d, c]] {
                if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                    triangles.push(t);
                }
            }
        }
    }
    Ok(TriMesh::new(vertices, triangles))
}

/// Sweeps a closed cross-section along an open 3D polyline, with flat caps.
///
/// The section (counter-clockwise in (u, v), star-shaped about its origin,
/// which rides on the path) is carried along the path by parallel transport,
/// so it does not twist; u starts as `up` projected off the first tangent and
/// v = t × u. At interior points the tangent is the mean of the neighbouring
/// segment directions (no miter correction: meant for smooth, finely sampled
/// paths). `scales` (empty, or one [su, sv] per path point) stretches the
/// section per station, for tapers and rounded-off ends.
pub fn sweep(
    path: &[Point3<f64>],
    section: &[[f64; 2]],
    scales: &[[f64; 2]],
    up: &Vector3<f64>,
) -> Result<TriMesh, PrimitiveError> {
    if path.iter().any(|p| !p.coords.iter().all(|c| c.is_finite())) || !up.iter().all(|c| c.is_finite()) {
        return Err(PrimitiveError::NonFinite { what: "sweep path" });
    }
    if !scales.is_empty() && scales.len() != path.len() {
        return Err(PrimitiveError::ScaleCount(scales.len(), path.len()));
    }
    for (i, s) in scales.iter().enumerate() {
        if !(s[0].is_finite() && s[1].is_finite() && s[0] > 0.0 && s[1] > 0.0) {
            return Err(PrimitiveError::BadScale(*s, i));
        }
    }
    // Merge repeated path points (keeping the first point's scale).
    let mut stations: Vec<(Point3<f64>, [f64; 2])> = Vec::with_capacity(path.len());
    for (i, p) in path.iter().enumerate() {
        let s = scales.get(i).copied().unwrap_or([1.0, 1.0]);
        match stations.last() {
            Some((q, _)) if (p - q).norm() <= MERGE_EPS => {}
            _ => stations.push((*p, s)),
        }
    }
    if stations.len() < 2 {
        return Err(PrimitiveError::TooFewPoints { what: "sweep path", min: 2, got: stations.len() });
    }
    let section = ccw_polygon("sweep section", section)?;
    let m = section.len();
    let n = stations.len();

    let dirs: Vec<Vector3<f64>> = (0..n - 1).map(|i| (stations[i + 1].0 - stations[i].0).normalize()).collect();
    let mut tangents = Vec::with_capacity(n);
    tangents.push(dirs[0]);
    for i in 1..n - 1 {
        let t = dirs[i - 1] + dirs[i];
        if t.norm() < 1e-9 {
            return Err(PrimitiveError::PathFoldsBack(i));
        }
        tangents.push(t.normalize());
    }
    tangents.push(dirs[n - 2]);

    let mut u = up - tangents[0] * up.dot(&tangents[0]);
    let up_norm = up.norm();
    if up_norm == 0.0 || u.norm() <= 1e-9 * up_norm {
        return Err(PrimitiveError::UpParallelToPath);
    }
    u.normalize_mut();

    let mut vertices = Vec::with_capacity(n * m + 2);
    for i in 0..n {
        if i > 0 {
            let rot = UnitQuaternion::rotation_between(&tangents[i - 1], &tangents[i])
                .ok_or(PrimitiveError::PathFoldsBack(i))?;
            u = rot * u;
            u = (u - tangents[i] * u.dot(&tangents[i])).normalize();
        }
        let v = tangents[i].cross(&u);
        let (c, s) = stations[i];
        vertices.extend(section.iter().map(|q| c + u * (s[0] * q[0]) + v * (s[1] * q[1])));
    }
    let start = vertices.len() as u32;
    vertices.push(stations[0].0);
    let end = start + 1;
    vertices.push(stations[n - 1].0);

    let id = |i: usize, k: usize| (i * m + k % m) as u32;
    let mut triangles = Vec::with_capacity(2 * n * m);
    for i in 0..n - 1 {
        for k in 0..m {
            // Section edge e (ccw) and tangent t: outward is e × t.
            let (a, b, c, d) = (id(i, k), id(i, k + 1), id(i + 1, k + 1), id(i + 1, k));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    for k in 0..m {
        triangles.push([start, id(0, k + 1), id(0, k)]);
        triangles.push([end, id(n - 1, k), id(n - 1, k + 1)]);
    }
    Ok(TriMesh::new(vertices, triangles))
}

/// [`sweep`] with a constant cross-section.
pub fn tube(path: &[Point3<f64>], section: &CrossSection, up: &Vector3<f64>) -> Result<TriMesh, PrimitiveError> {
    sweep(path, &section.polygon()?, &[], up)
}

/// A box centred at the origin with half extents `half`, its four edges
/// parallel to z rounded with `corner_radius` (0: sharp), and the top face
/// (z = +half.z) scaled in x and y by the factor (1 − `taper`); taper 0 is a
/// straight box, taper in (−1, 1) (negative widens the top).
pub fn rounded_box(half: &Vector3<f64>, corner_radius: f64, taper: f64) -> Result<TriMesh, PrimitiveError> {
    positive("box half.z", half.z)?;
    if !(taper.is_finite() && taper > -1.0 && taper < 1.0) {
        return Err(PrimitiveError::BadDimension { what: "box taper", value: taper });
    }
    let section =
        CrossSection::RoundedRect { half_u: half.x, half_v: half.y, corner_radius, corner_segments: 4 }.polygon()?;
    let top = 1.0 - taper;
    // The sweep frame along +z with up = +x has u = x, v = z × x = y.
    sweep(
        &[Point3::new(0.0, 0.0, -half.z), Point3::new(0.0, 0.0, half.z)],
        &section,
        &[[1.0, 1.0], [top, top]],
        &Vector3::x(),
    )
}

/// A capped frustum (cone segment) from `a` (radius `r_a`) to `b` (radius
/// `r_b`); either radius may be 0 for a cone. The cap centres are poles, so
/// `a` and `b` are mesh vertices.
pub fn frustum(
    a: &Point3<f64>,
    b: &Point3<f64>,
    r_a: f64,
    r_b: f64,
    segments: usize,
) -> Result<TriMesh, PrimitiveError> {
    let axis = b - a;
    let length = axis.norm();
    positive("frustum length", length)?;
    for r in [r_a, r_b] {
        if !(r.is_finite() && r >= 0.0) {
            return Err(PrimitiveError::BadDimension { what: "frustum radius", value: r });
        }
    }
    let mut mesh = revolve(&[[0.0, 0.0], [r_a, 0.0], [r_b, length], [0.0, length]], segments)?;
    transform(&mut mesh, &axis_frame(a, &axis));
    Ok(mesh)
}

/// A capped circular cylinder from `a` to `b`.
pub fn cylinder(a: &Point3<f64>, b: &Point3<f64>, radius: f64, segments: usize) -> Result<TriMesh, PrimitiveError> {
    frustum(a, b, radius, radius, segments)
}

/// The rigid frame whose origin is `origin` and whose z axis points along
/// `axis` (any non-zero vector): maps a revolved mesh onto that axis.
pub fn axis_frame(origin: &Point3<f64>, axis: &Vector3<f64>) -> Isometry3<f64> {
    let rot = UnitQuaternion::rotation_between(&Vector3::z(), axis)
        // Only an axis along −z has no unique shortest rotation: turn about x.
        .unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI));
    Isometry3::from_parts(Translation3::from(origin.coords), rot)
}

/// Applies a rigid motion in place (rigid motions keep the winding outward).
pub fn transform(mesh: &mut TriMesh, iso: &Isometry3<f64>) {
    mesh.map_vertices(|p| iso * p);
}

/// Appends the points of a circular arc (centre, radius, from angle `a0` to
/// `a1`, `steps` pieces, both ends included) to a 2D polyline: the building
/// block of fillets and rims in revolve profiles.
pub fn push_arc(pts: &mut Vec<[f64; 2]>, centre: [f64; 2], radius: f64, a0: f64, a1: f64, steps: usize) {
    let steps = steps.max(1);
    for k in 0..=steps {
        let a = a0 + (a1 - a0) * k as f64 / steps as f64;
        pts.push([centre[0] + radius * a.cos(), centre[1] + radius * a.sin()]);
    }
}

/// Appends a straight run to `to` split into pieces no longer than
/// `max_step` (the end point included, the start assumed already present),
/// so long walls do not become needle triangles.
pub fn push_line(pts: &mut Vec<[f64; 2]>, to: [f64; 2], max_step: f64) {
    let Some(&from) = pts.last() else {
        pts.push(to);
        return;
    };
    let len = ((to[0] - from[0]).powi(2) + (to[1] - from[1]).powi(2)).sqrt();
    let steps = if max_step > 0.0 && max_step.is_finite() { (len / max_step).ceil().max(1.0) as usize } else { 1 };
    for k in 1..=steps {
        let f = k as f64 / steps as f64;
        pts.push([from[0] + (to[0] - from[0]) * f, from[1] + (to[1] - from[1]) * f]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn closed(mesh: &TriMesh) {
        assert!(mesh.is_watertight(), "topology {:?}", mesh.topology());
        assert!(mesh.signed_volume() > 0.0, "volume {}", mesh.signed_volume());
    }

    #[test]
    fn revolved_solid_cylinder_is_closed_with_the_right_volume() {
        let m = revolve(&[[0.0, 0.0], [0.02, 0.0], [0.02, 0.1], [0.0, 0.1]], 64).unwrap();
        closed(&m);
        // A 64-gon prism: area = n/2 r² sin(2π/n).
        let expect = 32.0 * 0.02f64.powi(2) * (TAU / 64.0).sin() * 0.1;
        assert!((m.signed_volume() - expect).abs() < 1e-12);
        assert_eq!(m.triangles.len(), 4 * 64);
    }

    #[test]
    fn clockwise_profile_is_accepted() {
        let m = revolve(&[[0.0, 0.1], [0.02, 0.1], [0.02, 0.0], [0.0, 0.0]], 16).unwrap();
        closed(&m);
    }

    #[test]
    fn revolved_cup_with_floor_and_torus_are_closed() {
        // Cup: outer bottom, outer wall, rim, inner wall, floor, down the axis.
        let cup = [[0.0, 0.0], [0.04, 0.0], [0.04, 0.1], [0.036, 0.1], [0.036, 0.006], [0.0, 0.006]];
        let m = revolve(&cup, 48).unwrap();
        closed(&m);
        let solid = revolve(&[[0.0, 0.0], [0.04, 0.0], [0.04, 0.1], [0.0, 0.1]], 48).unwrap();
        let hollow = revolve(&[[0.0, 0.006], [0.036, 0.006], [0.036, 0.1], [0.0, 0.1]], 48).unwrap();
        assert!((m.signed_volume() - (solid.signed_volume() - hollow.signed_volume())).abs() < 1e-12);
        // A torus: profile never touches the axis.
        let mut ring = Vec::new();
        push_arc(&mut ring, [0.05, 0.0], 0.01, 0.0, TAU * 0.95, 19);
        closed(&revolve(&ring, 32).unwrap());
    }

    #[test]
    fn swept_tubes_are_closed() {
        let section = CrossSection::Ellipse { half_u: 0.006, half_v: 0.004, segments: 16 };
        let straight = tube(&[Point3::origin(), Point3::new(0.0, 0.0, 0.1)], &section, &Vector3::x()).unwrap();
        closed(&straight);
        let poly_area = 0.5 * 16.0 * 0.006 * 0.004 * (TAU / 16.0).sin();
        assert!((straight.signed_volume() - poly_area * 0.1).abs() < 1e-12);
        // A C-shaped handle in the xz-plane.
        let path: Vec<_> = (0..=24)
            .map(|k| {
                let a = PI * k as f64 / 24.0;
                Point3::new(0.03 * a.sin(), 0.0, 0.03 * a.cos())
            })
            .collect();
        let rect = CrossSection::RoundedRect { half_u: 0.007, half_v: 0.004, corner_radius: 0.002, corner_segments: 3 };
        closed(&tube(&path, &rect, &Vector3::y()).unwrap());
        // A stadium (corner radius = half size) merges the arc ends.
        let stadium =
            CrossSection::RoundedRect { half_u: 0.004, half_v: 0.004, corner_radius: 0.004, corner_segments: 4 };
        closed(&tube(&path, &stadium, &Vector3::y()).unwrap());
    }

    #[test]
    fn boxes_and_frusta_are_closed() {
        let b = rounded_box(&Vector3::new(0.03, 0.02, 0.01), 0.004, 0.0).unwrap();
        closed(&b);
        assert!(b.signed_volume() < 0.06 * 0.04 * 0.02 && b.signed_volume() > 0.9 * 0.06 * 0.04 * 0.02);
        closed(&rounded_box(&Vector3::new(0.03, 0.02, 0.01), 0.0, 0.3).unwrap());
        let a = Point3::new(0.1, -0.2, 0.3);
        for axis in [Vector3::new(1.0, 2.0, -0.5), -Vector3::z(), Vector3::z()] {
            let f = frustum(&a, &(a + axis * 0.05), 0.02, 0.01, 24).unwrap();
            closed(&f);
            // The cap centres are the end points.
            assert!(f.vertices.iter().any(|v| (v - a).norm() < 1e-12));
        }
        closed(&cylinder(&a, &Point3::new(0.1, 0.2, 0.3), 0.01, 12).unwrap());
    }

    #[test]
    fn bad_inputs_are_errors_not_panics() {
        assert!(revolve(&[[0.0, 0.0], [1.0, 0.0]], 8).is_err());
        assert!(revolve(&[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]], 2).is_err());
        assert!(matches!(
            revolve(&[[0.0, 0.0], [-1.0, 0.0], [1.0, 1.0]], 8),
            Err(PrimitiveError::NegativeRadius { .. })
        ));
        assert!(revolve(&[[0.0, 0.0], [f64::NAN, 0.0], [1.0, 1.0]], 8).is_err());
        assert!(revolve(&[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], 8).is_err());
        let s = CrossSection::Ellipse { half_u: 1.0, half_v: 1.0, segments: 8 };
        assert!(tube(&[Point3::origin()], &s, &Vector3::x()).is_err());
        assert!(tube(&[Point3::origin(), Point3::new(0.0, 0.0, 1.0)], &s, &Vector3::z()).is_err());
        assert!(tube(&[Point3::origin(), Point3::new(0.0, 0.0, 1.0), Point3::origin()], &s, &Vector3::x()).is_err());
        assert!(rounded_box(&Vector3::new(1.0, -1.0, 1.0), 0.0, 0.0).is_err());
        assert!(rounded_box(&Vector3::new(1.0, 1.0, 1.0), 0.0, 1.5).is_err());
        assert!(frustum(&Point3::origin(), &Point3::origin(), 1.0, 1.0, 8).is_err());
        assert!(CrossSection::Ellipse { half_u: 0.0, half_v: 1.0, segments: 8 }.polygon().is_err());
    }

    #[test]
    fn builders_are_deterministic() {
        let mk = || {
            let mut p = vec![[0.0, 0.0]];
            push_line(&mut p, [0.03, 0.0], 0.01);
            push_arc(&mut p, [0.03, 0.01], 0.01, -0.5 * PI, 0.5 * PI, 7);
            p.push([0.0, 0.02]);
            revolve(&p, 40).unwrap()
        };
        assert_eq!(mk(), mk());
    }
}
