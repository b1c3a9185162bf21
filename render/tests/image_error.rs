//! The image-error measures against known answers: a flat plane seen obliquely, its
//! depth made analytically, measured against the same plane raised by `delta` (every
//! pixel's error is the pinhole projection of that vertical step, worked out here
//! without the crate's camera code); PSNR of identical and of known-different images;
//! `unproject` inverting `project` at pixel centres; bad input as errors. On the GPU: a
//! frame of the in-memory planet of `examples/precision.rs` (deep levels, procedural
//! detail, three cube faces in view) read back, its depth checked against its cut and
//! measured against itself and its cut raised, and the same cut drawn in parts over one
//! another (bit-identical). The measures on rendered cuts of the
//! bundled repositories, streamed from a server, are in `tests/tests/image_error.rs`.
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../examples/precision.rs"]
mod precision;

use std::sync::Arc;

use glam::DVec3;
use precision::{FACE_SIDE, MadeUp, N, Planet, converge, patch_changes, places, view_at};
use quincunx_client::dag::Dag;
use quincunx_client::dag::Half;
use quincunx_render::domain::AffinePatch;
use quincunx_render::error::{error_map, error_map_with, geometric_error_with, recheck};
use quincunx_render::offscreen::{DepthReadback, OFFSCREEN_FORMAT, gpu_for_test};
use quincunx_render::{
    Camera, DepthImage, Geometry, Image, Offscreen, RendererConfig, SurfaceIndex, TerrainRenderer,
    WorldFrame, geometric_error, psnr_db, unproject,
};

const SIZE: [u32; 2] = [320, 200];

/// Whether two depth images hold the same bits at every pixel.
fn same_bits(a: &DepthImage, b: &DepthImage) -> bool {
    a.data.len() == b.data.len()
        && a.data
            .iter()
            .zip(&b.data)
            .all(|(x, y)| x.to_bits() == y.to_bits())
}

/// An oblique camera 120 m above the plane `z = 0`, looking down 15 degrees (the
/// horizon across the frame).
fn oblique() -> Camera {
    let pitch = 15f64.to_radians();
    let heading = 0.4f64;
    let horiz = DVec3::new(heading.sin(), heading.cos(), 0.0);
    Camera {
        eye: DVec3::new(1_000.0, -2_000.0, 120.0),
        forward: horiz * pitch.cos() - DVec3::Z * pitch.sin(),
        up: horiz * pitch.sin() + DVec3::Z * pitch.cos(),
        fov_y_rad: 50f64.to_radians(),
        viewport_px: SIZE,
    }
}

/// The pinhole camera written out: its orthonormal frame and the tangent of half the
/// vertical field of view.
struct Pinhole {
    eye: DVec3,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    tan: f64,
    aspect: f64,
}

impl Pinhole {
    fn of(c: &Camera) -> Pinhole {
        let forward = c.forward.normalize();
        let right = forward.cross(c.up).normalize();
        Pinhole {
            eye: c.eye,
            forward,
            right,
            up: right.cross(forward),
            tan: (c.fov_y_rad / 2.0).tan(),
            aspect: f64::from(c.viewport_px[0]) / f64::from(c.viewport_px[1]),
        }
    }

    /// The ray through pixel coordinates `(px, py)` (from the top-left corner).
    fn ray(&self, px: f64, py: f64) -> DVec3 {
        let [w, h] = SIZE.map(f64::from);
        let nx = 2.0 * px / w - 1.0;
        let ny = 1.0 - 2.0 * py / h;
        self.forward + self.right * (nx * self.tan * self.aspect) + self.up * (ny * self.tan)
    }

    /// Pixel coordinates of a world point.
    fn pixel(&self, p: DVec3) -> [f64; 2] {
        let q = p - self.eye;
        let [w, h] = SIZE.map(f64::from);
        let z = q.dot(self.forward);
        [
            w / 2.0 * (1.0 + q.dot(self.right) / z / (self.tan * self.aspect)),
            h / 2.0 * (1.0 - q.dot(self.up) / z / self.tan),
        ]
    }
}

/// The depth the renderer stores for a point at distance `z` along the view axis:
/// reversed Z, infinite far plane, near 0.05 m.
fn stored_depth(z: f64) -> f32 {
    (0.05 / z) as f32
}

/// The plane `z = 0` as the renderer would store it: each pixel centre's ray meets the
/// plane (or the sky: 0).
fn plane_depth(camera: &Camera) -> (DepthImage, Vec<Option<DVec3>>) {
    let pin = Pinhole::of(camera);
    let mut data = Vec::new();
    let mut ground = Vec::new();
    for y in 0..SIZE[1] {
        for x in 0..SIZE[0] {
            let d = pin.ray(f64::from(x) + 0.5, f64::from(y) + 0.5);
            if d.z < -1e-6 {
                let p = pin.eye + d * (-pin.eye.z / d.z);
                data.push(stored_depth((p - pin.eye).dot(pin.forward)));
                ground.push(Some(p));
            } else {
                data.push(0.0);
                ground.push(None);
            }
        }
    }
    let image = DepthImage {
        width: SIZE[0],
        height: SIZE[1],
        data,
    };
    (image, ground)
}

#[test]
fn error_on_a_raised_plane_is_the_projected_vertical_step() {
    let camera = oblique();
    let pin = Pinhole::of(&camera);
    let (depth, ground) = plane_depth(&camera);
    let sky = ground.iter().filter(|g| g.is_none()).count();
    assert!(
        sky > 1000 && sky < ground.len() / 2,
        "the view shows horizon and ground: {sky} sky pixels"
    );
    for delta in [1.0, 3.0, -2.0] {
        // The reference: the plane z = delta, met by the vertical line through X.
        let map =
            error_map_with(&camera, &depth, None, |x| Some(DVec3::new(x.x, x.y, delta))).unwrap();
        let mut worst: f64 = 0.0;
        let mut largest: f64 = 0.0;
        for (k, g) in ground.iter().enumerate() {
            let e = map.error_px[k];
            match g {
                None => assert!(e.is_nan(), "sky pixel {k}: {e}"),
                Some(p) => {
                    let (x, y) = ((k as u32 % SIZE[0]) as f64, (k as u32 / SIZE[0]) as f64);
                    let [qx, qy] = pin.pixel(*p + DVec3::Z * delta);
                    let want = (qx - (x + 0.5)).hypot(qy - (y + 0.5));
                    worst = worst.max((e - want).abs());
                    largest = largest.max(want);
                }
            }
        }
        println!("delta {delta} m: largest error {largest:.3} px, worst deviation {worst:.2e} px");
        assert!(largest > 1.0, "the step must be visible: {largest} px");
        assert!(
            worst < 1e-3,
            "delta {delta}: {worst} px from the closed form"
        );
        let s = map.summary();
        assert_eq!(s.pixels, ground.len() - sky);
        assert_eq!(s.pixels_without_reference, 0);
        assert!(s.p50_px > 0.0 && s.p50_px <= s.p99_px && s.p99_px <= s.max_px);
    }
    // Straight down from height H, a step delta at distance r off the nadir moves the
    // image by f r / (H - delta) - f r / H: the same measure agrees.
    let down = Camera {
        eye: DVec3::new(0.0, 0.0, 100.0),
        forward: DVec3::NEG_Z,
        up: DVec3::Y,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: SIZE,
    };
    let (depth, _) = plane_depth(&down);
    let map = error_map_with(&down, &depth, None, |x| Some(DVec3::new(x.x, x.y, 10.0))).unwrap();
    for (x, y) in [(0u32, 0u32), (17, 150), (160, 100), (319, 199)] {
        let r_px = (f64::from(x) + 0.5 - 160.0).hypot(f64::from(y) + 0.5 - 100.0);
        let want = r_px * 100.0 / 90.0 - r_px;
        let got = map.error_px[(y * SIZE[0] + x) as usize];
        assert!(
            (got - want).abs() < 1e-3,
            "({x}, {y}): {got} px, want {want}"
        );
    }
}

#[test]
fn a_reference_depth_bit_identical_to_the_test_depth_is_exactly_zero() {
    let camera = oblique();
    let (depth, _) = plane_depth(&camera);
    let s =
        geometric_error_with(&camera, &depth, Some(&depth), |x| Some(x + DVec3::Z * 5.0)).unwrap();
    assert!(s.pixels > 0);
    assert_eq!((s.max_px, s.mean_px), (0.0, 0.0));
    // One pixel changed by one bit of depth: measured against the raised plane.
    let mut test = depth.clone();
    let k = test.data.iter().rposition(|&d| d > 0.0).unwrap();
    test.data[k] = f32::from_bits(test.data[k].to_bits() + 1);
    let s =
        geometric_error_with(&camera, &test, Some(&depth), |x| Some(x + DVec3::Z * 5.0)).unwrap();
    let at = [k as u32 % SIZE[0], k as u32 / SIZE[0]];
    assert!(s.max_px > 0.1 && s.max_at == Some(at), "{s:?}");
}

#[test]
fn pixels_with_no_reference_are_counted_not_dropped() {
    let camera = oblique();
    let (depth, ground) = plane_depth(&camera);
    // A reference that only covers x < 1000 m.
    let s = geometric_error_with(&camera, &depth, None, |x| {
        (x.x < 1_000.0).then_some(DVec3::new(x.x, x.y, 1.0))
    })
    .unwrap();
    let covered = ground.iter().flatten().filter(|p| p.x < 1_000.0).count();
    let uncovered = ground.iter().flatten().count() - covered;
    assert!(covered > 100 && uncovered > 100);
    // Pixels on the border may fall either side with the rounding of the depth.
    assert!(s.pixels.abs_diff(covered) < 10, "{s:?} vs {covered}");
    assert_eq!(s.pixels + s.pixels_without_reference, covered + uncovered);
}

/// The plane `z = 0` over `[0, 4096]^2` m as a cut of two halves of one 4 x 4 patch.
fn flat_surface() -> SurfaceIndex {
    let world = WorldFrame {
        geometry: Geometry::Planar {
            metres_per_fine: 1.0,
            extent_fine: [4096, 4096],
        },
        value_scale_m: 1.0,
        value_offset_m: 0.0,
        n: 4,
        colour_n: 0,
    };
    let affine = AffinePatch {
        base: [0, 0, 0],
        e1: [1024, 0, 0],
        e2: [0, 1024, 0],
        level: 0,
    };
    let grid = Arc::new(vec![0; 25]);
    SurfaceIndex::from_patches(world, Half::BOTH.map(|h| (affine, h, Arc::clone(&grid))))
}

#[test]
fn recheck_moves_a_depth_off_the_surface_onto_it_and_keeps_real_errors() {
    let index = flat_surface();
    // The exact first hit of a ray, and a ray that misses (past the raster's edge).
    let hit = index
        .first_hit(DVec3::new(100.0, 200.0, 50.0), DVec3::new(1.0, 2.0, -1.0))
        .unwrap();
    assert!(
        (hit - DVec3::new(150.0, 300.0, 0.0)).length() < 1e-9,
        "{hit}"
    );
    assert!(
        index
            .first_hit(DVec3::new(100.0, 200.0, 50.0), DVec3::new(1.0, 2.0, 1.0))
            .is_none()
    );
    assert!(
        index
            .first_hit(DVec3::new(-10.0, 200.0, 50.0), DVec3::NEG_Z)
            .is_none()
    );
    // Looking down the plane at a slant from 100 m.
    let pitch = 40f64.to_radians();
    let camera = Camera {
        eye: DVec3::new(2_048.0, 1_000.0, 100.0),
        forward: DVec3::new(0.0, pitch.cos(), -pitch.sin()),
        up: DVec3::new(0.0, pitch.sin(), pitch.cos()),
        fov_y_rad: 50f64.to_radians(),
        viewport_px: SIZE,
    };
    let (mut depth, ground) = plane_depth(&camera);
    assert!(
        ground.iter().all(Option::is_some),
        "the plane fills the view"
    );
    // One pixel's depth 1.85x nearer than the plane, as a rasteriser may store for a
    // sliver it covers.
    let k = (SIZE[1] / 2 * SIZE[0] + SIZE[0] / 3) as usize;
    depth.data[k] *= 1.85;
    let mut map = error_map(&camera, &depth, None, &index).unwrap();
    let before = map.summary();
    assert!(before.max_px > 10.0 && before.over_1px == 1, "{before:?}");
    assert!(map.error_px[k] > 10.0);
    let done = recheck(&mut map, &camera, &depth, &index, &index, 1.0, 100).unwrap();
    assert_eq!(
        (done.checked, done.moved, done.no_hit, done.unchecked),
        (1, 1, 0, 0)
    );
    // The pixel exact, the others as the f32 depth of the plane rounds them.
    assert!(map.error_px[k] < 1e-9, "{}", map.error_px[k]);
    let after = map.summary();
    assert!(after.max_px < 1e-4, "{after:?}");
    // A surface truly 5 m off the reference: rechecked pixels keep their error.
    let raised = flat_surface().with_offset_m(5.0).unwrap();
    let depth = plane_depth(&camera).0;
    let mut map = error_map(&camera, &depth, None, &raised).unwrap();
    let want = map.clone();
    let over = want.summary().over_1px;
    assert!(over > 1_000, "{over}");
    let done = recheck(&mut map, &camera, &depth, &raised, &index, 1.0, 50).unwrap();
    assert_eq!(
        (done.checked, done.moved, done.unchecked),
        (50, 0, over - 50)
    );
    for (a, b) in map.error_px.iter().zip(&want.error_px) {
        assert!((a - b).abs() < 1e-4, "{a} against {b}");
    }
}

#[test]
fn unproject_inverts_project_at_pixel_centres() {
    let camera = oblique();
    let mut worst: f64 = 0.0;
    for (x, y) in [(0, 0), (319, 199), (160, 100), (3, 170), (301, 11)] {
        for depth in [1.0f32, 0.3, 1e-3, 1e-6, 1e-9] {
            let p = unproject(&camera, SIZE, x, y, depth).unwrap();
            let q = camera.project(p).unwrap();
            let dx = (q[0] - (f64::from(x) + 0.5)).abs();
            let dy = (q[1] - (f64::from(y) + 0.5)).abs();
            let dz = (q[2] - f64::from(depth)).abs() / f64::from(depth);
            worst = worst.max(dx).max(dy);
            assert!(
                dx < 1e-6 && dy < 1e-6 && dz < 1e-9,
                "({x}, {y}, {depth}): {q:?}"
            );
        }
    }
    println!("unproject -> project: worst {worst:.2e} px");
    for bad in [0.0, -0.5, f32::NAN, f32::INFINITY] {
        assert_eq!(unproject(&camera, SIZE, 10, 10, bad), None, "{bad}");
    }
    assert_eq!(unproject(&camera, [0, 10], 0, 0, 0.5), None);
}

#[test]
fn psnr_is_infinite_for_identical_images_and_closed_form_otherwise() {
    let (w, h) = (64u32, 48u32);
    let a = Image {
        width: w,
        height: h,
        rgba: (0..w * h * 4).map(|k| (k * 7 % 251) as u8).collect(),
    };
    assert_eq!(psnr_db(&a, &a).unwrap(), f64::INFINITY);
    // Alpha is ignored.
    let mut b = a.clone();
    b.rgba
        .iter_mut()
        .skip(3)
        .step_by(4)
        .for_each(|x| *x ^= 0xFF);
    assert_eq!(psnr_db(&a, &b).unwrap(), f64::INFINITY);
    // Red off by 10 everywhere, green off by 20 on every other pixel: MSE over the
    // three channels = (100 + 400 / 2) / 3.
    let mut c = a.clone();
    for (k, px) in c.rgba.chunks_exact_mut(4).enumerate() {
        px[0] = if px[0] >= 10 { px[0] - 10 } else { px[0] + 10 };
        if k % 2 == 0 {
            px[1] = if px[1] >= 20 { px[1] - 20 } else { px[1] + 20 };
        }
    }
    let mse = (100.0 + 400.0 / 2.0) / 3.0;
    let want = 10.0 * (255.0f64 * 255.0 / mse).log10();
    let got = psnr_db(&a, &c).unwrap();
    assert!((got - want).abs() < 1e-12, "{got} dB, want {want}");
    assert!((psnr_db(&c, &a).unwrap() - got).abs() < 1e-12);
}

#[test]
fn mismatched_inputs_are_errors() {
    let a = Image {
        width: 4,
        height: 4,
        rgba: vec![0; 64],
    };
    let b = Image {
        width: 4,
        height: 3,
        rgba: vec![0; 48],
    };
    assert!(psnr_db(&a, &b).is_err());
    let short = Image {
        width: 4,
        height: 4,
        rgba: vec![0; 60],
    };
    assert!(psnr_db(&a, &short).is_err());
    let camera = oblique();
    let (depth, _) = plane_depth(&camera);
    let small = DepthImage {
        width: 4,
        height: 4,
        data: vec![0.5; 16],
    };
    let up = |x: DVec3| Some(x);
    assert!(geometric_error_with(&camera, &small, None, up).is_err());
    assert!(geometric_error_with(&camera, &depth, Some(&small), up).is_err());
    let mut ragged = depth.clone();
    ragged.data.pop();
    let e = geometric_error_with(&camera, &ragged, None, up).unwrap_err();
    assert!(e.to_string().contains("values"), "{e}");
}

#[test]
fn a_planet_frame_reads_back_onto_its_cut_and_measures_zero_against_itself() {
    let Some(gpu) =
        gpu_for_test("a_planet_frame_reads_back_onto_its_cut_and_measures_zero_against_itself")
            .unwrap()
    else {
        return;
    };
    const MAGENTA: [u8; 3] = [255, 0, 255];
    let planet = Planet::new(FACE_SIDE, N).unwrap();
    // 20 km over the cube corner, looking 30 degrees down: three faces, the horizon.
    let corner = places()[3];
    let mut view = view_at(&corner, 0.0, 20_000.0, -30.0);
    view.viewport_px = [480, 270];
    let mut dag = Dag::new(Arc::clone(&planet.refiner));
    let mut source = MadeUp::new(Arc::clone(&planet.refiner));
    converge(&mut dag, planet.world, &view, &mut source).unwrap();
    let camera = Camera::from_view(&view);
    let config = RendererConfig {
        gpu_budget_bytes: 1 << 30,
        max_uploads_per_frame: 1 << 16,
        colour_format: OFFSCREEN_FORMAT,
        ..Default::default()
    };
    let mut renderer = TerrainRenderer::new(&gpu.device, planet.frame, config.clone()).unwrap();
    let changes = patch_changes(&mut dag);
    let cut = changes.entered.clone();
    renderer.apply(dag.refiner(), None, changes).unwrap();
    let mut stats = renderer.prepare(&gpu.queue, &camera);
    while stats.pending > 0 {
        stats = renderer.prepare(&gpu.queue, &camera);
    }
    let offscreen = Offscreen::new(&gpu, view.viewport_px).unwrap();
    offscreen
        .render(&gpu, MAGENTA, |pass| renderer.draw(pass))
        .unwrap();
    let image = offscreen.read(&gpu).unwrap();
    let depth = offscreen.read_depth(&gpu).unwrap();

    // The same cut drawn in three parts, each by a renderer of its own, depth-tested over
    // the last (how `quincunx trade` draws references larger than a pool): the same
    // pixels and depths, bit for bit.
    let parted = Offscreen::new(&gpu, view.viewport_px).unwrap();
    for (k, part) in cut.chunks(cut.len().div_ceil(3)).enumerate() {
        let mut renderer = TerrainRenderer::new(&gpu.device, planet.frame, config.clone()).unwrap();
        let changes = quincunx_client::dag::PatchChanges {
            entered: part.to_vec(),
            left: Vec::new(),
        };
        renderer.apply(dag.refiner(), None, changes).unwrap();
        while renderer.prepare(&gpu.queue, &camera).pending > 0 {}
        let draw = |pass: &mut wgpu::RenderPass<'_>| renderer.draw(pass);
        if k == 0 {
            parted.render(&gpu, MAGENTA, draw).unwrap();
        } else {
            parted.render_over(&gpu, draw).unwrap();
        }
    }
    assert!(cut.len() >= 3);
    assert!(
        parted.read(&gpu).unwrap().rgba == image.rgba,
        "parts drew other pixels"
    );
    let parted_depth = parted.read_depth(&gpu).unwrap();
    assert!(same_bits(&parted_depth, &depth), "parts left other depths");
    // Read by a draw (the path of adapters without depth copies, wgpu's GL one): the
    // same bits as the copy where the adapter has both.
    let drawn = offscreen
        .read_depth_with(&gpu, DepthReadback::Draw)
        .unwrap();
    assert!(
        same_bits(&drawn, &depth),
        "depth read by a draw differs from read_depth"
    );
    if gpu
        .adapter
        .get_downlevel_capabilities()
        .flags
        .contains(wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES)
    {
        let copied = offscreen
            .read_depth_with(&gpu, DepthReadback::Copy)
            .unwrap();
        assert!(
            same_bits(&copied, &drawn),
            "depth read by a draw differs from the copy"
        );
        println!("depth read by a draw: bit-identical to the copy");
    }
    let index = SurfaceIndex::from_dag(&dag, &planet.world);
    assert_eq!((index.patches(), index.skipped()), (stats.patches, 0));

    // Depth 0 exactly on the background; terrain pixels unproject onto the cut.
    let [w, h] = view.viewport_px;
    let (mut terrain, mut sky, mut off) = (0usize, 0usize, Vec::new());
    let mut faces = std::collections::HashSet::new();
    for y in 0..h {
        for x in 0..w {
            let d = depth.at(x, y).unwrap();
            let background = image.pixel(x, y)[..3] == MAGENTA;
            assert_eq!(d == 0.0, background, "({x}, {y}): depth {d}");
            if background {
                sky += 1;
                continue;
            }
            terrain += 1;
            let p = unproject(&camera, [w, h], x, y, d).unwrap();
            let r = index.along(p, index.up(p)).unwrap();
            off.push((p - r).length() / (p - camera.eye).length());
            let a = p.abs();
            faces.insert(if a.x >= a.y && a.x >= a.z {
                0
            } else if a.y >= a.z {
                1
            } else {
                2
            });
        }
    }
    off.sort_by(f64::total_cmp);
    let (p99, max) = (off[off.len() * 99 / 100], off[off.len() - 1]);
    println!(
        "{} patches, {terrain} terrain and {sky} sky pixels on {} faces; unprojected within \
         {p99:.2e} (p99), {max:.2e} (max) of their distance from the cut",
        stats.patches,
        faces.len()
    );
    assert!(terrain > 50_000 && sky > 1_000 && faces.len() == 3);
    // Depth quantisation leaves about 1e-7 of the distance; silhouette pixels more (see
    // tests/tests/image_error.rs).
    assert!(p99 < 1e-6 && max < 1e-3, "{p99:.3e} {max:.3e}");

    let same = geometric_error(&camera, &depth, Some(&depth), &index).unwrap();
    assert_eq!((same.pixels, same.max_px), (terrain, 0.0));
    let quantised = geometric_error(&camera, &depth, None, &index).unwrap();
    println!("without the reference depth: {quantised:?}");
    assert_eq!(quantised.pixels, terrain);
    assert!(quantised.p99_px < 1e-3, "{quantised:?}");

    // Raised by 100 m: each pixel's error is the projection of its reference point
    // raised by that much.
    let raise_m = 100.0;
    let map = error_map(
        &camera,
        &depth,
        None,
        &index.clone().with_offset_m(raise_m).unwrap(),
    )
    .unwrap();
    let mut worst_rel = 0.0f64;
    for y in 0..h {
        for x in 0..w {
            let k = (y * w + x) as usize;
            let Some(p) = unproject(&camera, [w, h], x, y, depth.data[k]) else {
                continue;
            };
            let up = index.up(p);
            let r = index.along(p, up).unwrap() + up * raise_m;
            let (a, b) = (camera.project(p).unwrap(), camera.project(r).unwrap());
            let want = (a[0] - b[0]).hypot(a[1] - b[1]);
            worst_rel = worst_rel.max((map.error_px[k] - want).abs() / want.max(0.01));
        }
    }
    let s = map.summary();
    println!("raised {raise_m} m: {s:?}, within {worst_rel:.2e} of the raised points");
    assert!(s.pixels == terrain && s.p50_px > 0.5, "{s:?}");
    assert!(worst_rel < 0.01, "{worst_rel:.3e}");
}
