#!/usr/bin/env node
// Decodes every blob of a static export (`quincunx export <repo> <dir>`) with the
// WebAssembly module (web/src/reconstruct.rs: the whole-raster decoder `quincunx verify`
// runs, or with `--decoder refiners` the refiners a viewer runs) and prints the
// reconstruction's size and hash, in the canonical layout of docs/blob-format.md, as one
// JSON line:
//   {"repo": .., "domain": .., "decoder": .., "channels": .., "samples": .., "sha256": .., ...}
// `samples` is the number of points in the layout (width x height, or 6 (2S+1)^2 for a
// planet: every copy of cube-edge points); `quincunx verify <repo> --json` prints the same
// hash as `decoded_sha256`. `decode_*` is the decode alone as the module times it (what
// `quincunx verify` times), `call_*` the module's whole call (the blob files read into
// memory and the module loaded first; copying the blobs in and the values out, parsing
// the metadata and building the geometry count); both count samples as `quincunx verify`
// does. A blob file of no diamond, a corrupt blob or bad metadata fails with the
// module's message.
//
// Usage: node web-demo/tools/decode-repo.mjs [--decoder whole|refiners] <export dir>
//        [repository name]
// (<export dir> holds repos/<name>/metadata.json; the name may be left out when it holds
// one repository; a repos/<name> folder itself is accepted too.)

import { existsSync, readdirSync, readFileSync, statSync } from "node:fs";
import { join } from "node:path";
import { canonicalSha256, reconstruct } from "../js/reconstruct.mjs";
import { loadWasm } from "../js/wasm.mjs";

function fail(message) {
  process.stderr.write(`decode-repo: ${message}\n`);
  process.exit(1);
}

/// The repository folder (holding metadata.json) named by the arguments.
function repoDir(dir, name) {
  if (existsSync(join(dir, "metadata.json"))) return dir;
  const repos = join(dir, "repos");
  if (!existsSync(repos)) fail(`${dir} holds neither metadata.json nor repos/`);
  if (name) return join(repos, name);
  const names = readdirSync(repos).filter((n) => existsSync(join(repos, n, "metadata.json")));
  if (names.length !== 1) {
    fail(`${repos} holds ${names.length} repositories (${names.join(", ")}): name one`);
  }
  return join(repos, names[0]);
}

/// Every blob file of the export, by centre ("x/y" or "x/y/z").
function readBlobs(dir, version) {
  const root = join(dir, "v", version, "d");
  const blobs = new Map();
  let bytes = 0;
  const walk = (path, parts) => {
    for (const entry of readdirSync(path)) {
      const p = join(path, entry);
      const next = [...parts, entry];
      if (statSync(p).isDirectory()) walk(p, next);
      else {
        // Only centres reach the module (which names any of no diamond).
        if (next.length < 2 || next.length > 3 || !next.every((s) => /^-?[0-9]+$/.test(s))) {
          fail(`blob file ${next.join("/")} belongs to no diamond`);
        }
        const b = readFileSync(p);
        blobs.set(next.join("/"), new Uint8Array(b.buffer, b.byteOffset, b.length));
        bytes += b.length;
      }
    }
  };
  if (existsSync(root)) walk(root, []);
  return { blobs, bytes };
}

async function main() {
  const args = process.argv.slice(2);
  let which = "whole";
  if (args[0] === "--decoder") {
    which = args[1];
    args.splice(0, 2);
    if (which !== "whole" && which !== "refiners") fail(`--decoder takes whole or refiners, not ${which}`);
  }
  const [dirArg, name] = args;
  if (!dirArg) fail("usage: decode-repo.mjs [--decoder whole|refiners] <export dir> [repository name]");
  const dir = repoDir(dirArg, name);
  let meta;
  try {
    meta = JSON.parse(readFileSync(join(dir, "metadata.json"), "utf8"));
  } catch (e) {
    fail(`reading ${join(dir, "metadata.json")}: ${e.message}`);
  }
  const version = String(meta.content_hash ?? "").slice(0, 16);
  const { blobs, bytes } = readBlobs(dir, version);
  try {
    await loadWasm();
  } catch (e) {
    fail(`loading the WebAssembly module: ${e.message}`);
  }
  const started = performance.now();
  let channels, decodeSeconds;
  try {
    ({ channels, decodeSeconds } = await reconstruct(meta, blobs, which));
  } catch (e) {
    fail(`decoding ${dir}: ${e.message}`);
  }
  const seconds = (performance.now() - started) / 1000;
  const samples = channels[0].length;
  // Decode speed counts the repository's samples as `quincunx verify` does (a planet's
  // distinct points, 6 a b + 2), so the two figures compare.
  const [a, b] = meta.extent;
  const counted = meta.domain === "sphere" ? 6 * a * b + 2 : a * b;
  const sha256 = await canonicalSha256(channels);
  process.stdout.write(
    JSON.stringify({
      repo: dir,
      domain: meta.domain,
      decoder: which,
      channels: channels.length,
      samples,
      sha256,
      blobs: blobs.size,
      blob_bytes: bytes,
      decode_seconds: decodeSeconds,
      decode_msamples_per_s: (counted * channels.length) / decodeSeconds / 1e6,
      call_seconds: seconds,
      call_msamples_per_s: (counted * channels.length) / seconds / 1e6,
    }) + "\n",
  );
}

main();
