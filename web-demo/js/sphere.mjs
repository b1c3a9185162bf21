// The planet side of the web demo: a bit-exact port of
// - diamond/src/sphere.rs: the cube-mapped sphere domain (SphereDomain, SphereId: the
//   integer centre [x, y, z] of a diamond on the surface of the cube [-2^m, 2^m]^3, its
//   face, level, storage key, children, parents, corners and vertex positions) and the
//   equal-angle cube -> unit sphere map;
// - the parts of codec/src/sphere_raster.rs a refiner needs (SphereFrame: a diamond's slot
//   in the cube raster, its mask under a sparse coverage, its blob context);
// - decoder/src/incremental/sphere.rs (SphereRefiner: decode, synthesise, assemble a child's
//   grid from its parents' lattices, also across cube edges);
// - `reconstructSphere(meta, getBlob)`: every diamond of every level refined through the
//   SphereRefiner, written into the cube raster as the whole-planet decoder
//   (codec::encode::decode_sphere_integers_with) writes it (the Rust test
//   codec/tests/incremental_sphere.rs checks the two agree).
//
// Procedural levels (SphereRefiner::with_procedural_levels) are not ported: a diamond below
// the repository's finest level is a leaf here (`info` is null, `isRefinable` false).
//
// Ids: `SphereId` holds its centre `c = [x, y, z]` as plain numbers; `String(id)` is
// "x,y,z" (a Map key). Coordinates and positions are exact while they stay below 2^53: the
// domain's exponent is limited to JS_MAX_M = 40 (positions reach 3 S 2N <= 2^(m + 12)).
// Repositories have m <= 23 (face side <= 2^24), so every real id fits; so do the ids of
// the finer domain `vertexFine` uses (m + log2 N).

import { DecodeError, decodeBlob, dequantizeMatrix, group, parseModel, splitChannels, splitSide } from "./codec.mjs";
import { BlockState, Coverage } from "./coverage.mjs";
import { DiamondMask, childHalf, scatterToChild, synthesize, synthesizeZero } from "./lifting.mjs";

/// Faces `+X, -X, +Y, -Y, +Z, -Z` (face `f`: normal axis `f >> 1`, sign `+` for even `f`).
export const POS_X = 0;
export const NEG_X = 1;
export const POS_Y = 2;
export const NEG_Y = 3;
export const POS_Z = 4;
export const NEG_Z = 5;
/// Short names of the faces, by index.
export const FACE_NAMES = ["+X", "-X", "+Y", "-Y", "+Z", "-Z"];

/// diamond::MAX_M (the Rust id space) and the largest exponent this port handles exactly.
export const MAX_M = 48;
export const JS_MAX_M = 40;
/// diamond::MAX_N: the largest diamond size.
export const MAX_N = 512;

/// A malformed or out-of-domain id, key or grid index (diamond::IdError).
export class IdError extends DecodeError {
  constructor(message) {
    super(message, "Id");
    this.name = "IdError";
  }
}

/// A diamond id: its integer centre `c = [x, y, z]` on the cube surface.
export class SphereId {
  constructor(c) {
    this.c = c;
  }

  /// "x,y,z": a key for Maps and Sets.
  toString() {
    return `${this.c[0]},${this.c[1]},${this.c[2]}`;
  }

  equals(other) {
    return (
      other != null &&
      this.c[0] === other.c[0] &&
      this.c[1] === other.c[1] &&
      this.c[2] === other.c[2]
    );
  }
}

/// "x,y,z" of an id (a SphereId or any `{c: [x, y, z]}`, e.g. one that went through
/// structured clone): a Map key.
export function idKey(id) {
  const c = id.c;
  return `${c[0]},${c[1]},${c[2]}`;
}

/// An id in error messages (Rust's Debug form).
function idText(id) {
  const c = id?.c;
  return Array.isArray(c) ? `SphereId { c: [${c.join(", ")}] }` : String(id);
}

/// Whether two ids (SphereIds or `{c}` objects) have the same centre.
export function sameId(a, b) {
  return a != null && b != null && a.c[0] === b.c[0] && a.c[1] === b.c[1] && a.c[2] === b.c[2];
}

const TWO32 = 4294967296;

/// Trailing zeros of an integer with tz(0) = 127 (diamond::tz).
function tz(v) {
  if (v === 0) return 127;
  let t = 0;
  let lo = v % TWO32;
  while (lo === 0) {
    v /= TWO32;
    t += 32;
    lo = v % TWO32;
  }
  lo |= 0;
  return t + 31 - Math.clz32(lo & -lo);
}

/// diamond::check_size: `n` a power of two in 2..=MAX_N.
function checkSize(n) {
  if (!Number.isInteger(n) || n < 2 || n > MAX_N || (n & (n - 1)) !== 0) {
    throw new IdError(`diamond size N = ${n} is not a power of two in 2..=${MAX_N}`);
  }
}

const AXES = [0, 1, 2, 3, 4, 5].map(makeAxes);

function makeAxes(face) {
  const a = (face >> 1) % 3;
  return face % 2 === 0
    ? { a, s: 1, b: (a + 1) % 3, c: (a + 2) % 3 }
    : { a, s: -1, b: (a + 2) % 3, c: (a + 1) % 3 };
}

/// Axes of face `face`: normal axis `a` with sign `s`, chart axes `b` (u) and `c` (v).
export function axes(face) {
  return AXES[face] ?? makeAxes(face);
}

/// Chart coordinates on `face` of a point lying on that face (half side `s`).
export function chartOf(face, p, s) {
  const ax = axes(face);
  return [p[ax.b] + s, p[ax.c] + s];
}

/// Chart coordinates on `face` (half side `s`) of a point `p` on `face` or on `across`
/// (a face adjacent to it, or null): points on `across` are unfolded across the shared
/// edge. null when `p` is on neither face or the faces are not adjacent.
export function unfold(face, across, p, s) {
  const ax = axes(face);
  if (p[ax.a] === ax.s * s) return chartOf(face, p, s);
  if (across == null || across >= 6) return null;
  const gx = axes(across);
  if (gx.a === ax.a || p[gx.a] !== gx.s * s) return null;
  // Distance from the shared edge, measured on `across`; unfolded it continues past it.
  const d = s - ax.s * p[ax.a];
  const q = [p[0], p[1], p[2]];
  q[gx.a] = gx.s * (s + d);
  q[ax.a] = ax.s * s;
  return chartOf(face, q, s);
}

/// Maps a point of the unfolded chart of `face` (half side `s`) back onto the cube: a
/// coordinate outside [0, 2s] is carried across that edge (at most one, by at most 2s).
export function fold(face, uv, s) {
  const ax = axes(face);
  let xa = ax.s * s;
  let xb = uv[0] - s;
  let xc = uv[1] - s;
  const ob = xb < -s || xb > s;
  const oc = xc < -s || xc > s;
  const bad = () => new IdError(`point [${uv[0]}, ${uv[1]}, ${face}] is outside the domain`);
  if (ob && oc) throw bad();
  if (ob) {
    const d = Math.abs(xb) - s;
    if (d > 2 * s) throw bad();
    xb = Math.sign(xb) * s;
    xa = ax.s * (s - d);
  }
  if (oc) {
    const d = Math.abs(xc) - s;
    if (d > 2 * s) throw bad();
    xc = Math.sign(xc) * s;
    xa = ax.s * (s - d);
  }
  const p = [0, 0, 0];
  // `+ 0` turns a negative zero (a sign times 0) into 0.
  p[ax.a] = xa + 0;
  p[ax.b] = xb + 0;
  p[ax.c] = xc + 0;
  return p;
}

/// diamond::planar::frame_order: `[E1, P1, E2, P2]`, E1 the lexicographically smaller end.
function frameOrder(ends, parents) {
  const [x, y] = ends;
  const smaller = x[0] < y[0] || (x[0] === y[0] && x[1] <= y[1]);
  const [e1, e2] = smaller ? [x, y] : [y, x];
  const a0 = parents[0][0] - e1[0];
  const a1 = parents[0][1] - e1[1];
  const b0 = parents[1][0] - e1[0];
  const b1 = parents[1][1] - e1[1];
  // Components are 0, +-h or +-2h (h a power of two): the products are exact.
  return a0 * b1 - a1 * b0 > 0
    ? [e1, parents[0], e2, parents[1]]
    : [e1, parents[1], e2, parents[0]];
}

/// diamond::planar::frame_point: the frame's point at doubled grid coordinates (p, q).
function framePoint(c, n, p, q) {
  const e1 = c[0];
  return [
    2 * n * e1[0] + p * (c[1][0] - e1[0]) + q * (c[3][0] - e1[0]),
    2 * n * e1[1] + p * (c[1][1] - e1[1]) + q * (c[3][1] - e1[1]),
  ];
}

function keyBytes(bits) {
  return Math.ceil((2 * bits) / 8);
}

/// The surface of the cube [-2^m, 2^m]^3.
export class SphereDomain {
  /// `m` in 1..=JS_MAX_M (Rust allows up to MAX_M = 48; see the module comment).
  constructor(m) {
    if (!Number.isInteger(m) || m < 1 || m > MAX_M) {
      throw new IdError(`domain exponent m = ${m} is outside 1..=${MAX_M}`);
    }
    if (m > JS_MAX_M) {
      throw new IdError(`domain exponent m = ${m} exceeds ${JS_MAX_M}, the exact range of this port`);
    }
    this._m = m;
    this._s = 2 ** m;
  }

  /// The exponent `m`.
  m() {
    return this._m;
  }

  /// The half side S = 2^m (a face chart spans [0, 2S]).
  size() {
    return this._s;
  }

  /// The six face roots (level 0), in face order.
  roots() {
    const s = this._s;
    return [
      new SphereId([s, 0, 0]),
      new SphereId([-s, 0, 0]),
      new SphereId([0, s, 0]),
      new SphereId([0, -s, 0]),
      new SphereId([0, 0, s]),
      new SphereId([0, 0, -s]),
    ];
  }

  /// The deepest level (2m + 1).
  maxLevel() {
    return 2 * this._m + 1;
  }

  /// Whether a point lies on the cube surface.
  onSurface(p) {
    const s = this._s;
    return p.every((x) => x >= -s && x <= s) && p.some((x) => x === s || x === -s);
  }

  /// `{face, other, uv, level, t}` of a checked id (throws IdError otherwise).
  _info(id) {
    const s = this._s;
    const p = id?.c;
    if (
      !Array.isArray(p) ||
      p.length !== 3 ||
      !p.every((x) => Number.isSafeInteger(x) && x >= -s && x <= s)
    ) {
      throw new IdError(`${String(p)} is outside the domain`);
    }
    let face = -1;
    let other = null;
    let count = 0;
    for (let axis = 0; axis < 3; axis++) {
      const x = p[axis];
      if (x === s || x === -s) {
        const f = 2 * axis + (x === -s ? 1 : 0);
        if (count === 0) face = f;
        else if (count === 1) other = f;
        count++;
      }
    }
    if (count === 0) throw new IdError(`${String(p)} is outside the domain`);
    if (count === 3) throw new IdError(`${String(p)} is not the centre of a diamond`);
    const uv = chartOf(face, p, s);
    const tu = tz(uv[0]);
    const tv = tz(uv[1]);
    const t = Math.min(tu, tv);
    if (t > this._m) throw new IdError(`${String(p)} is not the centre of a diamond`);
    const level = tu === tv ? 2 * (this._m - t) : 2 * (this._m - t) + 1;
    return { face, other, uv, level, t };
  }

  /// Throws IdError unless `id` is the centre of a diamond of this domain.
  check(id) {
    this._info(id);
  }

  /// Whether `id` is the centre of a diamond of this domain.
  isValid(id) {
    try {
      this._info(id);
      return true;
    } catch (e) {
      if (e instanceof IdError) return false;
      throw e;
    }
  }

  /// The level (face roots 0).
  level(id) {
    return this._info(id).level;
  }

  /// Half the diagonal of a rotated diamond / half the side of an axis-aligned one.
  halfExtent(id) {
    return 2 ** this._info(id).t;
  }

  /// The half-size exponent `t` of a level (m - level / 2, not below 0).
  levelExponent(level) {
    return Math.max(this._m - (level >> 1), 0);
  }

  /// `[face, other]`: the canonical face and, for edge diamonds, the other face (else null).
  faces(id) {
    const info = this._info(id);
    return [info.face, info.other];
  }

  /// Chart coordinates of the centre on `face`, one of its faces.
  faceChart(id, face) {
    const info = this._info(id);
    if (face === info.face || face === info.other) return chartOf(face, id.c, this._s);
    throw new IdError(`${idText(id)} is not on face ${face}`);
  }

  /// The id centred at chart point `uv` of `face`; `u, v` in [0, 2S].
  fromFaceChart(face, uv) {
    const s = this._s;
    if (!(face >= 0 && face < 6) || !uv.every((x) => x >= 0 && x <= 2 * s)) {
      throw new IdError(`point [${uv[0]}, ${uv[1]}, ${face}] is outside the domain`);
    }
    const id = new SphereId(fold(face, uv, s));
    this._info(id);
    return id;
  }

  /// `[face, other, corners]`: the frame corners `[E1, P1, E2, P2]` in the unfolded chart
  /// of the canonical face, that face and (edge diamonds) the other face.
  chartFrame(id) {
    const info = this._info(id);
    return [info.face, info.other, this._chartCorners(info)];
  }

  _chartCorners(info) {
    const [cu, cv] = info.uv;
    const h = 2 ** info.t;
    if (info.level === 0) {
      const s2 = 2 * this._s;
      return [
        [0, 0],
        [s2, 0],
        [s2, s2],
        [0, s2],
      ];
    }
    let ends;
    let parents;
    if (info.level % 2 === 1) {
      if (tz(cv) > tz(cu)) {
        ends = [
          [cu - h, cv],
          [cu + h, cv],
        ];
        parents = [
          [cu, cv - h],
          [cu, cv + h],
        ];
      } else {
        ends = [
          [cu, cv - h],
          [cu, cv + h],
        ];
        parents = [
          [cu - h, cv],
          [cu + h, cv],
        ];
      }
    } else {
      // Axis-aligned diamonds of level >= 2 lie inside one face.
      const all = [
        [cu - h, cv - h],
        [cu + h, cv - h],
        [cu + h, cv + h],
        [cu - h, cv + h],
      ];
      ends = [null, null];
      parents = [null, null];
      let ne = 0;
      let np = 0;
      for (const p of all) {
        const a = tz(p[0]);
        const b = tz(p[1]);
        if (a !== b && Math.min(a, b) === info.t + 1) {
          parents[Math.min(np, 1)] = p;
          np++;
        } else {
          ends[Math.min(ne, 1)] = p;
          ne++;
        }
      }
    }
    return frameOrder(ends, parents);
  }

  _foldId(face, uv) {
    return new SphereId(fold(face, uv, this._s));
  }

  /// Corners `[E1, P1, E2, P2]` as points on the cube surface.
  corners(id) {
    const info = this._info(id);
    const c = this._chartCorners(info);
    const s = this._s;
    return [fold(info.face, c[0], s), fold(info.face, c[1], s), fold(info.face, c[2], s), fold(info.face, c[3], s)];
  }

  /// Parents `[P1, P2]` (none for face roots).
  parents(id) {
    const info = this._info(id);
    if (info.level === 0) return [];
    const c = this._chartCorners(info);
    return [this._foldId(info.face, c[1]), this._foldId(info.face, c[3])];
  }

  /// Children centred on the side midpoints, in side order (none at the deepest level).
  children(id) {
    const info = this._info(id);
    if (info.level >= this.maxLevel()) return [];
    const c = this._chartCorners(info);
    const out = [];
    for (let k = 0; k < 4; k++) {
      const a = c[k];
      const b = c[(k + 1) % 4];
      out.push(this._foldId(info.face, [Math.trunc((a[0] + b[0]) / 2), Math.trunc((a[1] + b[1]) / 2)]));
    }
    return out;
  }

  /// The same-level neighbour across each side (side k joins corners k and k+1).
  neighbours(id) {
    const info = this._info(id);
    const c = this._chartCorners(info);
    const out = [];
    for (let k = 0; k < 4; k++) {
      const a = c[k];
      const b = c[(k + 1) % 4];
      out.push(this._foldId(info.face, [a[0] + b[0] - info.uv[0], a[1] + b[1] - info.uv[1]]));
    }
    return out;
  }

  /// Position of vertex (i, j), 0 <= i, j <= n, in id units x 2n: a point on the cube
  /// surface of half side S 2n.
  vertexPosition(id, n, i, j) {
    checkSize(n);
    if (!(i >= 0 && i <= n && j >= 0 && j <= n)) {
      throw new IdError(`grid index (${i}, ${j}) is outside the diamond grid`);
    }
    return this._samplePosition(id, n, 2 * i, 2 * j);
  }

  /// Position of cell centre (i, j), 0 <= i, j < n, in id units x 2n.
  cellPosition(id, n, i, j) {
    checkSize(n);
    if (!(i >= 0 && i < n && j >= 0 && j < n)) {
      throw new IdError(`grid index (${i}, ${j}) is outside the diamond grid`);
    }
    return this._samplePosition(id, n, 2 * i + 1, 2 * j + 1);
  }

  _samplePosition(id, n, p, q) {
    const info = this._info(id);
    const c = this._chartCorners(info);
    return fold(info.face, framePoint(c, n, p, q), this._s * 2 * n);
  }

  /// Storage key: level byte, face byte, then the Morton code of the canonical chart
  /// position divided by the level's step, big-endian, ceil(2 bits / 8) bytes.
  key(id) {
    const info = this._info(id);
    const bits = this._m - info.t + 2;
    const scale = 2 ** info.t;
    let a = info.uv[0] / scale;
    let b = info.uv[1] / scale;
    const nb = keyBytes(bits);
    const out = new Uint8Array(2 + nb);
    out[0] = info.level;
    out[1] = info.face;
    const last = 2 + nb - 1;
    for (let k = 0; k < bits; k++) {
      const abit = a % 2;
      const bbit = b % 2;
      a = (a - abit) / 2;
      b = (b - bbit) / 2;
      if (abit) out[last - ((2 * k + 1) >> 3)] |= 1 << ((2 * k + 1) & 7);
      if (bbit) out[last - ((2 * k) >> 3)] |= 1 << ((2 * k) & 7);
    }
    return out;
  }

  /// Inverse of `key`; any malformed or non-canonical key throws IdError.
  idFromKey(key) {
    if (key.length < 2) throw new IdError("malformed storage key: key shorter than its header");
    const level = key[0];
    const face = key[1];
    if (level > this.maxLevel()) {
      throw new IdError("malformed storage key: level deeper than the domain allows");
    }
    if (face >= 6) throw new IdError("malformed storage key: face index out of range");
    const t = this.levelExponent(level);
    const bits = this._m - t + 2;
    const nb = keyBytes(bits);
    if (key.length - 2 !== nb) throw new IdError("malformed storage key: wrong length for its level");
    const last = 2 + nb - 1;
    const bit = (pos) => (key[last - (pos >> 3)] >> (pos & 7)) & 1;
    for (let pos = 2 * bits; pos < 8 * nb; pos++) {
      if (bit(pos)) throw new IdError("malformed storage key: stray high bits");
    }
    let a = 0;
    let b = 0;
    for (let k = bits - 1; k >= 0; k--) {
      a = 2 * a + bit(2 * k + 1);
      b = 2 * b + bit(2 * k);
    }
    const scale = 2 ** t;
    const uv = [a * scale, b * scale];
    const s = this._s;
    if (!uv.every((x) => x >= 0 && x <= 2 * s)) {
      throw new IdError("malformed storage key: position outside the face");
    }
    let id;
    try {
      id = new SphereId(fold(face, uv, s));
    } catch {
      throw new IdError("malformed storage key: position outside the face");
    }
    let info;
    try {
      info = this._info(id);
    } catch {
      throw new IdError("malformed storage key: not a centre");
    }
    if (info.level !== level || info.face !== face) {
      throw new IdError("malformed storage key: not a canonical centre of its level");
    }
    return id;
  }
}

/// The equal-angle (tangent) cube -> unit sphere map (diamond::sphere::cube_to_unit_sphere):
/// `p` (any non-zero point, any unit) is scaled onto [-1, 1]^3, the two coordinates other
/// than the largest become tan(pi x / 4), then the point is normalised. The origin and
/// non-finite inputs are returned unchanged.
export function cubeToUnitSphere(p) {
  const big = Math.max(Math.abs(p[0]), Math.abs(p[1]), Math.abs(p[2]));
  if (big === 0 || !p.every((x) => Number.isFinite(x))) return [p[0], p[1], p[2]];
  const q = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    const x = p[k] / big;
    q[k] = Math.abs(p[k]) === big ? Math.sign(x) : Math.tan((Math.PI / 4) * x);
  }
  const norm = Math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
  return [q[0] / norm, q[1] / norm, q[2] / norm];
}

/// Inverse of `cubeToUnitSphere`: a direction to the cube [-1, 1]^3.
export function unitSphereToCube(q) {
  const big = Math.max(Math.abs(q[0]), Math.abs(q[1]), Math.abs(q[2]));
  if (big === 0 || !q.every((x) => Number.isFinite(x))) return [q[0], q[1], q[2]];
  const p = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    p[k] = Math.abs(q[k]) === big ? Math.sign(q[k]) : Math.atan(q[k] / big) / (Math.PI / 4);
  }
  return p;
}

/// World position (metres) of a cube point `p` (any unit) at height `heightM` above a
/// sphere of `radiusM`: the unit direction times (radius + height), as the Rust client and
/// renderer place planet vertices (client SphereWorld::point, render WorldFrame::point).
/// Height = value_offset + integer x value_scale.
export function planetPoint(p, radiusM, heightM) {
  const d = cubeToUnitSphere(p);
  const r = radiusM + heightM;
  return [d[0] * r, d[1] * r, d[2] * r];
}

// ---------------------------------------------------------------------------------------
// The cube raster and single diamonds in it (decoder/src/sphere_raster.rs).

/// An affine index map: vertex (i, j) at `v0 + i si + j sj`, cell (i, j) at
/// `c0 + i si + j sj` (cube-raster indices).
class Placement {
  constructor(v0, c0, si, sj) {
    this.v0 = v0;
    this.c0 = c0;
    this.si = si;
    this.sj = sj;
  }
}

/// Where one diamond's samples live in the cube raster (no child indices: the refiner
/// derives children from ids).
export class SphereSlot {
  constructor(id, key, lower, upper, diagUpper, mask) {
    /// The diamond.
    this.id = id;
    /// Its storage key (Uint8Array).
    this.key = key;
    /// Points with i >= j (all points of a diamond inside one face): P1's face.
    this.lower = lower;
    /// Edge diamonds: points with i <= j, on P2's face; else null.
    this.upper = upper;
    /// Whether the canonical copy of a diagonal point is the upper one.
    this.diagUpper = diagUpper;
    /// Valid points (DiamondMask), null when all are valid.
    this.mask = mask;
  }

  _pick(i, j) {
    const up = this.upper;
    return up !== null && (j > i || (j === i && this.diagUpper)) ? up : this.lower;
  }

  /// Cube-raster index of the canonical copy of vertex (i, j).
  vertexIndex(i, j) {
    const p = this._pick(i, j);
    return p.v0 + i * p.si + j * p.sj;
  }

  /// Cube-raster index of the canonical copy of cell (i, j).
  cellIndex(i, j) {
    const p = this._pick(i, j);
    return p.c0 + i * p.si + j * p.sj;
  }

  /// Whether the diamond straddles a cube edge.
  isEdge() {
    return this.upper !== null;
  }

  /// Writes points margin..side-margin of a side x side grid to every copy in `raster`
  /// (vertices: side N+1, margin 1; cells: side N, margin 0), as the whole-planet decoder
  /// does (SphereSlot::scatter).
  scatter(side, margin, cell, values, raster) {
    const lo = this.lower;
    const bl = cell ? lo.c0 : lo.v0;
    const end = side - margin;
    const up = this.upper;
    if (up === null) {
      for (let i = margin; i < end; i++) {
        let k = bl + i * lo.si + margin * lo.sj;
        let src = i * side + margin;
        for (let j = margin; j < end; j++, k += lo.sj, src++) raster[k] = values[src];
      }
      return;
    }
    const bu = cell ? up.c0 : up.v0;
    for (let i = margin; i < end; i++) {
      for (let j = margin; j < end; j++) {
        const x = values[i * side + j];
        if (j <= i) raster[bl + i * lo.si + j * lo.sj] = x;
        if (j >= i) raster[bu + i * up.si + j * up.sj] = x;
      }
    }
  }
}

function frameError(message) {
  return new DecodeError(`planet geometry: ${message}`);
}

/// A planet's placement in the sphere hierarchy (sphere_raster::SphereFrame): what refining
/// one diamond needs (slot in the cube raster, key, mask) derived from its id.
export class SphereFrame {
  /// A planet of `faceSide` samples per face side (N 2^k) coded with N x N diamonds and,
  /// for sparse planets, its `coverage` (a Coverage, or null).
  constructor(faceSide, n, coverage = null) {
    try {
      checkSize(n);
    } catch (e) {
      throw frameError(e.message);
    }
    if (!Number.isInteger(faceSide) || faceSide <= 0 || faceSide > 2 ** 24) {
      throw frameError(`bad dimensions ${faceSide} x ${faceSide}`);
    }
    const ratio = faceSide / n;
    if (!Number.isInteger(ratio) || (ratio & (ratio - 1)) !== 0) {
      throw frameError(`face side ${faceSide} is not N = ${n} times a power of two`);
    }
    const k = tz(ratio);
    const m = tz(faceSide) - 1;
    if (m === 0) throw frameError(`face side ${faceSide} is not N = ${n} times a power of two`);
    if (coverage !== null) {
      const b = coverage.blockSide();
      if (coverage.faces() !== 6 || coverage.cols() !== coverage.rows() || coverage.cols() * b !== faceSide) {
        throw frameError("coverage: block grid of another planet size");
      }
    }
    this._faceSide = faceSide;
    this._n = n;
    this._domain = new SphereDomain(m);
    this._detailLevels = 2 * k;
    this._coverage = coverage;
    this._noneMask = null;
  }

  /// Levels that carry details.
  detailLevels() {
    return this._detailLevels;
  }

  /// The detail level of `id`, or null when it is not a diamond of a detail level.
  codedLevel(id) {
    let level;
    try {
      level = this._domain.level(id);
    } catch (e) {
      if (e instanceof IdError) return null;
      throw e;
    }
    return level < this._detailLevels ? level : null;
  }

  /// Whether `id` has a slot (codedSlot is not null), without working out its mask.
  hasSlot(id) {
    if (this.codedLevel(id) === null) return false;
    try {
      this._slot(id);
      return true;
    } catch (e) {
      if (e instanceof DecodeError) return false;
      throw e;
    }
  }

  /// `[level, slot]` of a diamond that carries details (with its mask under a coverage),
  /// null for others.
  codedSlot(id) {
    const level = this.codedLevel(id);
    if (level === null) return null;
    let s;
    try {
      s = this._slot(id);
    } catch (e) {
      if (e instanceof DecodeError) return null;
      throw e;
    }
    if (this._coverage !== null) {
      this._noneMask ??= DiamondMask.none(this._n);
      s.mask = this._coverageMask(this._coverage, s, this._noneMask);
    }
    return [level, s];
  }

  /// The blob context (codec.mjs `decodeBlob`) of a slot at `level` with `owned` owned
  /// children; step 256 until the caller sets the level's step.
  slotContext(level, s, owned) {
    return {
      key: s.key,
      n: this._n,
      group: group(this._detailLevels - 1 - level),
      cells: s.mask === null ? null : s.mask.cells(),
      ownedChildren: owned,
      step: 256,
    };
  }

  _coverageMask(coverage, s, empty) {
    const n = this._n;
    const twoN = 2 * n;
    const corners = [];
    for (const [i, j] of [
      [0, 0],
      [n, 0],
      [n, n],
      [0, n],
    ]) {
      let p;
      try {
        p = this._domain.vertexPosition(s.id, n, i, j);
      } catch (e) {
        if (e instanceof IdError) continue;
        throw e;
      }
      corners.push(p.map((x) => Math.trunc(x / twoN)));
    }
    const half = this._half();
    const lo = [0, 1, 2].map((k) => (corners.length ? Math.min(...corners.map((p) => p[k])) : 0));
    const hi = [0, 1, 2].map((k) => (corners.length ? Math.max(...corners.map((p) => p[k])) : 0));
    const clamp = (x) => Math.min(Math.max(x + half, 0), 2 * half);
    let state = null;
    for (let f = 0; f < 6; f++) {
      const ax = axes(f);
      const plane = ax.s * half;
      if (!(lo[ax.a] <= plane && plane <= hi[ax.a])) continue;
      const here = coverage.state(f, [clamp(lo[ax.b]), clamp(hi[ax.b])], [clamp(lo[ax.c]), clamp(hi[ax.c])]);
      state = state === null ? here : state === here ? state : BlockState.Mixed;
    }
    switch (state ?? BlockState.Mixed) {
      case BlockState.Full:
        return null;
      case BlockState.Empty:
        return empty;
      default:
        return DiamondMask.fromFn(
          n,
          (i, j) => this._isValidIndex(coverage, s.vertexIndex(i, j)),
          (i, j) => this._isValidIndex(coverage, s.cellIndex(i, j)),
        );
    }
  }

  /// Whether cube-raster entry `index` is a valid point under `coverage`.
  _isValidIndex(coverage, index) {
    const w = this._width();
    const face = Math.floor(index / (w * w));
    const rest = index % (w * w);
    const u = rest % w;
    const v = Math.floor(rest / w);
    if (u >= 1 && u < w - 1 && v >= 1 && v < w - 1) return coverage.coversPoint(face, u, v);
    const p = this.samplePosition(face, u, v);
    const s = this._half();
    for (let f = 0; f < 6; f++) {
      const ax = axes(f);
      if (p[ax.a] === ax.s * s) {
        const [cu, cv] = chartOf(f, p, s);
        if (coverage.coversPoint(f, cu, cv)) return true;
      }
    }
    return false;
  }

  /// The coverage (null without one).
  coverage() {
    return this._coverage;
  }

  /// Whether cube-raster entry `index` is a valid point (always, without a coverage).
  isValid(index) {
    return index >= 0 && index < this.cubeLen() && (this._coverage === null || this._isValidIndex(this._coverage, index));
  }

  /// Samples per face side (2S).
  faceSide() {
    return this._faceSide;
  }

  /// Diamond size N.
  n() {
    return this._n;
  }

  /// The sphere domain (id units = samples, S = faceSide / 2).
  domain() {
    return this._domain;
  }

  /// Length of the cube raster: 6 (2S+1)^2.
  cubeLen() {
    const w = this._width();
    return 6 * w * w;
  }

  /// Number of distinct surface points: 6 (2S)^2 + 2.
  distinctPoints() {
    return 6 * this._faceSide * this._faceSide + 2;
  }

  _width() {
    return this._faceSide + 1;
  }

  _half() {
    return this._faceSide / 2;
  }

  /// Index of face `face`'s sample (u, v): `(face (2S+1) + v) (2S+1) + u`.
  cubeIndex(face, u, v) {
    const w = this._width();
    return (face * w + v) * w + u;
  }

  /// The cube point (id units) of face `face`'s sample (u, v).
  samplePosition(face, u, v) {
    const ax = axes(face);
    const s = this._half();
    const p = [0, 0, 0];
    p[ax.a] = ax.s * s;
    p[ax.b] = u - s;
    p[ax.c] = v - s;
    return p;
  }

  /// Cube-raster indices of every copy of surface point `p` (id units), canonical first.
  pointIndices(p) {
    const s = this._half();
    const out = [];
    if (!p.every((x) => x >= -s && x <= s)) return out;
    for (let f = 0; f < 6; f++) {
      const ax = axes(f);
      if (p[ax.a] === ax.s * s) {
        const [u, v] = chartOf(f, p, s);
        out.push(this.cubeIndex(f, u, v));
      }
    }
    return out;
  }

  /// Cube-raster indices of every copy of the point at entry `index`, canonical first.
  indexCopies(index) {
    const w = this._width();
    const face = Math.floor(index / (w * w));
    const rest = index % (w * w);
    return this.pointIndices(this.samplePosition(face, rest % w, Math.floor(rest / w)));
  }

  /// Whether cube-raster entry `index` is the canonical copy of its point.
  isCanonical(index) {
    const w = this._width();
    const face = Math.floor(index / (w * w));
    const rest = index % (w * w);
    const u = rest % w;
    const v = Math.floor(rest / w);
    if (u >= 1 && u < w - 1 && v >= 1 && v < w - 1) return true;
    return this.pointIndices(this.samplePosition(face, u, v))[0] === index;
  }

  /// The cube-raster placement of a diamond (no mask).
  _slot(id) {
    const d = this._domain;
    const n = this._n;
    const twoN = 2 * n;
    const at = (i, j) => d.vertexPosition(id, n, i, j).map((x) => Math.trunc(x / twoN));
    const cell = d.cellPosition(id, n, 0, 0).map((x) => Math.trunc(x / twoN));
    const v00 = at(0, 0);
    const v10 = at(1, 0);
    const v01 = at(0, 1);
    const s = this._half();
    const w = this._width();
    const lin = (f, p) => {
      const [u, v] = chartOf(f, p, s);
      return (f * w + v) * w + u;
    };
    const place = (f, a, b, c, e) => new Placement(lin(f, v00), lin(f, cell), lin(f, b) - lin(f, a), lin(f, e) - lin(f, c));
    const [face, other] = d.faces(id);
    let lower;
    let upper = null;
    let diagUpper = false;
    if (other === null) {
      lower = place(face, v00, v10, v00, v01);
    } else {
      const v11 = at(1, 1);
      const p1 = at(n, 0);
      const ax = axes(face);
      const lowerFace = p1[ax.a] === ax.s * s ? face : other;
      const upperFace = lowerFace === face ? other : face;
      lower = place(lowerFace, v00, v10, v10, v11);
      upper = place(upperFace, v01, v11, v00, v01);
      diagUpper = upperFace === face;
    }
    return new SphereSlot(id, d.key(id), lower, upper, diagUpper, null);
  }

  /// The slot of any diamond (roots and leaves too), without a mask.
  slot(id) {
    return this._slot(id);
  }
}


// ---------------------------------------------------------------------------------------
// Incremental decoding (decoder/src/incremental/sphere.rs and the shared parts of mod.rs).

/// A refinement error (incremental::RefineError): a bug of the caller or bad data.
export class RefineError extends DecodeError {
  constructor(message) {
    super(message, "Refine");
    this.name = "RefineError";
  }
}

const SLOT_CACHE = 4096;

/// Refines planet diamonds one at a time for a repository's parameters.
///
/// Returned shapes (mirroring Rust):
/// - `Details`: `{id, h: Int32Array(N^2), childClasses: [[childId, class], ...],
///   emptyChildren: [childId, ...]}`;
/// - `Refined`: `{id, vertices: Int32Array((N+1)^2), cells: Int32Array(N^2), childClasses}`;
/// - `DiamondInfo`: `{level, key: Uint8Array, mask: DiamondMask|null, children: [SphereId],
///   procedural: false}`.
export class SphereRefiner {
  /// A planet of `faceSide` samples per face side coded with N x N diamonds, its coverage
  /// (or null), quantiser steps, parsed entropy model and six face-root vertex grids.
  constructor(faceSide, n, coverage, steps, model, roots) {
    this._frame = new SphereFrame(faceSide, n, coverage);
    const side = (n + 1) * (n + 1);
    if (!Array.isArray(roots) || roots.length !== 6) {
      throw new RefineError(`expected 6 root grids, got ${roots?.length}`);
    }
    const bad = roots.find((r) => r.length !== side);
    if (bad !== undefined) throw new RefineError(`expected ${side} values, got ${bad.length}`);
    this._roots = roots.map((r) => Int32Array.from(r));
    this._steps = Array.from(steps);
    this._model = model;
    this._rootIds = this._frame.domain().roots();
    this._slots = new Map();
    /// Metres per integer value and at 0 (fromMetadata; else 1 and 0).
    this.valueScale = 1;
    this.valueOffset = 0;
    /// Planet radius in metres (fromMetadata; else null).
    this.radiusM = null;
  }

  /// The refiner of channel `channel` of a planet's metadata.json object (the checks of
  /// client-core/src/open.rs sphere_channel_refiner).
  static fromMetadata(meta, channel = 0) {
    const bad = (reason) => new DecodeError(`repository metadata: ${reason}`);
    if (meta === null || typeof meta !== "object") throw bad("not an object");
    if (meta.domain !== "sphere") throw bad(`domain ${JSON.stringify(meta.domain)}: not a planet`);
    if (meta.complete !== true) throw bad("the build did not complete");
    if (!Array.isArray(meta.channels) || meta.channels.length === 0) throw bad("no channels");
    const coding = meta.channels[channel];
    if (coding == null) throw bad(`no channel ${channel} (${meta.channels.length} channels)`);
    if (!Array.isArray(coding.roots) || coding.roots.length !== 6) {
      throw bad(`a planet has 6 root grids, not ${coding.roots?.length}`);
    }
    const bytes = (x, what) => {
      if (!Array.isArray(x) || !x.every((b) => Number.isInteger(b) && b >= 0 && b < 256)) {
        throw bad(`${what} is not a byte array`);
      }
      return Uint8Array.from(x);
    };
    let model;
    try {
      model = parseModel(bytes(coding.model, "entropy model"));
    } catch (e) {
      throw bad(`entropy model: ${e.message}`);
    }
    let coverage = null;
    if (meta.coverage != null) {
      try {
        coverage = Coverage.fromBytes(bytes(meta.coverage, "coverage"));
      } catch (e) {
        throw bad(`coverage: ${e.message}`);
      }
    }
    const ints = (x, what) => {
      if (!Array.isArray(x) || !x.every((v) => Number.isInteger(v) && v >= -(2 ** 31) && v < 2 ** 31)) {
        throw bad(`${what} is not an array of i32`);
      }
      return x;
    };
    const steps = ints(coding.steps ?? [], "steps");
    if (!steps.every((s) => s >= 0)) throw bad("negative quantiser step");
    const roots = coding.roots.map((r, k) => ints(r, `root grid ${k}`));
    const extent = meta.extent;
    if (!Array.isArray(extent) || !Number.isSafeInteger(extent[0])) throw bad("no extent");
    let r;
    try {
      r = new SphereRefiner(extent[0], meta.n, coverage, steps, model, roots);
    } catch (e) {
      throw bad(e.message);
    }
    if (r.detailLevels() !== meta.levels || r.domain().m() !== meta.m) {
      throw bad(
        `levels ${meta.levels} and m ${meta.m} disagree with the extent and N (levels ${r.detailLevels()}, m ${r.domain().m()})`,
      );
    }
    r.valueScale = Number(coding.value_scale ?? 1);
    r.valueOffset = Number(coding.value_offset ?? 0);
    r.radiusM = typeof meta.radius_m === "number" ? meta.radius_m : null;
    return r;
  }

  /// The id space.
  domain() {
    return this._frame.domain();
  }

  /// The placement of the planet's samples and of single diamonds.
  frame() {
    return this._frame;
  }

  /// Diamond size N.
  n() {
    return this._frame.n();
  }

  /// Levels that carry details.
  detailLevels() {
    return this._frame.detailLevels();
  }

  /// Levels that can be refined (no procedural levels in this port).
  levels() {
    return this._frame.detailLevels();
  }

  /// Whether `id` is refined from a blob of the repository.
  isCoded(id) {
    return this._frame.codedLevel(id) !== null;
  }

  /// The six face roots and their vertex grids: `[[id, Int32Array], ...]`, face order.
  roots() {
    return this._rootIds.map((id, f) => [id, this._roots[f]]);
  }

  /// SphereFrame.codedSlot through a bounded cache (slots and masks are immutable; a
  /// client asks for the same diamond's slot several times while refining it).
  _codedSlot(id) {
    let k;
    try {
      k = idKey(id);
    } catch {
      return null;
    }
    let found = this._slots.get(k);
    if (found === undefined) {
      found = this._frame.codedSlot(id);
      if (this._slots.size >= SLOT_CACHE) this._slots.clear();
      this._slots.set(k, found);
    }
    return found;
  }

  _slotOf(id) {
    const slot = this._codedSlot(id);
    if (slot === null) throw new RefineError(`diamond ${idText(id)} is not refinable in this repository`);
    return slot;
  }

  /// The children that carry details below detail `level`, null at the finest.
  _codedChildren(id, level) {
    if (level + 1 >= this._frame.detailLevels()) return null;
    return this._domainChildren(id);
  }

  _domainChildren(id) {
    try {
      return this.domain().children(id);
    } catch (e) {
      if (e instanceof IdError) return [];
      throw e;
    }
  }

  /// The coded children whose side information `id`'s blob carries, in side order (those
  /// whose first parent is `id`).
  ownedChildren(id, level) {
    const children = this._codedChildren(id, level) ?? [];
    return children.filter((c) => {
      const p = this.parents(c);
      return p.length > 0 && sameId(p[0], id);
    });
  }

  /// What a client needs to know about a refinable diamond; null for leaves.
  info(id) {
    const found = this._codedSlot(id);
    if (found === null) return null;
    const [level, slot] = found;
    const children = this._codedChildren(id, level) ?? this._domainChildren(id);
    return { level, key: slot.key, mask: slot.mask, children, procedural: false };
  }

  /// `info(id).children` without working out a mask; null for leaves.
  children(id) {
    const level = this._frame.codedLevel(id);
    if (level === null || !this._frame.hasSlot(id)) return null;
    return this._codedChildren(id, level) ?? this._domainChildren(id);
  }

  /// Whether `id` can be refined here.
  isRefinable(id) {
    return this.isCoded(id);
  }

  /// The parents of `id` (none for roots or invalid ids).
  parents(id) {
    try {
      return this.domain().parents(id);
    } catch (e) {
      if (e instanceof IdError) return [];
      throw e;
    }
  }

  /// The ids at the frame corners P1 and P2 (the parents holding the lower/upper half).
  sideParents(id) {
    const c = this.corners(id);
    return [new SphereId(c[1]), new SphereId(c[3])];
  }

  /// Frame corners `[E1, P1, E2, P2]` on the cube (zeros for an invalid id).
  corners(id) {
    try {
      return this.domain().corners(id);
    } catch (e) {
      if (e instanceof IdError) {
        return [
          [0, 0, 0],
          [0, 0, 0],
          [0, 0, 0],
          [0, 0, 0],
        ];
      }
      throw e;
    }
  }

  /// Storage key of `id` (Uint8Array).
  key(id) {
    return this.domain().key(id);
  }

  /// The blob URL centre of `id`: `[x, y, z]` (Refiner::key_of).
  centre(id) {
    return [id.c[0], id.c[1], id.c[2]];
  }

  /// Refiner::key_of (the id as a fetch key: its centre).
  static keyOf(id) {
    return [id.c[0], id.c[1], id.c[2]];
  }

  /// Refiner::id_of.
  static idOf(key) {
    return new SphereId([key[0], key[1], key[2]]);
  }

  /// Decodes the blob of `id` (one channel's bytes): dequantised details and side
  /// information. Throws DecodeError on bad bytes, RefineError for a non-refinable id.
  decode(id, blob) {
    const [level, slot] = this._slotOf(id);
    const owned = this.ownedChildren(id, level);
    const ctx = this._frame.slotContext(level, slot, owned.length);
    const step = this._steps[level] ?? 256;
    ctx.step = step;
    const { childClasses, q } = decodeBlob(blob, ctx, this._model);
    const h = dequantizeMatrix(q, step, q);
    const classes = [];
    const empty = [];
    const count = Math.min(owned.length, childClasses.length);
    for (let k = 0; k < count; k++) {
      const [cls, noData] = splitSide(childClasses[k]);
      classes.push([owned[k], cls]);
      if (noData) empty.push(owned[k]);
    }
    return { id, h, childClasses: classes, emptyChildren: empty };
  }

  /// Refines `id` from its vertex `grid` ((N+1)^2) and decoded `details` (null: zero
  /// details, the leaf refinement): `{id, vertices, cells, childClasses}`.
  synthesize(id, grid, details = null) {
    if (details != null && !sameId(details.id, id)) {
      throw new RefineError(`diamond ${idText(id)} is not refinable in this repository`);
    }
    const [, slot] = this._slotOf(id);
    const n = this.n();
    if (grid.length !== (n + 1) * (n + 1)) {
      throw new RefineError(`expected ${(n + 1) * (n + 1)} values, got ${grid.length}`);
    }
    if (details != null && details.h.length !== n * n) {
      throw new RefineError(`expected ${n * n} values, got ${details.h.length}`);
    }
    const vertices = Int32Array.from(grid);
    const cells = new Int32Array(n * n);
    if (details != null) synthesize(n, vertices, details.h, cells, slot.mask);
    // Zero details: the update changes nothing, the cells are the prediction (exactly
    // lifting::synthesize with a zero h).
    else synthesizeZero(n, vertices, cells, slot.mask);
    return { id, vertices, cells, childClasses: details != null ? details.childClasses : [] };
  }

  /// `[grid, written]`: the part of `child`'s vertex grid lying in the given refined
  /// parents (unwritten vertices 0) and which vertices were written (Uint8Array).
  partialChildGrid(child, parents) {
    const n = this.n();
    const domain = this.domain();
    const s = domain.size();
    const frame = domain.corners(child);
    const trueParents = domain.parents(child);
    const grid = new Int32Array((n + 1) * (n + 1));
    const written = new Uint8Array((n + 1) * (n + 1));
    for (const parent of parents) {
      const notAParent = () => new RefineError(`${idText(parent.id)} is not a parent of ${idText(child)}`);
      if (!trueParents.some((p) => sameId(p, parent.id))) throw notAParent();
      if (parent.vertices.length !== (n + 1) * (n + 1) || parent.cells.length !== n * n) {
        throw new RefineError(
          `expected ${(n + 1) * (n + 1) + n * n} values, got ${parent.vertices.length + parent.cells.length}`,
        );
      }
      // The child's half inside this parent, in the parent's chart: E1, E2 and the
      // parent's centre (P1 or P2 of the child's frame); the fourth corner completes it.
      const [face, other, parentFrame] = domain.chartFrame(parent.id);
      const chart = (p) => {
        const uv = unfold(face, other, p, s);
        if (uv === null) throw notAParent();
        return uv;
      };
      const e1 = chart(frame[0]);
      const e2 = chart(frame[2]);
      const centre = chart(parent.id.c);
      const opposite = [e1[0] + e2[0] - centre[0], e1[1] + e2[1] - centre[1]];
      const pc = parent.id.c;
      const isP1 = pc[0] === frame[1][0] && pc[1] === frame[1][1] && pc[2] === frame[1][2];
      const childFrame = isP1 ? [e1, centre, e2, opposite] : [e1, opposite, e2, centre];
      const map = childHalf(parentFrame, childFrame, n);
      if (map == null) throw notAParent();
      scatterToChild(map, n, parent.vertices, parent.cells, grid, written);
    }
    return [grid, written];
  }

  /// The vertex grid of `child`, cut from its refined parents' lattices (pass both).
  /// Invalid vertices are 0.
  childGrid(child, parents) {
    const [grid, written] = this.partialChildGrid(child, parents);
    // info(child).mask (a leaf has none).
    const found = this._codedSlot(child);
    const valid = found === null || found[1].mask === null ? null : found[1].mask.vertices();
    let missing = 0;
    for (let k = 0; k < written.length; k++) if (!written[k] && (valid === null || valid[k])) missing++;
    if (missing > 0) {
      throw new RefineError(`${missing} valid vertices of ${idText(child)} are in none of the given parents`);
    }
    return grid;
  }

  /// The position of grid vertex (i, j) of `id` in fine units (1/N sample) x 2N, exact at
  /// every level (client-core/src/domain.rs sphere_vertex_fine): a point on the cube of half
  /// side S N 2N. `planetPoint(vertexFine(id, i, j), radius, height)` places the vertex
  /// in the world (only the direction matters, so the unit is free). null on bad input.
  vertexFine(id, i, j) {
    const n = this.n();
    const t = tz(n);
    try {
      const fine = this._fineDomain ?? (this._fineDomain = new SphereDomain(this.domain().m() + t));
      const scale = 2 ** t;
      return fine.vertexPosition(new SphereId(id.c.map((x) => x * scale)), n, i, j);
    } catch (e) {
      if (e instanceof IdError) return null;
      throw e;
    }
  }

  /// Half side of the cube in `vertexFine` units (render Geometry::Planet half_side_fine
  /// is this over 2N).
  fineHalfSide() {
    return this.domain().size() * this.n() * 2 * this.n();
  }

  /// World position (metres) of vertex (i, j) of `id` at integer value `v`:
  /// the equal-angle direction times (radius + valueOffset + v valueScale).
  vertexWorld(id, i, j, v) {
    const p = this.vertexFine(id, i, j);
    if (p === null || this.radiusM === null) return null;
    return planetPoint(p, this.radiusM, this.valueOffset + v * this.valueScale);
  }
}

/// Decodes every diamond of every level of a planet through SphereRefiners (one per
/// channel, coarse to fine, each child's grid cut from its refined parents) and returns
/// one Int32Array per channel in the canonical layout: 6 (2S+1)^2 values at
/// `(f (2S+1) + v) (2S+1) + u`, every copy of cube-edge points written, points outside a
/// sparse coverage 0: what codec::encode::decode_sphere_integers_with returns.
/// `getBlob([x, y, z])` -> Uint8Array | null (null or empty: no blob, a leaf); a colour
/// repository's blob holds its channels framed (splitChannels).
export function reconstructSphere(meta, getBlob) {
  const count = Array.isArray(meta?.channels) ? meta.channels.length : 0;
  if (count === 0) throw new DecodeError("repository metadata: no channels");
  const refiners = [];
  for (let c = 0; c < count; c++) refiners.push(SphereRefiner.fromMetadata(meta, c));
  const r0 = refiners[0];
  const frame = r0.frame();
  const n = frame.n();
  const side = n + 1;
  if (frame.cubeLen() > 2 ** 30) {
    throw new DecodeError(`a planet of ${frame.cubeLen()} values is too large to reconstruct in memory`);
  }
  const rasters = refiners.map(() => new Int32Array(frame.cubeLen()));

  // The six root grids, every copy of each point (SphereGeometry::scatter_roots: a point
  // on a cube edge takes the value of its canonical face's root).
  const roots = r0.roots();
  const rootGrids = refiners.map((r) => r.roots().map(([, grid]) => grid));
  for (let f = 0; f < 6; f++) {
    const slot = frame.slot(roots[f][0]);
    for (let i = 0; i <= n; i++) {
      for (let j = 0; j <= n; j++) {
        const here = slot.vertexIndex(i, j);
        const interior = i > 0 && j > 0 && i < n && j < n;
        const copies = interior ? [here] : frame.indexCopies(here);
        if (copies[0] !== here) continue;
        for (let c = 0; c < count; c++) {
          const x = rootGrids[c][f][i * side + j];
          for (const k of copies) rasters[c][k] = x;
        }
      }
    }
  }

  // Level by level, as the whole-planet decoder (raster::synthesize_levels): a diamond
  // with details writes its interior vertices, every diamond its cells (diagonal points
  // of edge diamonds to both copies).
  let levelIds = roots.map(([id]) => id);
  let previous = refiners.map(() => new Map());
  for (let level = 0; level < frame.detailLevels(); level++) {
    const current = refiners.map(() => new Map());
    const next = new Map();
    for (const id of levelIds) {
      const found = r0._codedSlot(id);
      if (found === null || found[0] !== level) {
        throw new RefineError(`diamond ${idText(id)} is not refinable at level ${level}`);
      }
      const slot = found[1];
      let raw = getBlob(SphereRefiner.keyOf(id));
      if (raw != null && raw.length === 0) raw = null;
      const parts = raw == null ? null : splitChannels(raw, count);
      const parentIds = level === 0 ? [] : r0.parents(id);
      for (let c = 0; c < count; c++) {
        const r = refiners[c];
        let grid;
        if (level === 0) {
          grid = rootGrids[c][frame.domain().faces(id)[0]];
        } else {
          const parents = [];
          for (const p of parentIds) {
            const got = previous[c].get(idKey(p));
            if (got !== undefined) parents.push(got);
          }
          grid = r.childGrid(id, parents);
        }
        const part = parts === null || parts[c] == null || parts[c].length === 0 ? null : parts[c];
        const details = part === null ? null : r.decode(id, part);
        const out = r.synthesize(id, grid, details);
        if (details !== null) slot.scatter(side, 1, false, out.vertices, rasters[c]);
        slot.scatter(n, 0, true, out.cells, rasters[c]);
        if (level + 1 < frame.detailLevels()) current[c].set(idKey(id), out);
      }
      if (level + 1 < frame.detailLevels()) {
        for (const child of r0.children(id)) next.set(idKey(child), child);
      }
    }
    previous = current;
    levelIds = [...next.values()];
  }

  if (frame.coverage() !== null) {
    const len = frame.cubeLen();
    for (let k = 0; k < len; k++) {
      if (!frame.isValid(k)) for (const r of rasters) r[k] = 0;
    }
  }
  return rasters;
}
