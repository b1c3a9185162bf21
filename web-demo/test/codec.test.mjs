// Tests of web-demo/js/codec.mjs against the Rust codec: golden vectors written by
// codec/tests/js_golden.rs (web-demo/test/golden/codec-*.json) decode to exactly what
// Rust decodes, hostile bytes fail exactly where and how they fail in Rust, and any byte
// string gives a result or a DecodeError (never another exception, never a hang).
// Channel frames and packages mirror the Rust tests of repo-tools/src/layout.rs and
// meta/src/answer.rs.

import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { fileURLToPath } from "node:url";

import {
  CONTEXTS,
  CodecModel,
  DecodeError,
  HEADER_BYTES,
  NO_DATA,
  VERSION,
  blobContextOfLevel,
  classBound,
  crc16,
  decodeBlob,
  decodeBlobInto,
  dequantize,
  dequantizeMatrix,
  gammaClass,
  group,
  parseModel,
  parsePackage,
  rgbToYcocgR,
  splitChannels,
  splitSide,
  ycocgRPlanesToRgb,
  ycocgRToRgb,
} from "../js/codec.mjs";

const GOLDEN = new URL("./golden/", import.meta.url);

function load(name) {
  return JSON.parse(readFileSync(fileURLToPath(new URL(name, GOLDEN)), "utf8"));
}

function fromHex(s) {
  const out = new Uint8Array(s.length / 2);
  for (let i = 0; i < out.length; i++) out[i] = parseInt(s.substr(2 * i, 2), 16);
  return out;
}

/** Cells from the bitmap hex of the vectors (cell k = bit k % 8 of byte k / 8). */
function cellsOf(hex, n) {
  if (hex === null) return null;
  const bits = fromHex(hex);
  const cells = new Uint8Array(n * n);
  for (let k = 0; k < n * n; k++) cells[k] = (bits[k >> 3] >> (k & 7)) & 1;
  return cells;
}

function fnv1a(q) {
  let h = 0x811c9dc5;
  for (let k = 0; k < q.length; k++) {
    const x = q[k];
    for (let s = 0; s < 32; s += 8) h = Math.imul(h ^ ((x >>> s) & 0xff), 0x01000193) >>> 0;
  }
  return h >>> 0;
}

function expectedQ(v, n) {
  if (v.q) return Int32Array.from(v.q);
  const q = new Int32Array(n * n);
  for (let i = 0; i < v.qSparse.length; i += 2) q[v.qSparse[i]] = v.qSparse[i + 1];
  return q;
}

/** Vectors of a file with their contexts and models resolved. */
function vectors(file, base = null) {
  const models = new Map();
  for (const [name, hex] of Object.entries({ ...(base?.models ?? {}), ...file.models })) {
    models.set(name, parseModel(fromHex(hex)));
  }
  const byName = new Map((base?.vectors ?? file.vectors).map((v) => [v.name, v]));
  return file.vectors.map((v) => {
    const c = v.context ? byName.get(v.context) : v;
    assert.ok(c, `context ${v.context} of ${v.name}`);
    return {
      v,
      bytes: fromHex(v.blob),
      model: models.get(c.model),
      ctx: {
        key: fromHex(c.key),
        n: c.n,
        group: c.group,
        cells: cellsOf(c.cells, c.n),
        ownedChildren: c.ownedChildren,
        step: c.step,
      },
    };
  });
}

const committed = load("codec-committed-golden.json");
const paths = load("codec-encoder-paths.json");
const hostile = load("codec-hostile.json");
const tables = load("codec-tables.json");

/** Decodes, returning the result or the error's kind (dotted for entropy errors). */
function outcome(bytes, ctx, model) {
  try {
    return decodeBlob(bytes, ctx, model);
  } catch (e) {
    if (!(e instanceof DecodeError)) throw e;
    return { error: e.kind === "Entropy" ? `Entropy.${e.entropy}` : e.kind };
  }
}

for (const [name, file] of [
  ["committed golden blobs", committed],
  ["encoder path blobs", paths],
]) {
  test(`${name} decode to the committed values`, () => {
    const all = vectors(file);
    assert.ok(all.length > 10);
    assert.equal(file.blobVersion, VERSION);
    for (const { v, bytes, model, ctx } of all) {
      const got = decodeBlob(bytes, ctx, model);
      assert.deepEqual(Array.from(got.childClasses), v.childClasses, v.name);
      assert.equal(got.q.length, ctx.n * ctx.n);
      if (v.qFnv1a !== undefined) {
        assert.equal(fnv1a(got.q), v.qFnv1a, v.name);
      } else {
        assert.deepEqual(got.q, expectedQ(v, ctx.n), v.name);
      }
      // decodeBlobInto overwrites a dirty buffer with the same values.
      const q = new Int32Array(ctx.n * ctx.n).fill(7);
      const classes = decodeBlobInto(bytes, ctx, model, q);
      assert.deepEqual(classes, got.childClasses);
      assert.deepEqual(q, got.q, v.name);
    }
  });
}

test("hostile blobs fail or decode exactly as in Rust", () => {
  const all = vectors(hostile, paths);
  const kinds = new Set();
  for (const { v, bytes, model, ctx } of all) {
    const got = outcome(bytes, ctx, model);
    if (v.error !== null) {
      assert.equal(got.error, v.error, v.name);
    } else {
      assert.equal(got.error, undefined, `${v.name}: ${got.error}`);
      assert.deepEqual(Array.from(got.childClasses), v.childClasses, v.name);
      assert.equal(fnv1a(got.q), v.qFnv1a, v.name);
    }
    kinds.add(v.error ?? "ok");
  }
  for (const k of ["ok", "TooShort", "Version", "Size", "Checksum", "Entropy.Truncated", "Entropy.EscapeTooLong"]) {
    assert.ok(kinds.has(k), `no hostile vector gives ${k}`);
  }
});

test("header errors carry the Rust fields", () => {
  const [{ bytes, model, ctx }] = vectors(paths).filter(({ v }) => v.name === "medium_lossless/trained");
  const fail = (b, c = ctx) => {
    try {
      decodeBlob(b, c, model);
    } catch (e) {
      assert.ok(e instanceof DecodeError && e instanceof Error);
      assert.equal(e.name, "DecodeError");
      return e;
    }
    assert.fail("decoded");
  };
  let e = fail(bytes.subarray(0, 2));
  assert.equal(e.kind, "TooShort");
  assert.equal(e.length, 2);
  const v3 = bytes.slice();
  v3[0] = 0x35;
  e = fail(v3);
  assert.equal(e.kind, "Version");
  assert.equal(e.version, 3);
  assert.match(e.message, /version 3 is not supported \(expected 4 to 5\)/);
  const size = bytes.slice();
  size[0] = 0x46;
  e = fail(size);
  assert.equal(e.kind, "Size");
  assert.deepEqual([e.got, e.expected], [6, 32]);
  const flipped = bytes.slice();
  flipped[flipped.length - 1] ^= 1;
  e = fail(flipped);
  assert.equal(e.kind, "Checksum");
  assert.equal(e.stored, bytes[1] | (bytes[2] << 8));
  assert.notEqual(e.computed, e.stored);
  assert.match(e.message, /^checksum mismatch \(stored 0x[0-9a-f]{4}, computed 0x[0-9a-f]{4}\)$/);
  // The same bytes under another key.
  e = fail(bytes, { ...ctx, key: Uint8Array.from([...ctx.key, 1]) });
  assert.equal(e.kind, "Checksum");
  // The size nibble is checked against the context's n before the checksum.
  e = fail(bytes, { ...ctx, n: 16, cells: null });
  assert.equal(e.kind, "Size");
});

/** xorshift32, seeded. */
function rng(seed) {
  let x = seed >>> 0 || 1;
  return () => {
    x ^= x << 13;
    x >>>= 0;
    x ^= x >>> 17;
    x ^= x << 5;
    x >>>= 0;
    return x;
  };
}

function seal(ctx, payload) {
  const head = (VERSION << 4) | Math.log2(ctx.n);
  const crc = crc16(ctx.key, [head], payload);
  const out = new Uint8Array(HEADER_BYTES + payload.length);
  out[0] = head;
  out[1] = crc & 0xff;
  out[2] = crc >> 8;
  out.set(payload, HEADER_BYTES);
  return out;
}

test("every truncation and thousands of random mutations give a result or a DecodeError", () => {
  const all = [...vectors(committed), ...vectors(paths)];
  const next = rng(2023);
  let decoded = 0;
  let failed = 0;
  let sealedOk = 0;
  const tally = (bytes, ctx, model) => {
    const got = outcome(bytes, ctx, model); // throws anything but a DecodeError
    if (got.error) {
      failed++;
      return false;
    }
    assert.equal(got.q.length, ctx.n * ctx.n);
    assert.equal(got.childClasses.length, ctx.ownedChildren);
    decoded++;
    return true;
  };
  for (const { bytes, model, ctx } of all) {
    for (let len = 0; len < bytes.length; len++) tally(bytes.subarray(0, len), ctx, model);
    // Truncated payloads behind a valid checksum reach the entropy decoder.
    for (let len = 0; len < bytes.length - HEADER_BYTES; len += 1 + (len >> 3)) {
      tally(seal(ctx, bytes.subarray(HEADER_BYTES, HEADER_BYTES + len)), ctx, model);
    }
  }
  for (let r = 0; r < 4000; r++) {
    const { bytes, model, ctx } = all[next() % all.length];
    const b = bytes.slice();
    const flips = 1 + (next() % 4);
    for (let f = 0; f < flips; f++) b[next() % b.length] ^= 1 + (next() % 255);
    tally(b, ctx, model);
    // And with the checksum patched, so that the payload is decoded.
    if (b.length >= HEADER_BYTES) sealedOk += tally(seal(ctx, b.subarray(HEADER_BYTES)), ctx, model);
  }
  // Random bytes of every length, sealed.
  for (let r = 0; r < 2000; r++) {
    const { model, ctx } = all[next() % all.length];
    const payload = new Uint8Array(next() % 200);
    const style = next() % 3;
    for (let i = 0; i < payload.length; i++) {
      payload[i] = style === 0 ? next() & 0xff : style === 1 ? 0xff ^ (1 << (next() % 8)) : (next() % 4) << 6;
    }
    tally(seal(ctx, payload), ctx, model);
  }
  assert.ok(decoded > 0 && failed > 0 && sealedOk > 0, `${decoded} decoded, ${failed} failed`);
});

test("models parse like CodecModel::from_bytes", () => {
  assert.equal(tables.contexts, CONTEXTS);
  // Every context explicit, byte k % 256 at context k: MODEL_PROBS repeated.
  const mapLen = Math.ceil(CONTEXTS / 8);
  const explicit = new Uint8Array(mapLen + CONTEXTS).fill(0xff, 0, mapLen);
  explicit[mapLen - 1] = (1 << CONTEXTS % 8) - 1;
  for (let k = 0; k < CONTEXTS; k++) explicit[mapLen + k] = k % 256;
  const m = parseModel(explicit);
  assert.ok(m instanceof CodecModel);
  for (let k = 0; k < CONTEXTS; k++) assert.equal(m.probs[k], tables.modelProbs[k % 256], `context ${k}`);
  // Arrays of numbers (metadata JSON) parse too.
  assert.deepEqual(parseModel(Array.from(explicit)).probs, m.probs);
  // The default model is its bitmap alone.
  const def = parseModel(new Uint8Array(mapLen));
  assert.deepEqual(def.probs, CodecModel.default().probs);
  assert.ok(def.probs.every((p) => p === 32768));
  const bad = (bytes, reason) => {
    assert.throws(
      () => parseModel(bytes),
      (e) => e instanceof DecodeError && e.kind === "BadModel" && e.reason === reason,
    );
  };
  bad(explicit.subarray(0, mapLen - 1), "shorter than its bitmap");
  bad(explicit.subarray(0, explicit.length - 1), "wrong length");
  bad(Uint8Array.from([...explicit, 7]), "wrong length");
  const past = new Uint8Array(mapLen + 1);
  past[mapLen - 1] = 0x80;
  past[mapLen] = 7;
  bad(past, "bits set past the last context");
  bad([1, 2, 300], "not a byte");
  bad(null, "not a byte array");
});

test("tables, classes, dequantisation and colour match Rust", () => {
  assert.equal(crc16(new TextEncoder().encode("123456789")), tables.crc16_123456789);
  assert.equal(crc16(new TextEncoder().encode("1234"), [], new TextEncoder().encode("56789")), 0x29b1);
  assert.equal(crc16(), 0xffff);
  for (let k = 0; k < 64; k++) assert.equal(classBound(k), tables.classBounds[k], `class ${k}`);
  const [gammas, classes] = tables.gammaClasses;
  gammas.forEach((g, i) => assert.equal(gammaClass(g), classes[i], `gamma ${g}`));
  for (let e = 0; e < 256; e++) assert.deepEqual(splitSide(e), tables.splitSide[e], `entry ${e}`);
  assert.equal(NO_DATA, 0x80);
  for (const [q, s, h] of tables.dequantize) assert.equal(dequantize(q, s), h, `dequantize(${q}, ${s})`);
  const q = Int32Array.from(tables.dequantize.filter(([, s]) => s === 300).map(([x]) => x));
  assert.deepEqual(
    Array.from(dequantizeMatrix(q, 300)),
    tables.dequantize.filter(([, s]) => s === 300).map(([, , h]) => h),
  );
  for (const [r, g, b, y, co, cg] of tables.ycocgR) {
    assert.deepEqual(rgbToYcocgR(r, g, b), [y, co, cg]);
    assert.deepEqual(ycocgRToRgb(y, co, cg), [r, g, b]);
    const out = new Int32Array(3);
    ycocgRPlanesToRgb([y], [co], [cg], out);
    assert.deepEqual(Array.from(out), [r, g, b]);
  }
  // Every 8-bit colour round trips (colour.rs's test, on a grid of colours).
  for (let r = 0; r < 256; r += 5) {
    for (let g = 0; g < 256; g += 3) {
      for (const b of [0, 1, 77, 128, 254, 255]) {
        const [y, co, cg] = rgbToYcocgR(r, g, b);
        assert.deepEqual(ycocgRToRgb(y, co, cg), [r, g, b]);
      }
    }
  }
});

test("blob contexts of levels use the level group", () => {
  assert.equal(group(0), 0);
  assert.equal(group(4), 4);
  assert.equal(group(9), 5);
  const key = Uint8Array.of(3, 1);
  const ctx = blobContextOfLevel(key, 32, 8, 2, null, 2);
  assert.deepEqual(ctx, { key, n: 32, group: 5, cells: null, ownedChildren: 2, step: 256 });
  assert.equal(blobContextOfLevel(key, 32, 8, 7, null, 0, 600).group, 0);
  assert.equal(blobContextOfLevel(key, 32, 8, 7, null, 0, 600).step, 600);
});

// ---------------------------------------------------------------------------------------
// Channel frames (mirrors repo-tools/src/layout.rs's test of meta/src/channels.rs).

function varint(v) {
  const out = [];
  while (v >= 0x80) {
    out.push((v & 0x7f) | 0x80);
    v = Math.floor(v / 128);
  }
  out.push(v);
  return out;
}

function frameChannels(parts) {
  if (parts.length === 1) return parts[0];
  if (parts.every((p) => p === null)) return null;
  const out = [];
  for (const p of parts) {
    out.push(...varint(p ? p.length : 0), ...(p ?? []));
  }
  return Uint8Array.from(out);
}

test("channel frames split and reject truncation", () => {
  const a = new Uint8Array(200).fill(7);
  const parts = [a, null, new TextEncoder().encode("xyz")];
  const framed = frameChannels(parts);
  const split = splitChannels(framed, 3);
  assert.equal(split.length, 3);
  assert.deepEqual(split[0], a);
  assert.equal(split[1], null);
  assert.deepEqual(split[2], parts[2]);
  for (let cut = 0; cut < framed.length; cut++) {
    assert.throws(
      () => splitChannels(framed.subarray(0, cut), 3),
      (e) => e instanceof DecodeError && e.kind === "Frame",
      `cut ${cut}`,
    );
  }
  assert.equal(frameChannels([null, null, null]), null);
  assert.throws(() => splitChannels(new Uint8Array(8).fill(0xff), 3), /overlong length for channel 0/);
  assert.throws(() => splitChannels(Uint8Array.of(1, 9, 0, 0, 5), 3), /channel 2 claims 0|trailing/);
  assert.throws(() => splitChannels(Uint8Array.of(0, 0, 0, 0), 3), /1 trailing bytes/);
  assert.throws(() => splitChannels(Uint8Array.of(0, 5, 1), 3), /channel 1 claims 5 bytes, 1 remain/);
  // One channel: the blob itself, whatever it holds.
  const one = Uint8Array.of(0xff, 0xff);
  assert.equal(splitChannels(one, 1)[0], one);
  // Random bytes: a split or a DecodeError.
  const next = rng(77);
  for (let r = 0; r < 3000; r++) {
    const b = new Uint8Array(next() % 24);
    for (let i = 0; i < b.length; i++) b[i] = next() % 4 === 0 ? next() & 0xff : next() % 8;
    try {
      const s = splitChannels(b, 3);
      assert.equal(s.length, 3);
    } catch (e) {
      assert.ok(e instanceof DecodeError && e.kind === "Frame");
    }
  }
});

// ---------------------------------------------------------------------------------------
// Packages (mirrors meta/src/answer.rs's tests).

function writeAnswer(blob, children, packaged) {
  if (!packaged) return Uint8Array.from(blob);
  const mask = children.reduce((m, [i]) => m | (1 << i), 0);
  const out = [0xf0 | mask, ...varint(blob.length), ...blob];
  for (const [, child] of [...children].sort((x, y) => x[0] - y[0])) out.push(...varint(child.length), ...child);
  return Uint8Array.from(out);
}

const kindOf = (f) => {
  try {
    f();
  } catch (e) {
    assert.ok(e instanceof DecodeError, String(e));
    return e.kind === "Malformed" ? `Malformed(${e.reason})` : e.kind === "Trailing" ? `Trailing(${e.count})` : e.kind;
  }
  return "ok";
};

test("answers round trip", () => {
  const blob = [0xf5, 1, 2, 3];
  assert.deepEqual(writeAnswer(blob, [], false), Uint8Array.from(blob));
  assert.deepEqual(parsePackage(Uint8Array.from(blob), false).blob, Uint8Array.from(blob));
  assert.deepEqual(parsePackage(Uint8Array.from(blob), false).children, []);
  const grand = writeAnswer([0x25, 9], [], true);
  assert.deepEqual(grand, Uint8Array.of(0xf0, 2, 0x25, 9));
  const child = writeAnswer([0x25, 7, 7], [[1, grand]], true);
  const big = writeAnswer(new Array(300).fill(0x25), [], true);
  const answer = writeAnswer(blob, [[2, big], [0, child]], true);
  assert.equal(answer[0], 0xf5);
  const parsed = parsePackage(answer, true);
  assert.deepEqual(parsed.blob, Uint8Array.from(blob));
  assert.deepEqual(parsed.children, [
    [0, child],
    [2, big],
  ]);
  const inner = parsePackage(parsed.children[0][1], true);
  assert.deepEqual(inner.blob, Uint8Array.of(0x25, 7, 7));
  assert.deepEqual(inner.children, [[1, grand]]);
  assert.deepEqual(parsePackage(grand).children, []);
});

test("malformed answers are errors", () => {
  const good = writeAnswer([0x25, 1], [[0, writeAnswer([0x25, 2], [], true)]], true);
  assert.equal(kindOf(() => parsePackage(new Uint8Array(0), true)), "Malformed(empty)");
  assert.equal(kindOf(() => parsePackage(new Uint8Array(0), false)), "Malformed(empty)");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0x25, 1), true)), "Malformed(not a package)");
  assert.notEqual(kindOf(() => parsePackage(Uint8Array.of(0xf0, 1), true)), "ok");
  for (let cut = 1; cut < good.length; cut++) {
    assert.notEqual(kindOf(() => parsePackage(good.subarray(0, cut), true)), "ok", `cut at ${cut}`);
  }
  assert.equal(kindOf(() => parsePackage(Uint8Array.from([...good, 0]), true)), "Trailing(1)");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf1, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01), true)), "BadLength");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf1, 0xff, 0xff, 0xff, 0xff, 0x7f), true)), "BadLength");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf1, 0, 1, 0x25), true)), "Malformed(empty part)");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf0, 5, 1), true)), "Truncated");
  // The largest u32 length is a length (then truncated), one more is not.
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf0, 0xff, 0xff, 0xff, 0xff, 0x0f), true)), "Truncated");
  assert.equal(kindOf(() => parsePackage(Uint8Array.of(0xf0, 0x80, 0x80, 0x80, 0x80, 0x10), true)), "BadLength");
  // Arbitrary bytes never throw anything else (the Rust test's generator).
  let x = 0x12345678;
  for (let len = 0; len < 64; len++) {
    const bytes = new Uint8Array(len);
    for (let i = 0; i < len; i++) {
      x = (x ^ (x << 13)) >>> 0;
      x = (x ^ (x >>> 17)) >>> 0;
      x = (x ^ (x << 5)) >>> 0;
      bytes[i] = (x & 0xff) | (x & 0x100 ? 0xf0 : 0);
    }
    kindOf(() => parsePackage(bytes, true));
  }
});
