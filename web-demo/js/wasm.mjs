// The quincunx WebAssembly module (js/quincunx.wasm, built from the `quincunx-web` crate by
// web-demo/build-wasm.sh): the Rust decoder and client core, behind a small ABI of numbers
// and byte buffers (web/src/abi.rs is the other side). One instance per thread: the page's
// client and each decoding worker load their own.
//
//   const wasm = await loadWasm();
//   const decoder = wasm.decoder(open);       // open: {elevation: {name, meta}, colour, config}
//   decoder.decode(layer, key, bytes, packaged) -> Uint8Array (the details, web/src/wire.rs)
//   const client = wasm.client(open, nowMs);  // see client.mjs
//   wasm.reconstruct(meta, blobs, which)      // a whole repository (tools/decode-repo.mjs)
//   wasm.packFirst(url, answer) -> {fileLen, openLen}; wasm.packOpen(...) -> PackFile
//                                             // a repository file read by ranges (client.mjs)
//
// Failures inside the module are WasmError with the Rust message; bad input never traps.

/** A call the module refused, with its message. */
export class WasmError extends Error {
  constructor(message) {
    super(message);
    this.name = "WasmError";
  }
}

let loading = null;

/** The module's bytes: read from disk under node, fetched in a browser. */
async function moduleBytes(url) {
  if (globalThis.process?.versions?.node && url.protocol === "file:") {
    const { readFile } = await import("node:fs/promises");
    return readFile(url);
  }
  const response = await fetch(url);
  if (!response.ok) throw new WasmError(`loading ${url}: HTTP ${response.status}`);
  return response.arrayBuffer();
}

/** Loads (once per thread) and instantiates the module. */
export function loadWasm(url = new URL("./quincunx.wasm", import.meta.url)) {
  if (loading === null) {
    loading = (async () => {
      const bytes = await moduleBytes(url);
      const { instance } = await WebAssembly.instantiate(bytes, {
        env: { qx_now_ms: () => performance.now() },
      });
      return new Wasm(instance.exports);
    })();
    loading.catch(() => {
      loading = null;
    });
  }
  return loading;
}

const encoder = new TextEncoder();
/// The decoders of `reconstruct`, by their ABI codes (web/src/reconstruct.rs).
const DECODERS = { whole: 0, refiners: 1 };
const decoder = new TextDecoder();

/** The instance and its calls. */
export class Wasm {
  constructor(exports) {
    this.x = exports;
  }

  /** Copies `bytes` (Uint8Array) into the module's input buffer; returns its length. */
  input(bytes) {
    const ptr = this.x.qx_input(bytes.length);
    new Uint8Array(this.x.memory.buffer, ptr, bytes.length).set(bytes);
    return bytes.length;
  }

  /** A copy of the output buffer. */
  output() {
    const ptr = this.x.qx_output_ptr();
    const len = this.x.qx_output_len();
    return new Uint8Array(this.x.memory.buffer.slice(ptr, ptr + len));
  }

  /** The output as text. */
  text() {
    return decoder.decode(this.output());
  }

  /** Throws the module's message when `status` says the call failed. */
  check(status) {
    if (status < 0) throw new WasmError(this.text());
    return status;
  }

  /** Input bytes of a JSON value. */
  json(value) {
    return this.input(encoder.encode(JSON.stringify(value)));
  }

  /** A decoder of a session's answers. */
  decoder(open) {
    const h = this.check(this.x.qx_decoder_new(this.json(open)));
    return new AnswerDecoder(this, h);
  }

  /**
   * The first read of repository file `url` (web/src/pack.rs `PackReader::first`):
   * `answer` = {status, contentRange, etag, body}. Returns {fileLen, openLen}.
   */
  packFirst(url, answer) {
    const buf = concat([lengthPrefixed(encoder.encode(url)), rangeAnswer(answer)]);
    this.check(this.x.qx_pack_first(this.input(buf)));
    const v = new DataView(this.output().buffer);
    return { fileLen: v.getFloat64(0, true), openLen: v.getFloat64(8, true) };
  }

  /**
   * Opens repository file `url` from its first read (`first`: packFirst's figures,
   * `etag` and `body` of the first answer) and, when opening needs more, `rest` (the
   * answer to reading from the first body's end to `openLen`). A PackFile.
   */
  packOpen(url, first, etag, body, rest) {
    const head = new Uint8Array(16);
    const v = new DataView(head.buffer);
    v.setFloat64(0, first.fileLen, true);
    v.setFloat64(8, first.openLen, true);
    const parts = [lengthPrefixed(encoder.encode(url)), head, lengthPrefixed(encoder.encode(etag ?? "")), lengthPrefixed(body)];
    parts.push(Uint8Array.of(rest ? 1 : 0));
    if (rest) parts.push(rangeAnswer(rest));
    const h = this.check(this.x.qx_pack_new(this.input(concat(parts))));
    const info = JSON.parse(this.text());
    return new PackFile(this, h, info);
  }

  /** A client of a session at `nowMs`. */
  client(open, nowMs) {
    const h = this.check(this.x.qx_client_new(this.json(open), nowMs));
    return new WasmClient(this, h);
  }

  /**
   * A whole repository at full resolution: `meta` (metadata.json), `blobs` (Map "x/y" or
   * "x/y/z" -> Uint8Array), `which` decoder: "whole" (the whole-raster decoder `quincunx verify`
   * runs) or "refiners" (one diamond at a time, as a viewer refines). Returns `channels`,
   * one Int32Array per channel in the canonical sample order (docs/blob-format.md,
   * "Reconstruction hash"; both decoders give the same values), and `decodeSeconds`, the
   * decode alone as the module timed it (as `quincunx verify` times its decode: not
   * parsing the metadata, building the geometry or copying bytes in and out).
   */
  reconstruct(meta, blobs, which = "whole") {
    const code = DECODERS[which];
    if (code === undefined) throw new Error(`unknown decoder ${which}: whole or refiners`);
    const metaBytes = encoder.encode(JSON.stringify(meta));
    let size = 4 + metaBytes.length + 4;
    for (const b of blobs.values()) size += 24 + 4 + b.length;
    const buf = new Uint8Array(size);
    const view = new DataView(buf.buffer);
    let at = 0;
    view.setUint32(at, metaBytes.length, true);
    buf.set(metaBytes, 4);
    at = 4 + metaBytes.length;
    view.setUint32(at, blobs.size, true);
    at += 4;
    for (const [name, bytes] of blobs) {
      const parts = name.split("/").map(Number);
      for (let k = 0; k < 3; k++) {
        view.setBigInt64(at, BigInt(parts[k] ?? 0), true);
        at += 8;
      }
      view.setUint32(at, bytes.length, true);
      at += 4;
      buf.set(bytes, at);
      at += bytes.length;
    }
    this.check(this.x.qx_reconstruct(this.input(buf), code));
    const out = this.output();
    const v = new DataView(out.buffer);
    const channels = v.getUint32(0, true);
    const samples = v.getUint32(4, true);
    const decodeSeconds = v.getFloat64(8, true);
    // Views of the one copy: the values start at byte 16, 4-byte aligned.
    const result = [];
    for (let c = 0; c < channels; c++) result.push(new Int32Array(out.buffer, 16 + c * samples * 4, samples));
    return { channels: result, decodeSeconds };
  }
}

/** Writes the common header `u8 layer, u8 flag, key (3 x i64)` into a buffer. */
function header(layer, flag, key, extra) {
  const buf = new Uint8Array(26 + extra);
  const view = new DataView(buf.buffer);
  buf[0] = layer;
  buf[1] = flag;
  for (let k = 0; k < 3; k++) view.setBigInt64(2 + 8 * k, BigInt(key[k] ?? 0), true);
  return buf;
}

/** A decoding worker's decoder (web/src/decode.rs). */
export class AnswerDecoder {
  constructor(wasm, handle) {
    this.wasm = wasm;
    this.h = handle;
  }

  /** The details of answer `bytes` to `key` of `layer` (0 elevation, 1 colour). */
  decode(layer, key, bytes, packaged) {
    const buf = header(layer, packaged ? 1 : 0, key, bytes.length);
    buf.set(bytes, 26);
    const w = this.wasm;
    w.check(w.x.qx_decoder_decode(this.h, w.input(buf)));
    return w.output();
  }

  free() {
    this.wasm.x.qx_free(this.h);
  }
}

/** Bytes joined. */
function concat(parts) {
  const out = new Uint8Array(parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) {
    out.set(p, at);
    at += p.length;
  }
  return out;
}

/** `u32 length, bytes` (web/src/wire.rs `bytes`). */
function lengthPrefixed(bytes) {
  const out = new Uint8Array(4 + bytes.length);
  new DataView(out.buffer).setUint32(0, bytes.length, true);
  out.set(bytes, 4);
  return out;
}

/** An HTTP answer to a range read: `u32 status, bytes content_range, bytes etag, body`. */
function rangeAnswer({ status, contentRange, etag, body }) {
  const s = new Uint8Array(4);
  new DataView(s.buffer).setUint32(0, status, true);
  return concat([s, lengthPrefixed(encoder.encode(contentRange ?? "")), lengthPrefixed(encoder.encode(etag ?? "")), body]);
}

/**
 * A repository file read by HTTP range requests (web/src/pack.rs `PackReader`): the keys
 * the planner picks become range requests; their answers become the blobs and packages
 * a server would have answered. Steps: {leaves: [key], answers: [{key, kind, payload}]
 * (kind and payload as `WasmClient.answerRaw` takes them), requests: [{tag, offset,
 * len}]}.
 */
export class PackFile {
  constructor(wasm, handle, info) {
    this.wasm = wasm;
    this.h = handle;
    this.meta = info.meta;
    this.etag = info.etag;
    this.fileLen = info.fileLen;
  }

  /** What fetching `requests` ([{key, packaged}], as WasmClient.plan gives them) takes. */
  plan(requests) {
    const buf = new Uint8Array(4 + 25 * requests.length);
    const view = new DataView(buf.buffer);
    view.setUint32(0, requests.length, true);
    requests.forEach(({ key, packaged }, i) => {
      const at = 4 + 25 * i;
      buf[at] = packaged ? 1 : 0;
      for (let k = 0; k < 3; k++) view.setBigInt64(at + 1 + 8 * k, BigInt(key[k] ?? 0), true);
    });
    const w = this.wasm;
    w.check(w.x.qx_pack_plan(this.h, w.input(buf)));
    return parseStep(w.output());
  }

  /**
   * The answer to range request `tag`: {status, contentRange, etag, body}, or {error}
   * (a failed fetch), or {timeoutMs}.
   */
  answered(tag, answer) {
    const head = new Uint8Array(9);
    new DataView(head.buffer).setFloat64(0, tag, true);
    let rest;
    if (answer.error !== undefined) {
      head[8] = 1;
      rest = encoder.encode(answer.error);
    } else if (answer.timeoutMs !== undefined) {
      head[8] = 2;
      rest = new Uint8Array(8);
      new DataView(rest.buffer).setFloat64(0, answer.timeoutMs, true);
    } else {
      head[8] = 0;
      rest = rangeAnswer(answer);
    }
    const w = this.wasm;
    w.check(w.x.qx_pack_answered(this.h, w.input(concat([head, rest]))));
    return parseStep(w.output());
  }

  free() {
    this.wasm.x.qx_free(this.h);
  }
}

/** A range reader's step (web/src/api.rs `write_step`). */
function parseStep(out) {
  const view = new DataView(out.buffer, out.byteOffset, out.byteLength);
  let at = 0;
  const u32 = () => {
    const v = view.getUint32(at, true);
    at += 4;
    return v;
  };
  const f64 = () => {
    const v = view.getFloat64(at, true);
    at += 8;
    return v;
  };
  const key = () => {
    const k = [0, 1, 2].map((i) => Number(view.getBigInt64(at + 8 * i, true)));
    at += 24;
    return k;
  };
  const leaves = [];
  for (let n = u32(); n > 0; n--) leaves.push(key());
  const answers = [];
  for (let n = u32(); n > 0; n--) {
    const k = key();
    const kind = out[at++];
    const len = u32();
    answers.push({ key: k, kind, payload: out.slice(at, at + len) });
    at += len;
  }
  const requests = [];
  for (let n = u32(); n > 0; n--) requests.push({ tag: f64(), offset: f64(), len: f64() });
  return { leaves, answers, requests, overheadBytes: f64() };
}

/** Answer kinds (web/src/api.rs `client_answer`). */
const HTTP = 0;
const CONNECTION = 1;
const TIMEOUT = 2;

/** The client core with its planners (web/src/client.rs); client.mjs drives it. */
export class WasmClient {
  constructor(wasm, handle) {
    this.wasm = wasm;
    this.h = handle;
  }

  /** An HTTP answer; returns 0, or 1 / 2: decode the body bare / as a package. */
  answer(layer, key, status, body, nowMs) {
    const buf = header(layer, HTTP, key, 4 + body.length);
    new DataView(buf.buffer).setUint32(26, status, true);
    buf.set(body, 30);
    const w = this.wasm;
    return w.check(w.x.qx_client_answer(this.h, w.input(buf), nowMs));
  }

  /**
   * An answer as a range reader's step gives it: `kind` (0 HTTP, 1 connection failure, 2
   * timeout, 3 the file changed, 4 malformed) and its payload. Returns as `answer`.
   */
  answerRaw(layer, kind, key, payload, nowMs) {
    const buf = header(layer, kind, key, payload.length);
    buf.set(payload, 26);
    const w = this.wasm;
    return w.check(w.x.qx_client_answer(this.h, w.input(buf), nowMs));
  }

  /** A request that failed without an answer: `timeout` true for a timeout. */
  failed(layer, key, message, timeoutMs, nowMs) {
    let buf;
    if (timeoutMs !== null) {
      buf = header(layer, TIMEOUT, key, 8);
      new DataView(buf.buffer).setFloat64(26, timeoutMs, true);
    } else {
      const text = encoder.encode(message);
      buf = header(layer, CONNECTION, key, text.length);
      buf.set(text, 26);
    }
    const w = this.wasm;
    return w.check(w.x.qx_client_answer(this.h, w.input(buf), nowMs));
  }

  /** A worker's decoding of `key`'s body. */
  decoded(layer, key, details, nowMs) {
    const buf = header(layer, 0, key, details.length);
    buf.set(details, 26);
    const w = this.wasm;
    w.check(w.x.qx_client_decoded(this.h, w.input(buf), nowMs));
  }

  /** A worker refused `key`'s body. */
  decodeFailed(layer, key, reason, nowMs) {
    const text = encoder.encode(reason);
    const buf = header(layer, 0, key, text.length);
    buf.set(text, 26);
    const w = this.wasm;
    w.check(w.x.qx_client_decode_failed(this.h, w.input(buf), nowMs));
  }

  /** One frame (see client.mjs `update`): {fullQuality, settled, converged}. */
  frame(camera, viewportPx, tolerancePx, nowMs, budgetMs) {
    const buf = new Uint8Array(11 * 8 + 8);
    const view = new DataView(buf.buffer);
    const values = [...camera.position, ...camera.forward, ...camera.up, camera.fovYRad, tolerancePx];
    values.forEach((x, k) => view.setFloat64(8 * k, x, true));
    view.setUint32(88, viewportPx[0], true);
    view.setUint32(92, viewportPx[1], true);
    const w = this.wasm;
    const flags = w.check(w.x.qx_client_frame(this.h, w.input(buf), nowMs, budgetMs));
    return { fullQuality: (flags & 1) !== 0, settled: (flags & 2) !== 0, converged: (flags & 4) !== 0 };
  }

  /** The requests to send now: [{layer, key: [x, y, z], packaged}]. */
  plan(nowMs) {
    const w = this.wasm;
    w.check(w.x.qx_client_plan(this.h, nowMs));
    const out = w.output();
    const view = new DataView(out.buffer);
    const n = view.getUint32(0, true);
    const requests = [];
    let at = 4;
    for (let i = 0; i < n; i++) {
      const layer = out[at];
      const packaged = out[at + 1] === 1;
      const key = [0, 1, 2].map((k) => Number(view.getBigInt64(at + 2 + 8 * k, true)));
      requests.push({ layer, key, packaged });
      at += 26;
    }
    return requests;
  }

  /** Milliseconds until a retry is due (-1: none). */
  wakeIn(nowMs) {
    const t = this.wasm.x.qx_client_wake_in(this.h, nowMs);
    if (t === -2) throw new WasmError(this.wasm.text());
    return t;
  }

  /**
   * What entered and left the cut: {left: [{key, half}], entered: [{key, half,
   * generation, level, affine: {base, e1, e2} | null, corners, grid, colour}]}; keys are
   * [x, y, z] (planar z = 0).
   */
  changes() {
    const w = this.wasm;
    w.check(w.x.qx_client_changes(this.h));
    const out = w.output();
    const view = new DataView(out.buffer);
    let at = 0;
    const u32 = () => {
      const v = view.getUint32(at, true);
      at += 4;
      return v;
    };
    const i64 = () => {
      const v = Number(view.getBigInt64(at, true));
      at += 8;
      return v;
    };
    const key = () => [i64(), i64(), i64()];
    const i32s = () => {
      const n = u32();
      at += (4 - (at % 4)) % 4;
      const a = new Int32Array(out.buffer.slice(at, at + 4 * n));
      at += 4 * n;
      return a;
    };
    const left = [];
    for (let i = u32(); i > 0; i--) {
      const k = key();
      left.push({ key: k, half: out[at++] });
    }
    const entered = [];
    for (let i = u32(); i > 0; i--) {
      const k = key();
      const half = out[at++];
      const generation = i64();
      const level = u32();
      const hasAffine = out[at++] === 1;
      const affine = hasAffine ? { base: key(), e1: key(), e2: key() } : null;
      const corners = [key(), key(), key(), key()];
      const grid = i32s();
      const channels = u32();
      let colour = null;
      if (channels > 0) {
        colour = [];
        for (let c = 0; c < channels; c++) colour.push(i32s());
      }
      entered.push({ key: k, half, generation, level, affine, corners, grid, colour });
    }
    return { left, entered };
  }

  restart() {
    this.wasm.check(this.wasm.x.qx_client_restart(this.h));
  }

  setMaxCutHalves(max) {
    this.wasm.check(this.wasm.x.qx_client_set_max_cut_halves(this.h, max ?? -1));
  }

  /** {frame (the renderer's world frame), metric}. */
  info() {
    this.wasm.check(this.wasm.x.qx_client_info(this.h));
    return JSON.parse(this.wasm.text());
  }

  stats() {
    this.wasm.check(this.wasm.x.qx_client_stats(this.h));
    return JSON.parse(this.wasm.text());
  }

  checkCut() {
    this.wasm.check(this.wasm.x.qx_client_check(this.h));
    return JSON.parse(this.wasm.text());
  }

  heightRange() {
    this.wasm.check(this.wasm.x.qx_client_height_range(this.h));
    const v = new DataView(this.wasm.output().buffer);
    return [v.getFloat64(0, true), v.getFloat64(8, true)];
  }

  free() {
    this.wasm.x.qx_free(this.h);
  }
}
