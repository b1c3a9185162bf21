/**
 * The blob decoder of the web demo: a bit-exact port of the decoding half of the Rust
 * codec (spec: docs/blob-format.md).
 *
 * Ports, in the order of this file:
 * - `decoder/src/blob.rs`: `DecodeError`, `crc16`, `BlobContext` (`blobContextOfLevel`),
 *   `decodeBlob` / `decodeBlobInto` (`blob::decode` / `blob::decode_into`);
 * - `decoder/src/entropy/range.rs`: the range decoder (`RangeDecoder`);
 * - `decoder/src/entropy/mod.rs`: `CodecModel` (`parseModel` = `CodecModel::from_bytes`,
 *   with an exact copy of `MODEL_PROBS`), `group`, the side information and matrix
 *   readers, `classBound`, `gammaClass`, `splitSide`, `NO_DATA`;
 * - `codec/src/encode.rs`: `dequantize`;
 * - `decoder/src/colour.rs`: `ycocgRToRgb` (inverse YCoCg-R) and `rgbToYcocgR`;
 * - `meta/src/channels.rs`: `splitChannels`;
 * - `meta/src/answer.rs` (re-exported by `store/src/answer.rs`): `parsePackage`
 *   (`answer::parse`).
 *
 * Child classes (side information), as in Rust: `decodeBlob(..).childClasses[i]` is the
 * raw entry of the i-th owned child, a byte: bits 0-6 the class `k` (0..=63; the child's
 * finer surface departs from its own grid by at most `classBound(k)` value quanta, 0 =
 * not at all, so it needs no refining), bit 7 (`NO_DATA` = 0x80) set when the child and
 * its whole subtree have no blob (a client never asks for them). The flag only travels
 * with a nonzero class. `splitSide(entry)` returns `[class, noData]` exactly like
 * `entropy::split_side`.
 *
 * Errors: every failure on untrusted bytes (blobs, models, packages, channel frames) is
 * thrown as `DecodeError`, whose `kind` names the Rust variant:
 * - `decodeBlob`: "TooShort" (`length`), "Version" (`version`), "Size" (`got`,
 *   `expected`), "Checksum" (`stored`, `computed`), "Entropy" (`entropy`: "EscapeTooLong"
 *   or "Truncated"), checked in that order like `blob::decode_into`;
 * - `parseModel`: "BadModel" (`reason`);
 * - `parsePackage`: "Truncated", "BadLength", "Trailing" (`count`), "Malformed" (`reason`);
 * - `splitChannels`: "Frame".
 * Decoding never loops without bound: as in Rust, every loop is bounded by the matrix
 * size, and a stream that reads more than 64 bytes past its end is "Entropy"/"Truncated".
 *
 * Performance: the range coder keeps its state in int32 fields (no boxed numbers), the
 * probabilities of the one level group a blob uses are copied into a reused Uint16Array,
 * and the per-size work arrays are cached; nothing is allocated per bit or per cell.
 */

// ---------------------------------------------------------------------------------------
// Errors.

/** Why untrusted bytes could not be decoded. `kind` names the Rust error variant. */
export class DecodeError extends Error {
  /**
   * @param {string} message what went wrong (the Rust error's message where one exists)
   * @param {string} [kind] the Rust variant ("Checksum", "Entropy", ...); "Invalid" when
   *   the JavaScript side has no Rust counterpart
   * @param {object} [fields] extra fields (e.g. `{stored, computed}`), copied onto the error
   */
  constructor(message, kind = "Invalid", fields = undefined) {
    super(message);
    this.name = "DecodeError";
    this.kind = kind;
    if (fields) Object.assign(this, fields);
  }
}

// ---------------------------------------------------------------------------------------
// Blob header (decoder/src/blob.rs).

/** Current blob format version. */
export const VERSION = 5;
// Version 4 blobs have the same layout (only the side-information classes' meaning changed).
export const MIN_VERSION = 4;
/** Bytes before the payload. */
export const HEADER_BYTES = 3;

/** CRC-16/CCITT-FALSE of each byte value. */
const CRC_TABLE = (() => {
  const t = new Uint16Array(256);
  for (let b = 0; b < 256; b++) {
    let crc = b << 8;
    for (let k = 0; k < 8; k++) crc = crc & 0x8000 ? ((crc << 1) ^ 0x1021) & 0xffff : (crc << 1) & 0xffff;
    t[b] = crc;
  }
  return t;
})();

/**
 * CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over the concatenation of `parts`
 * (each an array-like of bytes), like `blob::crc16(&[..])`.
 * @param {...ArrayLike<number>} parts
 * @returns {number}
 */
export function crc16(...parts) {
  let crc = 0xffff;
  for (const part of parts) {
    for (let i = 0, len = part.length; i < len; i++) {
      crc = ((crc << 8) & 0xffff) ^ CRC_TABLE[((crc >>> 8) ^ part[i]) & 0xff];
    }
  }
  return crc;
}

// ---------------------------------------------------------------------------------------
// Model and context layout (decoder/src/entropy/mod.rs).

/** Number of level groups with their own contexts. */
export const GROUPS = 6;
const NONZERO = 0;
const GAMMA_ZERO = 1;
const GAMMA_UNARY = 2; // 16
const QUAD = 18; // 4 sizes x 3
const CLASSES = 10;
const SIG = 30; // CLASSES x (inside, outer ring)
const SIGN = SIG + 2 * CLASSES; // 81 contexts
const ESCAPES = 16;
const ESCAPE = SIGN + 81;
const MAG = ESCAPE + ESCAPES; // 2 x RING_SETS x MAG_BINS
const MAG_BINS = 14;
const RING_SETS = 10;
/** Contexts per level group. */
export const PER_GROUP = MAG + 2 * RING_SETS * MAG_BINS;
/** Total number of contexts of a model. */
export const CONTEXTS = GROUPS * PER_GROUP;
const RICE_MAX = 15;
/** Sign hiding: blocks with at least this many nonzeros hide their first sign. */
export const HIDDEN_SIGN_MIN = 8;
/** Neutral probability (of a 0, 16 bits). */
export const HALF = 1 << 15;
/** Flag on a side information entry: the child and its subtree have no blob. */
export const NO_DATA = 0x80;

/** Starting probability of each model byte (exact copy of the Rust `MODEL_PROBS`). */
// prettier-ignore
const MODEL_PROBS = new Uint16Array([
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
]);

/** Starting probabilities of every context (`entropy::CodecModel`). */
export class CodecModel {
  /** @param {Uint16Array} probs one probability (of a 0, 1/65536 units) per context */
  constructor(probs) {
    if (!(probs instanceof Uint16Array) || probs.length !== CONTEXTS) {
      throw new TypeError(`a CodecModel needs a Uint16Array of ${CONTEXTS} probabilities`);
    }
    this.probs = probs;
  }

  /** Every context at 1/2 (`CodecModel::default`). */
  static default() {
    return new CodecModel(new Uint16Array(CONTEXTS).fill(HALF));
  }

  /** Same as `parseModel(bytes)`. */
  static fromBytes(bytes) {
    return parseModel(bytes);
  }
}

/**
 * Bytes of an untrusted array-like (Uint8Array as it is; an Array of numbers, e.g. from
 * JSON, checked value by value).
 */
function asBytes(bytes, kind, what) {
  if (bytes instanceof Uint8Array) return bytes;
  if (bytes instanceof ArrayBuffer) return new Uint8Array(bytes);
  if (bytes == null || typeof bytes.length !== "number") {
    throw new DecodeError(`${what}: not a byte array`, kind, { reason: "not a byte array" });
  }
  const out = new Uint8Array(bytes.length);
  for (let i = 0; i < out.length; i++) {
    const b = bytes[i];
    if (!Number.isInteger(b) || b < 0 || b > 255) {
      throw new DecodeError(`${what}: element ${i} is not a byte`, kind, { reason: "not a byte" });
    }
    out[i] = b;
  }
  return out;
}

function badModel(reason) {
  return new DecodeError(`codec model: ${reason}`, "BadModel", { reason });
}

/**
 * Parses a model's bytes (`CodecModel::from_bytes`): a bitmap of the contexts whose
 * starting probability is not 1/2, then one byte per set bit, read through `MODEL_PROBS`.
 * @param {Uint8Array|number[]} bytes
 * @returns {CodecModel}
 */
export function parseModel(bytes) {
  bytes = asBytes(bytes, "BadModel", "codec model");
  const mapLen = Math.ceil(CONTEXTS / 8);
  if (bytes.length < mapLen) throw badModel("shorter than its bitmap");
  const set = (k) => (bytes[k >> 3] >> (k & 7)) & 1;
  for (let k = CONTEXTS; k < mapLen * 8; k++) {
    if (set(k)) throw badModel("bits set past the last context");
  }
  let count = 0;
  for (let i = 0; i < mapLen; i++) {
    let b = bytes[i];
    while (b) {
      count += b & 1;
      b >>= 1;
    }
  }
  if (bytes.length - mapLen !== count) throw badModel("wrong length");
  const probs = new Uint16Array(CONTEXTS);
  let v = mapLen;
  for (let k = 0; k < CONTEXTS; k++) probs[k] = set(k) ? MODEL_PROBS[bytes[v++]] : HALF;
  return new CodecModel(probs);
}

/**
 * Level group of a diamond `distance` levels above the finest detail level
 * (`entropy::group`).
 * @param {number} distance
 * @returns {number}
 */
export function group(distance) {
  return Math.min(distance, GROUPS - 1);
}

/** Class bounds 0..=63 (`class_bound`), computed like Rust: `ceil(2^((k-1)/2))`. */
const CLASS_BOUNDS = Array.from({ length: 64 }, (_, k) => (k === 0 ? 0 : Math.ceil(Math.pow(2, (k - 1) / 2))));

/**
 * Upper bound (value quanta) represented by a side information class: 0, then
 * `ceil(sqrt(2)^(k-1))` (`entropy::class_bound`).
 * @param {number} k class, 0..=255 (decoded classes are at most 63)
 * @returns {number}
 */
export function classBound(k) {
  if (k < 64) return CLASS_BOUNDS[k];
  // Rust's saturating f64 -> u64 cast, as a (rounded) number.
  return Math.min(Math.ceil(Math.pow(2, (k - 1) / 2)), 2 ** 64);
}

/**
 * Side information class of a bound `gamma`: 0 for 0, else the smallest `k` with
 * `gamma <= classBound(k)`, at most 63 (`entropy::gamma_class`).
 * @param {number} gamma
 * @returns {number}
 */
export function gammaClass(gamma) {
  for (let k = 0; k < 64; k++) if (CLASS_BOUNDS[k] >= gamma) return k;
  return 63;
}

/**
 * The class (0..=63) and the no-data flag of a side information entry
 * (`entropy::split_side`).
 * @param {number} entry a byte of `childClasses`
 * @returns {[number, boolean]}
 */
export function splitSide(entry) {
  const c = entry & ~NO_DATA & 0xff;
  return [Math.min(c, 63), (entry & NO_DATA) !== 0 && c !== 0];
}

// ---------------------------------------------------------------------------------------
// Range decoder (decoder/src/entropy/range.rs), with a model's probabilities of one group.

const TOP = 1 << 24;
const EMPTY = new Uint8Array(0);

/**
 * Binary adaptive range decoder over a byte array (reads zeros past its end), with its
 * own copy of one level group's probabilities (`ModelDecoder`). `code` and `range` hold
 * the Rust `u32`s as int32 bit patterns, compared unsigned (`>>> 0`).
 */
class RangeDecoder {
  constructor() {
    this.probs = new Uint16Array(PER_GROUP);
    this.data = EMPTY;
    this.len = 0;
    this.pos = 0;
    this.code = 0;
    this.range = 0;
  }

  /** Starts decoding `data` with group `g` of `model`. */
  reset(model, g, data) {
    this.probs.set(model.probs.subarray(g * PER_GROUP, (g + 1) * PER_GROUP));
    this.data = data;
    this.len = data.length;
    this.pos = 0;
    this.range = -1; // u32::MAX
    let code = 0;
    for (let i = 0; i < 4; i++) code = (code << 8) | this.next();
    this.code = code;
  }

  next() {
    const p = this.pos++;
    return p < this.len ? this.data[p] : 0;
  }

  /** Decodes one bit with the adaptive probability of context `c` (of the group). */
  bit(c) {
    const probs = this.probs;
    const p = probs[c];
    // (range >> 16) * p < 2^32: its low 32 bits are the u32 bound.
    const bound = Math.imul(this.range >>> 16, p);
    let bit;
    // The probabilities start within 32..=65504 (MODEL_PROBS, HALF) and adaptation
    // keeps them there, so the clamp of Rust's `adapt` never acts and is left out.
    if (this.code >>> 0 >= bound >>> 0) {
      this.code = (this.code - bound) | 0;
      this.range = (this.range - bound) | 0;
      probs[c] = p - (p >> 6);
      bit = 1;
    } else {
      this.range = bound;
      probs[c] = p + ((65536 - p) >> 6);
      bit = 0;
    }
    while (this.range >>> 0 < TOP) {
      this.range <<= 8;
      this.code = (this.code << 8) | this.next();
    }
    return bit;
  }

  /** Decodes `count` (<= 32) equiprobable bits, most significant first. */
  bypass(count) {
    let v = 0;
    for (let k = 0; k < count; k++) {
      this.range = (this.range >>> 1) | 0;
      if (this.code >>> 0 >= this.range) {
        this.code = (this.code - this.range) | 0;
        v = v * 2 + 1;
      } else {
        v = v * 2;
      }
      while (this.range >>> 0 < TOP) {
        this.range <<= 8;
        this.code = (this.code << 8) | this.next();
      }
    }
    return v;
  }

  /** Whether decoding ran more than the coder's lookahead past the payload. */
  overrun() {
    return this.pos > this.len + 64;
  }
}

const DECODER = new RangeDecoder();

function truncated() {
  return new DecodeError("coded data ends early", "Entropy", { entropy: "Truncated" });
}

function escapeTooLong() {
  return new DecodeError("magnitude escape longer than 32 bits", "Entropy", { entropy: "EscapeTooLong" });
}

/** Reads `count` side information entries (`entropy::read_gammas`). */
function readGammas(d, count) {
  const out = new Uint8Array(count);
  for (let c = 0; c < count; c++) {
    if (!d.bit(GAMMA_ZERO)) continue;
    let hi = 0;
    while (hi < 15 && d.bit(GAMMA_UNARY + hi)) hi++;
    const lo = d.bypass(2);
    const cls = Math.min(1 + (hi << 2) + lo, 63);
    out[c] = d.bypass(1) === 1 ? cls | NO_DATA : cls;
  }
  return out;
}

// Activity classes of activities below 50: 0, 1-2, 3-4, 5-6, 7-9, 10-13, 14-19, 20-29, 30-49.
const ACTIVITY = (() => {
  const t = new Uint8Array(50);
  const bounds = [0, 2, 4, 6, 9, 13, 19, 29, 49];
  for (let a = 0; a < 50; a++) {
    let c = 0;
    while (c < bounds.length && a > bounds[c]) c++;
    t[a] = c;
  }
  return t;
})();

function activityClass(a) {
  return a < 50 ? ACTIVITY[a] : CLASSES - 1;
}

/** Golomb-Rice parameter of activity `a` (`rice`'s `k`; `a` below 2^24). */
function riceK(a) {
  const t = (a + 8) >> 4;
  return t < 2 ? 0 : Math.min(31 - Math.clz32(t), RICE_MAX);
}

/** Magnitude context set of activity `a` off the ring (`rice`'s set, without the ring). */
function riceSet(a, k) {
  if (k > 0) return Math.min(2 + k, RING_SETS - 1);
  const c = activityClass(a);
  return c < 3 ? 0 : c < 6 ? 1 : 2;
}

// `rice` tabulated for small activities (larger ones are computed in `readMatrix`).
const RICE_TABLE_SIZE = 4096;
const RICE_K = new Uint8Array(RICE_TABLE_SIZE);
const RICE_SET = new Uint8Array(RICE_TABLE_SIZE);
for (let a = 0; a < RICE_TABLE_SIZE; a++) {
  RICE_K[a] = riceK(a);
  RICE_SET[a] = riceSet(a, RICE_K[a]);
}

/** Work arrays of one diamond size, reused by every decode of that size. */
class Workspace {
  constructor(n) {
    const b = Math.min(n, 4);
    const nb = n / b;
    this.n = n;
    this.b = b;
    this.nb = nb;
    this.top = 31 - Math.clz32(nb); // log2(nb)
    this.w = n + 4;
    // Coded coefficients with two zero columns each side and two zero rows on top.
    this.rec = new Int32Array((n + 4) * (n + 2));
    // Quadtree significance per node level (sig[lvl] of (nb / 2^lvl)^2 nodes, stored nb^2).
    this.sig = new Uint8Array((this.top + 1) * nb * nb);
    this.blockSig = new Uint8Array(nb * nb);
    // Valid blocks' summed-area table (masked diamonds only).
    this.sat = new Int32Array((nb + 1) * (nb + 1));
    this.stack = new Int32Array(3 * (4 * (this.top + 1) + 1));
    this.cellK = new Int32Array(16);
    this.cellI = new Int32Array(16);
    this.cellJ = new Int32Array(16);
  }
}

const WORKSPACES = new Map();

function workspace(n) {
  let ws = WORKSPACES.get(n);
  if (!ws) {
    ws = new Workspace(n);
    WORKSPACES.set(n, ws);
  }
  return ws;
}

/**
 * Cap of the magnitudes kept for the neighbours' activity. Rust sums the true magnitudes
 * (saturating at u32::MAX), but an activity only matters up to 2^19 - 8, where the Rice
 * parameter reaches its cap of 15 (and the class its last, 9, from 50): a capped term
 * makes both sums at least 2^20, so both give the same contexts. Capped, the sum stays an
 * int32 (at most 8 x 2^20), which keeps the hot loop in integer arithmetic.
 */
const REC_CAP = 1 << 20;

/** |v| of a value within +-REC_CAP (branch-free: signs of details are random). */
function abs(v) {
  const s = v >> 31;
  return (v ^ s) - s;
}

/**
 * The magnitude `|q|` after 14 unary bins (`read_matrix`'s escape): an Exp-Golomb escape
 * (context-coded prefix, bypass suffix), then the `kr` low bits. A number up to 2^31.
 */
function readEscape(d, kr) {
  let zeros = 0;
  while (!d.bit(ESCAPE + Math.min(zeros, ESCAPES - 1))) {
    zeros++;
    if (zeros > 31) throw escapeTooLong();
  }
  const e = 2 ** zeros + d.bypass(zeros);
  const hi = e - 1 + MAG_BINS;
  const low = kr > 0 ? d.bypass(kr) : 0;
  const mag = hi * 2 ** kr + low; // < 2^48: exact
  if (mag >= 2147483648) throw escapeTooLong();
  return mag + 1;
}

/** Sign class of v (within +-REC_CAP): 0 negative, 1 zero, 2 positive (`sgn3`). */
function sgn3(v) {
  return ((v >> 31) | (-v >>> 31)) + 1;
}

/**
 * Reads one quantised detail matrix into `q` (`entropy::read_matrix`); `cells`: valid
 * cells (1 = valid) or null.
 */
function readMatrix(d, n, q, cells, hideSigns) {
  q.fill(0);
  if (!d.bit(NONZERO)) return;
  const ws = workspace(n);
  const { b, nb, top, w, rec, sig, blockSig, sat, stack, cellK, cellI, cellJ } = ws;
  sig.fill(0);
  blockSig.fill(0);
  rec.fill(0);
  const nb2 = nb * nb;
  if (cells !== null) {
    // sat[(y) (nb+1) + x]: valid blocks among rows < y, columns < x.
    const sw = nb + 1;
    for (let by = 0; by < nb; by++) {
      let row = 0;
      for (let bx = 0; bx < nb; bx++) {
        let ok = 0;
        for (let i = by * b; i < (by + 1) * b && !ok; i++) {
          for (let j = bx * b; j < (bx + 1) * b; j++) {
            if (cells[i * n + j]) {
              ok = 1;
              break;
            }
          }
        }
        row += ok;
        sat[(by + 1) * sw + bx + 1] = sat[by * sw + bx + 1] + row;
      }
    }
  }
  const blockValid = (by, bx, size) => {
    if (cells === null) return true;
    const sw = nb + 1;
    return sat[(by + size) * sw + bx + size] - sat[by * sw + bx + size] - sat[(by + size) * sw + bx] + sat[by * sw + bx] > 0;
  };

  // Quadtree, depth first in Z order.
  sig[top * nb2] = 1;
  let sp = 0;
  stack[sp++] = 0;
  stack[sp++] = 0;
  stack[sp++] = nb;
  const candY = [0, 0, 0, 0];
  const candX = [0, 0, 0, 0];
  const kidY = [0, 0, 0, 0];
  const kidX = [0, 0, 0, 0];
  while (sp > 0) {
    const size = stack[--sp];
    const bx = stack[--sp];
    const by = stack[--sp];
    if (size === 1) {
      blockSig[by * nb + bx] = 1;
      continue;
    }
    const half = size >> 1;
    const lvl = 31 - Math.clz32(half);
    const side = nb / half;
    const base = lvl * nb2;
    let nc = 0;
    for (let kid = 0; kid < 4; kid++) {
      const y = by + (kid >> 1) * half;
      const x = bx + (kid & 1) * half;
      if (blockValid(y, x, half)) {
        candY[nc] = y;
        candX[nc] = x;
        nc++;
      }
    }
    let any = false;
    let ns = 0;
    for (let k = 0; k < nc; k++) {
      const y = candY[k];
      const x = candX[k];
      const cy = y / half;
      const cx = x / half;
      let isSig;
      if (k + 1 === nc && !any) {
        isSig = 1;
      } else {
        const left = cx > 0 ? sig[base + cy * side + cx - 1] : 0;
        const up = cy > 0 ? sig[base + (cy - 1) * side + cx] : 0;
        isSig = d.bit(QUAD + 3 * Math.min(lvl, 3) + left + up);
      }
      if (isSig) {
        any = true;
        sig[base + cy * side + cx] = 1;
        kidY[ns] = y;
        kidX[ns] = x;
        ns++;
      }
    }
    for (let k = ns - 1; k >= 0; k--) {
      stack[sp++] = kidY[k];
      stack[sp++] = kidX[k];
      stack[sp++] = half;
    }
  }

  // Coefficients of each significant block, blocks and cells in raster order.
  for (let by = 0; by < nb; by++) {
    for (let bx = 0; bx < nb; bx++) {
      if (!blockSig[by * nb + bx]) continue;
      let nc = 0;
      for (let i = by * b; i < (by + 1) * b; i++) {
        for (let j = bx * b; j < (bx + 1) * b; j++) {
          const k = i * n + j;
          if (cells === null || cells[k]) {
            cellK[nc] = k;
            cellI[nc] = i;
            cellJ[nc] = j;
            nc++;
          }
        }
      }
      let seen = false;
      // The block's first nonzero when its sign is hidden or deferred.
      let firstK = -1;
      let firstI = 0;
      let firstJ = 0;
      let firstCtx = 0;
      let firstM = 0;
      let count = 0;
      for (let idx = 0; idx < nc; idx++) {
        const i = cellI[idx];
        const j = cellJ[idx];
        const up = (i + 1) * w + j + 2;
        const here = up + w;
        const vw = rec[here - 1];
        const vn = rec[up];
        const vnw = rec[up - 1];
        const vne = rec[up + 1];
        // `rec` holds magnitudes capped at REC_CAP, so this int32 sum is the activity
        // wherever the activity matters (see REC_CAP).
        const a = 2 * (abs(vw) + abs(vn)) + abs(vnw) + abs(vne) + abs(rec[here - 2]) + abs(rec[up - w]);
        const ring = i === 0 || j === 0 || i + 1 === n || j + 1 === n ? 1 : 0;
        const cls = a < 50 ? ACTIVITY[a] : CLASSES - 1;
        const nonzero = idx + 1 === nc && !seen ? 1 : d.bit(SIG + cls + CLASSES * ring);
        if (!nonzero) continue;
        count++;
        const signCtx = SIGN + 27 * sgn3(vnw) + 9 * sgn3(vne) + 3 * sgn3(vw) + sgn3(vn);
        const hidden = hideSigns && !seen;
        const negative = !hidden && d.bit(signCtx) === 1;
        seen = true;
        let kr;
        let set;
        if (a < RICE_TABLE_SIZE) {
          kr = RICE_K[a];
          set = RICE_SET[a];
        } else {
          // t = (a + 8) / 16 >= 256: k >= 8, so the set is the last one (`rice`).
          kr = 31 - Math.clz32((a + 8) >> 4);
          if (kr > RICE_MAX) kr = RICE_MAX;
          set = RING_SETS - 1;
        }
        const magBase = MAG + (set + RING_SETS * ring) * MAG_BINS;
        let hi = 0;
        while (hi < MAG_BINS && d.bit(magBase + hi)) hi++;
        let m;
        if (hi < MAG_BINS) {
          m = ((hi << kr) | (kr > 0 ? d.bypass(kr) : 0)) + 1; // < 2^19
        } else {
          m = readEscape(d, kr); // up to 2^31: a double, kept off the common path
        }
        const v = negative ? -m | 0 : m > 2147483647 ? 2147483647 : m;
        const k = cellK[idx];
        q[k] = v;
        if (hidden) {
          firstK = k;
          firstI = i;
          firstJ = j;
          firstCtx = signCtx;
          firstM = m;
        }
        rec[(i + 2) * w + j + 2] = v > REC_CAP ? REC_CAP : v < -REC_CAP ? -REC_CAP : v;
      }
      if (firstK >= 0) {
        let negative;
        if (count < HIDDEN_SIGN_MIN) {
          negative = d.bit(firstCtx) === 1;
        } else {
          // The magnitudes' parity, the first one's as coded (2^31 is held as 2^31 - 1
          // until its sign is known).
          let parity = 0;
          for (let idx = 0; idx < nc; idx++) parity ^= q[cellK[idx]] & 1;
          negative = (parity ^ (q[firstK] !== firstM ? 1 : 0)) === 1;
        }
        const v = negative ? -firstM | 0 : firstM > 2147483647 ? 2147483647 : firstM;
        q[firstK] = v;
        rec[(firstI + 2) * w + firstJ + 2] = v > REC_CAP ? REC_CAP : v < -REC_CAP ? -REC_CAP : v;
      }
      if (d.overrun()) throw truncated();
    }
  }
}

// ---------------------------------------------------------------------------------------
// Blobs (decoder/src/blob.rs).

/**
 * What the decoder must know about a diamond besides its bytes (`BlobContext`):
 * `{key, n, group, cells, ownedChildren, step}`; `cells` is a Uint8Array of `n * n`
 * (1 = valid cell) or null (all valid).
 * @typedef {{key: ArrayLike<number>, n: number, group: number, cells: Uint8Array|null,
 *   ownedChildren: number, step: number}} BlobContext
 */

/**
 * The context of a diamond of detail level `level` of `detailLevels`
 * (`BlobContext::of_level`; `step` defaults to 256 like Rust's, which callers then set
 * from the repository's steps).
 * @returns {BlobContext}
 */
export function blobContextOfLevel(key, n, detailLevels, level, cells, ownedChildren, step = 256) {
  return { key, n, group: group(detailLevels - 1 - level), cells: cells ?? null, ownedChildren, step };
}

/** Whether a diamond's blocks hide signs (`BlobContext::hides_signs`). */
export function hidesSigns(ctx) {
  return ctx.step > 256;
}

/** `n`'s trailing zero bits (log2 of a power of two). */
function trailingZeros(n) {
  return n === 0 ? 32 : 31 - Math.clz32(n & -n);
}

function checkContext(ctx) {
  const { n, group: g, cells, ownedChildren } = ctx;
  if (!Number.isInteger(n) || n < 1 || n > 1 << 15 || (n & (n - 1)) !== 0) {
    throw new TypeError(`blob context: n = ${n} is not a power of two up to 2^15`);
  }
  if (!Number.isInteger(g) || g < 0 || g >= GROUPS) throw new TypeError(`blob context: bad group ${g}`);
  if (!Number.isInteger(ownedChildren) || ownedChildren < 0) {
    throw new TypeError(`blob context: bad ownedChildren ${ownedChildren}`);
  }
  if (cells != null && cells.length !== n * n) {
    throw new TypeError(`blob context: ${cells.length} cells for n = ${n}`);
  }
}

/**
 * Decodes a blob into `q` (an Int32Array of `n * n`, overwritten), returning the child
 * classes (`blob::decode_into`).
 * @param {Uint8Array} bytes the blob (untrusted)
 * @param {BlobContext} ctx
 * @param {CodecModel} model
 * @param {Int32Array} q
 * @returns {Uint8Array} one side information entry per owned child (see the module doc)
 */
export function decodeBlobInto(bytes, ctx, model, q) {
  checkContext(ctx);
  if (!(q instanceof Int32Array) || q.length !== ctx.n * ctx.n) {
    throw new TypeError(`decodeBlobInto: q must be an Int32Array of ${ctx.n * ctx.n}`);
  }
  if (!(bytes instanceof Uint8Array)) bytes = asBytes(bytes, "Invalid", "blob");
  if (bytes.length < HEADER_BYTES) {
    throw new DecodeError(`blob of ${bytes.length} bytes is shorter than its header`, "TooShort", {
      length: bytes.length,
    });
  }
  const head = bytes[0];
  if (head >> 4 < MIN_VERSION || head >> 4 > VERSION) {
    throw new DecodeError(`blob version ${head >> 4} is not supported (expected ${MIN_VERSION} to ${VERSION})`, "Version", {
      version: head >> 4,
    });
  }
  if ((head & 15) !== trailingZeros(ctx.n)) {
    throw new DecodeError(
      `blob diamond size 2^${head & 15} does not match the repository's N = ${ctx.n}`,
      "Size",
      { got: head & 15, expected: ctx.n },
    );
  }
  const stored = bytes[1] | (bytes[2] << 8);
  const payload = bytes.subarray(HEADER_BYTES);
  const computed = crc16(ctx.key, bytes.subarray(0, 1), payload);
  if (stored !== computed) {
    const hex = (v) => "0x" + v.toString(16).padStart(4, "0");
    throw new DecodeError(`checksum mismatch (stored ${hex(stored)}, computed ${hex(computed)})`, "Checksum", {
      stored,
      computed,
    });
  }
  const d = DECODER;
  d.reset(model, ctx.group, payload);
  try {
    const classes = readGammas(d, ctx.ownedChildren);
    const cells = ctx.cells ?? null;
    readMatrix(d, ctx.n, q, cells instanceof Uint8Array || cells === null ? cells : Uint8Array.from(cells, (c) => (c ? 1 : 0)), ctx.step > 256);
    if (d.overrun()) throw truncated();
    return classes;
  } finally {
    d.data = EMPTY; // drop the reference to the caller's bytes
  }
}

/**
 * Decodes a blob (`blob::decode`).
 * @param {Uint8Array} bytes the blob (untrusted)
 * @param {BlobContext} ctx
 * @param {CodecModel} model
 * @returns {{childClasses: Uint8Array, q: Int32Array}} side information entries of the
 *   owned children, and the quantised details `n x n` row-major
 */
export function decodeBlob(bytes, ctx, model) {
  checkContext(ctx);
  const q = new Int32Array(ctx.n * ctx.n);
  const childClasses = decodeBlobInto(bytes, ctx, model, q);
  return { childClasses, q };
}

// ---------------------------------------------------------------------------------------
// Dequantisation (codec/src/encode.rs).

/**
 * Dequantises one index with a level's step (1/256 units): `sign(q) ((|q| s + 128) >> 8)`,
 * saturated to i32 (`encode::dequantize`); step 256 is the identity.
 * @param {number} q int32
 * @param {number} s u32 step
 * @returns {number} int32
 */
export function dequantize(q, s) {
  if (s === 256) return q;
  const x = Math.abs(q) * s + 128; // exact below 2^53; above, far past the saturation
  const a = x >= 549755813888 ? 2147483647 : Math.floor(x / 256); // 2^39 = (i32::MAX + 1) << 8
  return q < 0 ? -a : a;
}

/**
 * Dequantises a whole matrix (what the incremental decoder does with a blob's `q`).
 * @param {Int32Array} q
 * @param {number} s
 * @param {Int32Array} [out] may be `q` itself
 * @returns {Int32Array}
 */
export function dequantizeMatrix(q, s, out = new Int32Array(q.length)) {
  if (s === 256) {
    if (out !== q) out.set(q);
    return out;
  }
  for (let k = 0; k < q.length; k++) out[k] = dequantize(q[k], s);
  return out;
}

// ---------------------------------------------------------------------------------------
// Colour (decoder/src/colour.rs).

/**
 * Inverse YCoCg-R of one pixel (`ycocg_r_to_rgb`).
 * @returns {[number, number, number]} `[r, g, b]`
 */
export function ycocgRToRgb(y, co, cg) {
  const t = (y - (cg >> 1)) | 0;
  const g = (cg + t) | 0;
  const b = (t - (co >> 1)) | 0;
  const r = (b + co) | 0;
  return [r, g, b];
}

/** Alias of `ycocgRToRgb`. */
export const ycocgrToRgb = ycocgRToRgb;

/**
 * Forward YCoCg-R of one pixel (`rgb_to_ycocg_r`).
 * @returns {[number, number, number]} `[y, co, cg]`
 */
export function rgbToYcocgR(r, g, b) {
  const co = (r - b) | 0;
  const t = (b + (co >> 1)) | 0;
  const cg = (g - t) | 0;
  const y = (t + (cg >> 1)) | 0;
  return [y, co, cg];
}

/** Alias of `rgbToYcocgR`. */
export const rgbToYcocgr = rgbToYcocgR;

/**
 * Inverse YCoCg-R of whole planes into interleaved RGB (`out[3 k..3 k + 3]`, any typed
 * array, e.g. a Uint8ClampedArray), without allocating per pixel.
 * @param {ArrayLike<number>} y
 * @param {ArrayLike<number>} co
 * @param {ArrayLike<number>} cg
 * @param {Int32Array|Uint8Array|Uint8ClampedArray|Float32Array} out length >= 3 y.length
 * @returns the `out` array
 */
export function ycocgRPlanesToRgb(y, co, cg, out) {
  for (let k = 0, o = 0; k < y.length; k++, o += 3) {
    const t = (y[k] - (cg[k] >> 1)) | 0;
    const b = (t - (co[k] >> 1)) | 0;
    out[o] = (b + co[k]) | 0;
    out[o + 1] = (cg[k] + t) | 0;
    out[o + 2] = b;
  }
  return out;
}

// ---------------------------------------------------------------------------------------
// Channel frames (meta/src/channels.rs).

function frameError(message) {
  return new DecodeError(`malformed channel frame: ${message}`, "Frame");
}

/**
 * Splits a stored blob into its `count` channel blobs (`channels::split_channels`):
 * LEB128 length then bytes per channel, length 0 = `null` (no details there). A single
 * channel is the blob itself.
 * @param {Uint8Array} bytes
 * @param {number} count
 * @returns {(Uint8Array|null)[]} views into `bytes`
 */
export function splitChannels(bytes, count) {
  if (!(bytes instanceof Uint8Array)) bytes = asBytes(bytes, "Frame", "channel frame");
  if (count === 1) return [bytes];
  const out = [];
  let at = 0;
  for (let c = 0; c < count; c++) {
    let len = 0;
    let shift = 0;
    for (;;) {
      if (at >= bytes.length) throw frameError(`truncated in the length of channel ${c}`);
      const b = bytes[at++];
      if (shift > 28) throw frameError(`overlong length for channel ${c}`);
      len += (b & 0x7f) * 2 ** shift;
      shift += 7;
      if ((b & 0x80) === 0) break;
    }
    const rest = bytes.length - at;
    if (len > rest) throw frameError(`channel ${c} claims ${len} bytes, ${rest} remain`);
    out.push(len > 0 ? bytes.subarray(at, at + len) : null);
    at += len;
  }
  if (at !== bytes.length) throw frameError(`${bytes.length - at} trailing bytes`);
  return out;
}

// ---------------------------------------------------------------------------------------
// Packages (meta/src/answer.rs, re-exported by store/src/answer.rs).

const PACKAGE_TAG = 0xf0;

function readVarint(bytes, state) {
  let v = 0;
  for (let shift = 0; shift < 35; shift += 7) {
    if (state.at >= bytes.length) throw new DecodeError("answer truncated", "Truncated");
    const b = bytes[state.at++];
    v += (b & 0x7f) * 2 ** shift;
    if ((b & 0x80) === 0) {
      if (v > 0xffffffff) throw new DecodeError("bad length field", "BadLength");
      return v;
    }
  }
  throw new DecodeError("bad length field", "BadLength");
}

function readPart(bytes, state) {
  const len = readVarint(bytes, state);
  const end = state.at + len;
  if (end > bytes.length) throw new DecodeError("answer truncated", "Truncated");
  if (len === 0) throw new DecodeError("malformed package: empty part", "Malformed", { reason: "empty part" });
  const part = bytes.subarray(state.at, end);
  state.at = end;
  return part;
}

/**
 * Splits an answer (`answer::parse`): a package when `packaged` (it was asked for as
 * one), else the bare blob.
 * @param {Uint8Array} bytes
 * @param {boolean} [packaged]
 * @returns {{blob: Uint8Array, children: [number, Uint8Array][]}} the diamond's blob and
 *   `[owned child index, that child's answer]` pairs in index order (views into `bytes`)
 */
export function parsePackage(bytes, packaged = true) {
  if (!(bytes instanceof Uint8Array)) bytes = asBytes(bytes, "Malformed", "answer");
  if (bytes.length === 0) throw new DecodeError("malformed package: empty", "Malformed", { reason: "empty" });
  if (!packaged) return { blob: bytes, children: [] };
  const first = bytes[0];
  if ((first & 0xf0) !== PACKAGE_TAG) {
    throw new DecodeError("malformed package: not a package", "Malformed", { reason: "not a package" });
  }
  const mask = first & 0x0f;
  const state = { at: 1 };
  const blob = readPart(bytes, state);
  const children = [];
  for (let i = 0; i < 4; i++) {
    if (mask & (1 << i)) children.push([i, readPart(bytes, state)]);
  }
  if (state.at !== bytes.length) {
    const count = bytes.length - state.at;
    throw new DecodeError(`${count} trailing bytes after the last child`, "Trailing", { count });
  }
  return { blob, children };
}

/** Alias of `parsePackage` under the Rust name. */
export const parseAnswer = parsePackage;
