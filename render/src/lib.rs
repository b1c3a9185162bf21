//! The quincunx renderer: draws the crack-free cut a [`quincunx_client`] session streams,
//! retained-mode and batched, with wgpu, into an app's own device, queue and render pass
//! (or offscreen, [`offscreen`]).
//!
//! - A patch (one half of a diamond in the cut) is uploaded once, when it enters the cut:
//!   its `(N+1)^2` integer heights, its colour (YCoCg-R, decoded in the shader) and an
//!   80-byte record of its exact affine map in integer *fine units*. Vertex positions are
//!   rebuilt on the GPU from those integers; nothing moves per frame but one uniform
//!   block and the draws that changed.
//! - Slots are equal-sized and pooled under a byte budget ([`pool`]); patches that left
//!   the cut stay cached (LRU) and come back without an upload.
//! - One shared index buffer, one `multi_draw_indexed_indirect` for the whole cut.
//! - Precision: the camera is split into integer limbs and a small remainder in f64 on
//!   the host; the shader subtracts exact integers, so only camera-relative numbers
//!   reach f32, and shared vertices come out bit-identical in neighbouring patches.
//!   Reversed Z, infinite far plane, `Depth32Float`; on backends without clip control
//!   (wgpu's GL) the fragment stage writes that depth itself
//!   ([`RendererConfig::fragment_depth`]), so it holds at planet distances there too.
//! - Image error ([`error`]): PSNR, and a geometric error in screen pixels from a frame's
//!   depth ([`Offscreen::read_depth`]) against a reference cut's surface as drawn
//!   ([`SurfaceIndex`]), for speed/accuracy trade studies.
//!
//! The frame loop of an app (see `examples/embed.rs`):
//!
//! ```text
//! session.update(&view, now, budget)?;          // the client refines its cut
//! renderer.sync(&mut session)?;                 // O(changes): what entered and left
//! renderer.prepare(&queue, &Camera::from_view(&view));
//! // in the app's render pass (depth cleared to 0, Depth32Float):
//! renderer.draw(&mut pass);
//! ```

/// The glam of the public API (`DVec3` camera positions and the like), re-exported from
/// [`quincunx_client`].
pub use quincunx_client::glam;
/// The wgpu this crate draws with: an app uses these types for its device, queue and pass.
pub use wgpu;

pub mod camera;
/// What the renderer needs of a domain (exact fine-unit positions, affine patches, the
/// world frame): the client core's [`quincunx_client::fine`], under its old path.
pub mod domain {
    pub use quincunx_client::fine::*;
}
pub mod error;
pub mod ground;
pub mod offscreen;
pub mod pool;
pub mod renderer;
pub mod scene;

pub use camera::{Camera, Lighting, Modes};
pub use domain::{Geometry, RenderDomain, WorldFrame};
pub use error::{ErrorMap, GeometricError, geometric_error, psnr_db, unproject};
pub use ground::SurfaceIndex;
pub use offscreen::{DepthImage, Gpu, Image, Offscreen};
pub use renderer::{DEPTH_FORMAT, RenderFrameStats, RendererConfig, TerrainRenderer};

/// Why rendering could not start or continue.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RenderError {
    /// No usable GPU adapter: none named as asked, or one without a capability the
    /// renderer needs.
    #[error("no usable GPU adapter: {0}")]
    NoAdapter(String),
    /// wgpu found no adapter.
    #[error("no usable GPU adapter")]
    RequestAdapter(#[source] wgpu::RequestAdapterError),
    /// The adapter gave no device.
    #[error("no usable GPU device")]
    RequestDevice(#[source] wgpu::RequestDeviceError),
    /// A setting the renderer cannot honour.
    #[error("renderer configuration: {0}")]
    Config(String),
    /// A patch whose geometry the renderer cannot express (a bug).
    #[error("patch geometry: {0}")]
    Geometry(String),
    /// The GPU reported an error while doing `what`.
    #[error("GPU: {what}")]
    Gpu {
        /// What the renderer was doing.
        what: &'static str,
        /// wgpu's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// Reading or writing the image file `path`.
    #[error("image {}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O or PNG error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}
