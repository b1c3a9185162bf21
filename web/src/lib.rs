//! The quincunx decoder and client core for browsers, compiled to one WebAssembly module
//! (`web-demo/js/quincunx.wasm`, built by `web-demo/build-wasm.sh`): the code the native
//! client runs, with JavaScript keeping only the page, WebGL2 and `fetch`.
//!
//! - [`client`]: the client core's [`quincunx_client_core::stream::StreamCore`] with a
//!   request [`quincunx_client_core::fetch::planner::Planner`] and decoded cache per
//!   layer: what the native `Session` holds, without its threads.
//! - [`decode`]: a decoding worker's side (one answer's bytes to details).
//! - [`reconstruct`]: a whole repository at full resolution, by the whole-raster decoder
//!   `quincunx verify` runs or by the refiners (the reconstruction hash `verify` prints).
//! - [`pack`]: a repository file read with range requests (the client core's range
//!   reader; the page runs `fetch`, this code checks every answer).
//! - [`wire`]: the byte layouts between workers, client and page; [`api`]: the calls on
//!   byte buffers; the exports themselves (`abi.rs`) exist on `wasm32` only.
//!
//! No threads, sockets or clocks: time comes from the page (`performance.now()`).

pub mod api;
pub mod client;
pub mod decode;
pub mod open;
pub mod pack;
pub mod reconstruct;
pub mod wire;

#[cfg(target_arch = "wasm32")]
mod abi;
