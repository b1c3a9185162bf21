// The surface under a point (render/src/ground.rs `surface_height_m`): where the line
// through a point along the local up meets the cut's grid triangles as drawn. Shared by
// the client (`Session.heightAt`) and the renderer (`TerrainRenderer.surfaceHeightM`,
// which puts the camera `height_m` above it, as `quincunx render` does).
//
// `frame` is a world frame (render/src/domain.rs `WorldFrame`: `n` and `geometry`, either
// `{kind: "planar", metresPerFine, extentFine}` or `{kind: "planet", radiusM,
// halfSideFine}`); `point(fine, v)` turns a fine-unit point at integer height `v` into
// world metres.

const INSIDE_EPS = 1e-7;
const EDGE_EPS = 1e-12;

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];

function faceOf(k, positive) {
  return 2 * k + (positive ? 1 : 0);
}

function otherAxes(k) {
  return k === 0 ? [1, 2] : k === 1 ? [0, 2] : [0, 1];
}

/** Faces to look on and the footprint of `x` on each, fine units (ground.rs `footprints`). */
function footprints(frame, x) {
  const g = frame.geometry;
  if (g.kind === "planar") return [[0, [x[0] / g.metresPerFine, x[1] / g.metresPerFine]]];
  const big = Math.max(Math.abs(x[0]), Math.abs(x[1]), Math.abs(x[2]));
  if (big === 0 || !Number.isFinite(big)) return [];
  const s = g.halfSideFine;
  const order = [0, 1, 2].sort((a, b) => Math.abs(x[b]) - Math.abs(x[a]));
  const out = [];
  for (const k of order) {
    if (Math.abs(x[k]) < big * (1 - 1e-9)) break;
    const c = otherAxes(k).map((a) => (Math.atan(x[a] / Math.abs(x[k])) / (Math.PI / 4)) * s);
    out.push([faceOf(k, x[k] > 0), c]);
  }
  return out;
}

/**
 * A cut patch prepared for height queries (ground.rs `index_patch`), or null: `affine`
 * ({base, e1, e2}: fine point of grid vertex (i, j) = base + i e1 + j e2), `lower` (the
 * half with i >= j), `grid` ((N+1)^2 integer heights).
 */
export function indexPatch(frame, affine, lower, grid) {
  const n = frame.n;
  if (!affine || !grid || grid.length !== (n + 1) * (n + 1)) return null;
  let face = 0;
  let ax = [0, 1];
  if (frame.geometry.kind === "planet") {
    const k = [0, 1, 2].find((q) => affine.e1[q] === 0 && affine.e2[q] === 0);
    if (k === undefined || Math.abs(affine.base[k]) !== frame.geometry.halfSideFine) return null;
    face = faceOf(k, affine.base[k] > 0);
    ax = otherAxes(k);
  }
  const [a11, a12] = [affine.e1[ax[0]], affine.e2[ax[0]]];
  const [a21, a22] = [affine.e1[ax[1]], affine.e2[ax[1]]];
  const det = a11 * a22 - a12 * a21;
  if (det === 0) return null;
  return { affine, lower, grid, face, ax, m: [a22 / det, -a12 / det, -a21 / det, a11 / det] };
}

function gridOf(p, c) {
  const b0 = c[0] - p.affine.base[p.ax[0]];
  const b1 = c[1] - p.affine.base[p.ax[1]];
  return [p.m[0] * b0 + p.m[1] * b1, p.m[2] * b0 + p.m[3] * b1];
}

function patchContains(p, n, [fi, fj], margin) {
  if (fi < -margin || fj < -margin || fi > n + margin || fj > n + margin) return false;
  return p.lower ? fi >= fj - margin : fi <= fj + margin;
}

function cellTriangles(lower, i, j) {
  const a = [i, j];
  const b = [i + 1, j];
  const c = [i + 1, j + 1];
  const d = [i, j + 1];
  const out = [];
  if (lower) {
    if (i >= j) out.push([a, b, c]);
    if (i > j) out.push([a, c, d]);
  } else {
    if (i <= j) out.push([a, c, d]);
    if (i < j) out.push([a, b, c]);
  }
  return out;
}

/** Where the line `x + s d` meets triangle `v`: `[s, point]` or null (Möller-Trumbore). */
function lineTriangle(x, d, v) {
  const e1 = sub(v[1], v[0]);
  const e2 = sub(v[2], v[0]);
  const pv = cross(d, e2);
  const det = dot(e1, pv);
  if (det === 0 || !Number.isFinite(det)) return null;
  const inv = 1 / det;
  const t = sub(x, v[0]);
  const a = dot(t, pv) * inv;
  if (!(a >= -EDGE_EPS && a <= 1 + EDGE_EPS)) return null;
  const q = cross(t, e1);
  const b = dot(d, q) * inv;
  if (b < -EDGE_EPS || a + b > 1 + EDGE_EPS) return null;
  const s = dot(e2, q) * inv;
  return [s, [x[0] + d[0] * s, x[1] + d[1] * s, x[2] + d[2] * s]];
}

/** Whether a world point lies on drawn data (the planar extent; a planet everywhere). */
function drawn(frame, r) {
  const g = frame.geometry;
  if (g.kind !== "planar") return true;
  const e = g.extentFine.map((v) => v * g.metresPerFine);
  const slack = 1e-5 * Math.max(e[0], e[1], 1);
  return r[0] >= -slack && r[1] >= -slack && r[0] <= e[0] + slack && r[1] <= e[1] + slack;
}

function hitCells(frame, point, p, g, reach, x, up) {
  const n = frame.n;
  const ci = Math.min(Math.max(Math.floor(g[0]), 0), n - 1);
  const cj = Math.min(Math.max(Math.floor(g[1]), 0), n - 1);
  let best = null;
  const vertex = ([i, j]) => {
    const a = p.affine;
    const f = [0, 1, 2].map((k) => a.base[k] + i * a.e1[k] + j * a.e2[k]);
    return point(f, p.grid[i * (n + 1) + j] ?? 0);
  };
  for (let i = Math.max(ci - reach, 0); i <= Math.min(ci + reach, n - 1); i++) {
    for (let j = Math.max(cj - reach, 0); j <= Math.min(cj + reach, n - 1); j++) {
      for (const tri of cellTriangles(p.lower, i, j)) {
        const hit = lineTriangle(x, up, tri.map(vertex));
        if (hit !== null && drawn(frame, hit[1]) && (best === null || Math.abs(hit[0]) < best[0])) {
          best = [Math.abs(hit[0]), hit[1]];
        }
      }
    }
  }
  return best;
}

/**
 * Height (metres above the datum) of the surface the `patches` (an iterable of
 * `indexPatch` results; nulls are skipped) draw below or above `x`, along `up`; null
 * where the line meets none (outside the data).
 */
export function surfaceHeightM(frame, point, patches, x, up) {
  const n = frame.n;
  const heightOf = (r) => {
    if (frame.geometry.kind === "planar") return r[2];
    return Math.sqrt(dot(r, r)) - frame.geometry.radiusM;
  };
  const feet = footprints(frame, x);
  const near = [];
  for (const p of patches) {
    if (p === null) continue;
    const foot = feet.find(([f]) => f === p.face);
    if (foot === undefined) continue;
    const g = gridOf(p, foot[1]);
    if (patchContains(p, n, g, INSIDE_EPS)) {
      const hit = hitCells(frame, point, p, g, 0, x, up);
      if (hit !== null) return heightOf(hit[1]);
    }
    if (patchContains(p, n, g, 1)) near.push([p, g]);
  }
  let best = null;
  for (const [p, g] of near) {
    const hit = hitCells(frame, point, p, g, 1, x, up);
    if (hit !== null && (best === null || hit[0] < best[0])) best = hit;
  }
  return best === null ? null : heightOf(best[1]);
}
