//! The quincunx streaming client: what people embed in their apps and what load tests
//! simulate. No GPU needed: rendering lives in `quincunx-render`, which reads a session's
//! cut changes ([`session::Session::cut_changes`]) or its whole cut ([`session::Snapshot`]).
//!
//! The modules without I/O ([`view`], [`dag`], [`refine`], [`open`], [`domain`],
//! [`colour`], [`fine`], and the request schedule and caches of [`fetch`]) are
//! `quincunx-client-core`'s, re-exported here; this crate adds the network thread, the
//! transports, the system clock ([`refine::SystemClock`]), [`session`] and [`flight`].
//!
//! - [`view`]: the camera (`f64` throughout), frustum, projected sizes, world mapping.
//! - [`dag`]: the in-core diamond DAG from the roots down to the current cut, with
//!   reconstructed vertex grids; refine (synthesis from parents' lattices and decoded
//!   details) and coarsen (free memory).
//! - [`refine`]: time-budgeted dual-queue refinement (ROAM-style split and merge queues)
//!   that ends every frame with a consistent, crack-free cut.
//! - [`fetch`]: the data access layer: a network thread ([`fetch::Fetcher`]) that takes the
//!   frame loop's wanted diamond keys with priorities, requests their blobs from a server
//!   or from a repository file with range requests ([`fetch::Remote`]) over a selectable
//!   transport ([`fetch::Transport`]: pipelined HTTP/1.1, plain HTTP/1.1 or HTTP/2; http
//!   or https), decodes them off the main thread and hands back results through
//!   channels, with a decoded-value cache and a set of known leaves. `fetch` never sees
//!   the DAG: keys, priorities and results only. [`fetch::link`] emulates a narrow,
//!   high-latency link for measurements.
//!
//! Invariants: time is passed in (`now`, `budget`), so refinement is deterministic under
//! test; every frame ends with a cut that covers the raster (or the whole planet) exactly
//! once and whose neighbouring patches agree bit for bit on shared edges.
//!
//! - [`session`]: a served repository streamed frame by frame: `fetch` feeding `refine`,
//!   with prefetch along the predicted camera; [`session::Session`] for planar
//!   repositories, [`session::PlanetSession`] for planets, each optionally with a colour
//!   layer.
//! - [`flight`]: camera paths (built-in and from files) and a headless real-time runner
//!   that measures a session along one (what `quincunx fly` and the fly load test run).
//!
//! - [`open`]: opening a repository: [`open::SessionError`] and the refiners and world
//!   mappings its metadata gives; it depends on no module above it.
//! - [`domain`]: what differs between planar repositories and planets (world boxes,
//!   exact vertex positions, coverage probes); everything above is generic over it.
//! - [`colour`]: an optional colour repository matched at run time to the elevation one
//!   (different depths and diamond sizes; procedural detail below the shallower layer).
//! - [`fine`]: what a renderer needs of a domain: exact vertex positions in a common
//!   integer unit, as a per-patch affine map, shared by every renderer.

/// The glam of the public API (`DVec3` camera positions, `Mat4` projections): an app
/// uses these types, whatever glam version it names itself.
pub use glam;

pub mod fetch;
pub mod flight;
pub mod refine;
pub mod session;

#[doc(inline)]
pub use quincunx_client_core::{colour, dag, domain, fine, open, view};
