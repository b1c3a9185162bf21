// What the browser tests against nginx share: finding nginx, Chromium and playwright-core
// (or the reason to skip), free ports, an nginx started from an `http { ... }` body in a
// temporary folder, the CORS rule of docs/hosting.md ("Browsers") and the access log.

import { spawn, execFileSync } from "node:child_process";
import { existsSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { createServer } from "node:net";
import { join } from "node:path";

export const NGINX = ["/usr/sbin/nginx", "/usr/bin/nginx"].find((p) => existsSync(p));
export const CHROMIUM = process.env.CHROMIUM ?? "/usr/bin/chromium";

/** The bucket's CORS rule as docs/hosting.md states it, in nginx's words; `extra` adds
 * headers to every answer. */
export function corsRule(extra = "") {
  return `
      add_header Access-Control-Allow-Origin * always;
      add_header Access-Control-Expose-Headers "Content-Range, ETag, Content-Length" always;${extra}
      if ($request_method = OPTIONS) {
        add_header Access-Control-Allow-Origin *;
        add_header Access-Control-Allow-Methods "GET, HEAD";
        add_header Access-Control-Allow-Headers "Range, If-Match";
        add_header Access-Control-Max-Age 3600;
        return 204;
      }`;
}

/** playwright-core once nginx and Chromium are here, or `{ absent }` with the reason to
 * skip; throws instead where REQUIRE_NGINX or REQUIRE_BROWSER asks for them. */
export async function prerequisites() {
  let playwright = null;
  try {
    playwright = await import("playwright-core");
  } catch {
    // reported below
  }
  if (!NGINX) {
    const absent = "nginx not installed (apt-get install nginx)";
    if (process.env.REQUIRE_NGINX) throw new Error(absent);
    return { absent };
  }
  if (!existsSync(CHROMIUM) || !playwright) {
    const absent = !playwright ? "no playwright-core (npm ci in web-demo/)" : `no ${CHROMIUM}`;
    if (process.env.REQUIRE_BROWSER) throw new Error(absent);
    return { absent };
  }
  return { absent: null, playwright };
}

export function freePort() {
  return new Promise((resolve, reject) => {
    const s = createServer();
    s.once("error", reject);
    s.listen(0, "127.0.0.1", () => {
      const { port } = s.address();
      s.close(() => resolve(port));
    });
  });
}

async function waitFor(url) {
  const deadline = Date.now() + 20_000;
  for (;;) {
    try {
      const r = await fetch(url);
      if (r.ok) return;
    } catch {
      // not yet listening
    }
    if (Date.now() > deadline) throw new Error(`nginx did not answer ${url}`);
    await new Promise((r) => setTimeout(r, 50));
  }
}

/** nginx with its files in `dir` (which `stop` removes), logging requests to
 * `dir/access.log` in the `ranges` format; `http` is the rest of the `http` block. Resolves
 * once every URL of `ready` answers 200. */
export async function startNginx(dir, http, ready) {
  const user = process.getuid?.() === 0 ? "user root;" : "";
  const conf = `daemon off; master_process on; worker_processes 1; ${user}
pid ${dir}/nginx.pid; error_log ${dir}/error.log info;
events { worker_connections 256; }
http {
  client_body_temp_path ${dir}/body; proxy_temp_path ${dir}/proxy;
  fastcgi_temp_path ${dir}/fastcgi; uwsgi_temp_path ${dir}/uwsgi; scgi_temp_path ${dir}/scgi;
  log_format ranges '$request_method $uri "$http_range" "$http_if_match" $status';
${http}
}
`;
  const args = ["-p", dir, "-c", join(dir, "nginx.conf"), "-e", join(dir, "error.log")];
  writeFileSync(join(dir, "nginx.conf"), conf);
  const child = spawn(NGINX, args, { stdio: ["ignore", "ignore", "inherit"] });
  const stop = () => {
    try {
      execFileSync(NGINX, [...args, "-s", "stop"]);
    } catch {
      child.kill();
    }
    rmSync(dir, { recursive: true, force: true });
  };
  try {
    for (const url of ready) await waitFor(url);
  } catch (e) {
    stop();
    throw e;
  }
  const log = join(dir, "access.log");
  /** The access log's lines so far. */
  const logLines = () =>
    existsSync(log)
      ? readFileSync(log, "utf8")
          .split("\n")
          .filter((l) => l.length > 0)
      : [];
  return { stop, logLines };
}
