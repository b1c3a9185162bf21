#!/usr/bin/env node
// Decode speed of the WebAssembly module in node and in Chromium, against the native Rust
// decoder (`quincunx verify`), on the same blobs: every blob of an exported repository
// decoded and synthesised to full resolution (web-demo/js/reconstruct.mjs, compiled to
// web-demo/js/quincunx.wasm) by each of the module's decoders: "whole" (the whole-raster
// decoder `verify` runs) and "refiners" (one diamond at a time, as the viewer refines).
// Medians of RUNS runs (the module loaded first), one JSON line per repository and
// decoder. `*_msamples_per_s` time what `verify` times, the decode alone (the module's
// own clock: the blobs and parsed coding in, full-resolution values out);
// `*_call_msamples_per_s` the whole call from JavaScript (also the copies in and out,
// parsing the metadata and building the geometry).
//
// Usage: node web-demo/tools/bench-decode.mjs <server url> <export dir> <quincunx binary>
//        <repo dir>... (each repo dir's last path component names its export)
// The server only provides the page origin the modules load from: `quincunx serve`
// (the modules compiled into its binary), or web-demo/tools/dev-server.mjs (from disk).
// Chromium: Debian's, headless (CHROMIUM, default /usr/bin/chromium), SwiftShader flags
// as in browser-views.mjs. Samples are counted as `quincunx verify` counts them.

import { execFileSync } from "node:child_process";
import { existsSync, readdirSync, readFileSync, statSync } from "node:fs";
import { basename, join } from "node:path";
import { chromium } from "playwright-core";
import { canonicalSha256, reconstruct } from "../js/reconstruct.mjs";
import { loadWasm } from "../js/wasm.mjs";

const [url, exportDir, bin, ...repos] = process.argv.slice(2);
if (!url || !exportDir || !bin || repos.length === 0) {
  process.stderr.write("usage: bench-decode.mjs <server url> <export dir> <quincunx> <repo dir>...\n");
  process.exit(2);
}
const RUNS = Number(process.env.RUNS ?? 5);
const median = (xs) => [...xs].sort((a, b) => a - b)[xs.length >> 1];

function readExport(dir) {
  const meta = JSON.parse(readFileSync(join(dir, "metadata.json"), "utf8"));
  const root = join(dir, "v", meta.content_hash.slice(0, 16), "d");
  const blobs = {};
  const walk = (p, parts) => {
    for (const e of readdirSync(p)) {
      const q = join(p, e);
      if (statSync(q).isDirectory()) walk(q, [...parts, e]);
      else blobs[[...parts, e].join("/")] = readFileSync(q).toString("base64");
    }
  };
  if (existsSync(root)) walk(root, []);
  return { meta, blobs };
}

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
});
try {
  const page = await browser.newPage();
  await page.goto(`${url}/healthz`);
  for (const repoDir of repos) {
    const name = basename(repoDir);
    const { meta, blobs } = readExport(join(exportDir, "repos", name));
    const [a, b] = meta.extent;
    const samples = (meta.domain === "sphere" ? 6 * a * b + 2 : a * b) * meta.channels.length;

    const decoded = new Map(Object.entries(blobs).map(([k, v]) => [k, new Uint8Array(Buffer.from(v, "base64"))]));
    await loadWasm();
    const rust = [];
    let rustHash;
    for (let r = 0; r < RUNS; r++) {
      const v = JSON.parse(execFileSync(bin, ["verify", repoDir, "--json"], { encoding: "utf8" }));
      rust.push(v.decode_msamples_per_s);
      rustHash = v.decoded_sha256;
    }
    const rustRate = median(rust);
    for (const which of ["whole", "refiners"]) {
      const nodeCalls = [];
      const nodeDecodes = [];
      let hash;
      for (let r = 0; r < RUNS; r++) {
        const t = performance.now();
        const { channels, decodeSeconds } = await reconstruct(meta, decoded, which);
        nodeCalls.push((performance.now() - t) / 1000);
        nodeDecodes.push(decodeSeconds);
        if (r === 0) hash = await canonicalSha256(channels);
      }

      const browserRuns = await page.evaluate(
        async ({ origin, meta, blobs, runs, which }) => {
          const { reconstruct, canonicalSha256 } = await import(`${origin}/demo/js/reconstruct.mjs`);
          const { loadWasm } = await import(`${origin}/demo/js/wasm.mjs`);
          const bytes = new Map();
          for (const [k, v] of Object.entries(blobs)) {
            const s = atob(v);
            const u = new Uint8Array(s.length);
            for (let i = 0; i < s.length; i++) u[i] = s.charCodeAt(i);
            bytes.set(k, u);
          }
          await loadWasm();
          const calls = [];
          const decodes = [];
          let hash;
          for (let r = 0; r < runs; r++) {
            const t = performance.now();
            const { channels, decodeSeconds } = await reconstruct(meta, bytes, which);
            calls.push((performance.now() - t) / 1000);
            decodes.push(decodeSeconds);
            if (r === 0) hash = await canonicalSha256(channels);
          }
          return { calls, decodes, hash };
        },
        { origin: url, meta, blobs, runs: RUNS, which },
      );

      const rate = (seconds) => samples / median(seconds) / 1e6;
      const nodeRate = rate(nodeDecodes);
      const chromeRate = rate(browserRuns.decodes);
      process.stdout.write(
        JSON.stringify({
          repo: name,
          decoder: which,
          samples,
          runs: RUNS,
          same_hash: hash === rustHash && browserRuns.hash === rustHash,
          rust_msamples_per_s: rustRate,
          node_msamples_per_s: nodeRate,
          chromium_msamples_per_s: chromeRate,
          node_over_rust: nodeRate / rustRate,
          chromium_over_rust: chromeRate / rustRate,
          node_call_msamples_per_s: rate(nodeCalls),
          chromium_call_msamples_per_s: rate(browserRuns.calls),
        }) + "\n",
      );
    }
  }
} finally {
  await browser.close();
}
