// Integer wavelet lifting of one diamond, and the gather/scatter between a refined
// diamond's lattice and its children's grids: a bit-exact port of
// decoder/src/lifting/mod.rs and decoder/src/lifting/gather.rs.
//
// A diamond holds an (N+1) x (N+1) vertex grid `v` (row-major, `v[i * (N+1) + j]`).
// Synthesis turns it into the level below's lattice inside its square: updated vertices
// plus N x N cell centres `c` (`c[i * N + j]`, cell (i, j) between vertices (i, j) and
// (i+1, j+1)). Prediction is the order-4 Neville quincunx filter where all 12 support
// points are valid, else the mean of the 4 corners, else (edge of the valid region) the
// mean of the valid corners; the update (sum of 4 details + 4) >> 3 touches only interior
// vertices whose 4 cells are valid.
//
// All arithmetic wraps modulo 2^32 as in Rust: sums are exact in doubles (far below 2^53)
// and wrapped by `| 0` / `>>` (ToInt32) or by the Int32Array stores.

/** Which vertices and cells of a diamond are valid samples (Rust `DiamondMask`). */
export class DiamondMask {
  /**
   * @param {number} n grid size N
   * @param {Uint8Array} vertex (N+1)^2 flags, row-major
   * @param {Uint8Array} cell N^2 flags, row-major
   */
  constructor(n, vertex, cell) {
    this._n = n;
    this._vertex = vertex;
    this._cell = cell;
  }

  /** A mask from predicates on vertex (i, j) and cell (i, j) indices. */
  static fromFn(n, vertex, cell) {
    const w = n + 1;
    const vs = new Uint8Array(w * w);
    for (let i = 0; i <= n; i++) for (let j = 0; j <= n; j++) vs[i * w + j] = vertex(i, j) ? 1 : 0;
    const cs = new Uint8Array(n * n);
    for (let i = 0; i < n; i++) for (let j = 0; j < n; j++) cs[i * n + j] = cell(i, j) ? 1 : 0;
    return new DiamondMask(n, vs, cs);
  }

  /** The mask of a diamond with no valid point. */
  static none(n) {
    return new DiamondMask(n, new Uint8Array((n + 1) * (n + 1)), new Uint8Array(n * n));
  }

  /** Grid size N. */
  n() {
    return this._n;
  }

  /** Whether vertex (i, j) is valid. */
  vertex(i, j) {
    return this._vertex[i * (this._n + 1) + j] === 1;
  }

  /** Whether cell (i, j) is valid. */
  cell(i, j) {
    return this._cell[i * this._n + j] === 1;
  }

  /** Cell validity, row-major, N^2 entries of 0/1 (shared: do not modify). */
  cells() {
    return this._cell;
  }

  /** Vertex validity, row-major, (N+1)^2 entries of 0/1 (shared: do not modify). */
  vertices() {
    return this._vertex;
  }

  /** Number of valid cells. */
  validCells() {
    let k = 0;
    for (const b of this._cell) k += b;
    return k;
  }

  /** Whether both masks have the same size and bits (Rust `PartialEq`). */
  equals(other) {
    if (!(other instanceof DiamondMask) || other._n !== this._n) return false;
    for (let k = 0; k < this._vertex.length; k++) if (this._vertex[k] !== other._vertex[k]) return false;
    for (let k = 0; k < this._cell.length; k++) if (this._cell[k] !== other._cell[k]) return false;
    return true;
  }
}

/**
 * Analysis of one diamond: `v` holds the fine vertex values on entry and the coarse ones
 * on exit; `c` holds the fine cell values; `h` receives the details (0 at invalid cells).
 */
export function analyze(n, v, c, h, mask) {
  predict(n, v, h, mask);
  const cells = mask ? mask._cell : null;
  for (let k = 0; k < n * n; k++) h[k] = cells === null || cells[k] ? (c[k] - h[k]) | 0 : 0;
  update(n, v, h, mask, false);
}

/**
 * Synthesis of one diamond, the exact inverse of `analyze`: `v` (Int32Array (N+1)^2) holds
 * the coarse vertices on entry and the fine ones on exit; `c` (Int32Array N^2) receives the
 * cell centres (0 at invalid cells); `h` the N^2 details; `mask` a DiamondMask or null.
 */
export function synthesize(n, v, h, c, mask) {
  update(n, v, h, mask, true);
  predict(n, v, c, mask);
  const cells = mask ? mask._cell : null;
  if (cells === null) {
    for (let k = 0; k < n * n; k++) c[k] = c[k] + h[k];
  } else {
    for (let k = 0; k < n * n; k++) c[k] = cells[k] ? c[k] + h[k] : 0;
  }
}

/**
 * Synthesis of a diamond whose details are all zero: `v` is left as it is and `c`
 * receives the prediction (0 at invalid cells), what `synthesize` gives with zero `h`.
 */
export function synthesizeZero(n, v, c, mask) {
  predict(n, v, c, mask);
  if (mask) {
    const cells = mask._cell;
    for (let k = 0; k < n * n; k++) if (!cells[k]) c[k] = 0;
  }
}

function predict(n, v, p, mask) {
  if (mask) predictMasked(n, v, p, mask);
  else predictFull(n, v, p);
}

function predictFull(n, v, p) {
  const w = n + 1;
  for (let i = 0; i < n; i++) {
    const r0 = i * w;
    const r1 = r0 + w;
    const pr = i * n;
    if (i === 0 || i === n - 1 || n < 4) {
      for (let j = 0; j < n; j++) {
        p[pr + j] = (v[r0 + j] + v[r0 + j + 1] + v[r1 + j] + v[r1 + j + 1] + 2) >> 2;
      }
      continue;
    }
    const rm = r0 - w;
    const r2 = r1 + w;
    p[pr] = (v[r0] + v[r0 + 1] + v[r1] + v[r1 + 1] + 2) >> 2;
    p[pr + n - 1] = (v[r0 + n - 1] + v[r0 + n] + v[r1 + n - 1] + v[r1 + n] + 2) >> 2;
    // A window sliding along the rows: 4 loads per cell instead of 12.
    let a0 = v[r0], a1 = v[r0 + 1], a2 = v[r0 + 2];
    let b0 = v[r1], b1 = v[r1 + 1], b2 = v[r1 + 2];
    let m1 = v[rm + 1], c1 = v[r2 + 1];
    for (let j = 1; j < n - 1; j++) {
      const a3 = v[r0 + j + 2];
      const b3 = v[r1 + j + 2];
      const m2 = v[rm + j + 1];
      const c2 = v[r2 + j + 1];
      const s4 = (a1 + a2 + b1 + b2) | 0;
      const s8 = m1 + m2 + c1 + c2 + a0 + b0 + a3 + b3;
      p[pr + j] = (s4 * 10 - s8 + 16) >> 5;
      a0 = a1; a1 = a2; a2 = a3;
      b0 = b1; b1 = b2; b2 = b3;
      m1 = m2; c1 = c2;
    }
  }
}

function predictMasked(n, v, p, m) {
  const w = n + 1;
  const vv = m._vertex;
  const cc = m._cell;
  for (let i = 0; i < n; i++) {
    for (let j = 0; j < n; j++) {
      if (!cc[i * n + j]) {
        p[i * n + j] = 0;
        continue;
      }
      const a = i * w + j; // vertex (i, j)
      const b = a + w; // vertex (i + 1, j)
      const ok0 = vv[a], ok1 = vv[a + 1], ok2 = vv[b], ok3 = vv[b + 1];
      const all4 = ok0 && ok1 && ok2 && ok3;
      const order4 =
        all4 && i >= 1 && i <= n - 2 && j >= 1 && j <= n - 2 &&
        vv[a - w] && vv[a - w + 1] && vv[b + w] && vv[b + w + 1] &&
        vv[a - 1] && vv[b - 1] && vv[a + 2] && vv[b + 2];
      if (order4) {
        const s4 = (v[a] + v[a + 1] + v[b] + v[b + 1]) | 0;
        const s8 =
          v[a - w] + v[a - w + 1] + v[b + w] + v[b + w + 1] +
          v[a - 1] + v[b - 1] + v[a + 2] + v[b + 2];
        p[i * n + j] = (s4 * 10 - s8 + 16) >> 5;
      } else if (all4) {
        p[i * n + j] = (v[a] + v[a + 1] + v[b] + v[b + 1] + 2) >> 2;
      } else {
        // Mean of the valid corners, rounded half up: exact in doubles (|sum| < 2^34),
        // and the quotient is at least 1/8 away from the next integer.
        let sum = 0;
        let k = 0;
        if (ok0) { sum += v[a]; k++; }
        if (ok1) { sum += v[a + 1]; k++; }
        if (ok2) { sum += v[b]; k++; }
        if (ok3) { sum += v[b + 1]; k++; }
        p[i * n + j] = k === 0 ? 0 : Math.floor((2 * sum + k) / (2 * k));
      }
    }
  }
}

function update(n, v, h, mask, inverse) {
  const w = n + 1;
  const cells = mask ? mask._cell : null;
  for (let i = 1; i < n; i++) {
    const ha = (i - 1) * n;
    const hb = i * n;
    const row = i * w;
    if (cells === null) {
      if (inverse) {
        for (let j = 1; j < n; j++) v[row + j] -= (h[ha + j - 1] + h[ha + j] + h[hb + j - 1] + h[hb + j] + 4) >> 3;
      } else {
        for (let j = 1; j < n; j++) v[row + j] += (h[ha + j - 1] + h[ha + j] + h[hb + j - 1] + h[hb + j] + 4) >> 3;
      }
      continue;
    }
    for (let j = 1; j < n; j++) {
      if (!(cells[ha + j - 1] && cells[ha + j] && cells[hb + j - 1] && cells[hb + j])) continue;
      const u = (h[ha + j - 1] + h[ha + j] + h[hb + j - 1] + h[hb + j] + 4) >> 3;
      if (inverse) v[row + j] -= u;
      else v[row + j] += u;
    }
  }
}

/**
 * Affine map from child vertex (i, j) to the parent's doubled lattice coordinates (p, q):
 * parent vertex (a, b) is (2a, 2b), cell (a, b) is (2a+1, 2b+1) (Rust `GridMap`).
 */
export class GridMap {
  constructor(p0, q0, dpi, dqi, dpj, dqj) {
    this.p0 = p0;
    this.q0 = q0;
    this.dpi = dpi;
    this.dqi = dqi;
    this.dpj = dpj;
    this.dqj = dqj;
  }

  /** Parent lattice coordinates [p, q] of child vertex (i, j). */
  map(i, j) {
    return [this.p0 + i * this.dpi + j * this.dpj, this.q0 + i * this.dqi + j * this.dqj];
  }
}

/**
 * The map from `child`'s vertex grid to `parent`'s refined lattice, or null when the
 * frames are not parent and child. Frames are corners [E1, P1, E2, P2], each [x, y] in
 * one common 2D chart (id units, integers). Exact: plain numbers while every product stays
 * below 2^53, BigInt beyond (the Rust code works in i128).
 */
export function childHalf(parent, child, n) {
  let big = 0;
  for (let k = 0; k < 4; k++) {
    big = Math.max(big, Math.abs(parent[k][0]), Math.abs(parent[k][1]), Math.abs(child[k][0]), Math.abs(child[k][1]));
  }
  // |pa| <= 2 * (2N * 2 big) * (2 big) = 16 N big^2.
  if (16 * n * big * big < 2 ** 52) return childHalfNumber(parent, child, n);
  return childHalfWith(parent, child, n, BigInt);
}

/** `childHalf` in plain numbers (every product below 2^53), without allocations. */
function childHalfNumber(parent, child, n) {
  const ax = parent[1][0] - parent[0][0];
  const ay = parent[1][1] - parent[0][1];
  const bx = parent[3][0] - parent[0][0];
  const by = parent[3][1] - parent[0][1];
  const la = ax * ax + ay * ay;
  const lb = bx * bx + by * by;
  if (la === 0 || lb === 0 || la !== lb || ax * bx + ay * by !== 0) return null;
  const d0x = 2 * n * (child[0][0] - parent[0][0]);
  const d0y = 2 * n * (child[0][1] - parent[0][1]);
  const cax = 2 * (child[1][0] - child[0][0]);
  const cay = 2 * (child[1][1] - child[0][1]);
  const cbx = 2 * (child[3][0] - child[0][0]);
  const cby = 2 * (child[3][1] - child[0][1]);
  // Projections onto A and B, which must be whole multiples of |A|^2 = |B|^2.
  const p0 = d0x * ax + d0y * ay;
  const q0 = d0x * bx + d0y * by;
  const dpi = cax * ax + cay * ay;
  const dqi = cax * bx + cay * by;
  const dpj = cbx * ax + cby * ay;
  const dqj = cbx * bx + cby * by;
  if (p0 % la !== 0 || q0 % la !== 0 || dpi % la !== 0 || dqi % la !== 0 || dpj % la !== 0 || dqj % la !== 0) {
    return null;
  }
  const z = (x) => (x === 0 ? 0 : x); // no -0
  const m = [z(p0 / la), z(q0 / la), z(dpi / la), z(dqi / la), z(dpj / la), z(dqj / la)];
  if (Math.abs(m[2]) > 1 || Math.abs(m[3]) > 1 || Math.abs(m[4]) > 1 || Math.abs(m[5]) > 1) return null;
  return new GridMap(m[0], m[1], m[2], m[3], m[4], m[5]);
}

function childHalfWith(parent, child, n, num) {
  const P = parent.map((p) => [num(p[0]), num(p[1])]);
  const C = child.map((p) => [num(p[0]), num(p[1])]);
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1];
  const zero = num(0);
  const bigA = sub(P[1], P[0]);
  const bigB = sub(P[3], P[0]);
  const la = dot(bigA, bigA);
  const lb = dot(bigB, bigB);
  if (la === zero || lb === zero || la !== lb || dot(bigA, bigB) !== zero) return null;
  const nn = num(n);
  const two = num(2);
  // Truncating division of exact multiples: plain `/` is exact for numbers here too.
  const proj = (x) => {
    const pa = x[0] * bigA[0] + x[1] * bigA[1];
    const pb = x[0] * bigB[0] + x[1] * bigB[1];
    if (pa % la !== zero || pb % lb !== zero) return null;
    return [Number(pa / la), Number(pb / lb)];
  };
  const d0 = sub(C[0], P[0]);
  const r0 = proj([two * nn * d0[0], two * nn * d0[1]]);
  if (r0 === null) return null;
  const ca = sub(C[1], C[0]);
  const cb = sub(C[3], C[0]);
  const ri = proj([two * ca[0], two * ca[1]]);
  if (ri === null) return null;
  const rj = proj([two * cb[0], two * cb[1]]);
  if (rj === null) return null;
  const d = [ri[0], ri[1], rj[0], rj[1]];
  if (d.some((x) => Math.abs(x) > 1)) return null;
  // -0 from a negative zero quotient is harmless but normalise it.
  const z = (x) => (x === 0 ? 0 : x);
  return new GridMap(z(r0[0]), z(r0[1]), z(d[0]), z(d[1]), z(d[2]), z(d[3]));
}

/**
 * Copies the part of the parent's refined lattice (`v`: (N+1)^2 updated vertices, `c`:
 * N^2 cell centres) that lies in the child into the child's vertex grid `childV`; marks
 * the written entries in `written` (Uint8Array (N+1)^2, or null). Returns the number of
 * vertices written.
 */
export function scatterToChild(map, n, v, c, childV, written) {
  const w = n + 1;
  const twoN = 2 * n;
  const last = n;
  let count = 0;
  const { dpj, dqj } = map;
  // Along a row, p and q are affine in j with slopes in {-1, 0, 1}: the entries on the
  // parent's lattice form one interval of j, every or every other entry.
  const sameParity = (dpj - dqj) % 2 === 0;
  for (let i = 0; i <= n; i++) {
    const a = map.p0 + i * map.dpi;
    const b = map.q0 + i * map.dqi;
    let lo = 0;
    let hi = last;
    if (dpj === 0) {
      if (a < 0 || a > twoN) continue;
    } else if (dpj === 1) {
      lo = Math.max(lo, -a);
      hi = Math.min(hi, twoN - a);
    } else {
      lo = Math.max(lo, a - twoN);
      hi = Math.min(hi, a);
    }
    if (dqj === 0) {
      if (b < 0 || b > twoN) continue;
    } else if (dqj === 1) {
      lo = Math.max(lo, -b);
      hi = Math.min(hi, twoN - b);
    } else {
      lo = Math.max(lo, b - twoN);
      hi = Math.min(hi, b);
    }
    // Every entry (p - q even all along), or every other one (p - q changes parity
    // with j: start where it is even). Entries j0, j0 + 2, ... share the parity of p, so
    // each class reads one array with a fixed stride: (p, q) moves by (2 dpj, 2 dqj),
    // i.e. (dpj, dqj) entries of that array.
    let classes;
    if (sameParity) {
      if ((a - b) % 2 !== 0) continue;
      classes = 2;
    } else {
      if ((((a - b + lo) % 2) + 2) % 2 !== 0) lo += 1;
      classes = 1;
    }
    for (let j0 = lo; j0 < lo + classes && j0 <= hi; j0++) {
      const p = a + j0 * dpj;
      const q = b + j0 * dqj;
      const odd = (p & 1) === 1;
      const src = odd ? c : v;
      const sw = odd ? n : w;
      let from = (p >> 1) * sw + (q >> 1);
      const stride = dpj * sw + dqj;
      for (let j = j0, at = i * w + j0; j <= hi; j += 2, at += 2, from += stride) {
        childV[at] = src[from];
        if (written) written[at] = 1;
        count++;
      }
    }
  }
  return count;
}
