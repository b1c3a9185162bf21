// Decoding off the main thread: a module Web Worker running the WebAssembly module's
// decoder (web/src/decode.rs): the bytes of one answer (a blob, or a package carrying
// small owned children's blobs) to decoded details, as the native client's network
// thread decodes them. client.mjs runs a small pool of these.
//
// Protocol (structured clone; buffers are transferred):
//   in  {type: "init", open}   (the session's repositories: wasm.mjs `decoder(open)`)
//   in  {type: "decode", job, layer, key: [x, y, z], bytes: ArrayBuffer, packaged}
//   out {job, ok: true, details: ArrayBuffer}   (web/src/wire.rs)
//   out {job, ok: false, error: "message"}

import { loadWasm } from "./wasm.mjs";

let decoder = null;

self.onmessage = async (event) => {
  const msg = event.data;
  if (msg.type === "init") {
    decoder = loadWasm().then((wasm) => wasm.decoder(msg.open));
    // A failure is reported with each job.
    decoder.catch(() => {});
    return;
  }
  if (msg.type !== "decode") return;
  try {
    if (decoder === null) throw new Error("decoder not initialised");
    const d = await decoder;
    const details = d.decode(msg.layer, msg.key, new Uint8Array(msg.bytes), msg.packaged);
    self.postMessage({ job: msg.job, ok: true, details: details.buffer }, [details.buffer]);
  } catch (e) {
    self.postMessage({ job: msg.job, ok: false, error: e?.message ?? String(e) });
  }
};
