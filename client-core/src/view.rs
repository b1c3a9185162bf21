//! The camera and what refinement needs from it: a frustum for culling, the projected
//! size of a world length at a distance, and the mapping from diamond ids and integer
//! samples to world metres.

use glam::{DMat4, DVec3, DVec4};

/// A camera for one frame. Everything is `f64`: planet-sized worlds keep metre precision.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Eye position (world metres).
    pub eye: DVec3,
    /// A point the camera looks at.
    pub target: DVec3,
    /// Up direction.
    pub up: DVec3,
    /// Vertical field of view, radians.
    pub fov_y_rad: f64,
    /// Viewport width and height, pixels.
    pub viewport_px: [u32; 2],
    /// Screen-space error tolerance, pixels.
    pub tolerance_px: f64,
}

/// An axis-aligned box in world metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub min: DVec3,
    /// Largest corner.
    pub max: DVec3,
}

impl Aabb {
    /// Distance from `p` to the box (0 inside).
    pub fn distance(&self, p: DVec3) -> f64 {
        let d = (self.min - p).max(p - self.max).max(DVec3::ZERO);
        d.length()
    }

    /// Its eight corners.
    pub fn corners(&self) -> [DVec3; 8] {
        std::array::from_fn(|k| {
            DVec3::new(
                if k & 1 == 0 { self.min.x } else { self.max.x },
                if k & 2 == 0 { self.min.y } else { self.max.y },
                if k & 4 == 0 { self.min.z } else { self.max.z },
            )
        })
    }
}

/// Six clip planes `(a, b, c, d)` with `a x + b y + c z + d >= 0` inside.
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    planes: [DVec4; 6],
}

impl Frustum {
    /// Whether the box may be visible (conservative: never culls a visible box).
    pub fn intersects(&self, b: &Aabb) -> bool {
        self.planes.iter().all(|p| {
            // The box corner furthest along the plane normal.
            let corner = DVec3::new(
                if p.x >= 0.0 { b.max.x } else { b.min.x },
                if p.y >= 0.0 { b.max.y } else { b.min.y },
                if p.z >= 0.0 { b.max.z } else { b.min.z },
            );
            p.truncate().dot(corner) + p.w >= 0.0
        })
    }
}

impl View {
    /// Near plane distance (metres): small enough for a camera 1 m above ground.
    pub const NEAR_M: f64 = 0.1;

    /// Clip space from world space (right-handed, depth 0..1, infinite far plane).
    pub fn clip_from_world(&self) -> DMat4 {
        let [w, h] = self.viewport_px;
        let aspect = f64::from(w.max(1)) / f64::from(h.max(1));
        let proj = glam::dcamera::rh::proj::directx::perspective_infinite(
            self.fov_y_rad,
            aspect,
            Self::NEAR_M,
        );
        proj * glam::dcamera::rh::view::look_at_mat4(self.eye, self.target, self.up)
    }

    /// The view frustum (the far plane is at infinity).
    pub fn frustum(&self) -> Frustum {
        let m = self.clip_from_world();
        let (r0, r1, r2, r3) = (m.row(0), m.row(1), m.row(2), m.row(3));
        let planes = [r3 + r0, r3 - r0, r3 + r1, r3 - r1, r2, r3 - r2];
        Frustum {
            planes: planes.map(|p| {
                let len = p.truncate().length();
                if len > 0.0 { p / len } else { p }
            }),
        }
    }

    /// Pixels per metre of a length facing the camera at `distance_m`.
    pub fn px_per_m(&self, distance_m: f64) -> f64 {
        let h = f64::from(self.viewport_px[1].max(1));
        h / (2.0 * (self.fov_y_rad / 2.0).tan() * distance_m.max(Self::NEAR_M))
    }

    /// How much larger than `px_per_m(distance)` a step of 1 m can look at a point
    /// `distance` away whose line of sight makes an angle `a` with the view's axis:
    /// `1 / cos^2 a` (the depth is `distance cos a`, and a step across the line of sight
    /// there moves the image `1 / cos a` more than on the axis). Its largest value over the
    /// viewport is at a corner: `1 + tan^2` of the half diagonal (2.39 at 60 degrees and
    /// 16:9).
    pub fn off_axis_factor(&self) -> f64 {
        let [w, h] = self.viewport_px.map(|v| f64::from(v.max(1)));
        let t = (self.fov_y_rad / 2.0).tan();
        1.0 + t * t * (1.0 + (w / h) * (w / h))
    }

    /// [`View::off_axis_factor`] over a box: the largest `1 / cos^2` of the angle between
    /// the view's axis and a line of sight to a point of the box (its largest angle is at a
    /// corner), at most the viewport's.
    pub fn off_axis_factor_of(&self, b: &Aabb) -> f64 {
        let most = self.off_axis_factor();
        let axis = (self.target - self.eye).normalize_or_zero();
        let mut worst = 1.0f64;
        for c in b.corners() {
            let d = c - self.eye;
            let cos = d.dot(axis) / d.length();
            // Behind the eye, at it, or not a number: the viewport's bound.
            if cos.is_nan() || cos <= 0.0 {
                return most;
            }
            worst = worst.max(1.0 / (cos * cos));
        }
        worst.min(most)
    }
}

/// Where a planar repository's ids and integer samples are in the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarWorld {
    /// Metres per id unit (the raster's sample spacing).
    pub spacing_m: f64,
    /// Metres per integer sample value.
    pub value_scale_m: f64,
    /// Metres at integer 0.
    pub value_offset_m: f64,
}

impl PlanarWorld {
    /// World position of a point in id units with integer value `v`.
    pub fn point(&self, xy: [i64; 2], v: i32) -> DVec3 {
        DVec3::new(
            xy[0] as f64 * self.spacing_m,
            xy[1] as f64 * self.spacing_m,
            self.value_offset_m + f64::from(v) * self.value_scale_m,
        )
    }
}

/// Where a planet's ids and integer samples are in the world: the cube (id units, half
/// side `half_side`) mapped onto the sphere of `radius_m` centred at the origin by the
/// equal-angle map ([`quincunx_decoder::diamond::sphere::cube_to_unit_sphere`]), heights
/// along the radius.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereWorld {
    /// Radius of height 0 (metres).
    pub radius_m: f64,
    /// Half side of the cube in id units (`2^m`).
    pub half_side: f64,
    /// Metres per integer sample value.
    pub value_scale_m: f64,
    /// Metres at integer 0.
    pub value_offset_m: f64,
    /// Radius of a sphere that lies inside the surface everywhere (the planet's radius
    /// plus a conservative lowest height), for horizon culling: what it hides from the
    /// eye is not drawn. 0: no horizon culling (until the lowest height is known).
    pub occluder_radius_m: f64,
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn view() -> View {
        View {
            eye: DVec3::new(0.0, 0.0, 100.0),
            target: DVec3::new(0.0, 1000.0, 0.0),
            up: DVec3::Z,
            fov_y_rad: 60f64.to_radians(),
            viewport_px: [1920, 1080],
            tolerance_px: 1.0,
        }
    }

    #[test]
    fn frustum_keeps_what_is_ahead_and_culls_what_is_behind() {
        let f = view().frustum();
        let ahead = Aabb {
            min: DVec3::new(-10.0, 500.0, 0.0),
            max: DVec3::new(10.0, 510.0, 10.0),
        };
        let behind = Aabb {
            min: DVec3::new(-10.0, -510.0, 0.0),
            max: DVec3::new(10.0, -500.0, 10.0),
        };
        let around_eye = Aabb {
            min: DVec3::new(-1.0, -1.0, 99.0),
            max: DVec3::new(1.0, 1.0, 101.0),
        };
        assert!(f.intersects(&ahead));
        assert!(!f.intersects(&behind));
        assert!(f.intersects(&around_eye));
    }

    #[test]
    fn projected_size_halves_with_twice_the_distance_and_stays_finite() {
        let v = view();
        let a = v.px_per_m(100.0);
        assert!((a / v.px_per_m(200.0) - 2.0).abs() < 1e-12);
        assert!((1080.0 / (2.0 * 30f64.to_radians().tan() * 100.0) - a).abs() < 1e-9);
        assert!(v.px_per_m(0.0).is_finite() && v.px_per_m(1e12) > 0.0);
    }

    #[test]
    fn off_axis_factors_grow_away_from_the_axis_up_to_the_corner() {
        let v = view();
        // 1 + tan^2(30 deg) (1 + (16/9)^2) at 60 degrees and 16:9.
        let most = 1.0 + (1.0 / 3.0) * (1.0 + (1920.0f64 / 1080.0).powi(2));
        assert!((v.off_axis_factor() - most).abs() < 1e-12);
        let axis = (v.target - v.eye).normalize();
        let at = |p: DVec3, r: f64| Aabb {
            min: p - DVec3::splat(r),
            max: p + DVec3::splat(r),
        };
        // A small box on the axis: about 1.
        let ahead = v.off_axis_factor_of(&at(v.eye + axis * 500.0, 0.01));
        assert!((ahead - 1.0).abs() < 1e-6, "{ahead}");
        // A box 45 degrees off the axis: 2 (1 / cos^2 45).
        let side = axis.cross(DVec3::Z).normalize();
        let off = v.off_axis_factor_of(&at(v.eye + (axis + side) * 500.0, 0.01));
        assert!((off - 2.0).abs() < 1e-3, "{off}");
        // Behind the eye, or around it: the viewport's largest.
        assert_eq!(v.off_axis_factor_of(&at(v.eye - axis * 500.0, 1.0)), most);
        assert_eq!(v.off_axis_factor_of(&at(v.eye, 1.0)), most);
    }

    #[test]
    fn distance_to_a_box_is_zero_inside() {
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        assert_eq!(b.distance(DVec3::splat(0.5)), 0.0);
        assert!((b.distance(DVec3::new(4.0, 5.0, 1.0)) - 5.0).abs() < 1e-12);
    }
}
