//! Evaluations that print the figures the issues ask for.

pub mod ambiguity;
pub mod grasp;
pub mod transfer;
pub mod ycb;
