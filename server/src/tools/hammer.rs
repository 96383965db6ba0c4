//! Hammers: a head block with a round striking face and either a curved
//! claw or a ball peen, and a tapered oval handle.

use super::{require, require_positive, uniform, unit, Category, Keypoint, Split, ToolModel, ToolsError};
use crate::geometry::primitives::{
    axis_frame, push_arc, push_line, revolve, rounded_box, sweep, transform, CrossSection,
};
use crate::geometry::TriMesh;
use nalgebra::{Isometry3, Point3, Vector3};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

pub const FRAME: &str =
    "z up; the hammer lies flat on the table (z = 0) on the side of its head, handle and head axes \
in the plane z = head_width/2; origin on the table under the head's centre (where the handle axis meets the head); \
handle along +y; head along x with the striking face toward +x and the claw or peen toward -x; right-handed, metres.";

pub const KEYPOINTS: [&str; 6] = ["handle_end", "handle_middle", "handle_neck", "head_face", "head_back", "head_top"];

/// Back end of the head: a claw (curving toward the handle) or a ball peen.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HeadVariant {
    Claw,
    Peen,
}

/// A hammer. Frame: see [`FRAME`]. Head layout along x, as shares of
/// `head_length` L: face at +0.42 L, back end (claw tip or peen) at −0.58 L,
/// head block over ±0.25 L.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HammerParams {
    /// Head centre (the handle axis' top end) to the butt of the handle (m).
    pub handle_length: f64,
    /// Handle half-thickness across the table (z) at the butt (m); the
    /// handle is oval, its half-width in the table plane 1.3× this.
    pub handle_radius: f64,
    /// Share by which the handle thins from the butt toward the head (-).
    pub handle_taper: f64,
    /// Striking face to the claw tip or peen end, along x (m).
    pub head_length: f64,
    /// Head thickness across the table, along z (m).
    pub head_width: f64,
    /// Head size along the handle, along y (m).
    pub head_height: f64,
    pub variant: HeadVariant,
}

const HANDLE_LENGTH: (f64, f64) = (0.25, 0.35);
const HANDLE_RADIUS: (f64, f64) = (0.010, 0.0135);
const HANDLE_TAPER: (f64, f64) = (0.0, 0.25);
const HEAD_LENGTH: (f64, f64) = (0.10, 0.18);
const HEAD_WIDTH: (f64, f64) = (0.024, 0.034);
const HEAD_HEIGHT: (f64, f64) = (0.022, 0.034);

/// Handle oval: in-plane half-width over half-thickness.
const HANDLE_OVAL: f64 = 1.3;
const FACE_X: f64 = 0.42;
const BACK_X: f64 = -0.58;
const BLOCK_HALF_X: f64 = 0.25;
/// Face and claw/peen start inside the block at ±0.2 L.
const ATTACH_X: f64 = 0.2;
/// Butt rounding length (m) and the section scale at the very end.
const BUTT: f64 = 0.008;
/// handle_neck keypoint: this far along the handle beyond the head (m).
const NECK_OFFSET: f64 = 0.015;
/// Train / test slots that get a peen head (the rest have claws), so both
/// variants are seen in training and in testing.
const PEEN_TRAIN: [usize; 3] = [2, 5, 8];
const PEEN_TEST: [usize; 1] = [1];

fn mid(r: (f64, f64)) -> f64 {
    0.5 * (r.0 + r.1)
}

impl HammerParams {
    fn zc(&self) -> f64 {
        0.5 * self.head_width
    }

    /// Handle half-thickness at distance y from the head centre (before the
    /// rounded butt): thinnest at the head, `handle_radius` at the butt.
    fn handle_r(&self, y: f64) -> f64 {
        let neck = self.handle_radius * (1.0 - self.handle_taper);
        let f = (y / (self.handle_length - BUTT)).clamp(0.0, 1.0);
        neck + (self.handle_radius - neck) * f
    }

    fn handle(&self) -> Result<TriMesh, ToolsError> {
        let l = self.handle_length;
        let zc = self.zc();
        let straight = l - BUTT;
        let n = (straight / 0.02).ceil().max(1.0) as usize;
        let mut ys: Vec<f64> = (0..=n).map(|k| straight * k as f64 / n as f64).collect();
        let mut scales: Vec<f64> = ys.iter().map(|&y| self.handle_r(y)).collect();
        // Rounded-off butt: a quarter-ellipse shoulder over the last BUTT.
        let r = self.handle_radius;
        for k in 1..=5 {
            let phi = 0.5 * PI * k as f64 / 5.0;
            ys.push(if k == 5 { l } else { straight + BUTT * phi.sin() });
            scales.push(r * (0.55 + 0.45 * phi.cos()));
        }
        let path: Vec<_> = ys.iter().map(|&y| Point3::new(0.0, y, zc)).collect();
        let scales: Vec<[f64; 2]> = scales.iter().map(|&s| [s, s]).collect();
        // up = +x: u = x (in-plane width), v = y × x = −z; the ellipse's
        // vertices at ±v lie on the handle's top and bottom lines.
        let section = CrossSection::Ellipse { half_u: HANDLE_OVAL, half_v: 1.0, segments: 16 }.polygon()?;
        Ok(sweep(&path, &section, &scales, &Vector3::x())?)
    }

    /// Claw tip (end of the claw's centreline) in the head's plane.
    fn claw_tip(&self) -> Point3<f64> {
        Point3::new(BACK_X * self.head_length, 0.7 * self.head_height, self.zc())
    }

    fn claw(&self) -> Result<TriMesh, ToolsError> {
        let x0 = -ATTACH_X * self.head_length;
        let tip = self.claw_tip();
        let n = 12;
        let mut path = Vec::with_capacity(n + 1);
        let mut scales = Vec::with_capacity(n + 1);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            // Curves toward the handle (+y) ever more steeply, like a claw.
            path.push(Point3::new(x0 + (tip.x - x0) * t, tip.y * t * t, tip.z));
            scales.push([self.head_width * (0.42 - 0.12 * t), self.head_height * (0.42 - 0.30 * t)]);
        }
        // up = +z: u = z (across the table), v in the table plane.
        let section = CrossSection::RoundedRect { half_u: 1.0, half_v: 1.0, corner_radius: 0.25, corner_segments: 3 }
            .polygon()?;
        Ok(sweep(&path, &section, &scales, &Vector3::z())?)
    }

    fn peen_ball_radius(&self) -> f64 {
        0.46 * self.head_width.min(self.head_height)
    }

    fn peen(&self) -> Result<TriMesh, ToolsError> {
        let length = (-BACK_X - ATTACH_X) * self.head_length;
        let rb = self.peen_ball_radius();
        let rn = 0.65 * rb;
        let centre = length - rb;
        let phi0 = -(rn / rb).acos();
        let mut p = vec![[0.0, 0.0], [rn, 0.0]];
        push_line(&mut p, [rn, centre + rb * phi0.sin()], 0.02);
        push_arc(&mut p, [0.0, centre], rb, phi0, 0.5 * PI, 10);
        let mut m = revolve(&p, 32)?;
        transform(&mut m, &axis_frame(&Point3::new(-ATTACH_X * self.head_length, 0.0, self.zc()), &-Vector3::x()));
        Ok(m)
    }

    fn face_radius(&self) -> f64 {
        0.47 * self.head_width.min(self.head_height)
    }

    fn face(&self) -> Result<TriMesh, ToolsError> {
        let length = (FACE_X - ATTACH_X) * self.head_length;
        let rf = self.face_radius();
        let neck = 0.78 * rf;
        let bevel = 0.0015;
        let p = [
            [0.0, 0.0],
            [0.9 * rf, 0.0],
            [neck, 0.45 * length],
            [rf, length - 0.003],
            [rf - bevel, length],
            [0.0, length],
        ];
        let mut m = revolve(&p, 32)?;
        transform(&mut m, &axis_frame(&Point3::new(ATTACH_X * self.head_length, 0.0, self.zc()), &Vector3::x()));
        Ok(m)
    }
}

impl ToolModel for HammerParams {
    const CATEGORY: Category = Category::Hammer;

    fn canonical() -> Self {
        Self {
            handle_length: mid(HANDLE_LENGTH),
            handle_radius: mid(HANDLE_RADIUS),
            handle_taper: mid(HANDLE_TAPER),
            head_length: mid(HEAD_LENGTH),
            head_width: mid(HEAD_WIDTH),
            head_height: mid(HEAD_HEIGHT),
            variant: HeadVariant::Claw,
        }
    }

    fn sample(rng: &mut ChaCha8Rng) -> Self {
        let handle_length = uniform(rng, HANDLE_LENGTH.0, HANDLE_LENGTH.1);
        let handle_radius = uniform(rng, HANDLE_RADIUS.0, HANDLE_RADIUS.1);
        let handle_taper = uniform(rng, HANDLE_TAPER.0, HANDLE_TAPER.1);
        let head_length = uniform(rng, HEAD_LENGTH.0, HEAD_LENGTH.1);
        let head_width = uniform(rng, HEAD_WIDTH.0, HEAD_WIDTH.1);
        let head_height = uniform(rng, HEAD_HEIGHT.0, HEAD_HEIGHT.1);
        Self {
            handle_length,
            // The handle must not be thicker than the head it lies beside,
            // or it would poke through the table.
            handle_radius: handle_radius.min(0.5 * head_width - 0.001),
            handle_taper,
            head_length,
            head_width,
            head_height,
            variant: HeadVariant::Claw,
        }
    }

    fn assign_slot(&mut self, split: Split, index: usize) {
        let peen = match split {
            Split::Canonical => false,
            Split::Train => PEEN_TRAIN.contains(&index),
            Split::Test => PEEN_TEST.contains(&index),
        };
        self.variant = if peen { HeadVariant::Peen } else { HeadVariant::Claw };
    }

    fn validate(&self) -> Result<(), ToolsError> {
        let c = Category::Hammer;
        require_positive(
            c,
            &[
                ("handle_length", self.handle_length),
                ("handle_radius", self.handle_radius),
                ("head_length", self.head_length),
                ("head_width", self.head_width),
                ("head_height", self.head_height),
            ],
        )?;
        let t = self.handle_taper;
        require(t.is_finite() && (0.0..0.8).contains(&t), c, || format!("handle_taper {t} outside [0, 0.8)"))?;
        require(self.handle_radius <= 0.5 * self.head_width - 0.0005, c, || {
            "handle thicker than the head (it would poke through the table)".into()
        })?;
        require(HANDLE_OVAL * self.handle_radius < (BLOCK_HALF_X - 0.02) * self.head_length, c, || {
            "handle wider than the head block".into()
        })?;
        require(self.handle_length > 0.5 * self.head_height + NECK_OFFSET + BUTT + 0.01, c, || {
            "handle too short for the head".into()
        })?;
        // The face's bevel and shoulder need some length.
        require((FACE_X - ATTACH_X) * self.head_length > 0.012, c, || "head too short".into())?;
        // The peen's neck must reach its ball.
        let rb = self.peen_ball_radius();
        let neck_end = (-BACK_X - ATTACH_X) * self.head_length - rb - rb * (1.0 - 0.65f64 * 0.65).sqrt();
        require(neck_end > 0.003, c, || "head too short for its peen".into())?;
        require(self.head_width < 0.5 * self.head_length && self.head_height < 0.5 * self.head_length, c, || {
            "head too thick for its length".into()
        })?;
        Ok(())
    }

    fn mesh(&self) -> Result<TriMesh, ToolsError> {
        self.validate()?;
        let mut mesh = TriMesh::default();
        let half = Vector3::new(BLOCK_HALF_X * self.head_length, 0.5 * self.head_height, 0.5 * self.head_width);
        let mut block = rounded_box(&half, 0.004_f64.min(0.3 * self.head_height), 0.0)?;
        transform(&mut block, &Isometry3::translation(0.0, 0.0, self.zc()));
        mesh.append(&block);
        mesh.append(&self.face()?);
        mesh.append(&match self.variant {
            HeadVariant::Claw => self.claw()?,
            HeadVariant::Peen => self.peen()?,
        });
        mesh.append(&self.handle()?);
        Ok(mesh)
    }

    fn keypoints(&self) -> Vec<Keypoint> {
        let zc = self.zc();
        let exposed = 0.5 * self.head_height;
        let y_mid = 0.5 * (exposed + self.handle_length);
        let y_neck = exposed + NECK_OFFSET;
        let back = match self.variant {
            HeadVariant::Claw => self.claw_tip(),
            HeadVariant::Peen => Point3::new(BACK_X * self.head_length, 0.0, zc),
        };
        vec![
            Keypoint::new("handle_end", [0.0, self.handle_length, zc]),
            // Top (+z) of the handle halfway along its exposed length.
            Keypoint::new("handle_middle", [0.0, y_mid, zc + self.handle_r(y_mid)]),
            // Top of the handle just below the head.
            Keypoint::new("handle_neck", [0.0, y_neck, zc + self.handle_r(y_neck)]),
            Keypoint::new("head_face", [FACE_X * self.head_length, 0.0, zc]),
            Keypoint::new("head_back", back.coords.into()),
            // Top of the head, opposite the handle.
            Keypoint::new("head_top", [0.0, -0.5 * self.head_height, zc]),
        ]
    }

    fn features(&self) -> Vec<f64> {
        vec![
            unit(self.handle_length, HANDLE_LENGTH.0, HANDLE_LENGTH.1),
            unit(self.handle_radius, HANDLE_RADIUS.0, HANDLE_RADIUS.1),
            unit(self.handle_taper, HANDLE_TAPER.0, HANDLE_TAPER.1),
            unit(self.head_length, HEAD_LENGTH.0, HEAD_LENGTH.1),
            unit(self.head_width, HEAD_WIDTH.0, HEAD_WIDTH.1),
            unit(self.head_height, HEAD_HEIGHT.0, HEAD_HEIGHT.1),
            match self.variant {
                HeadVariant::Claw => 0.0,
                HeadVariant::Peen => 1.0,
            },
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_hammer_matches_a_real_hammer() {
        let h = HammerParams::canonical();
        let mesh = h.mesh().unwrap();
        let (lo, hi) = mesh.aabb().unwrap();
        let e = hi - lo;
        // YCB hammer: 0.182 × 0.333 × 0.033.
        assert!((e.x - 0.15).abs() < 0.04 && (e.y - 0.32).abs() < 0.04 && (e.z - 0.03).abs() < 0.006, "{e:?}");
        assert!(lo.z.abs() < 1e-12, "lies on the table");
    }

    #[test]
    fn both_variants_build() {
        let mut h = HammerParams::canonical();
        h.variant = HeadVariant::Peen;
        let m = h.mesh().unwrap();
        assert!(m.is_watertight());
        let back = h.keypoints()[4].position;
        assert!((back[0] - m.aabb().unwrap().0.x).abs() < 1e-9, "peen is the -x end");
    }
}
