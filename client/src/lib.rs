//! The quincunx streaming client.
//!
//! So far this crate holds the data access layer, [`fetch`]: a network thread that takes
//! the frame loop's wanted diamond keys with priorities, requests their blobs over a
//! selectable transport (pipelined HTTP/1.1, plain HTTP/1.1 or HTTP/2), decodes them off
//! the main thread and hands back results through channels, with a decoded-value cache
//! and a set of known leaves.
//!
//! The diamond DAG, refinement (dual queues), synthesis and the `Session` API come next, in
//! their own modules; they will use `fetch` only through keys, priorities and results:
//! `fetch` never sees the DAG.

pub mod fetch;
