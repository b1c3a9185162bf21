//! Embedding the renderer in an app that owns its device, its frame and its other draws.
//!
//! The app below is headless (it renders into its own texture and saves a PNG), but the
//! renderer does not care where the pass goes: in a windowed app the colour attachment
//! is the surface texture (see `repo-tools/src/view.rs`). Run the demo server first:
//!
//! ```sh
//! cargo run --release --bin quincunx -- demo        # serves korea, earth on :8080
//! cargo run --release -p quincunx-render --example embed -- http://127.0.0.1:8080 korea embed.png
//! ```
//!
//! A fourth argument `N` then draws `N` more frames of the same view, each waited for,
//! and prints their median time as one JSON line (the Bevy plugin's bench compares with
//! it: `bevy/examples/bench.rs`).
//!
//! What the renderer wants from the app's device: `Features::INDIRECT_FIRST_INSTANCE` for
//! one indirect draw per frame (without it, one `draw_indexed` per patch), and buffer
//! limits large enough for its pool (it sizes the pool to `min(budget, device limits)`).
//! It draws into any colour format with a `Depth32Float` depth attachment cleared to 0
//! (reversed Z).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::session::{Session, SessionConfig};
use quincunx_client::view::View;
use quincunx_render::{Camera, DEPTH_FORMAT, RendererConfig, TerrainRenderer};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "http://127.0.0.1:8080".into());
    let repo = args.next().unwrap_or_else(|| "korea".into());
    let out = args.next().unwrap_or_else(|| "embed.png".into());
    let timed: Option<usize> = args.next().and_then(|a| a.parse().ok());
    let (width, height) = (960u32, 540u32);

    // --- The app's own GPU setup (nothing quincunx-specific). ---
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(instance.request_adapter(&Default::default()))?;
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("my app"),
        // One indirect draw for the whole cut needs first-instance indirect draws.
        required_features: adapter.features() & wgpu::Features::INDIRECT_FIRST_INSTANCE,
        // The adapter's own limits let the renderer's pool use large buffers.
        required_limits: adapter.limits(),
        ..Default::default()
    }))?;
    let format = wgpu::TextureFormat::Rgba8UnormSrgb;
    let target = |format, usage| {
        device.create_texture(&wgpu::TextureDescriptor {
            label: None,
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        })
    };
    let colour = target(
        format,
        wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
    );
    let depth = target(DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT);
    let (colour_view, depth_view) = (
        colour.create_view(&Default::default()),
        depth.create_view(&Default::default()),
    );

    // --- quincunx: a streaming session and a renderer on the app's device. ---
    let mut session: Session = Session::open(&url, &repo, SessionConfig::default())?;
    let config = RendererConfig {
        colour_format: format,
        ..RendererConfig::default()
    };
    let mut terrain = TerrainRenderer::for_session(&device, &session, config)?;
    let b = session.bounds();
    let centre = (b.min + b.max) / 2.0;
    let view = View {
        eye: DVec3::new(b.min.x, b.max.y, b.max.z + 8_000.0),
        target: DVec3::new(centre.x, centre.y, b.min.z),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [width, height],
        tolerance_px: 1.0,
    };

    // --- The app's frame loop. ---
    let start = Instant::now();
    let mut frame_times = Vec::new();
    for frame in 0.. {
        let began = Instant::now();
        let stats = session.update(&view, start.elapsed(), Duration::from_millis(4))?;
        terrain.sync(&mut session)?; // O(changes): patches in and out of the cut
        let drawn = terrain.prepare(&queue, &Camera::from_view(&view));
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("my app's main pass"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &colour_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: 0.25,
                            g: 0.4,
                            b: 0.65,
                            a: 1.0,
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &depth_view,
                    // Reversed Z: clear to 0, nearer is greater.
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            terrain.draw(&mut pass);
            // ... the app's own draws go here, in the same pass and depth buffer ...
        }
        queue.submit([encoder.finish()]);
        let done = stats.refine.full_quality && stats.wanted == 0 && drawn.current;
        if let Some(n) = timed.filter(|_| done) {
            // The timed frames: each waited for, as a frame that is shown must be.
            device.poll(wgpu::PollType::wait_indefinitely())?;
            frame_times.push(began.elapsed().as_secs_f64() * 1e3);
            if frame_times.len() <= n + 60 {
                continue;
            }
            let mut t = frame_times.split_off(60);
            t.sort_by(f64::total_cmp);
            println!(
                "{{\"app\":\"embed\",\"frames\":{},\"frame_ms_median\":{:.3},\"frame_ms_p90\":{:.3},\"triangles\":{}}}",
                t.len(),
                t[t.len() / 2],
                t[(t.len() - 1) * 9 / 10],
                drawn.triangles
            );
        }
        if done || start.elapsed() > Duration::from_secs(30) {
            println!(
                "frame {frame}: {} patches, {} triangles, {} draw call(s), full quality: {done}",
                drawn.patches, drawn.triangles, drawn.draw_calls
            );
            break;
        }
        if timed.is_none() {
            std::thread::sleep(Duration::from_millis(16));
        }
    }
    save_png(&device, &queue, &colour, [width, height], &out)?;
    println!("wrote {out}");
    Ok(())
}

/// Copies the app's texture to a buffer and writes it as a PNG.
fn save_png(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    [w, h]: [u32; 2],
    path: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    let row = (w * 4).div_ceil(256) * 256;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: None,
        size: u64::from(row * h),
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(h),
            },
        },
        texture.size(),
    );
    queue.submit([encoder.finish()]);
    buffer.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    device.poll(wgpu::PollType::wait_indefinitely())?;
    let data = buffer.slice(..).get_mapped_range()?;
    let image = quincunx_render::Image {
        width: w,
        height: h,
        rgba: (0..h as usize)
            .flat_map(|y| data[y * row as usize..y * row as usize + w as usize * 4].to_vec())
            .collect(),
    };
    image.write_png(std::path::Path::new(path))?;
    Ok(())
}
