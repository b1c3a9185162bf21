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

    /// How large a vertical step at a point of a box can look, relative to the same step
    /// facing the camera at the box's nearest point ([`View::px_per_m`] of
    /// [`Aabb::distance`]): a number in `(0, 1]`, to multiply with
    /// [`View::off_axis_factor_of`].
    ///
    /// A step along the up direction `u` at a point `r` from the eye moves the image by its
    /// component across the line of sight, `sin` of the angle between `u` and `r`, over
    /// `|r|` (before the off-axis factor): looking straight down at flat ground a height
    /// error does not move the image at all. `cone` is the box's up directions
    /// ([`crate::domain::World::up_cone`]: an axis and the sine of their largest angle to
    /// it); `None` gives 1. With `h` and `v` a point's distances across and along the
    /// axis, `sin / |r| <= h / (h^2 + v^2) + sin(cone)/|r|`, bounded over the box by the
    /// ranges of `h` (its largest at a corner, its smallest from the nearest distance and
    /// the largest `|v|`) and `v` (exact, from the corners), each taken independently.
    pub fn vertical_sight_of(&self, b: &Aabb, cone: Option<(DVec3, f64)>) -> f64 {
        let Some((axis, sin_cone)) = cone else {
            return 1.0;
        };
        let nearest = b.distance(self.eye).max(Self::NEAR_M);
        let (mut v_min, mut v_max, mut h_max) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
        for c in b.corners() {
            let r = c - self.eye;
            let v = r.dot(axis);
            (v_min, v_max) = (v_min.min(v), v_max.max(v));
            h_max = h_max.max((r - v * axis).length());
        }
        let v_near = if v_min <= 0.0 && v_max >= 0.0 {
            0.0
        } else {
            v_min.abs().min(v_max.abs())
        };
        let v_far = v_min.abs().max(v_max.abs());
        let h_near = (nearest * nearest - v_far * v_far).max(0.0).sqrt();
        // h / (h^2 + v^2) grows with h up to h = v, then falls; it is largest at the
        // smallest |v|.
        let h = v_near.clamp(h_near, h_max.max(h_near));
        let across = h / (h * h + v_near * v_near);
        let sight = nearest * across.min(1.0 / nearest) + sin_cone;
        if sight.is_nan() { 1.0 } else { sight.min(1.0) }
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

    /// `sin(up, r) / |r|` times the box's nearest distance at points of the box, against
    /// the bound, for boxes in every position around the eye, on the plane and on a
    /// planet; and the bound is small seen from above, about 1 from the side.
    #[test]
    fn vertical_sight_bounds_every_point_of_the_box() {
        use crate::domain::World;
        let planar = PlanarWorld {
            spacing_m: 1.0,
            value_scale_m: 1.0,
            value_offset_m: 0.0,
        };
        let sphere = SphereWorld {
            radius_m: 6_371_000.0,
            half_side: 1024.0,
            value_scale_m: 1.0,
            value_offset_m: 0.0,
            occluder_radius_m: 0.0,
        };
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut unit = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut v = view();
        let mut checked = 0;
        for case in 0..4000 {
            let on_planet = case % 2 == 1;
            let scale = [1.0, 100.0, 10_000.0, 1_000_000.0][case / 2 % 4];
            let centre = if on_planet {
                let d = DVec3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5).normalize();
                d * (sphere.radius_m + (unit() - 0.5) * scale)
            } else {
                DVec3::ZERO
            };
            let around = |u: f64| (u - 0.5) * 4.0 * scale;
            v.eye = centre + DVec3::new(around(unit()), around(unit()), around(unit()));
            let lo = centre + DVec3::new(around(unit()), around(unit()), around(unit()));
            let size = DVec3::new(unit(), unit(), unit()) * scale;
            let b = Aabb {
                min: lo,
                max: lo + size,
            };
            let cone = if on_planet {
                sphere.up_cone(&b)
            } else {
                planar.up_cone(&b)
            };
            let sight = v.vertical_sight_of(&b, cone);
            assert!(sight > 0.0 || size.x * size.y == 0.0, "{sight}");
            assert!(sight <= 1.0, "{sight}");
            let nearest = b.distance(v.eye).max(View::NEAR_M);
            for k in 0..125 {
                let t = DVec3::new(
                    f64::from(k % 5) / 4.0,
                    f64::from(k / 5 % 5) / 4.0,
                    f64::from(k / 25) / 4.0,
                );
                let p = b.min + size * t;
                let r = p - v.eye;
                let up = if on_planet {
                    sphere.up(p)
                } else {
                    planar.up(p)
                };
                let sin = r.normalize().cross(up).length();
                if r.length() < View::NEAR_M || !sin.is_finite() {
                    continue;
                }
                let seen = nearest * sin / r.length();
                assert!(
                    seen <= sight * (1.0 + 1e-9) + 1e-12,
                    "case {case}: {seen} > {sight}"
                );
                checked += 1;
            }
        }
        assert!(checked > 400_000, "{checked}");
        // 300 m above a 100 m square straight below: a fifth; far to the side: nearly 1.
        v.eye = DVec3::new(0.0, 0.0, 300.0);
        let below = Aabb {
            min: DVec3::new(-50.0, -50.0, 0.0),
            max: DVec3::new(50.0, 50.0, 10.0),
        };
        let sight = v.vertical_sight_of(&below, planar.up_cone(&below));
        assert!(sight > 0.1 && sight < 0.3, "{sight}");
        let aside = Aabb {
            min: DVec3::new(5000.0, -50.0, 0.0),
            max: DVec3::new(5100.0, 50.0, 10.0),
        };
        let sight = v.vertical_sight_of(&aside, planar.up_cone(&aside));
        assert!(sight > 0.99, "{sight}");
        // Around a planet's centre the up directions are not bounded.
        let all = Aabb {
            min: DVec3::splat(-7e6),
            max: DVec3::splat(7e6),
        };
        assert_eq!(sphere.up_cone(&all), None);
        assert_eq!(v.vertical_sight_of(&all, None), 1.0);
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
