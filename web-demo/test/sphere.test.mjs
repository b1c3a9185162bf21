// Tests of web-demo/js/sphere.mjs (the planet side) against the Rust code:
// - vectors written by codec/tests/js_sphere_vectors.rs (web-demo/test/golden/sphere-*.json:
//   ids, keys, hierarchy, positions; slots and masks; small planets with the cube rasters
//   of the whole-planet decoder; bulky values as SHA-256 of little-endian bytes, byte
//   strings in base64, masks in hex: see the Rust file's header);
// - the bundled planets' static exports (/work/export/repos/{earth,earth_colour}, or
//   $QUINCUNX_EXPORT_DIR/repos/...) reconstructed through the refiner, hashed in the
//   canonical layout and compared with `quincunx verify <repo> --json`'s decoded_sha256
//   (repositories in /work/demo or $QUINCUNX_DEMO_DIR; binary target/release/quincunx or
//   $QUINCUNX_BIN). Tests whose data is absent print `SKIP <name>: <reason>`.

import assert from "node:assert/strict";
import { spawnSync } from "node:child_process";
import { createHash } from "node:crypto";
import { existsSync, readFileSync, readdirSync } from "node:fs";
import { dirname, join } from "node:path";
import { test } from "node:test";
import { fileURLToPath } from "node:url";

import { DecodeError } from "../js/codec.mjs";
import {
  IdError,
  RefineError,
  SphereDomain,
  SphereFrame,
  SphereId,
  SphereRefiner,
  cubeToUnitSphere,
  planetPoint,
  reconstructSphere,
  unitSphereToCube,
} from "../js/sphere.mjs";
import { Coverage } from "../js/coverage.mjs";

const here = dirname(fileURLToPath(import.meta.url));
const golden = (name) => JSON.parse(readFileSync(join(here, "golden", name), "utf8"));
const hex = (bytes) => Buffer.from(bytes).toString("hex");
const fromHex = (text) => new Uint8Array(Buffer.from(text, "hex"));
const fromBase64 = (text) => new Uint8Array(Buffer.from(text, "base64"));
const ids = (list) => list.map((id) => id.c);
const id = (c) => new SphereId(c);

// The encodings of the golden files (codec/tests/js_sphere_vectors.rs).
const sha256 = (bytes) => createHash("sha256").update(bytes).digest("hex");
/// Little-endian bytes of integers, `width` bytes each (4: u32 or i32, 8: i64 as safe integers).
function leBytes(values, width, signed) {
  const view = new DataView(new ArrayBuffer(values.length * width));
  values.forEach((v, k) => {
    if (!Number.isSafeInteger(v)) throw new Error(`not an integer: ${v}`);
    if (width === 8) view.setBigInt64(k * width, BigInt(v), true);
    else if (signed) view.setInt32(k * width, v, true);
    else view.setUint32(k * width, v, true);
  });
  return new Uint8Array(view.buffer);
}
/// A string of 0 and 1 in hex: four bits a digit, first bit highest, the last padded with 0.
const bitsHex = (bits) => (bits.match(/.{1,4}/g) ?? []).map((b) => parseInt(b.padEnd(4, "0"), 2).toString(16)).join("");
/// sphere-planets.json with the metadata as a repository has it (byte strings as lists of
/// numbers) and the blobs decoded.
function goldenPlanets() {
  return golden("sphere-planets.json").map((p) => ({
    ...p,
    metadata: {
      ...p.metadata,
      coverage: p.metadata.coverage === null ? null : [...fromBase64(p.metadata.coverage)],
      channels: p.metadata.channels.map((c) => ({ ...c, model: [...fromBase64(c.model)] })),
    },
    blobs: Object.fromEntries(Object.entries(p.blobs).map(([k, b]) => [k, fromBase64(b)])),
  }));
}

test("sphere ids, keys, hierarchy and positions equal the Rust domain's", () => {
  const { domains } = golden("sphere-geometry.json");
  let checked = 0;
  for (const g of domains) {
    const d = new SphereDomain(g.m);
    assert.equal(d.size(), g.size);
    assert.equal(d.maxLevel(), g.max_level);
    assert.deepEqual(ids(d.roots()), g.roots);
    for (const v of g.ids) {
      const x = id(v.c);
      const what = `m=${g.m} ${v.c}`;
      assert.equal(d.level(x), v.level, what);
      assert.equal(d.halfExtent(x), v.half_extent, what);
      assert.deepEqual(d.faces(x), v.faces, what);
      assert.equal(hex(d.key(x)), v.key, what);
      assert.deepEqual(d.idFromKey(fromHex(v.key)).c, v.c, what);
      assert.deepEqual(ids(d.children(x)), v.children, what);
      assert.deepEqual(ids(d.parents(x)), v.parents, what);
      assert.deepEqual(d.corners(x), v.corners, what);
      assert.deepEqual(ids(d.neighbours(x)), v.neighbours, what);
      const [face, other, chart] = d.chartFrame(x);
      assert.deepEqual([face, other], v.faces, what);
      assert.deepEqual(chart, v.chart_frame, what);
      const positions = [
        ...g.vertex_picks.flatMap(([i, j]) => d.vertexPosition(x, g.n, i, j)),
        ...g.cell_picks.flatMap(([i, j]) => d.cellPosition(x, g.n, i, j)),
      ];
      assert.equal(sha256(leBytes(positions, 8)), v.positions, `${what} vertex and cell positions`);
      checked++;
    }
    for (const p of g.rejected) {
      assert.throws(() => d.check(id(p)), IdError, `m=${g.m} ${p}`);
      assert.equal(d.isValid(id(p)), false);
    }
    for (const k of g.bad_keys) assert.throws(() => d.idFromKey(fromHex(k)), IdError, `m=${g.m} key ${k}`);
  }
  assert.ok(checked > 200, `${checked} ids`);
  // Hostile ids never escape as anything but IdError.
  const d = new SphereDomain(3);
  for (const c of [[1.5, 8, 0], [NaN, 8, 0], [8, 0], [2 ** 60, 8, 0], ["8", 0, 0]]) {
    assert.throws(() => d.level(id(c)), IdError, String(c));
  }
  assert.throws(() => new SphereDomain(0), IdError);
  assert.throws(() => new SphereDomain(41), IdError);
  assert.throws(() => d.vertexPosition(d.roots()[0], 3, 0, 0), IdError);
  assert.throws(() => d.vertexPosition(d.roots()[0], 4, 5, 0), IdError);
});

test("the equal-angle map and world positions follow the Rust client", () => {
  const { unit_sphere } = golden("sphere-geometry.json");
  for (const { p, sphere, cube } of unit_sphere) {
    const q = cubeToUnitSphere(p);
    const back = unitSphereToCube(q);
    for (let k = 0; k < 3; k++) {
      assert.ok(Math.abs(q[k] - sphere[k]) < 1e-14, `${p} -> ${q} vs ${sphere}`);
      assert.ok(Math.abs(back[k] - cube[k]) < 1e-14, `${q} -> ${back} vs ${cube}`);
    }
  }
  assert.deepEqual(cubeToUnitSphere([0, 0, 0]), [0, 0, 0]);
  const w = planetPoint([0, 0, 7], 6371000, 100);
  assert.deepEqual(w, [0, 0, 6371100]);
});

/// A refiner over a frame with zero roots and no model (geometry only).
function bareRefiner(faceSide, n, coverage, levels) {
  const roots = Array.from({ length: 6 }, () => new Int32Array((n + 1) * (n + 1)));
  return new SphereRefiner(faceSide, n, coverage, new Array(levels).fill(256), null, roots);
}

test("slots, masks, blob contexts and children equal the Rust frame's", () => {
  const { frames } = golden("sphere-frames.json");
  let checked = 0;
  let masked = 0;
  for (const f of frames) {
    const coverage = f.coverage === null ? null : Coverage.fromBytes(fromBase64(f.coverage));
    const frame = new SphereFrame(f.face_side, f.n, coverage);
    assert.equal(frame.detailLevels(), f.detail_levels);
    const r = bareRefiner(f.face_side, f.n, coverage, f.detail_levels);
    const n = f.n;
    for (const v of f.slots) {
      const x = id(v.c);
      const what = `${f.face_side}/${n} ${v.c}`;
      const found = frame.codedSlot(x);
      if (!v.coded) {
        assert.equal(found, null, what);
        assert.equal(r.info(x) !== null, v.info, what);
        continue;
      }
      const [level, slot] = found;
      assert.equal(level, v.level, what);
      assert.equal(hex(slot.key), v.key, what);
      assert.equal(slot.isEdge(), v.edge, what);
      const indices = [];
      for (let i = 0; i <= n; i++) for (let j = 0; j <= n; j++) indices.push(slot.vertexIndex(i, j));
      for (let i = 0; i < n; i++) for (let j = 0; j < n; j++) indices.push(slot.cellIndex(i, j));
      assert.equal(sha256(leBytes(indices, 4, false)), v.indices, `${what} vertex and cell indices`);
      if (v.mask === null) {
        assert.equal(slot.mask, null, what);
      } else {
        const bits = (side, fn) => {
          let s = "";
          for (let k = 0; k < side * side; k++) s += fn(Math.floor(k / side), k % side) ? "1" : "0";
          return s;
        };
        assert.ok(slot.mask !== null, what);
        assert.equal(bitsHex(bits(n + 1, (i, j) => slot.mask.vertex(i, j))), v.mask.vertex, `${what} vertex mask`);
        assert.equal(bitsHex(bits(n, (i, j) => slot.mask.cell(i, j))), v.mask.cell, `${what} cell mask`);
        masked++;
      }
      const owned = r.ownedChildren(x, level);
      assert.equal(owned.length, v.owned, what);
      assert.equal(frame.slotContext(level, slot, owned.length).group, v.group, what);
      const info = r.info(x);
      assert.equal(info.level, v.level);
      assert.deepEqual(ids(info.children), v.children, what);
      assert.deepEqual(ids(r.children(x)), v.children, what);
      checked++;
    }
    if (f.valid !== null) {
      const valid = new Uint8Array(frame.cubeLen());
      for (let k = 0; k < valid.length; k++) valid[k] = frame.isValid(k) ? 1 : 0;
      assert.equal(sha256(valid), f.valid, `${f.face_side}/${n} valid points`);
    }
  }
  assert.ok(checked > 100 && masked > 30, `${checked} slots, ${masked} masks`);
});

const blobGetter = (blobs) => (c) => {
  const b = blobs[`${c[0]}/${c[1]}/${c[2]}`];
  return b === undefined ? null : b.slice();
};

test("small planets refined diamond by diamond equal the Rust planet decoder", () => {
  for (const p of goldenPlanets()) {
    const out = reconstructSphere(p.metadata, blobGetter(p.blobs));
    assert.equal(out.length, p.decoded.length, p.name);
    for (let c = 0; c < out.length; c++) {
      assert.equal(out[c].length, p.decoded[c].len, p.name);
      assert.equal(sha256(leBytes(Array.from(out[c]), 4, true)), p.decoded[c].sha256, `${p.name} channel ${c}`);
    }
  }
});

test("refiner errors: wrong parents, missing parents, bad blobs, bad metadata", () => {
  const [p] = goldenPlanets();
  const r = SphereRefiner.fromMetadata(p.metadata);
  assert.equal(r.radiusM, 6371000);
  const [[a, ga]] = r.roots();
  const ra = r.synthesize(a, ga, null);
  const child = r.info(a).children[0];
  const grandchild = r.info(child).children[0];
  assert.throws(() => r.partialChildGrid(grandchild, [ra]), RefineError);
  assert.throws(() => r.childGrid(child, [ra]), RefineError);
  assert.throws(() => r.synthesize(a, ga.subarray(1), null), RefineError);
  assert.throws(() => r.decode(a, new Uint8Array(3)), DecodeError);
  assert.throws(() => r.decode(new SphereId([1, 2, 3]), new Uint8Array(3)), RefineError);
  // A leaf (a child of the finest level) is not refinable, has no info.
  let leaf = a;
  while (r.info(leaf) !== null) leaf = r.info(leaf).children[0];
  assert.equal(r.isRefinable(leaf), false);
  assert.equal(r.children(leaf), null);
  // Every byte of a blob flipped: a DecodeError or other details, never anything else.
  const key = Object.keys(p.blobs)[0];
  const c = key.split("/").map(Number);
  const blob = p.blobs[key];
  for (let k = 0; k < blob.length; k++) {
    const bad = blob.slice();
    bad[k] ^= 0x5a;
    try {
      r.decode(new SphereId(c), bad);
    } catch (e) {
      assert.ok(e instanceof DecodeError, String(e));
    }
  }
  for (const broken of [
    { ...p.metadata, domain: "planar" },
    { ...p.metadata, complete: false },
    { ...p.metadata, channels: [] },
    { ...p.metadata, levels: p.metadata.levels + 1 },
    { ...p.metadata, extent: [48, 48] },
    { ...p.metadata, coverage: [1, 2, 3] },
    { ...p.metadata, channels: [{ ...p.metadata.channels[0], roots: [] }] },
    { ...p.metadata, channels: [{ ...p.metadata.channels[0], model: [1, 2] }] },
    { ...p.metadata, channels: [{ ...p.metadata.channels[0], steps: "x" }] },
    null,
  ]) {
    assert.throws(() => SphereRefiner.fromMetadata(broken), DecodeError);
  }
});

test("children's halves assemble across cube edges; cloned ids and details refine alike", () => {
  const p = goldenPlanets()[0];
  const r = SphereRefiner.fromMetadata(p.metadata);
  const getBlob = blobGetter(p.blobs);
  const n = r.n();
  const refined = new Map();
  const refine = (x, grid) => {
    const blob = getBlob(r.centre(x));
    // What a worker hands back: ids and details through structured clone (plain data).
    const details = blob === null ? null : structuredClone(r.decode(x, blob));
    const out = r.synthesize(structuredClone(x), grid, details);
    refined.set(String(x), out);
    return out;
  };
  for (const [x, grid] of r.roots()) refine(x, grid);
  let level = r.roots().map(([x]) => x);
  let halves = 0;
  for (let l = 1; l < r.detailLevels(); l++) {
    const next = new Map();
    for (const x of level) for (const c of r.children(x)) next.set(String(c), c);
    level = [...next.values()];
    for (const child of level) {
      const parents = r.parents(child).map((q) => refined.get(String(q)));
      const whole = r.childGrid(child, parents.map((q) => structuredClone(q)));
      // Each parent gives its half; together every vertex, the shared diagonal agreeing.
      const [g1, w1] = r.partialChildGrid(child, [parents[0]]);
      const [g2, w2] = r.partialChildGrid(child, [parents[1]]);
      for (let k = 0; k < (n + 1) * (n + 1); k++) {
        assert.ok(w1[k] || w2[k], `${child} vertex ${k}`);
        if (w1[k]) assert.equal(g1[k], whole[k]);
        if (w2[k]) assert.equal(g2[k], whole[k]);
      }
      halves++;
      refine(child, whole);
    }
  }
  assert.ok(halves > 50);
});

test("vertexFine positions vertices exactly at every level, as the Rust client", () => {
  const [p] = goldenPlanets();
  const r = SphereRefiner.fromMetadata(p.metadata);
  const n = r.n();
  const d = r.domain();
  const fineHalf = r.fineHalfSide();
  let id0 = r.roots()[2][0];
  for (let depth = 0; depth < 6; depth++) {
    for (const [i, j] of [
      [0, 0],
      [n, 0],
      [n, n],
      [3, 1],
    ]) {
      const fine = r.vertexFine(id0, i, j);
      // Coarse positions (x 2N) scaled by N: the same point.
      const coarse = d.vertexPosition(id0, n, i, j);
      if (coarse.every((x) => Number.isInteger(x))) assert.deepEqual(fine, coarse.map((x) => x * n));
      assert.ok(Math.max(...fine.map(Math.abs)) === fineHalf);
    }
    const kids = d.children(id0);
    id0 = kids[depth % kids.length];
  }
  const w = r.vertexWorld(r.roots()[4][0], n / 2, n / 2, 0);
  assert.ok(Math.abs(w[2] - (6371000 + r.valueOffset)) < 1e-6 && Math.abs(w[0]) < 1e-6);
});

// ---------------------------------------------------------------------------------------
// The bundled planets' static exports against the Rust decoder.

const exportDir = process.env.QUINCUNX_EXPORT_DIR || "/work/export";
const demoDir = process.env.QUINCUNX_DEMO_DIR || "/work/demo";
const binary = process.env.QUINCUNX_BIN || join(here, "../../target/release/quincunx");

/// `getBlob` over a static export, or null after printing why the test is skipped.
function openExport(test, name) {
  const root = join(exportDir, "repos", name);
  const metaFile = join(root, "metadata.json");
  if (!existsSync(metaFile)) {
    console.log(`SKIP ${test}: ${metaFile} not found (quincunx export ${demoDir}/${name} ${exportDir} --name ${name})`);
    return null;
  }
  const meta = JSON.parse(readFileSync(metaFile, "utf8"));
  const versions = readdirSync(join(root, "v"));
  const version = versions.find((v) => meta.content_hash?.startsWith(v)) ?? versions[0];
  const base = join(root, "v", version, "d");
  let bytes = 0;
  let files = 0;
  const getBlob = (c) => {
    try {
      const b = readFileSync(join(base, String(c[0]), String(c[1]), String(c[2])));
      bytes += b.length;
      files++;
      return new Uint8Array(b.buffer, b.byteOffset, b.length);
    } catch (e) {
      if (e.code === "ENOENT") return null;
      throw e;
    }
  };
  return { meta, getBlob, stats: () => ({ bytes, files }) };
}

/// The Rust decoder's reconstruction hash, or null after printing why.
function rustHash(test, name) {
  const repo = join(demoDir, name);
  if (!existsSync(binary)) {
    console.log(`SKIP ${test} (hash comparison): no binary at ${binary}`);
    return null;
  }
  if (!existsSync(repo)) {
    console.log(`SKIP ${test} (hash comparison): no repository at ${repo}`);
    return null;
  }
  const run = spawnSync(binary, ["verify", repo, "--json"], { encoding: "utf8", maxBuffer: 1 << 26 });
  if (run.status !== 0) throw new Error(`quincunx verify ${repo}: ${run.stderr}`);
  const report = JSON.parse(run.stdout.slice(run.stdout.indexOf("{")));
  if (typeof report.decoded_sha256 !== "string") {
    console.log(`SKIP ${test} (hash comparison): verify --json prints no decoded_sha256 yet`);
    return null;
  }
  return report.decoded_sha256;
}

for (const name of ["earth", "earth_colour"]) {
  const title = `the ${name} export reconstructs to the Rust decoder's hash`;
  test(title, async () => {
    const repo = openExport(title, name);
    if (repo === null) return;
    const started = performance.now();
    const channels = reconstructSphere(repo.meta, repo.getBlob);
    const seconds = (performance.now() - started) / 1000;
    const { canonicalSha256 } = await import("../js/reconstruct.mjs");
    const hash = await canonicalSha256(channels);
    const samples = channels[0].length * channels.length;
    const { bytes, files } = repo.stats();
    console.log(
      `${name}: ${channels.length} channel(s) of ${channels[0].length} values, ${files} blobs ` +
        `(${(bytes / 1e6).toFixed(1)} MB) in ${seconds.toFixed(2)} s: ` +
        `${(samples / seconds / 1e6).toFixed(2)} M samples/s; sha256 ${hash}`,
    );
    const want = rustHash(title, name);
    if (want !== null) assert.equal(hash, want, `${name}: JS reconstruction differs from the Rust decoder`);
  });
}
