// decode-repo.mjs against the Rust decoder: every bundled repository's export
// reconstructs to the `decoded_sha256` that `quincunx verify --json` prints, and a
// corrupt or truncated blob file makes the tool fail with a message, not a crash.
// Data: QUINCUNX_BIN, QUINCUNX_DEMO_DIR, QUINCUNX_EXPORT_DIR (set by
// repo-tools/tests/web_demo.rs), else this machine's defaults; SKIP when absent.

import { test } from "node:test";
import assert from "node:assert/strict";
import { execFileSync, spawnSync } from "node:child_process";
import { cpSync, existsSync, mkdtempSync, readdirSync, readFileSync, rmSync, statSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const workspace = join(here, "..", "..");
const tool = join(here, "..", "tools", "decode-repo.mjs");
const bin = process.env.QUINCUNX_BIN ?? join(workspace, "target", "release", "quincunx");
const demo = process.env.QUINCUNX_DEMO_DIR ?? "/work/demo";
const exported = process.env.QUINCUNX_EXPORT_DIR ?? "/work/export";

function missing(name) {
  for (const [what, path] of [["quincunx binary", bin], ["demo repositories", demo], ["exports", exported]]) {
    if (!existsSync(path)) {
      console.log(`SKIP ${name}: ${what} not found at ${path}`);
      return true;
    }
  }
  return false;
}

function decodeRepo(dir, name) {
  const r = spawnSync(process.execPath, [tool, dir, name], { encoding: "utf8" });
  return { status: r.status, out: r.stdout, err: r.stderr };
}

for (const name of ["korea", "earth", "earth_colour"]) {
  test(`${name}: the JS reconstruction hash equals quincunx verify's`, (t) => {
    if (missing(t.name)) return;
    const rust = JSON.parse(execFileSync(bin, ["verify", join(demo, name), "--json"], { encoding: "utf8" }));
    const js = decodeRepo(exported, name);
    assert.equal(js.status, 0, js.err);
    const report = JSON.parse(js.out);
    const meta = JSON.parse(readFileSync(join(exported, "repos", name, "metadata.json"), "utf8"));
    const [a, b] = meta.extent;
    const points = meta.domain === "sphere" ? 6 * (a + 1) * (a + 1) : a * b;
    assert.equal(report.samples, points);
    assert.equal(report.channels, meta.channels.length);
    assert.match(rust.decoded_sha256, /^[0-9a-f]{64}$/);
    assert.equal(report.sha256, rust.decoded_sha256);
    console.log(
      `${name}: ${report.sha256.slice(0, 16)}, JS ${report.decode_msamples_per_s.toFixed(2)} M samples/s, ` +
        `Rust ${rust.decode_msamples_per_s.toFixed(2)} M samples/s`,
    );
  });
}

/// Every blob file of an exported repository.
function blobFiles(dir) {
  const out = [];
  const walk = (p) => {
    for (const e of readdirSync(p)) {
      const q = join(p, e);
      if (statSync(q).isDirectory()) walk(q);
      else out.push(q);
    }
  };
  walk(join(dir, "v"));
  return out.sort();
}

test("a corrupt or truncated blob file is an error with a message", (t) => {
  if (missing(t.name)) return;
  const work = mkdtempSync(join(tmpdir(), "qx-decode-"));
  try {
    const src = join(exported, "repos", "korea");
    const copy = join(work, "korea");
    const files = blobFiles(src).filter((f) => f.includes("/d/"));
    assert.ok(files.length > 10);
    const cases = [
      ["flipped byte", (b) => { b[b.length >> 1] ^= 0x40; return b; }],
      ["truncated", (b) => b.subarray(0, b.length - 1)],
      ["header only", (b) => b.subarray(0, 3)],
      ["empty", () => new Uint8Array(0)],
    ];
    for (const [label, mutate] of cases) {
      rmSync(copy, { recursive: true, force: true });
      cpSync(src, copy, { recursive: true });
      // A blob of a coarse level with a payload: the largest of the first files.
      const target = files.slice(0, 8).reduce((a, f) => (statSync(f).size > statSync(a).size ? f : a));
      const path = join(copy, target.slice(src.length));
      writeFileSync(path, mutate(new Uint8Array(readFileSync(path))));
      const r = decodeRepo(copy);
      if (label === "empty") {
        // An empty file is what a server answers for a leaf: it decodes (as a leaf) or
        // fails cleanly, never crashes.
        assert.ok(r.status === 0 || /^decode-repo: /.test(r.err), `${label}: ${r.err}`);
        continue;
      }
      assert.equal(r.status, 1, `${label}: expected failure, got ${r.out}`);
      assert.match(r.err, /^decode-repo: decoding .*: .+/, label);
      assert.doesNotMatch(r.err, /\n\s+at /, `${label}: a stack trace escaped: ${r.err}`);
    }
  } finally {
    rmSync(work, { recursive: true, force: true });
  }
});
