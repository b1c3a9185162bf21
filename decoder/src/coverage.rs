//! Coverage: which coarse blocks of a raster (or of a planet's faces) hold data, for the
//! sparse encoding mode (`quincunx_codec::encode::EncodeOptions::sparse`).
//!
//! The sample array is cut into square blocks of `B x B` samples (`B` a power of two),
//! aligned at sample 0: block `(col, row)` of a face spans samples `col B ..= (col+1) B`
//! along `x`/`u` and `row B ..= (row+1) B` along `y`/`v` (closed: neighbouring blocks share
//! their border samples). A block is *covered* when a data sample lies in its half-open
//! part `[col B, (col+1) B) x [row B, (row+1) B)` (the last block of a planet face also owns
//! the face's far border). Then:
//!
//! - a point is **valid** when any closed block containing it is covered, on any face
//!   holding a copy of the point (so both copies of a cube edge point agree);
//! - every data sample is valid; nodata samples in covered blocks are valid too (the
//!   encoder fills them smoothly, as in dense mode): only voids of whole blocks become holes;
//! - invalid points are never coded and never read by predictions, like the points
//!   outside a planar raster.
//!
//! The decoder derives every diamond's [`crate::lifting::DiamondMask`] from the coverage
//! and the diamond's id alone, so the coverage travels in the repository metadata
//! ([`Coverage::to_bytes`]).
//!
//! # Block side
//! The encoder picks the smallest power of two `B >= N` whose bitmap has at most
//! [`MAX_BITS`] bits (4 KiB): for a planet `face_side / B <= 64`, i.e. at most
//! `6 x 64 x 64` bits = 3 KiB, blocks of `face_side / 64` samples (~1.4 degrees of
//! arc at the face centre). Voids smaller than a block stay filled. Decoders accept any
//! power-of-two block side whose bitmap shape matches the geometry.
//!
//! # Bytes
//! ```text
//! byte 0      format version (1)
//! byte 1      faces: 1 (planar raster) or 6 (planet)
//! byte 2      log2 B
//! bytes 3..7  columns of blocks per face (u32, little-endian)
//! bytes 7..11 rows of blocks per face (u32, little-endian)
//! bytes 11..  faces x rows x columns bits, face by face, row-major, least significant bit
//!             first; padding bits of the last byte are 0
//! ```

/// Current coverage format version.
pub const COVERAGE_VERSION: u8 = 1;
/// Largest bitmap the encoder chooses, in bits (4 KiB).
pub const MAX_BITS: usize = 1 << 15;
const HEADER_BYTES: usize = 11;
/// Largest block side and block count per side accepted (the geometries' own limits).
const MAX_SIDE: u64 = 1 << 24;

/// Why coverage bytes are not a valid coverage.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum CoverageError {
    /// Fewer bytes than the header.
    #[error("coverage of {0} bytes is shorter than its header")]
    TooShort(usize),
    /// Unknown format version.
    #[error("coverage version {0} is not supported (expected {COVERAGE_VERSION})")]
    Version(u8),
    /// A header field is out of range.
    #[error("coverage header is invalid: {0}")]
    Header(&'static str),
    /// The bitmap's length does not match the header.
    #[error("coverage bitmap of {got} bytes, the header says {expected}")]
    Length {
        /// bytes the header implies
        expected: u64,
        /// bytes given
        got: usize,
    },
    /// Padding bits after the last block are not zero.
    #[error("coverage padding bits are not zero")]
    Padding,
}

/// Which coarse blocks of samples hold data (see the module docs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Coverage {
    faces: u8,
    block_log2: u8,
    cols: u32,
    rows: u32,
    bits: Vec<u8>,
}

/// Whether the blocks met by a rectangle are all covered, none, or some.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockState {
    /// Every block met is covered.
    Full,
    /// No block met is covered (or no block is met).
    Empty,
    /// Some are, some are not.
    Mixed,
}

impl Coverage {
    /// An all-uncovered coverage of `faces` faces of `cols x rows` blocks of side
    /// `2^block_log2`.
    fn empty(faces: u8, block_log2: u8, cols: u32, rows: u32) -> Self {
        let bits = (faces as usize * cols as usize * rows as usize).div_ceil(8);
        Coverage {
            faces,
            block_log2,
            cols,
            rows,
            bits: vec![0; bits],
        }
    }

    /// The coverage of a planar `width x height` raster (row-major `data(k)`: whether
    /// sample `k` holds data), blocks as the encoder chooses them for diamond size `n`.
    pub fn of_raster(
        width: usize,
        height: usize,
        n: usize,
        data: impl Fn(usize) -> bool,
    ) -> Coverage {
        let mut rows = RasterCoverage::new(width, height, n);
        for y in 0..height {
            rows.mark_row(y, |x| data(y * width + x));
        }
        rows.finish()
    }

    /// The coverage of a planet's cube raster (`face_side` samples per face side, the
    /// cube-raster order of [`crate::sphere_raster`]; `data(k)`: whether entry `k` holds
    /// data, with consistent copies of edge points), blocks as the encoder chooses them
    /// for diamond size `n`.
    pub fn of_cube(face_side: usize, n: usize, data: impl Fn(usize) -> bool) -> Coverage {
        let mut cov = CubeCoverage::new(face_side, n);
        let w = face_side + 1;
        for face in 0..6 {
            for v in 0..w {
                cov.mark_row(face, v, |u| data((face * w + v) * w + u));
            }
        }
        cov.finish()
    }

    fn bit(&self, face: usize, col: usize, row: usize) -> usize {
        (face * self.rows as usize + row) * self.cols as usize + col
    }

    fn set(&mut self, face: usize, col: usize, row: usize) {
        let k = self.bit(face, col, row);
        self.bits[k / 8] |= 1 << (k % 8);
    }

    /// Faces: 1 for a planar raster, 6 for a planet.
    pub fn faces(&self) -> usize {
        self.faces as usize
    }

    /// Side of a block, in samples.
    pub fn block_side(&self) -> usize {
        1 << self.block_log2
    }

    /// Columns of blocks per face.
    pub fn cols(&self) -> usize {
        self.cols as usize
    }

    /// Rows of blocks per face.
    pub fn rows(&self) -> usize {
        self.rows as usize
    }

    /// Whether block `(col, row)` of face `face` holds data (`false` outside the bitmap).
    pub fn is_covered(&self, face: usize, col: usize, row: usize) -> bool {
        if face >= self.faces() || col >= self.cols() || row >= self.rows() {
            return false;
        }
        let k = self.bit(face, col, row);
        self.bits[k / 8] >> (k % 8) & 1 == 1
    }

    /// Set bits among bits `start .. end` of the bitmap.
    fn ones(&self, start: usize, end: usize) -> usize {
        let mut count = 0;
        let mut k = start;
        while k < end && !k.is_multiple_of(8) {
            count += usize::from(self.bits[k / 8] >> (k % 8) & 1 == 1);
            k += 1;
        }
        let whole = (end - k) / 8;
        let bytes = &self.bits[k / 8..k / 8 + whole];
        let mut words = bytes.chunks_exact(8);
        for w in &mut words {
            count += u64::from_le_bytes(w.try_into().unwrap_or([0; 8])).count_ones() as usize;
        }
        count += words
            .remainder()
            .iter()
            .map(|b| b.count_ones() as usize)
            .sum::<usize>();
        k += whole * 8;
        while k < end {
            count += usize::from(self.bits[k / 8] >> (k % 8) & 1 == 1);
            k += 1;
        }
        count
    }

    /// Number of covered blocks.
    pub fn covered_blocks(&self) -> usize {
        self.bits.iter().map(|b| b.count_ones() as usize).sum()
    }

    /// Number of blocks.
    pub fn blocks(&self) -> usize {
        self.faces() * self.cols() * self.rows()
    }

    /// Whether sample `(x, y)` of face `face` lies in a covered closed block.
    pub fn covers_point(&self, face: usize, x: usize, y: usize) -> bool {
        let b = self.block_log2;
        let near = |t: usize| {
            let own = t >> b;
            let prev = (t > 0 && t & ((1 << b) - 1) == 0).then(|| own - 1);
            [Some(own), prev]
        };
        let (xs, ys) = (near(x), near(y));
        xs.iter()
            .flatten()
            .any(|&c| ys.iter().flatten().any(|&r| self.is_covered(face, c, r)))
    }

    /// The state of the blocks of face `face` whose closed squares meet the closed
    /// rectangle `x0..=x1, y0..=y1` (samples; an empty rectangle meets no block).
    pub(crate) fn state(
        &self,
        face: usize,
        [x0, x1]: [usize; 2],
        [y0, y1]: [usize; 2],
    ) -> BlockState {
        let (mut any_in, mut any_out) = (false, false);
        if x0 <= x1 && y0 <= y1 {
            let b = self.block_log2;
            // Blocks `j` with `j B <= t1` and `(j + 1) B >= t0`.
            let lo = |t: usize| if t == 0 { 0 } else { (t - 1) >> b };
            let hi = |t: usize, count: usize| (t >> b).min(count - 1);
            let (c0, c1) = (lo(x0).min(self.cols() - 1), hi(x1, self.cols()));
            // A row's blocks are consecutive bits: count them a word at a time (a
            // planet's root diamonds span thousands of blocks, and a session asks at
            // open).
            for r in lo(y0).min(self.rows() - 1)..=hi(y1, self.rows()) {
                if face >= self.faces() || c0 > c1 {
                    any_out = true;
                } else {
                    let start = self.bit(face, c0, r);
                    let len = c1 - c0 + 1;
                    let ones = self.ones(start, start + len);
                    any_in |= ones > 0;
                    any_out |= ones < len;
                }
                if any_in && any_out {
                    return BlockState::Mixed;
                }
            }
        }
        match (any_in, any_out) {
            (true, false) => BlockState::Full,
            (false, _) => BlockState::Empty,
            (true, true) => BlockState::Mixed,
        }
    }

    /// Serialises the coverage (see the module docs).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + self.bits.len());
        out.push(COVERAGE_VERSION);
        out.push(self.faces);
        out.push(self.block_log2);
        out.extend_from_slice(&self.cols.to_le_bytes());
        out.extend_from_slice(&self.rows.to_le_bytes());
        out.extend_from_slice(&self.bits);
        out
    }

    /// Parses [`Coverage::to_bytes`]; hostile bytes give an `Err`, never a panic, and
    /// nothing is allocated beyond the bytes given.
    pub fn from_bytes(bytes: &[u8]) -> Result<Coverage, CoverageError> {
        let Some((head, bits)) = bytes.split_first_chunk::<HEADER_BYTES>() else {
            return Err(CoverageError::TooShort(bytes.len()));
        };
        let [version, faces, block_log2, c0, c1, c2, c3, r0, r1, r2, r3] = *head;
        if version != COVERAGE_VERSION {
            return Err(CoverageError::Version(version));
        }
        if faces != 1 && faces != 6 {
            return Err(CoverageError::Header("faces is neither 1 nor 6"));
        }
        if u64::from(block_log2) > u64::from(MAX_SIDE.trailing_zeros()) {
            return Err(CoverageError::Header("block side above 2^24"));
        }
        let cols = u32::from_le_bytes([c0, c1, c2, c3]);
        let rows = u32::from_le_bytes([r0, r1, r2, r3]);
        let side_ok = |x: u32| (1..=MAX_SIDE).contains(&u64::from(x));
        if !side_ok(cols) || !side_ok(rows) {
            return Err(CoverageError::Header("block counts out of range"));
        }
        if faces == 6 && cols != rows {
            return Err(CoverageError::Header("planet faces are not square"));
        }
        let count = u64::from(faces) * u64::from(cols) * u64::from(rows);
        let expected = count.div_ceil(8);
        if bits.len() as u64 != expected {
            return Err(CoverageError::Length {
                expected,
                got: bits.len(),
            });
        }
        let tail = (count % 8) as u32;
        if tail != 0 && bits.last().is_some_and(|&b| b >> tail != 0) {
            return Err(CoverageError::Padding);
        }
        Ok(Coverage {
            faces,
            block_log2,
            cols,
            rows,
            bits: bits.to_vec(),
        })
    }
}

/// The coverage of a planar raster built row by row (the out-of-core encoder sees each
/// row once): the same blocks and bits as [`Coverage::of_raster`].
#[derive(Clone, Debug)]
pub struct RasterCoverage {
    cov: Coverage,
    block: usize,
    width: usize,
}

impl RasterCoverage {
    /// An all-uncovered coverage of a `width x height` raster, blocks as the encoder
    /// chooses them for diamond size `n`.
    pub fn new(width: usize, height: usize, n: usize) -> Self {
        let blocks = |b: usize| ((width.max(1) - 1) / b + 1, (height.max(1) - 1) / b + 1);
        let mut b = n.max(1).next_power_of_two();
        while {
            let (c, r) = blocks(b);
            c * r > MAX_BITS
        } {
            b *= 2;
        }
        let (cols, rows) = blocks(b);
        RasterCoverage {
            cov: Coverage::empty(1, b.trailing_zeros() as u8, cols as u32, rows as u32),
            block: b,
            width,
        }
    }

    /// Marks the blocks of row `y` where `data(x)` holds data.
    pub fn mark_row(&mut self, y: usize, data: impl Fn(usize) -> bool) {
        let b = self.block;
        for x in 0..self.width {
            if data(x) {
                self.cov.set(0, x / b, y / b);
            }
        }
    }

    /// The coverage.
    pub fn finish(self) -> Coverage {
        self.cov
    }
}

/// [`Coverage::of_cube`] built one face row at a time (the out-of-core planet encoder's
/// first pass).
pub struct CubeCoverage {
    cov: Coverage,
    block: usize,
    side: usize,
    width: usize,
}

impl CubeCoverage {
    /// An all-uncovered coverage of a planet of `face_side`, blocks as the encoder
    /// chooses them for diamond size `n`.
    pub fn new(face_side: usize, n: usize) -> Self {
        let mut b = n.max(1).next_power_of_two().min(face_side.max(1));
        while 6 * (face_side / b) * (face_side / b) > MAX_BITS {
            b *= 2;
        }
        let side = (face_side / b).max(1);
        CubeCoverage {
            cov: Coverage::empty(6, b.trailing_zeros() as u8, side as u32, side as u32),
            block: b,
            side,
            width: face_side + 1,
        }
    }

    /// Marks the blocks of face `face`'s row `v` where `data(u)` holds data.
    pub fn mark_row(&mut self, face: usize, v: usize, data: impl Fn(usize) -> bool) {
        let (b, last) = (self.block, self.side - 1);
        for u in 0..self.width {
            if data(u) {
                self.cov.set(face, (u / b).min(last), (v / b).min(last));
            }
        }
    }

    /// The coverage.
    pub fn finish(self) -> Coverage {
        self.cov
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    /// `state` by looking at every block, as it did before it counted bits a word at a
    /// time.
    fn state_block_by_block(
        cov: &Coverage,
        face: usize,
        [x0, x1]: [usize; 2],
        [y0, y1]: [usize; 2],
    ) -> BlockState {
        let (mut any_in, mut any_out) = (false, false);
        if x0 <= x1 && y0 <= y1 {
            let b = cov.block_log2;
            let lo = |t: usize| if t == 0 { 0 } else { (t - 1) >> b };
            let hi = |t: usize, count: usize| (t >> b).min(count - 1);
            for r in lo(y0).min(cov.rows() - 1)..=hi(y1, cov.rows()) {
                for c in lo(x0).min(cov.cols() - 1)..=hi(x1, cov.cols()) {
                    if cov.is_covered(face, c, r) {
                        any_in = true;
                    } else {
                        any_out = true;
                    }
                }
            }
        }
        match (any_in, any_out) {
            (true, false) => BlockState::Full,
            (false, _) => BlockState::Empty,
            (true, true) => BlockState::Mixed,
        }
    }

    #[test]
    fn block_states_counted_by_words_are_the_blocks_states() {
        let mut seed = 11u64;
        let mut next = |m: usize| {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as usize % m
        };
        // 6 faces of 37 x 37 blocks of 8 samples (rows straddle bytes and words), some
        // faces full, some empty, some with runs and holes.
        let mut cov = Coverage::empty(6, 3, 37, 37);
        for face in 0..6 {
            for r in 0..37 {
                for c in 0..37 {
                    let on = match face {
                        0 => true,
                        1 => false,
                        2 => (c / 9 + r / 5) % 2 == 0,
                        _ => next(100) < 60 + 10 * face,
                    };
                    if on {
                        cov.set(face, c, r);
                    }
                }
            }
        }
        let side = 37 * 8;
        let mut seen = [0usize; 3];
        for _ in 0..20_000 {
            let face = next(6);
            let (x0, y0) = (next(side + 1), next(side + 1));
            let (x1, y1) = (x0 + next(side + 1 - x0), y0 + next(side + 1 - y0));
            let rect = if next(10) == 0 { [x1, x0] } else { [x0, x1] };
            let want = state_block_by_block(&cov, face, rect, [y0, y1]);
            assert_eq!(
                cov.state(face, rect, [y0, y1]),
                want,
                "{face} {rect:?} {y0} {y1}"
            );
            seen[want as usize] += 1;
        }
        assert!(seen.iter().all(|&k| k > 100), "{seen:?}");
    }

    #[test]
    fn closed_blocks_share_their_border_samples() {
        // 65 x 65 raster, N = 32: blocks of 32, 3 x 3 (the last ones hold the far border).
        let cov = Coverage::of_raster(65, 65, 32, |k| k % 65 < 10 && k / 65 < 10);
        assert_eq!((cov.block_side(), cov.cols(), cov.rows()), (32, 3, 3));
        assert_eq!(cov.covered_blocks(), 1);
        assert!(cov.covers_point(0, 32, 32));
        assert!(cov.covers_point(0, 0, 0));
        assert!(!cov.covers_point(0, 33, 0));
        assert_eq!(cov.state(0, [0, 31], [0, 31]), BlockState::Full);
        // Sample 32 is also in the closed block 1.
        assert_eq!(cov.state(0, [0, 32], [0, 31]), BlockState::Mixed);
        assert_eq!(cov.state(0, [0, 33], [0, 0]), BlockState::Mixed);
        assert_eq!(cov.state(0, [33, 64], [0, 64]), BlockState::Empty);
    }

    #[test]
    fn bytes_round_trip_and_reject_hostile_input() {
        let cov = Coverage::of_cube(128, 16, |k| k % 7 == 0 && k % 1000 < 300);
        assert_eq!(cov.blocks(), 6 * 8 * 8);
        let bytes = cov.to_bytes();
        assert_eq!(Coverage::from_bytes(&bytes).unwrap(), cov);
        for len in 0..bytes.len() {
            assert!(Coverage::from_bytes(&bytes[..len]).is_err());
        }
        let mut long = bytes.clone();
        long.push(0);
        assert!(Coverage::from_bytes(&long).is_err());
        let mut huge = bytes.clone();
        huge[3..7].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(Coverage::from_bytes(&huge).is_err());
    }
}
