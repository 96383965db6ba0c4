//! Authoring a demonstration grasp: "close until contact".
//!
//! The hand starts open at a chosen wrist pose and every actuated joint
//! moves from the open configuration toward its closed value at once; a
//! joint stops the moment any collision sphere it moves would pierce the
//! tool or the table (found by stepping, then bisection to `tolerance_m`),
//! or when it reaches its closed value. Fingers therefore end resting on
//! the surface, so the demonstration's keypoints lie on the tool, where a
//! transferred grasp can find them again.

use nalgebra::{Isometry3, Point3};

use super::penetration::{clearance, HandSpheres, Scene};
use super::{Grasp, GraspError};
use crate::hand::{HandKinematics, HandModel, JointDrive};

#[derive(Clone, Debug, PartialEq)]
pub struct CloseOptions {
    /// Closed value of each actuated joint; `None`: for each joint, the
    /// limit farther from the open hand (for the SIH: fingers and thumb
    /// rotation to their lower limit, thumb bend to its upper limit).
    pub closed: Option<Vec<f64>>,
    /// Largest joint move per step before contact is checked (rad or m):
    /// small enough that no phalanx jumps across a thin part.
    pub max_step: f64,
    /// Contact is located to this distance (metres).
    pub tolerance_m: f64,
    pub sphere_spacing: f64,
}

impl Default for CloseOptions {
    fn default() -> Self {
        Self { closed: None, max_step: 0.01, tolerance_m: 1e-4, sphere_spacing: 0.5 }
    }
}

/// The closed grasp and how each joint stopped.
#[derive(Clone, Debug, PartialEq)]
pub struct ClosedGrasp {
    pub grasp: Grasp,
    /// Per actuated joint: it stopped on contact (true) or at its closed value.
    pub in_contact: Vec<bool>,
    /// Smallest hand-to-scene distance at the end, metres (≥ 0, ≤ tolerance
    /// for joints in contact unless the palm is closer).
    pub min_clearance_m: f64,
}

/// Closes the open hand at `wrist_pose_world` onto the scene. Fails if the
/// open hand already pierces the scene (the wrist pose is wrong).
pub fn close_until_contact(
    hand: &HandModel,
    wrist_pose_world: &Isometry3<f64>,
    scene: &Scene,
    options: &CloseOptions,
) -> Result<ClosedGrasp, GraspError> {
    let n = hand.num_actuated();
    let open = hand.open_hand().to_vec();
    let closed = match &options.closed {
        Some(c) if c.len() != n => return Err(GraspError::WrongActuatedCount { expected: n, got: c.len() }),
        Some(c) => {
            let mut c = c.clone();
            hand.clamp_actuated(&mut c);
            c
        }
        None => open
            .iter()
            .zip(hand.actuated_limits())
            .map(|(&o, &[lo, hi])| if (o - lo).abs() >= (hi - o).abs() { lo } else { hi })
            .collect(),
    };
    if !closed.iter().all(|v| v.is_finite()) {
        return Err(GraspError::NonFinite { what: "closed configuration" });
    }
    for (what, v) in [("max_step", options.max_step), ("tolerance_m", options.tolerance_m)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(GraspError::InvalidOption { what, reason: format!("{v} is not a positive finite number") });
        }
    }
    Grasp::open(hand, *wrist_pose_world).validate(hand)?;

    let spheres = HandSpheres::new(hand, options.sphere_spacing);
    let moved_by = spheres_moved_by(hand, &spheres);
    let mut kin = HandKinematics::new(hand);
    let clearance_of = |kin: &mut HandKinematics, q: &[f64], k: usize| {
        kin.update(hand, wrist_pose_world, q);
        min_clearance(&spheres, kin, scene, &moved_by[k])
    };

    kin.update(hand, wrist_pose_world, &open);
    let all: Vec<usize> = (0..spheres.spheres().len()).collect();
    let start = min_clearance(&spheres, &kin, scene, &all);
    if start < 0.0 {
        return Err(GraspError::OpenHandPenetrates { depth_mm: -1e3 * start });
    }

    // Progress s ∈ [0, 1] of each joint along open → closed.
    let mut s = vec![0.0; n];
    let mut moving: Vec<bool> = (0..n).map(|k| closed[k] != open[k]).collect();
    let mut in_contact = vec![false; n];
    let ds: Vec<f64> = (0..n).map(|k| (options.max_step / (closed[k] - open[k]).abs()).min(1.0)).collect();
    // s = 1 is the closed value exactly (no rounding past a limit).
    let at = |s: &[f64]| -> Vec<f64> {
        (0..n).map(|k| if s[k] >= 1.0 { closed[k] } else { open[k] + s[k] * (closed[k] - open[k]) }).collect()
    };
    while moving.iter().any(|&m| m) {
        for k in 0..n {
            if !moving[k] {
                continue;
            }
            let mut trial = s.clone();
            trial[k] = (s[k] + ds[k]).min(1.0);
            if clearance_of(&mut kin, &at(&trial), k) >= 0.0 {
                s[k] = trial[k];
                if s[k] >= 1.0 {
                    moving[k] = false;
                }
                continue;
            }
            // Contact between s[k] (clear) and trial[k]: bisect, keeping the
            // clear side, until it is within tolerance of the surface.
            let (mut lo, mut hi) = (s[k], trial[k]);
            let mut probe = s.clone();
            for _ in 0..60 {
                probe[k] = lo;
                if clearance_of(&mut kin, &at(&probe), k) <= options.tolerance_m {
                    break;
                }
                probe[k] = 0.5 * (lo + hi);
                if clearance_of(&mut kin, &at(&probe), k) >= 0.0 {
                    lo = probe[k];
                } else {
                    hi = probe[k];
                }
            }
            s[k] = lo;
            moving[k] = false;
            in_contact[k] = true;
        }
    }
    let q = at(&s);
    kin.update(hand, wrist_pose_world, &q);
    let min_clearance_m = min_clearance(&spheres, &kin, scene, &all);
    Ok(ClosedGrasp { grasp: Grasp::new(hand, *wrist_pose_world, q), in_contact, min_clearance_m })
}

/// For each actuated joint, the spheres on links it moves (directly or
/// through a mimic joint).
fn spheres_moved_by(hand: &HandModel, spheres: &HandSpheres) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); hand.num_actuated()];
    for (i, s) in spheres.spheres().iter().enumerate() {
        let mut l = s.link;
        let mut drivers = Vec::new();
        while let Some(j) = hand.links()[l].parent_joint {
            let joint = &hand.joints()[j];
            match joint.drive {
                JointDrive::Actuated { index } | JointDrive::Mimic { driver: index, .. } => drivers.push(index),
                JointDrive::Fixed => {}
            }
            l = joint.parent;
        }
        drivers.sort_unstable();
        drivers.dedup();
        for k in drivers {
            out[k].push(i);
        }
    }
    out
}

fn min_clearance(spheres: &HandSpheres, kin: &HandKinematics, scene: &Scene, set: &[usize]) -> f64 {
    let mut min = f64::INFINITY;
    for &i in set {
        let c: Point3<f64> = spheres.center_world(kin, i);
        let r = spheres.spheres()[i].radius;
        if let Some(tool) = scene.tool {
            if let Some((sd, _)) = tool.signed_distance(&c, f64::INFINITY) {
                min = min.min(sd - r);
            }
        }
        if let Some(h) = scene.table_height_world {
            min = min.min(c.z - h - r);
        }
    }
    min
}

/// A demonstration as stored in `assets/demos/*.json`: the grasp in the
/// canonical tool's frame and the keypoints it defines there (the points the
/// shape space moves onto other tools).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Demonstration {
    /// URDF robot name of the hand it was made with.
    pub hand: String,
    /// Free text: which tool (e.g. "mug/canonical").
    pub tool: String,
    pub wrist_pose_tool: PoseFile,
    /// Actuated joint name → value (rad or m).
    pub actuated: std::collections::BTreeMap<String, f64>,
    /// The hand's keypoints in the tool frame, in the hand's keypoint order.
    pub keypoints_tool: Vec<NamedPoint>,
    /// The scene the grasp was made in: the tool resting on the table plane
    /// z = 0 of its frame (true), or held free of it (false: a hammer lying flat
    /// cannot be wrapped by fingers that cannot pass under its handle).
    #[serde(default = "default_true")]
    pub table: bool,
    /// Fingers the grasp leaves off the tool (e.g. a ring finger that its
    /// coupling to the little finger stops short).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub free_fingers: Vec<String>,
    /// How far the grasp's hand keeps off the registered shape when the
    /// demonstration is carried to another tool (metres; absent: the
    /// solver's own, 0). The registered shape is a few millimetres off the
    /// real surface, so fingers that rest on it may be inside the real tool;
    /// a margin trades a few millimetres of keypoint distance for that,
    /// which suits a wrap or pinch (mug, hammer) but not a finger that must
    /// rest on a trigger (drill).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub penetration_margin_m: Option<f64>,
    /// Carried to another tool, no hand keypoint is held further from the
    /// registered surface than it was from the demonstration's tool (a
    /// hook through a mug's handle, which a larger mug's stretch would
    /// hold short); absent or false, the offsets follow the deformation (a
    /// pinch then closes tighter on a smaller tool).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub keep_surface_offsets: bool,
}

fn default_true() -> bool {
    true
}

/// A pose in a file: translation (metres) and unit quaternion (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseFile {
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NamedPoint {
    pub name: String,
    pub position: [f64; 3],
}

impl PoseFile {
    pub fn from_isometry(pose: &Isometry3<f64>) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.coords; // (i, j, k, w)
        Self { translation: [t.x, t.y, t.z], rotation_xyzw: [q.x, q.y, q.z, q.w] }
    }

    /// The pose; the quaternion is normalised, and must be finite and nonzero.
    pub fn to_isometry(&self) -> Result<Isometry3<f64>, GraspError> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = nalgebra::Quaternion::new(w, x, y, z);
        if !(self.translation.iter().chain(&self.rotation_xyzw).all(|v| v.is_finite()) && q.norm() > 1e-9) {
            return Err(GraspError::NonFinite { what: "pose (or its quaternion is zero)" });
        }
        Ok(Isometry3::from_parts(
            nalgebra::Translation3::new(self.translation[0], self.translation[1], self.translation[2]),
            nalgebra::UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// Directory of the bundled demonstrations (`assets/demos`), fixed at compile time.
pub const DEMO_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/demos");

/// A demonstration file that cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum DemoFileError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not a demonstration file: {source}")]
    Json {
        path: std::path::PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{path}: {reason}")]
    Invalid { path: std::path::PathBuf, reason: String },
}

/// The largest margin a demonstration file may ask for, metres.
pub const MAX_PENETRATION_MARGIN_M: f64 = 0.01;

impl Demonstration {
    /// Reads a demonstration file (format: `assets/demos/README.md`).
    pub fn load(path: impl AsRef<std::path::Path>) -> Result<Self, DemoFileError> {
        let path = path.as_ref();
        let text =
            std::fs::read_to_string(path).map_err(|source| DemoFileError::Io { path: path.to_path_buf(), source })?;
        let demo: Self =
            serde_json::from_str(&text).map_err(|source| DemoFileError::Json { path: path.to_path_buf(), source })?;
        if let Some(m) = demo.penetration_margin_m {
            if !(m.is_finite() && (0.0..=MAX_PENETRATION_MARGIN_M).contains(&m)) {
                return Err(DemoFileError::Invalid {
                    path: path.to_path_buf(),
                    reason: format!("penetration_margin_m {m}: 0 to {MAX_PENETRATION_MARGIN_M} m"),
                });
            }
        }
        Ok(demo)
    }

    /// The bundled demonstration of a category (`assets/demos/NAME.json`).
    pub fn builtin(category: crate::tools::Category) -> Result<Self, DemoFileError> {
        Self::load(Self::builtin_path(category))
    }

    pub fn builtin_path(category: crate::tools::Category) -> std::path::PathBuf {
        std::path::Path::new(DEMO_DIR).join(format!("{}.json", category.name()))
    }

    /// Records `grasp` made on a tool placed at `tool_pose_world`.
    pub fn new(hand: &HandModel, tool: &str, grasp: &Grasp, tool_pose_world: &Isometry3<f64>) -> Self {
        let to_tool = tool_pose_world.inverse();
        let keypoints_tool = hand
            .keypoints()
            .iter()
            .zip(grasp.keypoints_world(hand))
            .map(|(k, p)| {
                let p = to_tool * p;
                NamedPoint { name: k.name.clone(), position: [p.x, p.y, p.z] }
            })
            .collect();
        Self {
            hand: hand.name().to_owned(),
            tool: tool.to_owned(),
            wrist_pose_tool: PoseFile::from_isometry(&(to_tool * grasp.wrist_pose_world)),
            actuated: hand.actuated_names().map(str::to_owned).zip(grasp.actuated.iter().copied()).collect(),
            keypoints_tool,
            table: true,
            free_fingers: Vec::new(),
            penetration_margin_m: None,
            keep_surface_offsets: false,
        }
    }

    /// The keypoints in the tool frame ([`Self::keypoints`]), once the
    /// demonstration is checked to be `hand`'s: the hand's name (the URDF
    /// robot's) and a value within its limits for each of its actuated
    /// joints as well.
    pub fn checked_keypoints(&self, hand: &HandModel) -> Result<Vec<Point3<f64>>, GraspError> {
        if self.hand != hand.name() {
            return Err(GraspError::DemonstrationOfAnotherHand {
                demo_hand: self.hand.clone(),
                hand: hand.name().into(),
            });
        }
        self.grasp_at(hand, &Isometry3::identity())?;
        self.keypoints(hand)
    }

    /// The demonstrated grasp with the tool at `tool_pose_world` (the CG
    /// grasp, and the natural warm start). Checks the file against `hand`.
    pub fn grasp_at(&self, hand: &HandModel, tool_pose_world: &Isometry3<f64>) -> Result<Grasp, GraspError> {
        let mut q = Vec::with_capacity(hand.num_actuated());
        for name in hand.actuated_names() {
            let v = *self.actuated.get(name).ok_or_else(|| GraspError::InvalidOption {
                what: "demonstration actuated joints",
                reason: format!("no value for joint `{name}` of hand `{}`", hand.name()),
            })?;
            q.push(v);
        }
        if self.actuated.len() != q.len() {
            return Err(GraspError::InvalidOption {
                what: "demonstration actuated joints",
                reason: format!("{} values for a hand with {} actuated joints", self.actuated.len(), q.len()),
            });
        }
        let grasp = Grasp::new(hand, tool_pose_world * self.wrist_pose_tool.to_isometry()?, q);
        grasp.validate(hand)?;
        Ok(grasp)
    }

    /// The keypoints in the tool frame, checked against `hand`'s keypoint names.
    pub fn keypoints(&self, hand: &HandModel) -> Result<Vec<Point3<f64>>, GraspError> {
        if self.keypoints_tool.len() != hand.keypoints().len() {
            return Err(GraspError::WrongKeypointCount {
                expected: hand.keypoints().len(),
                got: self.keypoints_tool.len(),
            });
        }
        self.keypoints_tool
            .iter()
            .zip(hand.keypoints())
            .enumerate()
            .map(|(index, (p, k))| {
                if p.name != k.name {
                    return Err(GraspError::InvalidOption {
                        what: "demonstration keypoints",
                        reason: format!("keypoint {index} is `{}`, the hand's is `{}`", p.name, k.name),
                    });
                }
                if !p.position.iter().all(|v| v.is_finite()) {
                    return Err(GraspError::NonFiniteKeypoint { index });
                }
                Ok(Point3::from(p.position))
            })
            .collect()
    }
}

/// What a demonstration must satisfy on its tool ([`check_demonstration`]).
#[derive(Clone, Debug, PartialEq)]
pub struct DemoCheckOptions {
    /// A finger touches the tool when some part of it is within this, millimetres.
    pub contact_mm: f64,
    /// Deepest allowed penetration of the hand into the tool or the table, millimetres.
    pub max_penetration_mm: f64,
    /// Fingers (fingertip names without `_tip`, e.g. "if") that may stay off
    /// the tool; every other finger must touch it.
    pub free_fingers: Vec<String>,
    /// Largest allowed distance between the file's keypoints and the
    /// keypoints of its own wrist pose and joints (forward kinematics), mm.
    pub max_keypoint_mismatch_mm: f64,
    pub sphere_spacing: f64,
}

impl Default for DemoCheckOptions {
    fn default() -> Self {
        Self {
            contact_mm: 3.0,
            max_penetration_mm: 1.0,
            free_fingers: Vec::new(),
            max_keypoint_mismatch_mm: 1.0,
            sphere_spacing: 0.5,
        }
    }
}

/// One finger's distance to the tool.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FingerClearance {
    /// The fingertip's name without `_tip` ("if", "mf", "rf", "lf", "th" for the SIH).
    pub finger: String,
    /// Smallest distance of the finger's distal link to the tool surface, mm
    /// (negative: piercing).
    pub tip_clearance_mm: f64,
    /// Smallest distance of any link of the finger to the tool surface, mm.
    pub clearance_mm: f64,
    /// `clearance_mm` ≤ the contact threshold.
    pub contact: bool,
}

/// How a demonstration sits on its tool.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct DemoCheck {
    pub fingers: Vec<FingerClearance>,
    /// Smallest distance of the palm (root link) to the tool, mm.
    pub palm_clearance_mm: f64,
    /// Smallest distance of the hand to the table, mm (absent without a table).
    pub table_clearance_mm: Option<f64>,
    /// Deepest penetration into the tool or the table, mm (0 when clear).
    pub penetration_mm: f64,
    /// Distance of the stated keypoints to the forward kinematics of the
    /// stated grasp, mm.
    pub keypoint_mismatch_mm: super::ResidualStats,
    /// Why the demonstration is refused; empty when it passes.
    pub problems: Vec<String>,
}

impl DemoCheck {
    pub fn ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// The links of each finger: for every fingertip, its link and its
/// ancestors up to (not including) the root, with the finger's name.
pub fn finger_links(hand: &HandModel) -> Vec<(String, Vec<crate::hand::LinkId>)> {
    hand.fingertips()
        .iter()
        .map(|tip| {
            let name = tip.name.strip_suffix("_tip").unwrap_or(&tip.name).to_owned();
            let mut links = Vec::new();
            let mut l = tip.link;
            while l != hand.root_link() {
                links.push(l);
                match hand.links()[l].parent_joint {
                    Some(j) => l = hand.joints()[j].parent,
                    None => break,
                }
            }
            (name, links)
        })
        .collect()
}

/// Checks `grasp` (stated keypoints `keypoints_world`, hand keypoint order)
/// against the tool and table of `scene`: every finger not listed as free
/// touches the tool, nothing pierces the tool or table deeper than allowed,
/// the joints are within limits and the stated keypoints are the grasp's own.
pub fn check_demonstration(
    hand: &HandModel,
    grasp: &Grasp,
    keypoints_world: &[Point3<f64>],
    scene: &Scene,
    options: &DemoCheckOptions,
) -> Result<DemoCheck, GraspError> {
    grasp.validate(hand)?;
    if keypoints_world.len() != hand.keypoints().len() {
        return Err(GraspError::WrongKeypointCount { expected: hand.keypoints().len(), got: keypoints_world.len() });
    }
    let spheres = HandSpheres::new(hand, options.sphere_spacing);
    let mut kin = HandKinematics::new(hand);
    kin.update(hand, &grasp.wrist_pose_world, &grasp.actuated);
    let tool_clearance = |i: usize| -> f64 {
        let c = spheres.center_world(&kin, i);
        scene
            .tool
            .and_then(|t| t.signed_distance(&c, f64::INFINITY))
            .map_or(f64::INFINITY, |(sd, _)| sd - spheres.spheres()[i].radius)
    };
    let per_sphere: Vec<f64> = (0..spheres.spheres().len()).map(tool_clearance).collect();
    let min_on = |links: &[crate::hand::LinkId]| -> f64 {
        spheres
            .spheres()
            .iter()
            .zip(&per_sphere)
            .filter(|(s, _)| links.contains(&s.link))
            .map(|(_, &c)| c)
            .fold(f64::INFINITY, f64::min)
    };
    let mut problems = Vec::new();
    let fingers: Vec<FingerClearance> = finger_links(hand)
        .into_iter()
        .map(|(finger, links)| {
            let clearance_mm = 1e3 * min_on(&links);
            let tip_clearance_mm = 1e3 * min_on(&links[..1]);
            FingerClearance { finger, tip_clearance_mm, clearance_mm, contact: clearance_mm <= options.contact_mm }
        })
        .collect();
    for name in &options.free_fingers {
        if !fingers.iter().any(|f| &f.finger == name) {
            return Err(GraspError::InvalidOption {
                what: "free fingers",
                reason: format!(
                    "no finger `{name}` (this hand's: {})",
                    fingers.iter().map(|f| f.finger.as_str()).collect::<Vec<_>>().join(", ")
                ),
            });
        }
    }
    for f in &fingers {
        if !f.contact && !options.free_fingers.contains(&f.finger) {
            problems.push(format!(
                "finger `{}` does not touch the tool ({:.2} mm away; contact is ≤ {} mm)",
                f.finger, f.clearance_mm, options.contact_mm
            ));
        }
    }
    let palm_clearance_mm = 1e3 * min_on(&[hand.root_link()]);
    let table_clearance_mm = scene.table_height_world.map(|h| {
        1e3 * (0..spheres.spheres().len())
            .map(|i| spheres.center_world(&kin, i).z - h - spheres.spheres()[i].radius)
            .fold(f64::INFINITY, f64::min)
    });
    let penetration_mm = 1e3 * clearance(&spheres, &kin, scene).penetration_m;
    if penetration_mm > options.max_penetration_mm {
        problems.push(format!(
            "the hand pierces the {} by {penetration_mm:.2} mm (at most {} mm allowed)",
            if table_clearance_mm.is_some_and(|t| -t >= penetration_mm - 1e-9) { "table" } else { "tool" },
            options.max_penetration_mm
        ));
    }
    for ((name, q), &[lo, hi]) in hand.actuated_names().zip(&grasp.actuated).zip(hand.actuated_limits()) {
        if *q < lo - 1e-9 || *q > hi + 1e-9 {
            problems.push(format!("joint `{name}` = {q} is outside its limits [{lo}, {hi}]"));
        }
    }
    let keypoint_mismatch_mm = super::residual_stats(kin.keypoints(), keypoints_world);
    if keypoint_mismatch_mm.max > options.max_keypoint_mismatch_mm {
        problems.push(format!(
            "the keypoints are up to {:.2} mm from those of the stated wrist pose and joints (at most {} mm allowed)",
            keypoint_mismatch_mm.max, options.max_keypoint_mismatch_mm
        ));
    }
    Ok(DemoCheck { fingers, palm_clearance_mm, table_clearance_mm, penetration_mm, keypoint_mismatch_mm, problems })
}
