// The demo page opening `/view?pack=<URL>`: a repository file on another origin (nginx
// with the CORS rule of docs/hosting.md, "Browsers"), read by range requests from headless
// Chromium, both started here; the page itself is served by a second nginx origin.
//
// - The view streams to full quality with no error, every request to the file is a range
//   request answered 206, none is preflighted or carries If-Match, the cut is crack-free
//   and the canvas shows terrain.
// - A file that is missing (404), a host without CORS, a host that ignores Range and a
//   file that changes while it streams each show a clear error on the page.
//
// Data: the korea repository file, `$QUINCUNX_PACK_FILE`, else
// `$QUINCUNX_DEMO_DIR/korea/repository.pack` (repo-tools/tests/web_demo.rs builds it).
// Prints SKIP without it, nginx, Chromium or playwright-core, unless QUINCUNX_DEMO_DIR
// (then the file must exist), REQUIRE_NGINX or REQUIRE_BROWSER is set.

import { after, before, test } from "node:test";
import assert from "node:assert/strict";
import { copyFileSync, existsSync, mkdtempSync, mkdirSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { fileURLToPath } from "node:url";
import { CHROMIUM, corsRule, freePort, prerequisites, startNginx } from "./nginx-chromium.mjs";

const DEMO = fileURLToPath(new URL("..", import.meta.url));
const PACK =
  process.env.QUINCUNX_PACK_FILE ?? (process.env.QUINCUNX_DEMO_DIR ? join(process.env.QUINCUNX_DEMO_DIR, "korea", "repository.pack") : null);
const SIZE = [480, 270];
const TIMEOUT_MS = Number(process.env.TIMEOUT_S ?? 180) * 1000;

let absent = null;
let nginx = null;
let browser = null;
let ports = null;

before(async () => {
  if (!PACK || !existsSync(PACK)) {
    absent = `no repository file (${PACK ?? "set QUINCUNX_PACK_FILE or QUINCUNX_DEMO_DIR"})`;
    if (process.env.QUINCUNX_DEMO_DIR || process.env.QUINCUNX_PACK_FILE) throw new Error(absent);
    return;
  }
  const found = await prerequisites();
  absent = found.absent;
  if (absent) return;
  const dir = mkdtempSync(join(tmpdir(), "qx-pack-view-"));
  const www = join(dir, "www");
  mkdirSync(www);
  copyFileSync(PACK, join(www, "korea.pack"));
  copyFileSync(PACK, join(www, "changing.pack"));
  ports = { page: await freePort(), files: await freePort() };
  const cors = corsRule();
  const http = `  types { text/html html; text/javascript mjs js; application/wasm wasm; }
  server {
    listen 127.0.0.1:${ports.page};
    access_log off;
    location = /view { default_type text/html; alias ${DEMO}index.html; }
    location /demo/ { alias ${DEMO}; }
  }
  server {
    listen 127.0.0.1:${ports.files};
    access_log ${dir}/access.log ranges;
    location /cors/ { alias ${www}/; ${cors} }
    location /norange/ { alias ${www}/; max_ranges 0; ${cors} }
    location /nocors/ { alias ${www}/; }
  }`;
  nginx = await startNginx(dir, http, [
    `http://127.0.0.1:${ports.page}/demo/index.html`,
    `http://127.0.0.1:${ports.files}/nocors/korea.pack`,
  ]);
  // WebGL2 without a GPU: ANGLE on SwiftShader, as tools/browser-views.mjs runs it.
  browser = await found.playwright.chromium.launch({
    executablePath: CHROMIUM,
    headless: true,
    args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
  });
});

after(async () => {
  await browser?.close();
  nginx?.stop();
});

const logLines = () => nginx.logLines();

const fileUrl = (path) => `http://127.0.0.1:${ports.files}${path}`;

/** Opens the page on `pack=url` (`query` added); resolves once it is full or failed. */
async function openView(url, query = "", beforeGoto = null) {
  const context = await browser.newContext({ viewport: { width: SIZE[0], height: SIZE[1] }, deviceScaleFactor: 1 });
  const page = await context.newPage();
  const consoleErrors = [];
  page.on("pageerror", (e) => consoleErrors.push(`pageerror: ${e.message}`));
  if (beforeGoto) await beforeGoto(page);
  const started = Date.now();
  await page.goto(`http://127.0.0.1:${ports.page}/view?pack=${encodeURIComponent(url)}&size=${SIZE[0]}x${SIZE[1]}${query}`);
  await page.waitForFunction(
    () => ["full", "error"].includes(document.body.dataset.state) || (window.quincunx?.errors?.length ?? 0) > 0,
    null,
    { timeout: TIMEOUT_MS, polling: 100 },
  );
  const state = await page.evaluate(() => ({
    state: document.body.dataset.state,
    status: document.getElementById("status").textContent,
    errors: [...window.quincunx.errors],
  }));
  return { context, page, state, consoleErrors, ms: Date.now() - started };
}

function skipped(t) {
  if (absent === null) return false;
  console.log(`SKIP ${t.name}: ${absent}`);
  t.skip(absent);
  return true;
}

test("pack_view: the page streams a repository file from another origin by ranges", async (t) => {
  if (skipped(t)) return;
  const at = logLines().length;
  const { context, page, state, consoleErrors, ms } = await openView(
    fileUrl("/cors/korea.pack"),
    "&uv=0.5,0.6&height_m=6000&pitch_deg=-35",
  );
  try {
    assert.equal(state.state, "full", JSON.stringify(state));
    assert.deepEqual(state.errors, []);
    assert.deepEqual(consoleErrors, []);
    const s = await page.evaluate(() => window.quincunx.clientStats());
    assert.equal(s.errors.total, 0, s.lastError);
    assert.ok(s.rangeRequests > 0, JSON.stringify(s));
    assert.deepEqual(Object.keys(s.rangeStatus), ["206"], JSON.stringify(s.rangeStatus));
    const cut = await page.evaluate(() => window.quincunx.checkCut());
    assert.ok(cut.ok, JSON.stringify(cut));
    assert.ok(cut.halves > 20, `${cut.halves} halves`);
    // What nginx saw: range GETs only, no preflight, no If-Match; each 206, or 304 when
    // Chromium revalidated a range in its own HTTP cache (the page still saw a 206).
    const lines = logLines().slice(at);
    assert.ok(lines.length > 0);
    const revalidated = lines.filter((l) => l.endsWith(" 304")).length;
    for (const l of lines) {
      const [method, uri, range, ifMatch, status] = l.split(" ");
      assert.equal(method, "GET", l);
      assert.equal(uri, "/cors/korea.pack", l);
      assert.match(range, /^"bytes=\d+-\d+"$/, l);
      assert.equal(ifMatch, '"-"', l);
      assert.ok(status === "206" || status === "304", l);
    }
    assert.ok(revalidated < lines.length, "mostly 206");
    // Terrain on the canvas: many colours, little of the sky's.
    const px = await page.evaluate(() => window.quincunx.readPixels());
    const rgba = Buffer.from(px.rgbaBase64, "base64");
    const colours = new Set();
    let sky = 0;
    for (let k = 0; k < rgba.length; k += 4) {
      colours.add((rgba[k] << 16) | (rgba[k + 1] << 8) | rgba[k + 2]);
      if (rgba[k] === 135 && rgba[k + 1] === 170 && rgba[k + 2] === 210) sky += 1;
    }
    const pixels = rgba.length / 4;
    assert.ok(colours.size > 200, `${colours.size} colours`);
    assert.ok(sky < pixels * 0.6, `${sky} of ${pixels} pixels are sky`);
    console.log(
      `pack_view: ${JSON.stringify({
        range_requests: s.rangeRequests,
        nginx_requests: lines.length,
        nginx_304: revalidated,
        keys_answered: s.responses,
        halves: cut.halves,
        bytes_received: s.bytesReceived,
        ms_to_full: ms,
        colours: colours.size,
      })}`,
    );
  } finally {
    await context.close();
  }
});

test("pack_view: a bad pack= URL or host is a clear error on the page", async (t) => {
  if (skipped(t)) return;
  const cases = [
    ["/cors/nothing.pack", /status 404/],
    ["/nocors/korea.pack", /CORS rule of docs\/hosting\.md/],
    ["/norange/korea.pack", /ignored the Range header/],
  ];
  for (const [path, expected] of cases) {
    const { context, state } = await openView(fileUrl(path));
    try {
      assert.equal(state.state, "error", `${path}: ${JSON.stringify(state)}`);
      assert.match(state.status, expected, path);
    } finally {
      await context.close();
    }
  }
  // Not a URL of this scheme at all.
  const { context, state } = await openView("ftp://127.0.0.1/x.pack");
  try {
    assert.equal(state.state, "error", JSON.stringify(state));
  } finally {
    await context.close();
  }
});

test("pack_view: a file that changes while the page streams it is a clear error", async (t) => {
  if (skipped(t)) return;
  // After the opening reads, the host answers with another ETag: the file changed.
  let seen = 0;
  const { context, page, state } = await openView(fileUrl("/cors/changing.pack"), "&uv=0.5,0.6&height_m=6000&pitch_deg=-35", (page) =>
    page.route("**/cors/changing.pack", async (route) => {
      seen += 1;
      try {
        if (seen <= 2 || route.request().method() !== "GET") return await route.continue();
        const response = await route.fetch();
        await route.fulfill({ response, headers: { ...response.headers(), etag: '"another-version"' } });
      } catch {
        // The page was closed while this request was held: nothing to answer.
      }
    }),
  );
  try {
    assert.equal(state.state, "error", JSON.stringify(state));
    assert.match(state.status, /changed since it was opened/, JSON.stringify(state));
  } finally {
    await page.unrouteAll({ behavior: "ignoreErrors" });
    await context.close();
  }
});
