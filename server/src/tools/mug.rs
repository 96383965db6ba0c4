//! Mugs: a revolved cup (outer wall, rounded rim, inner wall, floor) and a
//! D-shaped handle swept with an elliptic section.

use super::{require, require_positive, uniform, unit, Category, Keypoint, ToolModel, ToolsError};
use crate::geometry::primitives::{push_arc, push_line, revolve, tube, CrossSection};
use crate::geometry::TriMesh;
use nalgebra::{Point3, Vector3};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

pub const FRAME: &str = "z up along the mug's axis; origin at the centre of the base (the mug stands on z = 0); \
handle in the xz-plane toward +x; right-handed, metres.";

pub const KEYPOINTS: [&str; 6] =
    ["handle_middle", "handle_top", "handle_bottom", "rim_front", "rim_back", "base_centre"];

/// Meridians around the body (a multiple of 4: the rim keypoints at ±x are vertices).
const SEGMENTS: usize = 48;
const HANDLE_SEGMENTS: usize = 16;
/// Longest profile edge (keeps wall triangles from becoming needles).
const STEP: f64 = 0.015;
/// How far the handle's ends are sunk into the wall, as a share of the wall thickness.
const EMBED: f64 = 0.6;
/// Keypoints at the handle joints sit this far out from the body wall.
const JOINT_OFFSET: f64 = 0.002;

/// A mug. Frame: see [`FRAME`]. The outer wall is a cone: radius `radius`
/// at the rim, narrowing toward the base by `taper`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MugParams {
    /// Outer radius at the rim (m).
    pub radius: f64,
    /// Base to rim (m).
    pub height: f64,
    pub wall_thickness: f64,
    /// Solid floor thickness above the base (m).
    pub floor_thickness: f64,
    /// Wall half-angle (rad); positive means wider at the rim.
    pub taper: f64,
    /// Vertical distance between the centrelines of the handle's two joints (m).
    pub handle_height: f64,
    /// Height of the handle's middle above the base (m).
    pub handle_centre_z: f64,
    /// Outer wall (at `handle_centre_z`) to the handle's outermost surface (m).
    pub handle_reach: f64,
    /// Handle section size in the handle's plane (m).
    pub handle_thickness: f64,
    /// Handle section size across the handle's plane, along y (m).
    pub handle_width: f64,
}

/// Sampling ranges, (lo, hi). Handle height and centre are drawn as shares
/// of the mug's height, then fitted between base and rim.
const RADIUS: (f64, f64) = (0.035, 0.05);
const HEIGHT: (f64, f64) = (0.08, 0.12);
const WALL: (f64, f64) = (0.003, 0.006);
const FLOOR: (f64, f64) = (0.005, 0.009);
const TAPER: (f64, f64) = (0.0, 0.08);
const HANDLE_HEIGHT_SHARE: (f64, f64) = (0.5, 0.68);
const HANDLE_CENTRE_SHARE: (f64, f64) = (0.46, 0.56);
const REACH: (f64, f64) = (0.022, 0.034);
const HANDLE_THICKNESS: (f64, f64) = (0.007, 0.011);
const HANDLE_WIDTH: (f64, f64) = (0.010, 0.015);

fn mid(r: (f64, f64)) -> f64 {
    0.5 * (r.0 + r.1)
}

/// Derived layout, shared by the mesh and the keypoints.
struct Layout {
    tan: f64,
    r_bottom: f64,
    /// Top and bottom joint heights (handle centreline).
    z_top: f64,
    z_bottom: f64,
    /// Outermost handle centreline x and its corner radius.
    x_out: f64,
    corner: f64,
    /// Centre radius of the rim's half-round.
    rim_r: f64,
}

impl MugParams {
    fn layout(&self) -> Layout {
        let tan = self.taper.tan();
        let r_out = |z: f64| self.radius - (self.height - z) * tan;
        let z_top = self.handle_centre_z + 0.5 * self.handle_height;
        let z_bottom = self.handle_centre_z - 0.5 * self.handle_height;
        let x_out = r_out(self.handle_centre_z) + self.handle_reach - 0.5 * self.handle_thickness;
        let r_max = r_out(z_top).max(r_out(z_bottom));
        // Rounded corners of the D: as round as the handle allows, but no
        // tighter than the section (the inner side would fold).
        let corner = (0.75 * (x_out - r_max)).min(0.8 * 0.5 * self.handle_height);
        let rim_r = r_out(self.height - 0.5 * self.wall_thickness) - 0.5 * self.wall_thickness;
        Layout { tan, r_bottom: r_out(0.0), z_top, z_bottom, x_out, corner, rim_r }
    }

    /// Outer wall radius at height z.
    fn r_out(&self, z: f64) -> f64 {
        self.radius - (self.height - z) * self.taper.tan()
    }

    /// The (r, z) profile of the cup, counter-clockwise.
    fn body_profile(&self, l: &Layout) -> Vec<[f64; 2]> {
        let t = self.wall_thickness;
        let h = self.height;
        let zf = self.floor_thickness;
        let fillet_out = (0.5 * zf).min(0.003);
        let fillet_in = (0.25 * (l.r_bottom - t)).min(0.005);
        let r_in = |z: f64| self.r_out(z) - t;
        let mut p = vec![[0.0, 0.0]];
        push_line(&mut p, [l.r_bottom - fillet_out, 0.0], STEP);
        push_arc(&mut p, [l.r_bottom - fillet_out, fillet_out], fillet_out, -0.5 * PI, 0.0, 4);
        push_line(&mut p, [self.r_out(h - 0.5 * t), h - 0.5 * t], STEP);
        // Half-round rim; its apex (8 pieces: step 4 is at π/2) is at z = h.
        push_arc(&mut p, [l.rim_r, h - 0.5 * t], 0.5 * t, 0.0, PI, 8);
        let zc = zf + fillet_in;
        push_line(&mut p, [r_in(zc), zc], STEP);
        push_arc(&mut p, [r_in(zc) - fillet_in, zc], fillet_in, 0.0, -0.5 * PI, 5);
        push_line(&mut p, [0.0, zf], STEP);
        p
    }

    /// Handle centreline in the xz-plane: out from the wall at the top
    /// joint, round corner, down, round corner, back into the wall.
    fn handle_path(&self, l: &Layout) -> Vec<Point3<f64>> {
        let embed = EMBED * self.wall_thickness;
        let rc = l.corner;
        let mut q: Vec<[f64; 2]> = vec![[self.r_out(l.z_top) - embed, l.z_top]];
        push_line(&mut q, [l.x_out - rc, l.z_top], 0.006);
        push_arc(&mut q, [l.x_out - rc, l.z_top - rc], rc, 0.5 * PI, 0.0, 8);
        push_line(&mut q, [l.x_out, l.z_bottom + rc], 0.008);
        push_arc(&mut q, [l.x_out - rc, l.z_bottom + rc], rc, 0.0, -0.5 * PI, 8);
        push_line(&mut q, [self.r_out(l.z_bottom) - embed, l.z_bottom], 0.006);
        q.dedup();
        q.into_iter().map(|[x, z]| Point3::new(x, 0.0, z)).collect()
    }
}

impl ToolModel for MugParams {
    const CATEGORY: Category = Category::Mug;

    fn canonical() -> Self {
        let height = mid(HEIGHT);
        Self {
            radius: mid(RADIUS),
            height,
            wall_thickness: mid(WALL),
            floor_thickness: mid(FLOOR),
            taper: mid(TAPER),
            handle_height: mid(HANDLE_HEIGHT_SHARE) * height,
            handle_centre_z: mid(HANDLE_CENTRE_SHARE) * height,
            handle_reach: mid(REACH),
            handle_thickness: mid(HANDLE_THICKNESS),
            handle_width: mid(HANDLE_WIDTH),
        }
    }

    fn sample(rng: &mut ChaCha8Rng) -> Self {
        let radius = uniform(rng, RADIUS.0, RADIUS.1);
        let height = uniform(rng, HEIGHT.0, HEIGHT.1);
        let wall_thickness = uniform(rng, WALL.0, WALL.1);
        let floor_thickness = uniform(rng, FLOOR.0, FLOOR.1);
        let taper = uniform(rng, TAPER.0, TAPER.1);
        let handle_share = uniform(rng, HANDLE_HEIGHT_SHARE.0, HANDLE_HEIGHT_SHARE.1);
        let centre_share = uniform(rng, HANDLE_CENTRE_SHARE.0, HANDLE_CENTRE_SHARE.1);
        let handle_reach = uniform(rng, REACH.0, REACH.1);
        let handle_thickness = uniform(rng, HANDLE_THICKNESS.0, HANDLE_THICKNESS.1);
        let handle_width = uniform(rng, HANDLE_WIDTH.0, HANDLE_WIDTH.1);
        // Fit the handle between the base and the rim with a margin.
        let handle_centre_z = centre_share * height;
        let room_above = height - wall_thickness - 0.004 - 0.5 * handle_thickness - handle_centre_z;
        let room_below = handle_centre_z - 0.5 * handle_thickness - 0.004;
        let handle_height = (handle_share * height).min(2.0 * room_above.min(room_below));
        Self {
            radius,
            height,
            wall_thickness,
            floor_thickness,
            taper,
            handle_height,
            handle_centre_z,
            handle_reach,
            handle_thickness,
            handle_width,
        }
    }

    fn validate(&self) -> Result<(), ToolsError> {
        let c = Category::Mug;
        require_positive(
            c,
            &[
                ("radius", self.radius),
                ("height", self.height),
                ("wall_thickness", self.wall_thickness),
                ("floor_thickness", self.floor_thickness),
                ("handle_height", self.handle_height),
                ("handle_centre_z", self.handle_centre_z),
                ("handle_reach", self.handle_reach),
                ("handle_thickness", self.handle_thickness),
                ("handle_width", self.handle_width),
            ],
        )?;
        require(self.taper.is_finite() && self.taper.abs() < 0.5, c, || {
            format!("taper {} outside ±0.5 rad", self.taper)
        })?;
        let l = self.layout();
        let t = self.wall_thickness;
        require(l.r_bottom > 2.5 * t && self.r_out(self.height) > 2.5 * t, c, || {
            "wall too thick for the radius".into()
        })?;
        require(self.floor_thickness < 0.5 * self.height, c, || "floor thicker than half the height".into())?;
        require(t < 0.25 * self.height, c, || "wall thicker than a quarter of the height".into())?;
        let half = 0.5 * self.handle_thickness;
        require(l.z_bottom - half >= 0.0 && l.z_top + half <= self.height - t, c, || {
            "handle does not fit between the base and the rim".into()
        })?;
        require(self.handle_width < 2.0 * l.r_bottom && half < 2.0 * t + 0.02, c, || {
            "handle section too large".into()
        })?;
        // The joints are sunk EMBED·t into the wall. Their caps must stay
        // behind the outer wall, which curves inward by w²/8r across the
        // section's width and slants with the taper over its height, and in
        // front of the inner wall.
        let r_joint = self.r_out(l.z_bottom).min(self.r_out(l.z_top));
        let slant = half * l.tan.abs();
        let sag = self.handle_width * self.handle_width / (8.0 * r_joint);
        require(sag + slant < EMBED * t && EMBED * t + slant < t, c, || {
            "handle too wide for the wall to hide its ends".into()
        })?;
        require(l.corner >= 0.6 * self.handle_thickness, c, || {
            "handle too short or too tight for its thickness (its inside would fold)".into()
        })?;
        Ok(())
    }

    fn mesh(&self) -> Result<TriMesh, ToolsError> {
        self.validate()?;
        let l = self.layout();
        let mut mesh = TriMesh::default();
        mesh.append(&revolve(&self.body_profile(&l), SEGMENTS)?);
        let section = CrossSection::Ellipse {
            half_u: 0.5 * self.handle_width,
            half_v: 0.5 * self.handle_thickness,
            segments: HANDLE_SEGMENTS,
        };
        // The path lies in the xz-plane, so u stays +y all along; v = t × y
        // is the in-plane normal, which puts section vertices on the
        // handle's top, bottom and outermost lines.
        mesh.append(&tube(&self.handle_path(&l), &section, &Vector3::y())?);
        Ok(mesh)
    }

    fn keypoints(&self) -> Vec<Keypoint> {
        let l = self.layout();
        let half = 0.5 * self.handle_thickness;
        let mid_z = 0.5 * (l.z_top + l.z_bottom);
        vec![
            // Outermost point of the handle, where the fingers wrap.
            Keypoint::new("handle_middle", [l.x_out + half, 0.0, mid_z]),
            // On top of the handle just outside the upper joint.
            Keypoint::new("handle_top", [self.r_out(l.z_top) + JOINT_OFFSET, 0.0, l.z_top + half]),
            // Under the handle just outside the lower joint.
            Keypoint::new("handle_bottom", [self.r_out(l.z_bottom) + JOINT_OFFSET, 0.0, l.z_bottom - half]),
            // Apex of the rim, opposite the handle and on the handle side.
            Keypoint::new("rim_front", [-l.rim_r, 0.0, self.height]),
            Keypoint::new("rim_back", [l.rim_r, 0.0, self.height]),
            Keypoint::new("base_centre", [0.0, 0.0, 0.0]),
        ]
    }

    fn features(&self) -> Vec<f64> {
        vec![
            unit(self.radius, RADIUS.0, RADIUS.1),
            unit(self.height, HEIGHT.0, HEIGHT.1),
            unit(self.wall_thickness, WALL.0, WALL.1),
            unit(self.floor_thickness, FLOOR.0, FLOOR.1),
            unit(self.taper, TAPER.0, TAPER.1),
            unit(self.handle_height, HANDLE_HEIGHT_SHARE.0 * HEIGHT.0, HANDLE_HEIGHT_SHARE.1 * HEIGHT.1),
            unit(self.handle_centre_z, HANDLE_CENTRE_SHARE.0 * HEIGHT.0, HANDLE_CENTRE_SHARE.1 * HEIGHT.1),
            unit(self.handle_reach, REACH.0, REACH.1),
            unit(self.handle_thickness, HANDLE_THICKNESS.0, HANDLE_THICKNESS.1),
            unit(self.handle_width, HANDLE_WIDTH.0, HANDLE_WIDTH.1),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_mug_matches_a_real_mug() {
        let m = MugParams::canonical();
        let mesh = m.mesh().unwrap();
        let (lo, hi) = mesh.aabb().unwrap();
        // YCB mug: 0.117 × 0.093 × 0.081.
        assert!((hi.x - lo.x - 0.11).abs() < 0.02, "{:?}", hi - lo);
        assert!((hi.z - m.height).abs() < 1e-12 && lo.z.abs() < 1e-12);
        // Hollow: far less volume than the solid cylinder.
        let solid = PI * m.radius * m.radius * m.height;
        assert!(mesh.signed_volume() < 0.5 * solid);
    }

    #[test]
    fn handle_joints_are_hidden_in_the_wall() {
        // The handle tube's end caps lie between the inner and outer wall.
        let m = MugParams::canonical();
        let l = m.layout();
        let path = m.handle_path(&l);
        for (p, z) in [(path[0], l.z_top), (path[path.len() - 1], l.z_bottom)] {
            assert!(p.x < m.r_out(z) && p.x > m.r_out(z) - m.wall_thickness);
        }
    }
}
