//! Writing MJCF text: the document skeleton with the physics options every
//! scene shares, and the number and name formatting the generators use.
//!
//! Scenes are generated as text (not through MuJoCo's model-editing API) so
//! that a scene can be written to a file, read, and loaded by MuJoCo's own
//! tools when something looks wrong (`sim scene --out FILE.xml`).

use std::fmt::Write as _;

use nalgebra::{Isometry3, UnitQuaternion, Vector3};

/// Collision filtering (MuJoCo: two geoms may touch when either's `contype`
/// shares a bit with the other's `conaffinity`). The hand's geoms carry bit 2
/// and accept bit 1; tools and the table carry bit 1 and accept both. So the
/// hand touches tools and the table, tools touch each other and the table,
/// and the hand never touches itself.
pub const HAND_CONTYPE: u32 = 2;
pub const HAND_CONAFFINITY: u32 = 1;
pub const WORLD_CONTYPE: u32 = 1;
pub const WORLD_CONAFFINITY: u32 = 3;

/// Physics settings shared by every scene; the defaults are the ones the
/// engine trial measured (issue 6): a hand with the SIH's couplings held a
/// 0.6 kg mug through lift and 6-DoF motion with them.
#[derive(Clone, Debug, PartialEq)]
pub struct PhysicsOptions {
    /// Policy / controller rate (the paper's 30 Hz).
    pub control_hz: f64,
    /// Physics steps per control step; the timestep is 1 / (control_hz · substeps).
    pub substeps: usize,
    /// Ratio of frictional to normal constraint impedance; > 1 makes
    /// frictional contacts harder, which keeps a held tool from creeping.
    pub impratio: f64,
    /// Newton solver iterations per step (MuJoCo's default is 100; Newton
    /// converges in a few, the cap only bounds the worst step).
    pub iterations: usize,
    /// MuJoCo's no-slip post-solver iterations (0: off). It removes the slow
    /// creep soft contacts allow; measured on the scripted mug lift: 10 of 11
    /// mugs held with 10 iterations against 9 without, at about 1.5× the
    /// cost per step, so it is off by default.
    pub noslip_iterations: usize,
}

impl Default for PhysicsOptions {
    fn default() -> Self {
        Self { control_hz: 30.0, substeps: 4, impratio: 10.0, iterations: 50, noslip_iterations: 0 }
    }
}

impl PhysicsOptions {
    /// Physics timestep, seconds.
    pub fn timestep(&self) -> f64 {
        1.0 / (self.control_hz * self.substeps as f64)
    }

    /// The `<option>` element: implicit-in-velocity integration (stable with
    /// the stiff position servos and joint damping at this large timestep),
    /// Newton solver, elliptic friction cones (pyramids let grasped tools slip).
    fn option_xml(&self) -> String {
        format!(
            r#"<option timestep="{}" integrator="implicitfast" solver="Newton" cone="elliptic" impratio="{}" iterations="{}" noslip_iterations="{}" gravity="0 0 -9.81"/>"#,
            num(self.timestep()),
            num(self.impratio),
            self.iterations,
            self.noslip_iterations
        )
    }
}

/// An MJCF document assembled from sections; each entry is one element.
#[derive(Clone, Debug, Default)]
pub struct MjcfDocument {
    pub model_name: String,
    pub physics: PhysicsOptions,
    pub assets: Vec<String>,
    pub worldbody: Vec<String>,
    pub contact: Vec<String>,
    pub equality: Vec<String>,
    pub actuator: Vec<String>,
}

impl MjcfDocument {
    pub fn new(model_name: &str, physics: PhysicsOptions) -> Self {
        Self { model_name: model_name.to_owned(), physics, ..Default::default() }
    }

    /// The whole document. Angles are radians (`compiler angle="radian"`;
    /// MJCF's default is degrees). Inertia comes from explicit `<inertial>`
    /// elements where a body has one, else from its geoms (`auto`).
    pub fn to_xml(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, r#"<mujoco model="{}">"#, esc(&self.model_name));
        s.push_str("  <compiler angle=\"radian\" inertiafromgeom=\"auto\" autolimits=\"true\"/>\n");
        let _ = writeln!(s, "  {}", self.physics.option_xml());
        for (tag, items) in [
            ("asset", &self.assets),
            ("worldbody", &self.worldbody),
            ("contact", &self.contact),
            ("equality", &self.equality),
            ("actuator", &self.actuator),
        ] {
            if items.is_empty() {
                continue;
            }
            let _ = writeln!(s, "  <{tag}>");
            for item in items {
                for line in item.lines() {
                    let _ = writeln!(s, "    {line}");
                }
            }
            let _ = writeln!(s, "  </{tag}>");
        }
        s.push_str("</mujoco>\n");
        s
    }
}

/// A finite number as MJCF text (shortest representation that reads back to
/// the same f64). Callers check finiteness where the value comes from outside.
pub(crate) fn num(x: f64) -> String {
    debug_assert!(x.is_finite(), "non-finite number written to MJCF");
    format!("{x}")
}

pub(crate) fn nums(xs: &[f64]) -> String {
    xs.iter().map(|&x| num(x)).collect::<Vec<_>>().join(" ")
}

pub(crate) fn vec3(v: &Vector3<f64>) -> String {
    nums(&[v.x, v.y, v.z])
}

/// A rotation as MJCF's `quat` (w, x, y, z).
pub(crate) fn quat_wxyz(q: &UnitQuaternion<f64>) -> String {
    nums(&[q.w, q.i, q.j, q.k])
}

/// `pos="..." quat="..."` of a pose, leaving out identity parts.
pub(crate) fn pose_attrs(pose: &Isometry3<f64>) -> String {
    let mut s = String::new();
    let t = pose.translation.vector;
    if t != Vector3::zeros() {
        let _ = write!(s, r#" pos="{}""#, vec3(&t));
    }
    if pose.rotation.angle() != 0.0 {
        let _ = write!(s, r#" quat="{}""#, quat_wxyz(&pose.rotation));
    }
    s
}

/// Escapes text for an XML attribute value (names come from users' URDFs).
pub(crate) fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_read_back_exactly() {
        for x in [0.1, -1.571, 1e-7, 2.936197264, 1.0 / 120.0] {
            assert_eq!(num(x).parse::<f64>().unwrap(), x);
        }
    }

    #[test]
    fn names_are_escaped() {
        assert_eq!(esc(r#"a"b<c>&'"#), "a&quot;b&lt;c&gt;&amp;&apos;");
    }

    #[test]
    fn default_timestep_is_four_substeps_of_30_hz() {
        assert!((PhysicsOptions::default().timestep() - 1.0 / 120.0).abs() < 1e-15);
    }
}
