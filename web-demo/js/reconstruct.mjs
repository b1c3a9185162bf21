// The full-resolution reconstruction of a repository, and its hash in the canonical
// layout of docs/blob-format.md ("Reconstruction hash"): every point in the domain's
// sample order, its channels' decoded integers one after another, each i32 little-endian.
// `quincunx verify --json` prints the same hash as `decoded_sha256`.

import { reconstructPlanar } from "./planar.mjs";
import { reconstructSphere } from "./sphere.mjs";

/// Decodes every blob of a repository through the refiners (the code the viewer runs).
/// `getBlob(centre)` gives a diamond's stored bytes (`null` = a leaf). Returns one
/// Int32Array per channel in the domain's sample order.
export function reconstruct(meta, getBlob) {
  if (meta.domain === "planar") return reconstructPlanar(meta, getBlob);
  if (meta.domain === "sphere") return reconstructSphere(meta, getBlob);
  throw new Error(`unknown domain ${JSON.stringify(meta.domain)}`);
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
