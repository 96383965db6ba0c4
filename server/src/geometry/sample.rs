//! Area-weighted surface sampling.
//!
//! Every sample is drawn from a seeded ChaCha stream, so the same mesh, count
//! and seed give the same points on every machine. Samples that fall inside
//! another closed part of the mesh (the buried end of a mug handle) are
//! rejected: they are not on the surface a camera or a finger can touch.

use super::mesh::TriMesh;
use nalgebra::{Point3, Unit, Vector3};
use parry3d::query::PointQuery;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A point on a surface with its outward unit normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub position: Point3<f64>,
    pub normal: Unit<Vector3<f64>>,
}

/// Precomputed triangle areas and part containment for repeated sampling.
pub struct SurfaceSampler<'a> {
    mesh: &'a TriMesh,
    cumulative_area: Vec<f64>,
    part_of_triangle: Vec<usize>,
    /// One oriented parry mesh per part, for inside tests; empty for a single part.
    part_solids: Vec<Option<parry3d::shape::TriMesh>>,
}

#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    #[error("mesh has no triangle with positive area")]
    NoArea,
    #[error("only {got} of {wanted} samples landed on the outer surface after {tries} tries")]
    TooFewOuterSamples { got: usize, wanted: usize, tries: usize },
}

impl<'a> SurfaceSampler<'a> {
    pub fn new(mesh: &'a TriMesh) -> Result<Self, SampleError> {
        let mut cumulative_area = Vec::with_capacity(mesh.triangles.len());
        let mut acc = 0.0;
        for i in 0..mesh.triangles.len() {
            let a = 0.5 * mesh.triangle_normal_area2(i).norm();
            acc += if a.is_finite() { a } else { 0.0 };
            cumulative_area.push(acc);
        }
        if !(acc > 0.0) {
            return Err(SampleError::NoArea);
        }
        let parts = mesh.part_ranges();
        let mut part_of_triangle = vec![0; mesh.triangles.len()];
        for (p, r) in parts.iter().enumerate() {
            part_of_triangle[r.clone()].iter_mut().for_each(|x| *x = p);
        }
        let part_solids =
            if parts.len() > 1 { parts.iter().map(|r| to_parry_part(mesh, r.clone())).collect() } else { Vec::new() };
        Ok(Self { mesh, cumulative_area, part_of_triangle, part_solids })
    }

    pub fn total_area(&self) -> f64 {
        *self.cumulative_area.last().unwrap_or(&0.0)
    }

    /// `n` points distributed uniformly by area over the outer surface.
    pub fn sample(&self, n: usize, seed: u64) -> Result<Vec<SurfacePoint>, SampleError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut out = Vec::with_capacity(n);
        let max_tries = 20 * n + 1000;
        let mut tries = 0;
        while out.len() < n {
            if tries >= max_tries {
                return Err(SampleError::TooFewOuterSamples { got: out.len(), wanted: n, tries });
            }
            tries += 1;
            let (s, tri) = self.draw(&mut rng);
            if !self.buried(&s, self.part_of_triangle[tri]) {
                out.push(s);
            }
        }
        Ok(out)
    }

    fn draw(&self, rng: &mut ChaCha8Rng) -> (SurfacePoint, usize) {
        let total = self.total_area();
        let r = rng.random::<f64>() * total;
        let i = self.cumulative_area.partition_point(|&c| c <= r).min(self.cumulative_area.len() - 1);
        let [a, b, c] = self.mesh.triangle(i);
        // Uniform barycentric coordinates by the square-root trick.
        let (u, v): (f64, f64) = (rng.random(), rng.random());
        let su = u.sqrt();
        let p = a.coords * (1.0 - su) + b.coords * (su * (1.0 - v)) + c.coords * (su * v);
        let n = self.mesh.triangle_normal_area2(i);
        (SurfacePoint { position: Point3::from(p), normal: Unit::new_normalize(n) }, i)
    }

    fn buried(&self, s: &SurfacePoint, own_part: usize) -> bool {
        // Nudge outward so coplanar contact between parts does not count as inside.
        let q = s.position + s.normal.into_inner() * 1e-5;
        let qv = parry3d::math::Vector::new(q.x as f32, q.y as f32, q.z as f32);
        self.part_solids
            .iter()
            .enumerate()
            .any(|(p, solid)| p != own_part && solid.as_ref().is_some_and(|m| m.contains_local_point(qv)))
    }
}

/// A parry mesh of one part, oriented so that point containment works.
fn to_parry_part(mesh: &TriMesh, tris: std::ops::Range<usize>) -> Option<parry3d::shape::TriMesh> {
    let mut remap = std::collections::HashMap::new();
    let mut vertices = Vec::new();
    let mut indices = Vec::new();
    for t in &mesh.triangles[tris] {
        let mut out = [0u32; 3];
        for k in 0..3 {
            out[k] = *remap.entry(t[k]).or_insert_with(|| {
                let p = mesh.vertices[t[k] as usize];
                vertices.push(parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32));
                (vertices.len() - 1) as u32
            });
        }
        indices.push(out);
    }
    use parry3d::shape::TriMeshFlags;
    parry3d::shape::TriMesh::with_flags(
        vertices,
        indices,
        TriMeshFlags::ORIENTED | TriMeshFlags::MERGE_DUPLICATE_VERTICES,
    )
    .ok()
}

/// A parry copy of the whole mesh (f32), for ray casts and distance queries.
pub fn to_parry(mesh: &TriMesh) -> Option<parry3d::shape::TriMesh> {
    to_parry_part(mesh, 0..mesh.triangles.len())
}

/// `n` evenly spread surface points: farthest-point selection from `8n`
/// area-weighted samples (blue noise). CPD matches point *density*, so two
/// randomly sampled copies of one surface drift apart along it where their
/// densities happen to differ; evenly spread samples remove that drift.
pub fn sample_points_even(mesh: &TriMesh, n: usize, seed: u64) -> Result<Vec<Point3<f64>>, SampleError> {
    let dense: Vec<[f64; 3]> =
        sample_points(mesh, n.saturating_mul(8).max(1), seed)?.iter().map(|p| p.coords.into()).collect();
    Ok(super::farthest_point_order(&dense, n).into_iter().map(|i| Point3::from(dense[i])).collect())
}

/// Convenience: `n` sample positions only.
pub fn sample_points(mesh: &TriMesh, n: usize, seed: u64) -> Result<Vec<Point3<f64>>, SampleError> {
    Ok(SurfaceSampler::new(mesh)?.sample(n, seed)?.into_iter().map(|s| s.position).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_cube() -> TriMesh {
        let v = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
        let vertices = vec![
            v(0., 0., 0.),
            v(1., 0., 0.),
            v(1., 1., 0.),
            v(0., 1., 0.),
            v(0., 0., 1.),
            v(1., 0., 1.),
            v(1., 1., 1.),
            v(0., 1., 1.),
        ];
        let triangles = vec![
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ];
        TriMesh::new(vertices, triangles)
    }

    #[test]
    fn cube_is_watertight_with_unit_volume() {
        let m = unit_cube();
        assert!(m.is_watertight());
        assert!((m.signed_volume() - 1.0).abs() < 1e-12);
        assert!((m.area() - 6.0).abs() < 1e-12);
    }

    #[test]
    fn samples_lie_on_faces_and_are_deterministic() {
        let m = unit_cube();
        let a = sample_points(&m, 600, 7).unwrap();
        let b = sample_points(&m, 600, 7).unwrap();
        assert_eq!(a, b);
        let c = sample_points(&m, 600, 8).unwrap();
        assert_ne!(a, c);
        // On the surface: at least one coordinate is 0 or 1.
        for p in &a {
            assert!(p.coords.iter().any(|&x| x.abs() < 1e-9 || (x - 1.0).abs() < 1e-9));
        }
        // Area-weighted: each face gets about 1/6 of the samples.
        let bottom = a.iter().filter(|p| p.z.abs() < 1e-9).count();
        assert!((60..140).contains(&bottom), "bottom face got {bottom} of 600");
    }

    #[test]
    fn samples_buried_in_another_part_are_rejected() {
        let mut m = unit_cube();
        let mut inner = unit_cube();
        // A second cube overlapping the first by half.
        inner.map_vertices(|p| Point3::new(p.x + 0.5, p.y, p.z));
        m.append(&inner);
        assert_eq!(m.part_ranges().len(), 2);
        let pts = sample_points(&m, 400, 1).unwrap();
        for p in pts {
            let strictly_inside_first =
                p.x > 1e-6 && p.x < 1.0 - 1e-6 && p.y > 1e-6 && p.y < 1.0 - 1e-6 && p.z > 1e-6 && p.z < 1.0 - 1e-6;
            let strictly_inside_second = p.x > 0.5 + 1e-6
                && p.x < 1.5 - 1e-6
                && p.y > 1e-6
                && p.y < 1.0 - 1e-6
                && p.z > 1e-6
                && p.z < 1.0 - 1e-6;
            assert!(!strictly_inside_first && !strictly_inside_second, "buried sample {p}");
        }
    }

    #[test]
    fn degenerate_mesh_is_an_error() {
        let m = TriMesh::new(vec![Point3::origin(); 3], vec![[0, 1, 2]]);
        assert!(matches!(SurfaceSampler::new(&m), Err(SampleError::NoArea)));
    }
}
