//! The quincunx client's core, without I/O: no threads, sockets, clocks or async runtime
//! inside, so it builds for `wasm32-unknown-unknown` and runs wherever the caller can pass
//! in time and answers. `quincunx-client` wraps it with a network thread and transports.
//!
//! - [`view`]: the camera (`f64` throughout), frustum, projected sizes, world mapping.
//! - [`dag`]: the in-core diamond DAG from the roots down to the current cut, with
//!   reconstructed vertex grids; refine (synthesis from parents' lattices and decoded
//!   details) and coarsen (free memory).
//! - [`refine`]: time-budgeted dual-queue refinement (ROAM-style split and merge queues)
//!   that ends every frame with a consistent, crack-free cut.
//! - [`fetch`]: blob keys, fetch errors, the decoded-value cache and the request schedule
//!   (priorities, in flight, backoff).
//! - [`open`]: opening a repository: [`open::SessionError`] and the refiners and world
//!   mappings its metadata gives; it depends on no module above it.
//! - [`domain`]: what differs between planar repositories and planets (world boxes,
//!   exact vertex positions, coverage probes); everything above is generic over it.
//! - [`fine`]: exact vertex positions in fine units, each patch as an affine map, and
//!   the geometry a renderer draws ([`fine::WorldFrame`]).
//! - [`colour`]: an optional colour repository matched at run time to the elevation one
//!   (different depths and diamond sizes; procedural detail below the shallower layer).
//!
//! Invariants: time is passed in (`now`, `budget`, a [`refine::Clock`]), so refinement is
//! deterministic under test; every frame ends with a cut that covers the raster (or the
//! whole planet) exactly once and whose neighbouring patches agree bit for bit on shared
//! edges.

/// The glam of the public API (`DVec3` camera positions, `Mat4` projections): an app
/// uses these types, whatever glam version it names itself.
pub use glam;

pub mod colour;
pub mod dag;
pub mod domain;
pub mod fetch;
pub mod fine;
pub mod open;
pub mod refine;
pub mod stream;
pub mod view;
