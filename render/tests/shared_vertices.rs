//! Crack-free on the GPU: a vertex shared by several drawn patches (the same exact fine
//! point) gets bit-identical clip coordinates from the vertex shader in all of them, on
//! a planet around a cube corner (patches of three faces meet there) and on a plane.
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../examples/precision.rs"]
mod precision;

use std::collections::HashMap;
use std::sync::Arc;

use glam::DVec3;
use precision::{Captured, FACE_SIDE, MadeUp, N, Planet, capture, converge, places, view_at};
use quincunx_client::dag::Dag;
use quincunx_client::refine::{Availability, DetailSource};
use quincunx_client::view::{PlanarWorld, View};
use quincunx_codec::diamond::PlanarId;
use quincunx_codec::encode::{EncodeOptions, FromEncoded, Grid, RateMode, encode};
use quincunx_codec::incremental::PlanarRefiner;
use quincunx_render::offscreen::gpu_for_test_with;
use quincunx_render::{Camera, RenderDomain};

/// Points shared by two or more patches, points shared by two or more diamonds, and the
/// shared points whose clip coordinates differ in some bit.
fn shared<I: Copy + Eq + std::hash::Hash + std::fmt::Debug>(
    c: &Captured<I>,
) -> (usize, usize, Vec<[i64; 3]>) {
    let mut by_point: HashMap<[i64; 3], Vec<(I, [u32; 4])>> = HashMap::new();
    for &(key, i, j, clip) in &c.vertices {
        let (a, _) = &c.patches[&key];
        by_point
            .entry(a.at(i, j))
            .or_default()
            .push((key.0, clip.map(f32::to_bits)));
    }
    let mut patches = 0;
    let mut diamonds = 0;
    let mut differ = Vec::new();
    for (p, list) in &by_point {
        if list.len() < 2 {
            continue;
        }
        patches += 1;
        if list.iter().any(|(id, _)| *id != list[0].0) {
            diamonds += 1;
        }
        if list.iter().any(|(_, bits)| *bits != list[0].1) {
            differ.push(*p);
        }
    }
    (patches, diamonds, differ)
}

#[test]
fn shared_planet_vertices_are_bit_identical_across_cube_faces() {
    let Some(gpu) = gpu_for_test_with(
        "shared_planet_vertices_are_bit_identical_across_cube_faces",
        wgpu::Features::VERTEX_WRITABLE_STORAGE,
    )
    .unwrap() else {
        return;
    };
    let planet = Planet::new(FACE_SIDE, N).unwrap();
    let corner = places()[3];
    let view = view_at(&corner, 0.0, 200_000.0, -90.0);
    let mut dag = Dag::new(Arc::clone(&planet.refiner));
    let mut source = MadeUp::new(Arc::clone(&planet.refiner));
    converge(&mut dag, planet.world, &view, &mut source).unwrap();
    let c = capture(&gpu, &mut dag, planet.frame, &Camera::from_view(&view)).unwrap();
    let (patches, diamonds, differ) = shared(&c);
    // Points on a cube edge (two coordinates at +-S) shared by patches of two faces.
    let s = match planet.frame.geometry {
        quincunx_render::Geometry::Planet { half_side_fine, .. } => half_side_fine,
        _ => unreachable!(),
    };
    let on_edge = c
        .vertices
        .iter()
        .filter(|(key, i, j, _)| {
            let p = c.patches[key].0.at(*i, *j);
            p.iter().filter(|x| x.abs() == s).count() >= 2
        })
        .count();
    println!(
        "{} patches, {patches} shared points, {diamonds} across diamonds, {on_edge} edge vertices",
        c.patches.len()
    );
    assert!(
        diamonds > 100 && on_edge > 10,
        "too few shared vertices to test"
    );
    assert!(
        differ.is_empty(),
        "{} shared points differ, e.g. {:?}",
        differ.len(),
        &differ[..differ.len().min(5)]
    );
}

struct Local {
    blobs: HashMap<Vec<u8>, Vec<u8>>,
    refiner: Arc<PlanarRefiner>,
}

impl DetailSource for Local {
    fn details(&mut self, id: PlanarId, _priority: f64) -> Availability {
        let info = self.refiner.info(id).unwrap();
        if info.procedural {
            return Availability::Ready(None);
        }
        let blob = self.blobs.get(&info.key).map(Vec::as_slice);
        Availability::Ready(blob.map(|b| Arc::new(self.refiner.decode(id, b).unwrap())))
    }
}

#[test]
fn shared_planar_vertices_are_bit_identical() {
    let Some(gpu) = gpu_for_test_with(
        "shared_planar_vertices_are_bit_identical",
        wgpu::Features::VERTEX_WRITABLE_STORAGE,
    )
    .unwrap() else {
        return;
    };
    let (w, h) = (513, 513);
    let values_m = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (x, y) = (x as f64 / 37.0, y as f64 / 23.0);
            (400.0 * x.sin() * y.cos() + 90.0 * (3.1 * x + 1.7 * y).sin()).round()
        })
        .collect();
    let grid = Grid {
        width: w,
        height: h,
        values_m,
        quantum_m: Some(1.0),
    };
    let opts = EncodeOptions {
        n: 16,
        mode: RateMode::RmsM(1.0),
        sparse: false,
        rdo: Default::default(),
    };
    let enc = Arc::new(encode(&grid, opts).unwrap());
    let refiner = Arc::new(PlanarRefiner::from_encoded(&enc).unwrap());
    let world = PlanarWorld {
        spacing_m: 30.0,
        value_scale_m: enc.value_scale_m,
        value_offset_m: enc.value_offset_m,
    };
    let eye = DVec3::new(3_000.0, 9_000.0, 1_500.0);
    let view = View {
        eye,
        target: eye + DVec3::new(2_000.0, -500.0, -900.0),
        up: DVec3::Z,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    };
    let mut dag = Dag::new(Arc::clone(&refiner));
    let mut source = Local {
        blobs: enc.blobs_by_key().unwrap(),
        refiner: Arc::clone(&refiner),
    };
    converge(&mut dag, world, &view, &mut source).unwrap();
    let frame = refiner.world_frame(&world, 0);
    let c = capture(&gpu, &mut dag, frame, &Camera::from_view(&view)).unwrap();
    let (patches, diamonds, differ) = shared(&c);
    println!(
        "{} patches, {patches} shared points, {diamonds} across diamonds",
        c.patches.len()
    );
    assert!(diamonds > 100, "too few shared vertices to test");
    assert!(
        differ.is_empty(),
        "{} shared points differ, e.g. {:?}",
        differ.len(),
        &differ[..differ.len().min(5)]
    );
}
