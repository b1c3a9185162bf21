//! The quincunx codec: the shared vocabulary of the system.
//!
//! - [`diamond`]: diamond ids (planar and cube-mapped sphere), hierarchy laws, frames,
//!   sample positions and storage keys.
//! - [`lifting`]: integer-to-integer wavelet lifting of one diamond (analysis/synthesis).
//! - [`raster`] / [`sphere_raster`] / [`encode`]: the whole-raster transform (planar
//!   rasters and cube-mapped planets), rate control and blobs.
//! - [`incremental`]: one diamond at a time, as a streaming client refines its cut.
//! - [`stream`]: the out-of-core encoder of planar rasters (bounded memory, rows read on
//!   demand, blobs handed out as they are coded).
//! - [`coverage`]: which coarse blocks hold data, for sparse encoding (nodata areas are
//!   left out of the hierarchy instead of being filled and coded).
//! - [`colour`]: the reversible YCoCg-R colour transform.
//!
//! The crate is pure: no I/O, no async. Untrusted bytes are decoded into `Result`s, never
//! panics.

pub mod blob;
pub mod colour;
pub mod coverage;
pub mod encode;
pub mod entropy;
pub mod fill;
pub mod incremental;
pub mod lifting;
pub mod raster;
pub mod sphere_raster;
pub mod stream;

/// Diamond ids and hierarchy laws (the `quincunx-diamond` crate).
pub use quincunx_diamond as diamond;
