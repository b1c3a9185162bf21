//! The quincunx encoder, on the format of `quincunx-decoder`.
//!
//! - [`raster`] / [`sphere_raster`] / [`encode`]: the whole-raster transform (planar
//!   rasters and cube-mapped planets), quantisation, rate control, model training, blobs,
//!   and the whole-raster decode that checks them.
//! - [`rdo`]: the rate-distortion quantiser.
//! - [`stream`]: the out-of-core encoder of planar rasters and planets (bounded memory,
//!   rows read on demand, blobs handed out as they are coded) and its shards.
//! - [`fill`]: filling nodata holes before coding.
//!
//! The read side ([`blob`], [`entropy`], [`lifting`], [`incremental`], [`coverage`],
//! [`colour`], [`diamond`]) is re-exported from `quincunx-decoder`, which clients depend on
//! alone. The crate is pure: no I/O, no async. Untrusted bytes are decoded into `Result`s,
//! never panics.

pub mod encode;
pub mod fill;
pub mod raster;
pub mod rdo;
pub mod sphere_raster;
pub mod stream;

/// The format's read side, from `quincunx-decoder` (one definition, shared with clients).
pub use quincunx_decoder::{blob, colour, coverage, entropy, incremental, lifting};
/// Diamond ids and hierarchy laws (the `quincunx-diamond` crate).
pub use quincunx_diamond as diamond;
