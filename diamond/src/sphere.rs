//! The cube-mapped sphere domain: the surface of the cube `[-S, S]^3`, `S = 2^m`.
//!
//! # Ids
//! A [`SphereId`] is the integer centre of a diamond on the cube surface: at least one
//! coordinate equals `+-S`, all lie in `[-S, S]`. There is one root diamond per face,
//! centred on the face centre. The four children of a face root are centred on the
//! midpoints of the cube edges and straddle two faces (one triangle on each); so does every
//! diamond centred on a cube edge (*edge diamonds*, always of odd level). Every integer
//! point of the surface except the eight cube corners is the centre of exactly one diamond.
//!
//! # Faces and charts
//! Faces are numbered `0..6` = `+X, -X, +Y, -Y, +Z, -Z` ([`POS_X`] .. [`NEG_Z`]): face `f`
//! has normal axis `a = f / 2` and sign `+` for even `f`. Its chart `(u, v)` covers
//! `[0, 2S]^2`:
//!
//! | face | u       | v       |
//! |------|---------|---------|
//! | +X   | `y + S` | `z + S` |
//! | -X   | `z + S` | `y + S` |
//! | +Y   | `z + S` | `x + S` |
//! | -Y   | `x + S` | `z + S` |
//! | +Z   | `x + S` | `y + S` |
//! | -Z   | `y + S` | `x + S` |
//!
//! i.e. `(u, v)` follow the two other axes in cyclic order after `a` on `+` faces and in
//! reverse order on `-` faces, so every chart is right-handed seen from outside the cube
//! (`u x v` = outward normal). Frames are right-handed in their chart (see below), hence
//! every diamond's frame winds the same way seen from outside.
//!
//! # Levels
//! Computed from the chart exactly like the planar domain with `m' = m + 1` (a face side is
//! `2S = 2^(m+1)`): with `t = min(tz(u), tz(v))`, `tz(u) == tz(v)` is an axis-aligned
//! diamond of level `2 (m - t)`, otherwise a rotated one of level `2 (m - t) + 1`. A point on
//! an edge gets the same level from both faces' charts (the edge coordinate is shared and the
//! other one is `0` or `2S` in both). Face roots have level 0; the **deepest level is
//! `2 m + 1`** (97 for `m = MAX_M = 48`).
//!
//! # Frames
//! Corners, children, neighbours and sample positions are computed in the *unfolded chart*
//! of the diamond's **canonical face** (the lower face index for edge diamonds): the other
//! face is rotated into the canonical face's plane about the shared edge, so the chart is
//! extended beyond `[0, 2S]` by up to `S` (at most one coordinate out of range at a time),
//! and results are folded back onto the cube. The frame `[E1, P1, E2, P2]` follows the
//! planar convention in that chart: `E1` is the lexicographically smaller end of the
//! hypotenuse in `(u, v)`, and `P1` makes `cross(P1 - E1, P2 - E1) > 0`. For an edge
//! diamond the vertices `i > j` lie on `P1`'s face, `i < j` on `P2`'s face and the diagonal
//! `i == j` on the shared edge.
//!
//! # Positions on the sphere
//! Positions here are exact integer points on the cube. The recommended cube -> sphere map
//! is the **equal-angle (tangent) map** [`cube_to_unit_sphere`] (inverse
//! [`unit_sphere_to_cube`]): face coordinates `x in [-1, 1]` become `tan(pi x / 4)` before
//! normalising. Its area element varies by a factor `sqrt 2 = 1.414` over a face (largest
//! at the face centre, smallest at edge midpoints; 1.178 x and 0.836 x the mean, measured in
//! the unit tests), against `3 sqrt 3 = 5.2` for plain normalisation (gnomonic). Everitt's
//! cube-to-sphere map measures slightly lower (about 1.32) but has a messy inverse and more
//! angular distortion. The unit-sphere point is then scaled by the radius or ellipsoid and
//! displaced by elevation, in `f64`.

use crate::planar::{frame_order, frame_point};
use crate::{IdError, MAX_M, Orientation, check_size, morton2, push_be, read_be, tz, unmorton2};

/// Face `+X` (index 0).
pub const POS_X: u8 = 0;
/// Face `-X` (index 1).
pub const NEG_X: u8 = 1;
/// Face `+Y` (index 2).
pub const POS_Y: u8 = 2;
/// Face `-Y` (index 3).
pub const NEG_Y: u8 = 3;
/// Face `+Z` (index 4).
pub const POS_Z: u8 = 4;
/// Face `-Z` (index 5).
pub const NEG_Z: u8 = 5;

/// Short names of the faces, by index.
pub const FACE_NAMES: [&str; 6] = ["+X", "-X", "+Y", "-Y", "+Z", "-Z"];

/// A sphere diamond id: the integer centre of the diamond on the cube surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SphereId {
    /// Centre coordinates `[x, y, z]`.
    pub c: [i64; 3],
}

impl SphereId {
    /// A new id (not yet checked against a domain).
    pub const fn new(c: [i64; 3]) -> Self {
        SphereId { c }
    }
}

/// The surface of the cube `[-2^m, 2^m]^3`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SphereDomain {
    m: u32,
}

/// Axes of a face: normal axis `a` with sign `s`, chart axes `b` (u) and `c` (v).
#[derive(Clone, Copy, Debug)]
pub struct Axes {
    /// Normal axis (0 = x, 1 = y, 2 = z).
    pub a: usize,
    /// Sign of the face along its normal axis (+1 or -1).
    pub s: i64,
    /// Axis of the chart's u coordinate.
    pub b: usize,
    /// Axis of the chart's v coordinate.
    pub c: usize,
}

/// Axes of face `face` (< 6).
pub fn axes(face: u8) -> Axes {
    let a = (face / 2) as usize % 3;
    if face.is_multiple_of(2) {
        Axes {
            a,
            s: 1,
            b: (a + 1) % 3,
            c: (a + 2) % 3,
        }
    } else {
        Axes {
            a,
            s: -1,
            b: (a + 2) % 3,
            c: (a + 1) % 3,
        }
    }
}

/// Chart coordinates on `face` of a point lying on that face (half side `s`).
pub fn chart_of(face: u8, p: [i64; 3], s: i64) -> [i64; 2] {
    let ax = axes(face);
    [p[ax.b] + s, p[ax.c] + s]
}

/// Chart coordinates on `face` (half side `s`) of a point `p` on the cube surface that lies
/// on `face` or on `across`, a face adjacent to it: points on `across` are unfolded across
/// the edge the two faces share (the inverse of the folding that maps unfolded charts onto
/// the cube). `None` when `p` is on neither face or the faces are not adjacent.
pub fn unfold(face: u8, across: Option<u8>, p: [i64; 3], s: i64) -> Option<[i64; 2]> {
    let ax = axes(face);
    if p[ax.a] == ax.s * s {
        return Some(chart_of(face, p, s));
    }
    let g = across.filter(|&g| g < 6)?;
    let gx = axes(g);
    if gx.a == ax.a || p[gx.a] != gx.s * s {
        return None;
    }
    // Distance from the shared edge, measured on `g`; unfolded it continues past the edge.
    let d = s - ax.s * p[ax.a];
    let mut q = p;
    q[gx.a] = gx.s * (s + d);
    q[ax.a] = ax.s * s;
    Some(chart_of(face, q, s))
}

/// Maps a point of the unfolded chart of `face` (half side `s`) back onto the cube surface.
/// A coordinate outside `[0, 2s]` is carried across that edge onto the adjacent face; at
/// most one coordinate may be out of range, and by at most `2s`.
fn fold(face: u8, uv: [i64; 2], s: i64) -> Result<[i64; 3], IdError> {
    let ax = axes(face);
    let bad = || IdError::OutOfDomain([uv[0], uv[1], face as i64]);
    let (mut xa, mut xb, mut xc) = (ax.s * s, uv[0] - s, uv[1] - s);
    let (ob, oc) = (!(-s..=s).contains(&xb), !(-s..=s).contains(&xc));
    if ob && oc {
        return Err(bad());
    }
    for (x, out) in [(&mut xb, ob), (&mut xc, oc)] {
        if out {
            let d = x.abs() - s;
            if d > 2 * s {
                return Err(bad());
            }
            *x = x.signum() * s;
            xa = ax.s * (s - d);
        }
    }
    let mut p = [0; 3];
    p[ax.a] = xa;
    p[ax.b] = xb;
    p[ax.c] = xc;
    Ok(p)
}

/// A diamond's canonical face, its other face (edge diamonds) and its frame corners in
/// the canonical face's unfolded chart ([`SphereDomain::chart_frame`]).
pub type ChartFrame = (u8, Option<u8>, [[i64; 2]; 4]);

/// Level, exponent and canonical chart of a checked id.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Info {
    /// Canonical face (the lower index for edge points).
    face: u8,
    /// The second face of an edge point.
    other: Option<u8>,
    /// Chart coordinates on the canonical face.
    uv: [i64; 2],
    level: u32,
    t: u32,
}

impl SphereDomain {
    /// The cube `[-2^m, 2^m]^3`; `m` in `1..=MAX_M`.
    pub fn new(m: u32) -> Result<Self, IdError> {
        if (1..=MAX_M).contains(&m) {
            Ok(SphereDomain { m })
        } else {
            Err(IdError::BadExponent(m))
        }
    }

    /// The exponent `m`.
    pub fn m(&self) -> u32 {
        self.m
    }

    /// The half side `S = 2^m` of the cube in id units (a face chart spans `[0, 2S]`).
    pub fn size(&self) -> i64 {
        1i64 << self.m
    }

    /// The six face roots (level 0), centred on the face centres, in face order.
    pub fn roots(&self) -> [SphereId; 6] {
        let s = self.size();
        [
            SphereId::new([s, 0, 0]),
            SphereId::new([-s, 0, 0]),
            SphereId::new([0, s, 0]),
            SphereId::new([0, -s, 0]),
            SphereId::new([0, 0, s]),
            SphereId::new([0, 0, -s]),
        ]
    }

    /// The deepest level any id of this domain can have (`2 m + 1`).
    pub fn max_level(&self) -> u32 {
        2 * self.m + 1
    }

    /// Whether a point lies on the cube surface.
    pub fn on_surface(&self, p: [i64; 3]) -> bool {
        let s = self.size();
        p.iter().all(|x| (-s..=s).contains(x)) && p.iter().any(|&x| x == s || x == -s)
    }

    fn info(&self, id: SphereId) -> Result<Info, IdError> {
        let s = self.size();
        let p = id.c;
        if !p.iter().all(|x| (-s..=s).contains(x)) {
            return Err(IdError::OutOfDomain(p));
        }
        let mut faces = [0u8; 3];
        let mut n = 0;
        for (axis, &x) in p.iter().enumerate() {
            if x == s || x == -s {
                faces[n] = 2 * axis as u8 + u8::from(x == -s);
                n += 1;
            }
        }
        match n {
            0 => return Err(IdError::OutOfDomain(p)),
            3 => return Err(IdError::NotACentre(p)),
            _ => {}
        }
        let face = faces[0];
        let other = (n == 2).then_some(faces[1]);
        let uv = chart_of(face, p, s);
        let (tu, tv) = (tz(uv[0]), tz(uv[1]));
        let t = tu.min(tv);
        if t > self.m {
            return Err(IdError::NotACentre(p));
        }
        let level = if tu == tv {
            2 * (self.m - t)
        } else {
            2 * (self.m - t) + 1
        };
        Ok(Info {
            face,
            other,
            uv,
            level,
            t,
        })
    }

    /// Checks that `id` is the centre of a diamond of this domain.
    pub fn check(&self, id: SphereId) -> Result<(), IdError> {
        self.info(id).map(|_| ())
    }

    /// The level of a diamond (face roots = 0).
    pub fn level(&self, id: SphereId) -> Result<u32, IdError> {
        Ok(self.info(id)?.level)
    }

    /// Axis-aligned in its face chart (even level) or rotated (odd level).
    pub fn orientation(&self, id: SphereId) -> Result<Orientation, IdError> {
        Ok(Orientation::of_level(self.level(id)?))
    }

    /// Half of the diagonal of a rotated diamond / half the side of an axis-aligned one.
    pub fn half_extent(&self, id: SphereId) -> Result<i64, IdError> {
        Ok(1i64 << self.info(id)?.t)
    }

    /// The half-size exponent `t` shared by all diamonds of a level (`m - level / 2`).
    /// `level` must not exceed [`SphereDomain::max_level`].
    pub fn level_exponent(&self, level: u32) -> u32 {
        self.m.saturating_sub(level / 2)
    }

    /// The faces of a diamond: its canonical face and, for edge diamonds (centred on a
    /// cube edge, one triangle on each face), the second, higher-index face.
    pub fn faces(&self, id: SphereId) -> Result<(u8, Option<u8>), IdError> {
        let info = self.info(id)?;
        Ok((info.face, info.other))
    }

    /// Chart coordinates `(u, v)` of the centre on `face`, which must be one of its faces
    /// (an edge centre has a chart position on both faces).
    pub fn face_chart(&self, id: SphereId, face: u8) -> Result<[i64; 2], IdError> {
        let info = self.info(id)?;
        if face == info.face || Some(face) == info.other {
            Ok(chart_of(face, id.c, self.size()))
        } else {
            Err(IdError::OutOfDomain(id.c))
        }
    }

    /// The id centred at chart point `(u, v)` of `face`; `u, v` in `[0, 2S]`.
    pub fn from_face_chart(&self, face: u8, uv: [i64; 2]) -> Result<SphereId, IdError> {
        let s = self.size();
        if face >= 6 || !uv.iter().all(|x| (0..=2 * s).contains(x)) {
            return Err(IdError::OutOfDomain([uv[0], uv[1], face as i64]));
        }
        let id = SphereId::new(fold(face, uv, s)?);
        self.check(id)?;
        Ok(id)
    }

    /// The frame corners `[E1, P1, E2, P2]` in the unfolded chart of the canonical face,
    /// with that face and (edge diamonds) the other face; every point of the diamond
    /// unfolds into this chart with [`unfold`].
    pub fn chart_frame(&self, id: SphereId) -> Result<ChartFrame, IdError> {
        let info = self.info(id)?;
        Ok((info.face, info.other, self.chart_corners(&info)))
    }

    /// Corners in the unfolded chart of the canonical face, frame order.
    fn chart_corners(&self, info: &Info) -> [[i64; 2]; 4] {
        let [cu, cv] = info.uv;
        let h = 1i64 << info.t;
        if info.level == 0 {
            let s2 = 2 * self.size();
            return [[0, 0], [s2, 0], [s2, s2], [0, s2]];
        }
        let (ends, parents) = if info.level % 2 == 1 {
            if tz(cv) > tz(cu) {
                ([[cu - h, cv], [cu + h, cv]], [[cu, cv - h], [cu, cv + h]])
            } else {
                ([[cu, cv - h], [cu, cv + h]], [[cu - h, cv], [cu + h, cv]])
            }
        } else {
            // Axis-aligned diamonds of level >= 2 lie inside one face.
            let all = [
                [cu - h, cv - h],
                [cu + h, cv - h],
                [cu + h, cv + h],
                [cu - h, cv + h],
            ];
            let is_parent = |p: &[i64; 2]| {
                let (a, b) = (tz(p[0]), tz(p[1]));
                a != b && a.min(b) == info.t + 1
            };
            let mut ends = [[0; 2]; 2];
            let mut parents = [[0; 2]; 2];
            let (mut ne, mut np) = (0, 0);
            for p in all {
                if is_parent(&p) {
                    parents[np.min(1)] = p;
                    np += 1;
                } else {
                    ends[ne.min(1)] = p;
                    ne += 1;
                }
            }
            debug_assert!(ne == 2 && np == 2);
            (ends, parents)
        };
        frame_order(ends, parents)
    }

    fn fold_id(&self, face: u8, uv: [i64; 2]) -> Result<SphereId, IdError> {
        fold(face, uv, self.size()).map(SphereId::new)
    }

    /// Corners in frame order `[E1, P1, E2, P2]` as points on the cube surface. Corners of
    /// face roots and of level-1 edge diamonds include cube corners.
    pub fn corners(&self, id: SphereId) -> Result<[[i64; 3]; 4], IdError> {
        let info = self.info(id)?;
        let c = self.chart_corners(&info);
        let s = self.size();
        Ok([
            fold(info.face, c[0], s)?,
            fold(info.face, c[1], s)?,
            fold(info.face, c[2], s)?,
            fold(info.face, c[3], s)?,
        ])
    }

    /// Parents in frame order `[P1, P2]` (none for face roots, otherwise always 2). A parent
    /// of an edge diamond lies on each of its faces.
    pub fn parents(&self, id: SphereId) -> Result<Vec<SphereId>, IdError> {
        let info = self.info(id)?;
        if info.level == 0 {
            return Ok(Vec::new());
        }
        let c = self.chart_corners(&info);
        Ok(vec![
            self.fold_id(info.face, c[1])?,
            self.fold_id(info.face, c[3])?,
        ])
    }

    /// Children centred on the midpoints of the sides, in side order (side `k` joins corners
    /// `k` and `k+1`): always 4, none at the deepest level.
    pub fn children(&self, id: SphereId) -> Result<Vec<SphereId>, IdError> {
        let info = self.info(id)?;
        if info.level >= self.max_level() {
            return Ok(Vec::new());
        }
        let c = self.chart_corners(&info);
        (0..4)
            .map(|k| {
                let (a, b) = (c[k], c[(k + 1) % 4]);
                self.fold_id(info.face, [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2])
            })
            .collect()
    }

    /// The same-level neighbour across each side (side `k` joins corners `k` and `k+1`).
    /// The cube is closed, so there is always one.
    pub fn neighbours(&self, id: SphereId) -> Result<[SphereId; 4], IdError> {
        let info = self.info(id)?;
        let c = self.chart_corners(&info);
        let mut out = [id; 4];
        for (k, slot) in out.iter_mut().enumerate() {
            let (a, b) = (c[k], c[(k + 1) % 4]);
            *slot = self.fold_id(
                info.face,
                [a[0] + b[0] - info.uv[0], a[1] + b[1] - info.uv[1]],
            )?;
        }
        Ok(out)
    }

    /// Position of vertex `(i, j)`, `0 <= i, j <= n`, in sample units (id units x `2 n`),
    /// as a point on the cube surface of half side `S * 2 n`.
    pub fn vertex_position(
        &self,
        id: SphereId,
        n: usize,
        i: usize,
        j: usize,
    ) -> Result<[i64; 3], IdError> {
        check_size(n)?;
        if i > n || j > n {
            return Err(IdError::BadIndex(i, j));
        }
        self.sample_position(id, n, 2 * i as i64, 2 * j as i64)
    }

    /// Position of cell centre `(i, j)`, `0 <= i, j < n`, in sample units, on the cube
    /// surface.
    pub fn cell_position(
        &self,
        id: SphereId,
        n: usize,
        i: usize,
        j: usize,
    ) -> Result<[i64; 3], IdError> {
        check_size(n)?;
        if i >= n || j >= n {
            return Err(IdError::BadIndex(i, j));
        }
        self.sample_position(id, n, 2 * i as i64 + 1, 2 * j as i64 + 1)
    }

    fn sample_position(&self, id: SphereId, n: usize, p: i64, q: i64) -> Result<[i64; 3], IdError> {
        let info = self.info(id)?;
        let c = self.chart_corners(&info);
        fold(
            info.face,
            frame_point(&c, n, p, q),
            self.size() * 2 * n as i64,
        )
    }

    /// Storage key: one level byte, one face byte (the canonical face), then the Morton code
    /// of the canonical chart position divided by the level's coordinate step, in a fixed
    /// number of big-endian bytes per level. Keys sort by (level, face, Morton code).
    pub fn key(&self, id: SphereId) -> Result<Vec<u8>, IdError> {
        let info = self.info(id)?;
        let bits = self.m - info.t + 2;
        let code = morton2(
            (info.uv[0] >> info.t) as u64,
            (info.uv[1] >> info.t) as u64,
            bits,
        );
        let mut out = Vec::with_capacity(2 + key_bytes(bits));
        out.push(info.level as u8);
        out.push(info.face);
        push_be(&mut out, code, key_bytes(bits));
        Ok(out)
    }

    /// Inverse of [`SphereDomain::key`]; any malformed or non-canonical key is an error.
    pub fn id_from_key(&self, key: &[u8]) -> Result<SphereId, IdError> {
        let [level, face, rest @ ..] = key else {
            return Err(IdError::BadKey("key shorter than its header"));
        };
        let (level, face) = (*level as u32, *face);
        if level > self.max_level() {
            return Err(IdError::BadKey("level deeper than the domain allows"));
        }
        if face >= 6 {
            return Err(IdError::BadKey("face index out of range"));
        }
        let t = self.level_exponent(level);
        let bits = self.m - t + 2;
        if rest.len() != key_bytes(bits) {
            return Err(IdError::BadKey("wrong length for its level"));
        }
        let code = read_be(rest);
        if code >> (2 * bits) != 0 {
            return Err(IdError::BadKey("stray high bits"));
        }
        let (a, b) = unmorton2(code, bits);
        let uv = [(a as i64) << t, (b as i64) << t];
        let s = self.size();
        if !uv.iter().all(|x| (0..=2 * s).contains(x)) {
            return Err(IdError::BadKey("position outside the face"));
        }
        let id = SphereId::new(
            fold(face, uv, s).map_err(|_| IdError::BadKey("position outside the face"))?,
        );
        match self.info(id) {
            Ok(info) if info.level == level && info.face == face => Ok(id),
            Ok(_) => Err(IdError::BadKey("not a canonical centre of its level")),
            Err(_) => Err(IdError::BadKey("not a centre")),
        }
    }
}

/// Number of key bytes after the header for `bits` bits per coordinate.
fn key_bytes(bits: u32) -> usize {
    (2 * bits).div_ceil(8) as usize
}

/// The equal-angle (tangent) cube -> unit sphere map.
///
/// `p` is any non-zero point; it is first scaled onto the cube `[-1, 1]^3` (so sample
/// positions in any unit can be passed directly). On a face with normal axis `a`, the other
/// two coordinates `x` become `tan(pi x / 4)`, then the point is normalised. Max/min area
/// element ratio over a face: `sqrt 2 = 1.414` (see the module docs). The origin and
/// non-finite inputs are returned unchanged.
pub fn cube_to_unit_sphere(p: [f64; 3]) -> [f64; 3] {
    let big = p.iter().fold(0.0f64, |acc, x| acc.max(x.abs()));
    if big == 0.0 || !p.iter().all(|x| x.is_finite()) {
        return p;
    }
    let mut q = [0.0; 3];
    for k in 0..3 {
        let x = p[k] / big;
        q[k] = if p[k].abs() == big {
            x.signum()
        } else {
            (std::f64::consts::FRAC_PI_4 * x).tan()
        };
    }
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
    [q[0] / norm, q[1] / norm, q[2] / norm]
}

/// Inverse of [`cube_to_unit_sphere`]: a point of the unit sphere (any non-zero direction)
/// to the cube `[-1, 1]^3`. The origin and non-finite inputs are returned unchanged.
pub fn unit_sphere_to_cube(q: [f64; 3]) -> [f64; 3] {
    let big = q.iter().fold(0.0f64, |acc, x| acc.max(x.abs()));
    if big == 0.0 || !q.iter().all(|x| x.is_finite()) {
        return q;
    }
    let mut p = [0.0; 3];
    for k in 0..3 {
        p[k] = if q[k].abs() == big {
            q[k].signum()
        } else {
            (q[k] / big).atan() / std::f64::consts::FRAC_PI_4
        };
    }
    p
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn walk(d: &SphereDomain, mut id: SphereId, seed: &mut u64, depth: usize) -> Vec<SphereId> {
        let mut out = vec![id];
        for _ in 0..depth {
            let kids = d.children(id).unwrap();
            if kids.is_empty() {
                break;
            }
            *seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            id = kids[(*seed >> 33) as usize % kids.len()];
            out.push(id);
        }
        out
    }

    #[test]
    fn charts_are_right_handed_from_outside() {
        for face in 0..6u8 {
            let ax = axes(face);
            let (mut eb, mut ec) = ([0i64; 3], [0i64; 3]);
            eb[ax.b] = 1;
            ec[ax.c] = 1;
            let cross = [
                eb[1] * ec[2] - eb[2] * ec[1],
                eb[2] * ec[0] - eb[0] * ec[2],
                eb[0] * ec[1] - eb[1] * ec[0],
            ];
            let mut normal = [0i64; 3];
            normal[ax.a] = ax.s;
            assert_eq!(cross, normal, "face {}", FACE_NAMES[face as usize]);
        }
    }

    #[test]
    fn roots_and_edge_children() {
        let d = SphereDomain::new(3).unwrap();
        let s = d.size();
        for (f, r) in d.roots().into_iter().enumerate() {
            assert_eq!(d.level(r).unwrap(), 0);
            assert_eq!(d.faces(r).unwrap(), (f as u8, None));
            assert!(d.parents(r).unwrap().is_empty());
            for c in d.corners(r).unwrap() {
                assert!(
                    c.iter().all(|x| x.abs() == s),
                    "root corners are cube corners"
                );
            }
            let kids = d.children(r).unwrap();
            assert_eq!(kids.len(), 4);
            for k in kids {
                assert_eq!(d.level(k).unwrap(), 1);
                assert!(d.faces(k).unwrap().1.is_some());
                let ps = d.parents(k).unwrap();
                assert_eq!(ps.len(), 2);
                assert!(ps.contains(&r));
                assert!(ps.iter().all(|p| d.level(*p).unwrap() == 0));
            }
            let nb = d.neighbours(r).unwrap();
            for n in nb {
                assert_eq!(d.level(n).unwrap(), 0);
                assert_ne!(n, r);
                assert_ne!(n.c, r.c.map(|x| -x), "the opposite face is not a neighbour");
            }
        }
    }

    #[test]
    fn corners_and_interior_points_are_rejected() {
        let d = SphereDomain::new(2).unwrap();
        let s = d.size();
        for x in [-s, s] {
            for y in [-s, s] {
                for z in [-s, s] {
                    assert!(matches!(
                        d.check(SphereId::new([x, y, z])),
                        Err(IdError::NotACentre(_))
                    ));
                }
            }
        }
        assert!(matches!(
            d.check(SphereId::new([0, 0, 0])),
            Err(IdError::OutOfDomain(_))
        ));
        assert!(matches!(
            d.check(SphereId::new([s + 1, 0, 0])),
            Err(IdError::OutOfDomain(_))
        ));
        assert!(matches!(
            d.check(SphereId::new([i64::MIN, i64::MAX, s])),
            Err(IdError::OutOfDomain(_))
        ));
        assert!(SphereDomain::new(0).is_err());
        assert!(SphereDomain::new(MAX_M + 1).is_err());
    }

    #[test]
    fn every_surface_point_but_corners_is_a_centre_with_consistent_edge_levels() {
        let d = SphereDomain::new(3).unwrap();
        let s = d.size();
        let mut count = 0;
        for x in -s..=s {
            for y in -s..=s {
                for z in -s..=s {
                    let p = [x, y, z];
                    if !d.on_surface(p) {
                        continue;
                    }
                    let id = SphereId::new(p);
                    let on = p.iter().filter(|v| v.abs() == s).count();
                    if on == 3 {
                        assert!(d.check(id).is_err());
                        continue;
                    }
                    let info = d.info(id).unwrap();
                    count += 1;
                    if let Some(g) = info.other {
                        assert_eq!(info.level % 2, 1, "edge diamonds are rotated");
                        // Level from the other face's chart.
                        let uv = chart_of(g, p, s);
                        let (tu, tv) = (tz(uv[0]), tz(uv[1]));
                        let t = tu.min(tv);
                        let level = if tu == tv {
                            2 * (d.m - t)
                        } else {
                            2 * (d.m - t) + 1
                        };
                        assert_eq!((level, t), (info.level, info.t), "{p:?}");
                    }
                    // Key round trip.
                    assert_eq!(d.id_from_key(&d.key(id).unwrap()).unwrap(), id);
                }
            }
        }
        // 6 faces of (2S+1)^2 points, edges counted twice, corners thrice, minus 8 corners.
        let n = 2 * s + 1;
        assert_eq!(count, 6 * n * n - 12 * n + 8 - 8);
    }

    #[test]
    fn fold_round_trips_unfolded_charts() {
        let s = 8;
        for face in 0..6u8 {
            for u in -s..=3 * s {
                for v in -s..=3 * s {
                    let out_u = !(0..=2 * s).contains(&u);
                    let out_v = !(0..=2 * s).contains(&v);
                    let r = fold(face, [u, v], s);
                    if out_u && out_v {
                        assert!(r.is_err());
                        continue;
                    }
                    let p = r.unwrap();
                    assert!(p.iter().all(|x| x.abs() <= s) && p.iter().any(|x| x.abs() == s));
                    // Unfolding distance is preserved: the folded point is as far from the
                    // face plane (along the surface) as the chart point from the face.
                    let ax = axes(face);
                    let beyond = (-u).max(u - 2 * s).max(-v).max(v - 2 * s).max(0);
                    assert_eq!(s - ax.s * p[ax.a], beyond);
                }
            }
        }
    }

    #[test]
    fn unfold_inverts_fold_across_each_edge() {
        let s = 8;
        for face in 0..6u8 {
            let ax = axes(face);
            for u in -2 * s..=4 * s {
                for v in -2 * s..=4 * s {
                    let Ok(p) = fold(face, [u, v], s) else {
                        continue;
                    };
                    let across = if (0..=2 * s).contains(&u) && (0..=2 * s).contains(&v) {
                        None
                    } else {
                        let (axis, x) = if (0..=2 * s).contains(&u) {
                            (ax.c, v)
                        } else {
                            (ax.b, u)
                        };
                        Some(2 * axis as u8 + u8::from(x < s))
                    };
                    assert_eq!(unfold(face, across, p, s), Some([u, v]), "{face} {u} {v}");
                }
            }
            // A point on the opposite face is on neither.
            let mut far = [0; 3];
            far[ax.a] = -ax.s * s;
            assert_eq!(unfold(face, None, far, s), None);
        }
    }

    #[test]
    fn hierarchy_walks_at_max_m_do_not_overflow() {
        let d = SphereDomain::new(MAX_M).unwrap();
        let mut seed = 7u64;
        for r in d.roots() {
            for _ in 0..8 {
                let path = walk(&d, r, &mut seed, 200);
                let last = *path.last().unwrap();
                assert_eq!(d.level(last).unwrap(), d.max_level());
                assert!(d.children(last).unwrap().is_empty());
                for id in [path[0], path[1], last] {
                    for (i, j) in [
                        (0, 0),
                        (MAX_N_USIZE, 0),
                        (0, MAX_N_USIZE),
                        (MAX_N_USIZE, MAX_N_USIZE),
                    ] {
                        let p = d.vertex_position(id, MAX_N_USIZE, i, j).unwrap();
                        let big = d.size() * 2 * MAX_N_USIZE as i64;
                        assert!(
                            p.iter().all(|x| x.abs() <= big) && p.iter().any(|x| x.abs() == big)
                        );
                    }
                    d.neighbours(id).unwrap();
                    d.parents(id).unwrap();
                }
            }
        }
    }

    const MAX_N_USIZE: usize = super::super::MAX_N;

    #[test]
    fn equal_angle_map_area_distortion() {
        // Area of small grid cells of one face mapped to the sphere.
        let k = 256;
        let h = 2.0 / k as f64;
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        let mut total = 0.0;
        let tri = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| {
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let x = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
        };
        for i in 0..k {
            for j in 0..k {
                let (x, y) = (-1.0 + i as f64 * h, -1.0 + j as f64 * h);
                let p = [[x, y], [x + h, y], [x + h, y + h], [x, y + h]]
                    .map(|[a, b]| cube_to_unit_sphere([1.0, a, b]));
                let area = tri(p[0], p[1], p[2]) + tri(p[0], p[2], p[3]);
                lo = lo.min(area);
                hi = hi.max(area);
                total += area;
            }
        }
        let mean = total / (k * k) as f64;
        let ratio = hi / lo;
        assert!(
            (ratio - std::f64::consts::SQRT_2).abs() < 0.01,
            "max/min area ratio {ratio}"
        );
        assert!((hi / mean - 1.178).abs() < 0.005, "max/mean {}", hi / mean);
        assert!((lo / mean - 0.836).abs() < 0.005, "min/mean {}", lo / mean);
        // The face covers a sixth of the sphere.
        assert!((total - 4.0 * std::f64::consts::PI / 6.0).abs() < 1e-3);
    }

    #[test]
    fn equal_angle_map_round_trips() {
        for &p in &[
            [1.0, 0.3, -0.7],
            [-0.2, -1.0, 0.99],
            [0.5, 0.5, 1.0],
            [1.0, 1.0, 1.0],
            [0.0, 0.0, -1.0],
        ] {
            let q = cube_to_unit_sphere(p);
            assert!(((q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) - 1.0).abs() < 1e-12);
            let back = unit_sphere_to_cube(q);
            for k in 0..3 {
                assert!((back[k] - p[k]).abs() < 1e-12, "{p:?} -> {q:?} -> {back:?}");
            }
        }
        assert_eq!(cube_to_unit_sphere([0.0; 3]), [0.0; 3]);
        assert!(cube_to_unit_sphere([f64::NAN, 0.0, 1.0])[0].is_nan());
    }
}
