#!/usr/bin/env node
// The browser test's driver: opens views of the web demo in Debian's headless Chromium
// (driven by playwright-core, no browser download), waits for full quality, saves a
// screenshot of the canvas per view and prints one JSON line per view. The assertions
// (screenshots against `quincunx render`, background pixels, console errors) are made by
// repo-tools/tests/web_demo.rs, which starts the server and renders the references.
//
// Usage: node web-demo/tools/browser-views.mjs <server url> <out dir> <views.json>
//   views.json: [{"name": "korea_down", "query": "repo=korea&uv=0.5,0.5&...", "size": [640, 360],
//                 "fly": {"keys": ["KeyD"], "ms": 500} (optional: then `<name>.flown.png`,
//                 `flown_url`, and `<name>.shared.png`, that URL opened in a new page)}]
// Environment: CHROMIUM (default /usr/bin/chromium), TIMEOUT_S (per view, default 180).

import { readFileSync } from "node:fs";
import { join } from "node:path";
import { chromium } from "playwright-core";

const [url, out, viewsFile] = process.argv.slice(2);
if (!url || !out || !viewsFile) {
  process.stderr.write("usage: browser.mjs <server url> <out dir> <views.json>\n");
  process.exit(2);
}
const views = JSON.parse(readFileSync(viewsFile, "utf8"));
const timeoutMs = Number(process.env.TIMEOUT_S ?? 180) * 1000;

// WebGL2 in headless Chromium without a GPU: ANGLE on SwiftShader (software Vulkan).
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  args: [
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--disable-gpu-driver-bug-workarounds",
  ],
});
let failed = false;
try {
  for (const view of views) {
    const [w, h] = view.size;
    const context = await browser.newContext({ viewport: { width: w, height: h }, deviceScaleFactor: 1 });
    const page = await context.newPage();
    const consoleErrors = [];
    page.on("console", (m) => {
      if (m.type() === "error" || m.type() === "warning") consoleErrors.push(`${m.type()}: ${m.text()}`);
    });
    page.on("pageerror", (e) => consoleErrors.push(`pageerror: ${e.message}`));
    page.on("requestfailed", (r) => {
      // Requests the client cancels itself (stale fetches) are not failures.
      const why = r.failure()?.errorText ?? "";
      if (!why.includes("ERR_ABORTED")) consoleErrors.push(`requestfailed: ${r.url()} ${why}`);
    });
    const started = Date.now();
    const result = { name: view.name, query: view.query };
    try {
      await page.goto(`${url}/view?${view.query}&size=${w}x${h}`, { waitUntil: "load" });
      await page.waitForFunction(() => document.body.dataset.state === "full", null, {
        timeout: timeoutMs,
        polling: 100,
      });
      result.wall_ms = Date.now() - started;
      result.stats = await page.evaluate(() => window.quincunx.stats());
      const canvas = await page.$("canvas");
      await canvas.screenshot({ path: join(out, `${view.name}.png`) });
      result.screenshot = join(out, `${view.name}.png`);
      if (view.fly) {
        // Fly (keys held down), let the view stream to full quality again, and keep the
        // URL the page wrote: opened in a new page it must show the same view.
        await page.mouse.move(w / 2, h / 2);
        for (const key of view.fly.keys) await page.keyboard.down(key);
        await page.waitForTimeout(view.fly.ms);
        for (const key of view.fly.keys) await page.keyboard.up(key);
        await page.waitForFunction(() => document.body.dataset.state !== "full", null, { timeout: timeoutMs });
        await page.waitForFunction(() => document.body.dataset.state === "full", null, {
          timeout: timeoutMs,
          polling: 100,
        });
        await page.waitForTimeout(600); // the URL is written at most every 250 ms
        result.flown_url = page.url();
        await canvas.screenshot({ path: join(out, `${view.name}.flown.png`) });
        const shared = await context.newPage();
        shared.on("console", (m) => {
          if (m.type() === "error" || m.type() === "warning") consoleErrors.push(`${m.type()}: ${m.text()}`);
        });
        shared.on("pageerror", (e) => consoleErrors.push(`pageerror: ${e.message}`));
        const url = new URL(result.flown_url);
        url.searchParams.set("size", `${w}x${h}`);
        await shared.goto(url.href, { waitUntil: "load" });
        await shared.waitForFunction(() => document.body.dataset.state === "full", null, {
          timeout: timeoutMs,
          polling: 100,
        });
        await (await shared.$("canvas")).screenshot({ path: join(out, `${view.name}.shared.png`) });
      }
    } catch (e) {
      result.error = String(e.message ?? e).split("\n")[0];
      failed = true;
      try {
        await page.screenshot({ path: join(out, `${view.name}.failed.png`) });
        result.state = await page.evaluate(() => ({
          state: document.body.dataset.state,
          stats: window.quincunx?.stats?.(),
          errors: window.quincunx?.errors,
        }));
      } catch {
        // The page is gone: the error above says why.
      }
    }
    result.console_errors = consoleErrors;
    process.stdout.write(JSON.stringify(result) + "\n");
    await context.close();
  }
} finally {
  await browser.close();
}
process.exit(failed ? 1 : 0);
