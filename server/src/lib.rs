//! graspd: one-shot grasp transfer for multi-fingered hands.
//!
//! The engine (usable in-process without the daemon): see ARCHITECTURE.md at
//! the repository root for the data flow from a point cloud to an action.

pub mod eval;
pub mod geometry;
pub mod grasp;
pub mod hand;
pub mod io;
pub mod service;
pub mod shape;
pub mod simd;
pub mod tools;
