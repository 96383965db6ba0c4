//! graspd's simulator: the hand and tools in MuJoCo 3.17.0 (through
//! mujoco-rs 7.0.0), for the paper's tool-use tasks.
//!
//! The crate is separate from the engine (`graspd`) so that the daemon, the
//! wire contract and the client build without MuJoCo. The C library is
//! fetched by `scripts/fetch-mujoco.sh` into `third_party/mujoco/lib`;
//! `.cargo/config.toml` points mujoco-rs at it and this crate's build script
//! writes an rpath, so binaries and tests run without LD_LIBRARY_PATH.
//!
//! Units are SI, the world is z up, quaternions on the wire are (x, y, z, w)
//! (MuJoCo's own arrays are (w, x, y, z); conversions happen at this crate's
//! edges).

pub mod camera;
pub mod carry;
pub mod daemon;
pub mod engine;
pub mod env;
pub mod episode;
pub mod hand;
pub mod mjcf;
pub mod nail;
pub mod obs;
pub mod place;
pub mod plan;
pub mod position;
pub mod render;
pub mod scene;
pub mod task;
pub mod tool;
pub mod vecenv;

pub use engine::{load_mjcf, mujoco_version, SimError, MUJOCO_VERSION};
