//! graspd: one-shot grasp transfer for multi-fingered hands.
//!
//! The engine (usable in-process without the daemon): see ARCHITECTURE.md at
//! the repository root for the data flow from a point cloud to an action.

// `!(x > 0.0)` is how this crate rejects NaN together with the values out of
// range: the negation is the point, not an accident of style.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// Numeric kernels walk several arrays (and SIMD lanes) in lockstep by index:
// one index reads better there than a zip of four iterators.
#![allow(clippy::needless_range_loop)]

pub mod eval;
pub mod geometry;
pub mod grasp;
pub mod hand;
pub mod io;
pub mod service;
pub mod shape;
pub mod simd;
pub mod tools;
