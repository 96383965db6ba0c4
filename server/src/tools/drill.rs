//! Cordless drills: battery pack, raked pistol grip, motor housing with the
//! chuck in front (one revolved part), and a trigger.

use super::{require, require_positive, uniform, unit, Category, Keypoint, ToolModel, ToolsError};
use crate::geometry::primitives::{
    axis_frame, push_arc, push_line, revolve, rounded_box, transform, tube, CrossSection,
};
use crate::geometry::TriMesh;
use nalgebra::{Isometry3, Point3, Vector3};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

pub const FRAME: &str = "z up; the drill stands on its battery pack on z = 0; origin at the centre of the battery's \
footprint; chuck pointing +x along the housing axis (which lies in the xz-plane); grip roughly along z, its top raked \
toward +x; right-handed, metres.";

pub const KEYPOINTS: [&str; 6] = ["trigger", "grip_top", "grip_bottom", "chuck_tip", "body_back", "battery_front"];

const SEGMENTS: usize = 40;
const GRIP_SEGMENTS: usize = 16;
/// Grip axis position under the housing, as a share of the housing length
/// from its back (the motor sits over the grip).
const GRIP_AT: f64 = 0.45;
/// Grip base behind the battery centre, as a share of the battery length.
const GRIP_BASE_BACK: f64 = 0.12;
/// How deep the grip's lower end is sunk into the battery, along its axis (m).
const GRIP_EMBED: f64 = 0.016;
/// Trigger half extents (x, y, z) and the gap between its top and the housing (m).
const TRIGGER_HALF: [f64; 3] = [0.007, 0.005, 0.008];
const TRIGGER_GAP: f64 = 0.003;
/// How far the trigger's back is sunk into the grip's front (m).
const TRIGGER_EMBED: f64 = 0.006;
/// Grip keypoints sit this far from the housing / battery (m).
const GRIP_KEY_OFFSET: f64 = 0.004;

/// A cordless drill. Frame: see [`FRAME`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DrillParams {
    /// Motor housing, rear end to the chuck's base (m).
    pub body_length: f64,
    pub body_radius: f64,
    /// Rake of the grip from vertical (rad); its top is ahead (+x) of its bottom.
    pub grip_angle: f64,
    /// Along the grip axis, from the battery's top to the housing's underside (m).
    pub grip_length: f64,
    /// Grip section across (y) (m).
    pub grip_width: f64,
    /// Grip section fore-aft (m).
    pub grip_depth: f64,
    pub battery_length: f64,
    pub battery_width: f64,
    pub battery_height: f64,
    pub chuck_length: f64,
    pub chuck_radius: f64,
}

const BODY_LENGTH: (f64, f64) = (0.12, 0.155);
const BODY_RADIUS: (f64, f64) = (0.025, 0.032);
const GRIP_ANGLE: (f64, f64) = (0.12, 0.32);
const GRIP_LENGTH: (f64, f64) = (0.075, 0.10);
const GRIP_WIDTH: (f64, f64) = (0.028, 0.036);
const GRIP_DEPTH: (f64, f64) = (0.036, 0.044);
const BATTERY_LENGTH: (f64, f64) = (0.075, 0.095);
const BATTERY_WIDTH: (f64, f64) = (0.05, 0.065);
const BATTERY_HEIGHT: (f64, f64) = (0.03, 0.045);
const CHUCK_LENGTH: (f64, f64) = (0.04, 0.065);
const CHUCK_RADIUS: (f64, f64) = (0.011, 0.016);

fn mid(r: (f64, f64)) -> f64 {
    0.5 * (r.0 + r.1)
}

struct Layout {
    /// Grip axis direction (up, raked forward) and its forward normal.
    d: Vector3<f64>,
    n: Vector3<f64>,
    /// Grip axis on the battery's top face.
    base: Point3<f64>,
    z_axis: f64,
    x_back: f64,
    half_depth: f64,
    /// Length of the rounded rear dome of the housing.
    dome: f64,
    /// Radius where the housing meets the chuck.
    collar: f64,
}

impl DrillParams {
    fn layout(&self) -> Layout {
        let (s, c) = self.grip_angle.sin_cos();
        let d = Vector3::new(s, 0.0, c);
        let n = Vector3::new(c, 0.0, -s);
        let base = Point3::new(-GRIP_BASE_BACK * self.battery_length, 0.0, self.battery_height);
        let z_axis = self.battery_height + self.grip_length * c + self.body_radius;
        let grip_top_x = base.x + (self.grip_length + self.body_radius) * s;
        Layout {
            d,
            n,
            base,
            z_axis,
            x_back: grip_top_x - GRIP_AT * self.body_length,
            half_depth: 0.5 * self.grip_depth,
            dome: 0.5 * self.body_radius,
            collar: 0.75 * self.body_radius,
        }
    }

    /// The grip's front (`side` = +1) or rear (−1) surface line at height z.
    fn grip_surface_at(&self, l: &Layout, side: f64, z: f64) -> Point3<f64> {
        let offset = l.n * (side * l.half_depth);
        let s = (z - l.base.z - offset.z) / l.d.z;
        l.base + l.d * s + offset
    }

    fn trigger_centre(&self, l: &Layout) -> Point3<f64> {
        let z = l.z_axis - self.body_radius - TRIGGER_GAP - TRIGGER_HALF[2];
        let front = self.grip_surface_at(l, 1.0, z);
        Point3::new(front.x - TRIGGER_EMBED + TRIGGER_HALF[0], 0.0, z)
    }

    /// Housing and chuck as one (r, s) profile, s from the back along the axis.
    fn body_profile(&self, l: &Layout) -> Vec<[f64; 2]> {
        let r = self.body_radius;
        let lb = self.body_length;
        let tip = lb + self.chuck_length;
        let rc = self.chuck_radius;
        let mut p = vec![[0.0, 0.0]];
        // Rounded back: quarter ellipse.
        for k in 1..=6 {
            let phi = 0.5 * PI * k as f64 / 6.0;
            p.push([r * phi.sin(), l.dome * (1.0 - phi.cos())]);
        }
        push_line(&mut p, [r, 0.75 * lb], 0.02);
        push_line(&mut p, [l.collar, lb], 0.02);
        p.push([rc, lb]);
        push_line(&mut p, [rc, tip - 0.004], 0.02);
        // Chamfered nose.
        push_arc(&mut p, [rc - 0.004, tip - 0.004], 0.004, 0.0, 0.5 * PI, 3);
        p.push([0.0, tip]);
        p
    }
}

impl ToolModel for DrillParams {
    const CATEGORY: Category = Category::Drill;

    fn canonical() -> Self {
        Self {
            body_length: mid(BODY_LENGTH),
            body_radius: mid(BODY_RADIUS),
            grip_angle: mid(GRIP_ANGLE),
            grip_length: mid(GRIP_LENGTH),
            grip_width: mid(GRIP_WIDTH),
            grip_depth: mid(GRIP_DEPTH),
            battery_length: mid(BATTERY_LENGTH),
            battery_width: mid(BATTERY_WIDTH),
            battery_height: mid(BATTERY_HEIGHT),
            chuck_length: mid(CHUCK_LENGTH),
            chuck_radius: mid(CHUCK_RADIUS),
        }
    }

    fn sample(rng: &mut ChaCha8Rng) -> Self {
        Self {
            body_length: uniform(rng, BODY_LENGTH.0, BODY_LENGTH.1),
            body_radius: uniform(rng, BODY_RADIUS.0, BODY_RADIUS.1),
            grip_angle: uniform(rng, GRIP_ANGLE.0, GRIP_ANGLE.1),
            grip_length: uniform(rng, GRIP_LENGTH.0, GRIP_LENGTH.1),
            grip_width: uniform(rng, GRIP_WIDTH.0, GRIP_WIDTH.1),
            grip_depth: uniform(rng, GRIP_DEPTH.0, GRIP_DEPTH.1),
            battery_length: uniform(rng, BATTERY_LENGTH.0, BATTERY_LENGTH.1),
            battery_width: uniform(rng, BATTERY_WIDTH.0, BATTERY_WIDTH.1),
            battery_height: uniform(rng, BATTERY_HEIGHT.0, BATTERY_HEIGHT.1),
            chuck_length: uniform(rng, CHUCK_LENGTH.0, CHUCK_LENGTH.1),
            chuck_radius: uniform(rng, CHUCK_RADIUS.0, CHUCK_RADIUS.1),
        }
    }

    fn validate(&self) -> Result<(), ToolsError> {
        let c = Category::Drill;
        require_positive(
            c,
            &[
                ("body_length", self.body_length),
                ("body_radius", self.body_radius),
                ("grip_length", self.grip_length),
                ("grip_width", self.grip_width),
                ("grip_depth", self.grip_depth),
                ("battery_length", self.battery_length),
                ("battery_width", self.battery_width),
                ("battery_height", self.battery_height),
                ("chuck_length", self.chuck_length),
                ("chuck_radius", self.chuck_radius),
            ],
        )?;
        let a = self.grip_angle;
        require(a.is_finite() && (0.0..=0.6).contains(&a), c, || format!("grip_angle {a} outside [0, 0.6] rad"))?;
        let l = self.layout();
        let (s, co) = a.sin_cos();
        let (r, hw, hd) = (self.body_radius, 0.5 * self.grip_width, l.half_depth);
        // The grip's top cap (at axis height) must be hidden in the housing...
        require(hw * hw + (hd * s).powi(2) < (0.95 * r).powi(2) && hd < r, c, || {
            "grip too thick for the housing".into()
        })?;
        // ...under its cylindrical part, between the rear dome and the front taper.
        let rear = self.grip_surface_at(&l, -1.0, l.z_axis - r).x;
        let front = l.base.x + (self.grip_length + r) * s + hd * co;
        require(rear > l.x_back + l.dome && front < l.x_back + 0.75 * self.body_length, c, || {
            "housing too short for the grip".into()
        })?;
        // The grip's bottom cap must be hidden in the battery.
        let reach_x = l.base.x.abs() + hd * co + GRIP_EMBED * s;
        require(
            reach_x < 0.5 * self.battery_length - 0.002
                && hw < 0.5 * self.battery_width - 0.002
                && GRIP_EMBED * co + hd * s < self.battery_height - 0.002,
            c,
            || "battery too small to hold the grip".into(),
        )?;
        require(self.chuck_radius < l.collar && self.chuck_length > 0.008, c, || {
            "chuck does not fit the housing".into()
        })?;
        // Room for the trigger between battery and housing, its back in the grip.
        let t = self.trigger_centre(&l);
        require(
            t.z - TRIGGER_HALF[2] > self.battery_height + 0.01 && TRIGGER_HALF[2] * s / co < TRIGGER_EMBED - 0.001,
            c,
            || "grip too short or raked too far for the trigger".into(),
        )?;
        Ok(())
    }

    fn mesh(&self) -> Result<TriMesh, ToolsError> {
        self.validate()?;
        let l = self.layout();
        let mut mesh = TriMesh::default();

        let mut battery = rounded_box(
            &Vector3::new(0.5 * self.battery_length, 0.5 * self.battery_width, 0.5 * self.battery_height),
            0.008_f64.min(0.25 * self.battery_width),
            0.0,
        )?;
        transform(&mut battery, &Isometry3::translation(0.0, 0.0, 0.5 * self.battery_height));
        mesh.append(&battery);

        let start = l.base - l.d * GRIP_EMBED;
        let end = l.base + l.d * (self.grip_length + self.body_radius);
        let len = (end - start).norm();
        let stations = (len / 0.015).ceil().max(2.0) as usize;
        let path: Vec<_> = (0..=stations).map(|k| start + (end - start) * (k as f64 / stations as f64)).collect();
        // up = +y: u = y (width), v = d × y = −n (depth, toward the back).
        let section =
            CrossSection::Ellipse { half_u: 0.5 * self.grip_width, half_v: l.half_depth, segments: GRIP_SEGMENTS };
        mesh.append(&tube(&path, &section, &Vector3::y())?);

        let mut body = revolve(&self.body_profile(&l), SEGMENTS)?;
        transform(&mut body, &axis_frame(&Point3::new(l.x_back, 0.0, l.z_axis), &Vector3::x()));
        mesh.append(&body);

        let t = self.trigger_centre(&l);
        let mut trigger = rounded_box(&Vector3::from(TRIGGER_HALF), 0.002, 0.0)?;
        transform(&mut trigger, &Isometry3::translation(t.x, t.y, t.z));
        mesh.append(&trigger);
        Ok(mesh)
    }

    fn keypoints(&self) -> Vec<Keypoint> {
        let l = self.layout();
        let t = self.trigger_centre(&l);
        let top = self.grip_surface_at(&l, -1.0, l.z_axis - self.body_radius - GRIP_KEY_OFFSET);
        let bottom = self.grip_surface_at(&l, -1.0, self.battery_height + GRIP_KEY_OFFSET);
        vec![
            // Front face of the trigger, where the index finger presses.
            Keypoint::new("trigger", [t.x + TRIGGER_HALF[0], 0.0, t.z]),
            // Back of the grip just under the housing (the web of the hand).
            Keypoint::new("grip_top", top.coords.into()),
            // Back of the grip just above the battery.
            Keypoint::new("grip_bottom", bottom.coords.into()),
            Keypoint::new("chuck_tip", [l.x_back + self.body_length + self.chuck_length, 0.0, l.z_axis]),
            Keypoint::new("body_back", [l.x_back, 0.0, l.z_axis]),
            Keypoint::new("battery_front", [0.5 * self.battery_length, 0.0, 0.5 * self.battery_height]),
        ]
    }

    fn features(&self) -> Vec<f64> {
        vec![
            unit(self.body_length, BODY_LENGTH.0, BODY_LENGTH.1),
            unit(self.body_radius, BODY_RADIUS.0, BODY_RADIUS.1),
            unit(self.grip_angle, GRIP_ANGLE.0, GRIP_ANGLE.1),
            unit(self.grip_length, GRIP_LENGTH.0, GRIP_LENGTH.1),
            unit(self.grip_width, GRIP_WIDTH.0, GRIP_WIDTH.1),
            unit(self.grip_depth, GRIP_DEPTH.0, GRIP_DEPTH.1),
            unit(self.battery_length, BATTERY_LENGTH.0, BATTERY_LENGTH.1),
            unit(self.battery_width, BATTERY_WIDTH.0, BATTERY_WIDTH.1),
            unit(self.battery_height, BATTERY_HEIGHT.0, BATTERY_HEIGHT.1),
            unit(self.chuck_length, CHUCK_LENGTH.0, CHUCK_LENGTH.1),
            unit(self.chuck_radius, CHUCK_RADIUS.0, CHUCK_RADIUS.1),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_drill_matches_a_real_drill() {
        let mesh = DrillParams::canonical().mesh().unwrap();
        let (lo, hi) = mesh.aabb().unwrap();
        let e = hi - lo;
        // YCB power drill: 0.184 × 0.188 × 0.057 (length × height × width).
        assert!((e.x - 0.184).abs() < 0.02 && (e.z - 0.18).abs() < 0.03 && (e.y - 0.057).abs() < 0.01, "{e:?}");
        // Stands on the battery: the footprint centre is the origin.
        assert!(lo.z.abs() < 1e-12);
        assert_eq!(mesh.part_ranges().len(), 4);
    }
}
