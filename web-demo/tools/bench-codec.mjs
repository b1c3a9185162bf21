#!/usr/bin/env node
// Decoding speed of web-demo/js/codec.mjs on the golden blobs (web-demo/test/golden/
// codec-*.json), for comparison with the Rust decoder: decodes every blob repeatedly for
// about `--seconds` (default 3) of CPU time after a warm-up and prints one JSON line,
// {"msamples_per_s": ..., ...}, counting N x N decoded cells per blob. Rates are per
// second of this process's CPU time (robust to other load on the machine); the wall-clock
// rate is printed beside it.
//
// Usage: node web-demo/tools/bench-codec.mjs [--seconds S]

import { readFileSync } from "node:fs";
import { fileURLToPath } from "node:url";

import { decodeBlobInto, parseModel } from "../js/codec.mjs";

const args = process.argv.slice(2);
const at = args.indexOf("--seconds");
const seconds = at >= 0 ? Number(args[at + 1]) : 3;

const fromHex = (s) => Uint8Array.from(s.match(/../g) ?? [], (h) => parseInt(h, 16));

function blobs(name) {
  const file = JSON.parse(readFileSync(fileURLToPath(new URL(`../test/golden/${name}`, import.meta.url)), "utf8"));
  const models = new Map(Object.entries(file.models).map(([k, hex]) => [k, parseModel(fromHex(hex))]));
  return file.vectors.map((v) => {
    let cells = null;
    if (v.cells !== null) {
      const bits = fromHex(v.cells);
      cells = new Uint8Array(v.n * v.n);
      for (let k = 0; k < cells.length; k++) cells[k] = (bits[k >> 3] >> (k & 7)) & 1;
    }
    return {
      bytes: fromHex(v.blob),
      model: models.get(v.model),
      ctx: { key: fromHex(v.key), n: v.n, group: v.group, cells, ownedChildren: v.ownedChildren, step: v.step },
      q: new Int32Array(v.n * v.n),
    };
  });
}

const cpuSeconds = () => {
  const { user, system } = process.cpuUsage();
  return (user + system) / 1e6;
};

/** Decodes `set` round after round for `secs` of CPU time; returns rates per CPU second. */
function measure(set, secs) {
  let samples = 0;
  let bytes = 0;
  let rounds = 0;
  const start = cpuSeconds();
  const wallStart = process.hrtime.bigint();
  let elapsed = 0;
  while (elapsed < secs) {
    for (const b of set) {
      decodeBlobInto(b.bytes, b.ctx, b.model, b.q);
      samples += b.q.length;
      bytes += b.bytes.length;
    }
    rounds++;
    elapsed = cpuSeconds() - start;
  }
  const wall = Number(process.hrtime.bigint() - wallStart) / 1e9;
  return { samples_per_s: samples / elapsed, bytes_per_s: bytes / elapsed, wall_samples_per_s: samples / wall, rounds };
}

const golden = blobs("codec-committed-golden.json");
const paths = blobs("codec-encoder-paths.json");
const all = [...golden, ...paths];
measure(all, Math.min(1, seconds / 3)); // warm-up: let the JIT optimise
const total = measure(all, seconds);
const committed = measure(golden, seconds / 3);
const round = (x) => Math.round(x * 1000) / 1000;
console.log(
  JSON.stringify({
    msamples_per_s: round(total.samples_per_s / 1e6),
    mbytes_per_s: round(total.bytes_per_s / 1e6),
    wall_msamples_per_s: round(total.wall_samples_per_s / 1e6),
    committed_golden_msamples_per_s: round(committed.samples_per_s / 1e6),
    blobs: all.length,
    samples_per_round: all.reduce((s, b) => s + b.q.length, 0),
    bytes_per_round: all.reduce((s, b) => s + b.bytes.length, 0),
    rounds: total.rounds,
    node: process.version,
  }),
);
