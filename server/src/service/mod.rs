//! The daemon behind `graspd serve`: the engine served to co-located clients
//! over iceoryx2 shared memory (the contract: crate `graspd-proto`).

pub mod config;
pub mod daemon;
pub mod engine;
mod janitor;
pub mod stats;
pub mod uds;

pub use config::{Config, Waiting};
pub use daemon::{serve, ServeError, ServeOptions, ServeReport};
