// The planar side of the JavaScript decoder (js/lifting.mjs, js/coverage.mjs,
// js/planar.mjs) against the Rust code:
// - ids, keys, hierarchy, positions, raster frames (coded diamonds, masks, children,
//   owned children), one-diamond lifting and parent-to-child maps equal the vectors
//   codec/tests/js_planar_vectors.rs writes (test/golden/planar-*.json);
// - whole repositories decoded through PlanarRefiner hash like `quincunx verify --json`'s
//   `decoded_sha256`: the bundled korea export ($QUINCUNX_EXPORT_DIR/repos/korea, default
//   /work/export; repository in $QUINCUNX_DEMO_DIR, default /work/demo), and repositories
//   built here from data/ (a sparse one with holes, a colour one). Skipped (SKIP lines)
//   when the binary ($QUINCUNX_BIN or target/release/quincunx) or the data is absent.

import { test } from "node:test";
import assert from "node:assert/strict";
import { createHash } from "node:crypto";
import { execFileSync } from "node:child_process";
import { existsSync, mkdtempSync, readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

import { DecodeError } from "../js/codec.mjs";
import { BlockState, Coverage } from "../js/coverage.mjs";
import { DiamondMask, analyze, childHalf, GridMap, scatterToChild, synthesize, synthesizeZero } from "../js/lifting.mjs";
import { IdError, PlanarDomain, PlanarId, PlanarRefiner, RefineError, reconstructPlanar } from "../js/planar.mjs";

const here = dirname(fileURLToPath(import.meta.url));
const workspace = join(here, "..", "..");
const golden = (name) => JSON.parse(readFileSync(join(here, "golden", name), "utf8"));
const hex = (bytes) => [...bytes].map((b) => b.toString(16).padStart(2, "0")).join("");
const xy = (id) => [id.x, id.y];
const xys = (list) => list.map(xy);

// ---------------------------------------------------------------------------------------
// Geometry.

test("planar ids, keys, hierarchy and positions equal the Rust vectors", () => {
  const { domains } = golden("planar-geometry.json");
  let checked = 0;
  for (const g of domains) {
    const d = new PlanarDomain(g.m);
    assert.equal(d.size(), g.size);
    assert.equal(d.maxLevel(), g.max_level);
    assert.deepEqual(xy(d.root()), g.root);
    for (const v of g.ids) {
      const id = new PlanarId(v.c[0], v.c[1]);
      const at = `m ${g.m} id ${v.c}`;
      assert.equal(d.level(id), v.level, at);
      assert.equal(d.halfExtent(id), v.half_extent, at);
      assert.equal(hex(d.key(id)), v.key, at);
      assert.deepEqual(xy(d.idFromKey(d.key(id))), v.c, at);
      assert.deepEqual(d.corners(id), v.corners, at);
      assert.deepEqual(xys(d.parents(id)), v.parents, at);
      assert.deepEqual(xys(d.children(id)), v.children, at);
      assert.deepEqual(d.neighbours(id).map((x) => (x === null ? null : xy(x))), v.neighbours, at);
      assert.equal(d.isHalf(id), v.is_half, at);
      const n = v.n;
      assert.deepEqual(
        [d.vertexPosition(id, n, 0, 0), d.vertexPosition(id, n, n / 2, Math.floor(n / 3) + 1)],
        v.vertex,
        at,
      );
      assert.deepEqual(
        [d.cellPosition(id, n, 0, 0), d.cellPosition(id, n, n - 1, Math.floor(n / 4))],
        v.cell,
        at,
      );
      checked++;
    }
    for (const p of g.rejected) assert.throws(() => d.check(new PlanarId(p[0], p[1])), IdError, `m ${g.m} ${p}`);
    for (const k of g.bad_keys) {
      const key = Uint8Array.from(k.match(/../g) ?? [], (b) => parseInt(b, 16));
      assert.throws(() => d.idFromKey(key), IdError, `m ${g.m} key ${k}`);
    }
    for (const q of g.meeting) assert.deepEqual(xys(d.diamondsMeeting(q.level, q.rect)), q.ids, `m ${g.m} ${q.rect}`);
  }
  assert.ok(checked > 80, `${checked} ids`);
});

/** FNV-1a (32 bits) of a mask's vertex then cell flags (as the Rust vector writer). */
function maskHash(m) {
  let h = 0x811c9dc5;
  for (const bytes of [m.vertices(), m.cells()]) {
    for (const b of bytes) h = Math.imul(h ^ b, 0x01000193) >>> 0;
  }
  return h.toString(16).padStart(8, "0");
}

test("raster frames: coded diamonds, keys, masks, children and owned children equal the Rust vectors", () => {
  const { frames } = golden("planar-frames.json");
  for (const f of frames) {
    const coverage = f.coverage === null ? null : Coverage.fromBytes(f.coverage);
    if (coverage) assert.deepEqual([...coverage.toBytes()], f.coverage);
    const levels = f.detail_levels;
    const r = new PlanarRefiner(f.width, f.height, f.n, coverage, new Array(levels).fill(256), null,
      new Int32Array((f.n + 1) ** 2));
    assert.equal(r.detailLevels(), levels);
    assert.equal(r.domain().m(), f.m);
    assert.equal(r.levels(), levels);
    let masked = 0;
    for (const v of f.diamonds) {
      const id = new PlanarId(v.c[0], v.c[1]);
      const at = `${f.width}x${f.height} N=${f.n} id ${v.c}`;
      assert.equal(r.isCoded(id), v.coded, at);
      assert.equal(r.isRefinable(id), v.refinable, at);
      const info = r.info(id);
      if (v.level === undefined) {
        assert.equal(info, null, at);
        continue;
      }
      assert.equal(info.level, v.level, at);
      assert.equal(hex(info.key), v.key, at);
      assert.equal(info.procedural, false);
      if (v.mask === null) assert.equal(info.mask, null, at);
      else {
        masked++;
        assert.equal(info.mask.validCells(), v.mask.valid_cells, at);
        assert.equal(maskHash(info.mask), v.mask.hash, at);
      }
      assert.deepEqual(xys(info.children), v.children, at);
      assert.deepEqual(xys(r._ownedChildren(id, info.level)), v.owned, at);
      const [, slot] = r._slot(id);
      assert.deepEqual(slot.frame(), v.frame, at);
      assert.equal(r.geometry().slotContext(info.level, slot, v.owned.length).group, v.group, at);
    }
    assert.ok(masked > 0 || f.width === 1025, `${f.width}x${f.height}: masks checked`);
  }
});

// ---------------------------------------------------------------------------------------
// Lifting.

test("one-diamond synthesis, zero synthesis and analysis equal the Rust vectors", () => {
  const { cases } = golden("planar-lifting.json");
  for (const c of cases) {
    const { n } = c;
    const at = `n ${n} ${c.mask ? "masked" : "full"}`;
    const mask = c.mask ? new DiamondMask(n, Uint8Array.from(c.mask.vertex), Uint8Array.from(c.mask.cell)) : null;
    const v = Int32Array.from(c.v);
    const cells = new Int32Array(n * n).fill(7);
    synthesize(n, v, Int32Array.from(c.h), cells, mask);
    assert.deepEqual([...v], c.v_out, at);
    assert.deepEqual([...cells], c.c_out, at);
    const zero = new Int32Array(n * n).fill(9);
    const v0 = Int32Array.from(c.v);
    synthesizeZero(n, v0, zero, mask);
    assert.deepEqual([...zero], c.c_zero, at);
    assert.deepEqual([...v0], c.v, `${at}: synthesizeZero leaves the vertices`);
    const va = Int32Array.from(c.v);
    const h = new Int32Array(n * n);
    analyze(n, va, Int32Array.from(c.c_out), h, mask);
    assert.deepEqual([...va], c.analyze_v, at);
    assert.deepEqual([...h], c.analyze_h, at);
  }
});

test("child_half maps equal the Rust vectors", () => {
  const { maps } = golden("planar-lifting.json");
  const domains = new Map();
  for (const g of maps) {
    if (!domains.has(g.m)) domains.set(g.m, new PlanarDomain(g.m));
    const d = domains.get(g.m);
    const parent = new PlanarId(...g.parent);
    const child = new PlanarId(...g.child);
    const map = childHalf(d.corners(parent), d.corners(child), g.n);
    const got = map === null ? null : [map.map(0, 0), map.map(1, 0), map.map(0, 1)];
    assert.deepEqual(got, g.map, `m ${g.m} parent ${g.parent} child ${g.child}`);
  }
});

test("scatterToChild writes exactly what the definition says, for every map shape", () => {
  const n = 8;
  const w = n + 1;
  const v = Int32Array.from({ length: w * w }, (_, k) => k);
  const c = Int32Array.from({ length: n * n }, (_, k) => 1000 + k);
  let maps = 0;
  for (const dpi of [-1, 0, 1]) for (const dqi of [-1, 0, 1]) for (const dpj of [-1, 0, 1]) for (const dqj of [-1, 0, 1]) {
    for (const p0 of [-2 * n, -3, 0, 1, n, 2 * n, 3 * n]) {
      for (const q0 of [-1, 0, 2, n + 1, 2 * n]) {
        const map = new GridMap(p0, q0, dpi, dqi, dpj, dqj);
        const want = new Int32Array(w * w).fill(-1);
        const wantWritten = new Uint8Array(w * w);
        for (let i = 0; i <= n; i++) {
          for (let j = 0; j <= n; j++) {
            const [p, q] = map.map(i, j);
            if (p < 0 || p > 2 * n || q < 0 || q > 2 * n || (p - q) % 2 !== 0) continue;
            want[i * w + j] = p % 2 === 0 ? v[(p / 2) * w + q / 2] : c[((p - 1) / 2) * n + (q - 1) / 2];
            wantWritten[i * w + j] = 1;
          }
        }
        const got = new Int32Array(w * w).fill(-1);
        const written = new Uint8Array(w * w);
        const count = scatterToChild(map, n, v, c, got, written);
        const at = JSON.stringify(map);
        assert.deepEqual(got, want, at);
        assert.deepEqual(written, wantWritten, at);
        assert.equal(count, wantWritten.reduce((s, x) => s + x, 0), at);
        maps++;
      }
    }
  }
  assert.equal(maps, 81 * 35);
});

test("childHalf is exact beyond 2^53 (BigInt path) and refuses non-parents", () => {
  const d = new PlanarDomain(48);
  let id = d.root();
  for (let k = 0; k < 90; k++) id = d.children(id)[k % 2];
  for (const child of d.children(id)) {
    for (const p of d.parents(child)) assert.notEqual(childHalf(d.corners(p), d.corners(child), 512), null);
    assert.equal(childHalf(d.corners(d.root()), d.corners(child), 512), null);
  }
});

// ---------------------------------------------------------------------------------------
// Coverage.

test("coverage bytes round-trip, hostile bytes throw DecodeError, states match a block-by-block count", () => {
  // 6 faces of 37 x 37 blocks of 8 samples, a pattern that straddles bytes.
  const faces = 6, side = 37, log2 = 3;
  const count = faces * side * side;
  const bits = new Uint8Array(Math.ceil(count / 8));
  let seed = 11;
  const next = (m) => {
    seed = (Math.imul(seed, 1103515245) + 12345) >>> 0;
    return (seed >>> 8) % m;
  };
  for (let f = 0; f < faces; f++) for (let r = 0; r < side; r++) for (let col = 0; col < side; col++) {
    const on = f === 0 || (f === 2 ? (Math.floor(col / 9) + Math.floor(r / 5)) % 2 === 0 : f > 2 && next(100) < 60 + 10 * f);
    if (on) {
      const k = (f * side + r) * side + col;
      bits[k >> 3] |= 1 << (k & 7);
    }
  }
  const bytes = new Uint8Array(11 + bits.length);
  bytes.set([1, faces, log2]);
  new DataView(bytes.buffer).setUint32(3, side, true);
  new DataView(bytes.buffer).setUint32(7, side, true);
  bytes.set(bits, 11);
  const cov = Coverage.fromBytes(bytes);
  assert.deepEqual(cov.toBytes(), bytes);
  for (let len = 0; len < bytes.length; len++) assert.throws(() => Coverage.fromBytes(bytes.subarray(0, len)), DecodeError);
  assert.throws(() => Coverage.fromBytes([...bytes, 0]), DecodeError);
  const huge = bytes.slice();
  huge.set([255, 255, 255, 255], 3);
  assert.throws(() => Coverage.fromBytes(huge), DecodeError);

  const naive = (face, [x0, x1], [y0, y1]) => {
    let anyIn = false, anyOut = false;
    if (x0 <= x1 && y0 <= y1) {
      const lo = (t) => (t === 0 ? 0 : (t - 1) >> log2);
      const hi = (t, cnt) => Math.min(t >> log2, cnt - 1);
      for (let r = Math.min(lo(y0), side - 1); r <= hi(y1, side); r++) {
        for (let col = Math.min(lo(x0), side - 1); col <= hi(x1, side); col++) {
          if (cov.isCovered(face, col, r)) anyIn = true;
          else anyOut = true;
        }
      }
    }
    return anyIn && !anyOut ? BlockState.Full : !anyIn ? BlockState.Empty : BlockState.Mixed;
  };
  const samples = side * 8;
  const seen = [0, 0, 0];
  for (let t = 0; t < 5000; t++) {
    const face = next(6);
    const x0 = next(samples + 1), y0 = next(samples + 1);
    const x1 = x0 + next(samples + 1 - x0), y1 = y0 + next(samples + 1 - y0);
    const rect = next(10) === 0 ? [x1, x0] : [x0, x1];
    const want = naive(face, rect, [y0, y1]);
    assert.equal(cov.state(face, rect, [y0, y1]), want, `${face} ${rect} ${y0} ${y1}`);
    seen[want]++;
  }
  assert.ok(seen.every((k) => k > 20), `${seen}`);
  // Closed blocks share their border samples.
  for (let t = 0; t < 2000; t++) {
    const face = next(6), x = next(samples + 1), y = next(samples + 1);
    const near = (s) => [s >> log2, ...(s > 0 && s % 8 === 0 ? [(s >> log2) - 1] : [])];
    const want = near(x).some((col) => near(y).some((r) => cov.isCovered(face, col, r)));
    assert.equal(cov.coversPoint(face, x, y), want, `${face} ${x} ${y}`);
  }
});

// ---------------------------------------------------------------------------------------
// Refiner errors.

test("the refiner refuses what is not refinable, not a parent, or incomplete", () => {
  const r = new PlanarRefiner(100, 37, 8, null, new Array(8).fill(256), null, new Int32Array(81));
  const d = r.domain();
  const [root, grid] = r.root();
  const refined = r.synthesize(root, grid, null);
  const child = r.info(root).children[0];
  const other = d.children(child)[0];
  assert.throws(() => r.synthesize(new PlanarId(d.size(), d.size()), grid, null), DecodeError);
  assert.throws(() => r.synthesize(root, new Int32Array(5), null), RefineError);
  assert.throws(() => r.partialChildGrid(other, [refined]), RefineError);
  const [half, written] = r.partialChildGrid(child, [refined]);
  assert.equal(half.length, 81);
  assert.ok(written.some((b) => b));
  assert.deepEqual(r.childGrid(child, [refined]), half, "a border half diamond has one parent");
  // A diamond inside the raster with two parents: one parent's lattice is not enough.
  const big = new PlanarRefiner(300, 200, 8, null, new Array(10).fill(256), null, new Int32Array(81));
  const bd = big.domain();
  let inner = null;
  for (let level = 1, ids = big.info(big.root()[0]).children; inner === null && level < 6; level++) {
    inner = ids.find((c) => big.info(c).mask === null && bd.parents(c).length === 2) ?? null;
    ids = ids.flatMap((c) => big.info(c).children);
  }
  assert.ok(inner, "an inner diamond");
  const [p1, p2] = bd.parents(inner).map((p) => big.synthesize(p, new Int32Array(81), null));
  assert.throws(() => big.childGrid(inner, [p1]), RefineError, "one parent of two is missing");
  const [part, some] = big.partialChildGrid(inner, [p1]);
  assert.ok(some.some((b) => b) && !some.every((b) => b));
  assert.equal(part.length, 81);
  assert.equal(big.childGrid(inner, [p1, p2]).length, 81);
  assert.throws(() => r.decode(new PlanarId(d.size(), d.size()), new Uint8Array(4)), RefineError);
  // Points outside the domain are no diamonds, whatever was looked at before.
  const S = d.size();
  assert.notEqual(r.info(new PlanarId(S / 2, 0)), null);
  for (const p of [[S / 2 - 1, S + 1], [-1, 5], [0.5, 3], [S + 1, 0]]) {
    assert.equal(r.info(new PlanarId(...p)), null, `${p}`);
    assert.equal(r.isRefinable(new PlanarId(...p)), false, `${p}`);
  }
});

// ---------------------------------------------------------------------------------------
// Whole repositories against `quincunx verify --json`.

const bin = process.env.QUINCUNX_BIN || join(workspace, "target", "release", "quincunx");
const demoDir = process.env.QUINCUNX_DEMO_DIR || "/work/demo";
const exportDir = process.env.QUINCUNX_EXPORT_DIR || "/work/export";

/** Reads a static export's metadata and blob files (a missing file is a leaf). */
function openExport(dir) {
  const meta = JSON.parse(readFileSync(join(dir, "metadata.json"), "utf8"));
  const version = meta.content_hash.slice(0, 16);
  const cache = new Map();
  const getBlob = ([x, y]) => {
    const key = `${x}/${y}`;
    if (!cache.has(key)) {
      const path = join(dir, "v", version, "d", String(x), String(y));
      cache.set(key, existsSync(path) ? new Uint8Array(readFileSync(path)) : null);
    }
    return cache.get(key);
  };
  return { meta, getBlob };
}

/** SHA-256 of the canonical layout: per point, its channels' i32 little-endian. */
function canonicalSha256(channels) {
  const count = channels.length;
  const len = channels[0].length;
  const out = new Int32Array(len * count);
  for (let c = 0; c < count; c++) for (let k = 0; k < len; k++) out[k * count + c] = channels[c][k];
  const bytes = new Uint8Array(out.buffer);
  if (new Uint8Array(new Uint32Array([1]).buffer)[0] !== 1) {
    for (let k = 0; k < bytes.length; k += 4) bytes.subarray(k, k + 4).reverse();
  }
  return createHash("sha256").update(bytes).digest("hex");
}

function verifySha(repo) {
  const report = JSON.parse(execFileSync(bin, ["verify", repo, "--json"], { encoding: "utf8" }));
  assert.equal(report.blob_errors, 0);
  assert.ok(report.decoded_sha256, "verify --json prints decoded_sha256");
  return report.decoded_sha256;
}

/** Reconstructs an export through the refiner; checks the hash; returns the timing. */
function checkExport(name, repo, dir) {
  const { meta, getBlob } = openExport(dir);
  assert.equal(meta.domain, "planar");
  let channels = reconstructPlanar(meta, getBlob); // reads every file once (and warms up)
  let seconds = Infinity;
  for (let run = 0; run < 3; run++) {
    const started = performance.now();
    channels = reconstructPlanar(meta, getBlob);
    seconds = Math.min(seconds, (performance.now() - started) / 1000);
  }
  const [w, h] = meta.extent;
  assert.equal(channels.length, meta.channels.length);
  for (const c of channels) assert.equal(c.length, w * h);
  assert.equal(canonicalSha256(channels), verifySha(repo), `${name}: JS reconstruction differs from Rust's`);
  const rate = (w * h * channels.length) / seconds / 1e6;
  console.log(`${name}: ${w}x${h}x${channels.length} reconstructed in ${(seconds * 1000).toFixed(0)} ms (best of 3), ${rate.toFixed(1)} M samples/s`);
  return { meta, channels };
}

test("the korea export reconstructs to the Rust decoder's hash", () => {
  const dir = join(exportDir, "repos", "korea");
  const repo = join(demoDir, "korea");
  if (!existsSync(bin)) return console.log(`SKIP korea: no binary at ${bin}`);
  if (!existsSync(join(dir, "metadata.json"))) return console.log(`SKIP korea: no export at ${dir}`);
  if (!existsSync(repo)) return console.log(`SKIP korea: no repository at ${repo}`);
  checkExport("korea", repo, dir);
});

/** Builds and exports a repository from data/ into a temporary directory. */
function buildExport(name, args) {
  const tmp = mkdtempSync(join(tmpdir(), `quincunx-planar-${name}-`));
  const repo = join(tmp, name);
  execFileSync(bin, ["build", ...args, "-o", repo], { stdio: "ignore" });
  execFileSync(bin, ["export", repo, join(tmp, "x"), "--name", name], { stdio: "ignore" });
  return { tmp, repo, dir: join(tmp, "x", "repos", name) };
}

test("a sparse planar repository (holes, raster edges, N = 8) reconstructs to the Rust decoder's hash", () => {
  const source = join(workspace, "data", "fixture_gsi_dem_256.json");
  if (!existsSync(bin)) return console.log(`SKIP sparse: no binary at ${bin}`);
  if (!existsSync(source)) return console.log(`SKIP sparse: no ${source}`);
  const { tmp, repo, dir } = buildExport("gsi_sparse", [source, "--sparse", "--diamond-size", "9", "--max-error-m", "0.1"]);
  try {
    const { meta, channels } = checkExport("gsi_sparse", repo, dir);
    const cov = Coverage.fromBytes(meta.coverage);
    assert.ok(cov.coveredBlocks() < cov.blocks(), "the repository has holes");
    // Points in no covered block decode to 0 (unless a root vertex lies there).
    const [w] = meta.extent;
    let holes = 0;
    for (let k = 0; k < channels[0].length; k++) {
      if (!cov.coversPoint(0, k % w, Math.floor(k / w))) {
        holes++;
        if (channels[0][k] !== 0) assert.equal((k % w) % 32 + Math.floor(k / w) % 32, 0, `point ${k}`);
      }
    }
    assert.ok(holes > 0);
  } finally {
    rmSync(tmp, { recursive: true, force: true });
  }
});

test("a colour planar repository (3 channels framed per blob) reconstructs to the Rust decoder's hash", () => {
  const source = join(workspace, "data", "fixture_gsi_color_256.jpg");
  if (!existsSync(bin)) return console.log(`SKIP colour: no binary at ${bin}`);
  if (!existsSync(source)) return console.log(`SKIP colour: no ${source}`);
  const { tmp, repo, dir } = buildExport("gsi_colour", [source, "--colour", "--rms-m", "2"]);
  try {
    const { channels } = checkExport("gsi_colour", repo, dir);
    assert.equal(channels.length, 3);
  } finally {
    rmSync(tmp, { recursive: true, force: true });
  }
});

test("hostile metadata and blobs throw DecodeError", () => {
  const dir = join(exportDir, "repos", "korea");
  if (!existsSync(join(dir, "metadata.json"))) return console.log(`SKIP hostile: no export at ${dir}`);
  const { meta, getBlob } = openExport(dir);
  const channel = meta.channels[0];
  const broken = [
    { ...meta, domain: "sphere" },
    { ...meta, channels: [] },
    { ...meta, levels: meta.levels + 1 },
    { ...meta, m: meta.m + 1 },
    { ...meta, n: 33 },
    { ...meta, extent: [0, 5] },
    { ...meta, extent: [2 ** 25, 5] },
    { ...meta, coverage: [1, 2, 3] },
    { ...meta, channels: [{ ...channel, roots: [[1, 2, 3]] }] },
    { ...meta, channels: [{ ...channel, roots: [] }] },
    { ...meta, channels: [{ ...channel, roots: [channel.roots[0].map(() => 0.5)] }] },
    { ...meta, channels: [{ ...channel, steps: ["a"] }] },
    { ...meta, channels: [{ ...channel, model: [1, 2, 3] }] },
  ];
  for (const m of broken) {
    assert.throws(() => PlanarRefiner.fromMetadata(m), DecodeError, JSON.stringify(m).slice(0, 80));
    assert.throws(() => reconstructPlanar(m, getBlob), DecodeError);
  }
  assert.throws(() => PlanarRefiner.fromMetadata(meta, 1), DecodeError, "no channel 1");
  // A damaged blob anywhere is an error, never a wrong picture.
  const root = PlanarRefiner.fromMetadata(meta).root()[0];
  for (const flip of [0, 1, 5, -1]) {
    const damaged = ([x, y]) => {
      const b = getBlob([x, y]);
      if (b === null || x !== root.x || y !== root.y) return b;
      const copy = b.slice();
      copy[(flip + copy.length) % copy.length] ^= 0x10;
      return copy;
    };
    assert.throws(() => reconstructPlanar(meta, damaged), DecodeError, `byte ${flip}`);
  }
  assert.throws(() => reconstructPlanar(meta, ([x, y]) => getBlob([x, y])?.subarray(0, 2) ?? null), DecodeError);
});
