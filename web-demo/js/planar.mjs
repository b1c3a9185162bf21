// The planar domain and its incremental decoder: a bit-exact port of
// diamond/src/planar.rs (PlanarDomain, PlanarId), the per-diamond part of
// decoder/src/raster.rs (RasterFrame: placement, masks, keys, blob contexts) and
// decoder/src/incremental/mod.rs (PlanarRefiner), plus `reconstructPlanar`, which decodes a
// whole repository through the refiner (the path the viewer uses) into the canonical
// layout: per channel, width x height integers, row-major, as Rust's
// `encode::decode_integers_with` gives them.
//
// Not ported: procedural levels below the coded ones (`with_procedural_levels`; the
// refiner has exactly the repository's levels, `levels() == detailLevels()`), the
// encoder's whole-raster tables (`RasterGeometry`) and analysis.
//
// Numbers: ids are plain numbers. A domain holds m <= 48, so centres and keys are exact;
// sample positions (id x 2N) are exact while m + log2(2N) <= 53, which every raster
// domain satisfies (rasters are at most 2^24 samples a side, so m <= 25).
//
// Errors are thrown: IdError (a bad id or key) and RefineError (a diamond that cannot be
// refined or assembled), both DecodeError subclasses, and DecodeError from the blob
// decoder.

import { DecodeError, decodeBlobInto, group, parseModel, splitChannels, splitSide } from "./codec.mjs";
import { Coverage, BlockState } from "./coverage.mjs";
import { DiamondMask, synthesize as liftSynthesize, synthesizeZero, childHalf, scatterToChild } from "./lifting.mjs";

/** Deepest domain exponent (diamond/src/lib.rs `MAX_M`). */
export const MAX_M = 48;
/** Largest supported diamond size N. */
export const MAX_N = 512;

/** A malformed id, key or domain parameter (Rust `IdError`). */
export class IdError extends DecodeError {
  constructor(message) {
    super(message, "Id");
    this.name = "IdError";
  }
}

/** A diamond that cannot be refined or assembled (Rust `RefineError`). */
export class RefineError extends DecodeError {
  constructor(message) {
    super(message, "Refine");
    this.name = "RefineError";
  }
}

/** Checks that `n` is a supported diamond size (a power of two in 2..=512). */
export function checkSize(n) {
  if (!(Number.isInteger(n) && n >= 2 && n <= MAX_N && (n & (n - 1)) === 0)) {
    throw new IdError(`diamond size N = ${n} is not a power of two in 2..=${MAX_N}`);
  }
}

const TWO32 = 2 ** 32;

/** Trailing zeros with tz(0) = "infinity" (127), for integers up to 2^53. */
export function tz(v) {
  if (v === 0) return 127;
  if (v < 0) v = -v;
  const lo = v % TWO32;
  if (lo !== 0) return 31 - Math.clz32(lo & -lo);
  const hi = Math.floor(v / TWO32);
  return 63 - Math.clz32(hi & -hi);
}

/** A planar diamond id: the integer centre of the diamond. */
export class PlanarId {
  constructor(x, y) {
    this.x = x;
    this.y = y;
  }

  /** Same centre. */
  equals(other) {
    return other != null && other.x === this.x && other.y === this.y;
  }

  /** "x,y": a Map key. */
  toString() {
    return `${this.x},${this.y}`;
  }
}

function sameId(a, b) {
  return a.x === b.x && a.y === b.y;
}

/** Orientation of a level: "axis" (even) or "rotated" (odd). */
export function orientationOfLevel(level) {
  return level % 2 === 0 ? "axis" : "rotated";
}

/** Number of key bytes after the level byte for `bits` bits per coordinate. */
function keyBytes(bits) {
  return Math.ceil((2 * bits) / 8);
}

/** The planar domain [0, 2^m]^2 (Rust `PlanarDomain`). */
export class PlanarDomain {
  /** The domain [0, 2^m]^2; m in 1..=48. */
  constructor(m) {
    if (!(Number.isInteger(m) && m >= 1 && m <= MAX_M)) {
      throw new IdError(`domain exponent m = ${m} is outside 1..=${MAX_M}`);
    }
    this._m = m;
    this._size = 2 ** m;
  }

  /** The exponent m. */
  m() {
    return this._m;
  }

  /** The side S = 2^m in id units. */
  size() {
    return this._size;
  }

  /** The root diamond (level 0), centred at (S/2, S/2). */
  root() {
    return new PlanarId(this._size / 2, this._size / 2);
  }

  /** The deepest level any id of this domain can have (2m - 1). */
  maxLevel() {
    return 2 * this._m - 1;
  }

  /** Whether a point lies in the closed domain square. */
  contains(x, y) {
    return x >= 0 && x <= this._size && y >= 0 && y <= this._size;
  }

  /** {level, t} of an id, or null when it is not a centre of the domain (no throw). */
  _info(id) {
    const { x, y } = id;
    if (!Number.isInteger(x) || !Number.isInteger(y) || !this.contains(x, y)) return null;
    const tx = tz(x);
    const ty = tz(y);
    const t = Math.min(tx, ty);
    if (t >= this._m) return null;
    const level = tx === ty ? 2 * (this._m - 1 - t) : 2 * (this._m - t) - 1;
    return { level, t };
  }

  _infoOrThrow(id) {
    const info = this._info(id);
    if (info !== null) return info;
    const { x, y } = id ?? {};
    if (!Number.isInteger(x) || !Number.isInteger(y) || !this.contains(x, y)) {
      throw new IdError(`point [${x}, ${y}, 0] lies outside the domain`);
    }
    throw new IdError(`point [${x}, ${y}, 0] is not the centre of a diamond`);
  }

  /** Throws IdError unless `id` is the centre of a diamond of this domain. */
  check(id) {
    this._infoOrThrow(id);
  }

  /** Whether `id` is the centre of a diamond of this domain. */
  isValid(id) {
    return this._info(id) !== null;
  }

  /** The level of a diamond (root = 0). */
  level(id) {
    return this._infoOrThrow(id).level;
  }

  /** "axis" (even level) or "rotated" (odd level). */
  orientation(id) {
    return orientationOfLevel(this.level(id));
  }

  /** Half the diagonal of a rotated diamond / half the side of an axis-aligned one. */
  halfExtent(id) {
    return 2 ** this._infoOrThrow(id).t;
  }

  /** Corners [E1, P1, E2, P2] ([x, y] each); those of half diamonds may lie outside. */
  corners(id) {
    return this._corners(id, this._infoOrThrow(id));
  }

  _corners(id, info) {
    const cx = id.x;
    const cy = id.y;
    const h = 2 ** info.t;
    if (info.level === 0) {
      const s = this._size;
      return [[0, 0], [s, 0], [s, s], [0, s]];
    }
    // Scalars rather than arrays: this runs for every id the refiner looks at.
    let e0x, e0y, e1x, e1y, p0x, p0y, p1x, p1y;
    if (info.level % 2 === 1) {
      if (tz(cy) > tz(cx)) {
        e0x = cx - h; e0y = cy; e1x = cx + h; e1y = cy;
        p0x = cx; p0y = cy - h; p1x = cx; p1y = cy + h;
      } else {
        e0x = cx; e0y = cy - h; e1x = cx; e1y = cy + h;
        p0x = cx - h; p0y = cy; p1x = cx + h; p1y = cy;
      }
    } else {
      let ne = 0;
      let np = 0;
      for (let k = 0; k < 4; k++) {
        const x = k === 1 || k === 2 ? cx + h : cx - h;
        const y = k >= 2 ? cy + h : cy - h;
        const a = tz(x);
        const b = tz(y);
        if (a !== b && Math.min(a, b) === info.t + 1) {
          if (np === 0) { p0x = x; p0y = y; } else { p1x = x; p1y = y; }
          np++;
        } else {
          if (ne === 0) { e0x = x; e0y = y; } else { e1x = x; e1y = y; }
          ne++;
        }
      }
    }
    return frameOrderXY(e0x, e0y, e1x, e1y, p0x, p0y, p1x, p1y);
  }

  /** Parents (0 for the root, 1 for border half diamonds, else 2), in frame order. */
  parents(id) {
    const info = this._infoOrThrow(id);
    if (info.level === 0) return [];
    const c = this._corners(id, info);
    const out = [];
    for (const p of [c[1], c[3]]) if (this.contains(p[0], p[1])) out.push(new PlanarId(p[0], p[1]));
    return out;
  }

  /** Children on the midpoints of the sides, in side order, in-domain only. */
  children(id) {
    const info = this._infoOrThrow(id);
    if (info.level >= this.maxLevel()) return [];
    const c = this._corners(id, info);
    const out = [];
    for (let k = 0; k < 4; k++) {
      const a = c[k];
      const b = c[(k + 1) % 4];
      const x = (a[0] + b[0]) / 2;
      const y = (a[1] + b[1]) / 2;
      if (this.contains(x, y)) out.push(new PlanarId(x, y));
    }
    return out;
  }

  /** The same-level neighbour across each side (null on the domain border). */
  neighbours(id) {
    const c = this.corners(id);
    const out = [null, null, null, null];
    for (let k = 0; k < 4; k++) {
      const a = c[k];
      const b = c[(k + 1) % 4];
      const x = a[0] + b[0] - id.x;
      const y = a[1] + b[1] - id.y;
      const nb = new PlanarId(x, y);
      if (this.contains(x, y) && this._info(nb) !== null) out[k] = nb;
    }
    return out;
  }

  /** Whether the diamond is a border half diamond. */
  isHalf(id) {
    const level = this.level(id);
    const s = this._size;
    return level % 2 === 1 && (id.x === 0 || id.y === 0 || id.x === s || id.y === s);
  }

  /** Position of vertex (i, j) in sample units (id units x 2N). */
  vertexPosition(id, n, i, j) {
    checkSize(n);
    if (i > n || j > n || i < 0 || j < 0) throw new IdError(`grid index (${i}, ${j}) is outside the diamond grid`);
    return framePoint(this.corners(id), n, 2 * i, 2 * j);
  }

  /** Position of cell centre (i, j) in sample units. */
  cellPosition(id, n, i, j) {
    checkSize(n);
    if (i >= n || j >= n || i < 0 || j < 0) throw new IdError(`grid index (${i}, ${j}) is outside the diamond grid`);
    return framePoint(this.corners(id), n, 2 * i + 1, 2 * j + 1);
  }

  /**
   * Storage key (Uint8Array): the level byte, then the Morton code of the centre divided
   * by the level's coordinate step, big-endian in a fixed number of bytes per level.
   */
  key(id) {
    const info = this._infoOrThrow(id);
    const bits = this._m - info.t + 1;
    const len = keyBytes(bits);
    const out = new Uint8Array(1 + len);
    out[0] = info.level;
    let a = id.x / 2 ** info.t;
    let b = id.y / 2 ** info.t;
    for (let k = 0; k < bits; k++) {
      const ab = a % 2;
      const bb = b % 2;
      a = (a - ab) / 2;
      b = (b - bb) / 2;
      // Bit 2k+1 holds a's bit k, bit 2k b's; bit p sits in byte len - 1 - p/8.
      if (ab) out[1 + len - 1 - ((2 * k + 1) >> 3)] |= 1 << ((2 * k + 1) & 7);
      if (bb) out[1 + len - 1 - ((2 * k) >> 3)] |= 1 << ((2 * k) & 7);
    }
    return out;
  }

  /** Inverse of `key`; any malformed key throws IdError. */
  idFromKey(key) {
    if (key.length === 0) throw new IdError("malformed storage key: empty key");
    const level = key[0];
    if (level > this.maxLevel()) throw new IdError("malformed storage key: level deeper than the domain allows");
    const t = this.levelExponent(level);
    const bits = this._m - t + 1;
    const len = keyBytes(bits);
    if (key.length - 1 !== len) throw new IdError("malformed storage key: wrong length for its level");
    let a = 0;
    let b = 0;
    for (let p = 0; p < 8 * len; p++) {
      const bit = (key[1 + len - 1 - (p >> 3)] >> (p & 7)) & 1;
      if (!bit) continue;
      if (p >= 2 * bits) throw new IdError("malformed storage key: stray high bits");
      const k = p >> 1;
      if (p & 1) a += 2 ** k;
      else b += 2 ** k;
    }
    const id = new PlanarId(a * 2 ** t, b * 2 ** t);
    const info = this._info(id);
    if (info === null || info.level !== level) throw new IdError("malformed storage key: not a centre of its level");
    return id;
  }

  /** The half-size exponent t shared by all diamonds of a level. */
  levelExponent(level) {
    return level % 2 === 0 ? this._m - 1 - level / 2 : this._m - Math.ceil(level / 2);
  }

  /**
   * All diamonds of a level whose closed square meets the rectangle [x0, x1, y0, y1]
   * (id units), in row-major order of their centres.
   */
  diamondsMeeting(level, rect) {
    const [x0, x1, y0, y1] = rect;
    const t = this.levelExponent(level);
    const h = 2 ** t;
    const s = this._size;
    const remEuclid = (v) => ((v % h) + h) % h;
    const out = [];
    const ylo = Math.max(y0 - h, 0);
    const yhi = Math.min(y1 + h, s);
    for (let y = ylo - remEuclid(ylo); y <= yhi; y += h) {
      const xlo = Math.max(x0 - h, 0);
      const xhi = Math.min(x1 + h, s);
      for (let x = xlo - remEuclid(xlo); x <= xhi; x += h) {
        const id = new PlanarId(x, y);
        const info = this._info(id);
        if (info !== null && info.level === level && squareMeets(id, h, level, rect)) out.push(id);
      }
    }
    return out;
  }
}

function squareMeets(id, h, level, [x0, x1, y0, y1]) {
  const cx = id.x;
  const cy = id.y;
  if (level % 2 === 0) return cx + h >= x0 && cx - h <= x1 && cy + h >= y0 && cy - h <= y1;
  const dx = cx < x0 ? x0 - cx : cx > x1 ? cx - x1 : 0;
  const dy = cy < y0 ? y0 - cy : cy > y1 ? cy - y1 : 0;
  return dx + dy <= h;
}

/** Orders corners as [E1, P1, E2, P2] (E1 the lexicographically smaller end). */
export function frameOrder(ends, parents) {
  return frameOrderXY(ends[0][0], ends[0][1], ends[1][0], ends[1][1], parents[0][0], parents[0][1], parents[1][0], parents[1][1]);
}

function frameOrderXY(e0x, e0y, e1x, e1y, p0x, p0y, p1x, p1y) {
  const firstSmaller = e0x < e1x || (e0x === e1x && e0y <= e1y);
  const ax = firstSmaller ? e0x : e1x;
  const ay = firstSmaller ? e0y : e1y;
  const bx = firstSmaller ? e1x : e0x;
  const by = firstSmaller ? e1y : e0y;
  const ux = p0x - ax;
  const uy = p0y - ay;
  const vx = p1x - ax;
  const vy = p1y - ay;
  // The sign of a 2x2 cross product; exact while |coordinates| < 2^26, else BigInt.
  let positive;
  if (Math.max(Math.abs(ux), Math.abs(uy), Math.abs(vx), Math.abs(vy)) < 2 ** 26) {
    positive = ux * vy - uy * vx > 0;
  } else {
    positive = BigInt(ux) * BigInt(vy) - BigInt(uy) * BigInt(vx) > 0n;
  }
  return positive
    ? [[ax, ay], [p0x, p0y], [bx, by], [p1x, p1y]]
    : [[ax, ay], [p1x, p1y], [bx, by], [p0x, p0y]];
}

/** Point of a frame at doubled grid coordinates (p, q), in sample units. */
export function framePoint(c, n, p, q) {
  const e1 = c[0];
  const a = [c[1][0] - e1[0], c[1][1] - e1[1]];
  const b = [c[3][0] - e1[0], c[3][1] - e1[1]];
  return [2 * n * e1[0] + p * a[0] + q * b[0], 2 * n * e1[1] + p * a[1] + q * b[1]];
}

/**
 * Where one diamond's samples live in the raster (Rust `DiamondSlot`, without the
 * whole-raster decoder's linear-index shortcut): vertex (i, j) is raster point
 * (x0 + i a[0] + j b[0], y0 + i a[1] + j b[1]).
 */
export class DiamondSlot {
  constructor(id, x0, y0, a, b) {
    this.id = id;
    this.x0 = x0;
    this.y0 = y0;
    this.a = a;
    this.b = b;
    /** Valid points; null when every vertex and cell is valid. */
    this.mask = null;
    /** Storage key (Uint8Array). */
    this.key = new Uint8Array(0);
    /** Child indices (only filled by whole-raster tables; empty here). */
    this.children = [];
    this.owned = [];
  }

  /** Raster point [x, y] of vertex (i, j). */
  vertexXy(i, j) {
    return [this.x0 + i * this.a[0] + j * this.b[0], this.y0 + i * this.a[1] + j * this.b[1]];
  }

  /** Raster point [x, y] of cell (i, j). */
  cellXy(i, j) {
    const [x, y] = this.vertexXy(i, j);
    return [x + Math.trunc((this.a[0] + this.b[0]) / 2), y + Math.trunc((this.a[1] + this.b[1]) / 2)];
  }

  /** Raster position of vertex (0, 0) and the steps along i and j. */
  frame() {
    return [[this.x0, this.y0], this.a, this.b];
  }

  /** Number of valid cells (coded details). */
  validCells(n) {
    return this.mask === null ? n * n : this.mask.validCells();
  }
}

/** A diamond's frame as a slot (no key or mask), null outside the domain. */
function bareSlot(domain, id, n) {
  const info = domain._info(id);
  if (info === null) return null;
  const c = domain._corners(id, info);
  const a = [Math.trunc((c[1][0] - c[0][0]) / n), Math.trunc((c[1][1] - c[0][1]) / n)];
  const b = [Math.trunc((c[3][0] - c[0][0]) / n), Math.trunc((c[3][1] - c[0][1]) / n)];
  return new DiamondSlot(id, c[0][0], c[0][1], a, b);
}

/** A mask from a predicate on raster points, evaluated at the slot's vertices and cells. */
function maskOfPoints(s, n, pred) {
  const [ax, ay] = s.a;
  const [bx, by] = s.b;
  const hx = Math.trunc((ax + bx) / 2);
  const hy = Math.trunc((ay + by) / 2);
  return DiamondMask.fromFn(
    n,
    (i, j) => pred(s.x0 + i * ax + j * bx, s.y0 + i * ay + j * by),
    (i, j) => pred(s.x0 + i * ax + j * bx + hx, s.y0 + i * ay + j * by + hy),
  );
}

/** The raster placement of a diamond, null if none of its points is in the raster. */
function placeSlot(domain, id, n, width, height) {
  const s = bareSlot(domain, id, n);
  if (s === null) return null;
  s.key = domain.key(id);
  const inside = (x, y) => x >= 0 && y >= 0 && x < width && y < height;
  const allCorners = [[0, 0], [n, 0], [n, n], [0, n]].every(([i, j]) => inside(...s.vertexXy(i, j)));
  if (!allCorners) {
    const mask = maskOfPoints(s, n, inside);
    if (mask.validCells() === 0 && !mask.vertices().some((b) => b === 1)) return null;
    s.mask = mask;
  }
  return s;
}

/** Makes the points of slot `s` outside the covered blocks of `coverage` invalid. */
function applyCoverage(s, n, width, height, coverage, empty) {
  const covered = (x, y) => x >= 0 && y >= 0 && x < width && y < height && coverage.coversPoint(0, x, y);
  const corners = [[0, 0], [n, 0], [n, n], [0, n]].map(([i, j]) => s.vertexXy(i, j));
  const range = (k, hi) => {
    const lo = Math.min(...corners.map((c) => c[k]));
    const up = Math.max(...corners.map((c) => c[k]));
    return [Math.max(lo, 0), Math.max(Math.min(up, hi - 1), 0)];
  };
  const state = coverage.state(0, range(0, width), range(1, height));
  if (state === BlockState.Empty) s.mask = empty;
  else if (state === BlockState.Mixed) s.mask = maskOfPoints(s, n, covered);
}

/** Checks that `coverage` is a block grid of a width x height raster. */
function checkCoverage(width, height, coverage) {
  const b = coverage.blockSide();
  if (
    coverage.faces() !== 1 ||
    coverage.cols() !== Math.floor((width - 1) / b) + 1 ||
    coverage.rows() !== Math.floor((height - 1) / b) + 1
  ) {
    throw new RefineError("the coverage does not fit the geometry: block grid of another raster size");
  }
}

/**
 * Where a raster sits in the hierarchy (Rust `RasterFrame`): what refining one diamond
 * needs is derived from its id.
 */
export class RasterFrame {
  /** The frame of a width x height raster coded with N x N diamonds (and a coverage). */
  constructor(width, height, n, coverage = null) {
    checkSize(n);
    const dimOk = (v) => Number.isInteger(v) && v >= 1 && v <= 2 ** 24;
    if (!dimOk(width) || !dimOk(height)) {
      throw new RefineError(`raster of ${width} x ${height} samples is empty or too large`);
    }
    const extent = Math.max(Math.max(width, height) - 1, 1);
    let k = 0;
    while (n * 2 ** k < extent) k++;
    const m = Math.log2(n) + k;
    this._width = width;
    this._height = height;
    this._n = n;
    this._domain = new PlanarDomain(Math.max(m, 1));
    this._detailLevels = 2 * k;
    if (coverage) checkCoverage(width, height, coverage);
    this._coverage = coverage ?? null;
    this._empty = DiamondMask.none(n);
  }

  /** Raster width. */
  width() {
    return this._width;
  }

  /** Raster height. */
  height() {
    return this._height;
  }

  /** Diamond size N. */
  n() {
    return this._n;
  }

  /** The planar domain (id units = raster samples). */
  domain() {
    return this._domain;
  }

  /** Number of levels that carry details. */
  detailLevels() {
    return this._detailLevels;
  }

  /** The coverage (sparse repositories) or null. */
  coverage() {
    return this._coverage;
  }

  /** The detail level of `id` if it is a diamond of a detail level, else null. */
  _detailLevel(id) {
    const info = this._domain._info(id);
    return info !== null && info.level < this._detailLevels ? info.level : null;
  }

  /** Whether diamond `id` carries details: of a detail level, with a point in the raster. */
  isCoded(id) {
    return this._detailLevel(id) !== null && this._meets(id);
  }

  /** Whether a vertex or cell of diamond `id` lies in the raster. */
  _meets(id) {
    const s = bareSlot(this._domain, id, this._n);
    if (s === null) return false;
    const w = this._width;
    const h = this._height;
    const n = this._n;
    const inside = (x, y) => x >= 0 && y >= 0 && x < w && y < h;
    // Every point lies in the box of the corners: a box outside the raster has none.
    const { x0, y0, a, b } = s;
    const xs = [x0, x0 + n * a[0], x0 + n * (a[0] + b[0]), x0 + n * b[0]];
    const ys = [y0, y0 + n * a[1], y0 + n * (a[1] + b[1]), y0 + n * b[1]];
    const lo0 = Math.min(xs[0], xs[1], xs[2], xs[3]);
    const hi0 = Math.max(xs[0], xs[1], xs[2], xs[3]);
    const lo1 = Math.min(ys[0], ys[1], ys[2], ys[3]);
    const hi1 = Math.max(ys[0], ys[1], ys[2], ys[3]);
    if (lo0 >= w || hi0 < 0 || lo1 >= h || hi1 < 0) return false;
    for (let k = 0; k < 4; k++) if (inside(xs[k], ys[k])) return true;
    for (let i = 0; i <= n; i++) for (let j = 0; j <= n; j++) if (inside(...s.vertexXy(i, j))) return true;
    for (let i = 0; i < n; i++) for (let j = 0; j < n; j++) if (inside(...s.cellXy(i, j))) return true;
    return false;
  }

  /**
   * The slot of a diamond that carries details, as [level, DiamondSlot] (key and mask
   * with the raster's edges and coverage applied), null for others.
   */
  slot(id) {
    const level = this._detailLevel(id);
    if (level === null) return null;
    const s = placeSlot(this._domain, id, this._n, this._width, this._height);
    if (s === null) return null;
    if (this._coverage) applyCoverage(s, this._n, this._width, this._height, this._coverage, this._empty);
    return [level, s];
  }

  /**
   * The blob context (codec.mjs `decodeBlob`'s ctx) of a coded diamond's slot at `level`
   * with `owned` owned children; step 256 until the caller sets the level's step.
   */
  slotContext(level, s, owned) {
    return {
      key: s.key,
      n: this._n,
      group: group(this._detailLevels - 1 - level),
      cells: s.mask ? s.mask.cells() : null,
      mask: s.mask,
      ownedChildren: owned,
      step: 256,
    };
  }
}

/**
 * Dequantises a diamond's blob and splits its side information over its `owned` children
 * (Rust `decode_details`): {id, h: Int32Array, childClasses: [[child, class]],
 * emptyChildren: [child]}. Sets `ctx.step`; decodes into `h` (Int32Array N^2) when given.
 */
export function decodeDetails(id, blob, ctx, model, step, owned, h = null) {
  // The level's step decides sign hiding; the details are dequantised in place.
  ctx.step = step;
  if (h === null) h = new Int32Array(ctx.n * ctx.n);
  const classes = decodeBlobInto(blob, ctx, model, h);
  if (step !== 256) dequantizeInPlace(h, step);
  const childClasses = [];
  const emptyChildren = [];
  const count = Math.min(owned.length, classes.length);
  for (let k = 0; k < count; k++) {
    const [cls, noData] = splitSide(classes[k]);
    childClasses.push([owned[k], cls]);
    if (noData) emptyChildren.push(owned[k]);
  }
  return { id, h, childClasses, emptyChildren };
}

/**
 * `encode::dequantize` over a matrix, in place: sign(q) ((|q| s + 128) >> 8), saturated to
 * i32::MAX (|q| s + 128 is exact in a double below 2^53, and saturates from 2^39).
 */
function dequantizeInPlace(q, step) {
  for (let k = 0; k < q.length; k++) {
    const x = q[k];
    if (x === 0) continue;
    const p = (x < 0 ? -x : x) * step + 128;
    const a = p >= 549755813888 ? 2147483647 : Math.floor(p / 256);
    q[k] = x < 0 ? -a : a;
  }
}

/**
 * The `children` of `id` whose first parent is `id` (Rust `owned_by`); `parents(c)` may
 * throw (such children are not owned); `same(a, b)` compares ids.
 */
export function ownedBy(id, children, parents, same = (a, b) => String(a) === String(b)) {
  return children.filter((c) => {
    let p;
    try {
      p = parents(c);
    } catch {
      return false;
    }
    return p.length > 0 && same(p[0], id);
  });
}

/**
 * Lifting synthesis of one diamond from its vertex grid and details (null: zeros):
 * {id, vertices: Int32Array, cells: Int32Array, childClasses}. `into`, a refined diamond
 * no longer needed, is reused (its arrays overwritten) instead of allocating.
 */
export function synthesizeOne(n, id, grid, details, mask, into = null) {
  const side = (n + 1) * (n + 1);
  if (grid.length !== side) throw new RefineError(`expected ${side} values, got ${grid.length}`);
  if (details && details.h.length !== n * n) throw new RefineError(`expected ${n * n} values, got ${details.h.length}`);
  let vertices;
  let cells;
  if (into !== null && into.vertices.length === side && into.cells.length === n * n && into.vertices !== grid) {
    ({ vertices, cells } = into);
  } else {
    // One allocation for both (views of one buffer).
    const lattice = new Int32Array(side + n * n);
    vertices = lattice.subarray(0, side);
    cells = lattice.subarray(side);
  }
  vertices.set(grid);
  // Zero details leave the vertices as they are: synthesizeZero is synthesize with h = 0.
  if (details) liftSynthesize(n, vertices, details.h, cells, mask);
  else synthesizeZero(n, vertices, cells, mask);
  const childClasses = details ? details.childClasses.slice() : [];
  if (into === null) return { id, vertices, cells, childClasses };
  into.id = id;
  into.vertices = vertices;
  into.cells = cells;
  into.childClasses = childClasses;
  return into;
}

/** Checks a refined parent's lattice sizes. */
export function checkLattice(r, n) {
  if (r.vertices.length !== (n + 1) * (n + 1) || r.cells.length !== n * n) {
    throw new RefineError(
      `expected ${(n + 1) * (n + 1) + n * n} values, got ${r.vertices.length + r.cells.length}`,
    );
  }
}

/** Throws when a valid vertex of `child`'s grid was not written (a parent is missing). */
export function checkComplete(child, n, written, mask) {
  const valid = mask ? mask.vertices() : null;
  let missing = 0;
  for (let k = 0; k < (n + 1) * (n + 1); k++) if (!written[k] && (valid === null || valid[k])) missing++;
  if (missing > 0) {
    throw new RefineError(`${missing} valid vertices of ${child} are in none of the given parents`);
  }
}

const SLOT_CACHE = 4096;

/** Refines planar diamonds one at a time for a repository's parameters (Rust `PlanarRefiner`). */
export class PlanarRefiner {
  /**
   * @param {number} width raster width
   * @param {number} height raster height
   * @param {number} n diamond size
   * @param {Coverage|null} coverage sparse repositories
   * @param {number[]} steps quantiser step per detail level (1/256 units)
   * @param {object} model parsed entropy model (codec.mjs `parseModel`)
   * @param {Int32Array|number[]} root root vertex grid, (N+1)^2
   */
  constructor(width, height, n, coverage, steps, model, root) {
    this._geometry = new RasterFrame(width, height, n, coverage);
    const side = (n + 1) * (n + 1);
    if (root.length !== side) throw new RefineError(`expected ${side} values, got ${root.length}`);
    this._steps = Array.from(steps);
    this._model = model;
    this._root = Int32Array.from(root);
    this._slots = new Map();
    this._side = this._geometry.domain().size();
  }

  /**
   * The refiner of channel `channel` of a planar repository's metadata.json object
   * (roots, steps, model and coverage as arrays of numbers); throws DecodeError when the
   * metadata is not a usable planar repository.
   */
  static fromMetadata(meta, channel = 0) {
    const bad = (reason) => new DecodeError(`metadata: ${reason}`);
    if (meta == null || typeof meta !== "object") throw bad("not an object");
    if (meta.domain !== "planar") throw bad(`domain ${JSON.stringify(meta.domain)} is not planar`);
    if (meta.complete === false) throw bad("the build did not complete");
    const channels = meta.channels;
    if (!Array.isArray(channels) || channels.length === 0) throw bad("no channels");
    const coding = channels[channel];
    if (coding == null) throw bad(`no channel ${channel} (${channels.length} channels)`);
    if (!Array.isArray(meta.extent) || meta.extent.length !== 2) throw bad("extent is not [width, height]");
    if (!Array.isArray(coding.roots) || coding.roots.length !== 1) throw bad("a planar repository has one root grid");
    if (!Array.isArray(coding.steps) || !coding.steps.every((x) => Number.isInteger(x) && x >= 0 && x <= 0xffffffff)) {
      throw bad("steps are not a list of u32");
    }
    const root = coding.roots[0];
    if (!Array.isArray(root) || !root.every((x) => Number.isInteger(x) && x >= -(2 ** 31) && x < 2 ** 31)) {
      throw bad("the root grid is not a list of i32");
    }
    if (!Array.isArray(coding.model) && !(coding.model instanceof Uint8Array)) throw bad("model missing");
    const model = parseModel(Uint8Array.from(coding.model));
    const coverage = meta.coverage == null ? null : Coverage.fromBytes(meta.coverage);
    const r = new PlanarRefiner(
      meta.extent[0],
      meta.extent[1],
      meta.n,
      coverage,
      coding.steps,
      model,
      coding.roots[0],
    );
    if (r.detailLevels() !== meta.levels || r.domain().m() !== meta.m) {
      throw bad(
        `levels ${meta.levels} and m ${meta.m} disagree with the extent and N ` +
          `(levels ${r.detailLevels()}, m ${r.domain().m()})`,
      );
    }
    return r;
  }

  /** Diamond size N. */
  n() {
    return this._geometry.n();
  }

  /** Raster [width, height] in samples. */
  rasterSize() {
    return [this._geometry.width(), this._geometry.height()];
  }

  /** The id space. */
  domain() {
    return this._geometry.domain();
  }

  /** The raster frame. */
  geometry() {
    return this._geometry;
  }

  /** Levels that carry details. */
  detailLevels() {
    return this._geometry.detailLevels();
  }

  /** Levels that can be refined (no procedural levels here: the detail levels). */
  levels() {
    return this._geometry.detailLevels();
  }

  /** Whether `id` is refined from a blob of the repository. */
  isCoded(id) {
    return this._geometry.isCoded(id);
  }

  /** The root diamond and its vertex grid: [PlanarId, Int32Array]. */
  root() {
    return [this._geometry.domain().root(), this._root];
  }

  /** The roots, [[id, grid]] (one for planar). */
  roots() {
    return [this.root()];
  }

  /**
   * What is derived of one diamond, cached (bounded): its slot ([level, DiamondSlot] or
   * null; masks are immutable and shared), and lazily its coded children and owned ones.
   */
  _entry(id) {
    const { x, y } = id;
    if (!(Number.isInteger(x) && Number.isInteger(y) && x >= 0 && y >= 0 && x <= this._side && y <= this._side)) {
      return { found: null, coded: null, owned: null }; // outside the domain: no diamond
    }
    // A number key, unique in the domain: x (S + 1) + y < 2^51 (raster domains: S <= 2^25).
    const k = x * (this._side + 1) + y;
    let e = this._slots.get(k);
    if (e === undefined) {
      e = { found: this._geometry.slot(id), coded: null, owned: null };
      if (this._slots.size >= SLOT_CACHE) this._slots.clear();
      this._slots.set(k, e);
    }
    return e;
  }

  /** RasterFrame.slot of `id`, cached. */
  _slot(id) {
    return this._entry(id).found;
  }

  /**
   * What a client needs to know about a refinable diamond: {level, key, mask, children,
   * procedural: false}; null for leaves (outside the raster or finer than its levels).
   */
  info(id) {
    const found = this._slot(id);
    if (found === null) return null;
    const [level, slot] = found;
    const children =
      this._geometry.detailLevels() > level + 1 ? this._codedChildren(id) : this._childrenInRaster(id);
    return { level, key: slot.key, mask: slot.mask, children: children.slice(), procedural: false };
  }

  /** `info(id).children` alone (null for leaves). */
  children(id) {
    const i = this.info(id);
    return i === null ? null : i.children;
  }

  _codedChildren(id) {
    const e = this._entry(id);
    if (e.coded === null) e.coded = this._geometry.domain().children(id).filter((c) => this._geometry.isCoded(c));
    return e.coded;
  }

  _ownedChildren(id, level) {
    if (level + 1 >= this._geometry.detailLevels()) return [];
    const e = this._entry(id);
    if (e.owned === null) {
      const domain = this._geometry.domain();
      e.owned = ownedBy(id, this._codedChildren(id), (c) => domain.parents(c), sameId);
    }
    return e.owned;
  }

  _childrenInRaster(id) {
    return this._geometry.domain().children(id).filter((c) => this._meetsRaster(c));
  }

  /** Whether `id` can be refined here. */
  isRefinable(id) {
    return this._geometry.isCoded(id);
  }

  _meetsRaster(id) {
    const domain = this._geometry.domain();
    const info = domain._info(id);
    if (info === null) return false;
    const c = domain._corners(id, info);
    const w = this._geometry.width();
    const h = this._geometry.height();
    const minX = Math.min(c[0][0], c[1][0], c[2][0], c[3][0]);
    const maxX = Math.max(c[0][0], c[1][0], c[2][0], c[3][0]);
    const minY = Math.min(c[0][1], c[1][1], c[2][1], c[3][1]);
    const maxY = Math.max(c[0][1], c[1][1], c[2][1], c[3][1]);
    return minX < w && maxX >= 0 && minY < h && maxY >= 0;
  }

  /** The parents of `id` inside the domain (none for the root; [] for a bad id). */
  parents(id) {
    const domain = this._geometry.domain();
    return domain.isValid(id) ? domain.parents(id) : [];
  }

  /** The ids at the frame corners P1 and P2 (they may lie outside the domain). */
  sideParents(id) {
    const c = this._cornersOrZero(id);
    return [new PlanarId(c[1][0], c[1][1]), new PlanarId(c[3][0], c[3][1])];
  }

  _cornersOrZero(id) {
    const domain = this._geometry.domain();
    return domain.isValid(id) ? domain.corners(id) : [[0, 0], [0, 0], [0, 0], [0, 0]];
  }

  /** Frame corners [E1, P1, E2, P2] as [x, y, 0]. */
  corners(id) {
    return this._cornersOrZero(id).map((p) => [p[0], p[1], 0]);
  }

  /** Storage key of a diamond (Uint8Array). */
  key(id) {
    return this._geometry.domain().key(id);
  }

  /** The blob URL centre of an id: [x, y]. */
  centre(id) {
    return [id.x, id.y];
  }

  /** The id as a fetch key [x, y, 0]. */
  static keyOf(id) {
    return [id.x, id.y, 0];
  }

  /** The id of a fetch key. */
  static idOf(key) {
    return new PlanarId(key[0], key[1]);
  }

  /**
   * Decodes the blob of `id` (Uint8Array) into its details (see `decodeDetails`); into
   * `h` (Int32Array N^2, reused) when given.
   */
  decode(id, blob, h = null) {
    const found = this._slot(id);
    if (found === null) throw new RefineError(`diamond ${id} is not refinable in this repository`);
    const [level, slot] = found;
    const owned = this._ownedChildren(id, level);
    const ctx = this._geometry.slotContext(level, slot, owned.length);
    const step = this._steps[level] ?? 256;
    return decodeDetails(id, blob, ctx, this._model, step, owned.slice(), h);
  }

  /**
   * Refines `id` from its vertex grid and decoded details (null: no blob, zero details):
   * {id, vertices, cells, childClasses} (`vertices` and `cells` may be views of one
   * buffer). `into`: a refined diamond no longer needed, whose arrays are reused.
   */
  synthesize(id, grid, details, into = null) {
    if (details && !sameId(details.id, id)) throw new RefineError(`diamond ${id} is not refinable in this repository`);
    const found = this._slot(id);
    if (found === null) throw new RefineError(`diamond ${id} is not refinable in this repository`);
    return synthesizeOne(this.n(), id, grid, details ?? null, found[1].mask, into);
  }

  /** `decode` (when `blob` is not null) then `synthesize` (`into` as there). */
  refine(id, grid, blob, into = null) {
    const details = blob == null ? null : this.decode(id, blob);
    return this.synthesize(id, grid, details, into);
  }

  /**
   * The part of `child`'s vertex grid that lies in the given refined parents:
   * [grid: Int32Array (unwritten = 0), written: Uint8Array].
   */
  partialChildGrid(child, parents) {
    const n = this.n();
    const grid = new Int32Array((n + 1) * (n + 1));
    const written = new Uint8Array((n + 1) * (n + 1));
    this._scatterParents(child, parents, grid, written);
    return [grid, written];
  }

  _scatterParents(child, parents, grid, written) {
    const n = this.n();
    const domain = this._geometry.domain();
    const childFrame = domain.corners(child);
    const trueParents = domain.parents(child);
    for (const parent of parents) {
      const notAParent = () => new RefineError(`${parent.id} is not a parent of ${child}`);
      if (!trueParents.some((p) => sameId(p, parent.id))) throw notAParent();
      checkLattice(parent, n);
      const map = childHalf(domain.corners(parent.id), childFrame, n);
      if (map === null) throw notAParent();
      scatterToChild(map, n, parent.vertices, parent.cells, grid, written);
    }
  }

  /**
   * The vertex grid of `child` cut from its refined parents' lattices (pass both, or the
   * one of a border half diamond); every valid vertex must be covered. Invalid ones are 0.
   * Written into `out` (Int32Array (N+1)^2) when given.
   */
  childGrid(child, parents, out = null) {
    const n = this.n();
    const grid = out ?? new Int32Array((n + 1) * (n + 1));
    if (out !== null) grid.fill(0);
    if (this._written === undefined) this._written = new Uint8Array((n + 1) * (n + 1));
    const written = this._written;
    written.fill(0);
    this._scatterParents(child, parents, grid, written);
    if (this.isRefinable(child)) {
      const found = this._slot(child);
      checkComplete(child, n, written, found === null ? null : found[1].mask);
    }
    return grid;
  }
}

/** Writes a refined diamond's valid cells (and interior vertices when `vertices`) into `out`. */
function writeRefined(out, width, slot, n, r, vertices) {
  const { x0, y0, a, b, mask } = slot;
  const w = n + 1;
  const si = a[1] * width + a[0];
  const sj = b[1] * width + b[0];
  const v0 = y0 * width + x0;
  const c0 = v0 + Math.trunc((a[1] + b[1]) / 2) * width + Math.trunc((a[0] + b[0]) / 2);
  const rc = r.cells;
  const rv = r.vertices;
  if (mask === null) {
    for (let i = 0; i < n; i++) {
      let at = c0 + i * si;
      for (let k = i * n, end = k + n; k < end; k++, at += sj) out[at] = rc[k];
    }
    if (vertices) {
      for (let i = 1; i < n; i++) {
        let at = v0 + i * si + sj;
        for (let k = i * w + 1, end = i * w + n; k < end; k++, at += sj) out[at] = rv[k];
      }
    }
    return;
  }
  const cells = mask.cells();
  for (let i = 0; i < n; i++) {
    for (let j = 0; j < n; j++) if (cells[i * n + j]) out[c0 + i * si + j * sj] = rc[i * n + j];
  }
  if (vertices) {
    const vs = mask.vertices();
    for (let i = 1; i < n; i++) {
      for (let j = 1; j < n; j++) if (vs[i * w + j]) out[v0 + i * si + j * sj] = rv[i * w + j];
    }
  }
}

/**
 * Decodes every diamond of every level of a planar repository through PlanarRefiner
 * (coarse to fine, each child's grid cut from its refined parents) and returns one
 * Int32Array per channel: width x height integers, row-major, before value scale and
 * offset, exactly Rust's whole-raster decoder's output (points outside a sparse coverage
 * hold what it leaves there: 0, or the root grid's value at root vertices).
 *
 * @param {object} meta metadata.json object
 * @param {(centre: number[]) => (Uint8Array|null)} getBlob the stored blob of the diamond
 *   centred at [x, y] (for colour: the channel-framed blob), null for a leaf
 */
export function reconstructPlanar(meta, getBlob) {
  const count = Array.isArray(meta?.channels) ? meta.channels.length : 0;
  if (count === 0) throw new DecodeError("metadata: no channels");
  const refiners = [];
  for (let c = 0; c < count; c++) refiners.push(PlanarRefiner.fromMetadata(meta, c));
  const r0 = refiners[0];
  // The channels share one geometry: what is derived of a diamond is worked out once.
  for (const r of refiners) r._slots = r0._slots;
  const n = r0.n();
  const [width, height] = r0.rasterSize();
  const domain = r0.domain();
  let out;
  try {
    out = refiners.map(() => new Int32Array(width * height));
  } catch (e) {
    if (e instanceof RangeError) throw new DecodeError(`a ${width} x ${height} raster does not fit in memory here`);
    throw e;
  }

  // The root grid, at every vertex inside the raster (the whole-raster decoder's
  // scatter_root; with a coverage it includes invalid vertices).
  const [rootId] = r0.root();
  const rootSlot = bareSlot(domain, rootId, n);
  for (let c = 0; c < count; c++) {
    const grid = refiners[c].root()[1];
    for (let i = 0; i <= n; i++) {
      for (let j = 0; j <= n; j++) {
        const [x, y] = rootSlot.vertexXy(i, j);
        if (x >= 0 && y >= 0 && x < width && y < height) out[c][y * width + x] = grid[i * (n + 1) + j];
      }
    }
  }

  // Lattices of the level before the previous one are reused; one scratch grid and one
  // detail matrix serve every diamond (both are consumed by its synthesis).
  const pool = [];
  const grid = new Int32Array((n + 1) * (n + 1));
  const h = new Int32Array(n * n);
  const side = domain.size() + 1; // map keys x side + y, below 2^51
  let levelIds = [rootId];
  let previous = refiners.map(() => new Map());
  for (let level = 0; level < r0.detailLevels(); level++) {
    const current = refiners.map(() => new Map());
    const next = [];
    const seen = new Set();
    for (const id of levelIds) {
      const info = r0.info(id);
      if (info === null || info.level !== level) {
        throw new RefineError(`diamond ${id} is not refinable at level ${level}`);
      }
      const slot = r0._slot(id)[1];
      let raw = getBlob(r0.centre(id));
      if (raw != null && raw.length === 0) raw = null;
      const parts = raw === null ? new Array(count).fill(null) : count === 1 ? [raw] : splitChannels(raw, count);
      const parentIds = level === 0 ? [] : domain.parents(id);
      const key = id.x * side + id.y;
      for (let c = 0; c < count; c++) {
        const r = refiners[c];
        if (level > 0) {
          const parents = [];
          for (const p of parentIds) {
            const got = previous[c].get(p.x * side + p.y);
            if (got !== undefined) parents.push(got);
          }
          r.childGrid(id, parents, grid);
        }
        const part = parts[c] != null && parts[c].length > 0 ? parts[c] : null;
        const details = part === null ? null : r.decode(id, part, h);
        const refined = r.synthesize(id, level === 0 ? r.root()[1] : grid, details, pool.pop() ?? null);
        writeRefined(out[c], width, slot, n, refined, part !== null);
        current[c].set(key, refined);
      }
      for (const child of info.children) {
        const k = child.x * side + child.y;
        if (!seen.has(k)) {
          seen.add(k);
          next.push(child);
        }
      }
    }
    for (const m of previous) for (const r of m.values()) pool.push(r);
    previous = current;
    levelIds = next;
  }
  return out;
}
