// The WebAssembly module's decoder (js/quincunx.wasm through js/wasm.mjs) against the
// native Rust one, and against hostile bytes:
// - every answer of test/golden/wasm-decode.json (written by web/tests/golden.rs from
//   repositories built in memory: the committed golden blobs of codec/tests/golden, every
//   coding path, a sparse planar repository, colour layers, small planets, packages, and
//   hostile answers) decodes to the bytes the native module gives (their SHA-256) or
//   fails with the same message;
// - every truncation of a few answers, 4,000 seeded mutations (each also resealed behind
//   a valid checksum), 2,000 random payloads and random keys and layers give bytes or a
//   WasmError: never a trap (a Rust panic is a WebAssembly.RuntimeError) or any other
//   exception, and the module decodes good answers exactly as before afterwards;
// - bad `open` JSON, bad metadata and settings, a wrong layer, a short buffer, an unknown
//   or freed handle are WasmErrors with a message.

import { test } from "node:test";
import assert from "node:assert/strict";
import { createHash } from "node:crypto";
import { readFileSync } from "node:fs";

import { AnswerDecoder, WasmClient, WasmError, loadWasm } from "../js/wasm.mjs";

const golden = JSON.parse(readFileSync(new URL("./golden/wasm-decode.json", import.meta.url), "utf8"));
const wasm = await loadWasm();

const sha256 = (bytes) => createHash("sha256").update(bytes).digest("hex");
const fromBase64 = (text) => new Uint8Array(Buffer.from(text, "base64"));
const fromHex = (text) => new Uint8Array(Buffer.from(text, "hex"));
const isHostile = (a) => a.what.startsWith("hostile");

/** The cases with their bytes decoded and a decoder each. */
const cases = golden.cases.map((c) => ({
  ...c,
  decoder: wasm.decoder(c.open),
  answers: c.answers.map((a) => ({
    ...a,
    bytes: fromBase64(a.bytes),
    storageKey: a.storageKey === undefined ? null : fromHex(a.storageKey),
  })),
}));

/** Decodes; returns {out} or {error} for a WasmError, throws anything else. */
function outcome(decoder, layer, key, bytes, packaged) {
  try {
    return { out: decoder.decode(layer, key, bytes, packaged) };
  } catch (e) {
    if (e instanceof WasmError) {
      assert.ok(e.message.length > 0, "a WasmError without a message");
      return { error: e.message };
    }
    throw e;
  }
}

/** Checks one answer of the file against the module. */
function check(c, a) {
  const got = outcome(c.decoder, a.layer, a.key, a.bytes, a.packaged);
  const at = `${c.name}: ${a.what}`;
  if (a.error !== undefined) {
    assert.equal(got.error, a.error, at);
  } else {
    assert.equal(got.error, undefined, `${at}: ${got.error}`);
    assert.equal(got.out.length, a.len, at);
    assert.equal(sha256(got.out), a.sha256, at);
  }
}

test("every answer decodes to what the native module gives, or fails with its message", () => {
  let answers = 0;
  let errors = 0;
  for (const c of cases) {
    for (const a of c.answers) {
      check(c, a);
      answers++;
      if (a.error !== undefined) errors++;
    }
  }
  assert.ok(cases.length >= 15 && answers > 1000 && errors > 200, `${cases.length} cases, ${answers} answers`);
});

test("the committed golden blobs, every coding path, packages, colour and planets decode", () => {
  const names = cases.map((c) => c.name);
  for (const prefix of ["golden/lossless", "golden/v4_", "paths/raster_", "paths/synthetic_n2_", "paths/synthetic_n64_", "sparse/", "colour/", "planet/"]) {
    assert.ok(names.some((n) => n.startsWith(prefix)), `no case ${prefix}`);
  }
  const kinds = new Set();
  for (const c of cases) {
    for (const a of c.answers.filter((a) => !isHostile(a))) {
      assert.equal(a.error, undefined, `${c.name}: ${a.what} is a good answer`);
      kinds.add(`layer ${a.layer}${a.packaged ? " package" : ""}`);
    }
  }
  assert.deepEqual([...kinds].sort(), ["layer 0", "layer 0 package", "layer 1", "layer 1 package"]);
});

// ---------------------------------------------------------------------------------------
// Hostile bytes.

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

/** CRC-16/CCITT-FALSE (decoder/src/blob.rs `crc16`) over the parts. */
function crc16(...parts) {
  let crc = 0xffff;
  for (const part of parts) {
    for (const b of part) {
      crc ^= b << 8;
      for (let k = 0; k < 8; k++) crc = crc & 0x8000 ? ((crc << 1) ^ 0x1021) & 0xffff : (crc << 1) & 0xffff;
    }
  }
  return crc;
}

const HEADER_BYTES = 3;

/** `payload` behind header byte `head` and a valid checksum for `storageKey`. */
function seal(head, storageKey, payload) {
  const crc = crc16(storageKey, [head], payload);
  const out = new Uint8Array(HEADER_BYTES + payload.length);
  out[0] = head;
  out[1] = crc & 0xff;
  out[2] = crc >> 8;
  out.set(payload, HEADER_BYTES);
  return out;
}

/** The good answers, with their case. */
const seeds = cases.flatMap((c) => c.answers.filter((a) => !isHostile(a)).map((a) => ({ c, a })));
/** Bare elevation blobs, whose payloads can be resealed. */
const sealable = seeds.filter(({ a }) => a.layer === 0 && !a.packaged && a.storageKey !== null && a.bytes.length >= HEADER_BYTES);

test("the checksum the test reseals with is the blobs' own", () => {
  assert.ok(sealable.length > 300, `${sealable.length} blobs`);
  for (const { c, a } of sealable) {
    const resealed = seal(a.bytes[0], a.storageKey, a.bytes.subarray(HEADER_BYTES));
    assert.deepEqual(resealed, a.bytes, `${c.name}: ${a.what}`);
  }
});

/** Every good answer still decodes as before (the module survived what came before). */
function stillWorks() {
  for (const c of cases) {
    for (const a of c.answers.filter((a) => !isHostile(a)).slice(0, 3)) check(c, a);
  }
}

test("truncations, mutations and random payloads give bytes or a WasmError, never a trap", () => {
  const next = rng(2023);
  const tally = { decoded: 0, failed: 0, sealedDecoded: 0 };
  const run = (c, layer, key, bytes, packaged) => {
    const got = outcome(c.decoder, layer, key, bytes, packaged); // throws a trap
    if (got.error !== undefined) tally.failed++;
    else tally.decoded++;
    return got.error === undefined;
  };
  // Every truncation of the largest answer of each kind in a few cases.
  const largest = new Map();
  for (const s of seeds) {
    const kind = `${s.c.name.split("/")[0]} ${s.a.layer} ${s.a.packaged}`;
    if (!largest.has(kind) || largest.get(kind).a.bytes.length < s.a.bytes.length) largest.set(kind, s);
  }
  assert.ok(largest.size >= 8, [...largest.keys()].join(", "));
  for (const { c, a } of largest.values()) {
    for (let len = 0; len < a.bytes.length; len++) run(c, a.layer, a.key, a.bytes.subarray(0, len), a.packaged);
    // Truncated payloads behind a valid checksum reach the entropy decoder.
    if (a.layer === 0 && !a.packaged && a.storageKey !== null) {
      for (let len = 0; len < a.bytes.length - HEADER_BYTES; len += 1 + (len >> 3)) {
        run(c, a.layer, a.key, seal(a.bytes[0], a.storageKey, a.bytes.subarray(HEADER_BYTES, HEADER_BYTES + len)), false);
      }
    }
  }
  stillWorks();
  // Mutations: bytes flipped, and with the checksum patched so the payload is decoded;
  // now and then the packaged flag or the layer changed too.
  for (let r = 0; r < 4000; r++) {
    const { c, a } = seeds[next() % seeds.length];
    const b = a.bytes.slice();
    if (b.length === 0) continue;
    const flips = 1 + (next() % 4);
    for (let f = 0; f < flips; f++) b[next() % b.length] ^= 1 + (next() % 255);
    const roll = next() % 16;
    const packaged = roll === 0 ? !a.packaged : a.packaged;
    const layer = roll === 1 ? 1 - a.layer : a.layer;
    run(c, layer, a.key, b, packaged);
    if (a.layer === 0 && !a.packaged && a.storageKey !== null && b.length >= HEADER_BYTES) {
      if (run(c, 0, a.key, seal(b[0], a.storageKey, b.subarray(HEADER_BYTES)), false)) tally.sealedDecoded++;
    }
  }
  stillWorks();
  // Random payloads of every length, sealed: random bytes, mostly ones (long unary runs
  // and escapes), mostly zeros.
  for (let r = 0; r < 2000; r++) {
    const { c, a } = sealable[next() % sealable.length];
    const payload = new Uint8Array(next() % 200);
    const style = next() % 3;
    for (let i = 0; i < payload.length; i++) {
      payload[i] = style === 0 ? next() & 0xff : style === 1 ? 0xff ^ (1 << (next() % 8)) : (next() % 4) << 6;
    }
    if (run(c, 0, a.key, seal(a.bytes[0], a.storageKey, payload), false)) tally.sealedDecoded++;
  }
  // Random keys and layers, and large random answers.
  const extremes = [0, 1, -1, 2 ** 31, -(2 ** 31), 2 ** 32 + 1, 2 ** 53 - 1, -(2 ** 53) + 1];
  for (let r = 0; r < 600; r++) {
    const { c, a } = seeds[next() % seeds.length];
    const coordinate = () => (next() % 3 === 0 ? extremes[next() % extremes.length] : (next() % 4096) - 64);
    const key = [coordinate(), coordinate(), next() % 2 === 0 ? 0 : coordinate()];
    run(c, next() % 5 === 0 ? next() % 256 : a.layer, key, a.bytes, a.packaged);
  }
  for (let r = 0; r < 20; r++) {
    const { c, a } = seeds[next() % seeds.length];
    const big = new Uint8Array(1000 + (next() % 200_000));
    for (let i = 0; i < big.length; i++) big[i] = next() & 0xff;
    big[0] = a.bytes[0];
    run(c, a.layer, a.key, big, next() % 2 === 0);
  }
  stillWorks();
  assert.ok(tally.decoded > 0 && tally.failed > 0 && tally.sealedDecoded > 0, JSON.stringify(tally));
  console.log(`hostile: ${JSON.stringify(tally)}`);
});

// ---------------------------------------------------------------------------------------
// Calls that cannot succeed.

/** Asserts that `f` throws a WasmError whose message matches `pattern`. */
function refuses(f, pattern, what) {
  assert.throws(f, (e) => {
    assert.ok(e instanceof WasmError, `${what}: ${e}`);
    assert.match(e.message, pattern, what);
    return true;
  });
}

test("bad open JSON, bad metadata, a wrong layer, short buffers, unknown and freed handles are WasmErrors", () => {
  const planar = cases.find((c) => c.name === "paths/raster_rms_45x29_n8");
  const planet = cases.find((c) => c.name.startsWith("planet/dense"));
  const colour = cases.find((c) => c.name.startsWith("colour/"));
  const good = planar.answers.find((a) => !isHostile(a));
  const { open } = planar;
  const meta = open.elevation.meta;
  refuses(() => wasm.decoder({}), /missing field `elevation`/, "no elevation");
  refuses(() => wasm.decoder(null), /^opening: invalid type: null/, "null");
  refuses(() => wasm.decoder([1, 2]), /^opening: /, "an array");
  refuses(() => wasm.decoder({ elevation: { name: "x" } }), /missing field `meta`/, "no metadata");
  // Bytes that are not JSON, or not UTF-8, straight into the export.
  for (const text of [[0xff, 0xfe, 0x00], [0x7b], []]) {
    refuses(() => wasm.check(wasm.x.qx_decoder_new(wasm.input(Uint8Array.from(text)))), /^opening: /, `bytes ${text}`);
  }
  const broken = [
    [{ ...meta, levels: meta.levels + 1 }, /levels/],
    [{ ...meta, m: meta.m + 1 }, /\bm\b/],
    [{ ...meta, n: 33 }, /\bn\b/],
    [{ ...meta, channels: [] }, /channels/],
    [{ ...meta, domain: "sphere" }, /./],
    [{ ...meta, content_hash: "x" }, /content_hash/],
    [{ ...meta, coverage: [1, 2, 3] }, /./],
    [{ ...meta, channels: [{ ...meta.channels[0], model: [1, 2, 3] }] }, /./],
    [{ ...meta, channels: [{ ...meta.channels[0], roots: [] }] }, /./],
    [{ ...meta, inline_max_bytes: -1 }, /^opening: /],
  ];
  for (const [m, pattern] of broken) {
    refuses(() => wasm.decoder({ ...open, elevation: { name: "broken", meta: m } }), pattern, JSON.stringify(m).slice(0, 100));
  }
  refuses(() => wasm.decoder({ ...open, config: { bogus: 1 } }), /unknown field `bogus`/, "an unknown setting");
  refuses(() => wasm.decoder({ ...open, config: { prefetchAheadMs: -5 } }), /prefetchAheadMs/, "a negative duration");
  refuses(() => wasm.decoder({ ...open, config: { metric: "psychic" } }), /./, "an unknown metric");
  // A colour layer must be colour, of the same domain.
  refuses(() => wasm.decoder({ ...open, colour: open.elevation }), /colour/, "elevation as colour");
  refuses(() => wasm.decoder({ ...planet.open, colour: colour.open.colour }), /domain/, "planar colour on a planet");
  refuses(() => wasm.client({}, 0), /missing field `elevation`/, "a client of nothing");
  refuses(() => wasm.client(open, NaN), /NaN/, "a client at NaN ms");

  const d = wasm.decoder(open);
  refuses(() => d.decode(1, good.key, good.bytes, false), /^no colour layer$/, "layer 1 without colour");
  refuses(() => d.decode(2, good.key, good.bytes, false), /^no layer 2$/, "layer 2");
  // Buffers shorter than the header `u8 layer, u8 packaged, key`.
  for (const len of [0, 1, 2, 25]) {
    refuses(() => wasm.check(wasm.x.qx_decoder_decode(d.h, wasm.input(new Uint8Array(len)))), /^malformed buffer: /, `${len} bytes`);
  }
  // Handles: unknown, of another kind, freed.
  refuses(() => new AnswerDecoder(wasm, 0x7ffffff0).decode(0, good.key, good.bytes, false), /^no decoder \d+$/, "an unknown handle");
  refuses(() => new WasmClient(wasm, d.h).stats(), /^no client \d+$/, "a decoder as a client");
  assert.equal(sha256(d.decode(0, good.key, good.bytes, false)), good.sha256);
  d.free();
  refuses(() => d.decode(0, good.key, good.bytes, false), /^no decoder \d+$/, "a freed decoder");
  d.free(); // twice: nothing
  // The module is whole after all of this.
  stillWorks();
});
