// The browser's streaming client: the parts of the Rust client core (client/src/) that
// the web viewer needs, ported with the same names (camelCase) and the same decisions.
//
// - open.rs, domain.rs, view.rs: opening a repository from a base URL, the world
//   mappings (`PlanarWorld`, `SphereWorld`), the view (`View`: frustum, projected sizes),
//   world boxes of diamonds, horizon culling on planets, exact vertex positions.
// - colour.rs: an optional colour repository matched to the elevation (`ColourLayer`):
//   ids scaled by 2^shift, the shallower layer extended by procedural levels (zero
//   details: the lifting's smooth interpolation), every node carrying (Nc+1)^2 grids of
//   Y, Co and Cg beside its heights.
// - dag.rs: the diamond DAG (`Dag`): a diamond is refined only when all its parents are
//   (the 4-8 rule), each child receives the half lying in a refined parent, coarsening is
//   the reverse; `Dag.checkCut` is Rust's crack and coverage check.
// - refine.rs: time-budgeted dual-queue refinement (`Refinement`): split queue by
//   projected screen-space error (max of edge and texel), missing parents first, merge
//   queue with hysteresis, deferred re-evaluation, side-information flatness, frustum and
//   horizon culling, optional memory and cut budgets.
// - client-core's stream.rs, session.rs and fetch/: `Session` (below), a priority fetch
//   queue with a bounded number of requests in flight (shared by both layers),
//   cancellation of requests no longer wanted (AbortController), retries with backoff, a
//   decoded-details cache (LRU by bytes) and the set of known leaves, packages (`.../p/...` when the metadata has
//   `inline_max_bytes`), empty answers (and 404s of a static export) as leaves, lookahead
//   below wanted diamonds and prefetch along the predicted camera.
// - decoding off the main thread: worker.mjs in a small pool of module workers when
//   `Worker` exists; inline otherwise (node).
// - render/src/ground.rs `surface_height_m` (`Session.heightAt`) and render/src/domain.rs
//   `affine` (each patch's exact vertex positions as an affine map of the grid index).
//
// The interface the viewer codes against:
//
//   const session = await Session.open(baseUrl, repoName, {colour: colourRepoName | null,
//     maxInFlight = 8, workers (decoding workers; default cores - 1, at most 4; 0:
//     inline), cacheBytes = 64 MiB, fetch (a fetch function), refine: {hysteresis = 1,
//     flatFraction = 0.1, maxDagBytes, maxCutHalves}, lookaheadLevels = 2,
//     prefetchAheadMs = 500, packageFactor = 2, spacingM, timeoutMs = 10 s (metadata),
//     requestTimeoutMs = 10 s, cancelAfterMs = 250});
//     baseUrl: "http://host[:port][/prefix]", or "" for the page's origin. Rejects with
//     SessionError (bad name, metadata, a colour layer that does not match).
//   listRepositories(baseUrl) -> `GET /repos`'s list.
//   session.meta            the elevation metadata (metadata.json object)
//   session.colourMeta      the colour metadata, or null
//   session.domain          "planar" | "sphere"
//   session.n, session.colourN   diamond sizes (colourN 0 without colour)
//   session.world           PlanarWorld | SphereWorld (view.rs): kind ("planar" |
//                           "sphere"), valueScaleM, valueOffsetM, n, colourN, heightM(v),
//                           up(eye), frame() (render/src/domain.rs WorldFrame, the shape
//                           camera.mjs `worldFrame` gives: {geometry: {kind: "planar",
//                           metresPerFine, extentFine} | {kind: "planet", radiusM,
//                           halfSideFine}, valueScaleM, valueOffsetM, n, colourN}),
//                           pointFine(p, v) (WorldFrame::point); planar: spacingM,
//                           extent [w, h], point([x, y], v); planet: radiusM, halfSide,
//                           occluderRadiusM, direction(p), point(p, v). A planet's world
//                           is replaced (a new object) once its lowest height is known.
//   session.update(camera, {tolerancePx = 1, viewportPx = [1920, 1080], budgetMs = 4})
//       camera = {position: [x, y, z], forward: [x, y, z], up: [x, y, z], fovYRad,
//       near, far}: float64 world metres, the frame of view.rs and render/src/camera.rs
//       (planar: x along columns (east), y along rows (row 0 north, so north is -y), z
//       up, metres = id units * spacingM; planet: centred on the planet, +z the north
//       pole, x through longitude 0). Refines and coarsens within budgetMs and keeps the
//       network busy; returns nothing; never waits for the network. Culling uses Rust's
//       near plane (0.1 m) and an infinite far plane (near and far are not used); a
//       camera with non-finite numbers is ignored.
//   session.cutChanges() -> {entered: Patch[], left: [{id, half, key}]}
//       PatchChanges since the previous call (the first reports the whole cut). Patch =
//       {id, half (Half.Lower = 0: entries i >= j | Half.Upper = 1: i <= j), key
//       (patchKey(id, half)), corners ([[x, y, z] x4]: E1, P1, E2, P2 in id units; planar
//       z = 0), grid (Int32Array (N+1)^2, row-major i * (N+1) + j: on the plane vertex
//       (i, j) is at E1 + (i (P1 - E1) + j (P2 - E1)) / N), generation, colour ([Y, Co,
//       Cg] Int32Arrays (Nc+1)^2 on the same frame | null), level, affine ({base, e1,
//       e2}: the fine point of (i, j) is base + i e1 + j e2, in world.frame()'s fine
//       units; exact)}. Grids are never modified once handed out (a changed node gets
//       new arrays), so a renderer may keep them.
//   session.restartCutChanges()  the next cutChanges() reports the whole cut again.
//   patchKey(id, half) -> string  stable key of a patch ("x,y/0", "x,y,z/1").
//   session.stats() -> {triangles, patches, bytesReceived, bytesPerS, requestsInFlight,
//       queued, fullQuality, converged, settled, budgetLimited, timeToFullQualityMs,
//       errors: {clientStatus, serverStatus, connection, timeout, decode, refine, total},
//       failures, lastError, ...} (see `stats` below).
//   session.heightAt(position) -> metres (above the datum) of the streamed surface under
//       `position` along the local up, as drawn (the cut's grid triangles), or null
//       outside the data: `quincunx render --height-m H` puts the camera H above it.
//   session.heightRange() -> [lo, hi] metres (conservative over the cut);
//   session.bounds() (planar) -> {min, max}; session.colourLayer (ColourLayer | null:
//   scales, ycocg(grids, k), rgb(grids, k)); session.setMaxCutHalves(n | null) (a GPU
//   pool's size: the cut never exceeds it, stats().settled marks the best cut that
//   fits); session.checkCut() (dag.rs check_cut: {ok, cracks, colourCracks, ...});
//   session.close().
//
// Left out of the Rust session: transports (the browser's fetch decides: HTTP/2 or
// HTTP/1.1 without pipelining), the bandwidth estimate and its adaptive window (a fixed
// `maxInFlight`, shared by both layers), the bandwidth cap, link-adaptive lookahead depth
// (always `lookaheadLevels`), byte accounting per cut (`bytes_used`, `cut_blobs`),
// procedural noise (procedural levels use zero details, the Rust default), `warm_up`,
// snapshots, flights. Added: requests no frame has wanted for `cancelAfterMs` are
// aborted (Rust lets them finish).

// Numbers: ids, centres and fine positions are plain numbers (exact below 2^53: planar
// domains m <= 25, planets m <= 23). Time is `performance.now()` milliseconds.

import { DecodeError, classBound, ycocgRToRgb } from "./codec.mjs";
import { DiamondMask, synthesizeZero } from "./lifting.mjs";
import { PlanarId, PlanarRefiner, RefineError } from "./planar.mjs";
import { SphereId, SphereRefiner, axes, chartOf, cubeToUnitSphere } from "./sphere.mjs";
import { AnswerDecoder, COLOUR_CHANNELS } from "./worker.mjs";
import { indexPatch, surfaceHeightM } from "./ground.mjs";

// ---------------------------------------------------------------------------------------
// Small vector helpers (float64 arrays).

const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const len = (a) => Math.sqrt(dot(a, a));
const finite3 = (a) => Array.isArray(a) && a.length >= 3 && a.every(Number.isFinite);

/** glam `normalize_or_zero`. */
function normalizeOrZero(a) {
  const l = len(a);
  return l > 0 && Number.isFinite(1 / l) ? mul(a, 1 / l) : [0, 0, 0];
}

/** glam `any_orthonormal_vector` of a unit vector. */
function anyOrthonormal(a) {
  const sign = a[2] < 0 ? -1 : 1;
  const k = -1 / (sign + a[2]);
  const b = a[0] * a[1] * k;
  return [b, sign + a[1] * a[1] * k, -a[1]];
}

// ---------------------------------------------------------------------------------------
// Errors.

/** Why a session could not start (open.rs `SessionError`): bad URL, metadata, mismatch. */
export class SessionError extends Error {
  constructor(message) {
    super(message);
    this.name = "SessionError";
  }
}

/** The DAG refused an operation (open.rs `DagError`): a bug or inconsistent data. */
export class DagError extends Error {
  constructor(message) {
    super(message);
    this.name = "DagError";
  }
}

// ---------------------------------------------------------------------------------------
// Halves and patches (domain.rs `Half`).

/** The two triangles of a diamond's grid: Lower = entries i >= j, Upper = i <= j. */
export const Half = Object.freeze({ Lower: 0, Upper: 1 });
const BOTH = [Half.Lower, Half.Upper];

/** Whether grid entry (i, j) belongs to `half` (the diagonal to both). */
export function halfContains(half, i, j) {
  return half === Half.Lower ? i >= j : i <= j;
}

/** A stable string key of a patch (a half of a diamond). */
export function patchKey(id, half) {
  return `${String(id)}/${half}`;
}

/** Rust's `Ord` on ids: planar (x, y), planets the centre array. */
function cmpId(a, b) {
  if (a.c !== undefined) {
    for (let k = 0; k < 3; k++) if (a.c[k] !== b.c[k]) return a.c[k] < b.c[k] ? -1 : 1;
    return 0;
  }
  if (a.x !== b.x) return a.x < b.x ? -1 : 1;
  if (a.y !== b.y) return a.y < b.y ? -1 : 1;
  return 0;
}

// ---------------------------------------------------------------------------------------
// A binary heap (std BinaryHeap with an explicit order).

class Heap {
  /** `first(a, b)`: whether `a` comes out before `b`. */
  constructor(first, items = []) {
    this._a = [];
    this._first = first;
    for (const x of items) this.push(x);
  }

  get size() {
    return this._a.length;
  }

  push(x) {
    const a = this._a;
    a.push(x);
    let i = a.length - 1;
    while (i > 0) {
      const p = (i - 1) >> 1;
      if (!this._first(a[i], a[p])) break;
      [a[i], a[p]] = [a[p], a[i]];
      i = p;
    }
  }

  pop() {
    const a = this._a;
    if (a.length === 0) return undefined;
    const top = a[0];
    const last = a.pop();
    if (a.length > 0) {
      a[0] = last;
      let i = 0;
      for (;;) {
        const l = 2 * i + 1;
        const r = l + 1;
        let m = i;
        if (l < a.length && this._first(a[l], a[m])) m = l;
        if (r < a.length && this._first(a[r], a[m])) m = r;
        if (m === i) break;
        [a[i], a[m]] = [a[m], a[i]];
        i = m;
      }
    }
    return top;
  }

  /** Everything left, in no particular order; empties the heap. */
  drain() {
    const a = this._a;
    this._a = [];
    return a;
  }
}

// Split queue: largest error first (ties: largest id); merge queue: the reverse.
const splitFirst = (x, y) => x[0] > y[0] || (x[0] === y[0] && cmpId(x[1], y[1]) > 0);
const mergeFirst = (x, y) => x[0] < y[0] || (x[0] === y[0] && cmpId(x[1], y[1]) < 0);

// ---------------------------------------------------------------------------------------
// The view (view.rs).

/** Near plane distance (metres) of refinement's frustum and projected sizes. */
export const NEAR_M = 0.1;

/** An axis-aligned world box `{min, max}`: distance from a point (0 inside). */
function boxDistance(b, p) {
  let s = 0;
  for (let k = 0; k < 3; k++) {
    const d = Math.max(b.min[k] - p[k], p[k] - b.max[k], 0);
    s += d * d;
  }
  return Math.sqrt(s);
}

/** A camera for one frame (view.rs `View`), f64 throughout. */
export class View {
  /** `{eye, target, up, fovYRad, viewportPx: [w, h], tolerancePx}`. */
  constructor({ eye, target, up, fovYRad, viewportPx, tolerancePx }) {
    this.eye = eye;
    this.target = target;
    this.up = up;
    this.fovYRad = fovYRad;
    this.viewportPx = viewportPx;
    this.tolerancePx = tolerancePx;
  }

  /** The view of a viewer camera `{position, forward, up, fovYRad}`. */
  static fromCamera(camera, { tolerancePx = 1, viewportPx = [1920, 1080] } = {}) {
    const eye = Array.from(camera.position).slice(0, 3);
    return new View({
      eye,
      target: add(eye, camera.forward),
      up: Array.from(camera.up).slice(0, 3),
      fovYRad: camera.fovYRad,
      viewportPx: [Math.max(1, Math.round(viewportPx[0])), Math.max(1, Math.round(viewportPx[1]))],
      tolerancePx,
    });
  }

  /** A string that changes whenever anything refinement looks at changes. */
  signature() {
    return [...this.eye, ...this.target, ...this.up, this.fovYRad, ...this.viewportPx, this.tolerancePx].join(",");
  }

  /**
   * The frustum (`clip_from_world` = perspective_infinite_rh x look_at_rh, planes from
   * its rows): six planes `[a, b, c, d]`, inside where `a x + b y + c z + d >= 0`.
   */
  frustum() {
    const [w, h] = this.viewportPx;
    const aspect = Math.max(w, 1) / Math.max(h, 1);
    const half = this.fovYRad / 2;
    const fy = Math.cos(half) / Math.sin(half);
    const fx = fy / aspect;
    const f = normalizeOrZero(sub(this.target, this.eye));
    let upv = this.up;
    if (len(cross(f, upv)) < 1e-12) upv = anyOrthonormal(f);
    const s = normalizeOrZero(cross(f, upv));
    const u = cross(s, f);
    const e = this.eye;
    // Rows of the clip matrix: fx (s, -s.e), fy (u, -u.e), (f, -f.e - near), (f, -f.e).
    const r0 = [fx * s[0], fx * s[1], fx * s[2], -fx * dot(s, e)];
    const r1 = [fy * u[0], fy * u[1], fy * u[2], -fy * dot(u, e)];
    const r3 = [f[0], f[1], f[2], -dot(f, e)];
    const r2 = [f[0], f[1], f[2], -dot(f, e) - NEAR_M];
    const plus = (a, b) => a.map((x, k) => x + b[k]);
    const minus = (a, b) => a.map((x, k) => x - b[k]);
    const planes = [plus(r3, r0), minus(r3, r0), plus(r3, r1), minus(r3, r1), r2, minus(r3, r2)];
    return planes.map((p) => {
      const l = Math.hypot(p[0], p[1], p[2]);
      return l > 0 ? p.map((x) => x / l) : p;
    });
  }

  /** Pixels per metre of a length facing the camera at `distanceM`. */
  pxPerM(distanceM) {
    const h = Math.max(this.viewportPx[1], 1);
    return h / (2 * Math.tan(this.fovYRad / 2) * Math.max(distanceM, NEAR_M));
  }
}

/** Whether a box may be visible (conservative: never culls a visible box). */
function frustumIntersects(planes, b) {
  for (const p of planes) {
    const x = p[0] >= 0 ? b.max[0] : b.min[0];
    const y = p[1] >= 0 ? b.max[1] : b.min[1];
    const z = p[2] >= 0 ? b.max[2] : b.min[2];
    if (p[0] * x + p[1] * y + p[2] * z + p[3] < 0) return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------
// Worlds (view.rs, open.rs, domain.rs `World`, render/src/domain.rs `WorldFrame`).

/** Mean Earth radius (metres), for sample spacings of latitude/longitude grids. */
export const EARTH_RADIUS_M = 6_371_008.8;

/** Where a planar repository's ids and integer samples are in the world. */
export class PlanarWorld {
  constructor({ spacingM, valueScaleM, valueOffsetM, extent, n, colourN = 0 }) {
    this.kind = "planar";
    /** Metres per id unit (the raster's sample spacing). */
    this.spacingM = spacingM;
    /** Metres per integer sample value, and at integer 0. */
    this.valueScaleM = valueScaleM;
    this.valueOffsetM = valueOffsetM;
    /** Raster width and height in samples. */
    this.extent = extent;
    this.n = n;
    this.colourN = colourN;
  }

  heightM(v) {
    return this.valueOffsetM + v * this.valueScaleM;
  }

  fingerprint() {
    return [this.spacingM, this.valueScaleM, this.valueOffsetM, 0];
  }

  up() {
    return [0, 0, 1];
  }

  /** World position of a point in id units with integer value `v`. */
  point(xy, v) {
    return [xy[0] * this.spacingM, xy[1] * this.spacingM, this.heightM(v)];
  }

  /** render/src/domain.rs `world_frame`: fine unit = id unit / N. */
  frame() {
    const n = this.n;
    return {
      geometry: {
        kind: "planar",
        metresPerFine: this.spacingM / n,
        extentFine: [(this.extent[0] - 1) * n, (this.extent[1] - 1) * n],
      },
      valueScaleM: this.valueScaleM,
      valueOffsetM: this.valueOffsetM,
      n,
      colourN: this.colourN,
    };
  }

  /** `WorldFrame::point`: world position of a fine point at integer height `v`. */
  pointFine(p, v) {
    const m = this.spacingM / this.n;
    return [p[0] * m, p[1] * m, this.heightM(v)];
  }

  withLowestHeight() {
    return this;
  }
}

/**
 * Where a planet's ids and integer samples are: the cube (id units, half side
 * `halfSide`) mapped onto the sphere of `radiusM` at the origin by the equal-angle map,
 * heights along the radius; `occluderRadiusM` (0 until the lowest height is known) for
 * horizon culling.
 */
export class SphereWorld {
  constructor({ radiusM, halfSide, valueScaleM, valueOffsetM, occluderRadiusM = 0, n, colourN = 0 }) {
    this.kind = "sphere";
    this.radiusM = radiusM;
    this.halfSide = halfSide;
    this.valueScaleM = valueScaleM;
    this.valueOffsetM = valueOffsetM;
    this.occluderRadiusM = occluderRadiusM;
    this.n = n;
    this.colourN = colourN;
  }

  heightM(v) {
    return this.valueOffsetM + v * this.valueScaleM;
  }

  fingerprint() {
    return [this.radiusM, this.occluderRadiusM, this.valueScaleM, this.valueOffsetM];
  }

  up(eye) {
    const u = normalizeOrZero(eye);
    return u[0] === 0 && u[1] === 0 && u[2] === 0 ? [0, 0, 1] : u;
  }

  /** Unit direction of a cube point (any unit). */
  direction(p) {
    return cubeToUnitSphere(p);
  }

  /** World position of a cube point at integer height `v`. */
  point(p, v) {
    return mul(this.direction(p), this.radiusM + this.heightM(v));
  }

  /** render/src/domain.rs `world_frame`: fine units of `vertexFine` (half side S 2N^2). */
  frame() {
    return {
      geometry: { kind: "planet", radiusM: this.radiusM, halfSideFine: this.halfSide * 2 * this.n * this.n },
      valueScaleM: this.valueScaleM,
      valueOffsetM: this.valueOffsetM,
      n: this.n,
      colourN: this.colourN,
    };
  }

  pointFine(p, v) {
    return this.point(p, v);
  }

  /** The world once a conservative lowest height (metres) is known: horizon culling. */
  withLowestHeight(lowestM) {
    return new SphereWorld({ ...this, occluderRadiusM: Math.max(this.radiusM + lowestM, 0) });
  }
}

/** Metres between rows from a georeference (open.rs `georef_spacing_m`), or null. */
function georefSpacingM(meta) {
  const g = meta.georef;
  if (g == null) return null;
  const rows = meta.extent[1];
  const node = String(g.registration).toLowerCase() === "node";
  const intervals = node ? rows - 1 : rows;
  const crs = g.crs ?? "";
  const geographic =
    crs.includes("4326") ||
    ((crs === "" || crs.toLowerCase().includes("lat")) &&
      [g.west, g.east].every((v) => Math.abs(v) <= 360) &&
      [g.north, g.south].every((v) => Math.abs(v) <= 90));
  const perRow = Math.abs(g.north - g.south) / Math.max(intervals, 1);
  const spacing = geographic ? ((perRow * Math.PI) / 180) * EARTH_RADIUS_M : perRow;
  return Number.isFinite(spacing) && spacing > 0 ? spacing : null;
}

function channelScale(meta) {
  const c = meta.channels?.[0];
  return c ? [Number(c.value_scale), Number(c.value_offset)] : [1, 0];
}

// ---------------------------------------------------------------------------------------
// What differs between planar repositories and planets (domain.rs `Domain`).

/** `c * 2^shift`, exactly (null on a remainder). */
function scaleCoordinate(c, shift) {
  if (shift >= 0) return c * 2 ** shift;
  const d = 2 ** -shift;
  return c % d === 0 ? c / d : null;
}

/** Probe coordinates along one chart axis, off every diamond edge. */
function probeAxis(extent, steps, offset) {
  const out = [];
  for (let a = 0; a < steps; a++) out.push((extent * (a + 0.5 + 0.1 * offset)) / (steps + 0.5));
  return out;
}

/** Planar geometry of a refiner's diamonds. */
class PlanarOps {
  constructor(refiner) {
    this.refiner = refiner;
    this.kind = "planar";
  }

  keyOf(id) {
    return [id.x, id.y, 0];
  }

  idOf(key) {
    return new PlanarId(key[0], key[1]);
  }

  scaleId(id, shift) {
    const x = scaleCoordinate(id.x, shift);
    const y = scaleCoordinate(id.y, shift);
    return x === null || y === null ? null : new PlanarId(x, y);
  }

  level(id) {
    return this.refiner.domain().level(id);
  }

  footprint(world, id, c, z) {
    let [x0, x1, y0, y1] = [Infinity, -Infinity, Infinity, -Infinity];
    for (const p of c) {
      x0 = Math.min(x0, p[0]);
      x1 = Math.max(x1, p[0]);
      y0 = Math.min(y0, p[1]);
      y1 = Math.max(y1, p[1]);
    }
    const s = world.spacingM;
    const bbox = { min: [x0 * s, y0 * s, z[0]], max: [x1 * s, y1 * s, z[1]] };
    const d0 = c[1][0] - c[0][0];
    const d1 = c[1][1] - c[0][1];
    return [bbox, (Math.sqrt(d0 * d0 + d1 * d1) * s) / this.refiner.n()];
  }

  hidden() {
    return false;
  }

  /** Exact position (id units x N) of grid vertex (i, j), null outside the raster. */
  vertexPoint(id, c, i, j) {
    const p = this.finePoint(id, c, i, j);
    const n = this.refiner.n();
    const [w, h] = this.refiner.rasterSize();
    const inside = p[0] >= 0 && p[0] <= (w - 1) * n && p[1] >= 0 && p[1] <= (h - 1) * n;
    return inside ? p : null;
  }

  /** render/src/domain.rs `fine_point` (outside the raster too). */
  finePoint(_id, c, i, j) {
    const n = this.refiner.n();
    return [
      c[0][0] * n + i * (c[1][0] - c[0][0]) + j * (c[3][0] - c[0][0]),
      c[0][1] * n + i * (c[1][1] - c[0][1]) + j * (c[3][1] - c[0][1]),
      0,
    ];
  }

  halfTriangle(c, half) {
    const apex = half === Half.Lower ? c[1] : c[3];
    return [0, [c[0], apex, c[2]].map((p) => [p[0], p[1]])];
  }

  probes() {
    const [w, h] = this.refiner.rasterSize();
    const out = [];
    for (const x of probeAxis(w - 1, 41, Math.SQRT2)) {
      for (const y of probeAxis(h - 1, 41, Math.E)) out.push([0, [x, y]]);
    }
    return out;
  }
}

/** Angle between two unit vectors, accurate for tiny angles too. */
function angle(a, b) {
  return Math.atan2(len(cross(a, b)), dot(a, b));
}

/** The centre direction of a planet diamond and the angle of a cap around it holding it. */
function sphereCap(world, id, c) {
  const centre = world.direction(id.c);
  let cap = 0;
  for (const p of c) cap = Math.max(cap, angle(centre, world.direction(p)));
  return [centre, cap * 1.05 + 1e-12];
}

/** The world box and grid spacing of a planet diamond (domain.rs `sphere_footprint`). */
export function sphereFootprint(world, n, id, c, z) {
  const [centre, cap] = sphereCap(world, id, c);
  const r0 = Math.max(world.radiusM + z[0], 0);
  const r1 = Math.max(world.radiusM + z[1], 0);
  const min = [0, 0, 0];
  const max = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    const axis = [0, 0, 0];
    axis[k] = 1;
    const theta = angle(centre, axis);
    const hi = Math.cos(Math.max(theta - cap, 0));
    const lo = Math.cos(Math.min(theta + cap, Math.PI));
    const products = [r0 * lo, r0 * hi, r1 * lo, r1 * hi];
    min[k] = Math.min(...products);
    max[k] = Math.max(...products);
  }
  const spacing = (len(sub(world.direction(c[1]), world.direction(c[0]))) * world.radiusM) / n;
  return [{ min, max }, spacing];
}

/**
 * Horizon culling (domain.rs `below_horizon`): whether the sphere of radius `occluder`
 * hides every point within angle `cap` of `centre` and at most `rMax` from the planet's
 * centre, seen from `eye`.
 */
export function belowHorizon(eye, occluder, centre, cap, rMax) {
  if (occluder <= 0) return false;
  const e = mul(eye, 1 / occluder);
  const horizon2 = dot(e, e) - 1;
  if (horizon2 <= 0) return false;
  const beta = Math.acos(1 / Math.max(rMax / occluder, 1));
  if (cap + beta >= Math.PI / 2) return false;
  const p = mul(centre, 1 / Math.cos(cap + beta));
  const toPoint = sub(p, e);
  const along = -dot(toPoint, e);
  return along > horizon2 && (along * along) / dot(toPoint, toPoint) > horizon2;
}

/** Planet geometry of a refiner's diamonds. */
class SphereOps {
  constructor(refiner) {
    this.refiner = refiner;
    this.kind = "sphere";
  }

  keyOf(id) {
    return [id.c[0], id.c[1], id.c[2]];
  }

  idOf(key) {
    return new SphereId([key[0], key[1], key[2]]);
  }

  scaleId(id, shift) {
    const c = id.c.map((x) => scaleCoordinate(x, shift));
    return c.includes(null) ? null : new SphereId(c);
  }

  level(id) {
    return this.refiner.domain().level(id);
  }

  footprint(world, id, c, z) {
    return sphereFootprint(world, this.refiner.n(), id, c, z);
  }

  hidden(world, id, c, zMax, eye) {
    const [centre, cap] = sphereCap(world, id, c);
    return belowHorizon(eye, world.occluderRadiusM, centre, cap, world.radiusM + zMax);
  }

  vertexPoint(id, _c, i, j) {
    return this.refiner.vertexFine(id, i, j);
  }

  finePoint(id, _c, i, j) {
    return this.refiner.vertexFine(id, i, j);
  }

  halfTriangle(c, half) {
    const apex = half === Half.Lower ? c[1] : c[3];
    const s = this.refiner.domain().size();
    const points = [c[0], apex, c[2]];
    for (let f = 0; f < 6; f++) {
      const ax = axes(f);
      if (points.every((p) => p[ax.a] === ax.s * s)) return [f, points.map((p) => chartOf(f, p, s))];
    }
    return null;
  }

  probes() {
    const side = 2 * this.refiner.domain().size();
    const out = [];
    for (let f = 0; f < 6; f++) {
      for (const u of probeAxis(side, 17, Math.SQRT2)) {
        for (const v of probeAxis(side, 17, Math.E)) out.push([f, [u, v]]);
      }
    }
    return out;
  }
}

function opsFor(refiner, planar) {
  return planar ? new PlanarOps(refiner) : new SphereOps(refiner);
}

// ---------------------------------------------------------------------------------------
// Procedural levels (decoder/src/incremental: `with_procedural_levels`, Procedural::Zero),
// which the refiner ports leave out: levels below the coded ones refined with zero
// details, so a colour layer and its elevation refine to the deeper one's depth.

class ProceduralRefiner {
  constructor(base, extra, planar) {
    this.base = base;
    this.extra = extra;
    this.planar = planar;
  }

  n() {
    return this.base.n();
  }
  domain() {
    return this.base.domain();
  }
  rasterSize() {
    return this.base.rasterSize();
  }
  detailLevels() {
    return this.base.detailLevels();
  }
  levels() {
    return this.base.detailLevels() + this.extra;
  }
  isCoded(id) {
    return this.base.isCoded(id);
  }
  roots() {
    return this.base.roots();
  }
  parents(id) {
    return this.base.parents(id);
  }
  sideParents(id) {
    return this.base.sideParents(id);
  }
  corners(id) {
    return this.base.corners(id);
  }
  decode(id, blob) {
    return this.base.decode(id, blob);
  }
  partialChildGrid(child, parents) {
    return this.base.partialChildGrid(child, parents);
  }
  vertexFine(id, i, j) {
    return this.base.vertexFine(id, i, j);
  }

  /** The level of a procedural diamond, or null. */
  proceduralLevel(id) {
    let level;
    try {
      level = this.base.domain().level(id);
    } catch {
      return null;
    }
    const coded = this.base.detailLevels();
    if (level < coded || level >= coded + this.extra) return null;
    if (this.planar && !this._meetsRaster(id)) return null;
    return level;
  }

  _meetsRaster(id) {
    let c;
    try {
      c = this.base.domain().corners(id);
    } catch {
      return false;
    }
    const [w, h] = this.base.rasterSize();
    const xs = c.map((p) => p[0]);
    const ys = c.map((p) => p[1]);
    return Math.min(...xs) < w && Math.max(...xs) >= 0 && Math.min(...ys) < h && Math.max(...ys) >= 0;
  }

  /** A planar procedural diamond's valid points (PlanarRefiner::procedural_mask). */
  _mask(id) {
    if (!this.planar) return null;
    const c = this.base.domain().corners(id);
    const n = this.n();
    const [w, h] = this.base.rasterSize();
    const at = (i2, j2) => [0, 1].map((k) => 2 * n * c[0][k] + i2 * (c[1][k] - c[0][k]) + j2 * (c[3][k] - c[0][k]));
    const inside = (p) => p[0] >= 0 && p[0] <= 2 * n * (w - 1) && p[1] >= 0 && p[1] <= 2 * n * (h - 1);
    const cornersIn = [
      [0, 0],
      [2 * n, 0],
      [2 * n, 2 * n],
      [0, 2 * n],
    ].every(([i, j]) => inside(at(i, j)));
    if (cornersIn) return null;
    return DiamondMask.fromFn(
      n,
      (i, j) => inside(at(2 * i, 2 * j)),
      (i, j) => inside(at(2 * i + 1, 2 * j + 1)),
    );
  }

  _children(id) {
    const all = this.base.domain().children(id);
    return this.planar ? all.filter((c) => this._meetsRaster(c)) : all;
  }

  isRefinable(id) {
    return this.base.isCoded(id) || this.proceduralLevel(id) !== null;
  }

  info(id) {
    const i = this.base.info(id);
    if (i !== null) return i;
    const level = this.proceduralLevel(id);
    if (level === null) return null;
    return { level, key: new Uint8Array(0), mask: this._mask(id), children: this._children(id), procedural: true };
  }

  children(id) {
    const c = this.base.children(id);
    if (c !== null) return c;
    return this.proceduralLevel(id) === null ? null : this._children(id);
  }

  synthesize(id, grid, details = null) {
    if (this.base.isCoded(id)) return this.base.synthesize(id, grid, details);
    if (details != null || this.proceduralLevel(id) === null) {
      throw new RefineError(`diamond ${String(id)} is not refinable in this repository`);
    }
    const n = this.n();
    if (grid.length !== (n + 1) * (n + 1)) throw new RefineError(`expected ${(n + 1) * (n + 1)} values, got ${grid.length}`);
    const vertices = Int32Array.from(grid);
    const cells = new Int32Array(n * n);
    synthesizeZero(n, vertices, cells, this._mask(id));
    return { id, vertices, cells, childClasses: [] };
  }
}

/** The refiner extended by `extra` procedural levels (Extension::new's checks). */
function withProceduralLevels(refiner, extra, planar, sparse) {
  if (extra === 0) return refiner;
  if (sparse) throw new SessionError("a sparse repository (holes) cannot be extended procedurally");
  const coded = refiner.detailLevels();
  const max = refiner.domain().maxLevel();
  if (coded + extra > max) {
    throw new SessionError(`${coded} coded + ${extra} procedural levels exceed the id space's ${max}`);
  }
  return new ProceduralRefiner(refiner, extra, planar);
}

// ---------------------------------------------------------------------------------------
// Colour layers (colour.rs).

/** A colour diamond's details: per channel (Y, Co, Cg) its details or null. */
function colourEmptyChildren(details, children) {
  return children.filter((c) =>
    details.channels.every((d) => d === null || d.emptyChildren.some((e) => e.equals(c))),
  );
}

/** A colour repository matched to an elevation DAG. */
export class ColourLayer {
  constructor(channels, shift, scales, codedLevels, ops) {
    /** One refiner per channel, extended by procedural levels to the DAG's depth. */
    this.channels = channels;
    /** Colour id = elevation id * 2^shift. */
    this.shift = shift;
    /** Per channel [value_scale, value_offset]. */
    this.scales = scales;
    this.codedLevels = codedLevels;
    this.ops = ops;
  }

  /**
   * Matches colour repository `name` (`meta`) to the elevation refiner (`elevationMeta`):
   * same ground, and whichever is shallower extended by procedural levels. Returns
   * `[elevationRefiner, layer]`.
   */
  static matchTo(elevation, elevationMeta, name, meta) {
    const mismatch = (reason) => new SessionError(`repository ${JSON.stringify(name)}: ${reason}`);
    if (meta.attribute?.kind !== "colour" || meta.channels?.length !== COLOUR_CHANNELS) {
      throw mismatch(
        `a colour layer needs a colour repository of ${COLOUR_CHANNELS} channels, not ${meta.attribute?.kind} (${meta.channels?.length} channels)`,
      );
    }
    if (meta.domain !== elevationMeta.domain) {
      throw mismatch(`domain ${meta.domain} does not match the elevation's ${elevationMeta.domain}`);
    }
    const planar = meta.domain === "planar";
    const Refiner = planar ? PlanarRefiner : SphereRefiner;
    let channels;
    try {
      channels = [0, 1, 2].map((k) => Refiner.fromMetadata(meta, k));
    } catch (e) {
      throw mismatch(e.message);
    }
    const shift = channels[0].domain().m() - elevation.domain().m();
    const problem = checkSameDomain(elevationMeta, meta, shift);
    if (problem !== null) throw mismatch(problem);
    const coded = channels[0].detailLevels();
    const elevationLevels = elevation.detailLevels();
    const depth = Math.max(coded, elevationLevels);
    const extend = (r, levels, m) => {
      try {
        return withProceduralLevels(r, depth - levels, planar, m.coverage != null);
      } catch (e) {
        throw mismatch(e.message);
      }
    };
    const elevationExtended = extend(elevation, elevationLevels, elevationMeta);
    channels = channels.map((c) => extend(c, coded, meta));
    const scales = meta.channels.map((c) => [Number(c.value_scale), Number(c.value_offset)]);
    const layer = new ColourLayer(channels, shift, scales, coded, opsFor(channels[0], planar));
    return [elevationExtended, layer];
  }

  /** Colour diamond size Nc. */
  n() {
    return this.channels[0].n();
  }

  colourId(id) {
    return this.ops.scaleId(id, this.shift);
  }

  elevationId(id) {
    return this.ops.scaleId(id, -this.shift);
  }

  /** Whether colour diamond `c` has a blob to fetch (coded, not procedural). */
  isCoded(c) {
    return this.channels[0].isCoded(c);
  }

  isRefinable(c) {
    return this.channels[0].isRefinable(c);
  }

  /** The colour node of an elevation root: `{id, grids, refined}` or null. */
  rootGrids(root) {
    const id = this.colourId(root);
    if (id === null) return null;
    const grids = [];
    for (const c of this.channels) {
      const found = c.roots().find(([r]) => r.equals(id));
      if (found === undefined) return null;
      grids.push(Int32Array.from(found[1]));
    }
    return { id, grids, refined: null };
  }

  /** Refines a colour node from its grids and details (null: zero or procedural). */
  synthesize(node, details) {
    return this.channels.map((r, k) => r.synthesize(node.id, node.grids[k], details?.channels[k] ?? null));
  }

  /** The part of a child's colour grids inside one refined parent: `[grids, written]`. */
  childHalf(child, lattices) {
    let written = null;
    const grids = this.channels.map((r, k) => {
      const [g, w] = r.partialChildGrid(child, [lattices[k]]);
      written = w;
      return g;
    });
    return [grids, written];
  }

  /** The YCoCg-R integers `[Y, Co, Cg]` of vertex `k` of colour grids (scaled back). */
  ycocg(grids, k) {
    return [0, 1, 2].map((c) => Math.round(this.scales[c][1] + grids[c][k] * this.scales[c][0]));
  }

  /** The sRGB colour of vertex `k` (YCoCg-R inverted, clamped to bytes). */
  rgb(grids, k) {
    const [y, co, cg] = this.ycocg(grids, k);
    return ycocgRToRgb(y, co, cg).map((x) => Math.min(255, Math.max(0, x)));
  }
}

/** colour.rs `check_same_domain`: null when both cover the same ground, else why not. */
function checkSameDomain(elevation, colour, shift) {
  if (elevation.domain === "sphere") {
    const [a, b] = [elevation.radius_m, colour.radius_m];
    if (a != null && b != null && Math.abs(a - b) > 1e-9 * Math.max(Math.abs(a), Math.abs(b))) {
      return `planet radius ${b} m does not match the elevation's ${a} m`;
    }
    return null;
  }
  for (let axis = 0; axis < 2; axis++) {
    const e = Math.max(elevation.extent[axis] - 1, 0);
    const c = Math.max(colour.extent[axis] - 1, 0);
    const same = shift >= 0 ? e * 2 ** shift === c : c * 2 ** -shift === e;
    if (!same) {
      return `extent ${JSON.stringify(colour.extent)} does not line up with the elevation's ${JSON.stringify(elevation.extent)} (id scale 2^${shift}): the rasters must span the same ground, node to node`;
    }
  }
  const [a, b] = [elevation.georef, colour.georef];
  if (a != null && b != null) {
    for (const k of ["west", "east", "north", "south"]) {
      if (Math.abs(a[k] - b[k]) > 1e-6 * (1 + Math.abs(a[k]))) {
        return `georeference ${k} ${b[k]} does not match the elevation's ${a[k]}`;
      }
    }
  }
  return null;
}

// ---------------------------------------------------------------------------------------
// The DAG (dag.rs).

/** Smallest and largest value of the present halves of a grid. */
function zRange(grid, n, present) {
  let lo = Infinity;
  let hi = -Infinity;
  const w = n + 1;
  for (let i = 0; i <= n; i++) {
    const row = i * w;
    for (let j = 0; j <= n; j++) {
      if ((present[0] && i >= j) || (present[1] && i <= j)) {
        const v = grid[row + j];
        if (v < lo) lo = v;
        if (v > hi) hi = v;
      }
    }
  }
  return lo > hi ? [0, 0] : [lo, hi];
}

/** Whether every half of `node` that exists is present. */
function complete(node) {
  return (node.present[0] || !node.expected[0]) && (node.present[1] || !node.expected[1]);
}

/** The side-information bound on how far a node's subtree departs from its grid (m). */
function boundM(node, world) {
  return node.class === null ? 0 : classBound(node.class) * Math.abs(world.valueScaleM);
}

/** Lowest and highest height its subtree can reach (metres). */
export function heightBoundsM(node, world) {
  const b = boundM(node, world);
  const a = world.heightM(node.zRange[0]);
  const c = world.heightM(node.zRange[1]);
  return [Math.min(a, c) - b, Math.max(a, c) + b];
}

/** Calls `f(i, j)` for each valid vertex of `half` on an edge of the half. */
function edgeVertices(n, half, mask, f) {
  for (let i = 0; i <= n; i++) {
    for (let j = 0; j <= n; j++) {
      const onEdge = i === j || i === 0 || j === 0 || i === n || j === n;
      if (onEdge && halfContains(half, i, j) && (mask == null || mask.vertex(i, j))) f(i, j);
    }
  }
}

/** A copy of `grid` with the entries `written` taken from `half`. */
function merged(grid, half, written) {
  const out = Int32Array.from(grid);
  for (let k = 0; k < out.length; k++) if (written[k]) out[k] = half[k];
  return out;
}

/** A copy of `grid` keeping only the entries of half `keep`. */
function keepHalf(grid, n, keep) {
  const out = Int32Array.from(grid);
  for (let i = 0; i <= n; i++) {
    for (let j = 0; j <= n; j++) if (!halfContains(keep, i, j)) out[i * (n + 1) + j] = 0;
  }
  return out;
}

/**
 * The in-core diamond DAG (dag.rs `Dag`): the diamonds from the roots down to the cut,
 * each with its vertex grid. Nodes: `{id, grid, present: [lower, upper], expected,
 * refined: {id, childClasses} | null, class, zRange, corners, children, generation,
 * colour: {id, grids: [Y, Co, Cg], refined} | null}`. Grids are replaced, never
 * modified in place, once a node holds them.
 */
export class Dag {
  constructor(refiner, ops, colour = null) {
    this.refiner = refiner;
    this.ops = ops;
    this.colour = colour;
    this.nodes = new Map();
    this.generations = 1;
    this.refinedCount = 0;
    this.changes = 0;
    /** Diamonds whose halves may have entered or left the cut since takeCutChanges. */
    this.touched = new Map();
    /** Halves takeCutChanges has reported in the cut ("idStr/half"). */
    this.reported = new Set();
    const n = refiner.n();
    for (const [root, grid] of refiner.roots()) {
      const node = {
        id: root,
        corners: refiner.corners(root),
        children: refiner.children(root) ?? [],
        zRange: zRange(grid, n, [true, true]),
        generation: 0,
        grid: Int32Array.from(grid),
        present: [true, true],
        expected: [true, true],
        refined: null,
        class: null,
        colour: colour ? colour.rootGrids(root) : null,
      };
      const k = String(root);
      this.nodes.set(k, node);
      this.touched.set(k, root);
    }
    this.cutHalves = 2 * this.nodes.size;
  }

  node(id) {
    return this.nodes.get(String(id));
  }

  get size() {
    return this.nodes.size;
  }

  /** Colour texels per elevation grid step (0 without colour). */
  texelsPerEdge() {
    return this.colour ? this.colour.n() / this.refiner.n() : 0;
  }

  /** The colour id whose blob refining `id` needs (null: none, procedural or outside). */
  colourBlobId(id) {
    if (!this.colour) return null;
    const node = this.node(id);
    if (!node || !node.colour) return null;
    return this.colour.isCoded(node.colour.id) ? node.colour.id : null;
  }

  /** Bytes of grids and nodes held (an estimate in constant time). */
  memoryBytes() {
    const perNode = (n) => this.nodes.size * 4 * (n + 1) * (n + 1);
    const colour = this.colour ? COLOUR_CHANNELS * perNode(this.colour.n()) : 0;
    return this.nodes.size * Dag.nodeBytes(this.refiner.n()) + colour;
  }

  /** Bytes a refinement adds at most. */
  refinementBytes() {
    const n = this.refiner.n();
    let colour = 0;
    if (this.colour) {
      const nc = this.colour.n();
      colour = COLOUR_CHANNELS * (Dag.latticeBytes(nc) + 16 * (nc + 1) * (nc + 1));
    }
    return Dag.latticeBytes(n) + 4 * Dag.nodeBytes(n) + colour;
  }

  static nodeBytes(n) {
    return 4 * (n + 1) * (n + 1) + 256;
  }

  static latticeBytes(n) {
    return 4 * ((n + 1) * (n + 1) + n * n);
  }

  /** Whether `id` can be refined now: present, complete, unrefined and refinable. */
  isRefinable(id) {
    const n = this.node(id);
    return n !== undefined && complete(n) && n.refined === null && this.refiner.isRefinable(id);
  }

  /** Whether `id` can be coarsened now: refined, and none of its children refined. */
  isCoarsenable(id) {
    const n = this.node(id);
    if (n === undefined || n.refined === null) return false;
    for (const c of this.children(id)) {
      const cn = this.node(c);
      if (cn !== undefined && cn.refined !== null) return false;
    }
    return true;
  }

  children(id) {
    const n = this.node(id);
    return n !== undefined ? n.children : (this.refiner.children(id) ?? []);
  }

  parents(id) {
    return this.refiner.parents(id);
  }

  /**
   * Refines `id` with its details (null: none) and, with a colour layer, its colour
   * details; returns the children.
   */
  refineLayers(id, details, colour) {
    return this._countingCut(id, () => this._refineUncounted(id, details, colour));
  }

  _countingCut(id, op) {
    const near = () => {
      const halves = (x) => (this.inCut(x, 0) ? 1 : 0) + (this.inCut(x, 1) ? 1 : 0);
      let s = halves(id);
      for (const c of this.children(id)) s += halves(c);
      return s;
    };
    const before = near();
    const out = op();
    this.cutHalves = Math.max(this.cutHalves + near() - before, 0);
    this.changes += 1;
    return out;
  }

  _refineUncounted(id, details, colour) {
    const notRefinable = () => new DagError(`${String(id)} cannot be refined now`);
    if (!this.isRefinable(id)) throw notRefinable();
    const node = this.node(id);
    const refined = this.refiner.synthesize(id, node.grid, details ?? null);
    let colourRefined = null;
    if (this.colour && node.colour && this.colour.isRefinable(node.colour.id)) {
      if (colour != null && !colour.id.equals(node.colour.id)) throw notRefinable();
      colourRefined = this.colour.synthesize(node.colour, colour ?? null);
    }
    const classes = new Map(refined.childClasses.map(([c, k]) => [String(c), k]));
    const children = this.children(id);
    for (const child of children) {
      this._addHalf(child, refined, colourRefined);
      const cls = classes.get(String(child));
      const cn = this.node(child);
      if (cls !== undefined && cn !== undefined) cn.class = cls;
    }
    this.touched.set(String(id), id);
    const n = this.node(id);
    n.refined = { id, childClasses: refined.childClasses };
    if (n.colour) n.colour.refined = colourRefined ? colourRefined.map((r) => ({ id: r.id })) : null;
    this.refinedCount += 1;
    return children;
  }

  /** Coarsens `id`: drops its refinement and its children's halves that lay in it. */
  coarsen(id) {
    if (!this.isCoarsenable(id)) throw new DagError(`${String(id)} cannot be coarsened now`);
    this._countingCut(id, () => {
      this.touched.set(String(id), id);
      const node = this.node(id);
      node.refined = null;
      if (node.colour) node.colour.refined = null;
      this.refinedCount -= 1;
      for (const child of this.children(id)) this._removeHalf(child, id);
    });
  }

  /** Writes the half of `child` inside `parent` (its fresh lattices) into the child. */
  _addHalf(child, parent, colourLattices) {
    const sideParents = this.refiner.sideParents(child);
    const h = sideParents.findIndex((p) => p.equals(parent.id));
    if (h < 0) throw new DagError(`${String(parent.id)} is not a side parent of ${String(child)}`);
    const [half, written] = this.refiner.partialChildGrid(child, [parent]);
    let colourHalf = null;
    if (this.colour && colourLattices) {
      const c = this.colour.colourId(child);
      if (c !== null) colourHalf = [c, ...this.colour.childHalf(c, colourLattices)];
    }
    const key = String(child);
    let node = this.nodes.get(key);
    if (node !== undefined) {
      node.grid = merged(node.grid, half, written);
      node.present = node.present.slice();
      node.present[h] = true;
      if (node.colour && colourHalf) {
        node.colour = {
          ...node.colour,
          grids: node.colour.grids.map((g, k) => merged(g, colourHalf[1][k], colourHalf[2])),
        };
      } else if (!node.colour && colourHalf) {
        node.colour = { id: colourHalf[0], grids: colourHalf[1], refined: null };
      }
    } else {
      const parents = this.parents(child);
      const present = [false, false];
      present[h] = true;
      node = {
        id: child,
        generation: 0,
        corners: this.refiner.corners(child),
        children: this.refiner.children(child) ?? [],
        zRange: [0, 0],
        grid: half,
        present,
        expected: sideParents.map((p) => parents.some((q) => q.equals(p)) && this.refiner.isRefinable(p)),
        refined: null,
        class: null,
        colour: colourHalf ? { id: colourHalf[0], grids: colourHalf[1], refined: null } : null,
      };
    }
    this._insertChanged(node);
  }

  /** Clears the half of `child` inside `parent`; a child with no half leaves the DAG. */
  _removeHalf(child, parent) {
    const sideParents = this.refiner.sideParents(child);
    const h = sideParents.findIndex((p) => p.equals(parent));
    if (h < 0) return;
    const key = String(child);
    const node = this.nodes.get(key);
    if (node === undefined) return;
    this.touched.set(key, child);
    const present = node.present.slice();
    present[h] = false;
    if (!present[0] && !present[1]) {
      this.nodes.delete(key);
      return;
    }
    const keep = BOTH[1 - h];
    node.present = present;
    node.grid = keepHalf(node.grid, this.refiner.n(), keep);
    if (this.colour && node.colour) {
      const nc = this.colour.n();
      node.colour = { ...node.colour, grids: node.colour.grids.map((g) => keepHalf(g, nc, keep)) };
    }
    this._insertChanged(node);
  }

  _insertChanged(node) {
    this.generations += 1;
    node.generation = this.generations;
    node.zRange = zRange(node.grid, this.refiner.n(), node.present);
    const key = String(node.id);
    this.touched.set(key, node.id);
    this.nodes.set(key, node);
  }

  /** Whether a half is in the cut: present in an unrefined diamond. */
  inCut(id, half) {
    const n = this.node(id);
    return n !== undefined && n.refined === null && n.present[half];
  }

  /** Halves that entered and left the cut since the previous call (sorted). */
  takeCutChanges() {
    const entered = [];
    const left = [];
    const touched = this.touched;
    this.touched = new Map();
    for (const [k, id] of touched) {
      for (const half of BOTH) {
        const now = this.inCut(id, half);
        const rk = `${k}/${half}`;
        const was = this.reported.has(rk);
        if (now && !was) {
          this.reported.add(rk);
          entered.push([id, half]);
        } else if (was && !now) {
          this.reported.delete(rk);
          left.push([id, half]);
        }
      }
    }
    const order = (a, b) => cmpId(a[0], b[0]) || a[1] - b[1];
    entered.sort(order);
    left.sort(order);
    return { entered, left };
  }

  /** A half of the cut as a renderer takes it (null when the diamond is not here). */
  patch(id, half) {
    const node = this.node(id);
    if (node === undefined) return null;
    return {
      id,
      half,
      key: patchKey(id, half),
      corners: node.corners,
      grid: node.grid,
      generation: node.generation,
      colour: node.colour ? node.colour.grids : null,
      level: this.ops.level(id),
      affine: this.affine(id, node.corners, half),
    };
  }

  /** takeCutChanges with the patches that entered. */
  takePatchChanges() {
    const c = this.takeCutChanges();
    return {
      entered: c.entered.map(([id, half]) => this.patch(id, half)).filter((p) => p !== null),
      left: c.left.map(([id, half]) => ({ id, half, key: patchKey(id, half) })),
    };
  }

  /** Makes the next takeCutChanges report the whole cut as entered. */
  restartCutChanges() {
    this.reported.clear();
    this.touched = new Map([...this.nodes].map(([k, n]) => [k, n.id]));
  }

  cutLen() {
    return this.cutHalves;
  }

  /** The cut: every present half of every unrefined diamond, in a stable order. */
  cut() {
    const out = [];
    for (const n of this.nodes.values()) {
      if (n.refined !== null) continue;
      for (const h of BOTH) if (n.present[h]) out.push([n.id, h]);
    }
    out.sort((a, b) => cmpId(a[0], b[0]) || a[1] - b[1]);
    return out;
  }

  /**
   * render/src/domain.rs `affine`: the fine point of grid vertex (i, j) of a half as
   * `base + i e1 + j e2` (exact; checked against a vertex inside the half), or null.
   */
  affine(id, corners, half) {
    const n = this.refiner.n();
    const p = (i, j) => this.ops.finePoint(id, corners, i, j);
    const origin = p(0, 0);
    const a = half === Half.Lower ? p(n, 0) : p(0, n);
    const b = p(n, n);
    if (origin === null || a === null || b === null) return null;
    const step = (from, to) => {
      const out = [0, 0, 0];
      for (let k = 0; k < 3; k++) {
        const d = to[k] - from[k];
        if (d % n !== 0) return null;
        out[k] = d / n;
      }
      return out;
    };
    const [e1, e2] = half === Half.Lower ? [step(origin, a), step(a, b)] : [step(a, b), step(origin, a)];
    if (e1 === null || e2 === null) return null;
    const [ci, cj] = half === Half.Lower ? [Math.floor((n * 3) / 4), Math.floor(n / 4)] : [Math.floor(n / 4), Math.floor((n * 3) / 4)];
    const q = p(ci, cj);
    if (q === null) return null;
    for (let k = 0; k < 3; k++) if (q[k] !== origin[k] + ci * e1[k] + cj * e2[k]) return null;
    return { base: origin, e1, e2 };
  }

  /**
   * Checks the cut (dag.rs `check_cut`): neighbouring halves agree bit for bit on every
   * shared valid vertex (heights and colour), and every probe point of the domain lies
   * in exactly one half. `ok` is the verdict.
   */
  checkCut() {
    const n = this.refiner.n();
    const values = new Map();
    const cut = this.cut();
    const check = {
      halves: 0,
      countedHalves: this.cutHalves,
      sharedVertices: 0,
      cracks: 0,
      colourShared: 0,
      colourCracks: 0,
      probes: 0,
      uncovered: 0,
      overlaps: 0,
      ok: false,
    };
    const triangles = new Map();
    for (const [id, half] of cut) {
      check.halves += 1;
      const node = this.node(id);
      if (node === undefined) continue;
      const t = this.ops.halfTriangle(node.corners, half);
      if (t !== null) {
        if (!triangles.has(t[0])) triangles.set(t[0], []);
        triangles.get(t[0]).push(t[1]);
      }
      const info = this.refiner.info(id);
      const mask = info ? info.mask : null;
      edgeVertices(n, half, mask, (i, j) => {
        const pos = this.ops.vertexPoint(id, node.corners, i, j);
        if (pos === null) return;
        const k = pos.join(",");
        const v = node.grid[i * (n + 1) + j];
        const old = values.get(k);
        values.set(k, v);
        if (old === undefined) return;
        if (old !== v) check.cracks += 1;
        else check.sharedVertices += 1;
      });
    }
    this._colourCracks(cut, check);
    const probes = this.ops.probes();
    const buckets = new Map();
    for (const [chart, ts] of triangles) {
      buckets.set(
        chart,
        new Buckets(
          probes.filter((p) => p[0] === chart).map((p) => p[1]),
          ts,
        ),
      );
    }
    for (const [chart, p] of probes) {
      const ts = triangles.get(chart);
      const b = buckets.get(chart);
      let hits = 0;
      if (ts && b) for (const k of b.near(p)) if (inTriangle(p, ts[k])) hits += 1;
      if (hits === 0) check.uncovered += 1;
      else if (hits === 1) check.probes += 1;
      else check.overlaps += 1;
    }
    check.ok =
      check.cracks === 0 &&
      check.halves === check.countedHalves &&
      check.colourCracks === 0 &&
      check.uncovered === 0 &&
      check.overlaps === 0 &&
      check.probes > 0;
    return check;
  }

  _colourCracks(cut, check) {
    const layer = this.colour;
    if (!layer) return;
    const n = layer.n();
    const refiner = layer.channels[0];
    const values = new Map();
    for (const [id, half] of cut) {
      const node = this.node(id);
      const colour = node?.colour;
      if (!colour) continue;
      const corners = refiner.corners(colour.id);
      const info = refiner.info(colour.id);
      const mask = info ? info.mask : null;
      edgeVertices(n, half, mask, (i, j) => {
        const pos = layer.ops.vertexPoint(colour.id, corners, i, j);
        if (pos === null) return;
        const key = pos.join(",");
        const k = i * (n + 1) + j;
        const v = `${colour.grids[0][k]},${colour.grids[1][k]},${colour.grids[2][k]}`;
        const old = values.get(key);
        values.set(key, v);
        if (old === undefined) return;
        if (old !== v) check.colourCracks += 1;
        else check.colourShared += 1;
      });
    }
  }
}

/** Triangles of one chart bucketed on a grid over the probes' extent. */
class Buckets {
  static SIDE = 64;

  constructor(points, triangles) {
    const min = [Infinity, Infinity];
    const max = [-Infinity, -Infinity];
    for (const p of points) {
      for (let k = 0; k < 2; k++) {
        min[k] = Math.min(min[k], p[k]);
        max[k] = Math.max(max[k], p[k]);
      }
    }
    const S = Buckets.SIDE;
    this.min = min;
    this.cell = [0, 1].map((k) => Math.max((max[k] - min[k]) / S, 1e-9));
    this.cells = Array.from({ length: S * S }, () => []);
    if (!(Number.isFinite(min[0]) && Number.isFinite(min[1]))) return;
    triangles.forEach((t, k) => {
      const lo = [0, 1].map((a) => this.index(Math.min(...t.map((p) => p[a])), a));
      const hi = [0, 1].map((a) => this.index(Math.max(...t.map((p) => p[a])), a));
      for (let y = lo[1]; y <= hi[1]; y++) for (let x = lo[0]; x <= hi[0]; x++) this.cells[y * S + x].push(k);
    });
  }

  index(v, axis) {
    const i = Math.floor((v - this.min[axis]) / this.cell[axis]);
    return Math.min(Math.max(i, 0), Buckets.SIDE - 1);
  }

  near(p) {
    return this.cells[this.index(p[1], 1) * Buckets.SIDE + this.index(p[0], 0)];
  }
}

/** Whether `p` is strictly inside triangle `t` (either orientation). */
function inTriangle(p, t) {
  const side = (a, b) => (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
  const s = [side(t[0], t[1]), side(t[1], t[2]), side(t[2], t[0])];
  return s.every((x) => x > 0) || s.every((x) => x < 0);
}

// ---------------------------------------------------------------------------------------
// Refinement (refine.rs).

/** Details not here yet (refine.rs `Arrival::Pending`). */
export const PENDING = Symbol("pending");

const DONE = 0;
const WAITING = 1;
const IMPOSSIBLE = 2;

/** Tuning (refine.rs `RefineConfig`). */
export function defaultRefineConfig() {
  return { hysteresis: 1, flatFraction: 0.1, maxDagBytes: null, maxCutHalves: null };
}

/** Projects diamonds for one view (refine.rs `Projector`). */
class Projector {
  constructor(view, world, config) {
    this.view = view;
    this.frustum = view.frustum();
    this.world = world;
    this.config = config;
    this.pxAt1m = view.pxPerM(1);
    this.flatPx = config.flatFraction * view.tolerancePx;
    /** idStr -> [generation, appearance] */
    this.seen = new Map();
  }

  appearance(dag, id) {
    const node = dag.node(id);
    if (node === undefined) return this.measure(dag, id);
    const k = String(id);
    const s = this.seen.get(k);
    if (s !== undefined && s[0] === node.generation) return s[1];
    const a = this.measure(dag, id);
    this.seen.set(k, [node.generation, a]);
    return a;
  }

  measure(dag, id) {
    const node = dag.node(id);
    if (node === undefined) return { errorPx: 0, visible: false, flat: true, marginM: Infinity };
    const w = this.world;
    const bound = boundM(node, w);
    const z = heightBoundsM(node, w);
    const [bbox, edgeM] = dag.ops.footprint(w, id, node.corners, z);
    const errorM = node.colour ? edgeM * Math.max(1 / dag.texelsPerEdge(), 1) : edgeM;
    const distanceM = Math.max(boxDistance(bbox, this.view.eye), NEAR_M);
    const pxPerM = this.pxAt1m / distanceM;
    const heightsOnly = node.class !== null && node.colour === null;
    const flat = heightsOnly && bound * pxPerM < this.flatPx;
    let triggerM = (errorM * this.pxAt1m) / this.view.tolerancePx;
    if (heightsOnly && this.flatPx > 0) triggerM = Math.min(triggerM, (bound * this.pxAt1m) / this.flatPx);
    return {
      errorPx: errorM * pxPerM,
      visible: frustumIntersects(this.frustum, bbox) && !dag.ops.hidden(w, id, node.corners, z[1], this.view.eye),
      flat,
      marginM: Math.max(distanceM - triggerM, 0),
    };
  }

  wantsSplit(a) {
    return a.visible && !a.flat && a.errorPx > this.view.tolerancePx;
  }

  allowsMerge(a) {
    return !a.visible || a.flat || a.errorPx < this.view.tolerancePx * this.config.hysteresis;
  }

  childrenCalm(dag, id) {
    for (const c of dag.children(id)) {
      if (dag.node(c) !== undefined && this.wantsSplit(this.appearance(dag, c))) return false;
    }
    return true;
  }
}

function newFrameStats() {
  return {
    refined: 0,
    coarsened: 0,
    pending: 0,
    dagNodes: 0,
    cutHalves: 0,
    dagBytes: 0,
    overBudget: false,
    maxErrorPx: 0,
    outOfTime: false,
    converged: false,
    fullQuality: false,
    elapsedMs: 0,
    reused: false,
    errors: 0,
  };
}

/**
 * Refinement state kept across frames (refine.rs `Refinement`): the split and merge
 * queues run each frame within a budget; deferred evaluation of diamonds the camera is
 * far from; a quiet frame (nothing changed, nothing waited for) is not run again.
 */
export class Refinement {
  constructor(config = {}) {
    this.config = { ...defaultRefineConfig(), ...config };
    this.travelM = 0;
    this.lastEye = null;
    this.projection = null;
    /** idStr -> [travel at which to look again, generation] */
    this.deferred = new Map();
    this.quiet = null;
    this.seen = null;
    /** Diamonds whose refinement threw (bad data or a bug): never tried again. */
    this.broken = new Set();
    /** The last such error, for stats. */
    this.lastError = null;
  }

  _trackCamera(view, world) {
    const projection = [view.fovYRad, ...view.viewportPx, view.tolerancePx, ...world.fingerprint()].join(",");
    if (this.projection !== projection) {
      this.projection = projection;
      this.deferred.clear();
    }
    if (this.lastEye !== null) this.travelM += len(sub(view.eye, this.lastEye));
    this.lastEye = view.eye.slice();
  }

  _under(view, world) {
    const c = this.config;
    return [view.signature(), ...world.fingerprint(), c.hysteresis, c.flatFraction, c.maxDagBytes, c.maxCutHalves].join(",");
  }

  /** How diamond `id` looks from `view`. */
  appearance(dag, view, world, id) {
    return new Projector(view, world, this.config).appearance(dag, id);
  }

  /** The unrefined diamonds `view` would want refined, with their errors: `[[id, e]]`. */
  wantedSplits(dag, view, world) {
    const projector = new Projector(view, world, this.config);
    const out = [];
    for (const n of dag.nodes.values()) {
      if (n.refined !== null || !dag.refiner.isRefinable(n.id)) continue;
      const a = projector.appearance(dag, n.id);
      if (projector.wantsSplit(a)) out.push([n.id, a.errorPx]);
    }
    return out;
  }

  /**
   * Runs one frame: splits and merges until both queues are empty or `budgetMs` is
   * spent (checked between operations against `clock()`, milliseconds). `source`:
   * `{details(id, p), want(id, p), colour(id, c, p), wantColour(id, c, p)}`, each
   * details-like call returning the details, null (no blob) or PENDING.
   */
  update(dag, view, world, source, clock, budgetMs) {
    const start = clock();
    const deadline = start + budgetMs;
    const under = this._under(view, world);
    const q = this.quiet;
    if (q !== null && q.under === under && q.changes === dag.changes) {
      return { ...q.stats, elapsedMs: clock() - start, reused: true };
    }
    const projector = new Projector(view, world, this.config);
    if (this.seen !== null && this.seen.under === under) projector.seen = this.seen.map;
    this.seen = null;
    const stats = newFrameStats();
    let blocked = null;
    const config = this.config;

    this._trackCamera(view, world);
    const travel = this.travelM;
    const splits = new Heap(splitFirst);
    for (const [k, n] of dag.nodes) {
      if (n.refined !== null || !dag.refiner.isRefinable(n.id)) continue;
      const d = this.deferred.get(k);
      if (d !== undefined && d[1] === n.generation && travel < d[0]) continue;
      const a = projector.appearance(dag, n.id);
      if (projector.wantsSplit(a)) splits.push([a.errorPx, n.id]);
      else if (a.marginM > 0) this.deferred.set(k, [travel + a.marginM, n.generation]);
    }
    if (this.deferred.size > 4 * dag.size + 1024) {
      for (const k of [...this.deferred.keys()]) if (!dag.nodes.has(k)) this.deferred.delete(k);
    }
    let waiting = 0;
    let worked = false;
    const needed = new Set();
    for (;;) {
      const top = splits.pop();
      if (top === undefined) break;
      const [error, id] = top;
      if (worked && clock() >= deadline) {
        stats.outOfTime = true;
        stats.maxErrorPx = Math.max(stats.maxErrorPx, error);
        want(dag, source, id, error);
        for (const [e, other] of splits.drain()) {
          const n = dag.node(other);
          if (n !== undefined && n.refined === null) want(dag, source, other, e);
        }
        break;
      }
      const refinedBefore = stats.refined;
      const node = dag.node(id);
      if (node === undefined || node.refined !== null) continue;
      if (config.maxCutHalves != null && cutOver(dag, config.maxCutHalves, 2 * unrefinedClosure(dag, id, config.maxCutHalves))) {
        stats.overBudget = true;
        stats.maxErrorPx = Math.max(stats.maxErrorPx, error);
        blocked = error;
        break;
      }
      const newly = [];
      const outcome = this._refineWithParents(dag, id, error, source, stats, 0, projector, newly, needed);
      for (const r of newly) {
        for (const child of dag.children(r)) {
          const cn = dag.node(child);
          if (cn !== undefined && cn.refined === null && dag.refiner.isRefinable(child)) {
            const a = projector.appearance(dag, child);
            if (projector.wantsSplit(a)) splits.push([a.errorPx, child]);
          }
        }
      }
      if (outcome === WAITING) {
        waiting += 1;
        stats.maxErrorPx = Math.max(stats.maxErrorPx, error);
      }
      worked = stats.refined > refinedBefore;
    }

    const splitsDone = !stats.outOfTime;
    if (!stats.outOfTime) {
      const merges = new Heap(mergeFirst);
      for (const n of dag.nodes.values()) {
        if (n.refined === null || !dag.isCoarsenable(n.id)) continue;
        const a = projector.appearance(dag, n.id);
        if (projector.allowsMerge(a)) merges.push([a.errorPx, n.id]);
      }
      for (;;) {
        const top = merges.pop();
        if (top === undefined) break;
        const id = top[1];
        if (!dag.isCoarsenable(id)) continue;
        if (needed.has(String(id)) || !projector.childrenCalm(dag, id)) continue;
        const freed = coarsenInTime(dag, id, clock, deadline, stats);
        if (freed === null) break;
        for (const parent of freed) {
          const a = projector.appearance(dag, parent);
          if (projector.allowsMerge(a)) merges.push([a.errorPx, parent]);
        }
      }
    }

    const over = (d) => (config.maxDagBytes != null && d.memoryBytes() > config.maxDagBytes) || cutOver(d, config.maxCutHalves, 0);
    if (blocked !== null && config.maxCutHalves != null && !stats.outOfTime) {
      const max = config.maxCutHalves;
      const target = max - Math.min(Math.max(Math.floor(max / 16), 64), Math.floor(max / 2));
      const room = (d) => d.cutLen() > target;
      this._evict(dag, projector, room, [blocked / 2, needed], clock, deadline, stats);
    }
    if (over(dag) && !stats.outOfTime) {
      stats.overBudget = true;
      this._evict(dag, projector, over, null, clock, deadline, stats);
    }

    stats.pending = waiting;
    stats.dagBytes = dag.memoryBytes();
    stats.dagNodes = dag.size;
    stats.cutHalves = dag.cutLen();
    stats.converged = !stats.outOfTime && waiting === 0;
    stats.fullQuality = splitsDone && waiting === 0 && !stats.overBudget;
    const seen = projector.seen;
    if (seen.size > 2 * dag.size + 1024) {
      for (const k of [...seen.keys()]) if (!dag.nodes.has(k)) seen.delete(k);
    }
    this.seen = { under, map: seen };
    stats.elapsedMs = clock() - start;
    this.quiet =
      stats.converged && stats.refined === 0 && stats.coarsened === 0 ? { under, changes: dag.changes, stats } : null;
    return stats;
  }

  /** Coarsens until `over(dag)` is false (refine.rs `evict`). */
  _evict(dag, projector, over, below, clock, deadline, stats) {
    const rank = (id) => {
      const a = projector.appearance(dag, id);
      return [a.visible ? a.errorPx : -1 / (1 + a.errorPx), id];
    };
    const queue = new Heap(mergeFirst);
    for (const n of dag.nodes.values()) if (n.refined !== null && dag.isCoarsenable(n.id)) queue.push(rank(n.id));
    while (over(dag)) {
      const top = queue.pop();
      if (top === undefined) break;
      const [e, id] = top;
      if (below !== null && e >= below[0]) break;
      if (!dag.isCoarsenable(id)) continue;
      if (below !== null && (below[1].has(String(id)) || !projector.childrenCalm(dag, id))) continue;
      const freed = coarsenInTime(dag, id, clock, deadline, stats);
      if (freed === null) break;
      for (const parent of freed) queue.push(rank(parent));
    }
  }

  /** Refines `id`, refining its missing parents first (refine.rs `refine_with_parents`). */
  _refineWithParents(dag, id, priority, source, stats, depth, projector, newly, needed) {
    if (depth > 128 || !dag.refiner.isRefinable(id) || this.broken.has(String(id))) return IMPOSSIBLE;
    if (depth > 0) needed.add(String(id));
    const node = dag.node(id);
    if (node !== undefined && node.refined !== null) return DONE;
    let pending = false;
    for (const parent of dag.parents(id)) {
      if (!dag.refiner.isRefinable(parent)) continue;
      const pn = dag.node(parent);
      if (pn === undefined || pn.refined === null) {
        const o = this._refineWithParents(dag, parent, priority * Math.SQRT2, source, stats, depth + 1, projector, newly, needed);
        if (o === WAITING) pending = true;
        else if (o === IMPOSSIBLE) return IMPOSSIBLE;
      }
    }
    if (pending) return WAITING;
    if (!dag.isRefinable(id)) return IMPOSSIBLE;
    if (depth === 0 && !projector.wantsSplit(projector.appearance(dag, id))) return IMPOSSIBLE;
    if (this.config.maxDagBytes != null && dag.memoryBytes() + dag.refinementBytes() > this.config.maxDagBytes) {
      stats.overBudget = true;
      stats.maxErrorPx = Math.max(stats.maxErrorPx, priority);
      return IMPOSSIBLE;
    }
    // Both layers are asked at once, so both requests go out in the same frame.
    const details = dag.refiner.isCoded(id) ? source.details(id, priority) : null;
    const c = dag.colourBlobId(id);
    const colour = c !== null ? source.colour(id, c, priority) : null;
    if (details === PENDING || colour === PENDING) return WAITING;
    try {
      dag.refineLayers(id, details, colour);
    } catch (e) {
      this.broken.add(String(id));
      this.lastError = `refining ${String(id)}: ${e?.message ?? e}`;
      stats.errors += 1;
      return IMPOSSIBLE;
    }
    stats.refined += 1;
    newly.push(id);
    return DONE;
  }
}

/** How many diamonds refining `id` takes (itself and its unrefined ancestors). */
function unrefinedClosure(dag, id, limit) {
  const seen = new Set();
  const stack = [id];
  while (stack.length > 0) {
    const d = stack.pop();
    if (seen.size > limit) break;
    const n = dag.node(d);
    const k = String(d);
    if (!dag.refiner.isRefinable(d) || (n !== undefined && n.refined !== null) || seen.has(k)) continue;
    seen.add(k);
    stack.push(...dag.parents(d));
  }
  return seen.size;
}

function cutOver(dag, max, extra) {
  return max != null && dag.cutLen() + extra > max;
}

/** Coarsens `id` unless the deadline passed (null); returns its parents now coarsenable. */
function coarsenInTime(dag, id, clock, deadline, stats) {
  if (stats.coarsened > 0 && clock() >= deadline) {
    stats.outOfTime = true;
    return null;
  }
  dag.coarsen(id);
  stats.coarsened += 1;
  return dag.parents(id).filter((p) => dag.isCoarsenable(p));
}

/** Records that `id`'s data is wanted in every layer that fetches it. */
function want(dag, source, id, priority) {
  if (dag.refiner.isCoded(id)) source.want(id, priority);
  const c = dag.colourBlobId(id);
  if (c !== null) source.wantColour(id, c, priority);
}

// ---------------------------------------------------------------------------------------
// The decoded-details cache (fetch/cache.rs): LRU by bytes, plus the known leaves.

class DecodedCache {
  constructor(budgetBytes) {
    this.budgetBytes = budgetBytes;
    this.usedBytes = 0;
    this._map = new Map(); // ks -> [value, bytes], oldest first
    this.leaves = new Set();
  }

  get(ks) {
    const e = this._map.get(ks);
    if (e === undefined) return undefined;
    this._map.delete(ks);
    this._map.set(ks, e);
    return e[0];
  }

  has(ks) {
    return this._map.has(ks);
  }

  insert(ks, value, bytes) {
    const old = this._map.get(ks);
    if (old !== undefined) {
      this.usedBytes -= old[1];
      this._map.delete(ks);
    }
    if (bytes > this.budgetBytes) return;
    this._map.set(ks, [value, bytes]);
    this.usedBytes += bytes;
    for (const [k, e] of this._map) {
      if (this.usedBytes <= this.budgetBytes) break;
      this._map.delete(k);
      this.usedBytes -= e[1];
    }
  }

  get size() {
    return this._map.size;
  }
}

/** Memory a decoded value holds (Weigh). */
function weight(v) {
  const one = (d) => (d === null ? 0 : 64 + d.h.byteLength + 48 * (d.childClasses.length + d.emptyChildren.length));
  return v.channels ? 64 + v.channels.reduce((s, d) => s + one(d), 0) : one(v);
}

// ---------------------------------------------------------------------------------------
// Decoding off the main thread.

/** A small pool of module workers running worker.mjs, or inline decoding. */
class DecoderPool {
  constructor(layers, count) {
    // Built in any case: it checks the metadata now and decodes when no worker can.
    this._inline = new AnswerDecoder(layers);
    this._workers = [];
    this._jobs = new Map();
    this._nextJob = 1;
    if (count > 0 && typeof Worker !== "undefined") {
      for (let k = 0; k < count; k++) {
        try {
          const w = new Worker(new URL("./worker.mjs", import.meta.url), { type: "module" });
          const slot = { worker: w, pending: new Set() };
          w.onmessage = (e) => this._answer(slot, e.data);
          w.onerror = (e) => this._lost(slot, e);
          w.postMessage({ type: "init", layers });
          this._workers.push(slot);
        } catch {
          break;
        }
      }
    }
  }

  /** Workers running (0: decoding inline). */
  get workers() {
    return this._workers.length;
  }

  /** Decodes an answer: Promise of `{value, carried}` (plain values, see worker.mjs). */
  decode(layer, key, bytes, packaged) {
    if (this._workers.length === 0) return this._decodeInline(layer, key, bytes, packaged);
    let slot = this._workers[0];
    for (const s of this._workers) if (s.pending.size < slot.pending.size) slot = s;
    const job = this._nextJob++;
    return new Promise((resolve, reject) => {
      this._jobs.set(job, { resolve, reject, args: [layer, key, bytes, packaged] });
      slot.pending.add(job);
      // The bytes are copied (small): kept for inline decoding should the worker fail.
      slot.worker.postMessage({ type: "decode", job, layer, key, bytes: bytes.slice().buffer, packaged });
    });
  }

  _decodeInline(layer, key, bytes, packaged) {
    try {
      const { value, carried } = this._inline.decode(layer, key, bytes, packaged);
      return Promise.resolve({ value, carried });
    } catch (e) {
      return Promise.reject(e);
    }
  }

  _answer(slot, msg) {
    const job = this._jobs.get(msg.job);
    if (job === undefined) return;
    this._jobs.delete(msg.job);
    slot.pending.delete(msg.job);
    if (msg.ok) job.resolve({ value: msg.value, carried: msg.carried });
    else job.reject(new DecodeError(msg.error));
  }

  /** A worker failed (it may not even have loaded): its jobs are decoded inline. */
  _lost(slot, event) {
    event?.preventDefault?.();
    this._workers = this._workers.filter((s) => s !== slot);
    try {
      slot.worker.terminate();
    } catch {
      // already gone
    }
    for (const id of slot.pending) {
      const job = this._jobs.get(id);
      this._jobs.delete(id);
      if (job) this._decodeInline(...job.args).then(job.resolve, job.reject);
    }
    slot.pending.clear();
  }

  close() {
    for (const s of this._workers) s.worker.terminate();
    this._workers = [];
  }
}

/** Plain decoded data (worker.mjs) back into details with ids. */
function rehydrate(ops, key, value) {
  const id = ops.idOf(key);
  const one = (d) =>
    d === null
      ? null
      : {
          id,
          h: d.h,
          childClasses: d.childClasses.map(([k, c]) => [ops.idOf(k), c]),
          emptyChildren: d.emptyChildren.map((k) => ops.idOf(k)),
        };
  return value.channels ? { id, channels: value.channels.map(one) } : one(value);
}

// ---------------------------------------------------------------------------------------
// Layers: one repository's data access (client-core stream.rs `LayerState`, fetch/planner.rs, schedule.rs).

const keyString = (k) => `${k[0]},${k[1]},${k[2]}`;
const WANT = 0;
const PREFETCH = 1;

/** Transient failures in a row before a key is given up (reported failed). */
const MAX_ATTEMPTS = 4;
const RETRY_BACKOFF_MS = 50;
const MAX_BACKOFF_MS = 2000;

/** Checks a repository name (remote.rs `check_name`). */
function checkName(name) {
  if (typeof name !== "string" || name === "" || name.startsWith(".") || !/^[A-Za-z0-9_.-]+$/.test(name)) {
    throw new SessionError(`repository name ${JSON.stringify(name)}: ASCII letters, digits, '-', '_' or '.'`);
  }
}

function trimBase(baseUrl) {
  return String(baseUrl ?? "").replace(/\/+$/, "");
}

/** `GET {base}/repos`: the served repositories (docs/http-api.md). */
export async function listRepositories(baseUrl, { fetch: fetchFn = globalThis.fetch.bind(globalThis) } = {}) {
  const url = `${trimBase(baseUrl)}/repos`;
  const resp = await fetchFn(url);
  if (resp.status !== 200) throw new SessionError(`GET ${url}: status ${resp.status}`);
  const body = await resp.json();
  return body.repositories ?? [];
}

/** Fetches a repository's metadata and names its blobs (remote.rs `Remote::open`). */
async function openRemote(baseUrl, name, fetchFn, timeoutMs) {
  checkName(name);
  const base = trimBase(baseUrl);
  const url = `${base}/repos/${name}/metadata.json`;
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), timeoutMs);
  let meta;
  try {
    const resp = await fetchFn(url, { signal: controller.signal });
    if (resp.status !== 200) throw new SessionError(`GET ${url}: status ${resp.status}`);
    const text = await resp.text();
    try {
      meta = JSON.parse(text);
    } catch (e) {
      throw new SessionError(`${url}: ${e.message}`);
    }
  } catch (e) {
    if (e instanceof SessionError) throw e;
    throw new SessionError(
      controller.signal.aborted ? `timed out after ${timeoutMs / 1000} s fetching the metadata from ${url}` : `GET ${url}: ${e?.message ?? e}`,
    );
  } finally {
    clearTimeout(timer);
  }
  if (meta === null || typeof meta !== "object") throw new SessionError(`${url}: not a metadata object`);
  const hash = String(meta.content_hash ?? "");
  if (hash.length < 16 || !/^[0-9a-fA-F]+$/.test(hash)) {
    throw new SessionError(`${url}: content_hash ${JSON.stringify(meta.content_hash)} is not hex`);
  }
  return {
    name,
    base,
    meta,
    version: hash.slice(0, 16),
    sphere: meta.domain === "sphere",
    staticExport: meta.static_export === true,
  };
}

/** How a repository's answers carry small owned children (client-core stream.rs `Packing`). */
function packingOf(meta, ops) {
  const limit = meta.inline_max_bytes;
  if (limit == null) return null;
  const carried = new Array(meta.levels).fill(false);
  for (const s of meta.level_stats ?? []) {
    if (s.level >= 0 && s.level < carried.length) carried[s.level] = s.blobs > 0 && s.bytes <= limit * s.blobs;
  }
  const domain = ops.refiner.domain();
  return {
    likelyCarried(key) {
      try {
        return carried[domain.level(ops.idOf(key))] === true;
      } catch {
        return false;
      }
    },
    owner(key) {
      try {
        const p = domain.parents(ops.idOf(key));
        return p.length > 0 ? ops.keyOf(p[0]) : null;
      } catch {
        return null;
      }
    },
  };
}

/** One repository's data access: frame wants, fetch queue, cache, leaves. */
class Layer {
  constructor(index, remote, ops, cacheBytes) {
    this.index = index;
    this.remote = remote;
    this.name = remote.name;
    this.meta = remote.meta;
    this.ops = ops;
    this.packing = packingOf(remote.meta, ops);
    this.cache = new DecodedCache(cacheBytes);
    /** Delivered since the last frame: ks -> details | null (leaf). */
    this.arrived = new Map();
    /** Known without asking: children of leaves, and owned children flagged empty. */
    this.inferredLeaves = new Set();
    /** Wanted this frame: ks -> {key, priority}. */
    this.frameWants = new Map();
    // The fetch queue (schedule.rs `Scheduler`).
    this.queue = new Map(); // ks -> {key, cls, priority}
    this.order = [];
    this.inFlight = new Map(); // ks -> {controller, packaged, cls, timer, timedOut}
    this.decoding = new Set();
    this.retry = new Map(); // ks -> {failures, notBefore}
    this.packageAbove = null;
    /** Wanted answers ready for the frame loop: ks -> details | null. */
    this.results = new Map();
    this.failedSinceFrame = 0;
  }

  blobUrl(key, packaged) {
    const r = this.remote;
    const kind = packaged ? "p" : "d";
    const coords = r.sphere ? `${key[0]}/${key[1]}/${key[2]}` : `${key[0]}/${key[1]}`;
    return `${r.base}/repos/${r.name}/v/${r.version}/${kind}/${coords}`;
  }

  isLeaf(ks) {
    return this.inferredLeaves.has(ks) || this.cache.leaves.has(ks);
  }

  /** Takes what was delivered since the last frame; returns the failures. */
  poll() {
    for (const [ks, v] of this.results) this.arrived.set(ks, v);
    this.results.clear();
    const failed = this.failedSinceFrame;
    this.failedSinceFrame = 0;
    return failed;
  }

  /** The data of `key` if here (null: a leaf), else PENDING (client-core stream.rs `LayerState::lookup`). */
  lookup(key, parents) {
    const ks = keyString(key);
    if (this.arrived.has(ks)) return this.arrived.get(ks);
    if (this.isLeaf(ks)) return null;
    const v = this.cache.get(ks);
    if (v !== undefined) return v;
    if (parents().some((p) => this.isLeaf(keyString(p)))) {
      this.inferredLeaves.add(ks);
      return null;
    }
    return PENDING;
  }

  /** The data of `key` for refinement: learns its empty children, or records it wanted. */
  take(key, priority, parents, empty) {
    const d = this.lookup(key, parents);
    if (d === PENDING) {
      this.record(key, priority);
      return PENDING;
    }
    if (d !== null) for (const k of empty(d)) this.inferredLeaves.add(keyString(k));
    return d;
  }

  /** Wants `key`, asking for the answer likely to carry it. */
  record(key, priority) {
    const routed = this.route(key);
    const ks = keyString(routed);
    const w = this.frameWants.get(ks);
    if (w === undefined) this.frameWants.set(ks, { key: routed, priority });
    else w.priority = Math.max(w.priority, priority);
  }

  /** The key to ask for to get `key` (its owner's while that package may carry it). */
  route(key) {
    const p = this.packing;
    if (p === null) return key;
    let at = key;
    while (p.likelyCarried(at)) {
      const owner = p.owner(at);
      if (owner === null) break;
      const os = keyString(owner);
      if (this.cache.has(os) || this.isLeaf(os)) break;
      at = owner;
    }
    return at;
  }

  packageAboveFor(factor, tolerancePx) {
    return factor == null || this.packing === null ? null : factor * tolerancePx;
  }

  /** Prefetch keys: routed, once each, known leaves left out. */
  prefetchKeys(ahead) {
    const out = [];
    const seen = new Set();
    for (const [key, p] of ahead) {
      const routed = this.route(key);
      const ks = keyString(routed);
      if (!this.isLeaf(ks) && !seen.has(ks)) {
        seen.add(ks);
        out.push([routed, p]);
      }
    }
    return out;
  }

  takeWants() {
    const out = [...this.frameWants.values()].map((w) => [w.key, w.priority]);
    this.frameWants.clear();
    return out;
  }
}

// ---------------------------------------------------------------------------------------
// Camera motion for prefetch (client-core stream.rs `CameraTrack`).

class CameraTrack {
  constructor() {
    this.last = null;
    this.lastStepM = 0;
    this.velocity = [0, 0, 0];
  }

  observe(nowS, eye) {
    const last = this.last;
    this.last = [nowS, eye.slice()];
    if (last === null) return;
    if (nowS < last[0] || !finite3(eye)) {
      this.velocity = [0, 0, 0];
      this.lastStepM = 0;
      return;
    }
    const dt = nowS - last[0];
    if (dt <= 0) return;
    const step = len(sub(eye, last[1]));
    const jump = step > 10 * this.lastStepM + 100;
    this.lastStepM = step;
    const v = mul(sub(eye, last[1]), 1 / dt);
    const zero = this.velocity.every((x) => x === 0);
    this.velocity = jump ? [0, 0, 0] : zero ? v : add(mul(this.velocity, 0.7), mul(v, 0.3));
  }
}

// ---------------------------------------------------------------------------------------
// The session (client-core stream.rs `StreamCore`, wrapped by session.rs `Session`).

function defaultWorkers() {
  const cores = typeof navigator !== "undefined" && navigator.hardwareConcurrency ? navigator.hardwareConcurrency : 2;
  return Math.min(4, Math.max(1, cores - 1));
}

/**
 * A served elevation repository (planar or planet) and optionally a colour repository
 * matched to it, streamed frame by frame. See the module comment for the interface.
 */
export class Session {
  /**
   * Opens repository `repoName` at `baseUrl` (`http://host[:port][/prefix]`, or "" for
   * the page's origin): fetches its metadata (and the colour repository's).
   */
  static async open(baseUrl, repoName, options = {}) {
    const fetchFn = options.fetch ?? globalThis.fetch.bind(globalThis);
    const timeoutMs = options.timeoutMs ?? 10_000;
    const elevation = await openRemote(baseUrl, repoName, fetchFn, timeoutMs);
    const colour = options.colour ? await openRemote(baseUrl, options.colour, fetchFn, timeoutMs) : null;
    return new Session(elevation, colour, { ...options, fetch: fetchFn });
  }

  constructor(elevation, colour, options = {}) {
    const meta = elevation.meta;
    const name = JSON.stringify(elevation.name);
    if (meta.domain !== "planar" && meta.domain !== "sphere") {
      throw new SessionError(`repository ${name}: unknown domain ${JSON.stringify(meta.domain)}`);
    }
    if (!Array.isArray(meta.channels) || meta.channels.length > 1) {
      throw new SessionError(
        `repository ${name}: ${meta.channels?.length} channels (${meta.attribute?.kind}): open it as a colour layer of an elevation session`,
      );
    }
    const planar = meta.domain === "planar";
    this.domain = planar ? "planar" : "sphere";
    this.meta = meta;
    this.colourMeta = colour ? colour.meta : null;
    let refiner;
    try {
      refiner = (planar ? PlanarRefiner : SphereRefiner).fromMetadata(meta, 0);
    } catch (e) {
      throw new SessionError(`repository ${name}: ${e.message}`);
    }
    const baseOps = opsFor(refiner, planar);
    let layer = null;
    if (colour) [refiner, layer] = ColourLayer.matchTo(refiner, meta, colour.name, colour.meta);
    const ops = opsFor(refiner, planar);
    this.n = refiner.n();
    this.colourN = layer ? layer.n() : 0;
    const [valueScaleM, valueOffsetM] = channelScale(meta);
    if (planar) {
      const spacing = Number.isFinite(options.spacingM) && options.spacingM > 0 ? options.spacingM : georefSpacingM(meta);
      this._world = new PlanarWorld({
        spacingM: spacing ?? 1,
        valueScaleM,
        valueOffsetM,
        extent: refiner.rasterSize(),
        n: this.n,
        colourN: this.colourN,
      });
    } else {
      const r = meta.radius_m;
      if (!(Number.isFinite(r) && r > 0)) throw new SessionError(`repository ${name}: a planet needs a positive radius`);
      this._world = new SphereWorld({
        radiusM: r,
        halfSide: refiner.domain().size(),
        valueScaleM,
        valueOffsetM,
        n: this.n,
        colourN: this.colourN,
      });
    }
    this.refiner = refiner;
    this.ops = ops;
    /** The colour layer (matched to the elevation), or null. */
    this.colourLayer = layer;
    this.dag = new Dag(refiner, ops, layer);
    this.refinement = new Refinement(options.refine ?? {});
    this.config = {
      maxInFlight: Math.max(1, options.maxInFlight ?? 8),
      cacheBytes: options.cacheBytes ?? 64 << 20,
      lookaheadLevels: options.lookaheadLevels ?? 2,
      prefetchAheadMs: options.prefetchAheadMs ?? 500,
      prefetchEveryMs: options.prefetchEveryMs ?? 100,
      prefetchMax: options.prefetchMax ?? 1024,
      packageFactor: options.packageFactor === undefined ? 2 : options.packageFactor,
      requestTimeoutMs: options.requestTimeoutMs ?? 10_000,
      cancelAfterMs: options.cancelAfterMs ?? 250,
    };
    this._fetch = options.fetch ?? globalThis.fetch.bind(globalThis);
    this._layers = [new Layer(0, elevation, baseOps, this.config.cacheBytes)];
    if (colour) this._layers.push(new Layer(1, colour, layer.ops, this.config.cacheBytes));
    const decoderLayers = [{ meta, kind: "elevation" }];
    if (colour) decoderLayers.push({ meta: colour.meta, kind: "colour" });
    this._decoder = new DecoderPool(decoderLayers, options.workers ?? defaultWorkers());
    this._camera = new CameraTrack();
    this._lastPrefetch = null;
    this._lowestKnown = false;
    this._closed = false;
    this._inFlight = 0;
    this._counters = {
      requests: 0,
      responses: 0,
      bytesReceived: 0,
      leaves: 0,
      carried: 0,
      cancelled: 0,
      timeouts: 0,
      failures: 0,
      peakInFlight: 0,
      errors: { clientStatus: 0, serverStatus: 0, connection: 0, decode: 0, timeout: 0, refine: 0 },
      lastError: null,
    };
    this._arrivals = []; // [time ms, bytes], the last seconds
    this._frame = null;
    this._viewSignature = null;
    this._viewChangedAt = null;
    this._timeToFullQualityMs = null;
    this._clock = () => performance.now();
    this._source = this._makeSource();
  }

  /** Ids and integer samples to metres (view.rs `PlanarWorld` / `SphereWorld`). */
  get world() {
    return this._world;
  }

  /** Repository name. */
  get name() {
    return this._layers[0].name;
  }

  /** Decoding workers running (0: inline). */
  get workers() {
    return this._decoder.workers;
  }

  /** Sets the most halves the cut may hold (a renderer's GPU pool), or null. */
  setMaxCutHalves(max) {
    this.refinement.config.maxCutHalves = max;
  }

  /**
   * Runs one frame for `camera` (see the module comment): takes what arrived, refines
   * and coarsens within `budgetMs`, asks for what the view wants.
   */
  update(camera, { tolerancePx = 1, viewportPx = [1920, 1080], budgetMs = 4 } = {}) {
    if (this._closed) return;
    // A camera that is not finite would poison the camera's travel (deferred
    // evaluation) and every projection: such frames change nothing.
    const sane =
      finite3(Array.from(camera.position)) &&
      finite3(Array.from(camera.forward)) &&
      finite3(Array.from(camera.up)) &&
      Number.isFinite(camera.fovYRad) &&
      camera.fovYRad > 0 &&
      Number.isFinite(tolerancePx) &&
      tolerancePx > 0;
    if (!sane) return;
    const started = this._clock();
    let failed = 0;
    for (const l of this._layers) failed += l.poll();
    this._counters.failures += failed;
    if (!this._lowestKnown) {
      const lowest = this._lowestHeight();
      if (lowest !== null) {
        this._world = this._world.withLowestHeight(lowest);
        this._lowestKnown = true;
      }
    }
    const view = View.fromCamera(camera, { tolerancePx, viewportPx });
    const signature = view.signature();
    if (signature !== this._viewSignature) {
      this._viewSignature = signature;
      this._viewChangedAt = started;
      this._timeToFullQualityMs = null;
    }
    const refine = this.refinement.update(this.dag, view, this._world, this._source, this._clock, budgetMs);
    if (refine.errors > 0) {
      this._counters.errors.refine += refine.errors;
      this._counters.lastError = this.refinement.lastError;
    }
    const [elevation, colour] = this._layers;
    const wants = elevation.takeWants();
    const colourWants = colour ? colour.takeWants() : [];
    for (const l of this._layers) l.arrived.clear();

    // The diamonds any layer wants (elevation ids), for lookahead and prefetch.
    const wanted = new Map();
    for (const [k, p] of wants) wanted.set(keyString(k), [this.ops.idOf(k), p]);
    if (colour) {
      for (const [k, p] of colourWants) {
        const id = this.colourLayer.elevationId(colour.ops.idOf(k));
        if (id === null) continue;
        const ks = keyString(this.ops.keyOf(id));
        const e = wanted.get(ks);
        if (e === undefined) wanted.set(ks, [id, p]);
        else e[1] = Math.max(e[1], p);
      }
    }
    let ahead = this._lookahead(wanted, this.config.lookaheadLevels, tolerancePx);
    ahead = ahead.concat(this._prefetch(view, started, wanted));
    ahead.sort((a, b) => b[1] - a[1]);
    const seen = new Set();
    ahead = ahead.filter(([id]) => {
      const k = String(id);
      if (seen.has(k)) return false;
      seen.add(k);
      return true;
    });
    ahead.length = Math.min(ahead.length, this.config.prefetchMax);
    const elevationAhead = elevation.prefetchKeys(
      ahead.filter(([id]) => this.refiner.isCoded(id)).map(([id, p]) => [this.ops.keyOf(id), p]),
    );
    this._submit(elevation, wants, elevationAhead, elevation.packageAboveFor(this.config.packageFactor, tolerancePx));
    if (colour) {
      const colourAhead = colour.prefetchKeys(
        ahead.flatMap(([id, p]) => {
          const c = this.colourLayer.colourId(id);
          return c !== null && this.colourLayer.isCoded(c) ? [[colour.ops.keyOf(c), p]] : [];
        }),
      );
      this._submit(colour, colourWants, colourAhead, colour.packageAboveFor(this.config.packageFactor, tolerancePx));
    }
    this._pump();
    const now = this._clock();
    const wantedKeys = wants.length + colourWants.length;
    const fullQuality = refine.fullQuality && wantedKeys === 0;
    // FrameStats::settled: full quality, or the best cut the budgets allow.
    const settled =
      wantedKeys === 0 &&
      (refine.fullQuality || (refine.overBudget && refine.converged && refine.refined === 0 && refine.coarsened === 0));
    if (settled && this._timeToFullQualityMs === null) this._timeToFullQualityMs = now - this._viewChangedAt;
    this._frame = {
      refine,
      wanted: wantedKeys,
      prefetched: elevationAhead.length,
      failed,
      fullQuality,
      settled,
      elapsedMs: now - started,
    };
  }

  /** What entered and left the cut since the previous call (dag.rs `PatchChanges`). */
  cutChanges() {
    return this.dag.takePatchChanges();
  }

  /** Makes the next cutChanges() report the whole cut again. */
  restartCutChanges() {
    this.dag.restartCutChanges();
  }

  /** The exact affine map of a half (render/src/domain.rs `affine`), or null. */
  affine(id, corners, half) {
    return this.dag.affine(id, corners, half);
  }

  /** The crack and coverage check of the current cut (dag.rs `check_cut`). */
  checkCut() {
    return this.dag.checkCut();
  }

  /**
   * Figures for the viewer's HUD and the tests: the cut (`triangles`, `patches`), the
   * network (`bytesReceived`, `bytesPerS` over the last second, `requestsInFlight`,
   * `queued`: wanted and not yet asked for, `requests`, `responses`, `leaves`,
   * `carried`, `cancelled`, `peakInFlight`), `fullQuality` (the last frame left nothing
   * to refine or fetch for its view; coarsening may still go on), `converged` (nothing
   * left to do at all), `settled` (full quality, or with setMaxCutHalves the best cut the
   * budget allows: FrameStats::settled; `budgetLimited` when that is short of full
   * quality), `timeToFullQualityMs` (from the last view change to the first settled
   * frame; null until then), `errors` by class (each failed
   * attempt), `failures` (keys given up for now; asked for again while wanted),
   * `lastError`, the DAG (`dagNodes`, `dagBytes`), the decoded cache and the last frame
   * (`frame`: refinement figures).
   */
  stats() {
    const now = this._clock();
    while (this._arrivals.length > 0 && this._arrivals[0][0] < now - 1000) this._arrivals.shift();
    let recent = 0;
    for (const [, b] of this._arrivals) recent += b;
    let queued = 0;
    for (const l of this._layers) {
      for (const ks of l.queue.keys()) if (!l.inFlight.has(ks) && !l.decoding.has(ks)) queued += 1;
    }
    const c = this._counters;
    const errors = { ...c.errors };
    errors.total = Object.values(c.errors).reduce((s, x) => s + x, 0);
    const patches = this.dag.cutLen();
    return {
      triangles: patches * this.n * this.n,
      patches,
      bytesReceived: c.bytesReceived,
      bytesPerS: recent,
      requestsInFlight: this._inFlight,
      queued,
      fullQuality: this._frame !== null && this._frame.fullQuality,
      converged: this._frame !== null && this._frame.fullQuality && this._frame.refine.converged,
      settled: this._frame !== null && this._frame.settled,
      budgetLimited: this._frame !== null && this._frame.settled && !this._frame.fullQuality,
      timeToFullQualityMs: this._timeToFullQualityMs,
      requests: c.requests,
      responses: c.responses,
      leaves: c.leaves,
      carried: c.carried,
      cancelled: c.cancelled,
      peakInFlight: c.peakInFlight,
      decoding: this._layers.reduce((s, l) => s + l.decoding.size, 0),
      errors,
      failures: c.failures,
      lastError: c.lastError,
      dagNodes: this.dag.size,
      dagBytes: this.dag.memoryBytes(),
      cacheBytes: this._layers.reduce((s, l) => s + l.cache.usedBytes, 0),
      workers: this._decoder.workers,
      frame: this._frame,
    };
  }

  /**
   * A conservative range of the surface's heights (metres) over the cut: each unrefined
   * diamond's grid range widened by its side-information bound.
   */
  heightRange() {
    let lo = Infinity;
    let hi = -Infinity;
    for (const n of this.dag.nodes.values()) {
      if (n.refined !== null) continue;
      const [a, b] = heightBoundsM(n, this._world);
      lo = Math.min(lo, a);
      hi = Math.max(hi, b);
    }
    return Number.isFinite(lo) && Number.isFinite(hi) ? [lo, hi] : [0, 0];
  }

  /** The world box of a planar raster: its extent times heightRange(). */
  bounds() {
    if (this.domain !== "planar") return null;
    const [w, h] = this._world.extent;
    const [lo, hi] = this.heightRange();
    const a = this._world.point([0, 0], 0);
    const b = this._world.point([w - 1, h - 1], 0);
    return { min: [Math.min(a[0], b[0]), Math.min(a[1], b[1]), lo], max: [Math.max(a[0], b[0]), Math.max(a[1], b[1]), hi] };
  }

  /**
   * Height (metres) of the current cut's surface below `position` along the local up
   * (+z on the plane, the radius on a planet), where that line meets the patches' grid
   * triangles as drawn; null outside the data (ground.rs `surface_height_m`).
   */
  heightAt(position) {
    if (!finite3(position)) return null;
    const frame = this._world.frame();
    const world = this._world;
    const up = frame.geometry.kind === "planar" ? [0, 0, 1] : world.up(position);
    const dag = this.dag;
    function* patches() {
      for (const [id, half] of dag.cut()) {
        const node = dag.node(id);
        if (node === undefined) continue;
        yield indexPatch(frame, dag.affine(id, node.corners, half), half === Half.Lower, node.grid);
      }
    }
    return surfaceHeightM(frame, (f, v) => world.pointFine(f, v), patches(), position, up);
  }

  /** Stops: aborts every request, ends the decoding workers. */
  close() {
    this._closed = true;
    for (const l of this._layers) {
      for (const f of l.inFlight.values()) {
        clearTimeout(f.timer);
        f.controller.abort();
      }
    }
    this._decoder.close();
  }

  // ---- internals ----------------------------------------------------------------------

  /** Details for refinement from what arrived, the caches, or the network. */
  _makeSource() {
    const ops = this.ops;
    const refiner = this.refiner;
    const [elevation, colour] = this._layers;
    const layer = this.colourLayer;
    const parentsOf = (r, o, id) => () => r.parents(id).map((p) => o.keyOf(p));
    return {
      details: (id, priority) =>
        elevation.take(ops.keyOf(id), priority, parentsOf(refiner, ops, id), (d) => d.emptyChildren.map((c) => ops.keyOf(c))),
      want: (id, priority) => {
        const key = ops.keyOf(id);
        if (elevation.lookup(key, parentsOf(refiner, ops, id)) === PENDING) elevation.record(key, priority);
      },
      colour: (_id, c, priority) => {
        if (!colour) return null;
        const channel = layer.channels[0];
        return colour.take(colour.ops.keyOf(c), priority, parentsOf(channel, colour.ops, c), (d) =>
          colourEmptyChildren(d, channel.children(c) ?? []).map((x) => colour.ops.keyOf(x)),
        );
      },
      wantColour: (_id, c, priority) => {
        if (!colour) return;
        const key = colour.ops.keyOf(c);
        if (colour.lookup(key, parentsOf(layer.channels[0], colour.ops, c)) === PENDING) colour.record(key, priority);
      },
    };
  }

  /** Whether every root is refined. */
  _rootsRefined() {
    return this.refiner.roots().every(([r]) => {
      const n = this.dag.node(r);
      return n !== undefined && n.refined !== null;
    });
  }

  /** Once every root is refined, a conservative lowest height (metres), else null. */
  _lowestHeight() {
    if (!this._rootsRefined()) return null;
    let lowest = Infinity;
    for (const [root] of this.refiner.roots()) {
      for (const c of this.dag.children(root)) {
        const n = this.dag.node(c);
        if (n === undefined) return null;
        lowest = Math.min(lowest, heightBoundsM(n, this._world)[0]);
      }
    }
    return Number.isFinite(lowest) ? lowest : null;
  }

  /** Whether some layer would fetch data for `id`. */
  _fetchable(id) {
    const [elevation, colour] = this._layers;
    if (this.refiner.isCoded(id) && !elevation.isLeaf(keyString(this.ops.keyOf(id)))) return true;
    if (!colour) return false;
    const c = this.colourLayer.colourId(id);
    return c !== null && this.colourLayer.isCoded(c) && !colour.isLeaf(keyString(colour.ops.keyOf(c)));
  }

  /** Descendants of wanted diamonds that will be wanted once these arrive. */
  _lookahead(wanted, levels, tolerancePx) {
    if (levels === 0) return [];
    const out = new Map();
    let frontier = [...wanted.values()];
    for (let l = 0; l < levels; l++) {
      const next = [];
      for (const [id, p] of frontier) {
        const childError = p / Math.SQRT2;
        if (childError <= tolerancePx) continue;
        for (const c of this.dag.children(id)) {
          const ks = String(c);
          if (wanted.has(keyString(this.ops.keyOf(c))) || !this._fetchable(c)) continue;
          const e = out.get(ks);
          if (e === undefined || childError > e[1]) {
            out.set(ks, [c, childError]);
            next.push([c, childError]);
          }
        }
      }
      frontier = next;
    }
    return [...out.values()];
  }

  /** Tracks the camera and, when due, what the predicted view wants beyond this one. */
  _prefetch(view, nowMs, wanted) {
    this._camera.observe(nowMs / 1000, view.eye);
    const aheadS = this.config.prefetchAheadMs / 1000;
    const due = this._lastPrefetch === null || nowMs - this._lastPrefetch >= this.config.prefetchEveryMs;
    const v = this._camera.velocity;
    if (aheadS <= 0 || !due || dot(v, v) === 0) return [];
    this._lastPrefetch = nowMs;
    const shift = mul(v, aheadS);
    const predicted = new View({ ...view, eye: add(view.eye, shift), target: add(view.target, shift) });
    return this.refinement
      .wantedSplits(this.dag, predicted, this._world)
      .filter(([id]) => !wanted.has(keyString(this.ops.keyOf(id))) && this._fetchable(id));
  }

  /**
   * Replaces a layer's queue with this frame's wants and prefetch keys (schedule.rs
   * `set_wants`); requests in flight that are no longer wanted are cancelled.
   */
  _submit(layer, wants, prefetch, packageAbove) {
    const now = this._clock();
    const queue = new Map();
    for (const [key, p] of prefetch) {
      const ks = keyString(key);
      if (!layer.isLeaf(ks) && !layer.cache.has(ks)) queue.set(ks, { key, cls: PREFETCH, priority: p });
    }
    for (const [key, p] of wants) {
      const ks = keyString(key);
      // Answered at once from the cache or the leaf set (a value evicted mid-frame).
      if (layer.cache.leaves.has(ks)) {
        layer.results.set(ks, null);
        continue;
      }
      const v = layer.cache.get(ks);
      if (v !== undefined) {
        layer.results.set(ks, v);
        continue;
      }
      queue.set(ks, { key, cls: WANT, priority: p });
    }
    layer.queue = queue;
    layer.order = [...queue.keys()].sort((a, b) => {
      const x = queue.get(a);
      const y = queue.get(b);
      return x.cls - y.cls || y.priority - x.priority || (a < b ? -1 : a > b ? 1 : 0);
    });
    for (const [ks, r] of layer.retry) if (!queue.has(ks) && r.notBefore <= now) layer.retry.delete(ks);
    layer.packageAbove = packageAbove;
    // Requests no frame has wanted for a while are cancelled (the camera moved on); a
    // short grace keeps a key that drops out for a frame or two (a speculative
    // lookahead, a frame out of time) from costing its connection.
    for (const f of layer.inFlight.values()) {
      if (queue.has(f.ks)) {
        f.staleSince = null;
      } else if (f.staleSince === null) {
        f.staleSince = now;
      }
      if (f.staleSince !== null && now - f.staleSince >= this.config.cancelAfterMs) {
        f.cancelled = true;
        f.controller.abort();
      }
    }
  }

  /** Issues requests while fewer than maxInFlight are outstanding, most urgent first. */
  _pump() {
    if (this._closed) return;
    const now = this._clock();
    const cursors = this._layers.map(() => 0);
    // The next candidate of layer `l` (null: none), from its cursor on.
    const next = (l) => {
      const layer = this._layers[l];
      for (let at = cursors[l]; at < layer.order.length; at++) {
        const ks = layer.order[at];
        const q = layer.queue.get(ks);
        if (q === undefined || layer.inFlight.has(ks) || layer.decoding.has(ks)) continue;
        const r = layer.retry.get(ks);
        if (r !== undefined && r.notBefore > now) continue;
        if (layer.isLeaf(ks) || layer.cache.has(ks)) continue;
        cursors[l] = at;
        return q;
      }
      cursors[l] = layer.order.length;
      return null;
    };
    while (this._inFlight < this.config.maxInFlight) {
      let best = null;
      let bestLayer = -1;
      for (let l = 0; l < this._layers.length; l++) {
        const q = next(l);
        if (q !== null && (best === null || q.cls < best.cls || (q.cls === best.cls && q.priority > best.priority))) {
          best = q;
          bestLayer = l;
        }
      }
      if (best === null) break;
      cursors[bestLayer] += 1;
      this._issue(this._layers[bestLayer], best);
    }
  }

  _issue(layer, q) {
    const ks = keyString(q.key);
    const packaged = layer.packing !== null && layer.packageAbove !== null && q.priority >= layer.packageAbove;
    const url = layer.blobUrl(q.key, packaged);
    const controller = new AbortController();
    const flight = { ks, controller, packaged, cls: q.cls, cancelled: false, timedOut: false, timer: null, staleSince: null };
    flight.timer = setTimeout(() => {
      flight.timedOut = true;
      controller.abort();
    }, this.config.requestTimeoutMs);
    layer.inFlight.set(ks, flight);
    this._inFlight += 1;
    this._counters.requests += 1;
    this._counters.peakInFlight = Math.max(this._counters.peakInFlight, this._inFlight);
    const done = () => {
      clearTimeout(flight.timer);
      if (layer.inFlight.get(ks) === flight) {
        layer.inFlight.delete(ks);
        this._inFlight -= 1;
      }
    };
    Promise.resolve()
      .then(() => this._fetch(url, { signal: controller.signal }))
      .then(async (resp) => {
        const status = resp.status;
        const body = status === 200 ? new Uint8Array(await resp.arrayBuffer()) : null;
        if (body === null) {
          try {
            await resp.body?.cancel();
          } catch {
            // nothing to drain
          }
        }
        return [status, body];
      })
      .then(
        ([status, body]) => {
          done();
          if (this._closed) return;
          if (status === 200) this._answered(layer, q.key, ks, body, flight, url);
          else if (status === 404 && layer.remote.staticExport) this._answered(layer, q.key, ks, new Uint8Array(0), flight, url);
          else {
            const permanent = status >= 400 && status < 500 && status !== 408 && status !== 429;
            this._failed(layer, ks, flight, permanent ? "clientStatus" : "serverStatus", `${url}: HTTP status ${status}`, !permanent);
          }
          this._pump();
        },
        (e) => {
          done();
          if (this._closed) return;
          if (flight.cancelled && !flight.timedOut) {
            this._counters.cancelled += 1;
          } else if (flight.timedOut) {
            this._failed(layer, ks, flight, "timeout", `${url}: no response within ${this.config.requestTimeoutMs} ms`, true);
          } else {
            this._failed(layer, ks, flight, "connection", `${url}: ${e?.message ?? e}`, true);
          }
          this._pump();
        },
      );
  }

  /** A 200 answer: a leaf when empty, else a value (and what it carried) to decode. */
  _answered(layer, key, ks, body, flight, url) {
    const c = this._counters;
    c.responses += 1;
    c.bytesReceived += body.length;
    const now = this._clock();
    this._arrivals.push([now, body.length]);
    while (this._arrivals[0][0] < now - 1000) this._arrivals.shift();
    layer.retry.delete(ks);
    const report = flight.cls === WANT || layer.queue.get(ks)?.cls === WANT;
    layer.queue.delete(ks);
    if (body.length === 0) {
      c.leaves += 1;
      layer.cache.leaves.add(ks);
      if (report) layer.results.set(ks, null);
      return;
    }
    layer.decoding.add(ks);
    this._decoder
      .decode(layer.index, key, body, flight.packaged)
      .then(
        ({ value, carried }) => {
          if (this._closed) return;
          for (const [k, v] of carried) {
            const cs = keyString(k);
            c.carried += 1;
            const wanted = layer.queue.get(cs)?.cls === WANT;
            layer.queue.delete(cs);
            const d = rehydrate(layer.ops, k, v);
            layer.cache.insert(cs, d, weight(d));
            if (wanted) layer.results.set(cs, d);
          }
          const d = rehydrate(layer.ops, key, value);
          layer.cache.insert(ks, d, weight(d));
          if (report) layer.results.set(ks, d);
        },
        (e) => {
          if (this._closed) return;
          this._failed(layer, ks, { cls: report ? WANT : PREFETCH }, "decode", `${url}: decode: ${e?.message ?? e}`, false);
        },
      )
      .finally(() => {
        layer.decoding.delete(ks);
        this._pump();
      });
  }

  /** A failed attempt: retried after a backoff if transient, held back if permanent. */
  _failed(layer, ks, flight, kind, message, transient) {
    const c = this._counters;
    c.errors[kind] += 1;
    c.lastError = message;
    const now = this._clock();
    let giveUp;
    if (transient) {
      const failures = (layer.retry.get(ks)?.failures ?? 0) + 1;
      const delay = failures <= 1 ? 0 : Math.min(RETRY_BACKOFF_MS * 2 ** Math.min(failures - 2, 20), MAX_BACKOFF_MS);
      layer.retry.set(ks, { failures, notBefore: now + delay });
      giveUp = failures >= MAX_ATTEMPTS;
    } else {
      const failures = layer.retry.get(ks)?.failures ?? 0;
      layer.retry.set(ks, { failures, notBefore: now + MAX_BACKOFF_MS });
      giveUp = true;
    }
    if (giveUp) {
      const report = flight.cls === WANT || layer.queue.get(ks)?.cls === WANT;
      layer.queue.delete(ks);
      if (report) layer.failedSinceFrame += 1;
    }
  }
}
