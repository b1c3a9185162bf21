//! Vertex precision of the GPU path on an Earth-sized planet (issue 20, item 8).
//!
//! `cargo run --release -p quincunx-render --example precision -- [--json]`
//!
//! A planet of radius 6,371 km is made in memory: six root grids from
//! `encode_sphere` of a small cube raster with plausible heights, placed in the finest id
//! space this example can afford (`FACE_SIDE`), with seeded noise as the details of the
//! coded levels and [`Procedural::Noise`] below them down to the id space's deepest
//! level. For each case (camera height x place x pitch) the DAG is refined at 1 px until
//! converged, the cut is uploaded to a [`TerrainRenderer`], and the clip positions the
//! vertex shader computes are read back from the GPU. Every vertex inside the clip
//! volume is compared, in pixels, with the f64 reference projection
//! ([`Camera::project`] of [`WorldFrame::point`]). Bar: < 0.5 px everywhere.
//!
//! The depth limit: a planet's id space is set by its face side (`S = face_side / 2`
//! id units, deepest level `2 log2(S) + 1`), and the coded geometry enumerates every
//! coded diamond, so the finest reachable vertex spacing is about
//! `face edge / (face_side N)`; see `spacing_m` in the output.
#![allow(clippy::unwrap_used, clippy::expect_used, dead_code)]

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::dag::Dag;
use quincunx_client::domain::Domain;
use quincunx_client::refine::{Availability, DetailSource, Refinement, SystemClock};
use quincunx_client::session::PatchChanges;
use quincunx_client::view::{SphereWorld, View};
use quincunx_codec::diamond::SphereId;
use quincunx_codec::diamond::sphere::cube_to_unit_sphere;
use quincunx_codec::encode::{CubeGrid, EncodeOptions, RateMode, encode_sphere};
use quincunx_codec::incremental::{Details, Procedural, Refiner, SphereRefiner};
use quincunx_codec::sphere_raster::SphereGeometry;
use quincunx_render::domain::AffinePatch;
use quincunx_render::offscreen::OFFSCREEN_FORMAT;
use quincunx_render::renderer::{CapturedVertex, PatchKey};
use quincunx_render::{Camera, Gpu, RenderDomain, RendererConfig, TerrainRenderer, WorldFrame};

type Error = Box<dyn std::error::Error>;

/// Radius of the planet (metres).
pub const RADIUS_M: f64 = 6_371_000.0;
/// Diamond size.
pub const N: usize = 128;
/// Samples per face side of the id space (`S = FACE_SIDE / 2`).
pub const FACE_SIDE: usize = 16_384;
/// Metres per height unit.
pub const QUANTUM_M: f64 = 0.01;
/// Procedural detail amplitude below the coded levels (height units).
pub const PROCEDURAL_AMPLITUDE: i32 = 5;
/// Viewport and field of view of every case.
pub const VIEWPORT_PX: [u32; 2] = [1920, 1080];
/// Vertical field of view, degrees.
pub const FOV_DEG: f64 = 60.0;

/// The in-memory planet.
pub struct Planet {
    /// Its refiner (coded levels plus procedural ones).
    pub refiner: Arc<SphereRefiner>,
    /// Its world mapping.
    pub world: SphereWorld,
    /// The renderer's view of its geometry.
    pub frame: WorldFrame,
}

/// Plausible heights (metres) as a function of direction: continents and ranges.
fn height_at(d: DVec3) -> f64 {
    let a = (d.x * 3.1 + 0.4).sin() * (d.y * 2.7 - 0.3).cos() * (d.z * 3.7 + 1.1).sin();
    let b = (d.x * 11.0 + d.z * 7.0).sin() * (d.y * 13.0 - d.x * 5.0).cos();
    1200.0 * a + 600.0 * b + 200.0
}

impl Planet {
    /// Encodes six root grids, places them in the id space of `face_side` and extends
    /// the refiner procedurally to the id space's deepest level.
    pub fn new(face_side: usize, n: usize) -> Result<Planet, Error> {
        let small = 2 * n;
        let geom = SphereGeometry::new(small, n)?;
        let w = small + 1;
        let mut values_m = vec![0.0; geom.cube_len()];
        for f in 0..6u8 {
            for v in 0..w {
                for u in 0..w {
                    let p = geom.sample_position(f, u, v).map(|x| x as f64);
                    let d = DVec3::from_array(cube_to_unit_sphere(p));
                    values_m[geom.cube_index(f, u, v)] = height_at(d);
                }
            }
        }
        let grid = CubeGrid {
            face_side: small,
            values_m,
            quantum_m: Some(QUANTUM_M),
        };
        let opts = EncodeOptions {
            n,
            mode: RateMode::RmsM(1.0),
            sparse: false,
            rdo: Default::default(),
        };
        let enc = encode_sphere(&grid, opts)?;
        let coded = SphereRefiner::new(
            face_side,
            n,
            None,
            enc.steps.clone(),
            enc.model.clone(),
            enc.roots.clone(),
        )?;
        let max_level = coded.domain().max_level() as usize;
        let extra = max_level - coded.detail_levels();
        let refiner = coded.with_procedural_levels(
            extra,
            Procedural::Noise {
                amplitude: PROCEDURAL_AMPLITUDE,
                seed: 20,
            },
        )?;
        let lowest_m = enc
            .roots
            .iter()
            .flatten()
            .map(|&v| enc.value_offset_m + f64::from(v) * enc.value_scale_m)
            .fold(f64::INFINITY, f64::min);
        let world = SphereWorld {
            radius_m: RADIUS_M,
            half_side: refiner.domain().size() as f64,
            value_scale_m: enc.value_scale_m,
            value_offset_m: enc.value_offset_m,
            occluder_radius_m: 0.0,
        };
        // Horizon culling below the lowest possible surface (coded noise is bounded by
        // `CODED_AMPLITUDE` summed over levels: about 2.5 km).
        let world = SphereRefiner::with_lowest_height(world, lowest_m - 4_000.0);
        let frame = refiner.world_frame(&world, 0);
        Ok(Planet {
            refiner: Arc::new(refiner),
            world,
            frame,
        })
    }
}

/// Largest detail of the coded levels at level 0 (height units); halves every two
/// levels.
const CODED_AMPLITUDE: f64 = 40_000.0;

fn splitmix64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Details of the coded levels: seeded noise shrinking with the level (a fractal);
/// procedural levels get the refiner's own noise (`Ready(None)`).
pub struct MadeUp {
    refiner: Arc<SphereRefiner>,
}

impl MadeUp {
    /// The source for `refiner`.
    pub fn new(refiner: Arc<SphereRefiner>) -> MadeUp {
        MadeUp { refiner }
    }
}

impl DetailSource<SphereId> for MadeUp {
    fn details(&mut self, id: SphereId, _priority: f64) -> Availability<SphereId> {
        let Some(info) = self.refiner.info(id) else {
            return Availability::Ready(None);
        };
        if info.procedural {
            return Availability::Ready(None);
        }
        let n = self.refiner.n();
        let amplitude = (CODED_AMPLITUDE * 0.5f64.powf(info.level as f64 / 2.0)).max(2.0);
        let mut state = id.c.iter().fold(7u64, |h, &x| splitmix64(h ^ x as u64));
        let h = (0..n * n)
            .map(|_| {
                state = splitmix64(state);
                let u = (state >> 11) as f64 / (1u64 << 53) as f64;
                ((u * 2.0 - 1.0) * amplitude).round() as i32
            })
            .collect();
        Availability::Ready(Some(Arc::new(Details {
            id,
            h,
            child_classes: Vec::new(),
            empty_children: Vec::new(),
            child_profiles: Vec::new(),
        })))
    }
}

/// Refines `dag` for `view` until converged.
pub fn converge<R: Domain>(
    dag: &mut Dag<R>,
    world: R::World,
    view: &View,
    source: &mut dyn DetailSource<R::Id>,
) -> Result<(), Error> {
    let mut refinement = Refinement::default();
    let clock = SystemClock(Instant::now());
    for _ in 0..400 {
        let s = refinement.update(dag, view, world, source, &clock, Duration::from_secs(600))?;
        if s.converged {
            return Ok(());
        }
    }
    Err("the refinement did not converge".into())
}

/// Where a camera stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Place {
    /// Name in the output.
    pub name: &'static str,
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
}

/// The places of the cases: a face centre on the equator, a pole, a cube edge (between
/// the +x and +y faces) and a cube corner (direction (1, 1, 1)).
pub fn places() -> [Place; 4] {
    [
        Place {
            name: "equator",
            lat_deg: 0.0,
            lon_deg: 0.0,
        },
        Place {
            name: "pole",
            lat_deg: 90.0,
            lon_deg: 0.0,
        },
        Place {
            name: "cube edge",
            lat_deg: 0.0,
            lon_deg: 45.0,
        },
        Place {
            name: "cube corner",
            lat_deg: (1.0f64 / 3.0f64.sqrt()).asin().to_degrees(),
            lon_deg: 45.0,
        },
    ]
}

/// The view from `height_m` above `ground_m` at `place`, heading north, `pitch_deg`.
pub fn view_at(place: &Place, ground_m: f64, height_m: f64, pitch_deg: f64) -> View {
    let (la, lo) = (place.lat_deg.to_radians(), place.lon_deg.to_radians());
    let up = DVec3::new(la.cos() * lo.cos(), la.cos() * lo.sin(), la.sin());
    let mut north = (DVec3::Z - up * up.z).normalize_or_zero();
    if north == DVec3::ZERO {
        north = DVec3::new(-lo.cos(), -lo.sin(), 0.0);
    }
    let p = pitch_deg.to_radians();
    let forward = north * p.cos() + up * p.sin();
    let cam_up = -north * p.sin() + up * p.cos();
    let eye = up * (RADIUS_M + ground_m + height_m);
    View {
        eye,
        target: eye + forward * height_m.max(1.0),
        up: cam_up,
        fov_y_rad: FOV_DEG.to_radians(),
        viewport_px: VIEWPORT_PX,
        tolerance_px: 1.0,
    }
}

/// The height (metres) of the cut vertex closest in direction to `dir`.
pub fn ground_m(dag: &Dag<SphereRefiner>, frame: &WorldFrame, dir: DVec3) -> Option<f64> {
    let refiner = dag.refiner();
    let n = refiner.n();
    let dir = dir.normalize();
    let to_dir = |p: [i64; 3]| DVec3::from_array(cube_to_unit_sphere(p.map(|x| x as f64)));
    let mut best: Option<(f64, i32)> = None;
    for (id, half) in dag.cut() {
        let node = dag.node(id)?;
        let centre = to_dir(id.c);
        let cap = node
            .corners
            .iter()
            .map(|&c| centre.angle_between(to_dir(c)))
            .fold(0.0, f64::max);
        if centre.angle_between(dir) > cap * 1.2 + 1e-9 {
            continue;
        }
        let Some(a) = refiner.affine(id, &node.corners, half) else {
            continue;
        };
        for i in 0..=n {
            for j in 0..=n {
                if !half.contains(i, j) {
                    continue;
                }
                let angle = to_dir(a.at(i, j)).angle_between(dir);
                if best.is_none_or(|(b, _)| angle < b) {
                    best = Some((angle, node.grid[i * (n + 1) + j]));
                }
            }
        }
    }
    best.map(|(_, v)| frame.value_offset_m + f64::from(v) * frame.value_scale_m)
}

/// The cut's changes as the renderer takes them.
pub fn patch_changes<R: Domain>(dag: &mut Dag<R>) -> PatchChanges<R::Id> {
    dag.take_patch_changes()
}

/// A converged cut as the GPU computed it.
pub struct Captured<I> {
    /// Every vertex of every drawn patch.
    pub vertices: Vec<CapturedVertex<I>>,
    /// Each drawn patch's exact affine map and grid.
    pub patches: HashMap<PatchKey<I>, (AffinePatch, Arc<Vec<i32>>)>,
}

/// Patches per renderer: the capture binds every slot up to the highest drawn one in
/// one storage binding (`max_storage_buffer_binding_size`, 128 MiB on lavapipe), so a
/// large cut is drawn by several renderers in turn. The clip position of a vertex does
/// not depend on its slot or on the other patches.
fn patches_per_capture(gpu: &Gpu, frame: &WorldFrame) -> usize {
    let nv2 = u64::from((frame.n + 1) * (frame.n + 1));
    let limit = gpu.device.limits().max_storage_buffer_binding_size;
    ((limit / (nv2 * 16)) as usize).clamp(1, 4096)
}

/// Uploads the cut of `dag` to renderers, prepares a frame for `camera` and reads back
/// the clip positions of every vertex.
pub fn capture<R: RenderDomain>(
    gpu: &Gpu,
    dag: &mut Dag<R>,
    frame: WorldFrame,
    camera: &Camera,
) -> Result<Captured<R::Id>, Error> {
    let changes = patch_changes(dag);
    let mut patches = HashMap::new();
    for p in &changes.entered {
        let a = dag
            .refiner()
            .affine(p.id, &p.corners, p.half)
            .ok_or("a patch is not affine in fine units")?;
        patches.insert((p.id, p.half), (a, Arc::clone(&p.grid)));
    }
    let mut vertices = Vec::new();
    for chunk in changes.entered.chunks(patches_per_capture(gpu, &frame)) {
        let config = RendererConfig {
            gpu_budget_bytes: 1 << 30,
            max_uploads_per_frame: 1 << 16,
            colour_format: OFFSCREEN_FORMAT,
            ..Default::default()
        };
        let mut renderer = TerrainRenderer::new(&gpu.device, frame, config)?;
        let part = PatchChanges {
            entered: chunk.to_vec(),
            left: Vec::new(),
        };
        renderer.apply(dag.refiner(), None, part)?;
        let mut stats = renderer.prepare(&gpu.queue, camera);
        while stats.pending > 0 {
            stats = renderer.prepare(&gpu.queue, camera);
        }
        if stats.missing > 0 || stats.patches != chunk.len() {
            return Err(format!(
                "{} of {} patches drawn (budget {} patches)",
                stats.patches,
                chunk.len(),
                renderer.capacity()
            )
            .into());
        }
        vertices.extend(renderer.capture_clip_positions(gpu)?);
    }
    Ok(Captured { vertices, patches })
}

/// One case's measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct CaseResult {
    /// Camera height above the ground (metres).
    pub height_m: f64,
    /// Place name.
    pub place: &'static str,
    /// Pitch, degrees.
    pub pitch_deg: f64,
    /// Deepest level in view.
    pub level: u32,
    /// Vertices in view.
    pub vertices: usize,
    /// Largest distance between the GPU's and the reference's pixel positions.
    pub max_error_px: f64,
    /// Finest vertex spacing in view (metres).
    pub spacing_m: f64,
    /// Patches drawn.
    pub patches: usize,
}

/// Pixel position of a clip position (`None` outside the clip volume).
pub fn pixel_of(clip: [f32; 4], viewport: [u32; 2]) -> Option<[f64; 2]> {
    let [x, y, z, w] = clip.map(f64::from);
    let inside = w > 0.0 && x.abs() <= w && y.abs() <= w && (0.0..=w).contains(&z);
    let [vw, vh] = viewport.map(f64::from);
    inside.then(|| [(x / w * 0.5 + 0.5) * vw, (0.5 - y / w * 0.5) * vh])
}

/// Compares every captured vertex in view with the f64 reference projection.
pub fn measure<I: Copy + Eq + std::hash::Hash>(
    captured: &Captured<I>,
    frame: &WorldFrame,
    camera: &Camera,
) -> Result<(usize, f64, u32, f64), Error> {
    let n = frame.n as usize;
    let mut count = 0;
    let mut max_err = 0.0f64;
    let mut level = 0;
    let mut spacing = f64::INFINITY;
    let mut spacing_of = HashMap::new();
    for &(key, i, j, clip) in &captured.vertices {
        let Some(gpu_px) = pixel_of(clip, camera.viewport_px) else {
            continue;
        };
        let (a, grid) = captured
            .patches
            .get(&key)
            .ok_or("a captured patch the cut does not hold")?;
        let v = grid[i * (n + 1) + j];
        let reference = camera
            .project(frame.point(a.at(i, j), v))
            .ok_or("a vertex in the clip volume is behind the reference camera")?;
        let err = (gpu_px[0] - reference[0]).hypot(gpu_px[1] - reference[1]);
        max_err = max_err.max(if err.is_nan() { f64::INFINITY } else { err });
        count += 1;
        level = level.max(a.level);
        let s = *spacing_of.entry(key).or_insert_with(|| {
            let p = frame.point(a.base, v);
            let q = frame.point([0, 1, 2].map(|k| a.base[k] + a.e1[k]), v);
            (q - p).length()
        });
        spacing = spacing.min(s);
    }
    Ok((count, max_err, level, spacing))
}

/// Runs one case on a fresh DAG.
pub fn run_case(
    gpu: &Gpu,
    planet: &Planet,
    place: &Place,
    height_m: f64,
    pitch_deg: f64,
) -> Result<CaseResult, Error> {
    let mut dag = Dag::new(Arc::clone(&planet.refiner));
    let mut source = MadeUp::new(Arc::clone(&planet.refiner));
    let mut ground = 0.0;
    let mut view = view_at(place, ground, height_m, pitch_deg);
    // The camera stands on the refined ground: move it until the ground under it
    // settles (the cut depends on the camera).
    for _ in 0..6 {
        converge(&mut dag, planet.world, &view, &mut source)?;
        let g = ground_m(&dag, &planet.frame, view.eye).ok_or("no ground under the camera")?;
        let settled = (g - ground).abs() <= 1e-3 * height_m.max(1.0);
        ground = g;
        view = view_at(place, ground, height_m, pitch_deg);
        if settled {
            break;
        }
    }
    converge(&mut dag, planet.world, &view, &mut source)?;
    let camera = Camera::from_view(&view);
    let captured = capture(gpu, &mut dag, planet.frame, &camera)?;
    let (vertices, max_error_px, level, spacing_m) = measure(&captured, &planet.frame, &camera)?;
    Ok(CaseResult {
        height_m,
        place: place.name,
        pitch_deg,
        level,
        vertices,
        max_error_px,
        spacing_m,
        patches: captured.patches.len(),
    })
}

/// "YYYY-MM-DDTHH:MM:SSZ" of now.
pub fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil from days (H. Hinnant).
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

fn main() -> Result<(), Error> {
    let json = std::env::args().skip(1).any(|a| a == "--json");
    if let Some(bad) = std::env::args().skip(1).find(|a| a != "--json") {
        return Err(format!("unknown argument {bad:?} (usage: precision [--json])").into());
    }
    let gpu = Gpu::headless()?;
    let planet = Planet::new(FACE_SIDE, N)?;
    let mut cases = Vec::new();
    for height_m in [1.0, 100.0, 10_000.0, 1_000_000.0, 100_000_000.0] {
        for place in places() {
            // Oblique views look towards the horizon; from 100,000 km the planet is about
            // 7 degrees across, so the oblique view tilts by 5 degrees only to keep it in
            // the frame.
            let oblique = if height_m >= 1e7 { -85.0 } else { -20.0 };
            for pitch_deg in [-90.0, oblique] {
                let start = Instant::now();
                let c = run_case(&gpu, &planet, &place, height_m, pitch_deg)?;
                if c.vertices == 0 {
                    return Err(format!(
                        "{} m over {} at pitch {pitch_deg}: no vertex in view, nothing measured",
                        height_m, c.place
                    )
                    .into());
                }
                if !json {
                    println!(
                        "{:>12} m  {:<12} pitch {:>4}  level {:>2}  spacing {:>12.4} m  {:>9} vertices  {:>5} patches  max error {:.4} px  ({:.1} s)",
                        c.height_m,
                        c.place,
                        c.pitch_deg,
                        c.level,
                        c.spacing_m,
                        c.vertices,
                        c.patches,
                        c.max_error_px,
                        start.elapsed().as_secs_f64()
                    );
                }
                cases.push(c);
            }
        }
    }
    let max_error_px = cases.iter().map(|c| c.max_error_px).fold(0.0, f64::max);
    if json {
        let out = serde_json::json!({
            "date": utc_now(),
            "max_error_px": max_error_px,
            "bar_px": 0.5,
            "n": N,
            "face_side": FACE_SIDE,
            "deepest_level": planet.refiner.levels(),
            "viewport_px": VIEWPORT_PX,
            "fov_deg": FOV_DEG,
            "cases": cases.iter().map(|c| serde_json::json!({
                "height_m": c.height_m,
                "where": c.place,
                "pitch_deg": c.pitch_deg,
                "level": c.level,
                "vertices": c.vertices,
                "patches": c.patches,
                "max_error_px": c.max_error_px,
                "spacing_m": c.spacing_m,
            })).collect::<Vec<_>>(),
            "adapter": gpu.describe(),
        });
        println!("{out}");
    } else {
        println!(
            "max error {max_error_px:.4} px over {} cases (bar 0.5 px); adapter {}",
            cases.len(),
            gpu.describe()
        );
    }
    Ok(())
}
