//! Geometry the rest of the engine stands on: meshes, watertight primitives,
//! surface sampling, the virtual depth camera.

pub mod camera;
pub mod farthest;
pub mod mesh;
pub mod primitives;
pub mod sample;

pub use camera::{DepthCamera, DepthNoise, Intrinsics, PartialView, Scene};
pub use farthest::farthest_point_order;
pub use mesh::{Topology, TriMesh};
pub use sample::{sample_points, sample_points_even, SurfacePoint, SurfaceSampler};

/// A static k-d tree over 3-D points, answering nearest-point queries with
/// the point's index (kiddo's immutable tree: built once from a slice, the
/// fastest of its trees to query; 32 points a leaf bucket, as kiddo's own
/// examples use: the type has no default).
pub type PointTree = kiddo::immutable::float::kdtree::ImmutableKdTree<f64, u32, 3, 32>;

#[cfg(test)]
mod camera_mug_tests;
