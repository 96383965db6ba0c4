//! Geometry the rest of the engine stands on: meshes, surface sampling,
//! the virtual depth camera.

pub mod mesh;
pub mod primitives;

pub use mesh::{Topology, TriMesh};
