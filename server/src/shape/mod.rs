//! The shape engine: CPD, category shape spaces, registration of partial
//! views, keypoint transfer.

pub mod builtin;
pub mod cpd;
pub mod estep;
pub mod fastexp;
pub mod freespace;
pub mod grid;
pub mod kernel;
pub mod mstep;
pub mod register;
pub mod sampling;
pub mod space;

pub use register::{RegisterOptions, Registrar, Registration, YawArc};
pub use space::{BuildOptions, ShapeSpace};

#[cfg(test)]
mod tests;
