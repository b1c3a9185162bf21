//! The streamed surface under a point: what "metres above the terrain" means for a
//! camera (`quincunx render --height-m`, the viewer's fly mode).

use glam::DVec3;
use quincunx_client::dag::Half;
use quincunx_client::session::Session;

use crate::domain::{AffinePatch, Geometry, RenderDomain, WorldFrame};

/// Height (metres) of the current cut's surface below `eye` (along the up direction:
/// `+z` on the plane, the radius on a planet), interpolated on the patch's grid triangles
/// as they are drawn. `None` outside the data. Costs a pass over the cut.
pub fn surface_height_m<R: RenderDomain>(session: &Session<R>, eye: DVec3) -> Option<f64> {
    let dag = session.dag();
    let world = dag.refiner().world_frame(&session.world(), 0);
    let p = world.anchor(eye);
    let n = world.n as usize;
    for (id, half) in dag.cut() {
        let Some(node) = dag.node(id) else { continue };
        let Some(a) = dag.refiner().affine(id, &node.corners, half) else {
            continue;
        };
        let Some((fi, fj)) = grid_coordinates(&world, &a, p) else {
            continue;
        };
        let eps = 1e-9 * n as f64;
        let inside = fi >= -eps
            && fj >= -eps
            && fi <= n as f64 + eps
            && fj <= n as f64 + eps
            && match half {
                Half::Lower => fi >= fj - eps,
                Half::Upper => fi <= fj + eps,
            };
        if !inside {
            continue;
        }
        let (fi, fj) = (fi.clamp(0.0, n as f64), fj.clamp(0.0, n as f64));
        let ci = (fi.floor() as usize).min(n - 1);
        let cj = (fj.floor() as usize).min(n - 1);
        let (x, y) = (fi - ci as f64, fj - cj as f64);
        let g = |i: usize, j: usize| f64::from(node.grid[i * (n + 1) + j]);
        let v = if x >= y {
            g(ci, cj) + x * (g(ci + 1, cj) - g(ci, cj)) + y * (g(ci + 1, cj + 1) - g(ci + 1, cj))
        } else {
            g(ci, cj) + y * (g(ci, cj + 1) - g(ci, cj)) + x * (g(ci + 1, cj + 1) - g(ci, cj + 1))
        };
        return Some(world.value_offset_m + v * world.value_scale_m);
    }
    None
}

/// The grid coordinates `(i, j)` of fine point `p` in a patch's plane (`None` when `p`
/// is on another cube face).
fn grid_coordinates(world: &WorldFrame, a: &AffinePatch, p: DVec3) -> Option<(f64, f64)> {
    let (u, v) = match world.geometry {
        Geometry::Planar { .. } => (0, 1),
        Geometry::Planet { half_side_fine, .. } => {
            // The face: the axis along which the patch does not move, at +-S.
            let axis = (0..3).find(|&k| a.e1[k] == 0 && a.e2[k] == 0)?;
            let s = half_side_fine as f64;
            if (p[axis] - a.base[axis] as f64).abs() > 1e-6 * s {
                return None;
            }
            match axis {
                0 => (1, 2),
                1 => (0, 2),
                _ => (0, 1),
            }
        }
    };
    let (a11, a12) = (a.e1[u] as f64, a.e2[u] as f64);
    let (a21, a22) = (a.e1[v] as f64, a.e2[v] as f64);
    let det = a11 * a22 - a12 * a21;
    if det == 0.0 {
        return None;
    }
    let (bx, by) = (p[u] - a.base[u] as f64, p[v] - a.base[v] as f64);
    Some(((bx * a22 - a12 * by) / det, (a11 * by - a21 * bx) / det))
}
