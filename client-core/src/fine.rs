//! What a renderer needs of a domain: exact vertex positions in a common integer unit
//! (the *fine unit*), as a per-patch affine map a shader evaluates, and how fine units
//! and samples become metres. Here, not in `quincunx-render`, so that every renderer
//! (the wgpu one, the browser's WebGL2 one through `quincunx-web`) reads the same maps.

use crate::dag::Half;
use crate::domain::Domain;
use crate::view::{PlanarWorld, SphereWorld};
use glam::DVec3;
use quincunx_decoder::diamond::sphere::unit_sphere_to_cube;
use quincunx_decoder::incremental::{PlanarRefiner, Refiner, SphereRefiner};

/// The integer geometry of a repository, as the shader sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Geometry {
    /// A plane: fine unit = id unit / N (so grid vertices are integers).
    Planar {
        /// Metres per fine unit.
        metres_per_fine: f64,
        /// The raster's extent in fine units (`(w - 1) N`, `(h - 1) N`): nothing outside
        /// it is data, fragments there are discarded.
        extent_fine: [i64; 2],
    },
    /// A planet: the cube `[-S, S]^3` (fine units) mapped onto the sphere by the
    /// equal-angle map, heights along the radius.
    Planet {
        /// Radius of height 0 (metres).
        radius_m: f64,
        /// Cube half side `S` in fine units.
        half_side_fine: i64,
    },
}

/// A repository's geometry, heights and grid sizes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldFrame {
    /// Plane or planet.
    pub geometry: Geometry,
    /// Metres per integer sample.
    pub value_scale_m: f64,
    /// Metres at integer 0.
    pub value_offset_m: f64,
    /// Diamond size `N`.
    pub n: u32,
    /// Colour diamond size (0: no colour layer).
    pub colour_n: u32,
}

impl WorldFrame {
    /// Whether every fine point (and every difference of two) fits an i32: planar
    /// extents below 2^30 fine units. The shader then skips the 16-bit limbs.
    pub fn narrow(&self) -> bool {
        match self.geometry {
            Geometry::Planar { extent_fine, .. } => {
                extent_fine.iter().all(|&e| (0..(1i64 << 30)).contains(&e))
            }
            Geometry::Planet { .. } => false,
        }
    }

    /// World position (metres, f64) of a fine-unit point at integer height `v`.
    pub fn point(&self, p: [i64; 3], v: i32) -> DVec3 {
        let h = self.value_offset_m + f64::from(v) * self.value_scale_m;
        match self.geometry {
            Geometry::Planar {
                metres_per_fine, ..
            } => DVec3::new(
                p[0] as f64 * metres_per_fine,
                p[1] as f64 * metres_per_fine,
                h,
            ),
            Geometry::Planet { radius_m, .. } => {
                let d = DVec3::from_array(quincunx_decoder::diamond::sphere::cube_to_unit_sphere(
                    p.map(|x| x as f64),
                ));
                d * (radius_m + h)
            }
        }
    }

    /// The point of the cube surface (fine units, f64) in the direction of `eye`
    /// (planets), or `eye` in fine units on the plane.
    pub fn anchor(&self, eye: DVec3) -> DVec3 {
        match self.geometry {
            Geometry::Planar {
                metres_per_fine, ..
            } => DVec3::new(eye.x / metres_per_fine, eye.y / metres_per_fine, 0.0),
            Geometry::Planet { half_side_fine, .. } => {
                let d = eye.normalize_or(DVec3::Z);
                DVec3::from_array(unit_sphere_to_cube(d.to_array())) * half_side_fine as f64
            }
        }
    }
}

/// A patch's vertices as an exact affine map of the grid index: fine point of `(i, j)` =
/// `base + i e1 + j e2`, valid on the patch's half.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AffinePatch {
    /// Fine point of `(0, 0)`.
    pub base: [i64; 3],
    /// Step of `i`.
    pub e1: [i64; 3],
    /// Step of `j`.
    pub e2: [i64; 3],
    /// Level of the diamond.
    pub level: u32,
}

impl AffinePatch {
    /// Fine point of `(i, j)`.
    pub fn at(&self, i: usize, j: usize) -> [i64; 3] {
        let (i, j) = (i as i64, j as i64);
        [0, 1, 2].map(|k| self.base[k] + i * self.e1[k] + j * self.e2[k])
    }
}

/// A domain the renderer draws.
pub trait RenderDomain: Domain {
    /// The geometry of a repository of this domain.
    fn world_frame(&self, world: &Self::World, colour_n: usize) -> WorldFrame;

    /// The fine point of grid vertex `(i, j)` of a patch (exact).
    fn fine_point(
        &self,
        id: Self::Id,
        corners: &[[i64; 3]; 4],
        i: usize,
        j: usize,
    ) -> Option<[i64; 3]>;

    /// The level of a diamond.
    fn level_of(&self, id: Self::Id) -> u32;

    /// The affine map of a half, checked against the exact positions of its corners
    /// and its centre (`None` when the half is not affine in fine units, which would be a
    /// bug: every half lies on one face).
    fn affine(&self, id: Self::Id, corners: &[[i64; 3]; 4], half: Half) -> Option<AffinePatch> {
        let n = self.n();
        let p = |i, j| self.fine_point(id, corners, i, j);
        let origin = p(0, 0)?;
        let (a, b) = match half {
            Half::Lower => (p(n, 0)?, p(n, n)?),
            Half::Upper => (p(0, n)?, p(n, n)?),
        };
        let step = |from: [i64; 3], to: [i64; 3]| -> Option<[i64; 3]> {
            let mut out = [0; 3];
            for k in 0..3 {
                let d = to[k] - from[k];
                if d % n as i64 != 0 {
                    return None;
                }
                out[k] = d / n as i64;
            }
            Some(out)
        };
        let (e1, e2) = match half {
            Half::Lower => (step(origin, a)?, step(a, b)?),
            Half::Upper => (step(a, b)?, step(origin, a)?),
        };
        let affine = AffinePatch {
            base: origin,
            e1,
            e2,
            level: self.level_of(id),
        };
        // A vertex inside the half: the map must reproduce it exactly.
        let (ci, cj) = match half {
            Half::Lower => (n * 3 / 4, n / 4),
            Half::Upper => (n / 4, n * 3 / 4),
        };
        (p(ci, cj)? == affine.at(ci, cj)).then_some(affine)
    }
}

impl RenderDomain for PlanarRefiner {
    fn world_frame(&self, world: &PlanarWorld, colour_n: usize) -> WorldFrame {
        let n = self.n() as i64;
        let (w, h) = self.raster_size();
        WorldFrame {
            geometry: Geometry::Planar {
                metres_per_fine: world.spacing_m / n as f64,
                extent_fine: [(w as i64 - 1) * n, (h as i64 - 1) * n],
            },
            value_scale_m: world.value_scale_m,
            value_offset_m: world.value_offset_m,
            n: self.n() as u32,
            colour_n: colour_n as u32,
        }
    }

    fn fine_point(&self, _id: Self::Id, c: &[[i64; 3]; 4], i: usize, j: usize) -> Option<[i64; 3]> {
        // Id units times N, outside the raster too (the shader clips to the raster).
        let n = self.n() as i64;
        let (ii, jj) = (i as i64, j as i64);
        let p = [0, 1].map(|k| c[0][k] * n + ii * (c[1][k] - c[0][k]) + jj * (c[3][k] - c[0][k]));
        Some([p[0], p[1], 0])
    }

    fn level_of(&self, id: Self::Id) -> u32 {
        self.domain().level(id).unwrap_or(0)
    }
}

impl RenderDomain for SphereRefiner {
    fn world_frame(&self, world: &SphereWorld, colour_n: usize) -> WorldFrame {
        // Fine points of the roots' corners lie on the cube surface: S is the largest
        // coordinate of any of them.
        let s = self
            .roots()
            .first()
            .and_then(|(id, _)| self.vertex_point(*id, &self.corners(*id), 0, 0))
            .map_or(1, |p| p.iter().map(|x| x.abs()).max().unwrap_or(1));
        WorldFrame {
            geometry: Geometry::Planet {
                radius_m: world.radius_m,
                half_side_fine: s.max(1),
            },
            value_scale_m: world.value_scale_m,
            value_offset_m: world.value_offset_m,
            n: self.n() as u32,
            colour_n: colour_n as u32,
        }
    }

    fn fine_point(
        &self,
        id: Self::Id,
        corners: &[[i64; 3]; 4],
        i: usize,
        j: usize,
    ) -> Option<[i64; 3]> {
        self.vertex_point(id, corners, i, j)
    }

    fn level_of(&self, id: Self::Id) -> u32 {
        self.domain().level(id).unwrap_or(0)
    }
}
