// decode-repo.mjs (the WebAssembly module's reconstruction, web/src/reconstruct.rs)
// against the native Rust decoder: every bundled repository's export, and small sparse,
// colour and planet repositories built here, reconstruct to the `decoded_sha256` that
// `quincunx verify --json` prints; a corrupt or truncated blob file, or a blob file of no
// diamond, makes the tool fail with a one-line message, not a crash.
// Data: QUINCUNX_BIN, QUINCUNX_DEMO_DIR, QUINCUNX_EXPORT_DIR (set by
// repo-tools/tests/web_demo.rs), else this machine's defaults; SKIP when absent.

import { test } from "node:test";
import assert from "node:assert/strict";
import { execFileSync, spawnSync } from "node:child_process";
import { cpSync, existsSync, mkdirSync, mkdtempSync, readdirSync, readFileSync, rmSync, statSync, writeFileSync } from "node:fs";
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

function decodeRepo(dir, name, which = "whole") {
  const args = [tool, "--decoder", which, dir, ...(name ? [name] : [])];
  const r = spawnSync(process.execPath, args, { encoding: "utf8" });
  return { status: r.status, out: r.stdout, err: r.stderr };
}

/// `quincunx verify --json` of a repository.
function verify(repo) {
  const report = JSON.parse(execFileSync(bin, ["verify", repo, "--json"], { encoding: "utf8" }));
  assert.equal(report.blob_errors, 0);
  assert.match(report.decoded_sha256, /^[0-9a-f]{64}$/);
  return report;
}

/// decode-repo on repository `name` of export `dir`, by both of the module's decoders
/// (whole-raster and refiners), equals verify of `repo`; the metadata.
function sameHash(name, repo, dir) {
  const rust = verify(repo);
  const meta = JSON.parse(readFileSync(join(dir, "repos", name, "metadata.json"), "utf8"));
  for (const which of ["whole", "refiners"]) {
    const wasm = decodeRepo(dir, name, which);
    assert.equal(wasm.status, 0, wasm.err);
    const report = JSON.parse(wasm.out);
    const [a, b] = meta.extent;
    const points = meta.domain === "sphere" ? 6 * (a + 1) * (a + 1) : a * b;
    assert.equal(report.decoder, which);
    assert.equal(report.samples, points);
    assert.equal(report.channels, meta.channels.length);
    assert.equal(
      report.sha256,
      rust.decoded_sha256,
      `${name}: the module's reconstruction (${which}) differs from verify's`,
    );
    console.log(
      `${name} (${which}): ${report.sha256.slice(0, 16)}, WASM ${report.decode_msamples_per_s.toFixed(2)} M samples/s, ` +
        `Rust ${rust.decode_msamples_per_s.toFixed(2)} M samples/s`,
    );
  }
  return { meta };
}

for (const name of ["korea", "earth", "earth_colour"]) {
  test(`${name}: the WASM reconstruction hash equals quincunx verify's`, (t) => {
    if (missing(t.name)) return;
    sameHash(name, join(demo, name), exported);
  });
}

/// Small repositories built from data/ here: `[name, build arguments, check]`.
const built = [
  [
    "gsi_sparse",
    ["data/fixture_gsi_dem_256.json", "--sparse", "--diamond-size", "9", "--max-error-m", "0.1"],
    (meta) => assert.ok(meta.coverage, "a sparse repository has a coverage"),
  ],
  [
    "gsi_colour",
    ["data/fixture_gsi_color_256.jpg", "--colour", "--rms-m", "2"],
    (meta) => assert.equal(meta.channels.length, 3),
  ],
  [
    "etopo_planet",
    ["data/etopo20_global.json", "--planet", "--face-side", "64", "--diamond-size", "17", "--rms-m", "20"],
    (meta) => assert.equal(meta.domain, "sphere"),
  ],
];

for (const [name, args, check] of built) {
  test(`${name}: a small repository built here reconstructs to verify's hash`, (t) => {
    if (!existsSync(bin)) return console.log(`SKIP ${t.name}: quincunx binary not found at ${bin}`);
    const source = join(workspace, args[0]);
    if (!existsSync(source)) return console.log(`SKIP ${t.name}: ${source} not found`);
    const work = mkdtempSync(join(tmpdir(), `qx-decode-${name}-`));
    try {
      const repo = join(work, name);
      execFileSync(bin, ["build", source, ...args.slice(1), "-o", repo], { stdio: "ignore" });
      execFileSync(bin, ["export", repo, join(work, "x"), "--name", name], { stdio: "ignore" });
      const { meta } = sameHash(name, repo, join(work, "x"));
      check(meta);
    } finally {
      rmSync(work, { recursive: true, force: true });
    }
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
    cpSync(src, copy, { recursive: true });
    // A blob of a coarse level with a payload: the largest of the first files.
    const target = files.slice(0, 8).reduce((a, f) => (statSync(f).size > statSync(a).size ? f : a));
    const path = join(copy, target.slice(src.length));
    const original = readFileSync(path);
    for (const [label, mutate] of cases) {
      writeFileSync(path, mutate(new Uint8Array(original)));
      for (const which of ["whole", "refiners"]) {
        const r = decodeRepo(copy, undefined, which);
        if (label === "empty") {
          // An empty file is what a server answers for a leaf: it decodes (as a leaf) or
          // fails cleanly, never crashes.
          assert.ok(r.status === 0 || /^decode-repo: /.test(r.err), `${label}: ${r.err}`);
          continue;
        }
        assert.equal(r.status, 1, `${label} (${which}): expected failure, got ${r.out}`);
        assert.match(r.err, /^decode-repo: decoding .*: .+/, label);
        assert.doesNotMatch(r.err, /\n\s+at /, `${label}: a stack trace escaped: ${r.err}`);
      }
      writeFileSync(path, original);
    }
  } finally {
    rmSync(work, { recursive: true, force: true });
  }
});

test("a blob file of no diamond is an error naming it", (t) => {
  if (missing(t.name)) return;
  const work = mkdtempSync(join(tmpdir(), "qx-decode-"));
  try {
    const src = join(exported, "repos", "korea");
    const copy = join(work, "korea");
    const meta = JSON.parse(readFileSync(join(src, "metadata.json"), "utf8"));
    const d = join(copy, "v", meta.content_hash.slice(0, 16), "d");
    // (3, 5) is a diamond of a level finer than the repository's; the others no centre.
    cpSync(src, copy, { recursive: true });
    for (const [parts, named] of [
      [["3", "5"], "3/5"],
      [["4", "4", "1"], "4/4/1"],
      [["abc", "1"], "abc/1"],
    ]) {
      mkdirSync(join(d, ...parts.slice(0, -1)), { recursive: true });
      writeFileSync(join(d, ...parts), new Uint8Array([1, 2, 3]));
      for (const which of ["whole", "refiners"]) {
        const r = decodeRepo(copy, undefined, which);
        assert.equal(r.status, 1, `${named} (${which}): expected failure, got ${r.out}`);
        assert.match(r.err, /^decode-repo: .+\n$/, named);
        assert.ok(r.err.includes(named), `${named} (${which}): ${r.err}`);
      }
      rmSync(join(d, parts[0]), { recursive: true });
    }
  } finally {
    rmSync(work, { recursive: true, force: true });
  }
});
