//! graspd service contract (see README.md).
