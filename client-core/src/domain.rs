//! What the client needs of a domain besides incremental decoding: where its diamonds are
//! in the world (bounding boxes and grid spacing for projected errors), exact vertex
//! positions (crack checks) and a way to check that a cut covers the domain once.
//!
//! Implemented for planar repositories ([`PlanarRefiner`], flat world in metres) and
//! planets ([`SphereRefiner`], the cube mapped onto a sphere of the repository's radius,
//! centred at the origin).

use glam::DVec3;
use quincunx_decoder::diamond::SphereDomain;
use quincunx_decoder::diamond::sphere::{axes, chart_of, cube_to_unit_sphere};
use quincunx_decoder::diamond::{PlanarId, SphereId};
use quincunx_decoder::incremental::{
    PlanarRefiner, Procedural, RefineError, Refiner, SphereRefiner,
};
use quincunx_meta::Metadata;

use crate::open::{
    SessionError, planar_channel_refiner, planar_refiner, planar_world, sphere_channel_refiner,
    sphere_refiner, sphere_world,
};
use crate::view::{Aabb, PlanarWorld, SphereWorld, View};

/// One triangle of a diamond's grid. Grid vertex `(i, j)` lies at
/// `E1 + (i (P1 - E1) + j (P2 - E1)) / N` in the diamond's frame `[E1, P1, E2, P2]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Half {
    /// Entries with `i >= j`: the triangle `E1 P1 E2`, inside the parent centred at `P1`.
    Lower,
    /// Entries with `i <= j`: the triangle `E1 P2 E2`, inside the parent centred at `P2`.
    Upper,
}
impl Half {
    /// Both halves.
    pub const BOTH: [Half; 2] = [Half::Lower, Half::Upper];

    pub(crate) fn index(self) -> usize {
        match self {
            Half::Lower => 0,
            Half::Upper => 1,
        }
    }

    /// Whether grid entry `(i, j)` belongs to this half (the diagonal to both).
    pub fn contains(self, i: usize, j: usize) -> bool {
        match self {
            Half::Lower => i >= j,
            Half::Upper => i <= j,
        }
    }
}

/// A world mapping: ids and integer samples to metres.
pub trait World: Copy + std::fmt::Debug + PartialEq + Send + Sync + 'static {
    /// Metres per integer sample value.
    fn value_scale_m(&self) -> f64;
    /// Height (metres) of integer value `v`.
    fn height_m(&self, v: i32) -> f64;
    /// Everything projected errors depend on, to tell when cached judgements are stale.
    fn fingerprint(&self) -> [f64; 4];
    /// The up direction of a camera at `eye` (`+z` on the plane, away from a planet's
    /// centre).
    fn up(&self, eye: DVec3) -> DVec3;
}

impl World for PlanarWorld {
    fn value_scale_m(&self) -> f64 {
        self.value_scale_m
    }

    fn height_m(&self, v: i32) -> f64 {
        self.value_offset_m + f64::from(v) * self.value_scale_m
    }

    fn fingerprint(&self) -> [f64; 4] {
        [self.spacing_m, self.value_scale_m, self.value_offset_m, 0.0]
    }

    fn up(&self, _eye: DVec3) -> DVec3 {
        DVec3::Z
    }
}

impl World for SphereWorld {
    fn value_scale_m(&self) -> f64 {
        self.value_scale_m
    }

    fn height_m(&self, v: i32) -> f64 {
        self.value_offset_m + f64::from(v) * self.value_scale_m
    }

    fn fingerprint(&self) -> [f64; 4] {
        [
            self.radius_m,
            self.occluder_radius_m,
            self.value_scale_m,
            self.value_offset_m,
        ]
    }

    fn up(&self, eye: DVec3) -> DVec3 {
        let up = eye.normalize_or_zero();
        if up == DVec3::ZERO { DVec3::Z } else { up }
    }
}

/// A domain the client streams: its refiner plus geometry in the world.
pub trait Domain: Refiner + Sized {
    /// Its world mapping.
    type World: World;

    /// The repository metadata's domain.
    const KIND: quincunx_meta::Domain;

    /// The refiner and world mapping of a repository (`spacing_m` overrides a planar
    /// repository's sample spacing).
    fn from_metadata(
        name: &str,
        meta: &Metadata,
        spacing_m: Option<f64>,
    ) -> Result<(Self, Self::World), SessionError>;

    /// The refiner of channel `index` of a repository of this domain, whatever its
    /// attribute: what a colour layer decodes each of its channels with.
    fn channel_from_metadata(
        name: &str,
        meta: &Metadata,
        index: usize,
    ) -> Result<Self, SessionError>;

    /// The refiner extended by `extra` procedural levels (see
    /// [`quincunx_decoder::incremental::Procedural`]).
    fn with_procedural_levels(self, extra: usize, detail: Procedural) -> Result<Self, RefineError>;

    /// The exponent `m` of the id space (planar side, or a planet's cube half side, `2^m`).
    fn id_exponent(&self) -> u32;

    /// The same diamond in an id space `2^shift` times finer (coarser for `shift < 0`);
    /// `None` when it is not a diamond there.
    fn scale_id(id: Self::Id, shift: i32) -> Option<Self::Id>;

    /// A conservative world box of a diamond whose surface lies within `z` (metres, low
    /// and high), and its grid spacing (metres between neighbouring grid vertices).
    fn footprint(
        &self,
        world: &Self::World,
        id: Self::Id,
        corners: &[[i64; 3]; 4],
        z: (f64, f64),
    ) -> (Aabb, f64);

    /// Whether the domain itself hides the diamond from `eye`: a planet's horizon (never
    /// on the plane). `z_max` bounds its heights (metres).
    fn hidden(
        &self,
        _world: &Self::World,
        _id: Self::Id,
        _corners: &[[i64; 3]; 4],
        _z_max: f64,
        _eye: DVec3,
    ) -> bool {
        false
    }

    /// The world mapping once a conservative lowest height of the surface (metres) is
    /// known: planets cull by their horizon from then on.
    fn with_lowest_height(world: Self::World, _lowest_m: f64) -> Self::World {
        world
    }

    /// World position of grid vertex `(i, j)` of `id` with integer value `v`.
    fn vertex_world(
        &self,
        world: &Self::World,
        id: Self::Id,
        i: usize,
        j: usize,
        v: i32,
    ) -> Option<DVec3>;

    /// Exact position of grid vertex `(i, j)` of `id`, whose frame `corners` are given
    /// (a common integer unit for all diamonds), `None` outside the data: vertices with
    /// equal positions are one point.
    fn vertex_point(
        &self,
        id: Self::Id,
        corners: &[[i64; 3]; 4],
        i: usize,
        j: usize,
    ) -> Option<[i64; 3]>;

    /// The triangle of a half in a 2D chart: `(chart, corners)`. Charts are the plane
    /// (one) or the cube faces (every half of a planet lies on one face).
    fn half_triangle(&self, corners: &[[i64; 3]; 4], half: Half) -> Option<(u8, [[f64; 2]; 3])>;

    /// Probe points `(chart, point)` spread over the domain, off every diamond edge: a
    /// cut covers the domain once when each lies in exactly one half.
    fn probes(&self) -> Vec<(u8, [f64; 2])>;

    /// Views that together see the whole domain (the raster from as high as it is wide;
    /// a planet from three radii away on opposite sides), 1920x1080 at 1 px, whose
    /// surface lies within `heights`.
    fn overviews(&self, world: &Self::World, heights: (f64, f64)) -> Vec<View>;
}

/// The overview camera: 60 degrees, full HD, 1 px.
fn overview_view(eye: DVec3, target: DVec3, up: DVec3) -> View {
    View {
        eye,
        target,
        up,
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    }
}

/// `c * 2^shift`, exactly (`None` on overflow or a remainder).
fn scale_coordinate(c: i64, shift: i32) -> Option<i64> {
    if shift >= 0 {
        c.checked_mul(1i64.checked_shl(shift as u32)?)
    } else {
        let d = 1i64.checked_shl(shift.unsigned_abs())?;
        (c % d == 0).then_some(c / d)
    }
}

/// The position of grid vertex `(i, j)` of a planet diamond in `1/N` sample units: exact
/// at every level, procedural ones too (whose samples fall between the repository's).
fn sphere_vertex_fine(r: &SphereRefiner, id: SphereId, i: usize, j: usize) -> Option<[i64; 3]> {
    let n = r.n();
    let t = n.trailing_zeros();
    let fine = SphereDomain::new(r.domain().m() + t).ok()?;
    let scaled = SphereRefiner::scale_id(id, t as i32)?;
    fine.vertex_position(scaled, n, i, j).ok()
}

/// Probe coordinates along one chart axis of `extent`: irrational offsets keep them off
/// every diamond edge.
fn probe_axis(extent: f64, steps: usize, offset: f64) -> impl Iterator<Item = f64> {
    (0..steps).map(move |a| extent * (a as f64 + 0.5 + 0.1 * offset) / (steps as f64 + 0.5))
}

impl Domain for PlanarRefiner {
    type World = PlanarWorld;
    const KIND: quincunx_meta::Domain = quincunx_meta::Domain::Planar;

    fn from_metadata(
        name: &str,
        meta: &Metadata,
        spacing_m: Option<f64>,
    ) -> Result<(Self, PlanarWorld), SessionError> {
        Ok((planar_refiner(name, meta)?, planar_world(meta, spacing_m)))
    }

    fn channel_from_metadata(
        name: &str,
        meta: &Metadata,
        index: usize,
    ) -> Result<Self, SessionError> {
        planar_channel_refiner(name, meta, index)
    }

    fn with_procedural_levels(self, extra: usize, detail: Procedural) -> Result<Self, RefineError> {
        PlanarRefiner::with_procedural_levels(self, extra, detail)
    }

    fn id_exponent(&self) -> u32 {
        self.domain().m()
    }

    fn scale_id(id: PlanarId, shift: i32) -> Option<PlanarId> {
        let [x, y] = [id.x, id.y].map(|c| scale_coordinate(c, shift));
        Some(PlanarId::new(x?, y?))
    }

    fn footprint(
        &self,
        world: &PlanarWorld,
        _id: PlanarId,
        c: &[[i64; 3]; 4],
        z: (f64, f64),
    ) -> (Aabb, f64) {
        let (mut x0, mut x1, mut y0, mut y1) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
        for p in c {
            x0 = x0.min(p[0]);
            x1 = x1.max(p[0]);
            y0 = y0.min(p[1]);
            y1 = y1.max(p[1]);
        }
        let s = world.spacing_m;
        let bbox = Aabb {
            min: DVec3::new(x0 as f64 * s, y0 as f64 * s, z.0),
            max: DVec3::new(x1 as f64 * s, y1 as f64 * s, z.1),
        };
        let d = [(c[1][0] - c[0][0]) as f64, (c[1][1] - c[0][1]) as f64];
        let spacing = (d[0] * d[0] + d[1] * d[1]).sqrt() * s / self.n() as f64;
        (bbox, spacing)
    }

    fn vertex_world(
        &self,
        world: &PlanarWorld,
        id: PlanarId,
        i: usize,
        j: usize,
        v: i32,
    ) -> Option<DVec3> {
        let n = self.n() as f64;
        let c = Refiner::corners(self, id);
        let at = |k: usize| {
            (c[0][k] as f64 * n
                + i as f64 * (c[1][k] - c[0][k]) as f64
                + j as f64 * (c[3][k] - c[0][k]) as f64)
                / n
                * world.spacing_m
        };
        (i <= self.n() && j <= self.n()).then(|| DVec3::new(at(0), at(1), world.height_m(v)))
    }

    fn vertex_point(
        &self,
        _id: PlanarId,
        c: &[[i64; 3]; 4],
        i: usize,
        j: usize,
    ) -> Option<[i64; 3]> {
        let n = self.n() as i64;
        let (ii, jj) = (i as i64, j as i64);
        // Id units times N (exact).
        let pos = [0, 1].map(|k| c[0][k] * n + ii * (c[1][k] - c[0][k]) + jj * (c[3][k] - c[0][k]));
        let (w, h) = self.raster_size();
        let inside = (0..=(w as i64 - 1) * n).contains(&pos[0])
            && (0..=(h as i64 - 1) * n).contains(&pos[1]);
        inside.then_some([pos[0], pos[1], 0])
    }

    fn half_triangle(&self, c: &[[i64; 3]; 4], half: Half) -> Option<(u8, [[f64; 2]; 3])> {
        let apex = match half {
            Half::Lower => c[1],
            Half::Upper => c[3],
        };
        Some((0, [c[0], apex, c[2]].map(|p| [p[0] as f64, p[1] as f64])))
    }

    fn probes(&self) -> Vec<(u8, [f64; 2])> {
        let (w, h) = self.raster_size();
        let (w, h) = ((w - 1) as f64, (h - 1) as f64);
        probe_axis(w, 41, std::f64::consts::SQRT_2)
            .flat_map(|x| probe_axis(h, 41, std::f64::consts::E).map(move |y| (0, [x, y])))
            .collect()
    }

    fn overviews(&self, world: &PlanarWorld, heights: (f64, f64)) -> Vec<View> {
        let (w, h) = self.raster_size();
        let a = world.point([0, 0], 0);
        let b = world.point([w as i64 - 1, h as i64 - 1], 0);
        let mut centre = (a + b) / 2.0;
        centre.z = (heights.0 + heights.1) / 2.0;
        let span = (b - a).truncate().length().max(1.0);
        // The root's grid cells are many pixels wide from there, so it wants refining.
        vec![overview_view(
            centre + DVec3::new(0.0, 0.0, span),
            centre,
            DVec3::Y,
        )]
    }
}

impl SphereWorld {
    /// Unit direction of a cube point (id units).
    pub fn direction(&self, p: [i64; 3]) -> DVec3 {
        DVec3::from_array(cube_to_unit_sphere(p.map(|x| x as f64)))
    }

    /// World position of a cube point (id units) at integer height `v`.
    pub fn point(&self, p: [i64; 3], v: i32) -> DVec3 {
        self.direction(p) * (self.radius_m + self.height_m(v))
    }
}

/// The world box and grid spacing of a planet diamond (see [`Domain::footprint`]).
///
/// The diamond lies in the spherical cap around its centre's direction whose angle
/// reaches its corners (with a margin for edges that are not great circles): the box
/// bounds that cap between the lowest and highest radius, axis by axis. Angles come from
/// `atan2(|a x b|, a . b)`, accurate for the tiny diamonds of the deepest levels too.
pub fn sphere_footprint(
    world: &SphereWorld,
    n: usize,
    id: SphereId,
    c: &[[i64; 3]; 4],
    z: (f64, f64),
) -> (Aabb, f64) {
    let (centre, cap) = sphere_cap(world, id, c);
    let (r0, r1) = (
        (world.radius_m + z.0).max(0.0),
        (world.radius_m + z.1).max(0.0),
    );
    let mut min = DVec3::ZERO;
    let mut max = DVec3::ZERO;
    for k in 0..3 {
        // The angle between the centre and axis k.
        let mut axis = DVec3::ZERO;
        axis[k] = 1.0;
        let theta = angle(centre, axis);
        let hi = (theta - cap).max(0.0).cos();
        let lo = (theta + cap).min(std::f64::consts::PI).cos();
        let products = [r0 * lo, r0 * hi, r1 * lo, r1 * hi];
        min[k] = products.iter().copied().fold(f64::INFINITY, f64::min);
        max[k] = products.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    }
    let spacing =
        (world.direction(c[1]) - world.direction(c[0])).length() * world.radius_m / n as f64;
    (Aabb { min, max }, spacing)
}

/// Angle between two unit vectors, accurate for tiny angles too.
fn angle(a: DVec3, b: DVec3) -> f64 {
    a.cross(b).length().atan2(a.dot(b))
}

/// The direction of a planet diamond's centre and the angle of a cap around it that holds
/// the diamond.
fn sphere_cap(world: &SphereWorld, id: SphereId, c: &[[i64; 3]; 4]) -> (DVec3, f64) {
    let centre = world.direction(id.c);
    let cap = c
        .iter()
        .map(|&p| angle(centre, world.direction(p)))
        .fold(0.0, f64::max)
        * 1.05
        + 1e-12;
    (centre, cap)
}

/// Horizon culling: whether the sphere of `occluder` radius (inside the surface
/// everywhere) hides every point within angle `cap` of direction `centre` and at most
/// `r_max` from the planet's centre, seen from `eye`. The worst such point gives one
/// *horizon culling point* on the centre's ray; the region is hidden when that point is
/// (the point is beyond the occluder and inside its shadow cone from the eye).
pub fn below_horizon(eye: DVec3, occluder: f64, centre: DVec3, cap: f64, r_max: f64) -> bool {
    if occluder <= 0.0 {
        return false;
    }
    let e = eye / occluder;
    let horizon2 = e.length_squared() - 1.0;
    if horizon2 <= 0.0 {
        return false;
    }
    // A point at magnitude m (occluder units) is seen over the occluder's limb at most at
    // angle beta = acos(1/m) from the tangent point; lower points count as on it.
    let beta = (1.0 / (r_max / occluder).max(1.0)).acos();
    if cap + beta >= std::f64::consts::FRAC_PI_2 {
        return false;
    }
    let p = centre * (1.0 / (cap + beta).cos());
    let to_point = p - e;
    let along = -to_point.dot(e);
    along > horizon2 && along * along / to_point.length_squared() > horizon2
}

impl Domain for SphereRefiner {
    type World = SphereWorld;
    const KIND: quincunx_meta::Domain = quincunx_meta::Domain::Sphere;

    fn from_metadata(
        name: &str,
        meta: &Metadata,
        _spacing_m: Option<f64>,
    ) -> Result<(Self, SphereWorld), SessionError> {
        let refiner = sphere_refiner(name, meta)?;
        let world = sphere_world(name, meta, refiner.domain().size())?;
        Ok((refiner, world))
    }

    fn channel_from_metadata(
        name: &str,
        meta: &Metadata,
        index: usize,
    ) -> Result<Self, SessionError> {
        sphere_channel_refiner(name, meta, index)
    }

    fn with_procedural_levels(self, extra: usize, detail: Procedural) -> Result<Self, RefineError> {
        SphereRefiner::with_procedural_levels(self, extra, detail)
    }

    fn id_exponent(&self) -> u32 {
        self.domain().m()
    }

    fn scale_id(id: SphereId, shift: i32) -> Option<SphereId> {
        let [x, y, z] = id.c.map(|c| scale_coordinate(c, shift));
        Some(SphereId::new([x?, y?, z?]))
    }

    fn footprint(
        &self,
        world: &SphereWorld,
        id: SphereId,
        c: &[[i64; 3]; 4],
        z: (f64, f64),
    ) -> (Aabb, f64) {
        sphere_footprint(world, self.n(), id, c, z)
    }

    fn hidden(
        &self,
        world: &SphereWorld,
        id: SphereId,
        c: &[[i64; 3]; 4],
        z_max: f64,
        eye: DVec3,
    ) -> bool {
        let (centre, cap) = sphere_cap(world, id, c);
        below_horizon(
            eye,
            world.occluder_radius_m,
            centre,
            cap,
            world.radius_m + z_max,
        )
    }

    fn with_lowest_height(world: SphereWorld, lowest_m: f64) -> SphereWorld {
        SphereWorld {
            occluder_radius_m: (world.radius_m + lowest_m).max(0.0),
            ..world
        }
    }

    fn vertex_world(
        &self,
        world: &SphereWorld,
        id: SphereId,
        i: usize,
        j: usize,
        v: i32,
    ) -> Option<DVec3> {
        // Directions do not depend on the unit.
        let p = sphere_vertex_fine(self, id, i, j)?;
        Some(world.point(p, v))
    }

    fn vertex_point(
        &self,
        id: SphereId,
        _corners: &[[i64; 3]; 4],
        i: usize,
        j: usize,
    ) -> Option<[i64; 3]> {
        sphere_vertex_fine(self, id, i, j)
    }

    fn half_triangle(&self, c: &[[i64; 3]; 4], half: Half) -> Option<(u8, [[f64; 2]; 3])> {
        let apex = match half {
            Half::Lower => c[1],
            Half::Upper => c[3],
        };
        let s = self.domain().size();
        let points = [c[0], apex, c[2]];
        let face = (0..6u8).find(|&f| {
            let ax = axes(f);
            points.iter().all(|p| p[ax.a] == ax.s * s)
        })?;
        Some((face, points.map(|p| chart_of(face, p, s).map(|x| x as f64))))
    }

    fn probes(&self) -> Vec<(u8, [f64; 2])> {
        let side = 2.0 * self.domain().size() as f64;
        (0..6u8)
            .flat_map(|f| {
                probe_axis(side, 17, std::f64::consts::SQRT_2).flat_map(move |u| {
                    probe_axis(side, 17, std::f64::consts::E).map(move |v| (f, [u, v]))
                })
            })
            .collect()
    }

    fn overviews(&self, world: &SphereWorld, _heights: (f64, f64)) -> Vec<View> {
        let eye = DVec3::ONE.normalize() * 3.0 * world.radius_m;
        vec![
            overview_view(eye, DVec3::ZERO, DVec3::Z),
            overview_view(-eye, DVec3::ZERO, DVec3::Z),
        ]
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use quincunx_decoder::diamond::{MAX_M, SphereDomain};

    fn contains(b: &Aabb, p: DVec3) -> bool {
        let slack = 1e-6 * p.length().max(1.0);
        (p - b.min).min_element() >= -slack && (b.max - p).min_element() >= -slack
    }

    /// From the face roots to the deepest level of the largest domain, through cube
    /// corners, cube edges and the poles: boxes are finite and hold the diamond's
    /// vertices at both height extremes, and grid spacings halve every two levels.
    #[test]
    fn planet_boxes_are_finite_and_conservative_down_to_the_deepest_level() {
        let d = SphereDomain::new(MAX_M).unwrap();
        let world = SphereWorld {
            radius_m: 6_371_000.0,
            half_side: d.size() as f64,
            value_scale_m: 1.0,
            value_offset_m: 0.0,
            occluder_radius_m: 0.0,
        };
        let n = 32;
        let z = (-11_000.0, 9_000.0);
        let mut seed = 11u64;
        for root in d.roots() {
            for walk in 0..4 {
                let mut id = root;
                let mut last_spacing = f64::INFINITY;
                loop {
                    let c = d.corners(id).unwrap();
                    let (bbox, spacing) = sphere_footprint(&world, n, id, &c, z);
                    assert!(bbox.min.is_finite() && bbox.max.is_finite(), "{id:?}");
                    assert!(spacing.is_finite() && spacing > 0.0, "{id:?} {spacing}");
                    assert!(spacing <= last_spacing * 1.5, "{id:?}");
                    last_spacing = spacing;
                    for (i, j) in [(0, 0), (n, 0), (0, n), (n, n), (n / 2, n / 3), (7, 29)] {
                        let p = d.vertex_position(id, n, i, j).unwrap();
                        let dir = world.direction(p);
                        for h in [z.0, z.1] {
                            let q = dir * (world.radius_m + h);
                            assert!(contains(&bbox, q), "{id:?} ({i},{j}) {q} {bbox:?}");
                        }
                    }
                    let children = d.children(id).unwrap();
                    if children.is_empty() {
                        assert_eq!(d.level(id).unwrap(), d.max_level());
                        // Diamonds of the deepest level are about R / 2^49 across.
                        assert!(spacing < 1e-7, "{spacing}");
                        break;
                    }
                    // Walks 0 and 1 stay on a cube corner / the first child (edges and
                    // corners), the others wander.
                    seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                    let k = if walk < 2 {
                        walk
                    } else {
                        (seed >> 33) as usize % 4
                    };
                    id = children[k % children.len()];
                }
            }
        }
    }

    /// The horizon test against brute force: a cap is reported hidden only when every
    /// sampled point of it is below the occluder's horizon, and far-side caps are hidden.
    #[test]
    fn horizon_culling_is_conservative() {
        let ro = 6_360_000.0;
        let mut seed = 5u64;
        let mut rand = || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let visible = |eye: DVec3, p: DVec3| {
            // The segment eye -> p misses the occluder ball (p itself may be inside it).
            let d = p - eye;
            let t = (-eye.dot(d) / d.length_squared()).clamp(0.0, 1.0);
            (eye + d * t).length() >= ro * (1.0 - 1e-12) || p.length() < ro
        };
        let (mut hidden, mut tested) = (0, 0);
        for _ in 0..4000 {
            let dir = |r: &mut dyn FnMut() -> f64| {
                let z = 2.0 * r() - 1.0;
                let lon = r() * std::f64::consts::TAU;
                let s = (1.0 - z * z).sqrt();
                DVec3::new(s * lon.cos(), s * lon.sin(), z)
            };
            let eye = dir(&mut rand) * (ro + 10f64.powf(rand() * 8.0));
            let centre = dir(&mut rand);
            let cap = rand() * 0.3;
            let r_max = ro + rand() * 20_000.0;
            tested += 1;
            if !below_horizon(eye, ro, centre, cap, r_max) {
                continue;
            }
            hidden += 1;
            let axis = centre.any_orthonormal_vector();
            for k in 0..64 {
                let a = cap * (k % 8) as f64 / 7.0;
                let q = glam::DQuat::from_axis_angle(
                    centre,
                    std::f64::consts::TAU * (k / 8) as f64 / 8.0,
                );
                let p = glam::DQuat::from_axis_angle(q * axis, a) * centre * r_max;
                assert!(!visible(eye, p), "{eye} sees {p}");
            }
        }
        assert!(hidden > tested / 5, "{hidden} of {tested}");
        // Close to the surface, the far side is hidden and the ground below is not.
        let eye = DVec3::Z * (ro + 300.0);
        assert!(below_horizon(eye, ro, DVec3::NEG_Z, 0.1, ro + 9_000.0));
        assert!(!below_horizon(eye, ro, DVec3::Z, 0.001, ro + 9_000.0));
        assert!(!below_horizon(eye, 0.0, DVec3::NEG_Z, 0.1, ro));
    }

    #[test]
    fn planet_up_is_radial_and_planar_up_is_z() {
        let world = SphereWorld {
            radius_m: 3_396_000.0,
            half_side: 8.0,
            value_scale_m: 1.0,
            value_offset_m: 0.0,
            occluder_radius_m: 0.0,
        };
        let eye = DVec3::new(0.0, 0.0, -3_396_001.0);
        assert!((world.up(eye) - DVec3::NEG_Z).length() < 1e-15);
        assert_eq!(world.up(DVec3::ZERO), DVec3::Z);
        let planar = PlanarWorld {
            spacing_m: 30.0,
            value_scale_m: 1.0,
            value_offset_m: 0.0,
        };
        assert_eq!(planar.up(eye), DVec3::Z);
    }
}
