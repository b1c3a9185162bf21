// The browser client (js/client.mjs on the WebAssembly client core, js/worker.mjs) against a real `quincunx serve` over
// a loopback socket, with the bundled demo repositories (korea: planar; earth and
// earth_colour: a planet and its colour). Prints SKIP when the binary or the
// repositories are absent.
//
// What it checks, as client/tests/refinement.rs and tests/tests/{session,colour}.rs do
// for the Rust client:
// - a straight-down view reaches full quality, and the converged cut meets the tolerance
//   wherever it is visible;
// - every frame's cut is crack-free: neighbouring patches, as the viewer receives them
//   through cutChanges(), agree on every shared edge vertex (and the DAG's own check,
//   colour included, passes), and the cut covers the domain exactly once;
// - never more than maxInFlight requests at once;
// - moving the camera away coarsens and frees nodes;
// - corrupt or failing answers become errors in stats(), not exceptions;
// - a static export's 404s are leaves;
// - decoding in module workers (a worker_threads shim of the Web Worker API) gives the
//   same cut as decoding inline.

import { after, before, test } from "node:test";
import assert from "node:assert/strict";
import { execFileSync, spawn } from "node:child_process";
import { existsSync, mkdtempSync, readFileSync, rmSync, statSync } from "node:fs";
import { createServer } from "node:http";
import { tmpdir } from "node:os";
import { join, normalize } from "node:path";
import { fileURLToPath } from "node:url";
import { Worker as NodeWorker } from "node:worker_threads";

import { Half, Session, SessionError, patchKey } from "../js/client.mjs";

const workspace = fileURLToPath(new URL("../..", import.meta.url));
// Set by the Rust harness (repo-tools/tests/web_demo.rs): then nothing may be missing.
const harnessed = process.env.QUINCUNX_DEMO_DIR !== undefined;
const BIN = process.env.QUINCUNX_BIN ?? join(workspace, "target", "release", "quincunx");
const DEMO = process.env.QUINCUNX_DEMO_DIR ?? join(workspace, "target", "tmp", "web-demo", "demo");
const REPOS = { korea: join(DEMO, "korea"), earth: join(DEMO, "earth"), earth_colour: join(DEMO, "earth_colour") };

let server = null;
let absent = null;

before(async () => {
  const missing = [BIN, ...Object.values(REPOS)].filter((p) => !existsSync(p));
  if (missing.length > 0) {
    absent = `no ${missing.join(", ")}`;
    if (harnessed) throw new Error(absent);
    return;
  }
  server = await startServer();
});

after(() => {
  server?.stop();
});

/** Starts `quincunx serve` on a free port; resolves with its base URL. */
function startServer() {
  const args = ["serve", "--addr", "127.0.0.1:0"];
  for (const [name, path] of Object.entries(REPOS)) args.push("--repo", `${name}=${path}`);
  const child = spawn(BIN, args, { stdio: ["ignore", "pipe", "pipe"] });
  // Not left running if the tests end early.
  process.on("exit", () => child.kill());
  return new Promise((resolve, reject) => {
    let out = "";
    const timer = setTimeout(() => {
      child.kill();
      reject(new Error(`quincunx serve did not start: ${out}`));
    }, 20_000);
    child.stdout.on("data", (chunk) => {
      out += chunk;
      const m = /serving on (http:\/\/[^/\s]+)\//.exec(out);
      if (m) {
        clearTimeout(timer);
        resolve({ base: m[1], stop: () => child.kill() });
      }
    });
    child.stderr.on("data", (chunk) => {
      out += chunk;
    });
    child.on("exit", (code) => {
      clearTimeout(timer);
      reject(new Error(`quincunx serve exited (${code}): ${out}`));
    });
  });
}

/** Whether the test can run; prints SKIP otherwise. */
function ready(name) {
  if (absent !== null || server === null) {
    console.log(`SKIP ${name}: ${absent ?? "no server"}`);
    return false;
  }
  return true;
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

/** A fetch that counts requests outstanding at once (and can rewrite answers). */
function countingFetch(rewrite = null) {
  const f = async (url, init) => {
    f.now += 1;
    f.peak = Math.max(f.peak, f.now);
    f.calls += 1;
    try {
      const resp = await fetch(url, init);
      return rewrite ? await rewrite(String(url), resp) : resp;
    } finally {
      f.now -= 1;
    }
  };
  f.now = 0;
  f.peak = 0;
  f.calls = 0;
  return f;
}

// ---- cameras (render/src/scene.rs `Shot::view`) ------------------------------------

/** A planar camera `heightM` above datum `groundM` at raster fractions (u, v). */
function planarCamera(session, u, v, heightM, pitchDeg = -90, headingDeg = 0) {
  const g = session.world.frame().geometry;
  const base = [u * g.extentFine[0] * g.metresPerFine, v * g.extentFine[1] * g.metresPerFine, 0];
  return orient(base, [0, 0, 1], [0, -1, 0], heightM, pitchDeg, headingDeg);
}

/** A planet camera `heightM` above the datum at a latitude and longitude. */
function planetCamera(session, latDeg, lonDeg, heightM, pitchDeg = -90, headingDeg = 0) {
  const la = (latDeg * Math.PI) / 180;
  const lo = (lonDeg * Math.PI) / 180;
  const up = [Math.cos(la) * Math.cos(lo), Math.cos(la) * Math.sin(lo), Math.sin(la)];
  const n = [-up[0] * up[2], -up[1] * up[2], 1 - up[2] * up[2]];
  const l = Math.hypot(...n);
  const north = n.map((x) => x / l);
  const base = up.map((x) => x * session.world.frame().geometry.radiusM);
  return orient(base, up, north, heightM, pitchDeg, headingDeg);
}

function orient(base, up, north, heightM, pitchDeg, headingDeg) {
  const east = [
    up[1] * north[2] - up[2] * north[1],
    up[2] * north[0] - up[0] * north[2],
    up[0] * north[1] - up[1] * north[0],
  ];
  const h = (headingDeg * Math.PI) / 180;
  const p = (pitchDeg * Math.PI) / 180;
  const horiz = [0, 1, 2].map((k) => north[k] * Math.cos(h) + east[k] * Math.sin(h));
  return {
    position: [0, 1, 2].map((k) => base[k] + up[k] * heightM),
    forward: [0, 1, 2].map((k) => horiz[k] * Math.cos(p) + up[k] * Math.sin(p)),
    up: [0, 1, 2].map((k) => -horiz[k] * Math.sin(p) + up[k] * Math.cos(p)),
    fovYRad: Math.PI / 3,
    near: 0.05,
    far: Infinity,
  };
}

// ---- the viewer's side: patches from cutChanges() ------------------------------------

/**
 * Keeps the cut as a viewer would from cutChanges(), checking the changes make sense,
 * and checks the patches it holds for cracks: every edge vertex two patches share (same
 * exact fine point) has the same value.
 */
class Mirror {
  constructor(session) {
    this.session = session;
    this.patches = new Map();
    this.entered = 0;
    this.left = 0;
  }

  take() {
    const ch = this.session.cutChanges();
    const n = this.session.n;
    for (const l of ch.left) {
      assert.equal(l.key, patchKey(l.id, l.half));
      assert.ok(this.patches.delete(l.key), `${l.key} left without having entered`);
      this.left += 1;
    }
    for (const p of ch.entered) {
      assert.equal(p.key, patchKey(p.id, p.half));
      assert.ok(!this.patches.has(p.key), `${p.key} entered twice`);
      assert.equal(p.grid.length, (n + 1) * (n + 1));
      assert.ok(p.affine !== null, `${p.key} has no affine map`);
      this.patches.set(p.key, p);
      this.entered += 1;
    }
    assert.equal(this.patches.size, this.session.checkCut().halves, "the mirrored cut is the cut");
    return ch;
  }

  /** Edge vertices shared by two patches with different values (must be 0), and shared. */
  cracks() {
    const n = this.session.n;
    const frame = this.session.world.frame();
    const g = frame.geometry;
    const values = new Map();
    let cracks = 0;
    let shared = 0;
    for (const p of this.patches.values()) {
      const a = p.affine;
      for (let i = 0; i <= n; i++) {
        for (let j = 0; j <= n; j++) {
          const onEdge = i === j || i === 0 || j === 0 || i === n || j === n;
          const inHalf = p.half === Half.Lower ? i >= j : i <= j;
          if (!onEdge || !inHalf) continue;
          const f = [0, 1, 2].map((k) => a.base[k] + i * a.e1[k] + j * a.e2[k]);
          // Outside a planar raster vertices carry no data.
          if (g.kind === "planar" && (f[0] < 0 || f[1] < 0 || f[0] > g.extentFine[0] || f[1] > g.extentFine[1])) continue;
          const key = f.join(",");
          const v = p.grid[i * (n + 1) + j];
          const old = values.get(key);
          values.set(key, v);
          if (old === undefined) continue;
          if (old !== v) cracks += 1;
          else shared += 1;
        }
      }
    }
    return { cracks, shared };
  }
}

/**
 * Runs frames of `camera` until `done(stats)` (default: full quality) or `timeoutMs`,
 * checking every frame: the mirrored cut, no cracks (viewer side and the DAG's check),
 * requests in flight within maxInFlight. Returns the last stats.
 */
async function stream(session, mirror, camera, { done = (s) => s.fullQuality, timeoutMs = 30_000, maxInFlight, budgetMs = 8, check = true } = {}) {
  const t0 = performance.now();
  for (;;) {
    session.update(camera, { tolerancePx: 1, viewportPx: [1280, 720], budgetMs });
    mirror.take();
    const st = session.stats();
    if (maxInFlight !== undefined) assert.ok(st.requestsInFlight <= maxInFlight, `${st.requestsInFlight} requests in flight`);
    if (check) {
      const c = session.checkCut();
      assert.ok(c.ok, `the cut fails its check: ${JSON.stringify(c)}`);
      const m = mirror.cracks();
      assert.equal(m.cracks, 0, "patches disagree on a shared edge");
    }
    if (done(st)) return st;
    if (performance.now() - t0 > timeoutMs) assert.fail(`no full quality within ${timeoutMs} ms: ${JSON.stringify(st)}`);
    await sleep(4);
  }
}

/** Nothing left to refine, fetch or coarsen. */
const converged = (s) => s.converged;

/** Every visible diamond of the cut meets the tolerance (or is as fine as it gets). */
function assertMeetsTolerance(session) {
  const f = session.stats().frame;
  assert.ok(f.fullQuality && f.maxErrorPx <= 1, `a visible diamond is ${f.maxErrorPx} px off`);
}

// ---- the tests ----------------------------------------------------------------------

test("a planar session reaches full quality straight down, every frame crack-free", async () => {
  if (!ready("planar full quality")) return;
  const counting = countingFetch();
  const session = await Session.open(server.base, "korea", { maxInFlight: 4, fetch: counting });
  try {
    assert.equal(session.domain, "planar");
    assert.equal(session.n, 32);
    const g = session.world.frame().geometry;
    assert.deepEqual(g.extentFine.map((e) => e / 32 + 1), [1025, 1025]);
    assert.equal(session.metric, "geometric");
    const mirror = new Mirror(session);
    const camera = planarCamera(session, 0.5, 0.5, 30_000);
    const st = await stream(session, mirror, camera, { maxInFlight: 4 });
    assert.ok(st.fullQuality && st.timeToFullQualityMs > 0, JSON.stringify(st));
    // Coarsening may go on after full quality; then nothing changes any more.
    await stream(session, mirror, camera, { maxInFlight: 4, done: converged, budgetMs: 50 });
    assert.ok(st.patches > 100 && st.triangles === st.patches * 32 * 32, JSON.stringify(st));
    assert.equal(st.errors.total, 0, st.lastError);
    assert.ok(st.bytesReceived > 0 && st.responses > 0);
    assert.ok(counting.peak <= 4, `${counting.peak} requests at once`);
    assert.ok(counting.peak >= 2, "requests overlap");
    assertMeetsTolerance(session);
    const c = session.checkCut();
    assert.ok(c.ok && c.sharedVertices > 0 && c.probes > 0, JSON.stringify(c));
    const m = mirror.cracks();
    assert.ok(m.cracks === 0 && m.shared > 1000, JSON.stringify(m));
    // A held view changes nothing more: the frame is reused.
    session.update(camera, { tolerancePx: 1, viewportPx: [1280, 720], budgetMs: 8 });
    session.update(camera, { tolerancePx: 1, viewportPx: [1280, 720], budgetMs: 8 });
    const held = mirror.take();
    assert.equal(held.entered.length + held.left.length, 0);
    assert.equal(session.stats().frame.reused, true);
  } finally {
    session.close();
  }
});

test("the height under the camera is the drawn surface's", async () => {
  if (!ready("height under the camera")) return;
  const session = await Session.open(server.base, "korea", {});
  try {
    const mirror = new Mirror(session);
    const camera = planarCamera(session, 0.9, 0.1, 3000);
    await stream(session, mirror, camera, { check: false });
    const [lo, hi] = session.heightRange();
    const g = session.heightAt(camera.position);
    assert.ok(g !== null && g >= lo && g <= hi, `${g} not in ${lo}..${hi}`);
    // At a grid vertex the surface is the vertex itself.
    const world = session.world;
    let checked = 0;
    for (const p of mirror.patches.values()) {
      const [i, j] = p.half === Half.Lower ? [20, 5] : [5, 20];
      const f = [0, 1, 2].map((k) => p.affine.base[k] + i * p.affine.e1[k] + j * p.affine.e2[k]);
      const g0 = world.frame().geometry;
      if (f[0] <= 0 || f[1] <= 0 || f[0] >= g0.extentFine[0] || f[1] >= g0.extentFine[1]) continue;
      const x = world.pointFine(f, p.grid[i * 33 + j]);
      const h = session.heightAt([x[0], x[1], x[2] + 100]);
      assert.ok(Math.abs(h - x[2]) < 1e-6, `${h} vs ${x[2]}`);
      if (++checked >= 20) break;
    }
    assert.ok(checked > 0);
    assert.equal(session.heightAt([-1e6, -1e6, 100]), null, "outside the raster");
  } finally {
    session.close();
  }
});

test("extreme and broken cameras change nothing they should not", async () => {
  if (!ready("extreme cameras")) return;
  const session = await Session.open(server.base, "korea", {});
  try {
    const mirror = new Mirror(session);
    const good = planarCamera(session, 0.5, 0.5, 30_000);
    await stream(session, mirror, good, {});
    const cameras = [
      { ...good, position: [NaN, 0, 1000] },
      { ...good, forward: [0, 0, 0] },
      { ...good, up: [0, 0, -1], forward: [0, 0, -1] }, // up along the view direction
      { ...good, position: [1e12, -1e12, 1e9] },
      { ...good, position: [40_000, 40_000, -5000], forward: [0, 0, 1] }, // below, looking up
      { ...good, fovYRad: 1e-6 },
      planarCamera(session, 0.5, 0.5, 2, 0), // 2 m above the datum, level
    ];
    for (const camera of cameras) {
      for (let f = 0; f < 5; f++) {
        session.update(camera, { tolerancePx: 1, viewportPx: [1280, 720], budgetMs: 8 });
        mirror.take();
        assert.ok(session.checkCut().ok);
        await sleep(2);
      }
    }
    const st = await stream(session, mirror, good, {});
    assert.ok(st.fullQuality && Number.isFinite(st.bytesPerS));
  } finally {
    session.close();
  }
});

test("a planet with its colour layer reaches full quality crack-free in heights and colour", async () => {
  if (!ready("planet with colour")) return;
  const counting = countingFetch();
  const session = await Session.open(server.base, "earth", { colour: "earth_colour", maxInFlight: 2, fetch: counting });
  try {
    assert.equal(session.domain, "sphere");
    assert.equal(session.colourN, 64);
    const mirror = new Mirror(session);
    for (const camera of [
      planetCamera(session, 37.5, 127, 2_000_000),
      // Low over the Himalaya: the colour is refined procedurally below its levels.
      planetCamera(session, 27.9, 86.9, 20_000, -20, 45),
    ]) {
      // The bound is per repository, as in the native client: 2 + 2.
      const st = await stream(session, mirror, camera, { maxInFlight: 4 });
      assert.equal(st.errors.total, 0, st.lastError);
      assertMeetsTolerance(session);
      const c = session.checkCut();
      assert.ok(c.ok && c.colourShared > 0 && c.colourCracks === 0, JSON.stringify(c));
    }
    assert.ok(counting.peak <= 4, `${counting.peak} requests at once`);
    for (const p of mirror.patches.values()) {
      assert.ok(p.colour !== null && p.colour.length === 3 && p.colour[0].length === 65 * 65);
    }
    const rgb = session.colourLayer.rgb([...mirror.patches.values()][0].colour, 0);
    assert.ok(rgb.every((x) => Number.isInteger(x) && x >= 0 && x <= 255));
    const g = session.heightAt(planetCamera(session, 27.9, 86.9, 20_000).position);
    assert.ok(g > 1000 && g < 9000, `ground ${g} m under the Himalaya`);
  } finally {
    session.close();
  }
});

test("moving the camera away coarsens and frees nodes", async () => {
  if (!ready("coarsening")) return;
  const session = await Session.open(server.base, "korea", { maxInFlight: 8 });
  try {
    const mirror = new Mirror(session);
    await stream(session, mirror, planarCamera(session, 0.3, 0.7, 1000, -30), { done: converged, budgetMs: 50 });
    const near = session.stats();
    const left = mirror.left;
    await stream(session, mirror, planarCamera(session, 0.5, 0.5, 300_000), { done: converged, budgetMs: 50 });
    const far = session.stats();
    assert.ok(far.dagNodes < near.dagNodes / 2, `${near.dagNodes} -> ${far.dagNodes} nodes`);
    assert.ok(far.dagBytes < near.dagBytes && far.patches < near.patches);
    assert.ok(mirror.left > left, "patches left the cut");
  } finally {
    session.close();
  }
});

test("a cut budget is never exceeded, and shrinking it coarsens at once", async () => {
  if (!ready("cut budget")) return;
  const session = await Session.open(server.base, "korea", {});
  try {
    const mirror = new Mirror(session);
    const camera = planarCamera(session, 0.3, 0.7, 1000, -20);
    session.setMaxCutHalves(160);
    const within = (max) => (s) => {
      assert.ok(s.patches <= max && mirror.patches.size <= max, `${s.patches} halves over ${max}`);
      return s.settled && s.frame.converged;
    };
    const st = await stream(session, mirror, camera, { done: within(160), budgetMs: 50 });
    assert.ok(st.budgetLimited && !st.fullQuality && st.patches > 100, JSON.stringify(st));
    session.setMaxCutHalves(60);
    session.update(camera, { tolerancePx: 1, viewportPx: [1280, 720], budgetMs: 200 });
    mirror.take();
    assert.ok(session.stats().patches <= 60, `${session.stats().patches} halves`);
    await stream(session, mirror, camera, { done: within(60), budgetMs: 50 });
    session.setMaxCutHalves(null);
    const free = await stream(session, mirror, camera, { done: converged, budgetMs: 50 });
    assert.ok(free.fullQuality && free.patches > 160, `${free.patches} halves without a budget`);
  } finally {
    session.close();
  }
});

test("corrupt and failing answers become errors in stats, not exceptions", async () => {
  if (!ready("corrupt answers")) return;
  // Every answer of one diamond (the first level-1 diamond asked for) is corrupt: its
  // blob fails its checksum, for ever.
  let victim = null;
  const corrupt = countingFetch(async (url, resp) => {
    const m = /\/v\/[0-9a-f]{16}\/[dp]\/(\d+\/\d+)$/.exec(url);
    if (!m || resp.status !== 200) return resp;
    const body = new Uint8Array(await resp.arrayBuffer());
    if (victim === null && m[1] !== "512/512") victim = m[1];
    if (m[1] === victim && body.length > 8) body[body.length >> 1] ^= 0x5a;
    return new Response(body, { status: 200 });
  });
  const session = await Session.open(server.base, "korea", { maxInFlight: 4, fetch: corrupt });
  try {
    const mirror = new Mirror(session);
    const camera = planarCamera(session, 0.5, 0.5, 20_000);
    const t0 = performance.now();
    await stream(session, mirror, camera, { done: () => performance.now() - t0 > 4000 });
    const st = session.stats();
    assert.ok(st.errors.decode > 0, JSON.stringify(st.errors));
    assert.match(st.lastError, /decode/);
    assert.ok(!st.fullQuality, "a diamond without its data cannot be at full quality");
    assert.ok(st.patches > 2, "the rest of the view refined");
  } finally {
    session.close();
  }

  // Server errors and dropped connections on first attempts are retried.
  const seen = new Set();
  const flaky = countingFetch(async (url, resp) => {
    if (!url.includes("/v/") || seen.has(url)) return resp;
    seen.add(url);
    if (seen.size % 3 === 0) throw new TypeError("fetch failed (connection reset)");
    if (seen.size % 3 === 1) return new Response("busy", { status: 503 });
    return resp;
  });
  const retried = await Session.open(server.base, "korea", { maxInFlight: 4, fetch: flaky });
  try {
    const st = await stream(retried, new Mirror(retried), planarCamera(retried, 0.5, 0.5, 30_000), {});
    assert.ok(st.fullQuality);
    assert.ok(st.errors.serverStatus > 0 && st.errors.connection > 0, JSON.stringify(st.errors));
  } finally {
    retried.close();
  }

  // Unusable metadata is an error at open.
  const bad = async (url) => (String(url).endsWith("metadata.json") ? new Response("{\"domain\": 7}") : fetch(url));
  await assert.rejects(Session.open(server.base, "korea", { fetch: bad }), SessionError);
  await assert.rejects(Session.open(server.base, "nope"), SessionError);
  await assert.rejects(Session.open(server.base, "../etc"), SessionError);
  await assert.rejects(Session.open(server.base, "earth_colour"), /colour layer/);
  await assert.rejects(Session.open(server.base, "korea", { colour: "earth_colour" }), /domain/);
});

test("a static export's 404s are leaves", async () => {
  if (!ready("static export")) return;
  const dir = mkdtempSync(join(tmpdir(), "quincunx-client-export-"));
  let missing = 0;
  const files = createServer((req, res) => {
    const path = normalize(join(dir, decodeURIComponent(new URL(req.url, "http://x").pathname)));
    if (!path.startsWith(dir) || !existsSync(path) || !statSync(path).isFile()) {
      missing += 1;
      res.writeHead(404).end("not found");
      return;
    }
    res.writeHead(200, { "content-type": "application/octet-stream" }).end(readFileSync(path));
  });
  try {
    execFileSync(BIN, ["export", REPOS.korea, dir, "--name", "korea"], { stdio: "ignore" });
    // A blob the view needs is missing too: a static export cannot tell that 404 from an
    // empty blob's, so it is a leaf (coarser there, no error).
    const meta = JSON.parse(readFileSync(join(dir, "repos", "korea", "metadata.json"), "utf8"));
    const version = join(dir, "repos", "korea", "v", meta.content_hash.slice(0, 16));
    for (const kind of ["d", "p"]) rmSync(join(version, kind, "768", "256"), { force: true });
    await new Promise((r) => files.listen(0, "127.0.0.1", r));
    const base = `http://127.0.0.1:${files.address().port}`;
    const session = await Session.open(base, "korea", { maxInFlight: 6 });
    try {
      assert.equal(session.meta.static_export, true);
      const st = await stream(session, new Mirror(session), planarCamera(session, 0.5, 0.5, 30_000), {});
      assert.equal(st.errors.total, 0, st.lastError);
      assert.ok(missing > 0 && st.leaves > 0 && st.leaves <= missing, `${missing} 404s, ${st.leaves} leaves`);
      assert.ok(st.fullQuality);
    } finally {
      session.close();
    }
  } finally {
    files.close();
    rmSync(dir, { recursive: true, force: true });
  }
});

// The Web Worker API over worker_threads: `self`, `postMessage`, `onmessage`, and
// messages held until the module has set its handler (as a browser does).
const SHIM = `
const { parentPort, workerData } = require("node:worker_threads");
globalThis.WorkerGlobalScope = class WorkerGlobalScope {};
const scope = Object.create(WorkerGlobalScope.prototype);
globalThis.self = scope;
let handler = null;
const held = [];
Object.defineProperty(scope, "onmessage", {
  get: () => handler,
  set: (f) => { handler = f; for (const data of held.splice(0)) handler({ data }); },
});
scope.postMessage = (msg, transfer) => parentPort.postMessage(msg, transfer);
parentPort.on("message", (data) => (handler ? handler({ data }) : held.push(data)));
import(workerData.url);
`;

class ShimWorker {
  constructor(url) {
    this._w = new NodeWorker(SHIM, { eval: true, workerData: { url: String(url) } });
    this._w.on("message", (data) => this.onmessage?.({ data }));
    this._w.on("error", (e) => this.onerror?.(e));
    ShimWorker.started += 1;
  }
  postMessage(msg, transfer) {
    this._w.postMessage(msg, transfer);
  }
  terminate() {
    this._w.terminate();
  }
}
ShimWorker.started = 0;

test("decoding in workers gives the cut decoding inline gives", async () => {
  if (!ready("workers")) return;
  const cutOf = async (workers) => {
    const session = await Session.open(server.base, "earth", { colour: "earth_colour", workers });
    try {
      const camera = planetCamera(session, -60, -30, 20_000_000);
      const mirror = new Mirror(session);
      await stream(session, mirror, camera, { done: converged, budgetMs: 200, check: false });
      return [session.workers, [...mirror.patches.keys()].sort()];
    } finally {
      session.close();
    }
  };
  globalThis.Worker = ShimWorker;
  let inWorkers;
  try {
    inWorkers = await cutOf(2);
  } finally {
    delete globalThis.Worker;
  }
  const inline = await cutOf(0);
  assert.equal(ShimWorker.started, 2);
  assert.equal(inWorkers[0], 2);
  assert.equal(inline[0], 0);
  assert.deepEqual(inWorkers[1], inline[1]);
  assert.ok(inline[1].length > 100);
});
