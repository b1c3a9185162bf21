// The browser's streaming client: the Rust client core compiled to WebAssembly
// (web/src/client.rs: the core's StreamCore with a request Planner and decoded cache per
// layer, as the native Session holds them) and the glue only JavaScript can do: `fetch`,
// timers, and decoding in module Web Workers (worker.mjs).
//
// The interface the viewer codes against:
//
//   const session = await Session.open(baseUrl, repoName, {colour: colourRepoName | null,
//     maxInFlight = 16 (per repository), workers (decoding workers; default cores - 1, at most 4; 0:
//     inline), cacheBytes = 64 MiB, fetch (a fetch function), lookaheadLevels = 2,
//     prefetchAheadMs = 500, packageFactor = 2 (0: bare blobs), spacingM, metric
//     ("geometric" | "sampling", default the native client's), maxCutHalves,
//     timeoutMs = 10 s (metadata), requestTimeoutMs = 10 s});
//     baseUrl: "http://host[:port][/prefix]", or "" for the page's origin. Rejects with
//     SessionError (bad name, metadata, a colour layer that does not match).
//   const session = await Session.openPack(fileUrl, {colourPack: colourFileUrl | null,
//     ...the options above});
//     A repository file (`repository.pack`) on any HTTP host that answers Range requests
//     (a bucket, a CDN, nginx), read by ranges (web/src/pack.rs; docs/hosting.md,
//     "Browsers"). Rejects with SessionError (the host ignored Range, 403, 404, not a
//     repository file, a CORS failure). A file changed since it was opened, and a
//     failing fetch, are reported to `onError(message)` (option) and counted as errors.
//   listRepositories(baseUrl) -> `GET /repos`'s list.
//   session.meta, session.colourMeta   metadata.json objects (colour: null without)
//   session.domain          "planar" | "sphere"
//   session.n, session.colourN   diamond sizes (colourN 0 without colour)
//   session.world.frame()   the renderer's world frame (client-core fine.rs `WorldFrame`:
//                           {geometry: {kind: "planar", metresPerFine, extentFine} |
//                           {kind: "planet", radiusM, halfSideFine}, valueScaleM,
//                           valueOffsetM, n, colourN})
//   session.update(camera, {tolerancePx = 1, viewportPx = [1920, 1080], budgetMs = 4})
//       camera = {position, forward, up: [x, y, z], fovYRad}: float64 world metres in
//       client-core view.rs's frame (planar: x east, y south, z up; planet: centred, +z
//       north). Refines and coarsens within budgetMs, keeps the network busy, never waits
//       for it; a camera with non-finite numbers changes nothing.
//   session.cutChanges() -> {entered: Patch[], left: [{id, half, key}]} since the last
//       call (the first reports the whole cut). Patch = {id ([x, y] planar, [x, y, z] planet),
//       half (Half.Lower = 0: i >= j, Half.Upper = 1: i <= j), key (patchKey), corners,
//       grid (Int32Array (N+1)^2), generation, colour ([Y, Co, Cg] Int32Arrays | null),
//       level, affine ({base, e1, e2}: fine point of (i, j) = base + i e1 + j e2)}. Arrays
//       are the page's own copies.
//   session.restartCutChanges()   the next cutChanges() reports the whole cut again.
//   session.stats()   figures (see `stats` below).
//   session.heightAt(position) -> metres of the drawn surface under `position` along the
//       local up, or null outside the data (ground.mjs, as render/src/ground.rs).
//   session.heightRange() -> [lo, hi] metres over the cut; session.bounds() (planar);
//   session.colourLayer ({scales, ycocg(grids, k), rgb(grids, k)} | null);
//   session.setMaxCutHalves(n | null); session.checkCut() (dag.rs `check_cut`);
//   session.close().
//
// What the native client has that this one does not: its transports (the browser's fetch
// decides between HTTP/2 and HTTP/1.1), the bandwidth cap, procedural noise (procedural
// levels have zero details, the native default), `warm_up`, flights. Requests are never
// cancelled (as in Rust): the planner keeps at most `maxInFlight` outstanding.

import { indexPatch, surfaceHeightM } from "./ground.mjs";
import { upAt, worldPoint } from "./camera.mjs";
import { loadWasm, WasmError } from "./wasm.mjs";

/** Opening failed: a bad name, unreachable metadata, layers that do not match. */
export class SessionError extends Error {
  constructor(message) {
    super(message);
    this.name = "SessionError";
  }
}

/** The two triangles of a diamond's grid: Lower = entries i >= j, Upper = i <= j. */
export const Half = Object.freeze({ Lower: 0, Upper: 1 });

/** A stable string key of a patch: "x,y/half" on a plane, "x,y,z/half" on a planet. */
export function patchKey(id, half) {
  return `${id.join(",")}/${half}`;
}

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

/** Fetches a repository's metadata (remote.rs `Remote::open`). */
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
  return { name, base, meta, version: hash.slice(0, 16), sphere: meta.domain === "sphere" };
}

/** Bytes of a repository file's first read (meta/src/pack.rs `OPEN_BYTES`). */
const FIRST_READ = 16384;

/** A failed fetch of a cross-origin file: most likely the host's CORS rule. */
function fetchFailure(url, e) {
  const what = e?.message ?? String(e);
  if (e?.name === "TypeError") {
    return `GET ${url}: ${what} (a CORS failure or an unreachable host: a host on another origin needs the CORS rule of docs/hosting.md, "Browsers")`;
  }
  return `GET ${url}: ${what}`;
}

/** One range read of `url`: {status, contentRange, etag, body}. Never sends If-Match. */
async function rangeRead(fetchFn, url, offset, len, signal) {
  const resp = await fetchFn(url, { headers: { Range: `bytes=${offset}-${offset + len - 1}` }, signal });
  const body = new Uint8Array(await resp.arrayBuffer());
  return { status: resp.status, contentRange: resp.headers.get("content-range"), etag: resp.headers.get("etag"), body };
}

/** Opens repository file `url` by ranges: a layer of the session with its PackFile. */
async function openPackFile(wasm, url, fetchFn, timeoutMs) {
  let abs;
  try {
    abs = new URL(url, globalThis.location?.href).href;
  } catch {
    throw new SessionError(`pack=${url}: not a URL`);
  }
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), timeoutMs);
  const read = async (offset, len) => {
    try {
      return await rangeRead(fetchFn, abs, offset, len, controller.signal);
    } catch (e) {
      if (controller.signal.aborted) throw new SessionError(`timed out after ${timeoutMs / 1000} s opening ${abs}`);
      throw new SessionError(fetchFailure(abs, e));
    }
  };
  let file;
  try {
    const first = await read(0, FIRST_READ);
    let figures;
    try {
      figures = wasm.packFirst(abs, first);
    } catch (e) {
      throw new SessionError(e.message);
    }
    const have = first.body.length;
    const rest = figures.openLen > have ? await read(have, figures.openLen - have) : null;
    try {
      file = wasm.packOpen(abs, figures, first.etag, first.body, rest);
    } catch (e) {
      throw new SessionError(e.message);
    }
  } finally {
    clearTimeout(timer);
  }
  const meta = file.meta;
  const name = decodeURIComponent(new URL(abs).pathname.split("/").pop() || "repository.pack");
  return { name, base: null, url: abs, meta, version: "", sphere: meta.domain === "sphere", pack: file };
}

function defaultWorkers() {
  const cores = typeof navigator !== "undefined" && navigator.hardwareConcurrency ? navigator.hardwareConcurrency : 2;
  return Math.min(4, Math.max(1, cores - 1));
}

/** Decoding workers (worker.mjs), or the page's own module when there are none. */
class DecoderPool {
  constructor(wasm, open, count) {
    // Built in any case: it decodes when no worker can.
    this._inline = wasm.decoder(open);
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
          w.postMessage({ type: "init", open });
          this._workers.push(slot);
        } catch {
          break;
        }
      }
    }
  }

  get workers() {
    return this._workers.length;
  }

  /** Promise of the details (Uint8Array, web/src/wire.rs) of an answer. */
  decode(layer, key, bytes, packaged) {
    if (this._workers.length === 0) return this._decodeInline(layer, key, bytes, packaged);
    let slot = this._workers[0];
    for (const s of this._workers) if (s.pending.size < slot.pending.size) slot = s;
    const job = this._nextJob++;
    return new Promise((resolve, reject) => {
      this._jobs.set(job, { resolve, reject, args: [layer, key, bytes, packaged] });
      slot.pending.add(job);
      // Copied (small): kept for inline decoding should the worker fail.
      slot.worker.postMessage({ type: "decode", job, layer, key, bytes: bytes.slice().buffer, packaged });
    });
  }

  _decodeInline(layer, key, bytes, packaged) {
    try {
      return Promise.resolve(this._inline.decode(layer, key, bytes, packaged));
    } catch (e) {
      return Promise.reject(e);
    }
  }

  _answer(slot, msg) {
    const job = this._jobs.get(msg.job);
    if (job === undefined) return;
    this._jobs.delete(msg.job);
    slot.pending.delete(msg.job);
    if (msg.ok) job.resolve(new Uint8Array(msg.details));
    else job.reject(new WasmError(msg.error));
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
    this._inline.free();
  }
}

/** YCoCg-R integers to sRGB (decoder/src/colour.rs `ycocg_r_to_rgb`), clamped to bytes. */
function ycocgToRgb([y, co, cg]) {
  const t = y - (cg >> 1);
  const g = cg + t;
  const b = t - (co >> 1);
  const r = b + co;
  return [r, g, b].map((x) => Math.min(255, Math.max(0, x)));
}

const finite3 = (a) => Array.isArray(a) && a.length === 3 && a.every((x) => Number.isFinite(x));

/**
 * A served elevation repository (planar or planet) and optionally a colour repository
 * matched to it, streamed frame by frame. See the module comment for the interface.
 */
export class Session {
  /** Opens repository `repoName` at `baseUrl` (and its colour layer). */
  static async open(baseUrl, repoName, options = {}) {
    const fetchFn = options.fetch ?? globalThis.fetch.bind(globalThis);
    const timeoutMs = options.timeoutMs ?? 10_000;
    const elevation = await openRemote(baseUrl, repoName, fetchFn, timeoutMs);
    const colour = options.colour ? await openRemote(baseUrl, options.colour, fetchFn, timeoutMs) : null;
    const wasm = await loadWasm();
    return new Session(wasm, elevation, colour, { ...options, fetch: fetchFn });
  }

  /** Opens repository file `url` (and `options.colourPack`) by range requests. */
  static async openPack(url, options = {}) {
    const fetchFn = options.fetch ?? globalThis.fetch.bind(globalThis);
    const timeoutMs = options.timeoutMs ?? 10_000;
    const wasm = await loadWasm();
    const elevation = await openPackFile(wasm, url, fetchFn, timeoutMs);
    let colour = null;
    try {
      colour = options.colourPack ? await openPackFile(wasm, options.colourPack, fetchFn, timeoutMs) : null;
      return new Session(wasm, elevation, colour, { ...options, fetch: fetchFn });
    } catch (e) {
      elevation.pack.free();
      colour?.pack.free();
      throw e;
    }
  }

  constructor(wasm, elevation, colour, options = {}) {
    const config = {
      maxInFlight: options.maxInFlight,
      cacheBytes: options.cacheBytes,
      lookaheadLevels: options.lookaheadLevels,
      prefetchAheadMs: options.prefetchAheadMs,
      packageFactor: options.packageFactor === null ? 0 : options.packageFactor,
      spacingM: options.spacingM,
      maxCutHalves: options.maxCutHalves ?? options.refine?.maxCutHalves,
      metric: options.metric,
      staticExport: elevation.meta.static_export === true,
    };
    for (const k of Object.keys(config)) if (config[k] === undefined || config[k] === null) delete config[k];
    const open = {
      elevation: { name: elevation.name, meta: elevation.meta },
      colour: colour ? { name: colour.name, meta: colour.meta } : null,
      config,
    };
    try {
      this._client = wasm.client(open, performance.now());
    } catch (e) {
      throw new SessionError(e.message);
    }
    this._layers = [elevation, colour].filter((l) => l !== null);
    this.meta = elevation.meta;
    this.colourMeta = colour ? colour.meta : null;
    this.domain = elevation.sphere ? "sphere" : "planar";
    const info = this._client.info();
    this._frame = info.frame;
    this.n = info.frame.n;
    this.colourN = info.frame.colourN;
    this.metric = info.metric;
    const frame = this._frame;
    this.world = {
      kind: this.domain,
      frame: () => ({ ...frame, geometry: { ...frame.geometry } }),
      pointFine: (p, v) => worldPoint(frame, p, v),
      up: (x) => upAt(frame, x),
    };
    const scales = colour ? colour.meta.channels.map((c) => [c.value_scale, c.value_offset]) : null;
    this.colourLayer = colour
      ? {
          scales,
          ycocg: (grids, k) => grids.map((g, c) => Math.round(scales[c][1] + g[k] * scales[c][0])),
          rgb: (grids, k) => ycocgToRgb(grids.map((g, c) => Math.round(scales[c][1] + g[k] * scales[c][0]))),
        }
      : null;
    this._fetch = options.fetch ?? globalThis.fetch.bind(globalThis);
    this._requestTimeoutMs = options.requestTimeoutMs ?? 10_000;
    this._onError = options.onError ?? null;
    /** Range reads of repository files: how many, by status. */
    this._ranges = { requests: 0, byStatus: {} };
    this._decoder = new DecoderPool(wasm, open, options.workers ?? defaultWorkers());
    this._flights = new Set();
    this._decoding = 0;
    this._wake = null;
    this._closed = false;
    this._arrivals = []; // [time ms, bytes] of the last second
    this._peakInFlight = 0;
    this._last = null;
    this._viewSignature = null;
    this._viewChangedAt = null;
    this._timeToFullQualityMs = null;
    /** The cut as the page last synced it: key -> patch; and changes not yet taken. */
    this._cut = new Map();
    this._pendingEntered = new Map();
    this._pendingLeft = new Map();
  }

  /** Decoding workers running (0: decoding inline). */
  get workers() {
    return this._decoder.workers;
  }

  /** Sets the most halves the cut may hold (a renderer's GPU pool), or null. */
  setMaxCutHalves(max) {
    this._client.setMaxCutHalves(max);
  }

  /** One frame (see the module comment). */
  update(camera, { tolerancePx = 1, viewportPx = [1920, 1080], budgetMs = 4 } = {}) {
    if (this._closed) return;
    const sane =
      finite3(Array.from(camera.position)) &&
      finite3(Array.from(camera.forward)) &&
      finite3(Array.from(camera.up)) &&
      Array.from(camera.forward).some((x) => x !== 0) &&
      Number.isFinite(camera.fovYRad) &&
      camera.fovYRad > 0 &&
      Number.isFinite(tolerancePx) &&
      tolerancePx > 0;
    if (!sane) return;
    const started = performance.now();
    const signature = JSON.stringify([camera.position, camera.forward, camera.up, camera.fovYRad, tolerancePx, viewportPx]);
    if (signature !== this._viewSignature) {
      this._viewSignature = signature;
      this._viewChangedAt = started;
      this._timeToFullQualityMs = null;
    }
    const cam = {
      position: Array.from(camera.position),
      forward: Array.from(camera.forward),
      up: Array.from(camera.up),
      fovYRad: camera.fovYRad,
    };
    const flags = this._client.frame(cam, viewportPx, tolerancePx, started, budgetMs);
    const now = performance.now();
    if (flags.settled && this._timeToFullQualityMs === null) this._timeToFullQualityMs = now - this._viewChangedAt;
    this._last = { ...flags, elapsedMs: now - started };
    this._pump();
  }

  /** What entered and left the cut since the previous call. */
  cutChanges() {
    this._sync();
    const changes = { left: [...this._pendingLeft.values()], entered: [...this._pendingEntered.values()] };
    this._pendingLeft.clear();
    this._pendingEntered.clear();
    return changes;
  }

  /** Makes the next cutChanges() report the whole cut again. */
  restartCutChanges() {
    this._sync();
    this._pendingLeft.clear();
    this._pendingEntered = new Map(this._cut);
  }

  /** Takes the module's changes into the page's copy of the cut. */
  _sync() {
    const planet = this.domain === "sphere";
    const idOf = (k) => (planet ? k : [k[0], k[1]]);
    const { left, entered } = this._client.changes();
    for (const l of left) {
      const id = idOf(l.key);
      const key = patchKey(id, l.half);
      this._cut.delete(key);
      this._pendingEntered.delete(key);
      this._pendingLeft.set(key, { id, half: l.half, key });
    }
    for (const p of entered) {
      const id = idOf(p.key);
      const key = patchKey(id, p.half);
      const patch = { ...p, id, key };
      this._cut.set(key, patch);
      this._pendingEntered.set(key, patch);
    }
  }

  /** The crack and coverage check of the current cut (dag.rs `check_cut`). */
  checkCut() {
    return this._client.checkCut();
  }

  /**
   * Figures for the viewer's panel and the tests: the cut (`triangles`, `patches`), the
   * network (`bytesReceived`, `bytesPerS` over the last second, `requestsInFlight`,
   * `queued`: wanted and not yet asked for, `requests`, `responses`, `leaves`,
   * `carried`, `cacheHits`, `peakInFlight`, `window`: the planner's request window),
   * `fullQuality` (the last frame left nothing to refine or fetch), `converged` (nothing
   * left to do), `settled` (full quality, or the best cut the cut budget allows;
   * `budgetLimited` when short of full quality), `timeToFullQualityMs` (from the last
   * view change to the first settled frame), `errors` by class, `failures`, `lastError`,
   * `dagNodes`, `dagBytes`, `cacheBytes`, `decoding`, `workers`, `frame` (the last
   * frame's refinement figures).
   */
  stats() {
    const s = this._client.stats();
    const now = performance.now();
    while (this._arrivals.length > 0 && this._arrivals[0][0] < now - 1000) this._arrivals.shift();
    const last = this._last;
    return {
      ...s,
      bytesPerS: this._arrivals.reduce((sum, [, b]) => sum + b, 0),
      peakInFlight: this._peakInFlight,
      fullQuality: last !== null && last.fullQuality,
      converged: last !== null && last.fullQuality && last.converged,
      settled: last !== null && last.settled,
      budgetLimited: last !== null && last.settled && !last.fullQuality,
      timeToFullQualityMs: this._timeToFullQualityMs,
      decoding: this._decoding,
      workers: this._decoder.workers,
      rangeRequests: this._ranges.requests,
      rangeStatus: { ...this._ranges.byStatus },
    };
  }

  /** A conservative range of the cut's heights (metres). */
  heightRange() {
    return this._client.heightRange();
  }

  /** The world box of a planar raster (metres), or null on a planet. */
  bounds() {
    if (this.domain !== "planar") return null;
    const g = this._frame.geometry;
    const [lo, hi] = this.heightRange();
    return {
      min: [0, 0, lo],
      max: [g.extentFine[0] * g.metresPerFine, g.extentFine[1] * g.metresPerFine, hi],
    };
  }

  /** Height (metres) of the drawn surface under `position` along the local up, or null. */
  heightAt(position) {
    if (!finite3(Array.from(position))) return null;
    this._sync();
    const frame = this._frame;
    const cut = this._cut;
    function* patches() {
      for (const p of cut.values()) yield indexPatch(frame, p.affine, p.half === Half.Lower, p.grid);
    }
    return surfaceHeightM(frame, (f, v) => worldPoint(frame, f, v), patches(), Array.from(position), upAt(frame, position));
  }

  /** Stops: aborts every request, ends the workers, frees the module's client. */
  close() {
    if (this._closed) return;
    this._closed = true;
    clearTimeout(this._wake);
    for (const f of this._flights) {
      clearTimeout(f.timer);
      f.controller.abort();
    }
    this._decoder.close();
    this._client.free();
    for (const l of this._layers) l.pack?.free();
  }

  // ---- the network glue ---------------------------------------------------------------

  /** Sends what the planners pick, and sets a timer for their next retry. */
  _pump() {
    if (this._closed) return;
    const now = performance.now();
    // Rounds: a repository file's reader answers some keys at once (leaves, blobs it
    // holds), which lets the planner pick more.
    for (let round = 0; round < 8; round++) {
      const planned = this._client.plan(now);
      if (planned.length === 0) break;
      for (const r of planned) if (!this._layers[r.layer].pack) this._send(r);
      this._layers.forEach((l, layer) => {
        if (!l.pack) return;
        const keys = planned.filter((r) => r.layer === layer);
        if (keys.length > 0) this._step(layer, l.pack.plan(keys));
      });
    }
    clearTimeout(this._wake);
    const wake = this._client.wakeIn(now);
    this._wake = wake >= 0 ? setTimeout(() => this._pump(), Math.max(1, wake)) : null;
  }

  _url(layer, key, packaged) {
    const r = this._layers[layer];
    const coords = r.sphere ? `${key[0]}/${key[1]}/${key[2]}` : `${key[0]}/${key[1]}`;
    return `${r.base}/repos/${r.name}/v/${r.version}/${packaged ? "p" : "d"}/${coords}`;
  }

  _send({ layer, key, packaged }) {
    const url = this._url(layer, key, packaged);
    this._inFlight(
      async (signal) => {
        const resp = await this._fetch(url, { signal });
        return [resp.status, new Uint8Array(await resp.arrayBuffer())];
      },
      ([status, body]) => this._answered(layer, key, status, body),
      (timedOut, e) => {
        const now = performance.now();
        if (timedOut) this._client.failed(layer, key, "", this._requestTimeoutMs, now);
        else this._client.failed(layer, key, `${url}: ${e?.message ?? e}`, null, now);
        this._pump();
      },
    );
  }

  /** One request under the request timeout: `start(signal)` makes it, and `answered(value)`
   * or `failed(timedOut, error)` takes its outcome, unless the client has closed. */
  _inFlight(start, answered, failed) {
    const controller = new AbortController();
    const flight = { controller, timer: null, timedOut: false };
    flight.timer = setTimeout(() => {
      flight.timedOut = true;
      controller.abort();
    }, this._requestTimeoutMs);
    this._flights.add(flight);
    this._peakInFlight = Math.max(this._peakInFlight, this._flights.size);
    const done = () => {
      clearTimeout(flight.timer);
      this._flights.delete(flight);
      return !this._closed;
    };
    Promise.resolve()
      .then(() => start(controller.signal))
      .then(
        (value) => done() && answered(value),
        (e) => done() && failed(flight.timedOut, e),
      );
  }

  /** A range reader's step: answers to the client, range requests to `fetch`. */
  _step(layer, step) {
    const now = performance.now();
    // Not pumping per answer: the caller pumps once after the step.
    for (const key of step.leaves) this._answered(layer, key, 200, new Uint8Array(0), false);
    for (const { key, kind, payload } of step.answers) {
      if (kind === 0) {
        const status = new DataView(payload.buffer, payload.byteOffset).getUint32(0, true);
        this._answered(layer, key, status, payload.subarray(4), false);
      } else {
        if (kind !== 2) this._failure(new TextDecoder().decode(payload));
        this._client.answerRaw(layer, kind, key, payload, now);
      }
    }
    for (const r of step.requests) this._sendRange(layer, r);
  }

  /** A failure the page should show (once per message). */
  _failure(message) {
    this._reported ??= new Set();
    if (this._onError && !this._reported.has(message)) {
      this._reported.add(message);
      this._onError(message);
    }
  }

  _sendRange(layer, { tag, offset, len }) {
    const l = this._layers[layer];
    this._ranges.requests += 1;
    this._inFlight(
      (signal) => rangeRead(this._fetch, l.url, offset, len, signal),
      (answer) => {
        const by = this._ranges.byStatus;
        by[answer.status] = (by[answer.status] ?? 0) + 1;
        this._step(layer, l.pack.answered(tag, answer));
        this._pump();
      },
      (timedOut, e) => {
        const failure = timedOut ? { timeoutMs: this._requestTimeoutMs } : { error: fetchFailure(l.url, e) };
        this._step(layer, l.pack.answered(tag, failure));
        this._pump();
      },
    );
  }

  /** An HTTP answer: the planner says what it means; a body to decode goes to a worker. */
  _answered(layer, key, status, body, pump = true) {
    const now = performance.now();
    if (status === 200) this._arrivals.push([now, body.length]);
    const decode = this._client.answer(layer, key, status, body, now);
    if (decode > 0) {
      this._decoding += 1;
      this._decoder
        .decode(layer, key, body, decode === 2)
        .then(
          (details) => {
            if (!this._closed) this._client.decoded(layer, key, details, performance.now());
          },
          (e) => {
            if (!this._closed) this._client.decodeFailed(layer, key, e?.message ?? String(e), performance.now());
          },
        )
        .finally(() => {
          this._decoding -= 1;
          this._pump();
        });
    }
    if (pump) this._pump();
  }
}
