//! Image-error measures of a rendered frame against a reference of the same view (the
//! speed/accuracy trade study, `quincunx trade`): a photometric one ([`psnr_db`]) and a
//! geometric one, in screen pixels, from the frame's depth attachment and the
//! reference's surface.
//!
//! # The geometric error
//!
//! The *geometric error* of a test frame (its depth attachment, read back with
//! [`crate::Offscreen::read_depth`], and its [`Camera`]) against a reference surface (the
//! reference cut's triangles exactly as drawn, vertices in f64: [`SurfaceIndex`]) is,
//! for every pixel `(x, y)` whose test depth `d` is not 0 (the pixel shows terrain):
//!
//! 1. `X` = the world point the test frame shows there: the pixel centre
//!    `(x + 1/2, y + 1/2)` at depth `d`, taken back through the camera's projection in
//!    f64 ([`unproject`], the exact inverse of [`Camera::project`]);
//! 2. `R` = the point where the line through `X` along the local up direction (planar:
//!    `+z`; planet: radial, from the planet's centre) meets the reference surface, the
//!    one nearest to `X` (on either side);
//! 3. `error_px = |P(X) - P(R)|`, with `P` the camera's f64 projection to pixel
//!    coordinates (`x`, `y` only): how far on screen the reference surface's point lies
//!    from where the test frame draws that spot of ground (a height error seen in
//!    pixels, the quantity the refinement's screen-space tolerance bounds).
//!
//! When the reference frame's depth is given and is bit-identical to the test depth at a
//! pixel, that pixel shows a point of the reference surface and its error is exactly 0 (so
//! a reference compared with itself measures exactly 0). Pixels whose line meets no
//! reference triangle (or meets it only behind the camera) are not measured: they are
//! counted as [`GeometricError::pixels_without_reference`] (+inf in an [`ErrorMap`]).
//! The statistics are over the measured pixels, percentiles by nearest rank (the `p`-th
//! percentile of `n` sorted values is the `ceil(p n / 100)`-th).
//!
//! `X` comes from the rasteriser's depth, which for a triangle seen edge-on can lie off
//! the triangle ([`recheck`]); [`recheck`] re-measures chosen pixels (those over a
//! tolerance) at the exact first hit of their ray on the drawn triangles.

use std::sync::Mutex;

use glam::{DMat4, DVec3, DVec4};

use crate::RenderError;
use crate::camera::Camera;
use crate::ground::SurfaceIndex;
use crate::offscreen::{DepthImage, Image};

/// Peak signal-to-noise ratio (dB) of two equal-sized RGBA8 images over the red, green
/// and blue channels of every pixel (alpha ignored), peak 255:
/// `10 log10(255^2 / MSE)`; `f64::INFINITY` when they are identical. Errors when the
/// sizes differ or an image's bytes do not match its size.
pub fn psnr_db(a: &Image, b: &Image) -> Result<f64, RenderError> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(RenderError::Config(format!(
            "PSNR of images of different sizes: {}x{} and {}x{}",
            a.width, a.height, b.width, b.height
        )));
    }
    for image in [a, b] {
        let want = u64::from(image.width) * u64::from(image.height) * 4;
        if image.rgba.len() as u64 != want {
            return Err(RenderError::Config(format!(
                "image {}x{} holds {} bytes, not {want}",
                image.width,
                image.height,
                image.rgba.len()
            )));
        }
    }
    if a.rgba.is_empty() {
        return Err(RenderError::Config("PSNR of empty images".into()));
    }
    let sum: u64 = a
        .rgba
        .chunks_exact(4)
        .zip(b.rgba.chunks_exact(4))
        .map(|(p, q)| {
            (0..3)
                .map(|c| u64::from(p[c].abs_diff(q[c])).pow(2))
                .sum::<u64>()
        })
        .sum();
    if sum == 0 {
        return Ok(f64::INFINITY);
    }
    let mse = sum as f64 / (a.rgba.len() / 4 * 3) as f64;
    Ok(10.0 * (255.0f64 * 255.0 / mse).log10())
}

/// Pixel centres and depths back to world points, and world points to pixels, for one
/// camera and image size (the camera's matrices made once).
#[derive(Clone, Copy, Debug)]
struct Projector {
    clip_from_rel: DMat4,
    rel_from_clip: DMat4,
    eye: DVec3,
    size: [f64; 2],
}

impl Projector {
    fn new(camera: &Camera, size: [u32; 2]) -> Projector {
        let clip_from_rel = camera.clip_from_rel();
        Projector {
            clip_from_rel,
            rel_from_clip: clip_from_rel.inverse(),
            eye: camera.eye,
            size: size.map(f64::from),
        }
    }

    fn unproject(&self, x: u32, y: u32, depth: f32) -> Option<DVec3> {
        if !(depth.is_finite() && depth > 0.0) {
            return None;
        }
        let [w, h] = self.size;
        let ndc_x = (f64::from(x) + 0.5) / w * 2.0 - 1.0;
        let ndc_y = 1.0 - (f64::from(y) + 0.5) / h * 2.0;
        let c = self.rel_from_clip * DVec4::new(ndc_x, ndc_y, f64::from(depth), 1.0);
        let rel = c.truncate() / c.w;
        (c.w != 0.0 && rel.is_finite()).then(|| self.eye + rel)
    }

    /// [`Camera::project`]'s pixel position, the same arithmetic (for an image of the
    /// camera's viewport size).
    fn project(&self, world: DVec3) -> Option<[f64; 2]> {
        let c = self.clip_from_rel * (world - self.eye).extend(1.0);
        if c.w <= 0.0 {
            return None;
        }
        let [w, h] = self.size;
        Some([(c.x / c.w * 0.5 + 0.5) * w, (0.5 - c.y / c.w * 0.5) * h])
    }
}

/// The world point (f64 metres) shown at the centre of pixel `(x, y)` of an image of
/// `size` pixels with stored depth `depth`: the exact inverse of the camera's projection
/// ([`Camera::project`]: camera-relative, reversed Z, infinite far plane). `None` for
/// depth 0 (nothing drawn), negative or non-finite depths, and an empty size.
pub fn unproject(camera: &Camera, size: [u32; 2], x: u32, y: u32, depth: f32) -> Option<DVec3> {
    if size[0] == 0 || size[1] == 0 {
        return None;
    }
    Projector::new(camera, size).unproject(x, y, depth)
}

/// The geometric error of every pixel: row-major, top row first (as [`DepthImage`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorMap {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Pixels: the error (px) where measured, NaN where the test frame shows no terrain,
    /// +inf where the reference surface has no point on the pixel's line.
    pub error_px: Vec<f64>,
}

/// The geometric error of a frame (see the [module docs](self)), over the pixels where it
/// was measured.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GeometricError {
    /// Pixels measured (terrain in the test frame, a reference point on the line).
    pub pixels: usize,
    /// Terrain pixels of the test frame whose line meets no reference triangle (or only
    /// behind the camera): not measured.
    pub pixels_without_reference: usize,
    /// Median, px (0 when no pixel was measured, as the others).
    pub p50_px: f64,
    /// 99th percentile, px.
    pub p99_px: f64,
    /// Largest, px.
    pub max_px: f64,
    /// Mean, px.
    pub mean_px: f64,
    /// Pixels whose error is above 1 px.
    pub over_1px: usize,
    /// The pixel `[x, y]` of the largest error (the first in row-major order).
    pub max_at: Option<[u32; 2]>,
}

impl ErrorMap {
    /// The statistics of the measured pixels.
    pub fn summary(&self) -> GeometricError {
        let mut without = 0;
        let mut max_at: Option<(usize, f64)> = None;
        let mut measured = Vec::with_capacity(self.error_px.len());
        for (k, &e) in self.error_px.iter().enumerate() {
            if e.is_nan() {
                continue;
            }
            if e.is_infinite() {
                without += 1;
                continue;
            }
            measured.push(e);
            if max_at.is_none_or(|(_, m)| e > m) {
                max_at = Some((k, e));
            }
        }
        let n = measured.len();
        if n == 0 {
            return GeometricError {
                pixels_without_reference: without,
                ..GeometricError::default()
            };
        }
        let mean_px = measured.iter().sum::<f64>() / n as f64;
        measured.sort_unstable_by(f64::total_cmp);
        let rank = |p: usize| measured[(p * n).div_ceil(100).clamp(1, n) - 1];
        let w = self.width.max(1) as usize;
        GeometricError {
            pixels: n,
            pixels_without_reference: without,
            p50_px: rank(50),
            p99_px: rank(99),
            max_px: measured[n - 1],
            mean_px,
            over_1px: n - measured.partition_point(|&e| e <= 1.0),
            max_at: max_at.map(|(k, _)| [(k % w) as u32, (k / w) as u32]),
        }
    }
}

/// The geometric error of the frame `test` (depth attachment, drawn with `camera`)
/// against the reference surface `reference`; `reference_depth`, the reference frame's
/// depth attachment of the same view, when given, makes pixels with bit-identical depth
/// exactly 0. Errors when the images' sizes differ from each other or from the camera's
/// viewport.
pub fn geometric_error(
    camera: &Camera,
    test: &DepthImage,
    reference_depth: Option<&DepthImage>,
    reference: &SurfaceIndex,
) -> Result<GeometricError, RenderError> {
    Ok(error_map(camera, test, reference_depth, reference)?.summary())
}

/// [`geometric_error`] pixel by pixel.
pub fn error_map(
    camera: &Camera,
    test: &DepthImage,
    reference_depth: Option<&DepthImage>,
    reference: &SurfaceIndex,
) -> Result<ErrorMap, RenderError> {
    map_pixels(camera, test, reference_depth, || {
        let mut hint = None;
        move |x: DVec3| reference.along_hinted(x, reference.up(x), &mut hint)
    })
}

/// [`geometric_error`] with the reference surface given as a function: the reference
/// point `R` of a test point `X` (`None`: no reference surface on its line).
pub fn geometric_error_with(
    camera: &Camera,
    test: &DepthImage,
    reference_depth: Option<&DepthImage>,
    reference: impl Fn(DVec3) -> Option<DVec3> + Sync,
) -> Result<GeometricError, RenderError> {
    Ok(error_map_with(camera, test, reference_depth, reference)?.summary())
}

/// [`geometric_error_with`] pixel by pixel.
pub fn error_map_with(
    camera: &Camera,
    test: &DepthImage,
    reference_depth: Option<&DepthImage>,
    reference: impl Fn(DVec3) -> Option<DVec3> + Sync,
) -> Result<ErrorMap, RenderError> {
    map_pixels(camera, test, reference_depth, || &reference)
}

/// What [`recheck`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Recheck {
    /// Pixels re-measured at their ray's exact hit.
    pub checked: usize,
    /// Of those, pixels whose depth-buffer point lay off that hit by more than
    /// [`RECHECK_DEPTH_TOLERANCE`] of its distance: the rasteriser's depth, not the
    /// surface.
    pub moved: usize,
    /// Of those, pixels whose ray meets no drawn triangle (kept as measured).
    pub no_hit: usize,
    /// Pixels over the threshold left as measured (over the limit).
    pub unchecked: usize,
}

/// Relative distance along a pixel's ray past which [`recheck`] counts a depth-buffer
/// point as off the surface.
pub const RECHECK_DEPTH_TOLERANCE: f64 = 1e-3;

/// Re-measures the pixels of `map` whose error is above `above_px` (at most `limit` of
/// them, the largest first) with `X` the exact first hit of the pixel centre's ray on the
/// surface the test frame draws (`drawn`: the test cut's triangles,
/// [`SurfaceIndex::first_hit`]) instead of the point its depth attachment gives.
///
/// A rasteriser places a triangle's depth at the pixel centres it covers after snapping
/// its vertices to a sub-pixel grid and interpolating `z/w`; for a triangle seen edge-on
/// (a crest grazed by the line of sight) a covered centre can lie off the triangle and
/// its depth off the surface by any amount, which the measure would then read as an
/// error of the surface. The ray's hit is what the pixel shows without a rasteriser in
/// between. Pixels whose ray meets no drawn triangle keep their measured error.
pub fn recheck(
    map: &mut ErrorMap,
    camera: &Camera,
    test: &DepthImage,
    reference: &SurfaceIndex,
    drawn: &SurfaceIndex,
    above_px: f64,
    limit: usize,
) -> Result<Recheck, RenderError> {
    test.validate()?;
    if (test.width, test.height) != (map.width, map.height)
        || (test.width, test.height) != (camera.viewport_px[0], camera.viewport_px[1])
    {
        return Err(RenderError::Config(format!(
            "recheck: error map {}x{}, depth image {}x{}, camera viewport {}x{}",
            map.width,
            map.height,
            test.width,
            test.height,
            camera.viewport_px[0],
            camera.viewport_px[1]
        )));
    }
    let mut over: Vec<usize> = (0..map.error_px.len())
        .filter(|&k| map.error_px[k].is_finite() && map.error_px[k] > above_px)
        .collect();
    over.sort_by(|&a, &b| map.error_px[b].total_cmp(&map.error_px[a]));
    let mut done = Recheck {
        unchecked: over.len().saturating_sub(limit),
        ..Recheck::default()
    };
    let projector = Projector::new(camera, [test.width, test.height]);
    let w = test.width as usize;
    for &at in over.iter().take(limit) {
        let (x, y) = ((at % w) as u32, (at / w) as u32);
        let Some(p) = projector.unproject(x, y, test.data[at]) else {
            continue;
        };
        done.checked += 1;
        let dir = p - projector.eye;
        let Some(hit) = drawn.first_hit(projector.eye, dir) else {
            done.no_hit += 1;
            continue;
        };
        if (hit - p).length() > RECHECK_DEPTH_TOLERANCE * dir.length() {
            done.moved += 1;
        }
        map.error_px[at] = match (
            projector.project(hit),
            reference
                .along(hit, reference.up(hit))
                .and_then(|r| projector.project(r)),
        ) {
            (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
            _ => f64::INFINITY,
        };
    }
    Ok(done)
}

/// Rows per unit of work: each unit starts afresh (its own search hint), so the result
/// does not depend on how many threads share the work.
const BLOCK_ROWS: usize = 16;

/// The error of every pixel, rows in blocks over the available cores; `make` gives each
/// block its reference function.
fn map_pixels<M, F>(
    camera: &Camera,
    test: &DepthImage,
    reference_depth: Option<&DepthImage>,
    make: M,
) -> Result<ErrorMap, RenderError>
where
    M: Fn() -> F + Sync,
    F: FnMut(DVec3) -> Option<DVec3>,
{
    test.validate()?;
    if (test.width, test.height) != (camera.viewport_px[0], camera.viewport_px[1]) {
        return Err(RenderError::Config(format!(
            "depth image {}x{}, camera viewport {}x{}",
            test.width, test.height, camera.viewport_px[0], camera.viewport_px[1]
        )));
    }
    if let Some(r) = reference_depth {
        r.validate()?;
        if (r.width, r.height) != (test.width, test.height) {
            return Err(RenderError::Config(format!(
                "reference depth {}x{}, test depth {}x{}",
                r.width, r.height, test.width, test.height
            )));
        }
    }
    let (w, h) = (test.width as usize, test.height as usize);
    let mut error_px = vec![f64::NAN; w * h];
    if w == 0 || h == 0 {
        return Ok(ErrorMap {
            width: test.width,
            height: test.height,
            error_px,
        });
    }
    let camera = Projector::new(camera, [test.width, test.height]);
    let blocks = Mutex::new(error_px.chunks_mut(BLOCK_ROWS * w).enumerate());
    let work = || {
        loop {
            let next = match blocks.lock() {
                Ok(mut it) => it.next(),
                Err(_) => None,
            };
            let Some((b, out)) = next else { break };
            let mut reference = make();
            for (k, e) in out.iter_mut().enumerate() {
                let at = b * BLOCK_ROWS * w + k;
                let (x, y) = ((at % w) as u32, (at / w) as u32);
                let d = test.data[at];
                let Some(p) = camera.unproject(x, y, d) else {
                    continue;
                };
                if reference_depth.is_some_and(|r| r.data[at].to_bits() == d.to_bits()) {
                    *e = 0.0;
                    continue;
                }
                *e = match (
                    camera.project(p),
                    reference(p).and_then(|r| camera.project(r)),
                ) {
                    (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
                    _ => f64::INFINITY,
                };
            }
        }
    };
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    std::thread::scope(|s| {
        for _ in 1..threads {
            s.spawn(work);
        }
        work();
    });
    Ok(ErrorMap {
        width: test.width,
        height: test.height,
        error_px,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_are_nearest_rank_over_measured_pixels() {
        // 1..=100 px on a 10 x 12 map, then NaN (background) and +inf (no reference).
        let mut error_px: Vec<f64> = (1..=100).map(f64::from).collect();
        error_px.extend([f64::NAN; 15]);
        error_px.extend([f64::INFINITY; 5]);
        error_px.swap(99, 3);
        let s = ErrorMap {
            width: 10,
            height: 12,
            error_px,
        }
        .summary();
        assert_eq!((s.pixels, s.pixels_without_reference), (100, 5));
        assert_eq!((s.p50_px, s.p99_px, s.max_px), (50.0, 99.0, 100.0));
        assert!((s.mean_px - 50.5).abs() < 1e-12);
        assert_eq!(s.max_at, Some([3, 0]));
        let one = ErrorMap {
            width: 1,
            height: 1,
            error_px: vec![0.25],
        }
        .summary();
        assert_eq!((one.p50_px, one.p99_px, one.max_px), (0.25, 0.25, 0.25));
        let none = ErrorMap {
            width: 2,
            height: 1,
            error_px: vec![f64::NAN, f64::INFINITY],
        }
        .summary();
        assert_eq!((none.pixels, none.pixels_without_reference), (0, 1));
        assert_eq!(none.max_at, None);
    }
}
