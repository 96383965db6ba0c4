//! Evaluations that print the figures the issues ask for.

pub mod transfer;
pub mod ycb;
