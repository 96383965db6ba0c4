//! Triangle meshes: the one surface type of the engine.
//!
//! Vertices are in metres, f64 (the numerics run in f64; parry's f32 copy is
//! made only where ray casts need it). A mesh may consist of several closed
//! *parts* (a mug body and its handle): each part is watertight on its own,
//! parts may overlap, and surface sampling drops the samples buried inside
//! another part.

use nalgebra::{Point3, Vector3};
use std::collections::HashMap;
use std::ops::Range;

/// A triangle mesh made of one or more closed parts.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<Point3<f64>>,
    /// Counter-clockwise seen from outside (outward normals).
    pub triangles: Vec<[u32; 3]>,
    /// Triangle ranges of the closed parts; empty means "one part".
    pub parts: Vec<Range<usize>>,
}

/// Edge-topology summary, used to call a mesh watertight.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Topology {
    /// Undirected edges used by exactly one triangle.
    pub boundary_edges: usize,
    /// Undirected edges used by more than two triangles.
    pub non_manifold_edges: usize,
    /// Directed edges used twice (neighbouring triangles wound inconsistently).
    pub inconsistent_edges: usize,
}

impl Topology {
    pub fn is_watertight(&self) -> bool {
        self.boundary_edges == 0 && self.non_manifold_edges == 0 && self.inconsistent_edges == 0
    }
}

impl TriMesh {
    pub fn new(vertices: Vec<Point3<f64>>, triangles: Vec<[u32; 3]>) -> Self {
        Self { vertices, triangles, parts: Vec::new() }
    }

    /// Appends another mesh as new part(s).
    pub fn append(&mut self, other: &TriMesh) {
        let v0 = self.vertices.len() as u32;
        let own_parts = self.part_ranges();
        let t0 = self.triangles.len();
        self.parts = own_parts;
        self.vertices.extend_from_slice(&other.vertices);
        self.triangles.extend(other.triangles.iter().map(|t| [t[0] + v0, t[1] + v0, t[2] + v0]));
        for r in other.part_ranges() {
            self.parts.push(r.start + t0..r.end + t0);
        }
    }

    /// Triangle ranges of the parts (one range covering all when `parts` is empty).
    pub fn part_ranges(&self) -> Vec<Range<usize>> {
        if self.parts.is_empty() {
            if self.triangles.is_empty() {
                Vec::new()
            } else {
                // One range: every triangle.
                #[allow(clippy::single_range_in_vec_init)]
                let all = vec![0..self.triangles.len()];
                all
            }
        } else {
            self.parts.clone()
        }
    }

    pub fn triangle(&self, i: usize) -> [Point3<f64>; 3] {
        let t = self.triangles[i];
        [self.vertices[t[0] as usize], self.vertices[t[1] as usize], self.vertices[t[2] as usize]]
    }

    /// Twice the area vector (unnormalised outward normal) of triangle `i`.
    pub fn triangle_normal_area2(&self, i: usize) -> Vector3<f64> {
        let [a, b, c] = self.triangle(i);
        (b - a).cross(&(c - a))
    }

    pub fn area(&self) -> f64 {
        (0..self.triangles.len()).map(|i| 0.5 * self.triangle_normal_area2(i).norm()).sum()
    }

    /// Signed volume by the divergence theorem; positive for outward normals.
    /// Overlapping parts are counted once each.
    pub fn signed_volume(&self) -> f64 {
        (0..self.triangles.len())
            .map(|i| {
                let [a, b, c] = self.triangle(i);
                a.coords.dot(&b.coords.cross(&c.coords)) / 6.0
            })
            .sum()
    }

    pub fn aabb(&self) -> Option<(Point3<f64>, Point3<f64>)> {
        let first = *self.vertices.first()?;
        Some(self.vertices.iter().fold((first, first), |(lo, hi), p| (lo.inf(p), hi.sup(p))))
    }

    /// Length of the bounding-box diagonal (the object's size scale).
    pub fn diagonal(&self) -> f64 {
        self.aabb().map(|(lo, hi)| (hi - lo).norm()).unwrap_or(0.0)
    }

    /// Edge topology over the whole mesh (parts share no vertices, so each
    /// part's edges are checked on their own).
    pub fn topology(&self) -> Topology {
        let mut directed: HashMap<(u32, u32), u32> = HashMap::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        let mut topo = Topology { boundary_edges: 0, non_manifold_edges: 0, inconsistent_edges: 0 };
        for (&(a, b), &n) in &directed {
            if n > 1 {
                topo.inconsistent_edges += 1;
            }
            if a < b || !directed.contains_key(&(b, a)) {
                let total = n + directed.get(&(b, a)).copied().unwrap_or(0);
                match total {
                    1 => topo.boundary_edges += 1,
                    2 => {}
                    _ => topo.non_manifold_edges += 1,
                }
            }
        }
        topo
    }

    pub fn is_watertight(&self) -> bool {
        !self.triangles.is_empty() && self.topology().is_watertight()
    }

    /// Applies `f` to every vertex.
    pub fn map_vertices(&mut self, f: impl Fn(Point3<f64>) -> Point3<f64>) {
        for v in &mut self.vertices {
            *v = f(*v);
        }
    }
}
