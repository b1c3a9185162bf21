// Coverage of a sparse repository: which coarse blocks of a raster (or of a planet's
// faces) hold data. A port of the decoder's side of decoder/src/coverage.rs: parsing
// (`Coverage.fromBytes`, hostile bytes throw DecodeError) and the queries diamond masks
// are derived from (`coversPoint`, `state`). The encoder-side builders are not ported.
//
// Blocks are B x B samples (B = 2^block_log2), aligned at sample 0; block (col, row)
// spans samples col B ..= (col+1) B (closed: neighbours share border samples). A point is
// valid when any closed block containing it is covered.
//
// Bytes: version (1), faces (1 or 6), log2 B, cols (u32 LE), rows (u32 LE), then
// faces x rows x cols bits, face by face, row-major, least significant bit first.

import { DecodeError } from "./codec.mjs";

/** Current coverage format version. */
export const COVERAGE_VERSION = 1;
const HEADER_BYTES = 11;
const MAX_SIDE = 2 ** 24;

/** Whether the blocks met by a rectangle are all covered, none, or some (Rust order). */
export const BlockState = Object.freeze({ Full: 0, Empty: 1, Mixed: 2 });

const POPCOUNT = new Uint8Array(256);
for (let b = 1; b < 256; b++) POPCOUNT[b] = (b & 1) + POPCOUNT[b >> 1];

/** Which coarse blocks of samples hold data (Rust `Coverage`). */
export class Coverage {
  constructor(faces, blockLog2, cols, rows, bits) {
    this._faces = faces;
    this._blockLog2 = blockLog2;
    this._cols = cols;
    this._rows = rows;
    this._bits = bits;
  }

  /**
   * Parses the coverage bytes of a repository's metadata (Uint8Array or array of
   * numbers); throws DecodeError on anything malformed.
   */
  static fromBytes(input) {
    const bytes = input instanceof Uint8Array ? input : Uint8Array.from(input ?? []);
    if (bytes.length < HEADER_BYTES) {
      throw new DecodeError(`coverage of ${bytes.length} bytes is shorter than its header`);
    }
    const [version, faces, blockLog2] = bytes;
    if (version !== COVERAGE_VERSION) {
      throw new DecodeError(`coverage version ${version} is not supported (expected ${COVERAGE_VERSION})`);
    }
    if (faces !== 1 && faces !== 6) throw new DecodeError("coverage header is invalid: faces is neither 1 nor 6");
    if (blockLog2 > 24) throw new DecodeError("coverage header is invalid: block side above 2^24");
    const u32 = (k) => (bytes[k] | (bytes[k + 1] << 8) | (bytes[k + 2] << 16) | (bytes[k + 3] << 24)) >>> 0;
    const cols = u32(3);
    const rows = u32(7);
    const sideOk = (x) => x >= 1 && x <= MAX_SIDE;
    if (!sideOk(cols) || !sideOk(rows)) throw new DecodeError("coverage header is invalid: block counts out of range");
    if (faces === 6 && cols !== rows) throw new DecodeError("coverage header is invalid: planet faces are not square");
    const count = faces * cols * rows;
    const expected = Math.ceil(count / 8);
    const bits = bytes.subarray(HEADER_BYTES);
    if (bits.length !== expected) {
      throw new DecodeError(`coverage bitmap of ${bits.length} bytes, the header says ${expected}`);
    }
    const tail = count % 8;
    if (tail !== 0 && bits[bits.length - 1] >> tail !== 0) throw new DecodeError("coverage padding bits are not zero");
    return new Coverage(faces, blockLog2, cols, rows, bits.slice());
  }

  /** Serialises the coverage (Rust `to_bytes`). */
  toBytes() {
    const out = new Uint8Array(HEADER_BYTES + this._bits.length);
    out[0] = COVERAGE_VERSION;
    out[1] = this._faces;
    out[2] = this._blockLog2;
    new DataView(out.buffer).setUint32(3, this._cols, true);
    new DataView(out.buffer).setUint32(7, this._rows, true);
    out.set(this._bits, HEADER_BYTES);
    return out;
  }

  _bit(face, col, row) {
    return (face * this._rows + row) * this._cols + col;
  }

  /** Faces: 1 for a planar raster, 6 for a planet. */
  faces() {
    return this._faces;
  }

  /** Side of a block, in samples. */
  blockSide() {
    return 2 ** this._blockLog2;
  }

  /** log2 of the block side. */
  blockLog2() {
    return this._blockLog2;
  }

  /** Columns of blocks per face. */
  cols() {
    return this._cols;
  }

  /** Rows of blocks per face. */
  rows() {
    return this._rows;
  }

  /** Whether block (col, row) of face `face` holds data (false outside the bitmap). */
  isCovered(face, col, row) {
    if (face >= this._faces || col >= this._cols || row >= this._rows || face < 0 || col < 0 || row < 0) {
      return false;
    }
    const k = this._bit(face, col, row);
    return ((this._bits[k >> 3] >> (k & 7)) & 1) === 1;
  }

  /** Set bits among bits start .. end of the bitmap. */
  _ones(start, end) {
    let count = 0;
    let k = start;
    while (k < end && (k & 7) !== 0) {
      count += (this._bits[k >> 3] >> (k & 7)) & 1;
      k++;
    }
    while (k + 8 <= end) {
      count += POPCOUNT[this._bits[k >> 3]];
      k += 8;
    }
    while (k < end) {
      count += (this._bits[k >> 3] >> (k & 7)) & 1;
      k++;
    }
    return count;
  }

  /** Number of covered blocks. */
  coveredBlocks() {
    let count = 0;
    for (const b of this._bits) count += POPCOUNT[b];
    return count;
  }

  /** Number of blocks. */
  blocks() {
    return this._faces * this._cols * this._rows;
  }

  /** Whether sample (x, y) of face `face` lies in a covered closed block. */
  coversPoint(face, x, y) {
    const b = this._blockLog2;
    const mask = 2 ** b - 1;
    const ox = Math.floor(x / 2 ** b);
    const oy = Math.floor(y / 2 ** b);
    const px = x > 0 && (x & mask) === 0 ? ox - 1 : -1;
    const py = y > 0 && (y & mask) === 0 ? oy - 1 : -1;
    if (this.isCovered(face, ox, oy)) return true;
    if (py >= 0 && this.isCovered(face, ox, py)) return true;
    if (px >= 0 && (this.isCovered(face, px, oy) || (py >= 0 && this.isCovered(face, px, py)))) return true;
    return false;
  }

  /**
   * The state (BlockState) of the blocks of face `face` whose closed squares meet the
   * closed rectangle x0..=x1, y0..=y1 (samples; an empty rectangle meets no block).
   */
  state(face, [x0, x1], [y0, y1]) {
    let anyIn = false;
    let anyOut = false;
    if (x0 <= x1 && y0 <= y1) {
      const div = 2 ** this._blockLog2;
      const lo = (t) => (t === 0 ? 0 : Math.floor((t - 1) / div));
      const hi = (t, count) => Math.min(Math.floor(t / div), count - 1);
      const c0 = Math.min(lo(x0), this._cols - 1);
      const c1 = hi(x1, this._cols);
      const r1 = hi(y1, this._rows);
      for (let r = Math.min(lo(y0), this._rows - 1); r <= r1; r++) {
        if (face >= this._faces || c0 > c1) {
          anyOut = true;
        } else {
          const start = this._bit(face, c0, r);
          const len = c1 - c0 + 1;
          const ones = this._ones(start, start + len);
          anyIn ||= ones > 0;
          anyOut ||= ones < len;
        }
        if (anyIn && anyOut) return BlockState.Mixed;
      }
    }
    if (anyIn && !anyOut) return BlockState.Full;
    if (!anyIn) return BlockState.Empty;
    return BlockState.Mixed;
  }

  /** Whether both coverages are the same (Rust `PartialEq`). */
  equals(other) {
    if (!(other instanceof Coverage)) return false;
    const a = this.toBytes();
    const b = other.toBytes();
    return a.length === b.length && a.every((x, k) => x === b[k]);
  }
}
