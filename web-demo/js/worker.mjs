// Decoding off the main thread: a module Web Worker that turns the bytes of one answer
// (a blob, or a package carrying small owned children's blobs) into decoded details,
// what the Rust client's network thread does (client/src/session.rs `Layer::spawn`'s
// decode and `Packing::unpack`, client-core/src/colour.rs `ColourLayer::decode`).
//
// The same code runs inline: client.mjs imports `AnswerDecoder` and calls it directly
// when `Worker` does not exist (node tests) or a worker cannot start.
//
// Protocol (structured clone; the detail arrays are transferred, not copied):
//   in  {type: "init", layers: [{meta, kind: "elevation" | "colour"}, ...]}
//   in  {type: "decode", job, layer, key: [x, y, z], bytes: ArrayBuffer, packaged}
//   out {job, ok: true, value, carried: [[key, value], ...]}
//   out {job, ok: false, error: "message"}
// A value is plain data keyed by blob centres (ids do not survive structured clone):
//   elevation: {h: Int32Array(N^2), childClasses: [[key, class], ...], emptyChildren: [key, ...]}
//   colour:    {channels: [elevation-like value | null, x3]} (null: no details in that channel)
// client.mjs turns keys back into ids (`rehydrate`).

import { DecodeError, parsePackage, splitChannels } from "./codec.mjs";
import { PlanarRefiner } from "./planar.mjs";
import { SphereRefiner } from "./sphere.mjs";

/** Channels of a colour repository (Y, Co, Cg). */
export const COLOUR_CHANNELS = 3;

/** Decodes answers of one or more repositories (a session's layers). */
export class AnswerDecoder {
  /** `layers`: `[{meta, kind: "elevation" | "colour"}]` (metadata.json objects). */
  constructor(layers) {
    this._layers = layers.map(({ meta, kind }) => {
      const Refiner = meta.domain === "sphere" ? SphereRefiner : PlanarRefiner;
      const count = kind === "colour" ? COLOUR_CHANNELS : 1;
      const refiners = [];
      for (let k = 0; k < count; k++) refiners.push(Refiner.fromMetadata(meta, k));
      return { Refiner, refiners, colour: kind === "colour", levels: meta.levels };
    });
  }

  /**
   * Decodes the answer `bytes` (Uint8Array) of `key` in layer `layer`; `packaged`: it was
   * asked for as a package. Returns `{value, carried, transfer}` (`transfer`: the
   * ArrayBuffers a worker may hand over). Throws DecodeError (or a subclass) on bad bytes.
   */
  decode(layer, key, bytes, packaged) {
    const l = this._layers[layer];
    if (l === undefined) throw new DecodeError(`no layer ${layer}`);
    const transfer = [];
    const carried = [];
    const value = packaged
      ? this._unpack(l, key, bytes, carried, transfer)
      : this._decodeOne(l, key, bytes, transfer);
    return { value, carried, transfer };
  }

  /** Packing::unpack: the own blob, then the carried owned children, recursively. */
  _unpack(l, key, bytes, carried, transfer) {
    const parsed = parsePackage(bytes, true);
    const value = this._decodeOne(l, key, parsed.blob, transfer);
    if (parsed.children.length === 0) return value;
    const refiner = l.refiners[0];
    const domain = refiner.domain();
    const id = l.Refiner.idOf(key);
    const level = domain.level(id);
    if (level + 1 >= l.levels) throw new DecodeError(`a level ${level} answer carries children`);
    const owned = domain.children(id).filter((c) => {
      const p = domain.parents(c);
      return p.length > 0 && p[0].equals(id);
    });
    for (const [i, part] of parsed.children) {
      const child = owned[i];
      if (child === undefined) throw new DecodeError(`carries owned child ${i} of ${owned.length}`);
      const childKey = l.Refiner.keyOf(child);
      const v = this._unpack(l, childKey, part, carried, transfer);
      carried.push([childKey, v]);
    }
    return value;
  }

  /** One blob of one diamond: its details (all channels of a colour blob). */
  _decodeOne(l, key, bytes, transfer) {
    const id = l.Refiner.idOf(key);
    if (!l.colour) return plain(l.Refiner, l.refiners[0].decode(id, bytes), transfer);
    const parts = splitChannels(bytes, COLOUR_CHANNELS);
    return {
      channels: parts.map((part, k) =>
        part === null ? null : plain(l.Refiner, l.refiners[k].decode(id, part), transfer),
      ),
    };
  }
}

/** Details with ids as plain data with keys (structured-clone friendly). */
function plain(Refiner, d, transfer) {
  transfer.push(d.h.buffer);
  return {
    h: d.h,
    childClasses: d.childClasses.map(([c, k]) => [Refiner.keyOf(c), k]),
    emptyChildren: d.emptyChildren.map((c) => Refiner.keyOf(c)),
  };
}

// The worker side: runs only inside a dedicated worker.
const inWorker =
  typeof WorkerGlobalScope !== "undefined" &&
  typeof self !== "undefined" &&
  self instanceof WorkerGlobalScope; // eslint-disable-line no-undef

if (inWorker) {
  let decoder = null;
  let initError = null;
  self.onmessage = (event) => {
    const msg = event.data;
    if (msg.type === "init") {
      try {
        decoder = new AnswerDecoder(msg.layers);
        initError = null;
      } catch (e) {
        initError = e?.message ?? String(e);
      }
      return;
    }
    if (msg.type !== "decode") return;
    if (decoder === null) {
      self.postMessage({ job: msg.job, ok: false, error: `decoder not ready: ${initError}` });
      return;
    }
    try {
      const { value, carried, transfer } = decoder.decode(
        msg.layer,
        msg.key,
        new Uint8Array(msg.bytes),
        msg.packaged,
      );
      // A buffer may appear once in a transfer list.
      self.postMessage({ job: msg.job, ok: true, value, carried }, [...new Set(transfer)]);
    } catch (e) {
      self.postMessage({ job: msg.job, ok: false, error: e?.message ?? String(e) });
    }
  };
}
