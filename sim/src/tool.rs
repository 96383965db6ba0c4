//! Tools as MuJoCo bodies: any closed triangle mesh (our procedural families,
//! an OBJ/STL from outside) becomes a free body whose
//!
//! - collision shape is an approximate convex decomposition of the mesh
//!   (parry's V-HACD; MuJoCo collides convex meshes only, and one hull of a
//!   mug would fill its handle's opening and its cavity);
//! - mass, centre of mass and inertia come from the mesh itself (exact
//!   polyhedral integrals over the closed surface) and a density, not from
//!   the hulls, which overfill concave parts.
//!
//! Densities and friction per category are in [`ToolMaterial::for_category`].

use std::fmt::Write as _;

use graspd::geometry::TriMesh;
use graspd::tools::{Category, Instance};
use nalgebra::{Matrix3, Point3, Vector3};
use parry3d::transformation::vhacd::{VHACDParameters, VHACD};

use crate::engine::SimError;
use crate::mjcf::{esc, num, nums, vec3, WORLD_CONAFFINITY, WORLD_CONTYPE};

/// What a tool is made of, as far as the physics is concerned.
#[derive(Clone, Debug, PartialEq)]
pub struct ToolMaterial {
    /// kg/m³, applied to the mesh's enclosed volume.
    pub density: f64,
    /// Sliding, torsional, rolling friction (MuJoCo takes the larger of two
    /// touching geoms' values, so the hand's pads set hand-tool friction and
    /// the larger of tool and table sets tool-table friction).
    pub friction: [f64; 3],
}

impl ToolMaterial {
    /// Documented choices per category.
    ///
    /// - Mug: glazed stoneware, 2000 kg/m³ (stoneware and porcelain are
    ///   2000-2400); the canonical mug weighs about 0.3 kg, as real mugs do.
    ///   Sliding friction 0.5 (glazed ceramic on a wooden or laminate table
    ///   is about 0.4-0.6).
    /// - Drill and hammer: our meshes are solid where the real tools are
    ///   partly hollow (a drill) or of two materials (a steel head on a wooden
    ///   handle); 1000 kg/m³ is a stand-in until those tasks are built, so
    ///   their masses are only roughly right. Friction 0.6 (plastic, rubber
    ///   grip, wood).
    pub fn for_category(category: Category) -> Self {
        match category {
            Category::Mug => Self { density: 2000.0, friction: [0.5, 0.005, 0.0001] },
            Category::Drill | Category::Hammer => Self { density: 1000.0, friction: [0.6, 0.005, 0.0001] },
        }
    }
}

/// Convex decomposition settings (parry's V-HACD).
#[derive(Clone, Debug, PartialEq)]
pub struct DecompositionOptions {
    /// Voxel grid resolution along the mesh's longest side: a mug (about
    /// 0.13 m across with its handle) at 96 gets about 1.4 mm voxels, fine
    /// enough for its 3-6 mm walls and its handle's opening.
    pub resolution: u32,
    /// Largest concavity allowed per hull (V-HACD's measure, relative to the
    /// mesh's size). On the canonical mug 0.005 gives 22 hulls and keeps the
    /// handle's opening empty; 0.02 gives 13 and fills it.
    pub concavity: f32,
    pub max_hulls: u32,
}

impl Default for DecompositionOptions {
    fn default() -> Self {
        Self { resolution: 96, concavity: 0.005, max_hulls: 32 }
    }
}

/// Mass properties of a solid.
#[derive(Clone, Debug, PartialEq)]
pub struct MassProperties {
    /// kg.
    pub mass: f64,
    /// m³.
    pub volume: f64,
    /// Centre of mass in the mesh frame.
    pub com: Point3<f64>,
    /// Inertia tensor about the centre of mass, mesh axes, kg·m².
    pub inertia: Matrix3<f64>,
}

/// Mass properties of the solid a closed, outward-wound mesh encloses, at a
/// uniform density: each triangle with the origin spans a signed
/// tetrahedron, whose volume, first and second moments are exact.
/// Overlapping parts (a mug handle sunk into the wall) count twice where they
/// overlap; for our tools that is well under 1 % of the volume.
pub fn mass_properties(mesh: &TriMesh, density: f64) -> Result<MassProperties, SimError> {
    let mut volume = 0.0;
    let mut first = Vector3::zeros();
    // Second moment ∫ x xᵀ dV about the origin.
    let mut second = Matrix3::zeros();
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize].coords);
        let v = a.dot(&b.cross(&c)) / 6.0;
        volume += v;
        first += v * (a + b + c) / 4.0;
        let s = a + b + c;
        second += v / 20.0 * (a * a.transpose() + b * b.transpose() + c * c.transpose() + s * s.transpose());
    }
    if !(volume.is_finite() && volume > 0.0) {
        return Err(SimError::Tool {
            reason: format!("the mesh encloses no positive volume ({volume} m³): not closed or wound inward"),
        });
    }
    if !(density.is_finite() && density > 0.0) {
        return Err(SimError::Tool { reason: format!("density {density} is not a positive finite number") });
    }
    let com = first / volume;
    // About the centre of mass, then as an inertia tensor: I = tr(C)·1 − C.
    let c = density * (second - volume * com * com.transpose());
    let inertia = Matrix3::identity() * c.trace() - c;
    Ok(MassProperties { mass: density * volume, volume, com: Point3::from(com), inertia })
}

/// A convex piece of a tool's collision shape (vertices in the tool frame).
#[derive(Clone, Debug, PartialEq)]
pub struct Hull {
    pub vertices: Vec<Point3<f64>>,
}

/// Approximate convex decomposition of a closed mesh (V-HACD); hulls of the
/// mesh's own vertices within each part (not of the voxels, which would add
/// up to a voxel of thickness all round).
pub fn convex_decomposition(mesh: &TriMesh, opts: &DecompositionOptions) -> Result<Vec<Hull>, SimError> {
    if mesh.triangles.is_empty() {
        return Err(SimError::Tool { reason: "the mesh has no triangles".into() });
    }
    if !mesh.vertices.iter().all(|p| p.coords.iter().all(|v| v.is_finite())) {
        return Err(SimError::Tool { reason: "the mesh has non-finite vertices".into() });
    }
    let n = mesh.vertices.len() as u32;
    if let Some(t) = mesh.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
        return Err(SimError::Tool { reason: format!("triangle {t:?} indexes past the {n} vertices") });
    }
    let points: Vec<parry3d::math::Vector> =
        mesh.vertices.iter().map(|p| parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32)).collect();
    let params = VHACDParameters {
        resolution: opts.resolution,
        concavity: opts.concavity,
        max_convex_hulls: opts.max_hulls,
        ..VHACDParameters::default()
    };
    let vhacd = VHACD::decompose(&params, &points, &mesh.triangles, true);
    let hulls: Vec<Hull> = vhacd
        .compute_exact_convex_hulls(&points, &mesh.triangles)
        .into_iter()
        .map(|(verts, _)| Hull {
            vertices: verts.iter().map(|v| Point3::new(v.x as f64, v.y as f64, v.z as f64)).collect(),
        })
        // MuJoCo cannot give a flat or tiny hull a volume; such slivers add
        // nothing to the contact shape.
        .filter(|h| hull_is_solid(&h.vertices))
        .collect();
    if hulls.is_empty() {
        return Err(SimError::Tool { reason: "the convex decomposition produced no solid hull".into() });
    }
    Ok(hulls)
}

/// Whether a point set spans a volume: at least 4 points, not (nearly) on a
/// plane (thinner than 0.1 mm).
fn hull_is_solid(points: &[Point3<f64>]) -> bool {
    if points.len() < 4 {
        return false;
    }
    let n = points.len() as f64;
    let centre = points.iter().fold(Vector3::zeros(), |acc, p| acc + p.coords) / n;
    let cov = points.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = p.coords - centre;
        acc + d * d.transpose()
    }) / n;
    let smallest = cov.symmetric_eigenvalues().min();
    smallest.max(0.0).sqrt() > 1e-4
}

/// A tool ready to be placed in a scene.
#[derive(Clone, Debug)]
pub struct ToolBody {
    /// Body name in the scene (its mesh assets are named after it).
    pub name: String,
    pub mass: MassProperties,
    pub hulls: Vec<Hull>,
    pub material: ToolMaterial,
}

impl ToolBody {
    /// Decomposes the mesh and computes its mass properties.
    /// A tool instance of the built-in families, named after it, in its category's material.
    pub fn from_instance(instance: &Instance, decomposition: &DecompositionOptions) -> Result<Self, SimError> {
        Self::from_mesh(&instance.name, &instance.mesh, ToolMaterial::for_category(instance.category), decomposition)
    }

    pub fn from_mesh(
        name: &str,
        mesh: &TriMesh,
        material: ToolMaterial,
        decomposition: &DecompositionOptions,
    ) -> Result<Self, SimError> {
        let mass = mass_properties(mesh, material.density)?;
        let hulls = convex_decomposition(mesh, decomposition)?;
        Ok(Self { name: name.to_owned(), mass, hulls, material })
    }

    /// The hulls' vertices, tool frame: mesh vertices that include every
    /// extreme point of the tool (its lowest point in any pose is one of them).
    pub fn support_points(&self) -> Vec<Point3<f64>> {
        self.hulls.iter().flat_map(|h| h.vertices.iter().copied()).collect()
    }

    /// `<mesh>` assets, one per hull.
    pub fn assets(&self) -> Vec<String> {
        self.hulls
            .iter()
            .enumerate()
            .map(|(k, h)| {
                let verts: Vec<f64> = h.vertices.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
                format!(r#"<mesh name="{}_hull_{k}" vertex="{}"/>"#, esc(&self.name), nums(&verts))
            })
            .collect()
    }

    /// The free body, its frame at `pos` / `quat_wxyz` in the world.
    pub fn body(&self, pose: &nalgebra::Isometry3<f64>) -> String {
        let mut s = String::new();
        let name = esc(&self.name);
        let _ = writeln!(s, r#"<body name="{name}"{}>"#, crate::mjcf::pose_attrs(pose));
        let _ = writeln!(s, r#"  <freejoint name="{name}_free"/>"#);
        let i = &self.mass.inertia;
        let _ = writeln!(
            s,
            r#"  <inertial pos="{}" mass="{}" fullinertia="{}"/>"#,
            vec3(&self.mass.com.coords),
            num(self.mass.mass),
            nums(&[i[(0, 0)], i[(1, 1)], i[(2, 2)], i[(0, 1)], i[(0, 2)], i[(1, 2)]])
        );
        for k in 0..self.hulls.len() {
            let _ = writeln!(
                s,
                r#"  <geom type="mesh" mesh="{name}_hull_{k}" contype="{WORLD_CONTYPE}" conaffinity="{WORLD_CONAFFINITY}" condim="4" friction="{}" group="2"/>"#,
                nums(&self.material.friction)
            );
        }
        s.push_str("</body>");
        s
    }
}

/// The canonical mug and its body, decomposed with the default options:
/// the tool most of the simulator's tests stand on.
#[cfg(test)]
pub(crate) fn canonical_mug() -> (graspd::tools::Instance, ToolBody) {
    use graspd::tools::{self, Category};
    let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
    let body = ToolBody::from_mesh(
        "mug",
        &mug.mesh,
        ToolMaterial::for_category(Category::Mug),
        &DecompositionOptions::default(),
    )
    .unwrap();
    (mug, body)
}

#[cfg(test)]
mod tests {
    use super::*;
    use graspd::tools;

    fn cube(side: f64, centre: Vector3<f64>) -> TriMesh {
        let h = side / 2.0;
        let v: Vec<Point3<f64>> = (0..8)
            .map(|i| {
                let s = |bit: usize| if i & bit != 0 { h } else { -h };
                Point3::from(centre + Vector3::new(s(1), s(2), s(4)))
            })
            .collect();
        // Outward-wound faces of the cube (vertex index bits: x=1, y=2, z=4).
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let triangles = quads.iter().flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        TriMesh::new(v, triangles)
    }

    #[test]
    fn a_cube_has_the_textbook_mass_properties() {
        let mesh = cube(0.1, Vector3::new(0.3, -0.2, 0.05));
        let m = mass_properties(&mesh, 1000.0).unwrap();
        assert!((m.volume - 1e-3).abs() < 1e-15);
        assert!((m.mass - 1.0).abs() < 1e-12);
        assert!((m.com.coords - Vector3::new(0.3, -0.2, 0.05)).norm() < 1e-12);
        // m·s²/6 about every axis through the centre, no products.
        let expected = Matrix3::identity() * (1.0 * 0.01 / 6.0);
        assert!((m.inertia - expected).norm() < 1e-12, "{}", m.inertia);
    }

    #[test]
    fn an_inward_wound_mesh_is_refused() {
        let mut mesh = cube(0.1, Vector3::zeros());
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
        assert!(mass_properties(&mesh, 1000.0).unwrap_err().to_string().contains("volume"));
    }

    /// The canonical mug: a plausible mass, several hulls that cover the
    /// surface, and the handle's opening and the cavity left empty (a single
    /// hull would fill both and the fingers could not go through the handle).
    #[test]
    fn canonical_mug_decomposes_into_hulls_that_keep_its_openings() {
        let (mug, body) = canonical_mug();
        assert!(body.mass.mass > 0.2 && body.mass.mass < 0.5, "mug mass {} kg", body.mass.mass);
        assert!(body.hulls.len() >= 4, "{} hulls", body.hulls.len());

        let tools::ToolParams::Mug(p) = &mug.params else { unreachable!() };
        let planes: Vec<Vec<(Vector3<f64>, f64)>> = body.hulls.iter().map(|h| hull_planes(&h.vertices)).collect();
        // Largest signed distance to a hull's face planes: ≤ 0 inside the hull,
        // else a lower bound of the distance to it.
        let outside_by = |q: &Point3<f64>| {
            planes
                .iter()
                .map(|faces| faces.iter().map(|(n, d)| n.dot(&q.coords) - d).fold(f64::NEG_INFINITY, f64::max))
                .fold(f64::INFINITY, f64::min)
        };
        // The handle's opening: between the wall and the handle's inner side, at its middle height.
        let handle_mid = mug.keypoint("handle_middle").unwrap().position;
        let opening = Point3::new(0.5 * (p.radius + handle_mid[0] - p.handle_thickness), 0.0, p.handle_centre_z);
        assert!(outside_by(&opening) > 2e-3, "the handle's opening at {opening} is filled");
        // The cavity, on the axis from the floor up.
        for z in [0.3, 0.6, 0.9] {
            let q = Point3::new(0.0, 0.0, z * p.height);
            assert!(outside_by(&q) > 5e-3, "the cavity is filled at {q}");
        }
        // Every surface vertex lies on the collision shape (the hulls are
        // hulls of the mesh's own vertices, within float rounding).
        let worst = mug.mesh.vertices.iter().map(outside_by).fold(f64::NEG_INFINITY, f64::max);
        assert!(worst < 1e-4, "a mesh vertex lies {worst} m outside every hull");
    }

    /// Outward unit normals and offsets (n·x = d) of the convex hull's faces.
    fn hull_planes(points: &[Point3<f64>]) -> Vec<(Vector3<f64>, f64)> {
        let pts: Vec<parry3d::math::Vector> =
            points.iter().map(|p| parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32)).collect();
        let (v, faces) = parry3d::transformation::convex_hull(&pts);
        let v: Vec<Vector3<f64>> = v.iter().map(|p| Vector3::new(p.x as f64, p.y as f64, p.z as f64)).collect();
        let centre = v.iter().sum::<Vector3<f64>>() / v.len() as f64;
        faces
            .iter()
            .filter_map(|f| {
                let [a, b, c] = f.map(|i| v[i as usize]);
                let n = (b - a).cross(&(c - a));
                let len = n.norm();
                if len < 1e-12 {
                    return None;
                }
                let n = if n.dot(&(a - centre)) < 0.0 { -n / len } else { n / len };
                Some((n, n.dot(&a)))
            })
            .collect()
    }
}
