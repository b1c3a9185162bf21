#!/usr/bin/env node
// Decoding speed of the WebAssembly decoder (js/quincunx.wasm through js/wasm.mjs:
// `decoder.decode`, one answer's bytes to the details a client receives, copies across
// the module's boundary included) on the answers of test/golden/wasm-decode.json that
// decode: the committed golden blobs of codec/tests/golden, every coding path, packages,
// colour layers and planets. After a warm-up, each run decodes a set round after round
// for at least --min-ms (default 300); the rates are medians of --runs (default 7) runs,
// in blobs (answers) and input megabytes per second of wall-clock time, and for the
// golden blobs also in decoded samples (N x N cells per blob). Prints one JSON line.
//
// Whole repositories (decode and synthesis to full resolution) are bench-decode.mjs's.
//
// Usage: node web-demo/tools/bench-codec.mjs [--runs N] [--min-ms MS]

import { readFileSync } from "node:fs";

import { loadWasm } from "../js/wasm.mjs";

const args = process.argv.slice(2);
const option = (name, fallback) => {
  const at = args.indexOf(name);
  return at >= 0 ? Number(args[at + 1]) : fallback;
};
const RUNS = option("--runs", 7);
const MIN_MS = option("--min-ms", 300);

const golden = JSON.parse(readFileSync(new URL("../test/golden/wasm-decode.json", import.meta.url), "utf8"));
const wasm = await loadWasm();

/** Every answer that decodes, with its decoder and the samples of its own blob. */
const answers = golden.cases.flatMap((c) => {
  const decoder = wasm.decoder(c.open);
  return c.answers
    .filter((a) => a.error === undefined && !a.what.startsWith("hostile"))
    .map((a) => {
      const bytes = new Uint8Array(Buffer.from(a.bytes, "base64"));
      // The output starts with the elevation details' length (web/src/wire.rs).
      const out = decoder.decode(a.layer, a.key, bytes, a.packaged);
      const samples = a.layer === 0 ? new DataView(out.buffer).getUint32(0, true) : 0;
      return { set: c.name.split("/")[0], decoder, layer: a.layer, key: a.key, packaged: a.packaged, bytes, samples };
    });
});

const median = (xs) => [...xs].sort((a, b) => a - b)[xs.length >> 1];

/** Median rates of decoding `set` over RUNS runs of at least MIN_MS each. */
function measure(set) {
  const bytes = set.reduce((s, a) => s + a.bytes.length, 0);
  const samples = set.reduce((s, a) => s + a.samples, 0);
  const rates = { blobs: [], bytes: [], samples: [] };
  for (let run = 0; run < RUNS; run++) {
    let rounds = 0;
    const start = performance.now();
    let elapsed = 0;
    while (elapsed < MIN_MS) {
      for (const a of set) a.decoder.decode(a.layer, a.key, a.bytes, a.packaged);
      rounds++;
      elapsed = performance.now() - start;
    }
    const seconds = elapsed / 1000;
    rates.blobs.push((rounds * set.length) / seconds);
    rates.bytes.push((rounds * bytes) / seconds);
    rates.samples.push((rounds * samples) / seconds);
  }
  const round = (x) => Math.round(x * 1000) / 1000;
  return {
    blobs: set.length,
    bytes_per_round: bytes,
    blobs_per_s: Math.round(median(rates.blobs)),
    mbytes_per_s: round(median(rates.bytes) / 1e6),
    msamples_per_s: round(median(rates.samples) / 1e6),
  };
}

// Warm-up: let the engine tier the module up.
const warm = performance.now();
while (performance.now() - warm < 500) for (const a of answers) a.decoder.decode(a.layer, a.key, a.bytes, a.packaged);

const all = measure(answers);
const committed = measure(answers.filter((a) => a.set === "golden"));
const paths = measure(answers.filter((a) => a.set === "paths"));
console.log(
  JSON.stringify({
    blobs_per_s: all.blobs_per_s,
    mbytes_per_s: all.mbytes_per_s,
    committed_golden_blobs_per_s: committed.blobs_per_s,
    committed_golden_mbytes_per_s: committed.mbytes_per_s,
    committed_golden_msamples_per_s: committed.msamples_per_s,
    paths_blobs_per_s: paths.blobs_per_s,
    paths_mbytes_per_s: paths.mbytes_per_s,
    blobs: all.blobs,
    bytes_per_round: all.bytes_per_round,
    runs: RUNS,
    min_ms: MIN_MS,
    node: process.version,
  }),
);
