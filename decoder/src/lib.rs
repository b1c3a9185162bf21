//! The quincunx format, read side: what a client needs to turn blobs into surfaces.
//!
//! - [`blob`]: the blob format (header, checksum, side information, detail matrix).
//! - [`entropy`]: the context-modelled range coder the blobs are written with.
//! - [`lifting`]: integer wavelet lifting of one diamond (synthesis, and the analysis
//!   the encoder runs).
//! - [`raster`] / [`sphere_raster`]: where a planar raster or a cube-mapped planet sits in
//!   the hierarchy, one diamond at a time, and the tables of every diamond.
//! - [`layout`]: the whole-raster decoder, every level synthesised in place (what
//!   `quincunx verify` and the browser's whole-repository decode run).
//! - [`incremental`]: decoding one diamond at a time, as a streaming client refines its cut.
//! - [`coverage`]: which blocks of a sparse repository hold data.
//! - [`colour`]: the reversible YCoCg-R colour transform.
//!
//! No encoder, no threads, no I/O: the crate builds for `wasm32-unknown-unknown`. The
//! encoder (`quincunx-codec`) is built on it. Untrusted bytes are decoded into `Result`s,
//! never panics.

pub mod blob;
pub mod colour;
pub mod coverage;
pub mod entropy;
pub mod incremental;
pub mod lattice;
pub mod layout;
pub mod lifting;
pub mod raster;
pub mod sphere_raster;

/// Diamond ids and hierarchy laws (the `quincunx-diamond` crate).
pub use quincunx_diamond as diamond;

/// Inverse of the encoder's quantiser: a detail index `q` at step `s` (1/256 integer
/// units) reconstructed at its bin's centre.
#[inline]
pub fn dequantize(q: i32, s: u32) -> i32 {
    if s == 256 {
        return q;
    }
    let a = (q.unsigned_abs() as u64 * s as u64 + 128) >> 8;
    let a = a.min(i32::MAX as u64) as i32;
    if q < 0 { -a } else { a }
}
