//! The planar domain: the square `[0, S]^2`, `S = 2^m`, with one root diamond.
//!
//! With `t = min(tz(x), tz(y))` (`tz(0)` = infinity): `tz(x) == tz(y)` is an axis-aligned
//! diamond of level `2 (m - 1 - t)`, otherwise a rotated one of level `2 (m - t) - 1`.
//! Every integer point of the domain except its four corners is the centre of exactly one
//! diamond. Rotated diamonds centred on the border are *half diamonds*: one triangle in the
//! domain, one parent, two children.

use crate::{IdError, MAX_M, Orientation, check_size, morton2, push_be, read_be, tz, unmorton2};

/// A planar diamond id: the integer centre of the diamond.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PlanarId {
    /// Centre x (east).
    pub x: i64,
    /// Centre y.
    pub y: i64,
}

impl PlanarId {
    /// A new id (not yet checked against a domain).
    pub const fn new(x: i64, y: i64) -> Self {
        PlanarId { x, y }
    }
}

/// The planar domain `[0, 2^m]^2`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PlanarDomain {
    m: u32,
}

/// Level and half-size exponent of a checked id.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Info {
    level: u32,
    t: u32,
}

impl PlanarDomain {
    /// The domain `[0, 2^m]^2`; `m` in `1..=MAX_M`.
    pub fn new(m: u32) -> Result<Self, IdError> {
        if (1..=MAX_M).contains(&m) {
            Ok(PlanarDomain { m })
        } else {
            Err(IdError::BadExponent(m))
        }
    }

    /// The exponent `m`.
    pub fn m(&self) -> u32 {
        self.m
    }

    /// The side `S = 2^m` in id units.
    pub fn size(&self) -> i64 {
        1i64 << self.m
    }

    /// The root diamond (level 0), centred at `(S/2, S/2)`.
    pub fn root(&self) -> PlanarId {
        PlanarId::new(self.size() / 2, self.size() / 2)
    }

    /// The deepest level any id of this domain can have (`2 m - 1`).
    pub fn max_level(&self) -> u32 {
        2 * self.m - 1
    }

    /// Whether a point lies in the closed domain square.
    pub fn contains(&self, x: i64, y: i64) -> bool {
        let s = self.size();
        (0..=s).contains(&x) && (0..=s).contains(&y)
    }

    fn info(&self, id: PlanarId) -> Result<Info, IdError> {
        if !self.contains(id.x, id.y) {
            return Err(IdError::OutOfDomain([id.x, id.y, 0]));
        }
        let (tx, ty) = (tz(id.x), tz(id.y));
        let t = tx.min(ty);
        if t >= self.m {
            return Err(IdError::NotACentre([id.x, id.y, 0]));
        }
        let level = if tx == ty {
            2 * (self.m - 1 - t)
        } else {
            2 * (self.m - t) - 1
        };
        Ok(Info { level, t })
    }

    /// Checks that `id` is the centre of a diamond of this domain.
    pub fn check(&self, id: PlanarId) -> Result<(), IdError> {
        self.info(id).map(|_| ())
    }

    /// The level of a diamond (root = 0).
    pub fn level(&self, id: PlanarId) -> Result<u32, IdError> {
        Ok(self.info(id)?.level)
    }

    /// Axis-aligned (even level) or rotated (odd level).
    pub fn orientation(&self, id: PlanarId) -> Result<Orientation, IdError> {
        Ok(Orientation::of_level(self.level(id)?))
    }

    /// Half of the diagonal of a rotated diamond / half the side of an axis-aligned one.
    pub fn half_extent(&self, id: PlanarId) -> Result<i64, IdError> {
        Ok(1i64 << self.info(id)?.t)
    }

    /// Corners in frame order `[E1, P1, E2, P2]` (see the module docs of `diamond`).
    /// Corners of half diamonds may lie outside the domain.
    pub fn corners(&self, id: PlanarId) -> Result<[[i64; 2]; 4], IdError> {
        let info = self.info(id)?;
        let (cx, cy) = (id.x, id.y);
        let h = 1i64 << info.t;
        if info.level == 0 {
            let s = self.size();
            return Ok([[0, 0], [s, 0], [s, s], [0, s]]);
        }
        let (ends, parents) = if info.level % 2 == 1 {
            if tz(cy) > tz(cx) {
                ([[cx - h, cy], [cx + h, cy]], [[cx, cy - h], [cx, cy + h]])
            } else {
                ([[cx, cy - h], [cx, cy + h]], [[cx - h, cy], [cx + h, cy]])
            }
        } else {
            let all = [
                [cx - h, cy - h],
                [cx + h, cy - h],
                [cx + h, cy + h],
                [cx - h, cy + h],
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
        Ok(frame_order(ends, parents))
    }

    /// Parents (0 for the root, 1 for border half diamonds, else 2), in frame order.
    pub fn parents(&self, id: PlanarId) -> Result<Vec<PlanarId>, IdError> {
        let level = self.level(id)?;
        if level == 0 {
            return Ok(Vec::new());
        }
        let c = self.corners(id)?;
        Ok([c[1], c[3]]
            .into_iter()
            .filter(|p| self.contains(p[0], p[1]))
            .map(|p| PlanarId::new(p[0], p[1]))
            .collect())
    }

    /// Children centred on the midpoints of the sides, in side order, in-domain only
    /// (4, or 2 for half diamonds). Children of the deepest level are not ids (empty).
    pub fn children(&self, id: PlanarId) -> Result<Vec<PlanarId>, IdError> {
        let level = self.level(id)?;
        if level >= self.max_level() {
            return Ok(Vec::new());
        }
        let c = self.corners(id)?;
        Ok((0..4)
            .map(|k| {
                let (a, b) = (c[k], c[(k + 1) % 4]);
                [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2]
            })
            .filter(|p| self.contains(p[0], p[1]))
            .map(|p| PlanarId::new(p[0], p[1]))
            .collect())
    }

    /// The same-level neighbour across each side (side `k` joins corners `k` and `k+1`),
    /// `None` where the side lies on the domain border.
    pub fn neighbours(&self, id: PlanarId) -> Result<[Option<PlanarId>; 4], IdError> {
        let c = self.corners(id)?;
        let mut out = [None; 4];
        for (k, slot) in out.iter_mut().enumerate() {
            let (a, b) = (c[k], c[(k + 1) % 4]);
            let (x, y) = (a[0] + b[0] - id.x, a[1] + b[1] - id.y);
            if self.contains(x, y) && self.check(PlanarId::new(x, y)).is_ok() {
                *slot = Some(PlanarId::new(x, y));
            }
        }
        Ok(out)
    }

    /// Whether the diamond is a border half diamond (only one triangle in the domain).
    pub fn is_half(&self, id: PlanarId) -> Result<bool, IdError> {
        let level = self.level(id)?;
        let s = self.size();
        Ok(level % 2 == 1 && (id.x == 0 || id.y == 0 || id.x == s || id.y == s))
    }

    /// Position of vertex `(i, j)`, `0 <= i, j <= n`, in sample units (id units x `2 n`).
    pub fn vertex_position(
        &self,
        id: PlanarId,
        n: usize,
        i: usize,
        j: usize,
    ) -> Result<[i64; 2], IdError> {
        check_size(n)?;
        if i > n || j > n {
            return Err(IdError::BadIndex(i, j));
        }
        let c = self.corners(id)?;
        Ok(frame_point(&c, n, 2 * i as i64, 2 * j as i64))
    }

    /// Position of cell centre `(i, j)`, `0 <= i, j < n`, in sample units.
    pub fn cell_position(
        &self,
        id: PlanarId,
        n: usize,
        i: usize,
        j: usize,
    ) -> Result<[i64; 2], IdError> {
        check_size(n)?;
        if i >= n || j >= n {
            return Err(IdError::BadIndex(i, j));
        }
        let c = self.corners(id)?;
        Ok(frame_point(&c, n, 2 * i as i64 + 1, 2 * j as i64 + 1))
    }

    /// Storage key: one level byte, then the Morton code of the centre (divided by the
    /// level's coordinate step) in a fixed number of big-endian bytes per level. Sorting
    /// keys groups a level together and keeps nearby diamonds nearby.
    pub fn key(&self, id: PlanarId) -> Result<Vec<u8>, IdError> {
        let info = self.info(id)?;
        let bits = self.m - info.t + 1;
        let code = morton2((id.x >> info.t) as u64, (id.y >> info.t) as u64, bits);
        let mut out = Vec::with_capacity(1 + key_bytes(bits));
        out.push(info.level as u8);
        push_be(&mut out, code, key_bytes(bits));
        Ok(out)
    }

    /// Inverse of [`PlanarDomain::key`]; any malformed key is an error.
    pub fn id_from_key(&self, key: &[u8]) -> Result<PlanarId, IdError> {
        let (&level, rest) = key.split_first().ok_or(IdError::BadKey("empty key"))?;
        let level = level as u32;
        if level > self.max_level() {
            return Err(IdError::BadKey("level deeper than the domain allows"));
        }
        let t = self.level_exponent(level);
        let bits = self.m - t + 1;
        if rest.len() != key_bytes(bits) {
            return Err(IdError::BadKey("wrong length for its level"));
        }
        let code = read_be(rest);
        if code >> (2 * bits) != 0 {
            return Err(IdError::BadKey("stray high bits"));
        }
        let (a, b) = unmorton2(code, bits);
        let id = PlanarId::new((a as i64) << t, (b as i64) << t);
        match self.info(id) {
            Ok(info) if info.level == level => Ok(id),
            _ => Err(IdError::BadKey("not a centre of its level")),
        }
    }

    /// The half-size exponent `t` shared by all diamonds of a level.
    pub fn level_exponent(&self, level: u32) -> u32 {
        if level.is_multiple_of(2) {
            self.m - 1 - level / 2
        } else {
            self.m - level.div_ceil(2)
        }
    }

    /// All diamonds of a level whose closed square meets the rectangle
    /// `[x0, x1] x [y0, y1]` (id units), in row-major order of their centres.
    pub fn diamonds_meeting(&self, level: u32, rect: [i64; 4]) -> Vec<PlanarId> {
        let [x0, x1, y0, y1] = rect;
        let t = self.level_exponent(level);
        let h = 1i64 << t;
        let s = self.size();
        let mut out = Vec::new();
        let ylo = (y0 - h).max(0);
        let yhi = (y1 + h).min(s);
        let mut y = ylo - ylo.rem_euclid(h);
        while y <= yhi {
            let xlo = (x0 - h).max(0);
            let xhi = (x1 + h).min(s);
            let mut x = xlo - xlo.rem_euclid(h);
            while x <= xhi {
                let id = PlanarId::new(x, y);
                if let Ok(info) = self.info(id)
                    && info.level == level
                    && self.square_meets(id, h, level, rect)
                {
                    out.push(id);
                }
                x += h;
            }
            y += h;
        }
        out
    }

    fn square_meets(&self, id: PlanarId, h: i64, level: u32, [x0, x1, y0, y1]: [i64; 4]) -> bool {
        let (cx, cy) = (id.x, id.y);
        if level.is_multiple_of(2) {
            cx + h >= x0 && cx - h <= x1 && cy + h >= y0 && cy - h <= y1
        } else {
            // |x - cx| + |y - cy| <= h meets the box: distance from centre to box in L1.
            let dx = if cx < x0 {
                x0 - cx
            } else if cx > x1 {
                cx - x1
            } else {
                0
            };
            let dy = if cy < y0 {
                y0 - cy
            } else if cy > y1 {
                cy - y1
            } else {
                0
            };
            dx + dy <= h
        }
    }
}

/// Number of key bytes after the level byte for `bits` bits per coordinate.
fn key_bytes(bits: u32) -> usize {
    (2 * bits).div_ceil(8) as usize
}

/// Orders corners as `[E1, P1, E2, P2]`: `E1` the lexicographically smaller hypotenuse
/// end, `P1` the parent that makes the frame right-handed.
pub(crate) fn frame_order(ends: [[i64; 2]; 2], parents: [[i64; 2]; 2]) -> [[i64; 2]; 4] {
    let (e1, e2) = if ends[0] <= ends[1] {
        (ends[0], ends[1])
    } else {
        (ends[1], ends[0])
    };
    let a = [parents[0][0] - e1[0], parents[0][1] - e1[1]];
    let b = [parents[1][0] - e1[0], parents[1][1] - e1[1]];
    let cross = a[0] as i128 * b[1] as i128 - a[1] as i128 * b[0] as i128;
    if cross > 0 {
        [e1, parents[0], e2, parents[1]]
    } else {
        [e1, parents[1], e2, parents[0]]
    }
}

/// Point of a frame at doubled grid coordinates `(p, q)` (vertex `(i,j)` = `(2i, 2j)`),
/// in sample units.
pub(crate) fn frame_point(c: &[[i64; 2]; 4], n: usize, p: i64, q: i64) -> [i64; 2] {
    let n = n as i64;
    let e1 = c[0];
    let a = [c[1][0] - e1[0], c[1][1] - e1[1]];
    let b = [c[3][0] - e1[0], c[3][1] - e1[1]];
    [
        2 * n * e1[0] + p * a[0] + q * b[0],
        2 * n * e1[1] + p * a[1] + q * b[1],
    ]
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn root_and_its_children_have_the_documented_levels() {
        let d = PlanarDomain::new(4).unwrap();
        assert_eq!(d.level(d.root()).unwrap(), 0);
        let kids = d.children(d.root()).unwrap();
        assert_eq!(kids.len(), 4);
        for k in &kids {
            assert_eq!(d.level(*k).unwrap(), 1);
            assert!(d.is_half(*k).unwrap());
            assert_eq!(d.parents(*k).unwrap(), vec![d.root()]);
            assert_eq!(d.children(*k).unwrap().len(), 2);
        }
    }

    #[test]
    fn corners_are_rejected_as_centres() {
        let d = PlanarDomain::new(3).unwrap();
        for (x, y) in [(0, 0), (8, 0), (0, 8), (8, 8)] {
            assert!(matches!(
                d.check(PlanarId::new(x, y)),
                Err(IdError::NotACentre(_))
            ));
        }
        assert!(matches!(
            d.check(PlanarId::new(9, 1)),
            Err(IdError::OutOfDomain(_))
        ));
        assert!(matches!(
            d.check(PlanarId::new(-1, 1)),
            Err(IdError::OutOfDomain(_))
        ));
    }
}
