//! The coefficient coder: context-modelled binary range coding of one diamond's quantised
//! detail matrix, with per-repository trained priors.
//!
//! Design (why): blobs are small (tens of bytes at 0.2 bits/sample), so an adaptive coder
//! that starts from flat probabilities learns nothing before the blob ends. Each context's
//! starting probability is therefore trained on the whole repository at build time and
//! shipped once in its metadata ([`CodecModel`], 1-2.5 KB); within a blob the probabilities
//! still adapt. Decoding is built for weak clients: all-zero regions are skipped by a
//! quadtree of 4x4 blocks (one or two binary decisions for a flat diamond), and each
//! coefficient costs one decision when zero, about three when small.
//!
//! Binarisation of a matrix (level group `g` = distance from the finest level, capped):
//! - a `nonzero` flag;
//! - quadtree significance of 4x4 blocks (the last candidate child of a significant node
//!   is inferred), context = node size and significant left/upper neighbours;
//! - per valid cell of a significant block, in raster order: significance (context:
//!   activity `a = 2|W| + 2|N| + |NW| + |NE| + |WW| + |NN|` of already coded
//!   neighbours), sign (context: signs of W, N, NW and NE), then the magnitude `|q| - 1` split
//!   Golomb-Rice style by a parameter `k` that grows with `a`
//!   (`k = floor(log2((a + 8) / 16))`, 0 below 24): its
//!   high part `(|q| - 1) >> k` in unary over 14 context-coded bins (context set: the
//!   activity bucket for `k = 0`, else `k`), escaping past 14 to Exp-Golomb with a
//!   context-coded prefix and a bypass suffix, then its `k` low bits in bypass bits.
//!   (Blob version 2 coded every magnitude in unary from 1 with a bypass-coded escape:
//!   at korea RMS 1 m the escapes alone were 9 % of the bytes.)

pub mod range;

use range::{Decoder, Encoder, HALF, Prob};

/// Number of level groups with their own contexts (distance from the finest level,
/// capped at `GROUPS - 1`).
pub const GROUPS: usize = 6;

/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub const NONZERO: usize = 0;
const GAMMA_ZERO: usize = 1;
const GAMMA_UNARY: usize = 2; // 16
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub const QUAD: usize = 18; // 4 sizes x 3
/// Activity classes (significance contexts per ring position).
const CLASSES: usize = 10;
const SIG: usize = 30; // CLASSES x (inside, outer ring)
/// Sign contexts: the signs of W, N, NW and NE.
const SIGNS: usize = 81;
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub const SIGN: usize = SIG + 2 * CLASSES;
/// Exp-Golomb prefix positions of magnitude escapes with their own context (the last
/// shared by all longer prefixes).
const ESCAPES: usize = 16;
const ESCAPE: usize = SIGN + SIGNS;
const MAG: usize = ESCAPE + ESCAPES; // 2 x RING_SETS x MAG_BINS
const MAG_BINS: usize = 14;
/// Magnitude context sets per ring position: 3 activity buckets for `k = 0`, then
/// `k = 1..=6` and one for larger `k`.
const RING_SETS: usize = 10;
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub const PER_GROUP: usize = MAG + 2 * RING_SETS * MAG_BINS;
/// Largest Golomb-Rice parameter (bounds the bypass bits of one magnitude's low part).
const RICE_MAX: u32 = 15;
/// Sign hiding (blob version 4, quantised levels only): in a 4x4 block with at least this
/// many nonzero coefficients, the sign of the first is not coded: it is negative exactly
/// when the block's magnitudes sum to an odd number (the encoder makes it so, see
/// `encode::prune_block`). In other blocks that sign is coded after the block's last cell.
pub const HIDDEN_SIGN_MIN: usize = 8;

/// Total number of contexts.
pub const CONTEXTS: usize = GROUPS * PER_GROUP;

/// Why a coded matrix could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum EntropyError {
    /// An escape code announced more than 32 bits.
    #[error("magnitude escape longer than 32 bits")]
    EscapeTooLong,
    /// The decoder read past the end of the payload by more than the coder's lookahead.
    #[error("coded data ends early")]
    Truncated,
    /// The model bytes are malformed.
    #[error("codec model: {0}")]
    BadModel(&'static str),
}

/// Starting probabilities of every context: trained per repository, shipped once.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CodecModel {
    probs: Vec<Prob>,
}

impl Default for CodecModel {
    fn default() -> Self {
        CodecModel {
            probs: vec![HALF; CONTEXTS],
        }
    }
}

/// Starting probability (of a 0, 16 bits) of each model byte `b`: log-odds
/// `(b - 128) / 16`, clamped to the coder's range. A table, not `exp`, so every platform
/// decodes the same bits from the same model bytes.
const MODEL_PROBS: [Prob; 256] = [
    32, 32, 32, 32, 32, 32, 32, 34, 36, 39, 41, 44, 47, 50, 53, 56, 60, 64, 68, 72, 77, 82, 87, 92,
    98, 105, 111, 119, 126, 134, 143, 152, 162, 172, 184, 195, 208, 221, 236, 251, 267, 284, 302,
    321, 342, 364, 387, 412, 439, 467, 497, 528, 562, 598, 636, 677, 720, 766, 815, 867, 922, 980,
    1042, 1109, 1179, 1253, 1333, 1417, 1506, 1601, 1701, 1808, 1921, 2041, 2168, 2303, 2446, 2598,
    2758, 2928, 3108, 3298, 3500, 3713, 3938, 4176, 4427, 4692, 4971, 5266, 5577, 5904, 6249, 6611,
    6992, 7392, 7812, 8252, 8714, 9197, 9702, 10230, 10782, 11357, 11955, 12579, 13226, 13898,
    14595, 15316, 16062, 16832, 17625, 18442, 19282, 20143, 21025, 21928, 22849, 23788, 24743,
    25712, 26695, 27689, 28693, 29705, 30723, 31744, 32768, 33792, 34813, 35831, 36843, 37847,
    38841, 39824, 40793, 41748, 42687, 43608, 44511, 45393, 46254, 47094, 47911, 48704, 49474,
    50220, 50941, 51638, 52310, 52957, 53581, 54179, 54754, 55306, 55834, 56339, 56822, 57284,
    57724, 58144, 58544, 58925, 59287, 59632, 59959, 60270, 60565, 60844, 61109, 61360, 61598,
    61823, 62036, 62238, 62428, 62608, 62778, 62938, 63090, 63233, 63368, 63495, 63615, 63728,
    63835, 63935, 64030, 64119, 64203, 64283, 64357, 64427, 64494, 64556, 64614, 64669, 64721,
    64770, 64816, 64859, 64900, 64938, 64974, 65008, 65039, 65069, 65097, 65124, 65149, 65172,
    65194, 65215, 65234, 65252, 65269, 65285, 65300, 65315, 65328, 65341, 65352, 65364, 65374,
    65384, 65393, 65402, 65410, 65417, 65425, 65431, 65438, 65444, 65449, 65454, 65459, 65464,
    65468, 65472, 65476, 65480, 65483, 65486, 65489, 65492, 65495, 65497, 65500, 65502, 65504,
    65504, 65504, 65504, 65504, 65504,
];

impl CodecModel {
    /// The starting probability of every context.
    pub fn probs(&self) -> &[Prob] {
        &self.probs
    }

    /// A model from per-context counts of zeros and ones (each probability rounded to a
    /// model byte, so a model survives [`CodecModel::to_bytes`] exactly).
    pub fn from_counts(counts: &ContextCounts) -> Self {
        let probs = counts
            .counts
            .iter()
            .map(|&[n0, n1]| {
                let p = (n0 as f64 + 0.4) / (n0 as f64 + n1 as f64 + 0.8);
                MODEL_PROBS[model_byte(p) as usize]
            })
            .collect();
        CodecModel { probs }
    }

    /// Serialised form: a bitmap of the contexts whose starting probability is not 1/2
    /// (bit `k % 8` of byte `k / 8`), then one byte per such context, in order: the
    /// log-odds of its probability in 1/16 steps. Blob version 2 stored a `u16` for every
    /// context; a small repository uses few of them, and at 0.26 bits/sample the model's
    /// bytes are part of the rate.
    pub fn to_bytes(&self) -> Vec<u8> {
        let bytes: Vec<u8> = self
            .probs
            .iter()
            .map(|&p| model_byte(f64::from(p) / 65536.0))
            .collect();
        let mut out = vec![0u8; CONTEXTS.div_ceil(8)];
        for (k, &b) in bytes.iter().enumerate() {
            if b != 128 {
                out[k / 8] |= 1 << (k % 8);
            }
        }
        out.extend(bytes.iter().filter(|&&b| b != 128));
        out
    }

    /// Parses [`CodecModel::to_bytes`]; any byte is a valid probability.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, EntropyError> {
        let map_len = CONTEXTS.div_ceil(8);
        let Some((map, values)) = bytes.split_at_checked(map_len) else {
            return Err(EntropyError::BadModel("shorter than its bitmap"));
        };
        let set = |k: usize| map[k / 8] >> (k % 8) & 1 == 1;
        if (CONTEXTS..map_len * 8).any(set) {
            return Err(EntropyError::BadModel("bits set past the last context"));
        }
        let count = map.iter().map(|b| b.count_ones() as usize).sum::<usize>();
        if values.len() != count {
            return Err(EntropyError::BadModel("wrong length"));
        }
        let mut values = values.iter();
        let probs = (0..CONTEXTS)
            .map(|k| match set(k) {
                true => values.next().map_or(HALF, |&b| MODEL_PROBS[b as usize]),
                false => HALF,
            })
            .collect();
        Ok(CodecModel { probs })
    }
}

/// The model byte whose probability is closest to `p` in log-odds.
fn model_byte(p: f64) -> u8 {
    let p = p.clamp(1e-9, 1.0 - 1e-9);
    (16.0 * (p / (1.0 - p)).ln() + 128.0)
        .round()
        .clamp(0.0, 255.0) as u8
}

/// Per-context counts of coded zeros and ones (for training a [`CodecModel`]).
#[derive(Clone, Debug)]
pub struct ContextCounts {
    counts: Vec<[u64; 2]>,
}

impl Default for ContextCounts {
    fn default() -> Self {
        ContextCounts {
            counts: vec![[0; 2]; CONTEXTS],
        }
    }
}

impl ContextCounts {
    /// The counts, `[zeros, ones]` per context (a sharded build's parts carry them).
    pub fn to_pairs(&self) -> Vec<[u64; 2]> {
        self.counts.clone()
    }

    /// Counts from [`ContextCounts::to_pairs`]; `None` if the context count differs.
    pub fn from_pairs(counts: Vec<[u64; 2]>) -> Option<Self> {
        (counts.len() == CONTEXTS).then_some(ContextCounts { counts })
    }

    /// Adds another set of counts.
    pub fn merge(&mut self, other: &ContextCounts) {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            a[0] += b[0];
            a[1] += b[1];
        }
    }
}

/// Where binary decisions go: a range encoder or a counter.
pub trait BitSink {
    /// A context-coded decision.
    fn bit(&mut self, ctx: usize, bit: bool);
    /// `count` equiprobable bits of `value`, most significant first.
    fn bypass(&mut self, value: u32, count: u32);
}

impl BitSink for ContextCounts {
    fn bit(&mut self, ctx: usize, bit: bool) {
        self.counts[ctx][bit as usize] += 1;
    }
    fn bypass(&mut self, _value: u32, _count: u32) {}
}

/// A range encoder with its own copy of the model's probabilities.
pub struct ModelEncoder {
    enc: Encoder,
    probs: Vec<Prob>,
}

impl ModelEncoder {
    /// Starts a payload.
    pub fn new(model: &CodecModel) -> Self {
        ModelEncoder {
            enc: Encoder::new(),
            probs: model.probs.clone(),
        }
    }

    /// Ends the payload.
    pub fn finish(self) -> Vec<u8> {
        self.enc.finish()
    }
}

impl BitSink for ModelEncoder {
    #[inline(always)]
    fn bit(&mut self, ctx: usize, bit: bool) {
        self.enc.bit(&mut self.probs[ctx], bit);
    }
    fn bypass(&mut self, value: u32, count: u32) {
        self.enc.bypass(value, count);
    }
}

/// A range decoder with its own copy of the model's probabilities.
pub struct ModelDecoder<'a> {
    dec: Decoder<'a>,
    probs: Vec<Prob>,
    len: usize,
}

impl<'a> ModelDecoder<'a> {
    /// Starts decoding a payload.
    pub fn new(model: &CodecModel, data: &'a [u8]) -> Self {
        ModelDecoder {
            dec: Decoder::new(data),
            probs: model.probs.clone(),
            len: data.len(),
        }
    }

    #[inline(always)]
    fn bit(&mut self, ctx: usize) -> bool {
        self.dec.bit(&mut self.probs[ctx])
    }

    /// Bytes consumed so far (including zeros read past the end).
    pub fn consumed(&self) -> usize {
        self.dec.consumed()
    }

    /// Checks that decoding did not run far past the payload (a truncated blob).
    pub fn finish(&self) -> Result<(), EntropyError> {
        if self.dec.consumed() > self.len + 64 {
            Err(EntropyError::Truncated)
        } else {
            Ok(())
        }
    }
}

/// Level group of a diamond `distance` levels above the finest detail level.
pub fn group(distance: usize) -> usize {
    distance.min(GROUPS - 1)
}

fn ctx(g: usize, offset: usize) -> usize {
    g * PER_GROUP + offset
}

/// Side information class of a bound `gamma` (value quanta): 0 for 0, else the smallest
/// `k` with `gamma <= class_bound(k)`.
pub fn gamma_class(gamma: u64) -> u8 {
    (0..=63u8).find(|&k| class_bound(k) >= gamma).unwrap_or(63)
}

/// Upper bound represented by a side information class: 0, then `ceil(sqrt(2)^(k-1))`.
pub fn class_bound(k: u8) -> u64 {
    if k == 0 {
        0
    } else {
        (2f64).powf((k as f64 - 1.0) / 2.0).ceil() as u64
    }
}

/// Flag on a side information entry: the child and all its descendants have no details
/// (no blob). Only carried with a nonzero class: a class-0 child is never refined.
pub const NO_DATA: u8 = 0x80;

/// The class (0..=63) and the [`NO_DATA`] flag of a side information entry.
pub fn split_side(entry: u8) -> (u8, bool) {
    (
        (entry & !NO_DATA).min(63),
        entry & NO_DATA != 0 && entry & !NO_DATA != 0,
    )
}

/// Writes side information entries (one per owned child): a class, and for a nonzero
/// class the [`NO_DATA`] flag as one bypass bit.
pub fn write_gammas<S: BitSink>(s: &mut S, g: usize, classes: &[u8]) {
    for &entry in classes {
        let (c, no_data) = split_side(entry);
        let c = u32::from(c);
        s.bit(ctx(g, GAMMA_ZERO), c > 0);
        if c > 0 {
            let hi = (c - 1) >> 2;
            for k in 0..hi.min(15) {
                s.bit(ctx(g, GAMMA_UNARY + k as usize), true);
            }
            if hi < 15 {
                s.bit(ctx(g, GAMMA_UNARY + hi as usize), false);
            }
            s.bypass((c - 1) & 3, 2);
            s.bypass(u32::from(no_data), 1);
        }
    }
}

/// Reads side information classes.
pub fn read_gammas(d: &mut ModelDecoder<'_>, g: usize, count: usize) -> Vec<u8> {
    (0..count)
        .map(|_| {
            if !d.bit(ctx(g, GAMMA_ZERO)) {
                return 0;
            }
            let mut hi = 0u32;
            while hi < 15 && d.bit(ctx(g, GAMMA_UNARY + hi as usize)) {
                hi += 1;
            }
            let lo = d.dec.bypass(2);
            let class = (1 + (hi << 2) + lo).min(63) as u8;
            if d.dec.bypass(1) == 1 {
                class | NO_DATA
            } else {
                class
            }
        })
        .collect()
}

/// Longest bound profile read (a class per level below a child: never more than the
/// id space's levels).
pub const MAX_PROFILE: usize = 64;

/// Writes a bound profile (classes, at most [`MAX_PROFILE`]): each as the side entry
/// `class + 1`, then a 0 that ends it.
pub fn write_profile<S: BitSink>(s: &mut S, g: usize, profile: &[u8]) {
    let entries: Vec<u8> = profile
        .iter()
        .take(MAX_PROFILE)
        .map(|&c| c.min(62) + 1)
        .chain([0])
        .collect();
    write_gammas(s, g, &entries);
}

/// Reads a bound profile (what [`write_profile`] wrote; at most [`MAX_PROFILE`] classes).
pub fn read_profile(d: &mut ModelDecoder<'_>, g: usize) -> Vec<u8> {
    let mut out = Vec::new();
    while out.len() < MAX_PROFILE {
        let e = read_gammas(d, g, 1)[0] & !NO_DATA;
        if e == 0 {
            break;
        }
        out.push(e - 1);
    }
    out
}

/// Activity classes of activities below 50 (50 and above: class 9).
const ACTIVITY: [u8; 50] = {
    let mut t = [0u8; 50];
    let bounds = [0u32, 2, 4, 6, 9, 13, 19, 29, 49];
    let mut a = 0;
    while a < 50 {
        let mut c = 0;
        while c < bounds.len() && (a as u32) > bounds[c] {
            c += 1;
        }
        t[a] = c as u8;
        a += 1;
    }
    t
};

/// Class of activity `a`: 0, 1-2, 3-4, 5-6, 7-9, 10-13, 14-19, 20-29, 30-49, 50+.
#[inline(always)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub fn activity_class(a: u32) -> usize {
    ACTIVITY
        .get(a as usize)
        .map_or(CLASSES - 1, |&c| c as usize)
}

fn sgn3(v: i32) -> usize {
    match v.signum() {
        -1 => 0,
        0 => 1,
        _ => 2,
    }
}

/// Block geometry of an `n x n` matrix: 4x4 blocks (or `n x n` when `n < 4`).
struct Blocks {
    b: usize,
    nb: usize,
}

impl Blocks {
    fn new(n: usize) -> Self {
        let b = n.min(4);
        Blocks { b, nb: n / b }
    }
}

/// The coefficients coded so far, padded with two zero columns on each side and two zero
/// rows on top, so every cell's causal neighbours are read without bounds tests.
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub struct Causal {
    w: usize,
    v: Vec<i32>,
}

impl Causal {
    pub fn new(n: usize) -> Self {
        Causal {
            w: n + 4,
            v: vec![0; (n + 4) * (n + 2)],
        }
    }

    #[inline(always)]
    pub fn set(&mut self, i: usize, j: usize, x: i32) {
        self.v[(i + 2) * self.w + j + 2] = x;
    }

    /// Indices in `v` of the row above cell `(i, j)` (at its column) and of the cell.
    #[inline(always)]
    pub fn at(&self, i: usize, j: usize) -> (usize, usize) {
        let up = (i + 1) * self.w + j + 2;
        (up, up + self.w)
    }

    /// W, N, NW and NE of cell `(i, j)` (0 outside the matrix or not yet coded).
    #[inline(always)]
    pub fn near(&self, i: usize, j: usize) -> [i32; 4] {
        let (up, here) = self.at(i, j);
        [self.v[here - 1], self.v[up], self.v[up - 1], self.v[up + 1]]
    }

    /// Activity of coefficient `(i, j)`: `2|W| + 2|N| + |NW| + |NE| + |WW| + |NN|`
    /// (saturating; `WW`, `NN` two cells west and north; outside the matrix counts as 0).
    #[inline(always)]
    pub fn activity(&self, i: usize, j: usize) -> u32 {
        let [w, nn, nw, ne] = self.near(i, j);
        let (up, here) = self.at(i, j);
        2u32.saturating_mul(w.unsigned_abs())
            .saturating_add(2u32.saturating_mul(nn.unsigned_abs()))
            .saturating_add(nw.unsigned_abs())
            .saturating_add(ne.unsigned_abs())
            .saturating_add(self.v[here - 2].unsigned_abs())
            .saturating_add(self.v[up - self.w].unsigned_abs())
    }

    /// Sign context of coefficient `(i, j)`: the signs of W, N, NW and NE (81). Asked only
    /// for nonzero coefficients.
    #[inline(always)]
    pub fn sign_context(&self, i: usize, j: usize) -> usize {
        let [w, nn, nw, ne] = self.near(i, j);
        27 * sgn3(nw) + 9 * sgn3(ne) + 3 * sgn3(w) + sgn3(nn)
    }
}

/// Whether cell `(i, j)` of an `n x n` matrix is on its outer ring, where the transform
/// predicts with order 2 only (larger details).
#[inline(always)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub fn on_ring(n: usize, i: usize, j: usize) -> bool {
    i == 0 || j == 0 || i + 1 == n || j + 1 == n
}

/// Significance context of a coefficient of activity class `class`.
#[inline(always)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub fn sig_ctx(class: usize, ring: bool) -> usize {
    SIG + class + CLASSES * ring as usize
}

/// Golomb-Rice parameter and magnitude context set of a coefficient with activity `a`
/// (activity class `class`; `ring`: on the outer ring).
#[inline(always)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub fn rice(a: u32, class: usize, ring: bool) -> (u32, usize) {
    let t = a.saturating_add(8) / 16;
    let k = if t < 2 {
        0
    } else {
        (31 - t.leading_zeros()).min(RICE_MAX)
    };
    let set = if k == 0 {
        if class < 3 {
            0
        } else if class < 6 {
            1
        } else {
            2
        }
    } else {
        (2 + k as usize).min(RING_SETS - 1)
    };
    (k, set + RING_SETS * ring as usize)
}

fn size_class(size_in_blocks: usize) -> usize {
    (size_in_blocks.trailing_zeros() as usize).min(3)
}

/// Writes one quantised detail matrix (`valid` marks coded cells; others must be 0).
///
/// With `hide_signs` (a quantised level), each block's first nonzero sign follows
/// [`HIDDEN_SIGN_MIN`]; the caller guarantees the parity rule for blocks that hide it.
pub fn write_matrix<S: BitSink>(
    s: &mut S,
    g: usize,
    n: usize,
    q: &[i32],
    valid: Option<&[bool]>,
    hide_signs: bool,
) {
    let is_valid = |k: usize| valid.is_none_or(|v| v[k]);
    let nonzero = q.iter().any(|&x| x != 0);
    s.bit(ctx(g, NONZERO), nonzero);
    if !nonzero {
        return;
    }
    let bl = Blocks::new(n);
    // Per block: any non-zero, any valid cell (the quadtree asks about unions of these).
    let mut block_nz = vec![false; bl.nb * bl.nb];
    let mut block_ok = vec![false; bl.nb * bl.nb];
    for i in 0..n {
        for j in 0..n {
            let k = i * n + j;
            let blk = (i / bl.b) * bl.nb + j / bl.b;
            block_nz[blk] |= q[k] != 0;
            block_ok[blk] |= is_valid(k);
        }
    }
    let block_any = |by: usize, bx: usize, size: usize, table: &[bool]| {
        (by..by + size).any(|y| {
            table[y * bl.nb + bx..y * bl.nb + bx + size]
                .iter()
                .any(|&t| t)
        })
    };
    let top = bl.nb.trailing_zeros() as usize;
    let mut sig = vec![vec![false; bl.nb * bl.nb]; top + 1];
    sig[top][0] = true;
    // Quadtree, depth first in Z-order.
    let mut stack = vec![(0usize, 0usize, bl.nb)];
    let mut blocks = Vec::new();
    while let Some((by, bx, size)) = stack.pop() {
        if size == 1 {
            blocks.push((by, bx));
            continue;
        }
        let half = size / 2;
        let lvl = half.trailing_zeros() as usize;
        let side = bl.nb / half;
        let kids = [
            (by, bx),
            (by, bx + half),
            (by + half, bx),
            (by + half, bx + half),
        ];
        let mut candidates = [(0usize, 0usize); 4];
        let mut nc = 0;
        for (y, x) in kids {
            if block_any(y, x, half, &block_ok) {
                candidates[nc] = (y, x);
                nc += 1;
            }
        }
        let mut any = false;
        let mut sig_kids = [(0usize, 0usize); 4];
        let mut ns = 0;
        for (k, &(y, x)) in candidates[..nc].iter().enumerate() {
            let is_sig = block_any(y, x, half, &block_nz);
            let (cy, cx) = (y / half, x / half);
            if k + 1 != nc || any {
                let left = cx > 0 && sig[lvl][cy * side + cx - 1];
                let up = cy > 0 && sig[lvl][(cy - 1) * side + cx];
                s.bit(
                    ctx(g, QUAD + 3 * size_class(half) + left as usize + up as usize),
                    is_sig,
                );
            }
            if is_sig {
                any = true;
                sig[lvl][cy * side + cx] = true;
                sig_kids[ns] = (y, x);
                ns += 1;
            }
        }
        for &(y, x) in sig_kids[..ns].iter().rev() {
            stack.push((y, x, half));
        }
    }
    let mut rec = Causal::new(n);
    blocks.sort_unstable();
    // (index, row, column) of the block's valid cells (no division per cell).
    let mut cells = [(0usize, 0usize, 0usize); 16];
    for (by, bx) in blocks {
        let mut nc = 0;
        for i in by * bl.b..(by + 1) * bl.b {
            for j in bx * bl.b..(bx + 1) * bl.b {
                if is_valid(i * n + j) {
                    cells[nc] = (i * n + j, i, j);
                    nc += 1;
                }
            }
        }
        let mut seen = false;
        // The block's first nonzero, when its sign is hidden or deferred: (row, column,
        // value, sign context).
        let mut first: Option<(usize, usize, i32, usize)> = None;
        for (idx, &(k, i, j)) in cells[..nc].iter().enumerate() {
            let a = rec.activity(i, j);
            let class = activity_class(a);
            let v = q[k];
            let ring = on_ring(n, i, j);
            if idx + 1 != nc || seen {
                s.bit(ctx(g, sig_ctx(class, ring)), v != 0);
            }
            if v == 0 {
                continue;
            }
            let sign_ctx = SIGN + rec.sign_context(i, j);
            if hide_signs && !seen {
                first = Some((i, j, v, sign_ctx));
            } else {
                s.bit(ctx(g, sign_ctx), v < 0);
            }
            seen = true;
            let (kr, set) = rice(a, class, ring);
            magnitude_decisions(set, kr, v.unsigned_abs() - 1, |d| match d {
                Decision::Bit(c, bit) => s.bit(ctx(g, c), bit),
                Decision::Bypass(value, count) => s.bypass(value, count),
            });
            // Until the block ends, a first sign that is hidden or deferred reads as +.
            rec.set(
                i,
                j,
                if first.is_some_and(|f| (f.0, f.1) == (i, j)) {
                    v.unsigned_abs().min(i32::MAX as u32) as i32
                } else {
                    v
                },
            );
        }
        if let Some((i, j, v, sign_ctx)) = first {
            let nonzero = cells[..nc].iter().filter(|c| q[c.0] != 0).count();
            if nonzero < HIDDEN_SIGN_MIN {
                s.bit(ctx(g, sign_ctx), v < 0);
            } else {
                debug_assert_eq!(block_parity(q, &cells[..nc]), v < 0, "hidden sign parity");
            }
            rec.set(i, j, v);
        }
    }
}

/// One binary decision of a coded value.
#[derive(Clone, Copy)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub enum Decision {
    /// A context-coded bit (context relative to the level group).
    Bit(usize, bool),
    /// `count` equiprobable bits of a value.
    Bypass(u32, u32),
}

/// The decisions of magnitude `mag = |q| - 1` in magnitude context set `set` with
/// Golomb-Rice parameter `kr`, in coding order: the high part `mag >> kr` in unary over
/// [`MAG_BINS`] context-coded bins, past them an Exp-Golomb escape (context-coded prefix,
/// bypass suffix), then the `kr` low bits in bypass. The coder and the rate-distortion
/// quantiser's costs both walk this.
#[inline(always)]
/// Used by the encoder's rate-distortion quantiser (`quincunx_codec::rdo`).
#[doc(hidden)]
pub fn magnitude_decisions(set: usize, kr: u32, mag: u32, mut emit: impl FnMut(Decision)) {
    let hi = mag >> kr;
    let mut b = 0;
    while b < MAG_BINS {
        let more = hi > b as u32;
        emit(Decision::Bit(MAG + set * MAG_BINS + b, more));
        if !more {
            break;
        }
        b += 1;
    }
    if b == MAG_BINS {
        let e = hi - MAG_BINS as u32 + 1;
        let len = 32 - e.leading_zeros();
        for p in 0..len as usize {
            emit(Decision::Bit(
                ESCAPE + p.min(ESCAPES - 1),
                p + 1 == len as usize,
            ));
        }
        emit(Decision::Bypass(e, len - 1));
    }
    if kr > 0 {
        emit(Decision::Bypass(mag, kr));
    }
}

/// Whether the magnitudes of a block's cells sum to an odd number.
fn block_parity(q: &[i32], cells: &[(usize, usize, usize)]) -> bool {
    cells
        .iter()
        .fold(0u32, |acc, c| acc ^ (q[c.0].unsigned_abs() & 1))
        == 1
}

/// Reads one quantised detail matrix written by [`write_matrix`] into `q` (`n x n`).
pub fn read_matrix(
    d: &mut ModelDecoder<'_>,
    g: usize,
    n: usize,
    q: &mut [i32],
    valid: Option<&[bool]>,
    hide_signs: bool,
) -> Result<(), EntropyError> {
    q.iter_mut().for_each(|x| *x = 0);
    if !d.bit(ctx(g, NONZERO)) {
        return Ok(());
    }
    let is_valid = |k: usize| valid.is_none_or(|v| v[k]);
    let bl = Blocks::new(n);
    let block_valid = |by: usize, bx: usize, size: usize| {
        valid.is_none()
            || (by * bl.b..(by + size) * bl.b)
                .any(|i| (bx * bl.b..(bx + size) * bl.b).any(|j| is_valid(i * n + j)))
    };
    let top = bl.nb.trailing_zeros() as usize;
    let mut sig = vec![vec![false; bl.nb * bl.nb]; top + 1];
    sig[top][0] = true;
    let mut stack = vec![(0usize, 0usize, bl.nb)];
    let mut blocks = Vec::new();
    while let Some((by, bx, size)) = stack.pop() {
        if size == 1 {
            blocks.push((by, bx));
            continue;
        }
        let half = size / 2;
        let lvl = half.trailing_zeros() as usize;
        let side = bl.nb / half;
        let kids = [
            (by, bx),
            (by, bx + half),
            (by + half, bx),
            (by + half, bx + half),
        ];
        let mut candidates = [(0usize, 0usize); 4];
        let mut nc = 0;
        for (y, x) in kids {
            if block_valid(y, x, half) {
                candidates[nc] = (y, x);
                nc += 1;
            }
        }
        let mut any = false;
        let mut sig_kids = [(0usize, 0usize); 4];
        let mut ns = 0;
        for (k, &(y, x)) in candidates[..nc].iter().enumerate() {
            let (cy, cx) = (y / half, x / half);
            let is_sig = if k + 1 == nc && !any {
                true
            } else {
                let left = cx > 0 && sig[lvl][cy * side + cx - 1];
                let up = cy > 0 && sig[lvl][(cy - 1) * side + cx];
                d.bit(ctx(
                    g,
                    QUAD + 3 * size_class(half) + left as usize + up as usize,
                ))
            };
            if is_sig {
                any = true;
                sig[lvl][cy * side + cx] = true;
                sig_kids[ns] = (y, x);
                ns += 1;
            }
        }
        for &(y, x) in sig_kids[..ns].iter().rev() {
            stack.push((y, x, half));
        }
    }
    let mut rec = Causal::new(n);
    blocks.sort_unstable();
    // (index, row, column) of the block's valid cells (no division per cell).
    let mut cells = [(0usize, 0usize, 0usize); 16];
    for (by, bx) in blocks {
        let mut nc = 0;
        for i in by * bl.b..(by + 1) * bl.b {
            for j in bx * bl.b..(bx + 1) * bl.b {
                if is_valid(i * n + j) {
                    cells[nc] = (i * n + j, i, j);
                    nc += 1;
                }
            }
        }
        let mut seen = false;
        // The block's first nonzero, when its sign is hidden or deferred: (index, row,
        // column, sign context).
        let mut first: Option<(usize, usize, usize, usize, i64)> = None;
        let mut count = 0;
        for (idx, &(k, i, j)) in cells[..nc].iter().enumerate() {
            let a = rec.activity(i, j);
            let class = activity_class(a);
            let ring = on_ring(n, i, j);
            let nonzero = if idx + 1 == nc && !seen {
                true
            } else {
                d.bit(ctx(g, sig_ctx(class, ring)))
            };
            if !nonzero {
                continue;
            }
            count += 1;
            let sign_ctx = SIGN + rec.sign_context(i, j);
            let hidden = hide_signs && !seen;
            let negative = !hidden && d.bit(ctx(g, sign_ctx));
            seen = true;
            let (kr, set) = rice(a, class, ring);
            let mut hi = 0u32;
            while (hi as usize) < MAG_BINS && d.bit(ctx(g, MAG + set * MAG_BINS + hi as usize)) {
                hi += 1;
            }
            let mut hi = u64::from(hi);
            if hi as usize == MAG_BINS {
                let mut zeros = 0usize;
                while !d.bit(ctx(g, ESCAPE + zeros.min(ESCAPES - 1))) {
                    zeros += 1;
                    if zeros > 31 {
                        return Err(EntropyError::EscapeTooLong);
                    }
                }
                let e = (1u64 << zeros) | u64::from(d.dec.bypass(zeros as u32));
                hi = e - 1 + MAG_BINS as u64;
            }
            let low = if kr > 0 { d.dec.bypass(kr) } else { 0 };
            let mag = (hi << kr) | u64::from(low);
            if mag >= 1 << 31 {
                return Err(EntropyError::EscapeTooLong);
            }
            let m = (mag as i64) + 1;
            q[k] = if negative {
                (-m) as i32
            } else {
                m.min(i32::MAX as i64) as i32
            };
            if hidden {
                first = Some((k, i, j, sign_ctx, m));
            }
            rec.set(i, j, q[k]);
        }
        if let Some((k, i, j, sign_ctx, m)) = first {
            let negative = if count < HIDDEN_SIGN_MIN {
                d.bit(ctx(g, sign_ctx))
            } else {
                // The magnitudes' parity, the first one's as coded (`2^31` is held as
                // `2^31 - 1` until its sign is known).
                block_parity(q, &cells[..nc]) ^ (i64::from(q[k]) != m)
            };
            q[k] = if negative {
                (-m) as i32
            } else {
                m.min(i32::MAX as i64) as i32
            };
            rec.set(i, j, q[k]);
        }
        if d.dec.consumed() > d.len + 64 {
            return Err(EntropyError::Truncated);
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    fn round_trip(n: usize, q: &[i32], valid: Option<&[bool]>, model: &CodecModel) -> usize {
        round_trip_hiding(n, q, valid, model, false)
    }

    fn round_trip_hiding(
        n: usize,
        q: &[i32],
        valid: Option<&[bool]>,
        model: &CodecModel,
        hide: bool,
    ) -> usize {
        let mut e = ModelEncoder::new(model);
        write_gammas(&mut e, 2, &[0, 5, 63, 7 | NO_DATA, NO_DATA]);
        write_matrix(&mut e, 2, n, q, valid, hide);
        let bytes = e.finish();
        let mut d = ModelDecoder::new(model, &bytes);
        // The flag travels with nonzero classes; class 0 never carries it.
        assert_eq!(read_gammas(&mut d, 2, 5), vec![0, 5, 63, 7 | NO_DATA, 0]);
        let mut out = vec![7; n * n];
        read_matrix(&mut d, 2, n, &mut out, valid, hide).unwrap();
        assert_eq!(out, q);
        bytes.len()
    }

    /// Makes every 4x4 block with at least [`HIDDEN_SIGN_MIN`] nonzeros obey the parity
    /// rule, like the encoder: by moving one magnitude (here the last nonzero's) by one.
    fn obey_parity(n: usize, q: &mut [i32]) {
        for bi in (0..n).step_by(4) {
            for bj in (0..n).step_by(4) {
                let cells: Vec<usize> = (bi..bi + 4)
                    .flat_map(|i| (bj..bj + 4).map(move |j| i * n + j))
                    .filter(|&k| q[k] != 0)
                    .collect();
                if cells.len() >= HIDDEN_SIGN_MIN {
                    let odd = cells.iter().fold(0, |a, &k| a ^ (q[k].unsigned_abs() & 1)) == 1;
                    if odd != (q[cells[0]] < 0) {
                        let last = cells[cells.len() - 1];
                        q[last] += q[last].signum();
                    }
                }
            }
        }
    }

    #[test]
    fn hidden_signs_round_trip_and_save_bits() {
        let model = CodecModel::default();
        let mut seed = 5u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            seed >> 33
        };
        for density in [2u64, 5, 9, 16] {
            let mut q: Vec<i32> = (0..32 * 32)
                .map(|_| {
                    let r = next();
                    if r % 16 < density {
                        ((r >> 8) % 40) as i32 - 20
                    } else {
                        0
                    }
                })
                .collect();
            // Extreme magnitudes as a block's first nonzero, hidden and not.
            q[0] = i32::MIN;
            q[4] = i32::MAX;
            obey_parity(32, &mut q);
            let plain = round_trip_hiding(32, &q, None, &model, false);
            let hidden = round_trip_hiding(32, &q, None, &model, true);
            if density >= 9 {
                assert!(hidden < plain, "density {density}: {hidden} >= {plain}");
            }
        }
    }

    #[test]
    fn the_hidden_sign_is_the_parity_of_the_block() {
        // Eight nonzeros: the first sign is not coded. Even magnitudes give +, odd give -
        // (a decoder that read a sign here, or took the other parity, would not round trip).
        let model = CodecModel::default();
        let mut q = vec![0; 16];
        q[..8].copy_from_slice(&[3, 1, 1, 1, 1, 1, 1, 1]); // sum 10: even, first positive
        round_trip_hiding(4, &q, None, &model, true);
        q[..2].copy_from_slice(&[-3, 2]); // sum 11: odd, first negative
        round_trip_hiding(4, &q, None, &model, true);
    }

    #[test]
    fn matrices_round_trip_including_extreme_values() {
        let model = CodecModel::default();
        let mut seed = 3u64;
        for n in [2usize, 4, 8, 32, 64] {
            for density in [0u64, 1, 10, 50, 100] {
                let q: Vec<i32> = (0..n * n)
                    .map(|_| {
                        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                        if (seed >> 33) % 100 < density {
                            match (seed >> 20) % 5 {
                                0 => i32::MIN,
                                1 => i32::MAX,
                                _ => ((seed >> 40) % 41) as i32 - 20,
                            }
                        } else {
                            0
                        }
                    })
                    .collect();
                round_trip(n, &q, None, &model);
                let valid: Vec<bool> = (0..n * n).map(|k| k % 3 != 0).collect();
                let qm: Vec<i32> = q
                    .iter()
                    .enumerate()
                    .map(|(k, &x)| if valid[k] { x } else { 0 })
                    .collect();
                round_trip(n, &qm, Some(&valid), &model);
            }
        }
    }

    /// A model's bytes with every context explicit (bitmap all ones).
    fn explicit(values: &[u8]) -> Vec<u8> {
        let mut bytes = vec![0u8; CONTEXTS.div_ceil(8)];
        for k in 0..CONTEXTS {
            bytes[k / 8] |= 1 << (k % 8);
        }
        bytes.extend_from_slice(values);
        bytes
    }

    #[test]
    fn models_survive_their_bytes_and_reject_malformed_ones() {
        // Every byte is a probability, and a model's bytes give it back exactly.
        for b in 0..=255u8 {
            let m = CodecModel::from_bytes(&explicit(&vec![b; CONTEXTS])).unwrap();
            assert_eq!(
                CodecModel::from_bytes(&m.to_bytes()).unwrap(),
                m,
                "byte {b}"
            );
        }
        assert_eq!(MODEL_PROBS[128], HALF);
        assert!(MODEL_PROBS.windows(2).all(|w| w[0] <= w[1]));
        // The default model is its bitmap alone.
        let default = CodecModel::default();
        assert_eq!(default.to_bytes(), vec![0; CONTEXTS.div_ceil(8)]);
        let mut counts = ContextCounts::default();
        for (k, c) in counts.counts.iter_mut().enumerate() {
            if k % 3 != 0 {
                *c = [(k as u64 * 7919) % 1000, (k as u64 * 104_729) % 997];
            }
        }
        let trained = CodecModel::from_counts(&counts);
        let bytes = trained.to_bytes();
        assert!(bytes.len() < CONTEXTS.div_ceil(8) + CONTEXTS * 2 / 3 + 1);
        assert_eq!(CodecModel::from_bytes(&bytes).unwrap(), trained);
        // Trained probabilities stay close to the counts' (1/32 in log-odds).
        for (&p, &[n0, n1]) in trained.probs.iter().zip(&counts.counts) {
            let want = (n0 as f64 + 0.4) / ((n0 + n1) as f64 + 0.8);
            let got = f64::from(p) / 65536.0;
            let lo = |x: f64| (x / (1.0 - x)).ln();
            assert!(
                (lo(got) - lo(want.clamp(5e-4, 1.0 - 5e-4))).abs() <= 0.04,
                "{want} {got}"
            );
        }
        // Malformed: too short, a value missing or extra, bits past the last context.
        let map_len = CONTEXTS.div_ceil(8);
        assert!(CodecModel::from_bytes(&bytes[..map_len - 1]).is_err());
        assert!(CodecModel::from_bytes(&bytes[..bytes.len() - 1]).is_err());
        let mut extra = bytes.clone();
        extra.push(7);
        assert!(CodecModel::from_bytes(&extra).is_err());
        if !CONTEXTS.is_multiple_of(8) {
            let mut past = vec![0u8; map_len];
            past[map_len - 1] = 0x80;
            past.push(7);
            assert!(CodecModel::from_bytes(&past).is_err());
        }
    }

    #[test]
    fn golomb_rice_parameters_grow_with_activity_and_stay_bounded() {
        assert_eq!(rice(0, 0, false), (0, 0));
        assert_eq!(rice(23, activity_class(23), false), (0, 2));
        assert_eq!(rice(24, activity_class(24), false), (1, 3));
        assert_eq!(rice(55, activity_class(55), true).0, 1);
        assert_eq!(rice(56, activity_class(56), false).0, 2);
        assert_eq!(rice(u32::MAX, 9, false), (RICE_MAX, 9));
        assert_eq!(rice(u32::MAX, 9, true), (RICE_MAX, 2 * RING_SETS - 1));
        let mut last = 0;
        for a in (0..100_000u32).step_by(7) {
            let (k, set) = rice(a, activity_class(a), a % 2 == 0);
            assert!(k >= last && set < 2 * RING_SETS);
            last = k;
        }
    }

    /// Writes a 4 x 4 matrix whose first coefficient escapes with `zeros` prefix zeros
    /// and an all-ones suffix (its magnitude is then `2^(zeros + 1) + 13`), the rest 0.
    fn escape_stream(zeros: usize) -> Vec<u8> {
        let model = CodecModel::default();
        let mut e = ModelEncoder::new(&model);
        e.bit(ctx(0, NONZERO), true);
        // Cell (0, 0): on the ring, activity 0, k = 0, magnitude set 0 + 10.
        assert_eq!(rice(0, 0, true), (0, 10));
        e.bit(ctx(0, sig_ctx(0, true)), true);
        e.bit(ctx(0, SIGN + 40), false); // W, N, NW and NE all zero: 27 + 9 + 3 + 1
        for b in 0..MAG_BINS {
            e.bit(ctx(0, MAG + RING_SETS * MAG_BINS + b), true);
        }
        for p in 0..zeros {
            e.bit(ctx(0, ESCAPE + p.min(ESCAPES - 1)), false);
        }
        e.bit(ctx(0, ESCAPE + zeros.min(ESCAPES - 1)), true);
        e.bypass(u32::MAX, zeros as u32);
        // The other 15 cells: zero, each in the context its neighbours give it.
        let mut rec = Causal::new(4);
        rec.set(0, 0, (1i32 << (zeros + 1).min(30)) + 13);
        for k in 1..16 {
            let (i, j) = (k / 4, k % 4);
            let a = rec.activity(i, j);
            e.bit(ctx(0, sig_ctx(activity_class(a), on_ring(4, i, j))), false);
        }
        e.finish()
    }

    #[test]
    fn magnitude_escapes_decode_up_to_i32_and_are_errors_beyond() {
        let model = CodecModel::default();
        let mut q = vec![0; 16];
        // 17 prefix zeros, 17 one bits: e = 2^18 - 1, |q| - 1 = e - 1 + 14.
        let bytes = escape_stream(17);
        read_matrix(
            &mut ModelDecoder::new(&model, &bytes),
            0,
            4,
            &mut q,
            None,
            false,
        )
        .unwrap();
        assert_eq!(q[0], (1 << 18) + 13);
        assert!(q[1..].iter().all(|&x| x == 0));
        for zeros in [31, 32, 40] {
            let bytes = escape_stream(zeros);
            let got = read_matrix(
                &mut ModelDecoder::new(&model, &bytes),
                0,
                4,
                &mut q,
                None,
                false,
            );
            assert_eq!(
                got,
                Err(EntropyError::EscapeTooLong),
                "{zeros} prefix zeros"
            );
        }
    }

    #[test]
    fn an_all_zero_matrix_costs_at_most_a_byte() {
        let mut e = ModelEncoder::new(&CodecModel::default());
        write_matrix(&mut e, 0, 32, &[0; 1024], None, false);
        assert!(e.finish().len() <= 1);
    }

    #[test]
    fn gamma_classes_bound_their_values() {
        for g in [0u64, 1, 2, 3, 5, 100, 12345, 1 << 30] {
            let c = gamma_class(g);
            assert!(class_bound(c) >= g);
            if c > 0 {
                assert!(class_bound(c - 1) < g);
            }
        }
    }
}
