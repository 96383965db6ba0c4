//! Geometry the rest of the engine stands on: meshes, watertight primitives,
//! surface sampling, the virtual depth camera.

pub mod camera;
pub mod mesh;
pub mod primitives;
pub mod sample;

pub use camera::{DepthCamera, DepthNoise, Intrinsics, PartialView, Scene};
pub use mesh::{Topology, TriMesh};
pub use sample::{sample_points, sample_points_even, SurfacePoint, SurfaceSampler};

#[cfg(test)]
mod camera_mug_tests;
