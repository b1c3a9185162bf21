//! The retained-mode terrain renderer: a pool of equal-sized GPU slots (heights, colour,
//! per-patch frame data), one shared index buffer, and a dense list of indirect draws,
//! all updated in proportion to what changed.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use bytemuck::{Pod, Zeroable};
use quincunx_client::colour::ColourLayer;
use quincunx_client::dag::Half;
use quincunx_client::session::{Patch, PatchChanges, Session};
use wgpu::util::DeviceExt;

use crate::RenderError;
use crate::camera::{Camera, FrameUniforms, Lighting, Modes, frame_uniforms, limbs};
use crate::domain::{AffinePatch, RenderDomain, WorldFrame};
use crate::pool::{Placement, Pool, PoolStats};

/// A patch: a half of a diamond.
pub type PatchKey<I> = (I, Half);

/// A vertex's clip position as the GPU computed it: patch, grid index `(i, j)`, clip.
pub type CapturedVertex<I> = (PatchKey<I>, usize, usize, [f32; 4]);

/// Renderer settings.
#[derive(Clone, Debug)]
pub struct RendererConfig {
    /// GPU memory for patches (heights, colour, frame data, draw), bytes. The slots are
    /// allocated up front; the budget is never exceeded.
    pub gpu_budget_bytes: u64,
    /// Most patches uploaded per frame; the drawn cut switches to the new one once all
    /// its patches are resident, so a capped frame shows the previous cut, never a hole.
    pub max_uploads_per_frame: usize,
    /// Format of the colour target the app renders into.
    pub colour_format: wgpu::TextureFormat,
    /// Depth format ([`DEPTH_FORMAT`]: reversed Z needs 32-bit float).
    pub depth_format: wgpu::TextureFormat,
    /// MSAA samples of the target.
    pub sample_count: u32,
    /// Use `multi_draw_indexed_indirect` (`None`: where the adapter executes indirect
    /// draws natively; otherwise, or without `Features::INDIRECT_FIRST_INSTANCE` on the
    /// device, one `draw_indexed` per patch).
    pub multi_draw: Option<bool>,
    /// Write the reversed-Z depth in the fragment stage (`near / w`) instead of letting
    /// the rasteriser interpolate it (`None`: where the backend has no clip control,
    /// that is wgpu's GL backend, whose `[-1, 1]` depth range rounds `near / distance`
    /// to 0 at planet distances). Either way the stored depth is `near / w`, reversed Z
    /// with an infinite far plane; the fragment path costs early depth rejection.
    /// [`TerrainRenderer::config`] reports the resolved choice.
    pub fragment_depth: Option<bool>,
}

/// The height range the land tint spans (`Lighting::tint_m`): sea level to the highest
/// height the roots' grids reach (at least 50 m). Fixed by the repository, whatever the
/// cut is when a renderer is made.
pub fn land_tint_m<R: RenderDomain>(domain: &R, world: &WorldFrame) -> (f64, f64) {
    let top = domain
        .roots()
        .iter()
        .flat_map(|(_, grid)| grid.iter())
        .map(|&v| world.value_offset_m + f64::from(v) * world.value_scale_m)
        .fold(f64::NEG_INFINITY, f64::max);
    (0.0, top.max(50.0))
}

/// The depth format the renderer expects.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

impl Default for RendererConfig {
    fn default() -> Self {
        RendererConfig {
            gpu_budget_bytes: 128 << 20,
            max_uploads_per_frame: 512,
            colour_format: wgpu::TextureFormat::Rgba8Unorm,
            depth_format: DEPTH_FORMAT,
            sample_count: 1,
            multi_draw: None,
            fragment_depth: None,
        }
    }
}

/// What one [`TerrainRenderer::prepare`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderFrameStats {
    /// Patches drawn.
    pub patches: usize,
    /// Triangles drawn.
    pub triangles: u64,
    /// Draw calls the pass will record.
    pub draw_calls: usize,
    /// Patches uploaded this frame.
    pub uploads: usize,
    /// Bytes written to the GPU this frame (patch data, draws, uniforms).
    pub upload_bytes: u64,
    /// Patches of the cut waiting for an upload (capped frames).
    pub pending: usize,
    /// Patches of the cut with no slot (the budget is smaller than the cut).
    pub missing: usize,
    /// Whether the drawn cut is the client's current one.
    pub current: bool,
    /// Host time of `apply` plus `prepare` since the previous frame, ms.
    pub cpu_ms: f64,
    /// GPU bytes held by patches (resident and cached slots).
    pub gpu_bytes_used: u64,
    /// GPU bytes allocated for the pool (the budget, rounded down to whole slots).
    pub gpu_bytes_allocated: u64,
    /// GPU bytes of one patch slot.
    pub slot_bytes: u64,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct PatchGpu {
    xy: [i32; 4],
    e1: [i32; 4],
    e2: [i32; 4],
    z: [i32; 4],
    zi: [i32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct DrawArgs {
    index_count: u32,
    instance_count: u32,
    first_index: u32,
    base_vertex: i32,
    first_instance: u32,
}

/// Waiting to enter the drawn cut.
struct Pending {
    patch: Option<Patch<()>>,
    affine: AffinePatch,
    colour: Option<Vec<u32>>,
    /// No slot yet (the pool was full).
    unplaced: bool,
}

/// The drawn patches as a dense array of indirect draws (swap-remove).
struct DrawList<K> {
    draws: Vec<DrawArgs>,
    keys: Vec<K>,
    index: HashMap<K, usize>,
    dirty: Option<(usize, usize)>,
}

impl<K: std::hash::Hash + Eq + Clone> DrawList<K> {
    fn new() -> Self {
        DrawList {
            draws: Vec::new(),
            keys: Vec::new(),
            index: HashMap::new(),
            dirty: None,
        }
    }

    fn touch(&mut self, at: usize) {
        self.dirty = Some(match self.dirty {
            Some((a, b)) => (a.min(at), b.max(at + 1)),
            None => (at, at + 1),
        });
    }

    fn insert(&mut self, key: K, draw: DrawArgs) {
        if self.index.contains_key(&key) {
            return;
        }
        self.index.insert(key.clone(), self.draws.len());
        self.keys.push(key);
        self.draws.push(draw);
        self.touch(self.draws.len() - 1);
    }

    fn remove(&mut self, key: &K) {
        let Some(at) = self.index.remove(key) else {
            return;
        };
        let last = self.draws.len() - 1;
        self.draws.swap_remove(at);
        self.keys.swap_remove(at);
        if at < last {
            self.index.insert(self.keys[at].clone(), at);
            self.touch(at);
        }
    }

    fn contains(&self, key: &K) -> bool {
        self.index.contains_key(key)
    }
}

/// Draws the cut of one repository (with its optional colour layer) into an app's render
/// pass. See the crate docs for the frame loop.
pub struct TerrainRenderer<R: RenderDomain> {
    world: WorldFrame,
    config: RendererConfig,
    /// One pipeline per drawing mode used so far.
    pipelines: HashMap<Modes, wgpu::RenderPipeline>,
    pipeline_layout: wgpu::PipelineLayout,
    shader: wgpu::ShaderModule,
    layout: wgpu::BindGroupLayout,
    bind_group: wgpu::BindGroup,
    uniforms: wgpu::Buffer,
    heights: wgpu::Buffer,
    patches: wgpu::Buffer,
    colours: wgpu::Buffer,
    indirect: wgpu::Buffer,
    index: wgpu::Buffer,
    half_indices: u32,
    multi_draw: bool,
    pool: Pool<PatchKey<R::Id>>,
    slot_bytes: u64,
    drawn: DrawList<PatchKey<R::Id>>,
    pending: HashMap<PatchKey<R::Id>, Pending>,
    uploads: VecDeque<PatchKey<R::Id>>,
    leaving: HashSet<PatchKey<R::Id>>,
    cpu_s: f64,
    srgb: bool,
    /// Lighting.
    pub lighting: Lighting,
    modes: Modes,
}

impl<R: RenderDomain> TerrainRenderer<R> {
    /// A renderer for a repository whose geometry is `world`, drawing into targets of
    /// `config`'s formats on `device`.
    pub fn new(
        device: &wgpu::Device,
        world: WorldFrame,
        mut config: RendererConfig,
    ) -> Result<Self, RenderError> {
        config.fragment_depth = Some(
            config
                .fragment_depth
                .unwrap_or_else(|| !has_clip_control(device.adapter_info().backend)),
        );
        if config.depth_format != DEPTH_FORMAT {
            return Err(RenderError::Config(format!(
                "depth format {:?}: reversed Z needs {DEPTH_FORMAT:?}",
                config.depth_format
            )));
        }
        let n = world.n as u64;
        if !(2..=1024).contains(&n) {
            return Err(RenderError::Config(format!("diamond size N = {n}")));
        }
        let nv2 = (n + 1) * (n + 1);
        let nc = u64::from(world.colour_n);
        let ncv2 = if nc > 0 { (nc + 1) * (nc + 1) } else { 0 };
        let slot_bytes = nv2 * 4 + ncv2 * 4 + std::mem::size_of::<PatchGpu>() as u64 + 20;
        let limits = device.limits();
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let by_budget = config.gpu_budget_bytes / slot_bytes;
        // Heights and records are vertex buffers (one buffer each); colour is a storage
        // binding.
        let by_heights = limits.max_buffer_size / (nv2 * 4);
        let by_colour = if ncv2 > 0 {
            max_binding / (ncv2 * 4)
        } else {
            u64::MAX
        };
        let capacity = by_budget.min(by_heights).min(by_colour).min(1 << 24) as u32;
        if capacity == 0 {
            return Err(RenderError::Config(format!(
                "a GPU budget of {} bytes holds no patch ({} bytes each)",
                config.gpu_budget_bytes, slot_bytes
            )));
        }
        // Indirect execution is native on Vulkan (lavapipe too), Metal and DX12; on GL
        // wgpu emulates it, and WebGL2 has none: draw in a loop there. Each draw names
        // its slot as its first instance, which indirect draws allow only with
        // INDIRECT_FIRST_INSTANCE.
        let first_instance = device
            .features()
            .contains(wgpu::Features::INDIRECT_FIRST_INSTANCE);
        let multi_draw = first_instance
            && config.multi_draw.unwrap_or_else(|| {
                !matches!(
                    device.adapter_info().backend,
                    wgpu::Backend::Gl | wgpu::Backend::BrowserWebGpu
                )
            });
        let cap = u64::from(capacity);
        let storage = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(16),
                usage: usage | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let heights = storage(
            "quincunx heights",
            cap * nv2 * 4,
            wgpu::BufferUsages::VERTEX,
        );
        let patches = storage(
            "quincunx patches",
            cap * std::mem::size_of::<PatchGpu>() as u64,
            wgpu::BufferUsages::VERTEX,
        );
        let colours = storage(
            "quincunx colours",
            cap * ncv2 * 4,
            wgpu::BufferUsages::STORAGE,
        );
        let indirect = storage("quincunx draws", cap * 20, wgpu::BufferUsages::INDIRECT);
        let uniforms = storage(
            "quincunx frame",
            std::mem::size_of::<FrameUniforms>() as u64,
            wgpu::BufferUsages::UNIFORM,
        );
        let (indices, half_indices) = grid_indices(world.n);
        let index = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("quincunx grid indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::INDEX,
        });
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("quincunx terrain"),
            source: wgpu::ShaderSource::Wgsl(include_str!("terrain.wgsl").into()),
        });
        let entry = |binding: u32, ty: wgpu::BufferBindingType, vis: wgpu::ShaderStages| {
            wgpu::BindGroupLayoutEntry {
                binding,
                visibility: vis,
                ty: wgpu::BindingType::Buffer {
                    ty,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }
        };
        let both = wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT;
        let ro = wgpu::BufferBindingType::Storage { read_only: true };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("quincunx terrain"),
            entries: &[
                entry(0, wgpu::BufferBindingType::Uniform, both),
                entry(1, ro, wgpu::ShaderStages::FRAGMENT),
            ],
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("quincunx terrain"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: uniforms.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: colours.as_entire_binding(),
                },
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("quincunx terrain"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let modes = Modes::default();
        let pipeline = terrain_pipeline(
            device,
            &shader,
            &pipeline_layout,
            &config,
            is_planet(&world),
            &pipeline_constants(&world, modes, config.colour_format.is_srgb()),
        );
        let mut pipelines = HashMap::new();
        pipelines.insert(modes, pipeline);
        Ok(TerrainRenderer {
            srgb: config.colour_format.is_srgb(),
            world,
            config,
            pipelines,
            pipeline_layout,
            shader,
            layout,
            bind_group,
            uniforms,
            heights,
            patches,
            colours,
            indirect,
            index,
            half_indices,
            multi_draw,
            pool: Pool::new(capacity),
            slot_bytes,
            drawn: DrawList::new(),
            pending: HashMap::new(),
            uploads: VecDeque::new(),
            leaving: HashSet::new(),
            cpu_s: 0.0,
            lighting: Lighting::default(),
            modes,
        })
    }

    /// A renderer for a session's repository.
    pub fn for_session(
        device: &wgpu::Device,
        session: &Session<R>,
        config: RendererConfig,
    ) -> Result<Self, RenderError> {
        let colour_n = session.dag().colour().map_or(0, ColourLayer::n);
        let world = session
            .dag()
            .refiner()
            .world_frame(&session.world(), colour_n);
        let mut renderer = TerrainRenderer::new(device, world, config)?;
        renderer.lighting.tint_m = Some(land_tint_m(session.dag().refiner(), &world));
        Ok(renderer)
    }

    /// The repository geometry.
    pub fn world(&self) -> &WorldFrame {
        &self.world
    }

    /// The settings.
    pub fn config(&self) -> &RendererConfig {
        &self.config
    }

    /// Bounds the session's cut by the patches the pool holds
    /// ([`Session::set_max_cut_halves`], unless it is bounded tighter already), so the
    /// cut it is given always fits: a tolerance finer than the GPU budget allows draws the
    /// finest cut that fits instead of leaving patches out.
    pub fn bound_cut(&self, session: &mut Session<R>) {
        let slots = self.pool.capacity() as usize;
        if session.max_cut_halves().is_none_or(|max| max > slots) {
            session.set_max_cut_halves(Some(slots));
        }
    }

    /// Patch slots in the pool.
    pub fn capacity(&self) -> u32 {
        self.pool.capacity()
    }

    /// Pool counters (uploads, cache hits, evictions, refusals).
    pub fn pool_stats(&self) -> PoolStats {
        self.pool.stats()
    }

    /// The drawing modes.
    pub fn modes(&self) -> Modes {
        self.modes
    }

    /// Switches drawing modes (wireframe, colour by level, colour off). Each mode is its
    /// own pipeline, compiled on first use: a constant branch costs nothing per
    /// fragment, a uniform one does on some drivers (llvmpipe: about 40 % of the
    /// fragment time).
    pub fn set_modes(&mut self, device: &wgpu::Device, modes: Modes) {
        if !self.pipelines.contains_key(&modes) {
            let constants = pipeline_constants(&self.world, modes, self.srgb);
            let pipeline = terrain_pipeline(
                device,
                &self.shader,
                &self.pipeline_layout,
                &self.config,
                is_planet(&self.world),
                &constants,
            );
            self.pipelines.insert(modes, pipeline);
        }
        self.modes = modes;
    }

    /// Whether draws go through `multi_draw_indexed_indirect`.
    pub fn multi_draw(&self) -> bool {
        self.multi_draw
    }

    /// Takes the session's cut changes since the previous frame ([`Session::cut_changes`]),
    /// and bounds the session's cut by the pool ([`TerrainRenderer::bound_cut`]).
    pub fn sync(&mut self, session: &mut Session<R>) -> Result<(), RenderError> {
        self.bound_cut(session);
        let changes = session.cut_changes();
        let dag = session.dag();
        self.apply(dag.refiner(), dag.colour(), changes)
    }

    /// Records cut changes: patches that left stop being drawn once the new cut is
    /// resident (they stay cached), patches that entered are queued for upload (or found
    /// in the cache). O(changes).
    pub fn apply(
        &mut self,
        domain: &R,
        colour: Option<&ColourLayer<R>>,
        changes: PatchChanges<R::Id>,
    ) -> Result<(), RenderError> {
        let start = Instant::now();
        for key in changes.left {
            if self.pending.remove(&key).is_some() {
                self.pool.release(&key);
            } else if self.drawn.contains(&key) {
                self.leaving.insert(key);
            }
        }
        for patch in changes.entered {
            let key = (patch.id, patch.half);
            if self.leaving.remove(&key) || self.drawn.contains(&key) {
                continue;
            }
            let affine = domain
                .affine(patch.id, &patch.corners, patch.half)
                .ok_or_else(|| RenderError::Geometry(format!("{:?} is not affine", key)))?;
            let colour = match (colour, &patch.colour) {
                (Some(layer), Some(grids)) => Some(pack_colour(layer, grids, self.world.colour_n)),
                _ => None,
            };
            let mut pending = Pending {
                patch: Some(Patch {
                    id: (),
                    half: patch.half,
                    corners: patch.corners,
                    grid: Arc::clone(&patch.grid),
                    generation: patch.generation,
                    colour: None,
                }),
                affine,
                colour,
                unplaced: false,
            };
            match self.pool.want(key) {
                Placement::Resident(_) => pending.patch = None,
                Placement::Upload(_) => self.uploads.push_back(key),
                Placement::Full => pending.unplaced = true,
            }
            self.pending.insert(key, pending);
        }
        self.cpu_s += start.elapsed().as_secs_f64();
        Ok(())
    }

    /// Uploads queued patches (up to the per-frame cap), switches to the new cut once it
    /// is resident, and writes the frame's uniforms and changed draws. Call once per
    /// frame before [`TerrainRenderer::draw`].
    pub fn prepare(&mut self, queue: &wgpu::Queue, camera: &Camera) -> RenderFrameStats {
        let start = Instant::now();
        let mut stats = RenderFrameStats::default();
        // Patches the pool could not place: try again (cached slots may have freed).
        let unplaced: Vec<PatchKey<R::Id>> = self
            .pending
            .iter()
            .filter(|(_, p)| p.unplaced)
            .map(|(k, _)| *k)
            .collect();
        for key in unplaced {
            match self.pool.want(key) {
                Placement::Upload(_) => {
                    self.uploads.push_back(key);
                    if let Some(p) = self.pending.get_mut(&key) {
                        p.unplaced = false;
                    }
                }
                Placement::Resident(_) => {
                    if let Some(p) = self.pending.get_mut(&key) {
                        p.unplaced = false;
                        p.patch = None;
                    }
                }
                Placement::Full => {}
            }
        }
        let nv2 = u64::from((self.world.n + 1) * (self.world.n + 1));
        let ncv2 = if self.world.colour_n > 0 {
            u64::from((self.world.colour_n + 1) * (self.world.colour_n + 1))
        } else {
            0
        };
        while stats.uploads < self.config.max_uploads_per_frame {
            let Some(key) = self.uploads.pop_front() else {
                break;
            };
            let (Some(slot), Some(p)) = (self.pool.slot(&key), self.pending.get_mut(&key)) else {
                continue;
            };
            let Some(patch) = p.patch.take() else {
                continue;
            };
            let slot = u64::from(slot);
            let heights: &[i32] = &patch.grid;
            queue.write_buffer(&self.heights, slot * nv2 * 4, bytemuck::cast_slice(heights));
            let record = patch_record(&p.affine, p.colour.is_some(), self.world.narrow());
            let rec_size = std::mem::size_of::<PatchGpu>() as u64;
            queue.write_buffer(&self.patches, slot * rec_size, bytemuck::bytes_of(&record));
            stats.upload_bytes += nv2 * 4 + rec_size;
            if let Some(c) = &p.colour {
                queue.write_buffer(&self.colours, slot * ncv2 * 4, bytemuck::cast_slice(c));
                stats.upload_bytes += ncv2 * 4;
            }
            self.pool.written(&key);
            stats.uploads += 1;
        }
        stats.pending = self.uploads.len();
        // Switch once the new cut is resident: never a frame with a hole from a capped
        // upload (patches with no slot at all are drawn without, and counted).
        if self.uploads.is_empty() {
            for key in self.leaving.drain() {
                self.drawn.remove(&key);
                self.pool.release(&key);
            }
            let ready: Vec<PatchKey<R::Id>> = self
                .pending
                .iter()
                .filter(|(_, p)| !p.unplaced)
                .map(|(k, _)| *k)
                .collect();
            for key in ready {
                self.pending.remove(&key);
                if let Some(slot) = self.pool.slot(&key) {
                    let first = match key.1 {
                        Half::Lower => 0,
                        Half::Upper => self.half_indices,
                    };
                    self.drawn.insert(
                        key,
                        DrawArgs {
                            index_count: self.half_indices,
                            instance_count: 1,
                            first_index: first,
                            base_vertex: (u64::from(slot) * nv2) as i32,
                            first_instance: slot,
                        },
                    );
                }
            }
        }
        stats.missing = self.pending.values().filter(|p| p.unplaced).count();
        stats.current = self.uploads.is_empty() && stats.missing == 0 && self.leaving.is_empty();
        if let Some((a, b)) = self.drawn.dirty.take() {
            let b = b.min(self.drawn.draws.len());
            if a < b {
                queue.write_buffer(
                    &self.indirect,
                    (a * 20) as u64,
                    bytemuck::cast_slice(&self.drawn.draws[a..b]),
                );
                stats.upload_bytes += ((b - a) * 20) as u64;
            }
        }
        let uniforms = frame_uniforms(&self.world, camera, &self.lighting);
        queue.write_buffer(&self.uniforms, 0, bytemuck::bytes_of(&uniforms));
        stats.upload_bytes += std::mem::size_of::<FrameUniforms>() as u64;
        stats.patches = self.drawn.draws.len();
        stats.triangles = stats.patches as u64 * u64::from(self.world.n * self.world.n);
        stats.draw_calls = if self.multi_draw {
            usize::from(stats.patches > 0)
        } else {
            stats.patches
        };
        stats.gpu_bytes_used = self.pool.occupied() as u64 * self.slot_bytes;
        stats.gpu_bytes_allocated = u64::from(self.pool.capacity()) * self.slot_bytes;
        stats.slot_bytes = self.slot_bytes;
        stats.cpu_ms = (self.cpu_s + start.elapsed().as_secs_f64()) * 1e3;
        self.cpu_s = 0.0;
        stats
    }

    /// Records the terrain's draws into the app's pass (whose targets have the
    /// configured formats; depth cleared to 0).
    pub fn draw(&self, pass: &mut wgpu::RenderPass<'_>) {
        let count = self.drawn.draws.len() as u32;
        if count == 0 {
            return;
        }
        let Some(pipeline) = self.pipelines.get(&self.modes) else {
            return;
        };
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, self.heights.slice(..));
        pass.set_vertex_buffer(1, self.patches.slice(..));
        pass.set_index_buffer(self.index.slice(..), wgpu::IndexFormat::Uint32);
        if self.multi_draw {
            pass.multi_draw_indexed_indirect(&self.indirect, 0, count);
        } else {
            for d in &self.drawn.draws {
                pass.draw_indexed(
                    d.first_index..d.first_index + d.index_count,
                    d.base_vertex,
                    d.first_instance..d.first_instance + 1,
                );
            }
        }
    }

    /// The drawn patches' keys and slots (for tests and tools).
    pub fn drawn(&self) -> impl Iterator<Item = (&PatchKey<R::Id>, u32)> {
        self.drawn
            .keys
            .iter()
            .filter_map(|k| self.pool.slot(k).map(|s| (k, s)))
    }

    /// Indices drawn per patch (`3 N^2`).
    pub fn index_count_per_patch(&self) -> u32 {
        self.half_indices
    }

    /// The clip positions the vertex shader computes for every vertex of every drawn
    /// patch, read back from the GPU (the same vertex function as [`Self::draw`], run by
    /// a capture pipeline that stores its output): `(patch, i, j, clip)`. Needs
    /// `Features::VERTEX_WRITABLE_STORAGE` ([`crate::offscreen::Gpu::headless`] asks for
    /// it). Call after [`Self::prepare`].
    pub fn capture_clip_positions(
        &self,
        gpu: &crate::offscreen::Gpu,
    ) -> Result<Vec<CapturedVertex<R::Id>>, RenderError> {
        let device = &gpu.device;
        if !device
            .features()
            .contains(wgpu::Features::VERTEX_WRITABLE_STORAGE)
        {
            return Err(RenderError::NoAdapter(
                "capturing vertex positions needs VERTEX_WRITABLE_STORAGE".into(),
            ));
        }
        let drawn: Vec<(PatchKey<R::Id>, u32)> = self.drawn().map(|(k, s)| (*k, s)).collect();
        let Some(max_slot) = drawn.iter().map(|d| d.1).max() else {
            return Ok(Vec::new());
        };
        let n = self.world.n as usize;
        let nv2 = ((n + 1) * (n + 1)) as u64;
        let size = (u64::from(max_slot) + 1) * nv2 * 16;
        let captured = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("quincunx captured clip positions"),
            size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let read = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("quincunx captured read"),
            size,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let layout1 = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("quincunx capture"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: false },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let group1 = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("quincunx capture"),
            layout: &layout1,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: captured.as_entire_binding(),
            }],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("quincunx capture"),
            bind_group_layouts: &[Some(&self.layout), Some(&layout1)],
            immediate_size: 0,
        });
        let constants = pipeline_constants(&self.world, self.modes, self.srgb);
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("quincunx capture"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &self.shader,
                entry_point: Some(if is_planet(&self.world) {
                    "capture_planet"
                } else {
                    "capture_planar"
                }),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    ..Default::default()
                },
                buffers: &vertex_layouts(is_planet(&self.world)),
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::PointList,
                ..Default::default()
            },
            // A pipeline needs an attachment: a tiny depth target, never written (the
            // points land outside the clip volume).
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(false),
                depth_compare: Some(wgpu::CompareFunction::Always),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: None,
            multiview_mask: None,
            cache: None,
        });
        let target = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("quincunx capture target"),
            size: wgpu::Extent3d {
                width: 4,
                height: 4,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        let view = target.create_view(&Default::default());
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("quincunx capture"),
                color_attachments: &[],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.set_bind_group(1, &group1, &[]);
            pass.set_vertex_buffer(0, self.heights.slice(..));
            pass.set_vertex_buffer(1, self.patches.slice(..));
            for (_, slot) in &drawn {
                let first = u64::from(*slot) * nv2;
                pass.draw(first as u32..(first + nv2) as u32, *slot..*slot + 1);
            }
        }
        encoder.copy_buffer_to_buffer(&captured, 0, &read, 0, size);
        gpu.queue.submit([encoder.finish()]);
        let clips: Vec<[f32; 4]> =
            crate::offscreen::map_read(gpu, &read, bytemuck::pod_collect_to_vec)?;
        let mut out = Vec::new();
        for (key, slot) in drawn {
            for i in 0..=n {
                for j in 0..=n {
                    if key.1.contains(i, j) {
                        let k = slot as usize * (n + 1) * (n + 1) + i * (n + 1) + j;
                        out.push((key, i, j, clips[k]));
                    }
                }
            }
        }
        Ok(out)
    }
}

/// Vertex inputs: the heights (one `i32` per grid vertex; `base_vertex` selects the
/// slot) and the patch record (per instance; the first instance is the slot).
fn vertex_layouts(planet: bool) -> [Option<wgpu::VertexBufferLayout<'static>>; 2] {
    const HEIGHT: [wgpu::VertexAttribute; 1] = wgpu::vertex_attr_array![0 => Sint32];
    const PLANET: [wgpu::VertexAttribute; 5] = wgpu::vertex_attr_array![
        1 => Sint32x4, 2 => Sint32x4, 3 => Sint32x4, 4 => Sint32x4, 5 => Sint32x4
    ];
    // The plane skips the z limbs (location 4, offset 48).
    const PLANAR: [wgpu::VertexAttribute; 4] = [
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Sint32x4,
            offset: 0,
            shader_location: 1,
        },
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Sint32x4,
            offset: 16,
            shader_location: 2,
        },
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Sint32x4,
            offset: 32,
            shader_location: 3,
        },
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Sint32x4,
            offset: 64,
            shader_location: 5,
        },
    ];
    [
        Some(wgpu::VertexBufferLayout {
            array_stride: 4,
            step_mode: wgpu::VertexStepMode::Vertex,
            attributes: &HEIGHT,
        }),
        Some(wgpu::VertexBufferLayout {
            array_stride: std::mem::size_of::<PatchGpu>() as u64,
            step_mode: wgpu::VertexStepMode::Instance,
            attributes: if planet { &PLANET } else { &PLANAR },
        }),
    ]
}

/// Whether a backend maps clip `z / w` in `[0, 1]` to depth as is (Vulkan, Metal, DX12,
/// WebGPU); wgpu's GL backend has no clip control (naga rewrites `z` to `2z - w` for
/// OpenGL's `[-1, 1]` range).
pub fn has_clip_control(backend: wgpu::Backend) -> bool {
    !matches!(backend, wgpu::Backend::Gl)
}

/// Whether the repository is a planet (the shader's entry points and inputs differ).
fn is_planet(world: &WorldFrame) -> bool {
    matches!(world.geometry, crate::domain::Geometry::Planet { .. })
}

/// The shader's pipeline constants: the repository's domain, grid size and colour layer,
/// the drawing modes and the target's encoding.
fn pipeline_constants(world: &WorldFrame, modes: Modes, srgb: bool) -> [(&'static str, f64); 7] {
    let planet = matches!(world.geometry, crate::domain::Geometry::Planet { .. });
    let flag = |b: bool| f64::from(u8::from(b));
    [
        ("PLANET", flag(planet)),
        ("GRID_N", f64::from(world.n)),
        ("COLOUR", flag(world.colour_n > 0 && !modes.no_colour)),
        ("LEVELS", flag(modes.colour_by_level)),
        ("WIREFRAME", flag(modes.wireframe)),
        ("SRGB", flag(srgb)),
        ("NARROW", flag(world.narrow())),
    ]
}

/// The terrain pipeline for one set of constants.
fn terrain_pipeline(
    device: &wgpu::Device,
    shader: &wgpu::ShaderModule,
    layout: &wgpu::PipelineLayout,
    config: &RendererConfig,
    planet: bool,
    constants: &[(&str, f64)],
) -> wgpu::RenderPipeline {
    // The plain fragment stage where no mode needs the grid coordinates or the slot.
    let on = |name: &str| constants.iter().any(|(k, v)| *k == name && *v != 0.0);
    let full = on("COLOUR") || on("LEVELS") || on("WIREFRAME");
    let fragment = match (full, config.fragment_depth == Some(true)) {
        (true, false) => "fs_main",
        (false, false) => "fs_plain",
        (true, true) => "fs_main_depth",
        (false, true) => "fs_plain_depth",
    };
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("quincunx terrain"),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module: shader,
            entry_point: Some(if planet { "vs_planet" } else { "vs_planar" }),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                ..Default::default()
            },
            buffers: &vertex_layouts(planet),
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
        multisample: wgpu::MultisampleState {
            count: config.sample_count,
            ..Default::default()
        },
        fragment: Some(wgpu::FragmentState {
            module: shader,
            entry_point: Some(fragment),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                ..Default::default()
            },
            targets: &[Some(config.colour_format.into())],
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// The per-patch record: the affine map in limbs, level and flags.
fn patch_record(a: &AffinePatch, has_colour: bool, narrow: bool) -> PatchGpu {
    let split = |v: [i64; 3]| v.map(|x| if narrow { (x as i32, 0) } else { limbs(x) });
    let (b, e1, e2) = (split(a.base), split(a.e1), split(a.e2));
    PatchGpu {
        xy: [b[0].0, b[1].0, b[0].1, b[1].1],
        e1: [e1[0].0, e1[1].0, e1[0].1, e1[1].1],
        e2: [e2[0].0, e2[1].0, e2[0].1, e2[1].1],
        z: [b[2].0, b[2].1, e1[2].0, e1[2].1],
        zi: [e2[2].0, e2[2].1, a.level as i32, i32::from(has_colour)],
    }
}

/// YCoCg-R integers packed as three signed 10-bit fields (the shader inverts the
/// transform).
fn pack_colour<R: RenderDomain>(layer: &ColourLayer<R>, grids: &[Vec<i32>], nc: u32) -> Vec<u32> {
    let count = ((nc + 1) * (nc + 1)) as usize;
    (0..count)
        .map(|k| {
            let [y, co, cg] = layer.ycocg(grids, k).unwrap_or([0, 0, 0]);
            let f = |x: i32| (x.clamp(-512, 511) as u32) & 0x3FF;
            f(y) | (f(co) << 10) | (f(cg) << 20)
        })
        .collect()
}

/// The shared index buffer: the lower half's triangles, then the upper half's, of an
/// `(N+1)^2` grid whose cells split along `i = j` (as the halves do). Returns the indices
/// and the count per half.
pub fn grid_indices(n: u32) -> (Vec<u32>, u32) {
    let nv = n + 1;
    let at = |i: u32, j: u32| i * nv + j;
    let mut lower = Vec::new();
    let mut upper = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
            if i >= j {
                lower.extend([a, b, c]);
            }
            if i > j {
                lower.extend([a, c, d]);
            }
            if i <= j {
                upper.extend([a, c, d]);
            }
            if i < j {
                upper.extend([a, b, c]);
            }
        }
    }
    let half = lower.len() as u32;
    debug_assert_eq!(lower.len(), upper.len());
    lower.extend(upper);
    (lower, half)
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn each_half_has_n_squared_triangles_inside_it() {
        for n in [2u32, 8, 32] {
            let (idx, half) = grid_indices(n);
            assert_eq!(half, 3 * n * n);
            assert_eq!(idx.len() as u32, 2 * half);
            let nv = n + 1;
            for (t, tri) in idx.chunks(3).enumerate() {
                let lower = (t as u32) < n * n;
                for &v in tri {
                    let (i, j) = (v / nv, v % nv);
                    assert!(if lower { i >= j } else { i <= j });
                }
            }
        }
    }
}
