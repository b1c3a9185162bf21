//! The precision bar of `examples/precision.rs` (< 0.5 px between the GPU's clip
//! positions and the f64 projection) on a subset of its cases: 1 m over a face centre on
//! the equator and over a cube corner, 100,000 km over a pole.
#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../examples/precision.rs"]
mod precision;

use precision::{FACE_SIDE, N, Planet, places, run_case};
use quincunx_render::offscreen::gpu_for_test_with;

#[test]
fn gpu_vertices_project_within_half_a_pixel_of_the_f64_reference() {
    let Some(gpu) = gpu_for_test_with(
        "gpu_vertices_project_within_half_a_pixel_of_the_f64_reference",
        wgpu::Features::VERTEX_WRITABLE_STORAGE,
    )
    .unwrap() else {
        return;
    };
    let planet = Planet::new(FACE_SIDE, N).unwrap();
    let [equator, pole, _, corner] = places();
    for (place, height_m) in [(equator, 1.0), (corner, 1.0), (pole, 1e8)] {
        let c = run_case(&gpu, &planet, &place, height_m, -90.0).unwrap();
        println!("{c:?}");
        assert!(c.vertices > 0, "no vertex in view: {c:?}");
        assert!(c.max_error_px < 0.5, "{c:?}");
    }
}
