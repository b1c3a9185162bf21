// Range requests from a page to a repository file on another origin (a bucket or CDN),
// in headless Chromium against nginx, both started here; `docs/hosting.md`, "Browsers".
//
// - With the documented CORS rule (allow Range and If-Match, expose Content-Range, ETag
//   and Content-Length) a cross-origin `fetch` with `Range` answers 206 and the page reads
//   Content-Range and ETag; `If-Match` with the pinned ETag passes, another one gives 412.
// - Without Access-Control-Expose-Headers the page cannot read Content-Range or ETag
//   (the reader then refuses the answer: it cannot check it); without any CORS header the
//   fetch fails (a TypeError, which the page reports as a connection failure).
// - A `Range` request alone needs no CORS preflight (Range is a safelisted header).
// - Measured, not assumed: which repeated or overlapping ranges Chromium answers from its
//   HTTP cache (the file is served with `Cache-Control: public, max-age=3600`), and the
//   preflights `If-Match` costs. Printed as a JSON line for the docs.
//
// Prints SKIP without nginx, Chromium or playwright-core, unless REQUIRE_NGINX /
// REQUIRE_BROWSER is set.

import { after, before, test } from "node:test";
import assert from "node:assert/strict";
import { mkdtempSync, mkdirSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { randomBytes } from "node:crypto";
import { CHROMIUM, corsRule, freePort, prerequisites, startNginx } from "./nginx-chromium.mjs";

const FILE_LEN = 300_000;

let absent = null;
let nginx = null;
let browser = null;
let page = null;
let ports = null;
let file = null;

before(async () => {
  const found = await prerequisites();
  absent = found.absent;
  if (absent) return;
  const dir = mkdtempSync(join(tmpdir(), "qx-range-cors-"));
  const www = join(dir, "www");
  mkdirSync(join(www, "page"), { recursive: true });
  mkdirSync(join(www, "files"), { recursive: true });
  writeFileSync(join(www, "page", "index.html"), "<!doctype html><title>page</title>");
  file = randomBytes(FILE_LEN);
  writeFileSync(join(www, "files", "r.pack"), file);
  ports = { page: await freePort(), files: await freePort() };
  const cors = corsRule(`
      add_header Cache-Control "public, max-age=3600" always;`);
  const http = `  server { listen 127.0.0.1:${ports.page}; root ${www}/page; access_log off; }
  server {
    listen 127.0.0.1:${ports.files};
    access_log ${dir}/access.log ranges;
    location /cors/ { alias ${www}/files/; ${cors} }
    location /noexpose/ { alias ${www}/files/; add_header Access-Control-Allow-Origin * always; }
    location /nocors/ { alias ${www}/files/; }
  }`;
  nginx = await startNginx(dir, http, [
    `http://127.0.0.1:${ports.page}/index.html`,
    `http://127.0.0.1:${ports.files}/nocors/r.pack`,
  ]);
  browser = await found.playwright.chromium.launch({ executablePath: CHROMIUM, headless: true, args: ["--no-sandbox"] });
  page = await browser.newPage();
  await page.goto(`http://127.0.0.1:${ports.page}/index.html`);
});

after(async () => {
  await browser?.close();
  nginx?.stop();
});

/** Fetches `url` in the page with `headers`: status, the headers the page can read, body
 * length and first bytes, or the error's text. */
function pageFetch(url, headers) {
  return page.evaluate(
    async ([url, headers]) => {
      try {
        const r = await fetch(url, { headers });
        const body = new Uint8Array(await r.arrayBuffer());
        return {
          status: r.status,
          contentRange: r.headers.get("content-range"),
          etag: r.headers.get("etag"),
          len: body.length,
          head: Array.from(body.subarray(0, 8)),
        };
      } catch (e) {
        return { error: `${e.name}: ${e.message}` };
      }
    },
    [url, headers],
  );
}

const logLines = () => nginx.logLines();

test("a cross-origin page reads ranges of a repository file with the documented CORS rule", async (t) => {
  if (absent) return t.skip(`SKIP range_cors: ${absent}`) ?? console.log(`SKIP range_cors: ${absent}`);
  const url = `http://127.0.0.1:${ports.files}/cors/r.pack`;
  let before = logLines().length;
  const first = await pageFetch(url, { Range: "bytes=0-16383" });
  assert.equal(first.status, 206, JSON.stringify(first));
  assert.equal(first.contentRange, `bytes 0-16383/${FILE_LEN}`);
  assert.equal(first.len, 16384);
  assert.deepEqual(first.head, Array.from(file.subarray(0, 8)));
  assert.match(first.etag ?? "", /^"[0-9a-f]+-[0-9a-f]+"$/, "a strong ETag, readable");
  // `Range` (one range) is a CORS-safelisted header: no preflight, one request.
  const firstLines = logLines().slice(before);
  assert.deepEqual(
    firstLines.map((l) => l.split(" ")[0]),
    ["GET"],
    `a Range request costs no preflight: ${JSON.stringify(firstLines)}`,
  );

  // What Chromium's HTTP cache does with ranges (measured, printed; the page keeps its
  // own decoded cache and never relies on it).
  const reached = async (range, extra = {}) => {
    const at = logLines().length;
    const r = await pageFetch(url, { Range: range, ...extra });
    assert.equal(r.status, 206, `${range}: ${JSON.stringify(r)}`);
    const [a, b] = range.slice(6).split("-").map(Number);
    assert.equal(r.contentRange, `bytes ${a}-${b}/${FILE_LEN}`);
    assert.deepEqual(r.head, Array.from(file.subarray(a, a + 8)));
    return logLines().slice(at);
  };
  const measured = {
    same_range_again: (await reached("bytes=0-16383")).length,
    inside_a_cached_range: (await reached("bytes=1000-1999")).length,
    new_range: (await reached("bytes=50000-59999")).length,
    new_range_again: (await reached("bytes=50000-59999")).length,
    overlapping_a_cached_one: (await reached("bytes=55000-64999")).length,
  };
  // If-Match is not safelisted: a preflight (OPTIONS) first.
  const pinned = await reached("bytes=100000-100999", { "If-Match": first.etag });
  const pinnedAgain = await reached("bytes=100000-100999", { "If-Match": first.etag });
  measured.if_match_requests = pinned.map((l) => l.split(" ")[0]);
  measured.if_match_repeated = pinnedAgain.map((l) => l.split(" ")[0]);
  assert.ok(pinned.some((l) => l.startsWith("GET")), JSON.stringify(pinned));
  const other = await pageFetch(url, { Range: "bytes=200000-200999", "If-Match": '"other"' });
  assert.equal(other.status, 412, "another ETag: 412, which the reader reports as a changed file");
  console.log(`range_cors: ${JSON.stringify(measured)}`);
});

test("without exposed headers the page cannot check an answer; without CORS the fetch fails", async (t) => {
  if (absent) return t.skip(`SKIP range_cors: ${absent}`) ?? console.log(`SKIP range_cors: ${absent}`);
  const hidden = await pageFetch(`http://127.0.0.1:${ports.files}/noexpose/r.pack`, { Range: "bytes=0-16383" });
  assert.equal(hidden.status, 206);
  assert.equal(hidden.contentRange, null, "Content-Range is not exposed");
  assert.equal(hidden.etag, null, "ETag is not exposed");
  const blocked = await pageFetch(`http://127.0.0.1:${ports.files}/nocors/r.pack`, { Range: "bytes=0-16383" });
  assert.match(blocked.error ?? "", /TypeError/, JSON.stringify(blocked));
  const missing = await pageFetch(`http://127.0.0.1:${ports.files}/cors/nothing.pack`, { Range: "bytes=0-16383" });
  assert.equal(missing.status, 404);
});
