//! Headless rendering: a device without a window, an offscreen colour and depth target,
//! read back to RGBA pixels (and PNG files) and to depth values, with GPU timing where
//! the adapter has timestamp queries.

use std::path::Path;

use crate::RenderError;
use crate::renderer::DEPTH_FORMAT;

/// The colour format of offscreen frames (PNG bytes as they are).
pub const OFFSCREEN_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// A device and queue of a headless adapter.
pub struct Gpu {
    /// The adapter.
    pub adapter: wgpu::Adapter,
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
}

impl Gpu {
    /// A headless device on the first adapter the environment allows (`WGPU_BACKEND`,
    /// `WGPU_ADAPTER_NAME` as substring, `WGPU_POWER_PREF`), with the adapter's own
    /// limits (large storage bindings) and timestamp queries where it has them.
    pub fn headless() -> Result<Gpu, RenderError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        Gpu::from_instance(&instance, None)
    }

    /// A device on an adapter of `instance` (compatible with `surface` when given).
    pub fn from_instance(
        instance: &wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Gpu, RenderError> {
        let adapter = match std::env::var("WGPU_ADAPTER_NAME") {
            Ok(name) if !name.is_empty() => {
                let want = name.to_lowercase();
                let adapters =
                    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
                adapters
                    .into_iter()
                    .find(|a| a.get_info().name.to_lowercase().contains(&want))
                    .ok_or_else(|| {
                        RenderError::NoAdapter(format!("no adapter named like {name:?}"))
                    })?
            }
            _ => pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
                compatible_surface: surface,
                ..Default::default()
            }))
            .map_err(RenderError::RequestAdapter)?,
        };
        let downlevel = adapter.get_downlevel_capabilities();
        if !downlevel
            .flags
            .contains(wgpu::DownlevelFlags::VERTEX_STORAGE)
        {
            return Err(RenderError::NoAdapter(format!(
                "adapter {:?} cannot read storage buffers in vertex shaders",
                adapter.get_info().name
            )));
        }
        let features = adapter.features()
            & (wgpu::Features::TIMESTAMP_QUERY
                | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS
                | wgpu::Features::VERTEX_WRITABLE_STORAGE
                | wgpu::Features::INDIRECT_FIRST_INSTANCE);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("quincunx"),
            required_features: features,
            required_limits: adapter.limits(),
            ..Default::default()
        }))
        .map_err(RenderError::RequestDevice)?;
        Ok(Gpu {
            adapter,
            device,
            queue,
        })
    }

    /// "name (backend, device type)".
    pub fn describe(&self) -> String {
        let info = self.adapter.get_info();
        format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type)
    }
}

/// A headless device for tests: `Ok(None)` (after printing `SKIP <test>: <reason>`)
/// when there is none, unless `REQUIRE_GPU=1`, which turns that into an error.
/// Prints the adapter it found (`GPU <test>: <adapter>`), so a log shows which backend
/// each test ran on.
pub fn gpu_for_test(test: &str) -> Result<Option<Gpu>, RenderError> {
    gpu_for_test_with(test, wgpu::Features::empty())
}

/// [`gpu_for_test`] for a test that also needs device `features`: on an adapter without
/// them it prints `SKIP <test>: adapter <name> lacks <features>` and gives `Ok(None)`,
/// `REQUIRE_GPU=1` or not (that variable asks for an adapter, not for every feature).
pub fn gpu_for_test_with(test: &str, features: wgpu::Features) -> Result<Option<Gpu>, RenderError> {
    let gpu = match Gpu::headless() {
        Ok(gpu) => gpu,
        Err(e) if std::env::var("REQUIRE_GPU").is_ok_and(|v| v == "1") => return Err(e),
        Err(e) => {
            test_line(&format!("SKIP {test}: no GPU adapter ({e})"));
            return Ok(None);
        }
    };
    let missing = features - gpu.device.features();
    if !missing.is_empty() {
        test_line(&format!(
            "SKIP {test}: adapter {} lacks {missing:?}",
            gpu.describe()
        ));
        return Ok(None);
    }
    test_line(&format!("GPU {test}: {}", gpu.describe()));
    Ok(Some(gpu))
}

/// One line straight to standard error, where `cargo test` shows it: libtest captures the
/// `print!` output of passing tests, so a `println!` SKIP line would never be seen.
fn test_line(line: &str) {
    use std::io::Write as _;
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}

/// An RGBA8 image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Rows top to bottom, 4 bytes per pixel.
    pub rgba: Vec<u8>,
}

impl Image {
    /// The pixel at `(x, y)`.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let k = ((y * self.width + x) * 4) as usize;
        [
            self.rgba[k],
            self.rgba[k + 1],
            self.rgba[k + 2],
            self.rgba[k + 3],
        ]
    }

    /// Writes a PNG (RGB).
    pub fn write_png(&self, path: &Path) -> Result<(), RenderError> {
        let io = |e: std::io::Error| image_error(path, e);
        let png = |e: png::EncodingError| image_error(path, e);
        let file = std::fs::File::create(path).map_err(io)?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().map_err(png)?;
        let rgb: Vec<u8> = self
            .rgba
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect();
        w.write_image_data(&rgb).map_err(png)?;
        w.finish().map_err(png)
    }

    /// Reads a PNG (RGB or RGBA, 8 bits).
    pub fn read_png(path: &Path) -> Result<Image, RenderError> {
        let err = |e: Box<dyn std::error::Error + Send + Sync>| image_error(path, e);
        let file = std::fs::File::open(path).map_err(|e| err(e.into()))?;
        let mut dec = png::Decoder::new(std::io::BufReader::new(file));
        dec.set_transformations(png::Transformations::EXPAND);
        let mut reader = dec.read_info().map_err(|e| err(e.into()))?;
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).map_err(|e| err(e.into()))?;
        let px = (info.width * info.height) as usize;
        let rgba = match info.color_type {
            png::ColorType::Rgba => buf[..px * 4].to_vec(),
            png::ColorType::Rgb => buf[..px * 3]
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect(),
            other => return Err(err(format!("unsupported colour type {other:?}").into())),
        };
        Ok(Image {
            width: info.width,
            height: info.height,
            rgba,
        })
    }
}

/// Reading or writing the image file `path` failed with `source`.
fn image_error(
    path: &Path,
    source: impl Into<Box<dyn std::error::Error + Send + Sync>>,
) -> RenderError {
    RenderError::Io {
        path: path.to_path_buf(),
        source: source.into(),
    }
}

/// The depth attachment of a frame, as stored: reversed Z with an infinite far plane
/// (`NEAR_M / distance along the view axis`, 1 at the near plane), 0 where nothing was
/// drawn (the clear value).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Rows top to bottom (as [`Image`]), one value per pixel.
    pub data: Vec<f32>,
}

impl DepthImage {
    /// The `width x height` depths of a read-back buffer's bytes, rows `padded_row` bytes
    /// apart ([`readback_buffer`]).
    pub fn from_padded(bytes: &[u8], width: u32, height: u32, padded_row: u32) -> DepthImage {
        let (row, padded) = (width as usize * 4, padded_row as usize);
        let mut data = Vec::with_capacity(width as usize * height as usize);
        for y in 0..height as usize {
            data.extend(
                bytes[y * padded..y * padded + row]
                    .chunks_exact(4)
                    .map(|c| f32::from_ne_bytes([c[0], c[1], c[2], c[3]])),
            );
        }
        DepthImage {
            width,
            height,
            data,
        }
    }

    /// The depth at `(x, y)` (`None` outside the image or when `data` is short).
    pub fn at(&self, x: u32, y: u32) -> Option<f32> {
        if x >= self.width || y >= self.height {
            return None;
        }
        self.data
            .get(y as usize * self.width as usize + x as usize)
            .copied()
    }

    /// Checks that `data` holds `width * height` values.
    pub fn validate(&self) -> Result<(), RenderError> {
        let want = u64::from(self.width) * u64::from(self.height);
        if self.data.len() as u64 != want {
            return Err(RenderError::Config(format!(
                "depth image {}x{} holds {} values, not {want}",
                self.width,
                self.height,
                self.data.len()
            )));
        }
        Ok(())
    }
}

/// An offscreen colour + depth target with a readback buffer.
pub struct Offscreen {
    /// Width, height.
    pub size: [u32; 2],
    colour: wgpu::Texture,
    colour_view: wgpu::TextureView,
    depth: wgpu::Texture,
    depth_view: wgpu::TextureView,
    readback: wgpu::Buffer,
    padded_row: u32,
    timer: Option<(wgpu::QuerySet, wgpu::Buffer, wgpu::Buffer)>,
    /// The pass that copies depth into a colour target, made on first use.
    depth_draw: std::sync::OnceLock<DepthDraw>,
}

/// How [`Offscreen::read_depth`] gets the depth attachment into a buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthReadback {
    /// A texture-to-buffer copy of the depth aspect (needs
    /// `DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES`: Vulkan, Metal, DX12).
    Copy,
    /// A full-screen draw that loads each depth texel and writes its bits into an
    /// `R32Uint` colour target, which is then copied like the colour (every backend,
    /// wgpu's GL one included). Bit-identical to [`DepthReadback::Copy`].
    Draw,
}

/// The depth-to-colour pass of [`DepthReadback::Draw`].
struct DepthDraw {
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
    target: wgpu::Texture,
    target_view: wgpu::TextureView,
}

/// Loads each depth texel and writes its bits, unchanged, into an `R32Uint` target.
const DEPTH_TO_COLOUR_WGSL: &str = r"
@group(0) @binding(0) var depth: texture_2d<f32>;

@vertex
fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
    // One triangle over the whole target.
    let x = f32((i << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(i & 2u) * 2.0 - 1.0;
    return vec4<f32>(x, y, 0.0, 1.0);
}

@fragment
fn fs(@builtin(position) p: vec4<f32>) -> @location(0) u32 {
    return bitcast<u32>(textureLoad(depth, vec2<i32>(p.xy), 0).r);
}
";

/// What one offscreen frame took on the GPU.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuTiming {
    /// Render pass time, ms (`None` without timestamp queries).
    pub gpu_ms: Option<f64>,
}

impl Offscreen {
    /// A target of `size` pixels.
    pub fn new(gpu: &Gpu, size: [u32; 2]) -> Result<Offscreen, RenderError> {
        let [w, h] = size;
        let max = gpu.device.limits().max_texture_dimension_2d;
        if w == 0 || h == 0 || w > max || h > max {
            return Err(RenderError::Config(format!(
                "image size {w}x{h}: each side must be 1..={max}"
            )));
        }
        let extent = wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        };
        let texture = |format, usage, label| {
            gpu.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: extent,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        let colour = texture(
            OFFSCREEN_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            "quincunx offscreen colour",
        );
        let depth = texture(
            DEPTH_FORMAT,
            wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::TEXTURE_BINDING,
            "quincunx offscreen depth",
        );
        let (readback, padded_row) = readback_buffer(&gpu.device, [w, h], "quincunx readback");
        let timer = gpu
            .device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| {
                let set = gpu.device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("quincunx timer"),
                    ty: wgpu::QueryType::Timestamp,
                    count: 2,
                });
                let resolve = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("quincunx timer resolve"),
                    size: 16,
                    usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    mapped_at_creation: false,
                });
                let read = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("quincunx timer read"),
                    size: 16,
                    usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
                    mapped_at_creation: false,
                });
                (set, resolve, read)
            });
        Ok(Offscreen {
            size,
            colour_view: colour.create_view(&Default::default()),
            colour,
            depth_view: depth.create_view(&Default::default()),
            depth,
            readback,
            padded_row,
            timer,
            depth_draw: std::sync::OnceLock::new(),
        })
    }

    /// Renders one frame: clears to `background` (sRGB bytes) and depth 0, lets `draw`
    /// record into the pass, and waits for the GPU. Returns the pass's GPU time.
    pub fn render(
        &self,
        gpu: &Gpu,
        background: [u8; 3],
        draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
    ) -> Result<GpuTiming, RenderError> {
        self.render_then(gpu, Some(background), draw, || {})
    }

    /// [`Offscreen::render`] without clearing: draws over the colour and depth the last
    /// pass left (depth-tested against them), so a scene too large for one renderer's
    /// pool can be drawn in parts.
    pub fn render_over(
        &self,
        gpu: &Gpu,
        draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
    ) -> Result<GpuTiming, RenderError> {
        self.render_then(gpu, None, draw, || {})
    }

    /// [`Offscreen::render`], storing in `cpu_ms` the milliseconds from `since` until the
    /// commands are submitted (before waiting for the GPU): the host's share of a frame.
    pub fn render_timed(
        &self,
        gpu: &Gpu,
        background: [u8; 3],
        draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
        cpu_ms: &mut f64,
        since: std::time::Instant,
    ) -> Result<GpuTiming, RenderError> {
        self.render_then(gpu, Some(background), draw, || {
            *cpu_ms = since.elapsed().as_secs_f64() * 1e3;
        })
    }

    /// Records the pass into a finished command buffer without submitting it (for
    /// measuring what encoding costs the host).
    pub fn encode(
        &self,
        gpu: &Gpu,
        background: [u8; 3],
        draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
    ) -> wgpu::CommandBuffer {
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = self.begin(&mut encoder, Some(background), None);
            draw(&mut pass);
        }
        encoder.finish()
    }

    /// A pass over the colour and depth targets: cleared to `background` (and depth 0),
    /// or, with `None`, drawing over what they hold.
    fn begin<'e>(
        &'e self,
        encoder: &'e mut wgpu::CommandEncoder,
        background: Option<[u8; 3]>,
        timestamp_writes: Option<wgpu::RenderPassTimestampWrites<'e>>,
    ) -> wgpu::RenderPass<'e> {
        let (colour_load, depth_load) = match background {
            Some(background) => {
                let c = background.map(|x| f64::from(x) / 255.0);
                (
                    wgpu::LoadOp::Clear(wgpu::Color {
                        r: c[0],
                        g: c[1],
                        b: c[2],
                        a: 1.0,
                    }),
                    wgpu::LoadOp::Clear(0.0),
                )
            }
            None => (wgpu::LoadOp::Load, wgpu::LoadOp::Load),
        };
        encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("quincunx offscreen"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.colour_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: colour_load,
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: depth_load,
                    // Kept for `read_depth`.
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            timestamp_writes,
            occlusion_query_set: None,
            multiview_mask: None,
        })
    }

    fn render_then(
        &self,
        gpu: &Gpu,
        background: Option<[u8; 3]>,
        draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
        submitted: impl FnOnce(),
    ) -> Result<GpuTiming, RenderError> {
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let timestamp_writes =
                self.timer
                    .as_ref()
                    .map(|(set, _, _)| wgpu::RenderPassTimestampWrites {
                        query_set: set,
                        beginning_of_pass_write_index: Some(0),
                        end_of_pass_write_index: Some(1),
                    });
            let mut pass = self.begin(&mut encoder, background, timestamp_writes);
            draw(&mut pass);
        }
        if let Some((set, resolve, read)) = &self.timer {
            encoder.resolve_query_set(set, 0..2, resolve, 0);
            encoder.copy_buffer_to_buffer(resolve, 0, read, 0, 16);
        }
        gpu.queue.submit([encoder.finish()]);
        submitted();
        let gpu_ms = match &self.timer {
            Some((_, _, read)) => {
                let ticks = map_read(gpu, read, |b| {
                    let t0 = u64::from_le_bytes(b[0..8].try_into().unwrap_or_default());
                    let t1 = u64::from_le_bytes(b[8..16].try_into().unwrap_or_default());
                    t1.saturating_sub(t0)
                })?;
                Some(ticks as f64 * f64::from(gpu.queue.get_timestamp_period()) / 1e6)
            }
            None => {
                gpu.device
                    .poll(wgpu::PollType::wait_indefinitely())
                    .map_err(|e| RenderError::Gpu {
                        what: "waiting for the frame",
                        source: e.into(),
                    })?;
                None
            }
        };
        Ok(GpuTiming { gpu_ms })
    }

    /// Reads the colour target back.
    pub fn read(&self, gpu: &Gpu) -> Result<Image, RenderError> {
        let [w, h] = self.size;
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        copy_for_readback(
            &mut encoder,
            &self.colour,
            wgpu::TextureAspect::All,
            &self.readback,
            self.padded_row,
        );
        gpu.queue.submit([encoder.finish()]);
        let row = (w * 4) as usize;
        let padded = self.padded_row as usize;
        let rgba = map_read(gpu, &self.readback, |b| {
            let mut out = Vec::with_capacity(row * h as usize);
            for y in 0..h as usize {
                out.extend_from_slice(&b[y * padded..y * padded + row]);
            }
            out
        })?;
        Ok(Image {
            width: w,
            height: h,
            rgba,
        })
    }

    /// Reads the depth attachment of the last frame back ([`DepthImage`]; 0 where nothing
    /// was drawn), by a copy where the adapter can copy depth textures to buffers, else by
    /// a draw ([`DepthReadback`]). Allocates its own readback buffer (4 bytes a pixel,
    /// rows padded to 256 bytes) for the call.
    pub fn read_depth(&self, gpu: &Gpu) -> Result<DepthImage, RenderError> {
        let how = if depth_copies(gpu.adapter.get_downlevel_capabilities().flags) {
            DepthReadback::Copy
        } else {
            DepthReadback::Draw
        };
        self.read_depth_with(gpu, how)
    }

    /// [`Offscreen::read_depth`] by the given path; [`DepthReadback::Copy`] is an error on
    /// an adapter without depth texture copies.
    pub fn read_depth_with(
        &self,
        gpu: &Gpu,
        how: DepthReadback,
    ) -> Result<DepthImage, RenderError> {
        let source = match how {
            DepthReadback::Copy => {
                if !depth_copies(gpu.adapter.get_downlevel_capabilities().flags) {
                    return Err(RenderError::NoAdapter(format!(
                        "adapter {:?} cannot copy depth textures to buffers \
                         (DEPTH_TEXTURE_AND_BUFFER_COPIES); read depth by a draw instead",
                        gpu.adapter.get_info().name
                    )));
                }
                &self.depth
            }
            DepthReadback::Draw => {
                let draw = self.depth_draw.get_or_init(|| self.make_depth_draw(gpu));
                let mut encoder = gpu
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
                {
                    let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                        label: Some("quincunx depth to colour"),
                        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                            view: &draw.target_view,
                            depth_slice: None,
                            resolve_target: None,
                            ops: wgpu::Operations {
                                load: wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
                                store: wgpu::StoreOp::Store,
                            },
                        })],
                        depth_stencil_attachment: None,
                        timestamp_writes: None,
                        occlusion_query_set: None,
                        multiview_mask: None,
                    });
                    pass.set_pipeline(&draw.pipeline);
                    pass.set_bind_group(0, &draw.bind_group, &[]);
                    pass.draw(0..3, 0..1);
                }
                gpu.queue.submit([encoder.finish()]);
                &draw.target
            }
        };
        let aspect = match how {
            DepthReadback::Copy => wgpu::TextureAspect::DepthOnly,
            DepthReadback::Draw => wgpu::TextureAspect::All,
        };
        let [w, h] = self.size;
        let (buffer, padded) = readback_buffer(&gpu.device, [w, h], "quincunx depth readback");
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        copy_for_readback(&mut encoder, source, aspect, &buffer, padded);
        gpu.queue.submit([encoder.finish()]);
        map_read(gpu, &buffer, |b| DepthImage::from_padded(b, w, h, padded))
    }
}

impl Offscreen {
    fn make_depth_draw(&self, gpu: &Gpu) -> DepthDraw {
        let device = &gpu.device;
        let [w, h] = self.size;
        let target = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("quincunx depth as colour"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::R32Uint,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("quincunx depth to colour"),
            source: wgpu::ShaderSource::Wgsl(DEPTH_TO_COLOUR_WGSL.into()),
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("quincunx depth to colour"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::FRAGMENT,
                // A depth texture bound as unfilterable float: GLSL cannot `texelFetch` a
                // shadow sampler, which `texture_depth_2d` becomes on GL.
                ty: wgpu::BindingType::Texture {
                    sample_type: wgpu::TextureSampleType::Float { filterable: false },
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            }],
        });
        let depth_view = self.depth.create_view(&wgpu::TextureViewDescriptor {
            aspect: wgpu::TextureAspect::DepthOnly,
            ..Default::default()
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("quincunx depth to colour"),
            layout: &layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::TextureView(&depth_view),
            }],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("quincunx depth to colour"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("quincunx depth to colour"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: Default::default(),
            depth_stencil: None,
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::TextureFormat::R32Uint.into())],
            }),
            multiview_mask: None,
            cache: None,
        });
        DepthDraw {
            pipeline,
            bind_group,
            target_view: target.create_view(&Default::default()),
            target,
        }
    }
}

/// Maps a buffer for reading, waits, runs `f` on its bytes and unmaps.
pub fn map_read<T>(
    gpu: &Gpu,
    buffer: &wgpu::Buffer,
    f: impl FnOnce(&[u8]) -> T,
) -> Result<T, RenderError> {
    map_read_on(&gpu.device, buffer, f)
}

/// [`map_read`] on any device (an app's own, Bevy's).
pub fn map_read_on<T>(
    device: &wgpu::Device,
    buffer: &wgpu::Buffer,
    f: impl FnOnce(&[u8]) -> T,
) -> Result<T, RenderError> {
    let slice = buffer.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    let fail = |e: Box<dyn std::error::Error + Send + Sync>| RenderError::Gpu {
        what: "reading a buffer back",
        source: e,
    };
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| fail(e.into()))?;
    rx.recv()
        .map_err(|e| fail(e.into()))?
        .map_err(|e| fail(e.into()))?;
    let out = {
        let view = slice.get_mapped_range().map_err(|e| fail(e.into()))?;
        f(&view)
    };
    buffer.unmap();
    Ok(out)
}
/// A buffer to read a `size` texture of 4-byte texels back into, and its row length in
/// bytes (padded to wgpu's copy alignment).
pub fn readback_buffer(device: &wgpu::Device, size: [u32; 2], label: &str) -> (wgpu::Buffer, u32) {
    let padded_row = (size[0] * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
        * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: u64::from(padded_row) * u64::from(size[1]),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    (buffer, padded_row)
}

/// Records the copy of `aspect` of the whole of `texture` (4-byte texels) into `buffer`,
/// rows `padded_row` bytes apart ([`readback_buffer`]).
pub fn copy_for_readback(
    encoder: &mut wgpu::CommandEncoder,
    texture: &wgpu::Texture,
    aspect: wgpu::TextureAspect,
    buffer: &wgpu::Buffer,
    padded_row: u32,
) {
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect,
        },
        wgpu::TexelCopyBufferInfo {
            buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded_row),
                rows_per_image: Some(texture.height()),
            },
        },
        wgpu::Extent3d {
            width: texture.width(),
            height: texture.height(),
            depth_or_array_layers: 1,
        },
    );
}

/// Whether an adapter with downlevel `flags` can copy a depth texture to a buffer
/// ([`DepthReadback::Copy`]; wgpu's GL backend cannot, and wgpu would panic).
fn depth_copies(flags: wgpu::DownlevelFlags) -> bool {
    flags.contains(wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn image_errors_name_the_file_and_keep_their_cause() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.png");
        let e = Image::read_png(&missing).unwrap_err();
        assert_eq!(e.to_string(), format!("image {}", missing.display()));
        let cause = std::error::Error::source(&e).unwrap();
        let io = cause.downcast_ref::<std::io::Error>().unwrap();
        assert_eq!(io.kind(), std::io::ErrorKind::NotFound);
        // Not a PNG: the decoder's error is the cause.
        let text = dir.path().join("text.png");
        std::fs::write(&text, b"not a png").unwrap();
        let e = Image::read_png(&text).unwrap_err();
        let cause = std::error::Error::source(&e).unwrap();
        assert!(
            cause.downcast_ref::<png::DecodingError>().is_some(),
            "{cause:?}"
        );
        // Writing into a folder that does not exist.
        let image = Image {
            width: 1,
            height: 1,
            rgba: vec![0; 4],
        };
        let e = image
            .write_png(&dir.path().join("no/such/dir.png"))
            .unwrap_err();
        assert!(matches!(e, RenderError::Io { .. }), "{e:?}");
    }

    #[test]
    fn only_adapters_with_depth_copies_read_depth_by_a_copy() {
        let all = wgpu::DownlevelFlags::all();
        assert!(depth_copies(all));
        assert!(!depth_copies(
            all - wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES
        ));
    }
}
