//! Hand-versus-scene distances for the penetration term and the pre-grasp
//! check.
//!
//! Every hand collision primitive is covered by spheres ([`HandSpheres`]):
//! a sphere is itself, a cylinder becomes spheres of its radius along its
//! axis (a capsule chain), a box becomes spheres of its half thickness over
//! its mid-plane (a rounded box). A sphere of radius r centred at c pierces
//! a solid by r − sd(c), sd the signed distance of c to the solid's surface,
//! and the gradient of sd is the unit vector from the closest surface point
//! to c (flipped inside). That gives each sphere an exact penetration depth
//! and an analytic Jacobian row, n̂ᵀ·J_point(c), for the least squares.
//!
//! The spacing of the chain sets how much a sphere chain under-covers its
//! primitive between centres: with spacing s·r the chain's thinnest waist is
//! r·√(1 − s²/4) along a capsule and r·√(1 − s²/2) over a box (s = 0.5:
//! 3 % and 6 %, i.e. ≤ 0.3 mm on a finger, ≤ 0.9 mm on the palm).

use nalgebra::{Isometry3, Point3, Vector3};
use parry3d::math::VectorExt;
use parry3d::query::PointQueryWithLocation;
use parry3d::shape::{TriMeshFlags, TrianglePointLocation};

use super::GraspError;
use crate::geometry::TriMesh;
use crate::hand::{CollisionShape, HandKinematics, HandModel, LinkId};

/// One sphere of the hand's collision cover.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereSample {
    pub link: LinkId,
    /// Centre in the link frame, metres.
    pub center_link: Vector3<f64>,
    pub radius: f64,
    /// Index in [`HandModel::collision_primitives`] it covers.
    pub primitive: usize,
}

/// The spheres of one primitive, with a bound for culling them together.
#[derive(Clone, Debug, PartialEq)]
pub struct SphereGroup {
    pub link: LinkId,
    /// Centre of the group in the link frame.
    pub center_link: Vector3<f64>,
    /// Largest distance from the centre to any point of a member sphere.
    pub reach: f64,
    /// Members, as a range of [`HandSpheres::spheres`].
    pub members: std::ops::Range<usize>,
}

/// Spheres covering all collision primitives of a hand.
#[derive(Clone, Debug)]
pub struct HandSpheres {
    spheres: Vec<SphereSample>,
    groups: Vec<SphereGroup>,
}

/// A sphere closer to the scene than the margin: one penetration residual.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Contact {
    pub sphere: usize,
    pub center_world: Point3<f64>,
    /// sd − r − margin (< 0), metres.
    pub residual: f64,
    /// World gradient of the signed distance at the centre (unit).
    pub normal_world: Vector3<f64>,
}

impl HandSpheres {
    /// Covers `hand`'s primitives with centres at most `spacing_ratio`·r
    /// apart (clamped to [0.1, 1.5]).
    pub fn new(hand: &HandModel, spacing_ratio: f64) -> Self {
        let s = spacing_ratio.clamp(0.1, 1.5);
        let mut spheres = Vec::new();
        let mut groups = Vec::new();
        for (primitive, prim) in hand.collision_primitives().iter().enumerate() {
            let first = spheres.len();
            let mut push = |local: Vector3<f64>, radius: f64| {
                let center_link = (prim.origin * Point3::from(local)).coords;
                spheres.push(SphereSample { link: prim.link, center_link, radius, primitive });
            };
            match prim.shape {
                CollisionShape::Sphere { radius } => push(Vector3::zeros(), radius),
                CollisionShape::Cylinder { radius, half_length } => {
                    for z in grid(half_length, s * radius) {
                        push(Vector3::new(0.0, 0.0, z), radius);
                    }
                }
                CollisionShape::Box { half_extents } => {
                    let thin = half_extents.imin();
                    let (b, c) = ((thin + 1) % 3, (thin + 2) % 3);
                    let r = half_extents[thin];
                    for u in grid(half_extents[b] - r, s * r) {
                        for v in grid(half_extents[c] - r, s * r) {
                            let mut local = Vector3::zeros();
                            local[b] = u;
                            local[c] = v;
                            push(local, r);
                        }
                    }
                }
            }
            let members = &spheres[first..];
            let center_link = members.iter().map(|m| m.center_link).sum::<Vector3<f64>>() / members.len() as f64;
            let reach = members.iter().map(|m| (m.center_link - center_link).norm() + m.radius).fold(0.0, f64::max);
            groups.push(SphereGroup { link: prim.link, center_link, reach, members: first..spheres.len() });
        }
        Self { spheres, groups }
    }

    pub fn spheres(&self) -> &[SphereSample] {
        &self.spheres
    }
    /// One group per collision primitive.
    pub fn groups(&self) -> &[SphereGroup] {
        &self.groups
    }

    /// Appends to `out` every sphere closer than `margin` to the tool or the
    /// table, for the state in `kin` (two entries if it is near both). A
    /// group is skipped whole when its centre is farther from the scene than
    /// its reach plus the margin: signed distance is 1-Lipschitz, so no member
    /// can then be near. `bounds` remembers each group centre's and each
    /// sphere's last distance to the tool, so that one that has moved less
    /// than its remaining room is skipped without a query (it must hold
    /// bounds for this scene's tool, or be fresh). `out` is not cleared; with capacity
    /// for two entries per sphere it never reallocates.
    pub fn collect_contacts(
        &self,
        kin: &HandKinematics,
        scene: &Scene,
        margin: f64,
        bounds: &mut DistanceBounds,
        out: &mut Vec<Contact>,
    ) {
        let first_sphere = self.groups.len();
        bounds.fit(first_sphere + self.spheres.len());
        for (k, g) in self.groups.iter().enumerate() {
            let cg = kin.link_pose(g.link) * Point3::from(g.center_link);
            let clear = g.reach + margin;
            if let Some(tool) = scene.tool {
                if bounds.may_be_closer_than(k, cg, clear, tool) {
                    for i in g.members.clone() {
                        let c = self.center_world(kin, i);
                        let r = self.spheres[i].radius;
                        if let Some((sd, n)) = bounds.closer_than(first_sphere + i, c, r + margin, tool) {
                            let residual = sd - r - margin;
                            if residual < 0.0 {
                                out.push(Contact { sphere: i, center_world: c, residual, normal_world: n });
                            }
                        }
                    }
                }
            }
            if let Some(h) = scene.table_height_world {
                if cg.z - h < clear {
                    for i in g.members.clone() {
                        let c = self.center_world(kin, i);
                        let residual = c.z - h - self.spheres[i].radius - margin;
                        if residual < 0.0 {
                            out.push(Contact { sphere: i, center_world: c, residual, normal_world: Vector3::z() });
                        }
                    }
                }
            }
        }
    }

    /// World centre of sphere `i` for the state in `kin`.
    pub fn center_world(&self, kin: &HandKinematics, i: usize) -> Point3<f64> {
        let s = &self.spheres[i];
        kin.link_pose(s.link) * Point3::from(s.center_link)
    }
}

/// Lower bounds on the signed distance of the sphere groups' centres and of
/// the spheres' centres to one tool: the distance last measured at a point,
/// less how far the centre has moved from it (signed distance is
/// 1-Lipschitz). An optimiser's small steps leave a sphere a few
/// millimetres from the tool unqueried for many iterations. And upper
/// bounds, the distance measured there plus how far the centre has moved:
/// a group whose centre is certainly within reach of the tool has its
/// members measured without measuring the centre again.
#[derive(Clone, Debug, Default)]
pub struct DistanceBounds {
    /// Groups first, then spheres: where the centre was measured, a lower
    /// bound of the distance there (NaN: never) and an upper one (+∞: none).
    at: Vec<(Point3<f64>, f64, f64)>,
}

impl DistanceBounds {
    /// No bounds yet, sized for `spheres`.
    pub fn new(spheres: &HandSpheres) -> Self {
        Self { at: vec![(Point3::origin(), f64::NAN, f64::INFINITY); spheres.groups.len() + spheres.spheres.len()] }
    }

    /// Forgets every bound (a new tool or pose).
    pub fn clear(&mut self) {
        for a in &mut self.at {
            (a.1, a.2) = (f64::NAN, f64::INFINITY);
        }
    }

    fn fit(&mut self, len: usize) {
        if self.at.len() != len {
            self.at = vec![(Point3::origin(), f64::NAN, f64::INFINITY); len];
        }
    }

    /// The tool's signed distance and gradient at `centre` (entry `k`) when
    /// it is under `clear`; None when it is not, without a query while
    /// entry `k`'s bound (−∞ when never measured) shows it cannot be.
    fn closer_than(
        &mut self,
        k: usize,
        centre: Point3<f64>,
        clear: f64,
        tool: &ToolCollider,
    ) -> Option<(f64, Vector3<f64>)> {
        let (p, sd, _) = self.at[k];
        if !sd.is_nan() && sd - (centre - p).norm() >= clear {
            return None;
        }
        let (measured, culled) = tool.signed_distance_and_bound(&centre, clear + 1e-6);
        let sd = measured.map_or(f64::INFINITY, |(sd, _)| sd);
        self.at[k] = (centre, sd.min(culled), sd);
        measured.filter(|&(sd, _)| sd < clear)
    }

    /// Whether entry `k`'s centre may be under `clear` from the tool: false
    /// when its lower bound shows it cannot be, true without a query when
    /// its upper bound shows it is; else measured.
    fn may_be_closer_than(&mut self, k: usize, centre: Point3<f64>, clear: f64, tool: &ToolCollider) -> bool {
        let (p, _, upper) = self.at[k];
        if upper + (centre - p).norm() < clear {
            return true;
        }
        self.closer_than(k, centre, clear, tool).is_some()
    }
}

/// Evenly spaced points on [−half, half] at most `step` apart (just 0 when
/// the span is empty).
fn grid(half: f64, step: f64) -> impl Iterator<Item = f64> {
    let half = half.max(0.0);
    let n = if half > 0.0 { (2.0 * half / step).ceil().max(1.0) as usize } else { 0 };
    (0..=n).map(move |k| if n == 0 { 0.0 } else { -half + 2.0 * half * k as f64 / n as f64 })
}

#[derive(Clone)]
struct Part {
    mesh: parry3d::shape::TriMesh,
    normals: PseudoNormals,
    /// The tool mesh's index of each of the part's vertices.
    vertex_ids: Vec<u32>,
    /// Tool-frame bounding box, for culling far queries.
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    /// Half the box's smallest side: no point inside the part is farther
    /// than this from its surface.
    max_depth: f64,
}

impl Part {
    /// How far a tool-frame point lies outside the part's box (0 inside).
    fn box_distance(&self, p: &Vector3<f64>) -> f64 {
        (self.lo - p).sup(&(p - self.hi)).sup(&Vector3::zeros()).norm()
    }

    fn set_box(&mut self, vertices_tool: &[Point3<f64>]) {
        let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
        for &i in &self.vertex_ids {
            let p = vertices_tool[i as usize].coords;
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        (self.lo, self.hi, self.max_depth) = (lo, hi, 0.5 * (hi - lo).min());
    }
}

/// The pseudo-normals (Bærentzen and Aanæs) of a closed part, which tell
/// inside from outside at a closest point: a vertex's is the sum of its
/// faces' normals weighted by their angles there, an edge's the sum of its
/// two faces' normals. Computed as parry computes them (the same sums in
/// the same order, so the same bits), but over index arrays made once per
/// part, not parry's hash maps at every deformation (a quarter of a Grasp's
/// transfer stage on the mug).
#[derive(Clone)]
struct PseudoNormals {
    /// Each triangle's edges (its vertices 0-1, 1-2, 2-0) as indices into `edge`.
    triangle_edges: Vec<[u32; 3]>,
    vertex: Vec<parry3d::math::Vector>,
    edge: Vec<parry3d::math::Vector>,
}

impl PseudoNormals {
    fn new(indices: &[[u32; 3]]) -> Self {
        let mut ids = std::collections::HashMap::new();
        let mut id = |a: u32, b: u32| {
            let n = ids.len() as u32;
            *ids.entry((a.min(b), a.max(b))).or_insert(n)
        };
        let triangle_edges = indices.iter().map(|t| [id(t[0], t[1]), id(t[1], t[2]), id(t[2], t[0])]).collect();
        let vertices = indices.iter().flatten().map(|&i| i as usize + 1).max().unwrap_or(0);
        let zero = parry3d::math::Vector::ZERO;
        Self { triangle_edges, vertex: vec![zero; vertices], edge: vec![zero; ids.len()] }
    }

    fn update(&mut self, mesh: &parry3d::shape::TriMesh) {
        self.vertex.fill(parry3d::math::Vector::ZERO);
        self.edge.fill(parry3d::math::Vector::ZERO);
        for (idx, edges) in mesh.indices().iter().zip(&self.triangle_edges) {
            let v = mesh.vertices();
            let tri = parry3d::shape::Triangle::new(v[idx[0] as usize], v[idx[1] as usize], v[idx[2] as usize]);
            if let Some(n) = tri.normal() {
                let ang1 = (tri.b - tri.a).angle(tri.c - tri.a);
                let ang2 = (tri.a - tri.b).angle(tri.c - tri.b);
                let ang3 = (tri.b - tri.c).angle(tri.a - tri.c);
                self.vertex[idx[0] as usize] += n * ang1;
                self.vertex[idx[1] as usize] += n * ang2;
                self.vertex[idx[2] as usize] += n * ang3;
                for &e in edges {
                    self.edge[e as usize] += n;
                }
            }
        }
    }

    /// Whether a point `offset` from its closest point on triangle `tri`
    /// (at `location`) lies behind the pseudo-normal there: inside.
    fn inside(
        &self,
        mesh: &parry3d::shape::TriMesh,
        tri: u32,
        location: &TrianglePointLocation,
        offset: parry3d::math::Vector,
    ) -> bool {
        let normal = match *location {
            TrianglePointLocation::OnFace(..) | TrianglePointLocation::OnSolid => mesh.triangle(tri).scaled_normal(),
            TrianglePointLocation::OnEdge(i, _) => self.edge[self.triangle_edges[tri as usize][i as usize] as usize],
            TrianglePointLocation::OnVertex(i) => self.vertex[mesh.indices()[tri as usize][i as usize] as usize],
        };
        offset.dot(normal) <= 0.0
    }
}

/// Every vertex finite, or the error that says not.
fn check_vertices(vertices: &[Point3<f64>]) -> Result<(), GraspError> {
    if vertices.iter().all(|p| p.coords.iter().all(|v| v.is_finite())) {
        Ok(())
    } else {
        Err(GraspError::BadToolMesh { reason: "a vertex is not finite".into() })
    }
}

fn check_pose(pose_world: &Isometry3<f64>) -> Result<(), GraspError> {
    if pose_world.to_homogeneous().iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(GraspError::NonFinite { what: "tool pose" })
    }
}

fn to_parry(p: &Point3<f64>) -> parry3d::math::Vector {
    parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32)
}

/// The registered tool as a solid: a watertight triangle mesh in its own
/// frame, placed in the world by `pose_world`. Parts of a multi-part mesh
/// (a mug and its handle) are separate solids; the tool is their union.
#[derive(Clone)]
pub struct ToolCollider {
    parts: Vec<Part>,
    /// How many of the tool mesh's vertices its triangles reach (the most a
    /// [`Self::deformed`] needs).
    vertices_used: usize,
    pose_world: Isometry3<f64>,
}

impl std::fmt::Debug for ToolCollider {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ToolCollider").field("parts", &self.parts.len()).field("pose_world", &self.pose_world).finish()
    }
}

impl ToolCollider {
    /// `mesh_tool`: vertices in the tool frame (metres), outward winding,
    /// every part closed. Inside/outside is decided by pseudo-normals (`PseudoNormals`),
    /// which need a closed, consistently wound surface; anything else is refused.
    pub fn new(mesh_tool: &TriMesh, pose_world: Isometry3<f64>) -> Result<Self, GraspError> {
        let bad = |reason: String| GraspError::BadToolMesh { reason };
        if mesh_tool.triangles.is_empty() {
            return Err(bad("no triangles".into()));
        }
        check_vertices(&mesh_tool.vertices)?;
        if let Some(t) = mesh_tool.triangles.iter().find(|t| t.iter().any(|&i| i as usize >= mesh_tool.vertices.len()))
        {
            return Err(bad(format!("triangle {t:?} indexes past the {} vertices", mesh_tool.vertices.len())));
        }
        let topo = mesh_tool.topology();
        if !topo.is_watertight() {
            return Err(bad(format!(
                "not a closed consistently wound surface ({} boundary, {} non-manifold, {} inconsistently wound edges); \
                 inside and outside are undefined",
                topo.boundary_edges, topo.non_manifold_edges, topo.inconsistent_edges
            )));
        }
        check_pose(&pose_world)?;
        let mut parts = Vec::new();
        for range in mesh_tool.part_ranges() {
            let mut remap = std::collections::HashMap::new();
            let (mut vertex_ids, mut indices) = (Vec::new(), Vec::new());
            for t in &mesh_tool.triangles[range] {
                let mut out = [0u32; 3];
                for k in 0..3 {
                    out[k] = *remap.entry(t[k]).or_insert_with(|| {
                        vertex_ids.push(t[k]);
                        (vertex_ids.len() - 1) as u32
                    });
                }
                indices.push(out);
            }
            let vertices = vertex_ids.iter().map(|&i| to_parry(&mesh_tool.vertices[i as usize])).collect();
            let mut normals = PseudoNormals::new(&indices);
            let mesh = parry3d::shape::TriMesh::with_flags(vertices, indices, TriMeshFlags::empty())
                .map_err(|e| bad(format!("parry refused a part: {e:?}")))?;
            normals.update(&mesh);
            let mut part =
                Part { mesh, normals, vertex_ids, lo: Vector3::zeros(), hi: Vector3::zeros(), max_depth: 0.0 };
            part.set_box(&mesh_tool.vertices);
            parts.push(part);
        }
        let vertices_used =
            parts.iter().flat_map(|p: &Part| p.vertex_ids.iter()).map(|&i| i as usize + 1).max().unwrap_or(0);
        Ok(Self { parts, vertices_used, pose_world })
    }

    /// This tool with its vertices moved to `vertices_tool` (the same mesh's
    /// vertices, in order, e.g. the canonical mesh carried through a latent
    /// shape) and placed by `pose_world`. The topology is this tool's, checked
    /// when it was made: each part's bounding-volume tree is refitted and its
    /// pseudo-normals recomputed, instead of building both from scratch (the
    /// mug's 4,064 triangles: building took most of a Grasp's 3 ms transfer
    /// stage, `bench_grasp`).
    pub fn deformed(&self, vertices_tool: &[Point3<f64>], pose_world: Isometry3<f64>) -> Result<Self, GraspError> {
        if vertices_tool.len() < self.vertices_used {
            return Err(GraspError::BadToolMesh {
                reason: format!("{} vertices; the tool's triangles index {}", vertices_tool.len(), self.vertices_used),
            });
        }
        check_vertices(vertices_tool)?;
        check_pose(&pose_world)?;
        let mut out = self.clone();
        out.pose_world = pose_world;
        for part in &mut out.parts {
            let ids = &part.vertex_ids;
            part.mesh.update_vertices(|v| {
                for (v, &i) in v.iter_mut().zip(ids) {
                    *v = to_parry(&vertices_tool[i as usize]);
                }
            });
            part.normals.update(&part.mesh);
            part.set_box(vertices_tool);
        }
        Ok(out)
    }

    pub fn pose_world(&self) -> &Isometry3<f64> {
        &self.pose_world
    }
    pub fn set_pose_world(&mut self, pose_world: Isometry3<f64>) {
        self.pose_world = pose_world;
    }

    /// Signed distance of a world point to the tool's surface (negative
    /// inside) and its world gradient (unit), or `None` when the point is
    /// certainly more than `max_distance` outside (bounding-box cull; a point
    /// inside a part's box is always queried, so deep penetration is seen).
    pub fn signed_distance(&self, p_world: &Point3<f64>, max_distance: f64) -> Option<(f64, Vector3<f64>)> {
        self.signed_distance_and_bound(p_world, max_distance).0
    }

    /// A lower bound of the signed distance at a world point, without a
    /// query: the distance to the nearest part's box, or, inside a box, the
    /// deepest a point can lie in that part (half its smallest side).
    pub fn signed_distance_lower_bound(&self, p_world: &Point3<f64>) -> f64 {
        let p = self.pose_world.inverse_transform_point(p_world).coords;
        self.parts
            .iter()
            .map(|part| {
                let outside = part.box_distance(&p);
                if outside > 0.0 {
                    outside
                } else {
                    -(part.max_depth + 1e-6)
                }
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// [`Self::signed_distance`], and a lower bound of the distance to the
    /// parts it culled (+∞ when none was): the point's distance to the
    /// nearest culled part's box.
    pub fn signed_distance_and_bound(
        &self,
        p_world: &Point3<f64>,
        max_distance: f64,
    ) -> (Option<(f64, Vector3<f64>)>, f64) {
        let p = self.pose_world.inverse_transform_point(p_world).coords;
        let pf = parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32);
        let mut best: Option<(f64, Vector3<f64>)> = None;
        let mut culled = f64::INFINITY;
        for part in &self.parts {
            let outside = part.box_distance(&p);
            if outside > max_distance {
                culled = culled.min(outside);
                continue;
            }
            // Inside/outside comes from pseudo-normals, which a deformed
            // (registered) mesh with folded or sliver triangles can get wrong
            // far from the fold. Two facts no solid can break bound that: a
            // point outside the part's box is outside it, and no inside point
            // is deeper than half the box's smallest side.
            let in_box = (p - part.lo).min() >= 0.0 && (part.hi - p).min() >= 0.0;
            // The tree search bounded by `max_distance` first: it prunes every
            // node farther than that. A point it finds nothing for is farther
            // from the surface; outside the box, that settles it (outside,
            // beyond `max_distance`); inside the box it may lie deep inside
            // the solid, so the unbounded search decides.
            let bounded = if max_distance.is_finite() {
                part.mesh.project_local_point_and_get_location_with_max_dist(pf, false, max_distance as f32)
            } else {
                None
            };
            let (proj, (tri, location)) = match bounded {
                Some(hit) => hit,
                None if !in_box && max_distance.is_finite() => {
                    culled = culled.min(max_distance);
                    continue;
                }
                None => part.mesh.project_local_point_and_get_location(pf, false),
            };
            let q = Vector3::new(proj.point.x as f64, proj.point.y as f64, proj.point.z as f64);
            let d = p - q;
            let dist = d.norm();
            let inside = part.normals.inside(&part.mesh, tri, &location, pf - proj.point)
                && in_box
                && dist <= part.max_depth + 1e-6;
            let sign = if inside { -1.0 } else { 1.0 };
            let grad = if dist > 1e-7 {
                d * (sign / dist)
            } else {
                // On the surface the direction is the face normal.
                let n = part.mesh.triangle(tri).scaled_normal();
                Vector3::new(n.x as f64, n.y as f64, n.z as f64).normalize()
            };
            let sd = sign * dist;
            if best.is_none_or(|(b, _)| sd < b) {
                best = Some((sd, grad));
            }
        }
        (best.map(|(sd, g)| (sd, self.pose_world.rotation * g)), culled)
    }
}

/// What the hand must not pierce. `Scene::default()` is empty space.
#[derive(Clone, Copy, Debug, Default)]
pub struct Scene<'a> {
    pub tool: Option<&'a ToolCollider>,
    /// The table top is the plane z = h in the world, solid below.
    pub table_height_world: Option<f64>,
}

impl Scene<'_> {
    pub fn is_empty(&self) -> bool {
        self.tool.is_none() && self.table_height_world.is_none()
    }
}

/// Distance of the hand to the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Clearance {
    /// Smallest surface-to-surface distance of any hand sphere to the tool or
    /// the table, metres; negative when piercing; +∞ for an empty scene.
    pub min_clearance_m: f64,
    /// max(0, −min_clearance_m).
    pub penetration_m: f64,
}

impl Clearance {
    pub fn collision_free(&self) -> bool {
        self.min_clearance_m >= 0.0
    }
}

/// Exact clearance of the hand state in `kin`. A group's members are all at
/// least its centre's distance less its reach from the scene (signed
/// distance is 1-Lipschitz), so groups are measured nearest bound first and
/// a group whose bound is no lower than the smallest clearance found so far
/// is skipped whole: the same minimum as measuring every sphere, with about
/// one query per primitive for the parts of the hand far from the tool.
pub fn clearance(spheres: &HandSpheres, kin: &HandKinematics, scene: &Scene) -> Clearance {
    clearance_with(spheres, kin, scene, &mut Vec::new())
}

/// [`clearance`] with the caller's buffer for the groups' bounds (no
/// allocation once it has room for one entry per group).
pub fn clearance_with(
    spheres: &HandSpheres,
    kin: &HandKinematics,
    scene: &Scene,
    bounds: &mut Vec<(f64, usize)>,
) -> Clearance {
    // Each group's clearance bounded below without a query: by the tool
    // parts' boxes (and the table, exactly). Groups are then measured in
    // that order while their bound can still lower the minimum, each query
    // bounded by what could: a hand sphere far from the tool is settled by
    // the box or a tree search cut off early, where an unbounded search for
    // its nearest triangle was most of a pre-grasp search's time
    // (`bench_grasp drill`, perf).
    bounds.clear();
    bounds.extend(spheres.groups().iter().enumerate().map(|(k, g)| {
        let cg = kin.link_pose(g.link) * Point3::from(g.center_link);
        let mut bound = scene.tool.map_or(f64::INFINITY, |tool| tool.signed_distance_lower_bound(&cg) - g.reach);
        if let Some(h) = scene.table_height_world {
            bound = bound.min(cg.z - h - g.reach);
        }
        (bound, k)
    }));
    bounds.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    let mut min = f64::INFINITY;
    // The tool's signed distance at `c` when it is under `limit` (None: not).
    let tool_below = |c: &Point3<f64>, limit: f64| {
        scene.tool.and_then(|tool| tool.signed_distance(c, limit.max(0.0))).map(|(sd, _)| sd).filter(|&sd| sd < limit)
    };
    for &(bound, k) in bounds.iter() {
        if bound >= min {
            break;
        }
        let g = &spheres.groups()[k];
        let cg = kin.link_pose(g.link) * Point3::from(g.center_link);
        let table = scene.table_height_world.map_or(f64::INFINITY, |h| cg.z - h - g.reach);
        if table >= min && tool_below(&cg, min + g.reach).is_none() {
            continue;
        }
        for i in g.members.clone() {
            let c = spheres.center_world(kin, i);
            let r = spheres.spheres()[i].radius;
            if let Some(sd) = tool_below(&c, min + r) {
                min = min.min(sd - r);
            }
            if let Some(h) = scene.table_height_world {
                min = min.min(c.z - h - r);
            }
        }
    }
    Clearance { min_clearance_m: min, penetration_m: (-min).max(0.0) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use parry3d::query::PointQueryWithLocation;
    use rand::{Rng, SeedableRng};

    /// Our pseudo-normals call inside what parry's oriented mesh calls
    /// inside, point for point: the canonical mug (two parts, body and
    /// handle) as built, and carried through a smooth non-rigid change.
    #[test]
    fn pseudo_normals_decide_inside_as_parry_does() {
        let family = crate::tools::family(crate::tools::Category::Mug).unwrap();
        let mug = &family.iter().find(|i| i.split == crate::tools::Split::Canonical).unwrap().mesh;
        let base = ToolCollider::new(mug, Isometry3::identity()).unwrap();
        let bent: Vec<Point3<f64>> = mug
            .vertices
            .iter()
            .map(|p| Point3::new(p.x * (1.0 + 3.0 * p.z), p.y * 1.1, p.z + 2.0 * p.x * p.x))
            .collect();
        let deformed = base.deformed(&bent, Isometry3::identity()).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let (mut inside, mut outside) = (0, 0);
        for tool in [&base, &deformed] {
            assert_eq!(tool.parts.len(), 2);
            for part in &tool.parts {
                let oriented = parry3d::shape::TriMesh::with_flags(
                    part.mesh.vertices().to_vec(),
                    part.mesh.indices().to_vec(),
                    TriMeshFlags::ORIENTED,
                )
                .unwrap();
                for _ in 0..1500 {
                    let p =
                        Vector3::from_fn(|i, _| part.lo[i] + (part.hi[i] - part.lo[i]) * rng.random_range(-0.2..1.2));
                    let pf = to_parry(&Point3::from(p));
                    let (proj, (tri, location)) = part.mesh.project_local_point_and_get_location(pf, false);
                    let (want, _) = oriented.project_local_point_and_get_location(pf, false);
                    assert_eq!(part.normals.inside(&part.mesh, tri, &location, pf - proj.point), want.is_inside);
                    *(if want.is_inside { &mut inside } else { &mut outside }) += 1;
                }
            }
        }
        assert!(inside > 300 && outside > 300, "{inside} inside, {outside} outside: sample the parts better");
    }
}
