//! The quincunx streaming client core: what people embed in their apps and what load
//! tests simulate. No GPU needed.
//!
//! - [`view`]: the camera (`f64` throughout), frustum, projected sizes, world mapping.
//! - [`dag`]: the in-core diamond DAG from the roots down to the current cut, with
//!   reconstructed vertex grids; refine (synthesis from parents' lattices and decoded
//!   details) and coarsen (free memory).
//! - [`refine`]: time-budgeted dual-queue refinement (ROAM-style split and merge queues)
//!   that ends every frame with a consistent, crack-free cut.
//!
//! Invariants: time is passed in (`now`, `budget`), so refinement is deterministic under
//! test; every frame ends with a cut that covers the raster exactly once and whose
//! neighbouring patches agree bit for bit on shared edges.
//!
//! This version covers planar repositories; planets, the network thread, the session
//! and headless flights come next (see issue 5).

pub mod dag;
pub mod refine;
pub mod view;
