//! Task-space keypoints: the points on the palmar surfaces that a grasp must
//! keep (paper §III-C), the fingertips, the palm normal and the open hand,
//! read from the JSON file that accompanies a URDF.
//!
//! Format (documented for users in `assets/hands/sih_right/README.md`):
//! ```json
//! {
//!   "keypoints":  [ { "name": "palm", "link": "palm", "offset": [0, 0.018, 0.09] }, ... ],
//!   "fingertips": [ { "name": "if_tip", "link": "if_distal", "offset": [0, 0, 0.052] }, ... ],
//!   "palm_normal": [0, 1, 0],
//!   "open_hand": { "palm_to_if_proximal": 0.0, ... }
//! }
//! ```
//! Offsets are in the link frame (metres); `palm_normal` is in the root link
//! frame; `open_hand` maps every actuated joint to its angle (rad or m).
//! `fingertips` and `open_hand` may be omitted (none; every actuated joint at
//! 0 clamped into its limits).

use std::collections::{BTreeMap, HashSet};

use nalgebra::{Unit, Vector3};
use serde::Deserialize;

use super::model::{HandModel, HandModelError, JointDrive, LinkId};

/// A point fixed on a link.
#[derive(Clone, Debug, PartialEq)]
pub struct Keypoint {
    pub name: String,
    pub link: LinkId,
    /// Position in the link frame, metres.
    pub offset: Vector3<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileEntry {
    name: String,
    link: String,
    offset: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    keypoints: Vec<FileEntry>,
    #[serde(default)]
    fingertips: Vec<FileEntry>,
    palm_normal: [f64; 3],
    #[serde(default)]
    open_hand: Option<BTreeMap<String, f64>>,
}

/// The keypoints file, resolved against a model.
pub(crate) struct KeypointSet {
    pub keypoints: Vec<Keypoint>,
    pub fingertips: Vec<Keypoint>,
    pub palm_normal: Unit<Vector3<f64>>,
    pub open_hand: Vec<f64>,
}

pub(crate) fn parse_keypoints_json(json: &str, model: &HandModel) -> Result<KeypointSet, HandModelError> {
    let file: File =
        serde_json::from_str(json).map_err(|e| HandModelError::MalformedKeypoints { reason: e.to_string() })?;
    let keypoints = resolve("keypoint", &file.keypoints, model)?;
    let fingertips = resolve("fingertip", &file.fingertips, model)?;

    let n = Vector3::from(file.palm_normal);
    let norm = n.norm();
    if !norm.is_finite() || norm < 1e-9 {
        return Err(HandModelError::InvalidPalmNormal { normal: file.palm_normal });
    }
    let palm_normal = Unit::new_unchecked(n / norm);

    let limits = model.actuated_limits();
    let open_hand = match file.open_hand {
        None => {
            let mut q = vec![0.0; model.num_actuated()];
            model.clamp_actuated(&mut q);
            q
        }
        Some(map) => {
            let mut q = vec![f64::NAN; model.num_actuated()];
            for (joint, &angle) in &map {
                let bad = |reason: String| HandModelError::InvalidOpenHand { joint: joint.clone(), reason };
                let id = model.joint_index(joint).ok_or_else(|| bad("no such joint in the URDF".into()))?;
                let JointDrive::Actuated { index } = model.joints()[id].drive else {
                    return Err(bad("not an actuated joint (fixed or mimic)".into()));
                };
                let [lo, hi] = limits[index];
                if !angle.is_finite() || angle < lo || angle > hi {
                    return Err(bad(format!("{angle} is outside the joint's range [{lo}, {hi}]")));
                }
                q[index] = angle;
            }
            if let Some(missing) = q.iter().position(|v| v.is_nan()) {
                let joint = model.joints()[model.actuated_joints()[missing]].name.clone();
                return Err(HandModelError::InvalidOpenHand {
                    joint,
                    reason: "missing; give every actuated joint".into(),
                });
            }
            q
        }
    };
    Ok(KeypointSet { keypoints, fingertips, palm_normal, open_hand })
}

fn resolve(section: &'static str, entries: &[FileEntry], model: &HandModel) -> Result<Vec<Keypoint>, HandModelError> {
    let mut names = HashSet::new();
    entries
        .iter()
        .map(|e| {
            if !names.insert(e.name.as_str()) {
                return Err(HandModelError::DuplicateKeypoint { section, name: e.name.clone() });
            }
            let link = model.link_index(&e.link).ok_or_else(|| HandModelError::KeypointUnknownLink {
                section,
                name: e.name.clone(),
                link: e.link.clone(),
            })?;
            if !e.offset.iter().all(|v| v.is_finite()) {
                return Err(HandModelError::NonFinite { element: format!("{section} `{}`", e.name), what: "offset" });
            }
            Ok(Keypoint { name: e.name.clone(), link, offset: Vector3::from(e.offset) })
        })
        .collect()
}
