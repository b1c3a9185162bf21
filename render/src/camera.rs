//! The camera and the per-frame uniforms: everything in f64 on the host, split into
//! exact integer limbs and small f32 remainders for the shader.

use bytemuck::{Pod, Zeroable};
use glam::{DMat4, DVec3, Mat4};
use quincunx_client::view::View;

use crate::domain::{Geometry, WorldFrame};

/// Near plane (metres). With reversed Z and an infinite far plane the depth resolution is
/// relative (about 1.2e-7 of the distance at every distance), so the near plane can sit
/// this close without z-fighting further out.
pub const NEAR_M: f64 = 0.05;

/// Limb size of the split integers (`hi * LIMB + lo`, `0 <= lo < LIMB`).
pub const LIMB: i64 = 1 << 16;

/// A camera: position and orientation in world metres (f64), projection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye (world metres).
    pub eye: DVec3,
    /// Viewing direction (need not be normalised).
    pub forward: DVec3,
    /// Up direction.
    pub up: DVec3,
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
    /// Viewport, pixels.
    pub viewport_px: [u32; 2],
}

impl Camera {
    /// The camera of a client [`View`].
    pub fn from_view(view: &View) -> Camera {
        Camera {
            eye: view.eye,
            forward: view.target - view.eye,
            up: view.up,
            fov_y_rad: view.fov_y_rad,
            viewport_px: view.viewport_px,
        }
    }

    /// The view rotation (camera at the origin): a pure rotation, f64.
    pub fn rotation(&self) -> DMat4 {
        let f = self.forward.normalize_or(DVec3::NEG_Z);
        let mut up = self.up.normalize_or(DVec3::Z);
        if f.cross(up).length_squared() < 1e-24 {
            up = f.any_orthonormal_vector();
        }
        glam::dcamera::rh::view::look_to_mat4(DVec3::ZERO, f, up)
    }

    /// Reversed-Z perspective with an infinite far plane (depth 1 at the near plane, 0 at
    /// infinity; compare `Greater`, clear to 0).
    pub fn projection(&self) -> DMat4 {
        let [w, h] = self.viewport_px;
        let aspect = f64::from(w.max(1)) / f64::from(h.max(1));
        glam::dcamera::rh::proj::directx::perspective_infinite_reverse(
            self.fov_y_rad,
            aspect,
            NEAR_M,
        )
    }

    /// Clip space from camera-relative world metres.
    pub fn clip_from_rel(&self) -> DMat4 {
        self.projection() * self.rotation()
    }

    /// Pixel position (x right, y down) and depth of a world point, in f64: the
    /// reference the GPU path is measured against. `None` behind the camera.
    pub fn project(&self, world: DVec3) -> Option<[f64; 3]> {
        let c = self.clip_from_rel() * (world - self.eye).extend(1.0);
        if c.w <= 0.0 {
            return None;
        }
        let [w, h] = self.viewport_px.map(f64::from);
        Some([
            (c.x / c.w * 0.5 + 0.5) * w,
            (0.5 - c.y / c.w * 0.5) * h,
            c.z / c.w,
        ])
    }
}

/// The frame uniforms (layout of `Frame` in `terrain.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable, PartialEq)]
pub struct FrameUniforms {
    /// Projection times view rotation.
    pub clip_from_rel: [[f32; 4]; 4],
    /// Camera anchor, high limbs; w = kind.
    pub cam_hi: [i32; 4],
    /// Camera anchor, low limbs; w = N.
    pub cam_lo: [i32; 4],
    /// Anchor remainder; w = camera height remainder (samples).
    pub cam_frac: [f32; 4],
    /// Planet: camera direction; w = metres per fine unit (planar).
    pub cam_dir: [f32; 4],
    /// Planet: cos(a c); w = a.
    pub cos_ac: [f32; 4],
    /// Planet: tan(a c); w = its length.
    pub tan_c: [f32; 4],
    /// Light direction; w = ambient share.
    pub light: [f32; 4],
    /// Height scale, radius + offset (or offset), tint low, tint high.
    pub heights: [f32; 4],
    /// Camera height integer part, Nc, mode bits, raster clip.
    pub ints: [i32; 4],
    /// Height offset (z).
    pub raster: [f32; 4],
    /// Planar raster bounds relative to the eye, metres (x0, y0, x1, y1).
    pub rect: [f32; 4],
}

/// Drawing modes (pipeline constants of the shader: one pipeline each).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Modes {
    /// Grid lines over the shading.
    pub wireframe: bool,
    /// Each level in its own colour instead of the tint or colour layer.
    pub colour_by_level: bool,
    /// Ignore the colour layer (height tint).
    pub no_colour: bool,
}

/// Splits a non-negative-remainder integer into limbs.
pub fn limbs(x: i64) -> (i32, i32) {
    let hi = x.div_euclid(LIMB);
    let lo = x.rem_euclid(LIMB);
    (hi.clamp(i32::MIN as i64, i32::MAX as i64) as i32, lo as i32)
}

/// What the frame needs besides the camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// Direction towards the light (world); `None` picks one from the camera.
    pub light_dir: Option<DVec3>,
    /// Share of ambient light.
    pub ambient: f64,
    /// Height range the tint spans (metres above 0); `None`: from 0 to the highest
    /// height of the repository's roots ([`crate::TerrainRenderer::for_session`]), or
    /// 3,000 m.
    pub tint_m: Option<(f64, f64)>,
}

impl Default for Lighting {
    fn default() -> Self {
        Lighting {
            light_dir: None,
            ambient: 0.35,
            tint_m: None,
        }
    }
}

/// The default light: from the north-west, 50 degrees up (the plane's `-y` is north:
/// row 0 of a raster), or the same relative to the local up on a planet.
pub fn default_light(world: &WorldFrame, eye: DVec3) -> DVec3 {
    match world.geometry {
        Geometry::Planar { .. } => DVec3::new(-0.45, -0.45, 0.77).normalize(),
        Geometry::Planet { .. } => {
            let up = eye.normalize_or(DVec3::Z);
            let east = DVec3::Z.cross(up).normalize_or(DVec3::X);
            let north = up.cross(east);
            (up * 0.77 - east * 0.45 + north * 0.45).normalize()
        }
    }
}

/// The uniforms of one frame.
pub fn frame_uniforms(world: &WorldFrame, camera: &Camera, lighting: &Lighting) -> FrameUniforms {
    let m = camera.clip_from_rel();
    let clip_from_rel: Mat4 = m.as_mat4();
    let anchor = world.anchor(camera.eye);
    let narrow = world.narrow();
    // Narrow planar repositories: the whole anchor in the high fields, clamped so that a
    // difference with any fine point fits an i32 (a camera further out keeps the rest
    // in the remainder, relative to its distance).
    let cell = if narrow {
        anchor
            .floor()
            .clamp(DVec3::splat(-1073741824.0), DVec3::splat(1073741824.0))
    } else {
        anchor.floor()
    };
    let frac = anchor - cell;
    let split = [cell.x, cell.y, cell.z].map(|c| {
        if narrow {
            (c as i32, 0)
        } else {
            limbs(c as i64)
        }
    });
    let scale = if world.value_scale_m != 0.0 {
        world.value_scale_m
    } else {
        1.0
    };
    let (kind, cam_dir, cos_ac, tan_c, heights_y, height_m) = match world.geometry {
        Geometry::Planar {
            metres_per_fine, ..
        } => (
            0,
            [0.0, 0.0, 0.0, metres_per_fine as f32],
            [1.0, 1.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            world.value_offset_m,
            camera.eye.z,
        ),
        Geometry::Planet {
            radius_m,
            half_side_fine,
        } => {
            let s = half_side_fine as f64;
            let a = std::f64::consts::FRAC_PI_4 / s;
            let t = [anchor.x, anchor.y, anchor.z].map(|c| (a * c).tan());
            let cs = [anchor.x, anchor.y, anchor.z].map(|c| (a * c).cos());
            let tv = DVec3::from_array(t);
            let g = tv / tv.length();
            (
                1,
                [g.x as f32, g.y as f32, g.z as f32, 0.0],
                [cs[0] as f32, cs[1] as f32, cs[2] as f32, a as f32],
                [t[0] as f32, t[1] as f32, t[2] as f32, tv.length() as f32],
                radius_m + world.value_offset_m,
                camera.eye.length() - radius_m,
            )
        }
    };
    // The camera's height in samples, split like the anchor.
    let vc = (height_m - world.value_offset_m) / scale;
    let vc_int = vc.floor().clamp(-(1i64 << 30) as f64, (1i64 << 30) as f64);
    let light = lighting
        .light_dir
        .unwrap_or_else(|| default_light(world, camera.eye))
        .normalize_or(DVec3::Z);
    let (clip, rect) = match world.geometry {
        Geometry::Planar {
            extent_fine,
            metres_per_fine,
        } => {
            let e = extent_fine.map(|x| x as f64 * metres_per_fine);
            (
                1,
                [
                    (-camera.eye.x) as f32,
                    (-camera.eye.y) as f32,
                    (e[0] - camera.eye.x) as f32,
                    (e[1] - camera.eye.y) as f32,
                ],
            )
        }
        Geometry::Planet { .. } => (0, [0.0; 4]),
    };
    FrameUniforms {
        clip_from_rel: clip_from_rel.to_cols_array_2d(),
        cam_hi: [split[0].0, split[1].0, split[2].0, kind],
        cam_lo: [split[0].1, split[1].1, split[2].1, world.n as i32],
        cam_frac: [
            frac.x as f32,
            frac.y as f32,
            frac.z as f32,
            (vc - vc_int) as f32,
        ],
        cam_dir,
        cos_ac,
        tan_c,
        light: [
            light.x as f32,
            light.y as f32,
            light.z as f32,
            lighting.ambient as f32,
        ],
        heights: [
            scale as f32,
            heights_y as f32,
            lighting.tint_m.unwrap_or((0.0, 3000.0)).0 as f32,
            lighting.tint_m.unwrap_or((0.0, 3000.0)).1 as f32,
        ],
        ints: [vc_int as i32, world.colour_n as i32, 0, clip],
        raster: [0.0, 0.0, world.value_offset_m as f32, 0.0],
        rect,
    }
}

/// The smallest distance step (metres) beyond `d` that changes the stored depth, with
/// this module's projection and f32 arithmetic: the depth resolution at `d`. `gl`: as on
/// wgpu's GL backend, which maps clip `z` to `2z - w` (no clip control) and stores
/// `(z_ndc + 1) / 2`; otherwise Vulkan/Metal/DX12 (`z / w` stored as is).
pub fn depth_resolution_m(d: f64, gl: bool) -> f64 {
    let stored = |dist: f64| -> f32 {
        // Clip z and w of a point straight ahead at `dist` (reversed Z, infinite far).
        let (z, w) = (NEAR_M as f32, dist as f32);
        if gl {
            let z = 2.0 * z - w;
            (z / w + 1.0) * 0.5
        } else {
            z / w
        }
    };
    let at = stored(d);
    // Double the step until the stored value changes, then bisect.
    let mut step = d * 1e-9;
    while stored(d + step) == at && step < d * 1e6 {
        step *= 2.0;
    }
    let (mut lo, mut hi) = (step / 2.0, step);
    for _ in 0..40 {
        let mid = (lo + hi) / 2.0;
        if stored(d + mid) == at {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn reversed_z_resolution_is_relative_and_gl_loses_it_with_distance() {
        for d in [1.0, 100.0, 1e4, 1e6, 1e8] {
            let r = depth_resolution_m(d, false);
            // A float step of near/d is relative: about 2^-23 of d, never worse than 2^-22.
            assert!(r <= d * 2.5e-7 && r > d * 1e-8, "{d}: {r}");
        }
        // Without clip control the step is absolute in depth: about 6e-8 d^2 / near.
        for d in [100.0, 1e3, 1e4] {
            println!(
                "depth resolution at {d} m: {:.3e} m (Vulkan), {:.3e} m (GL)",
                depth_resolution_m(d, false),
                depth_resolution_m(d, true)
            );
        }
        let r = depth_resolution_m(1e3, true);
        assert!(r > 0.2 && r < 3.0, "{r}");
        assert!(depth_resolution_m(1e4, true) > 50.0 * depth_resolution_m(1e3, true));
    }

    #[test]
    fn limbs_recombine_exactly_with_a_non_negative_low_part() {
        for x in [
            0i64,
            1,
            -1,
            65535,
            65536,
            -65536,
            -65537,
            1 << 40,
            -(1 << 40) - 3,
        ] {
            let (hi, lo) = limbs(x);
            assert!((0..LIMB as i32).contains(&lo));
            assert_eq!(i64::from(hi) * LIMB + i64::from(lo), x);
        }
    }

    #[test]
    fn reversed_z_puts_near_at_one_and_far_towards_zero() {
        let cam = Camera {
            eye: DVec3::ZERO,
            forward: DVec3::Y,
            up: DVec3::Z,
            fov_y_rad: 1.0,
            viewport_px: [100, 100],
        };
        let near = cam.project(DVec3::new(0.0, NEAR_M, 0.0)).unwrap();
        let far = cam.project(DVec3::new(0.0, 1e9, 0.0)).unwrap();
        assert!((near[2] - 1.0).abs() < 1e-9 && far[2] > 0.0 && far[2] < 1e-9);
        assert!((near[0] - 50.0).abs() < 1e-9 && (near[1] - 50.0).abs() < 1e-9);
        assert!(cam.project(DVec3::new(0.0, -1.0, 0.0)).is_none());
    }
}
