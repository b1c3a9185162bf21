//! quincunx diamond ids and the hierarchy laws of the 4-8 (longest-edge bisection) hierarchy.
//!
//! A diamond is identified by the integer coordinates of its centre only: level,
//! orientation, parents, children, neighbours and sample positions are pure functions
//! of the id and the domain. Two domains exist: a planar square ([`planar`]) and the
//! cube-mapped sphere ([`sphere`]).
//!
//! This crate is the part of the codec's vocabulary that the server also needs (to
//! validate ids and find storage keys) without linking a decoder; `quincunx-codec`
//! re-exports it as `quincunx_codec::diamond`. Pure: std and thiserror only.
//!
//! Every diamond has an intrinsic *frame*: corners `[E1, P1, E2, P2]` where `E1`, `E2`
//! are the ends of its hypotenuse and `P1`, `P2` the centres of its parents. Vertex
//! `(i, j)` of its `(N+1) x (N+1)` grid lies at `E1 + (i (P1 - E1) + j (P2 - E1)) / N`,
//! so the hypotenuse is the grid diagonal `i == j` and the parents sit at `(N, 0)` and
//! `(0, N)`. Cell centre `(i, j)` lies at vertex position `(i + 1/2, j + 1/2)`.
//! Positions are returned in *sample units*: id units multiplied by `2 N`, so that every
//! vertex and cell centre of every diamond is an integer point.

pub mod planar;
pub mod sphere;

pub use planar::{PlanarDomain, PlanarId};
pub use sphere::{SphereDomain, SphereId};

/// A fast hasher for diamond ids (two `i64`s; FxHash's multiply-rotate mixing). Ids are
/// not attacker-chosen here: they come from the repository's own hierarchy.
#[derive(Clone, Copy, Debug, Default)]
pub struct IdHasher(u64);

impl std::hash::Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_i64(&mut self, v: i64) {
        self.write_u64(v as u64);
    }

    fn write_usize(&mut self, v: usize) {
        self.write_u64(v as u64);
    }
}

/// A map keyed by diamond id (planar unless `K` says otherwise) with [`IdHasher`].
pub type IdMap<V, K = PlanarId> =
    std::collections::HashMap<K, V, std::hash::BuildHasherDefault<IdHasher>>;

/// Deepest domain exponent: a planar domain is `[0, 2^m]^2`, a sphere the cube `[-2^m, 2^m]^3`.
///
/// With `m <= 48` the deepest planar level is `2 m - 1 = 95` and the deepest sphere level
/// `2 m + 1 = 97`. Sample positions are id coordinates times `2 N` with `N <= MAX_N`, at
/// most `2^(48 + 1 + 1 + 10) = 2^60` in magnitude (unfolded sphere charts reach `3 S`),
/// so every intermediate sum fits an `i64` with room to spare.
pub const MAX_M: u32 = 48;

/// Largest supported diamond size `N` (cells per side); `N` is a power of two.
pub const MAX_N: usize = 512;

/// Whether a diamond's square is aligned with the domain axes (even levels) or rotated by
/// 45 degrees (odd levels).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Orientation {
    /// Even level: sides parallel to the axes, hypotenuse along a diagonal.
    Axis,
    /// Odd level: sides at 45 degrees, hypotenuse parallel to an axis.
    Rotated,
}

impl Orientation {
    /// Orientation of a given level.
    pub fn of_level(level: u32) -> Self {
        if level.is_multiple_of(2) {
            Orientation::Axis
        } else {
            Orientation::Rotated
        }
    }
}

/// Why an id (or a key, or a domain parameter) was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum IdError {
    /// The point lies outside the domain.
    #[error("point {0:?} lies outside the domain")]
    OutOfDomain([i64; 3]),
    /// The point is in the domain but is not the centre of any diamond (e.g. a corner).
    #[error("point {0:?} is not the centre of a diamond")]
    NotACentre([i64; 3]),
    /// The domain exponent is outside `1..=MAX_M`.
    #[error("domain exponent m = {0} is outside 1..={MAX_M}")]
    BadExponent(u32),
    /// The diamond size is not a power of two in `2..=MAX_N`.
    #[error("diamond size N = {0} is not a power of two in 2..={MAX_N}")]
    BadSize(usize),
    /// A storage key could not be decoded.
    #[error("malformed storage key: {0}")]
    BadKey(&'static str),
    /// A grid index is outside `0..=N` (vertices) or `0..N` (cells).
    #[error("grid index ({0}, {1}) is outside the diamond grid")]
    BadIndex(usize, usize),
}

/// Checks that `n` is a supported diamond size.
pub fn check_size(n: usize) -> Result<(), IdError> {
    if n.is_power_of_two() && (2..=MAX_N).contains(&n) {
        Ok(())
    } else {
        Err(IdError::BadSize(n))
    }
}

/// Trailing zeros with `tz(0) = infinity` (represented as 127).
pub(crate) fn tz(v: i64) -> u32 {
    if v == 0 { 127 } else { v.trailing_zeros() }
}

/// Interleaves the low `bits` bits of `a` and `b` (a in the odd positions).
pub(crate) fn morton2(a: u64, b: u64, bits: u32) -> u128 {
    let mut out = 0u128;
    for k in 0..bits {
        out |= (((a >> k) & 1) as u128) << (2 * k + 1);
        out |= (((b >> k) & 1) as u128) << (2 * k);
    }
    out
}

/// Inverse of [`morton2`].
pub(crate) fn unmorton2(code: u128, bits: u32) -> (u64, u64) {
    let (mut a, mut b) = (0u64, 0u64);
    for k in 0..bits {
        a |= (((code >> (2 * k + 1)) & 1) as u64) << k;
        b |= (((code >> (2 * k)) & 1) as u64) << k;
    }
    (a, b)
}

/// Writes `code` as `bytes` big-endian bytes (so byte order is numeric order).
pub(crate) fn push_be(out: &mut Vec<u8>, code: u128, bytes: usize) {
    for k in (0..bytes).rev() {
        out.push((code >> (8 * k)) as u8);
    }
}

/// Reads `bytes` big-endian bytes.
pub(crate) fn read_be(data: &[u8]) -> u128 {
    data.iter().fold(0u128, |acc, &b| (acc << 8) | b as u128)
}
