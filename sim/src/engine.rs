//! The thin layer over mujoco-rs: loading MJCF text with errors in our
//! vocabulary, and the linked library's version.

use mujoco_rs::prelude::{MjModel, MjModelError};
use thiserror::Error;

/// The MuJoCo release this crate is built for (mujoco-rs 7.0.0 compiles its
/// struct layouts for it; scripts/fetch-mujoco.sh fetches it).
pub const MUJOCO_VERSION: &str = "3.17.0";

/// Everything that can go wrong in the simulator.
#[derive(Debug, Error)]
pub enum SimError {
    /// MuJoCo rejected a model; `reason` is its compiler's message.
    #[error("MuJoCo cannot compile the model: {reason}")]
    Compile { reason: String },
}

/// The version string of the MuJoCo library linked at run time.
pub fn mujoco_version() -> &'static str {
    mujoco_rs::mujoco_version()
}

/// Compiles MJCF text (no external files: meshes go inline) into a model.
pub fn load_mjcf(xml: &str) -> Result<MjModel, SimError> {
    MjModel::from_xml_string(xml).map_err(|e| SimError::Compile {
        reason: match e {
            MjModelError::LoadFailed(msg) => msg,
            other => other.to_string(),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mujoco_rs::prelude::MjData;

    #[test]
    fn linked_library_is_the_pinned_release() {
        assert_eq!(mujoco_version(), MUJOCO_VERSION);
    }

    /// A 0.1 m cube dropped from 0.3 m onto a plane settles with its centre
    /// 0.05 m above it: the library loads MJCF, steps, and resolves contacts.
    #[test]
    fn a_dropped_box_comes_to_rest_on_the_floor() {
        let model = load_mjcf(
            r#"<mujoco>
                 <compiler angle="radian"/>
                 <option timestep="0.002"/>
                 <worldbody>
                   <geom name="floor" type="plane" size="1 1 0.1"/>
                   <body name="box" pos="0 0 0.3" euler="0.2 0.1 0">
                     <freejoint/>
                     <geom type="box" size="0.05 0.05 0.05" density="500"/>
                   </body>
                 </worldbody>
               </mujoco>"#,
        )
        .expect("the model compiles");
        let mut data = MjData::new(&model);
        let z0 = data.qpos()[2];
        for _ in 0..1000 {
            data.step();
        }
        assert!((data.time() - 2.0).abs() < 1e-9, "time {}", data.time());
        let z = data.qpos()[2];
        assert!((z0 - 0.3).abs() < 1e-12);
        assert!((z - 0.05).abs() < 2e-3, "box centre at {z} m, expected 0.05 m");
        let speed = data.qvel()[..3].iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!(speed < 1e-2, "box still moving at {speed} m/s");
    }

    #[test]
    fn a_malformed_model_is_an_error_naming_the_problem() {
        let err = load_mjcf("<mujoco><worldbody><geom type=\"nosuchshape\"/></worldbody></mujoco>").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("nosuchshape") || msg.contains("type"), "{msg}");
    }
}
