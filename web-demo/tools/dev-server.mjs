#!/usr/bin/env node
// A tiny development server for the web demo: serves web-demo/ from disk at /demo/<path>,
// index.html at / and /view (as `quincunx serve` does from the files compiled into its
// binary), and proxies every other path (/repos, blobs, packages, metadata) to a running
// quincunx server. Edit the JavaScript, reload the page; no Rust rebuild.
//
//   node web-demo/tools/dev-server.mjs [--port 8081] [--addr 127.0.0.1]
//                                      [--upstream http://127.0.0.1:8080]

import { createReadStream, statSync } from "node:fs";
import http from "node:http";
import path from "node:path";
import { fileURLToPath } from "node:url";

const root = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..");

function options(argv) {
  const out = { port: 8081, addr: "127.0.0.1", upstream: "http://127.0.0.1:8080" };
  for (let k = 0; k < argv.length; k++) {
    const [flag, inline] = argv[k].split("=", 2);
    const value = () => (inline !== undefined ? inline : argv[++k]);
    if (flag === "--port") out.port = Number(value());
    else if (flag === "--addr") out.addr = value();
    else if (flag === "--upstream") out.upstream = value();
    else if (flag === "--help" || flag === "-h") {
      process.stdout.write("usage: dev-server.mjs [--port 8081] [--addr 127.0.0.1] [--upstream http://127.0.0.1:8080]\n");
      process.exit(0);
    } else {
      process.stderr.write(`unknown argument ${argv[k]}\n`);
      process.exit(2);
    }
  }
  if (!Number.isInteger(out.port) || out.port < 0 || out.port > 65535) {
    process.stderr.write(`--port ${out.port} is not a port\n`);
    process.exit(2);
  }
  return out;
}

const TYPES = {
  ".html": "text/html; charset=utf-8",
  ".mjs": "text/javascript; charset=utf-8",
  ".js": "text/javascript; charset=utf-8",
  ".css": "text/css; charset=utf-8",
  ".json": "application/json",
  ".png": "image/png",
  ".svg": "image/svg+xml",
  ".md": "text/markdown; charset=utf-8",
};

function sendFile(res, file, method) {
  let st;
  try {
    st = statSync(file);
  } catch {
    st = null;
  }
  if (!st || !st.isFile()) {
    res.writeHead(404, { "content-type": "text/plain", "cache-control": "no-store" });
    res.end("not found\n");
    return;
  }
  res.writeHead(200, {
    "content-type": TYPES[path.extname(file)] || "application/octet-stream",
    "content-length": st.size,
    "cache-control": "no-cache",
  });
  if (method === "HEAD") res.end();
  else createReadStream(file).pipe(res);
}

function proxy(req, res, upstream) {
  const target = new URL(req.url, upstream);
  const headers = { ...req.headers, host: target.host };
  const out = http.request(target, { method: req.method, headers }, (up) => {
    res.writeHead(up.statusCode || 502, up.headers);
    up.pipe(res);
  });
  out.on("error", (e) => {
    if (!res.headersSent) res.writeHead(502, { "content-type": "text/plain", "cache-control": "no-store" });
    res.end(`upstream ${upstream}: ${e.message}\n`);
  });
  req.pipe(out);
}

function main() {
  const opt = options(process.argv.slice(2));
  const server = http.createServer((req, res) => {
    const url = new URL(req.url, "http://localhost");
    const p = url.pathname;
    if ((req.method === "GET" || req.method === "HEAD") && (p === "/" || p === "/view" || p === "/index.html")) {
      sendFile(res, path.join(root, "index.html"), req.method);
    } else if ((req.method === "GET" || req.method === "HEAD") && p.startsWith("/demo/")) {
      const rel = decodeURIComponent(p.slice("/demo/".length));
      const file = path.resolve(root, rel);
      if (!file.startsWith(root + path.sep) || rel.split("/").some((s) => s.startsWith("."))) {
        res.writeHead(404, { "content-type": "text/plain" });
        res.end("not found\n");
      } else {
        sendFile(res, file, req.method);
      }
    } else {
      proxy(req, res, opt.upstream);
    }
  });
  server.listen(opt.port, opt.addr, () => {
    const a = server.address();
    process.stdout.write(`web demo on http://${a.address}:${a.port}/ (files from ${root}, API from ${opt.upstream})\n`);
  });
}

main();
