// The full-resolution reconstruction of a repository, and its hash in the canonical
// layout of docs/blob-format.md ("Reconstruction hash"): every point in the domain's
// sample order, its channels' decoded integers one after another, each i32 little-endian.
// `quincunx verify --json` prints the same hash as `decoded_sha256`.
//
// The reconstruction runs in the WebAssembly module (web/src/reconstruct.rs: the Rust
// whole-raster decoder `quincunx verify` runs, or the refiners, level by level, as a
// client refines); this file adds the hash.

import { loadWasm } from "./wasm.mjs";

/// Decodes every blob of a repository. `meta` is its metadata.json, `blobs` a Map of every
/// stored blob by centre ("x/y" on the plane, "x/y/z" on a planet) to its bytes
/// (Uint8Array; a missing diamond is a leaf), `which` the decoder ("whole" or
/// "refiners": the same values). Resolves to `{channels, decodeSeconds}`: one Int32Array
/// per channel in the domain's sample order, and the decode alone as the module timed it
/// (Wasm.reconstruct); rejects with the module's message (WasmError) on bad metadata, a
/// corrupt blob or a blob of no diamond.
export async function reconstruct(meta, blobs, which = "whole") {
  return (await loadWasm()).reconstruct(meta, blobs, which);
}

/// The canonical bytes of `channels` (equal lengths), interleaved per point.
export function canonicalBytes(channels) {
  const count = channels.length;
  const len = count ? channels[0].length : 0;
  for (const c of channels) {
    if (c.length !== len) throw new Error("channels of different lengths");
  }
  const out = new Int32Array(len * count);
  for (let c = 0; c < count; c++) {
    const src = channels[c];
    for (let k = 0, o = c; k < len; k++, o += count) out[o] = src[k];
  }
  // Int32Array is in the platform's byte order; every platform node and browsers run on
  // is little-endian, and the check below refuses any other.
  if (new Uint8Array(new Uint32Array([1]).buffer)[0] !== 1) {
    throw new Error("big-endian platform: canonical bytes need byte swapping");
  }
  return new Uint8Array(out.buffer);
}

/// SHA-256 (hex) of the canonical bytes: node's crypto, or WebCrypto in a browser.
export async function canonicalSha256(channels) {
  const bytes = canonicalBytes(channels);
  if (globalThis.process?.versions?.node) {
    const { createHash } = await import("node:crypto");
    return createHash("sha256").update(bytes).digest("hex");
  }
  const digest = await crypto.subtle.digest("SHA-256", bytes);
  return [...new Uint8Array(digest)].map((b) => b.toString(16).padStart(2, "0")).join("");
}
