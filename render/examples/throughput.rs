//! Batched renderer against a raw single-buffer draw of the same triangles (issue 20,
//! item 9).
//!
//! `cargo run --release -p quincunx-render --example throughput -- [--json] [--rounds K]`
//!
//! The cut: the bundled SRTM3 crop (`data/korea_srtm3_1025.i16`, 90 m), coded at 2 m RMS
//! with N = 64, refined at 0.5 px for a low oblique view (1920x1080, 60 degrees).
//!
//! - *batched*: [`TerrainRenderer`] as apps use it: heights in a pooled vertex buffer,
//!   positions rebuilt in the vertex shader from exact integer limbs, one shared index
//!   buffer, one `multi_draw_indexed_indirect` (or a loop of `draw_indexed` on GL).
//! - *raw*: one vertex buffer of f32 camera-relative positions plus the height in metres
//!   (computed on the host in f64: `world - eye`), one index buffer holding every
//!   patch's half triangles (the same triangles, the same vertex order), one
//!   `draw_indexed`. Its vertex shader multiplies by the same clip-from-relative matrix;
//!   its fragment shader does what the batched one does for an elevation-only planar
//!   repository: face normal from `dpdx`/`dpdy` of the relative position, the same
//!   directional light and ambient share, the same height tint, the raster clip test.
//!
//! The batched renderer also draws with a loop of `draw_indexed`, and with the other
//! depth path (`RendererConfig::fragment_depth` flipped: the reversed-Z depth written per
//! fragment where the backend has clip control, rasterised on GL).
//!
//! Both draw into the same 1920x1080 offscreen target (Rgba8Unorm + Depth32Float,
//! reversed Z, compare Greater), alternating, `rounds` frames each; GPU time from
//! timestamp queries around the render pass where the adapter has them, else wall time
//! of submit + wait. Prints medians.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytemuck::{Pod, Zeroable};
use glam::DVec3;
use quincunx_client::dag::Dag;
use quincunx_client::refine::{Availability, DetailSource, Refinement, SystemClock};
use quincunx_client::view::{PlanarWorld, View};
use quincunx_codec::diamond::PlanarId;
use quincunx_codec::encode::{EncodeOptions, Encoded, FromEncoded, Grid, RateMode, encode};
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_render::camera::default_light;
use quincunx_render::offscreen::OFFSCREEN_FORMAT;
use quincunx_render::renderer::grid_indices;
use quincunx_render::{
    Camera, DEPTH_FORMAT, Gpu, Offscreen, RenderDomain, RendererConfig, TerrainRenderer,
};
use wgpu::util::DeviceExt;

type Error = Box<dyn std::error::Error>;

const N: usize = 64;
const SIZE: [u32; 2] = [1920, 1080];
const BACKGROUND: [u8; 3] = [135, 170, 210];

struct Local {
    blobs: HashMap<Vec<u8>, Vec<u8>>,
    refiner: Arc<PlanarRefiner>,
}

impl DetailSource for Local {
    fn details(&mut self, id: PlanarId, _priority: f64) -> Availability {
        let Some(info) = self.refiner.info(id) else {
            return Availability::Ready(None);
        };
        if info.procedural {
            return Availability::Ready(None);
        }
        let blob = self.blobs.get(&info.key).map(Vec::as_slice);
        Availability::Ready(blob.and_then(|b| self.refiner.decode(id, b).ok().map(Arc::new)))
    }
}

fn korea() -> Result<Encoded, Error> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/korea_srtm3_1025.i16");
    let raw = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let side = 1025;
    if raw.len() != side * side * 2 {
        return Err(format!(
            "{}: {} bytes, want {}",
            path.display(),
            raw.len(),
            side * side * 2
        )
        .into());
    }
    let values_m = raw
        .chunks_exact(2)
        .map(|b| f64::from(i16::from_le_bytes([b[0], b[1]])))
        .collect();
    let grid = Grid {
        width: side,
        height: side,
        values_m,
        quantum_m: Some(1.0),
    };
    let opts = EncodeOptions {
        n: N,
        mode: RateMode::RmsM(2.0),
        sparse: false,
        rdo: Default::default(),
    };
    Ok(encode(&grid, opts)?)
}

/// Frame uniforms of the raw pipeline.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct RawUniforms {
    clip_from_rel: [[f32; 4]; 4],
    light: [f32; 4],
    /// tint low, tint high, raster extent x, y (metres, relative to the eye).
    tint: [f32; 4],
    /// Raster origin relative to the eye (x, y), unused.
    origin: [f32; 4],
}

const RAW_WGSL: &str = r#"
struct Frame {
    clip_from_rel: mat4x4<f32>,
    light: vec4<f32>,
    tint: vec4<f32>,
    origin: vec4<f32>,
}
@group(0) @binding(0) var<uniform> frame: Frame;

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) rel: vec3<f32>,
    @location(1) height_m: f32,
}

@vertex
fn vs_main(@location(0) rel_h: vec4<f32>) -> VertexOut {
    var out: VertexOut;
    out.clip = frame.clip_from_rel * vec4<f32>(rel_h.xyz, 1.0);
    out.rel = rel_h.xyz;
    out.height_m = rel_h.w;
    return out;
}

fn tint(h: f32) -> vec3<f32> {
    let t_sea = clamp(-h / 6000.0, 0.0, 1.0);
    let sea = mix(vec3<f32>(0.36, 0.56, 0.74), vec3<f32>(0.07, 0.16, 0.36), sqrt(t_sea));
    let shore = smoothstep(0.0, 2.0, h);
    if shore <= 0.0 {
        return sea;
    }
    return mix(sea, land(h), shore);
}

fn land(h: f32) -> vec3<f32> {
    let t = clamp((h - frame.tint.x) / max(frame.tint.y - frame.tint.x, 1.0), 0.0, 1.0);
    let c0 = vec3<f32>(0.30, 0.52, 0.28);
    let c1 = vec3<f32>(0.72, 0.68, 0.42);
    let c2 = vec3<f32>(0.52, 0.38, 0.26);
    let c3 = vec3<f32>(0.94, 0.94, 0.94);
    if t < 0.35 {
        return mix(c0, c1, t / 0.35);
    } else if t < 0.75 {
        return mix(c1, c2, (t - 0.35) / 0.4);
    }
    return mix(c2, c3, (t - 0.75) / 0.25);
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    let dx = dpdx(in.rel);
    let dy = dpdy(in.rel);
    // The raster clip test of the batched shader (relative to the eye here).
    let p = in.rel.xy - frame.origin.xy;
    if p.x < 0.0 || p.y < 0.0 || p.x > frame.tint.z || p.y > frame.tint.w {
        discard;
    }
    var nrm = normalize(cross(dx, dy));
    if dot(nrm, in.rel) > 0.0 {
        nrm = -nrm;
    }
    let ambient = frame.light.w;
    let lit = ambient + (1.0 - ambient) * max(dot(nrm, frame.light.xyz), 0.0);
    return vec4<f32>(tint(in.height_m) * lit, 1.0);
}
"#;

struct Raw {
    pipeline: wgpu::RenderPipeline,
    bind_group: wgpu::BindGroup,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    index_count: u32,
}

impl Raw {
    fn new(
        gpu: &Gpu,
        dag: &Dag,
        world: &PlanarWorld,
        frame: &quincunx_render::WorldFrame,
        camera: &Camera,
    ) -> Result<Raw, Error> {
        let device = &gpu.device;
        let n = dag.refiner().n();
        let nv = n + 1;
        let (grid_idx, half) = grid_indices(n as u32);
        let mut vertices: Vec<[f32; 4]> = Vec::new();
        let mut indices: Vec<u32> = Vec::new();
        for (id, h) in dag.cut() {
            let node = dag.node(id).ok_or("cut node missing")?;
            let a = dag
                .refiner()
                .affine(id, &node.corners, h)
                .ok_or("patch not affine")?;
            let base = vertices.len() as u32;
            for i in 0..nv {
                for j in 0..nv {
                    let v = node.grid[i * nv + j];
                    let p = frame.point(a.at(i, j), v) - camera.eye;
                    let h_m = world.value_offset_m + f64::from(v) * world.value_scale_m;
                    vertices.push([p.x as f32, p.y as f32, p.z as f32, h_m as f32]);
                }
            }
            let first = match h {
                quincunx_client::dag::Half::Lower => 0,
                quincunx_client::dag::Half::Upper => half as usize,
            };
            indices.extend(
                grid_idx[first..first + half as usize]
                    .iter()
                    .map(|k| k + base),
            );
        }
        let vbuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("raw vertices"),
            contents: bytemuck::cast_slice(&vertices),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let ibuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("raw indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::INDEX,
        });
        let light = default_light(frame, camera.eye);
        let extent = match frame.geometry {
            quincunx_render::Geometry::Planar {
                metres_per_fine,
                extent_fine,
            } => extent_fine.map(|x| x as f64 * metres_per_fine),
            quincunx_render::Geometry::Planet { .. } => return Err("planar only".into()),
        };
        let lighting = quincunx_render::Lighting::default();
        let uniforms = RawUniforms {
            clip_from_rel: camera.clip_from_rel().as_mat4().to_cols_array_2d(),
            light: [
                light.x as f32,
                light.y as f32,
                light.z as f32,
                lighting.ambient as f32,
            ],
            tint: [
                lighting.tint_m.unwrap_or((0.0, 3000.0)).0 as f32,
                lighting.tint_m.unwrap_or((0.0, 3000.0)).1 as f32,
                extent[0] as f32,
                extent[1] as f32,
            ],
            origin: [-camera.eye.x as f32, -camera.eye.y as f32, 0.0, 0.0],
        };
        let ubuf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("raw frame"),
            contents: bytemuck::bytes_of(&uniforms),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("raw"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("raw"),
            layout: &layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: ubuf.as_entire_binding(),
            }],
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("raw"),
            source: wgpu::ShaderSource::Wgsl(RAW_WGSL.into()),
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("raw"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("raw"),
            layout: Some(&pipeline_layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs_main"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: 16,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &wgpu::vertex_attr_array![0 => Float32x4],
                })],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs_main"),
                compilation_options: Default::default(),
                targets: &[Some(OFFSCREEN_FORMAT.into())],
            }),
            multiview_mask: None,
            cache: None,
        });
        Ok(Raw {
            pipeline,
            bind_group,
            vertices: vbuf,
            indices: ibuf,
            index_count: indices.len() as u32,
        })
    }

    fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, self.vertices.slice(..));
        pass.set_index_buffer(self.indices.slice(..), wgpu::IndexFormat::Uint32);
        pass.draw_indexed(0..self.index_count, 0, 0..1);
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// One frame's time (ms): the pass's GPU time, or submit-to-idle wall time.
fn timed(
    gpu: &Gpu,
    offscreen: &Offscreen,
    draw: impl FnOnce(&mut wgpu::RenderPass<'_>),
) -> Result<(f64, bool), Error> {
    let start = Instant::now();
    let t = offscreen.render(gpu, BACKGROUND, draw)?;
    let wall = start.elapsed().as_secs_f64() * 1e3;
    Ok(match t.gpu_ms {
        Some(ms) => (ms, true),
        None => (wall, false),
    })
}

fn main() -> Result<(), Error> {
    let mut json = false;
    let mut rounds = 11usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--json" => json = true,
            "--rounds" => {
                rounds = args
                    .next()
                    .and_then(|r| r.parse().ok())
                    .filter(|&r| r > 0)
                    .ok_or("--rounds needs a positive integer")?
            }
            other => {
                return Err(format!(
                    "unknown argument {other:?} (usage: throughput [--json] [--rounds K])"
                )
                .into());
            }
        }
    }
    let gpu = Gpu::headless()?;
    let enc = Arc::new(korea()?);
    let refiner = Arc::new(PlanarRefiner::from_encoded(&enc)?);
    let world = PlanarWorld {
        spacing_m: 90.0,
        value_scale_m: enc.value_scale_m,
        value_offset_m: enc.value_offset_m,
    };
    let eye = DVec3::new(20_000.0, 80_000.0, 2_500.0);
    let view = View {
        eye,
        target: eye + DVec3::new(3_000.0, -1_000.0, -700.0),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: SIZE,
        tolerance_px: 0.5,
    };
    let mut dag = Dag::new(Arc::clone(&refiner));
    let mut source = Local {
        blobs: enc.blobs_by_key()?,
        refiner: Arc::clone(&refiner),
    };
    let mut refinement = Refinement::default();
    let clock = SystemClock(Instant::now());
    let mut converged = false;
    for _ in 0..400 {
        let s = refinement.update(
            &mut dag,
            &view,
            world,
            &mut source,
            &clock,
            Duration::from_secs(600),
        )?;
        if s.converged {
            converged = true;
            break;
        }
    }
    if !converged {
        return Err("the refinement did not converge".into());
    }
    let camera = Camera::from_view(&view);
    let frame = refiner.world_frame(&world, 0);
    let config = RendererConfig {
        gpu_budget_bytes: 1 << 30,
        max_uploads_per_frame: 1 << 16,
        colour_format: OFFSCREEN_FORMAT,
        ..Default::default()
    };
    let mut renderer: TerrainRenderer<PlanarRefiner> =
        TerrainRenderer::new(&gpu.device, frame, config)?;
    renderer.apply(&*refiner, None, dag.take_patch_changes())?;
    // The same renderer drawing with a loop of `draw_indexed` instead of one indirect
    // multi-draw: separates the cost of indirect draws from the vertex shader's.
    let mut looped: TerrainRenderer<PlanarRefiner> = TerrainRenderer::new(
        &gpu.device,
        frame,
        RendererConfig {
            multi_draw: Some(false),
            ..renderer.config().clone()
        },
    )?;
    dag.restart_cut_changes();
    looped.apply(&*refiner, None, dag.take_patch_changes())?;
    while looped.prepare(&gpu.queue, &camera).pending > 0 {}
    // The same renderer with the other depth path: reversed Z written by the fragment
    // stage where the backend has clip control (the GL path), rasterised on GL.
    let flip = !renderer.config().fragment_depth.unwrap_or(false);
    let mut other_depth: TerrainRenderer<PlanarRefiner> = TerrainRenderer::new(
        &gpu.device,
        frame,
        RendererConfig {
            fragment_depth: Some(flip),
            ..renderer.config().clone()
        },
    )?;
    dag.restart_cut_changes();
    other_depth.apply(&*refiner, None, dag.take_patch_changes())?;
    while other_depth.prepare(&gpu.queue, &camera).pending > 0 {}
    let mut stats = renderer.prepare(&gpu.queue, &camera);
    while stats.pending > 0 {
        stats = renderer.prepare(&gpu.queue, &camera);
    }
    if stats.missing > 0 {
        return Err(format!("{} patches found no GPU slot", stats.missing).into());
    }
    let raw = Raw::new(&gpu, &dag, &world, &frame, &camera)?;
    let triangles = stats.triangles;
    if u64::from(raw.index_count) != triangles * 3 {
        return Err(format!(
            "raw draw has {} indices, batched {} triangles",
            raw.index_count, triangles
        )
        .into());
    }
    let offscreen = Offscreen::new(&gpu, SIZE)?;
    // Warm up both pipelines (shader compilation, first-use allocations).
    timed(&gpu, &offscreen, |p| renderer.draw(p))?;
    timed(&gpu, &offscreen, |p| raw.draw(p))?;
    timed(&gpu, &offscreen, |p| looped.draw(p))?;
    timed(&gpu, &offscreen, |p| other_depth.draw(p))?;
    let (mut batched, mut raw_ms, mut loop_ms) = (Vec::new(), Vec::new(), Vec::new());
    let mut other_ms = Vec::new();
    let mut gpu_timed = true;
    for _ in 0..rounds {
        let (b, tb) = timed(&gpu, &offscreen, |p| renderer.draw(p))?;
        let (r, tr) = timed(&gpu, &offscreen, |p| raw.draw(p))?;
        let (l, tl) = timed(&gpu, &offscreen, |p| looped.draw(p))?;
        let (o, to) = timed(&gpu, &offscreen, |p| other_depth.draw(p))?;
        gpu_timed &= tb && tr && tl && to;
        other_ms.push(o);
        batched.push(b);
        raw_ms.push(r);
        loop_ms.push(l);
    }
    let (b, r) = (median(batched.clone()), median(raw_ms.clone()));
    let l = median(loop_ms.clone());
    let o = median(other_ms.clone());
    let tps = |ms: f64| triangles as f64 / (ms / 1e3);
    let ratio = tps(b) / tps(r);
    if json {
        let out = serde_json::json!({
            "date": utc_now(),
            "triangles": triangles,
            "patches": stats.patches,
            "draw_calls": stats.draw_calls,
            "multi_draw": renderer.multi_draw(),
            "batched_ms_median": b,
            "raw_ms_median": r,
            "batched_triangles_per_s": tps(b),
            "raw_triangles_per_s": tps(r),
            "ratio": ratio,
            "batched_loop_triangles_per_s": tps(l),
            "fragment_depth": !flip,
            "batched_other_depth_triangles_per_s": tps(o),
            "indirect_validation": gpu_indirect_validation(),
            "rounds": rounds,
            "timing": if gpu_timed { "timestamp queries" } else { "wall time, submit to idle" },
            "size": SIZE,
            "n": N,
            "adapter": gpu.describe(),
        });
        println!("{out}");
    } else {
        println!(
            "{triangles} triangles in {} patches ({} draw calls), {rounds} rounds, {}",
            stats.patches,
            stats.draw_calls,
            if gpu_timed {
                "GPU timestamps"
            } else {
                "wall time"
            }
        );
        println!(
            "batched: median {b:.2} ms = {:.3e} triangles/s  (all: {batched:.1?})",
            tps(b)
        );
        println!(
            "raw:     median {r:.2} ms = {:.3e} triangles/s  (all: {raw_ms:.1?})",
            tps(r)
        );
        println!(
            "depth {}: median {o:.2} ms = {:.3e} triangles/s  (all: {other_ms:.1?})",
            if flip { "per fragment" } else { "rasterised" },
            tps(o)
        );
        println!(
            "ratio (batched/raw): {ratio:.3}  (bar >= 0.9); adapter {}",
            gpu.describe()
        );
    }
    Ok(())
}

/// "YYYY-MM-DDTHH:MM:SSZ" of now.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem / 60 % 60,
        rem % 60
    )
}

/// Whether wgpu validates indirect draws (on unless `WGPU_VALIDATION_INDIRECT_CALL=0`).
fn gpu_indirect_validation() -> bool {
    wgpu::InstanceFlags::from_build_config()
        .with_env()
        .contains(wgpu::InstanceFlags::VALIDATION_INDIRECT_CALL)
}
