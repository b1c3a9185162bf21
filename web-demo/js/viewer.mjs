// The web demo's page: picks a repository (and a matching colour layer) from `GET /repos`,
// streams it with the client (client.mjs), draws it with the renderer (render.mjs), flies
// with mouse and keyboard, and keeps the view in the URL.
//
// The URL names a view the way `quincunx render` does (render/src/scene.rs `Shot`):
// `/view?repo=korea&uv=0.5,0.5&height_m=2000&pitch_deg=-60` (planar; `lat_lon=LAT,LON` on
// planets), plus `heading_deg`, `fov_deg`, `tolerance_px`, `colour=<repo>` and
// `size=WxH` (a canvas of exactly that many device pixels, for tests). `pack=<URL>` (and
// `colour_pack=<URL>`) opens a repository file on any HTTP host that answers Range
// requests instead of a repository of the page's server (client.mjs `Session.openPack`). A loaded view is
// streamed like `quincunx render` streams it (scene.rs `stream_to`): the camera stands
// `height_m` above the surface of the cut under it, re-read as the cut refines, until the
// cut is at full quality and the ground stays put twice in a row; then
// `document.body.dataset.state` becomes "full".
//
// For tests: `window.quincunx = {ready, fullQuality(), stats(), errors, view(),
// readPixels()}`. Nothing is logged to the console in normal operation: errors go to the
// panel and to `quincunx.errors`.

import {
  add,
  cameraFromView,
  cross,
  dot,
  formatViewQuery,
  length,
  normalizeOr,
  parseViewQuery,
  scale,
  shotFromEye,
  shotGround,
  shotView,
  sub,
  validateShot,
  worldFrame,
} from "./camera.mjs";
import { TerrainRenderer } from "./render.mjs";

const $ = (id) => document.getElementById(id);

/** Per-frame time the client may spend refining (ms). */
const BUDGET_MS = 8;
/** GPU memory for patches (bytes): `quincunx render --gpu-budget-mb` 128. */
const GPU_BUDGET_BYTES = 128 * 1048576;
/** Milliseconds between client updates between frames while a view streams. */
const PUMP_MS = 4;
/** Milliseconds between client updates of a still view at full quality. */
const IDLE_UPDATE_MS = 250;
/** Milliseconds between frames drawn while a still view streams. */
const LOADING_DRAW_MS = 200;

const api = {
  errors: [],
  ready: null,
  fullQuality: () => false,
  stats: () => ({}),
  view: () => null,
  readPixels: () => null,
};
window.quincunx = api;

let resolveReady;
api.ready = new Promise((resolve) => {
  resolveReady = resolve;
});

function report(error) {
  const message = error && error.message ? error.message : String(error);
  api.errors.push(message);
  const s = $("status");
  s.textContent = message;
  s.className = "error";
  document.body.dataset.state = "error";
}

window.addEventListener("error", (e) => {
  report(e.error || e.message);
  e.preventDefault();
});
window.addEventListener("unhandledrejection", (e) => {
  report(e.reason);
  e.preventDefault();
});

// ---- repositories -------------------------------------------------------------------

async function getJson(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status} ${(await r.text()).trim()}`);
  return r.json();
}

const metaCache = new Map();
function metadata(name) {
  if (!metaCache.has(name)) metaCache.set(name, getJson(`/repos/${encodeURIComponent(name)}/metadata.json`));
  return metaCache.get(name);
}

/** Whether colour repository `c` covers the ground of elevation `e` (client-core/src/colour.rs). */
function coloursMatch(e, c) {
  if (c.attribute?.kind !== "colour" || c.channels?.length !== 3 || c.domain !== e.domain) return false;
  if (e.domain === "sphere") {
    const [a, b] = [e.radius_m, c.radius_m];
    return !(a && b) || Math.abs(a - b) <= 1e-9 * Math.max(Math.abs(a), Math.abs(b));
  }
  const shift = c.m - e.m;
  for (let axis = 0; axis < 2; axis++) {
    const ee = Math.max(e.extent[axis] - 1, 0);
    const cc = Math.max(c.extent[axis] - 1, 0);
    const same = shift >= 0 ? ee * 2 ** shift === cc : cc * 2 ** -shift === ee;
    if (!same) return false;
  }
  return true;
}

// ---- the viewer ---------------------------------------------------------------------

class Viewer {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", {
      antialias: false,
      depth: false,
      stencil: false,
      alpha: false,
      premultipliedAlpha: false,
      preserveDrawingBuffer: false,
      powerPreference: "high-performance",
    });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.session = null;
    this.renderer = null;
    this.shot = null;
    this.ground = 0;
    this.settled = 0;
    this.interacting = false;
    this.keys = new Set();
    this.drag = null;
    this.dirty = true;
    this.full = false;
    this.viewStart = performance.now();
    this.timeToFullMs = null;
    this.frames = [];
    this.lastFrame = performance.now();
    this.urlDirty = false;
    this.lastUrl = 0;
    this.openToken = 0;
    this.fixedSize = null;
    this.lastFigures = 0;
    this.loops = 0;
    this.draws = 0;
    this.lastUpdate = -Infinity;
    /** Main-thread milliseconds spent per part (cumulative): the figures' `cpuMs`. */
    this.cpu = { update: 0, pump: 0, apply: 0, ground: 0, prepare: 0, draw: 0 };
    this.rate = { t: performance.now(), bytes: 0, perS: 0 };
    this.installInput();
    this.loop = this.loop.bind(this);
  }

  /**
   * Opens `repo` (with `colour`) at `shot`; or, with `packs` ({pack, colourPack}: URLs),
   * those repository files by ranges (`shot` null: a default view of them).
   */
  async open(repo, colour, shot, { fromUrl, packs = null }) {
    const token = ++this.openToken;
    this.close();
    const status = $("status");
    status.className = "";
    status.textContent = `opening ${packs ? packs.pack : repo}...`;
    document.body.dataset.state = "loading";
    const { Session } = await import("./client.mjs");
    let session;
    let meta;
    let colourMeta = null;
    if (packs) {
      session = await Session.openPack(packs.pack, { colourPack: packs.colourPack, onError: (m) => report(new Error(m)) });
      meta = session.meta;
      colourMeta = session.colourMeta;
      repo = packs.pack;
      colour = packs.colourPack;
      if (!shot) {
        // The URL's size and tolerance, if it gave them, with a default place.
        const given = packs.given;
        shot = defaultShotFor({ domain: meta.domain }, meta);
        if (given) {
          shot.size = given.size;
          shot.tolerancePx = given.tolerancePx;
        }
      }
    } else {
      meta = await metadata(repo);
      colourMeta = colour ? await metadata(colour) : null;
      if (colourMeta && !coloursMatch(meta, colourMeta)) {
        throw new Error(`${colour} does not cover the same ground as ${repo}`);
      }
      session = await Session.open(location.origin, repo, { colour: colour || null });
    }
    if (token !== this.openToken) {
      session.close?.();
      return;
    }
    this.packs = packs;
    this.repo = repo;
    this.colour = colour || null;
    this.meta = session.meta || meta;
    this.session = session;
    const cMeta = session.colourMeta || colourMeta;
    const colourN = session.colourN ?? (cMeta ? cMeta.n : 0);
    // The client's world frame when it has one (the same numbers as render/src/domain.rs).
    const world = session.world?.frame ? session.world.frame() : worldFrame(this.meta, colourN);
    world.colourN = colourN;
    this.world = world;
    if (shot.place.uv && world.geometry.kind === "planet") shot.place = { latLon: [20, 0] };
    if (shot.place.latLon && world.geometry.kind === "planar") shot.place = { uv: [0.5, 0.5] };
    const bad = validateShot(shot);
    if (bad) throw new Error(bad);
    shotGround(shot, world);
    this.shot = shot;
    const colourScales = cMeta ? cMeta.channels.map((c) => [c.value_scale, c.value_offset]) : null;
    this.renderer = new TerrainRenderer(this.gl, {
      world,
      colourScales,
      tintM: [0, Math.max(rootTop(this.meta, world), 50)],
      // `depth=frag` in the URL: the depth path of browsers without EXT_clip_control.
      clipControl: new URLSearchParams(location.search).get("depth") !== "frag",
    });
    // Bound the cut by what `quincunx render`'s default GPU budget holds (renderer.rs
    // `bound_cut`), so both draw the same cut when the budget binds.
    const slotBytes = (world.n + 1) ** 2 * 4 + (colourN > 0 ? (colourN + 1) ** 2 * 4 : 0) + 80 + 20;
    session.setMaxCutHalves?.(Math.min(Math.floor(GPU_BUDGET_BYTES / slotBytes), 1 << 24));
    this.ground = initialGround(session, this.meta, world);
    this.settled = 0;
    this.full = false;
    this.restart();
    this.setFixedSize(shot.size);
    $("f-depth").textContent = this.renderer.depthMode;
    status.textContent = `${repo}${colour ? ` + ${colour}` : ""}: ${this.meta.domain}, N = ${this.meta.n}, ${this.meta.levels} levels`;
    if (!fromUrl) this.urlDirty = true;
    resolveReady({ ok: true, repo, colour: this.colour });
    if (!this.running) {
      this.running = true;
      requestAnimationFrame(this.loop);
    }
  }

  close() {
    if (this.renderer) this.renderer.dispose();
    if (this.session) this.session.close?.();
    this.renderer = null;
    this.session = null;
  }

  /** A new view to stream to: the clock for time to full quality starts again. */
  restart() {
    this.viewStart = performance.now();
    this.timeToFullMs = null;
    this.settled = 0;
    this.full = false;
    this.dirty = true;
    document.body.dataset.state = "loading";
  }

  setFixedSize(size) {
    const view = $("view");
    const panel = $("panel");
    this.fixedSize = size;
    if (size) {
      const dpr = window.devicePixelRatio || 1;
      view.classList.add("fixed");
      view.style.width = `${size[0] / dpr}px`;
      view.style.height = `${size[1] / dpr}px`;
      // The panel beside the canvas, never over it: screenshots see the terrain only.
      panel.style.left = `${size[0] / dpr + 8}px`;
      panel.style.top = "0";
    } else {
      view.classList.remove("fixed");
      view.style.width = "";
      view.style.height = "";
      panel.style.left = "";
      panel.style.top = "";
    }
  }

  /** The canvas size in device pixels (fixed by `size=`, else the element's). */
  resize() {
    const c = this.canvas;
    let w;
    let h;
    if (this.fixedSize) {
      [w, h] = this.fixedSize;
    } else {
      const dpr = window.devicePixelRatio || 1;
      w = Math.max(1, Math.round(c.clientWidth * dpr));
      h = Math.max(1, Math.round(c.clientHeight * dpr));
    }
    if (c.width !== w || c.height !== h) {
      c.width = w;
      c.height = h;
      this.dirty = true;
      if (!this.interacting) this.restartIfFull();
    }
    return [w, h];
  }

  restartIfFull() {
    if (this.full) this.restart();
    else this.settled = 0;
  }

  // ---- the frame loop ---------------------------------------------------------------

  /** The client's camera for the current shot (float64 world metres). */
  clientCamera(viewport) {
    const view = shotView(this.shot, this.world, this.ground, viewport);
    return { position: view.eye, forward: sub(view.target, view.eye), up: view.up, fovYRad: view.fovYRad };
  }

  /**
   * Runs the client between frames too while the view streams: arrivals are taken and
   * new requests made without waiting for the next frame (a software rasteriser can take
   * tens of milliseconds a frame).
   */
  pump() {
    this.pumpTimer = null;
    if (!this.session || this.full || this.interacting) return;
    try {
      const t0 = performance.now();
      const viewport = [this.canvas.width, this.canvas.height];
      this.session.update(this.clientCamera(viewport), {
        tolerancePx: this.shot.tolerancePx,
        viewportPx: viewport,
        budgetMs: BUDGET_MS,
      });
      this.cpu.pump += performance.now() - t0;
    } catch (e) {
      report(e);
      this.close();
      return;
    }
    this.schedulePump();
  }

  schedulePump() {
    if (this.pumpTimer === null || this.pumpTimer === undefined) this.pumpTimer = setTimeout(() => this.pump(), PUMP_MS);
  }

  loop(now) {
    requestAnimationFrame(this.loop);
    if (!this.session || !this.renderer) return;
    try {
      this.frame(now);
    } catch (e) {
      report(e);
      this.close();
    }
  }

  frame(now) {
    this.loops++;
    const dt = Math.min(0.1, Math.max(0, (now - this.lastFrame) / 1000));
    this.lastFrame = now;
    const viewport = this.resize();
    if (this.fly(dt)) {
      this.interacting = true;
      this.idleSince = now;
      this.dirty = true;
      this.urlDirty = true;
      if (this.full || this.timeToFullMs !== null || this.settled > 0) this.restart();
    } else if (this.interacting && now - this.idleSince > 150 && !this.drag) {
      // Input stopped: stream this view to full quality from here.
      this.interacting = false;
      this.restart();
    }
    const shot = this.shot;
    if (this.full && !this.interacting && !this.dirty && now - this.lastUpdate < IDLE_UPDATE_MS) {
      // A still view at full quality: nothing to refine; look again now and then.
      this.updateFigures(now, this.session.stats(), this.renderer.lastStats);
      return;
    }
    this.lastUpdate = now;
    let t0 = performance.now();
    this.session.update(this.clientCamera(viewport), {
      tolerancePx: shot.tolerancePx,
      viewportPx: viewport,
      budgetMs: BUDGET_MS,
    });
    const changes = this.session.cutChanges();
    let t1 = performance.now();
    this.cpu.update += t1 - t0;
    if (changes.entered.length > 0 || changes.left.length > 0) this.dirty = true;
    this.renderer.apply(changes);
    const s = this.session.stats();
    t0 = performance.now();
    this.cpu.apply += t0 - t1;

    // The ground under the camera (scene.rs stream_to): while flying it follows the cut
    // smoothly; once the client is at full quality it is re-read until it stays put twice.
    const { base, up } = shotGround(shot, this.world);
    const probe = add(base, scale(up, 1e-3));
    if (this.interacting) {
      const g = this.renderer.surfaceHeightM(probe);
      if (g !== null) {
        const k = Math.min(1, dt * 6);
        this.ground = Math.max(this.ground + (g - this.ground) * k, g - 0.5 * shot.heightM);
      }
    } else if (!this.full && (s.fullQuality || (s.settled && s.budgetLimited))) {
      // (A cut budget that binds means full quality cannot come: as scene.rs stream_to,
      // a settled cut is then the final one.)
      const g = this.renderer.surfaceHeightM(probe);
      const ground = g === null ? this.ground : g;
      if (Math.abs(ground - this.ground) <= 1e-3 * Math.max(shot.heightM, 1)) {
        this.settled++;
      } else {
        this.settled = 0;
        this.ground = ground;
        this.dirty = true;
      }
    }
    t1 = performance.now();
    this.cpu.ground += t1 - t0;
    const view = shotView(shot, this.world, this.ground, viewport);
    const stats = this.renderer.prepare(cameraFromView(view));
    this.cpu.prepare += performance.now() - t1;
    if (stats.uploads > 0 || (stats.current && this.pendingSwitch)) this.dirty = true;
    this.pendingSwitch = !stats.current;
    if (!this.interacting && !this.full && this.settled >= 2 && stats.current) {
      this.full = true;
      this.fullAtMs = performance.now();
      this.timeToFullMs = this.fullAtMs - this.viewStart;
    }
    // What a drawn frame costs: the time until the next frame after one was drawn (the
    // browser paces frames by the GPU; a software rasteriser takes 100s of ms).
    if (this.drewLastFrame) this.frameCostMs = 0.7 * (this.frameCostMs ?? 0) + 0.3 * (now - this.lastDraw);
    this.drewLastFrame = false;
    // Streaming a still view: show progress now and then, spending at most a quarter of
    // the time drawing (the client needs the rest). Flying and the final frame: now.
    const gap = Math.max(LOADING_DRAW_MS, 3 * (this.frameCostMs ?? 0));
    const throttled = !this.interacting && !this.full && now - (this.lastDraw ?? -Infinity) < gap;
    if (this.dirty && !throttled) {
      this.lastDraw = now;
      this.drewLastFrame = true;
      const t0 = performance.now();
      this.renderer.draw(viewport[0], viewport[1]);
      this.drawMs = performance.now() - t0;
      this.cpu.draw += this.drawMs;
      this.frames.push(now);
      this.draws++;
      this.dirty = false;
    }
    if (this.full && !this.dirty && document.body.dataset.state !== "full") {
      // The settled view's frame has been drawn: the next composite shows it.
      document.body.dataset.state = "full";
    }
    if (!this.full && !this.interacting) this.schedulePump();
    this.updateFigures(now, s, stats);
    this.updateUrl(now);
  }

  // ---- figures and the URL ----------------------------------------------------------

  updateFigures(now, s, stats) {
    while (this.frames.length && now - this.frames[0] > 1000) this.frames.shift();
    const received = s.bytesReceived ?? 0;
    if (now - this.rate.t >= 500) {
      this.rate.perS = ((received - this.rate.bytes) * 1000) / (now - this.rate.t);
      this.rate.bytes = received;
      this.rate.t = now;
    }
    this.figures = {
      fps: this.frames.length,
      drawMs: this.drawMs ?? null,
      frameCostMs: this.frameCostMs ?? null,
      triangles: stats.triangles,
      patches: stats.patches,
      bytesReceived: received,
      bytesPerS: s.bytesPerS ?? this.rate.perS,
      requestsInFlight: s.requestsInFlight ?? 0,
      queued: s.queued ?? 0,
      fullQuality: this.full,
      clientFullQuality: Boolean(s.fullQuality),
      timeToFullQualityMs: this.timeToFullMs,
      fullQualityAtMs: this.full ? this.fullAtMs : null,
      clientTimeToFullQualityMs: s.timeToFullQualityMs ?? null,
      groundM: this.ground,
      heightM: this.shot.heightM,
      uploads: this.renderer.uploadsTotal,
      uploadBytes: this.renderer.uploadBytesTotal,
      depthMode: this.renderer.depthMode,
      loops: this.loops,
      draws: this.draws,
      cpuMs: Object.fromEntries(Object.entries(this.cpu).map(([k, v]) => [k, Math.round(v)])),
      viewport: [this.canvas.width, this.canvas.height],
    };
    if (now - this.lastFigures < 250 && !(this.full && !this.figuresFull)) return;
    this.lastFigures = now;
    this.figuresFull = this.full;
    const f = this.figures;
    $("f-fps").textContent = f.fps
      ? `${f.fps}${f.frameCostMs ? ` (${Math.round(f.frameCostMs)} ms a frame)` : ""}`
      : "idle";
    $("f-triangles").textContent = f.triangles.toLocaleString("en");
    $("f-patches").textContent = f.patches.toLocaleString("en");
    $("f-bytes").textContent = bytes(f.bytesReceived);
    $("f-rate").textContent = `${bytes(f.bytesPerS)}/s`;
    $("f-requests").textContent = `${f.requestsInFlight} in flight, ${f.queued} queued`;
    $("f-full").textContent =
      f.timeToFullQualityMs !== null ? `in ${(f.timeToFullQualityMs / 1000).toFixed(2)} s` : "streaming...";
    $("f-height").textContent = `${metres(f.heightM)} over ${metres(f.groundM)}`;
  }

  updateUrl(now) {
    if (!this.urlDirty || now - this.lastUrl < 250) return;
    this.urlDirty = false;
    this.lastUrl = now;
    const q = formatViewQuery(this.repo, this.colour, this.shot, this.packs);
    history.replaceState(null, "", `/view?${q}`);
  }

  // ---- flying -----------------------------------------------------------------------

  installInput() {
    const c = this.canvas;
    c.addEventListener("webglcontextlost", (e) => {
      // Keep the context restorable; the renderer's objects are gone with it.
      e.preventDefault();
      if (this.renderer) this.renderer.lost = true;
      this.close();
      $("status").textContent = "WebGL context lost; waiting for it to come back...";
      document.body.dataset.state = "loading";
    });
    c.addEventListener("webglcontextrestored", () => {
      if (this.repo && this.shot) {
        this.open(this.repo, this.colour, { ...this.shot }, { fromUrl: true, packs: this.packs }).catch(report);
      }
    });
    c.addEventListener("contextmenu", (e) => e.preventDefault());
    c.addEventListener("pointerdown", (e) => {
      c.focus();
      const orbit = e.button === 2 || e.shiftKey;
      this.drag = { x: e.clientX, y: e.clientY, orbit, id: e.pointerId, pivot: null };
      c.setPointerCapture(e.pointerId);
      c.classList.add("dragging");
      e.preventDefault();
    });
    c.addEventListener("pointermove", (e) => {
      if (!this.drag || e.pointerId !== this.drag.id) return;
      const dx = e.clientX - this.drag.x;
      const dy = e.clientY - this.drag.y;
      this.drag.x = e.clientX;
      this.drag.y = e.clientY;
      this.pendingDrag = this.pendingDrag || [0, 0];
      this.pendingDrag[0] += dx;
      this.pendingDrag[1] += dy;
    });
    const end = (e) => {
      if (!this.drag || e.pointerId !== this.drag.id) return;
      this.drag = null;
      c.classList.remove("dragging");
    };
    c.addEventListener("pointerup", end);
    c.addEventListener("pointercancel", end);
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        const lines = e.deltaMode === 1 ? 33 : e.deltaMode === 2 ? 400 : 1;
        this.pendingWheel = (this.pendingWheel || 0) + e.deltaY * lines;
      },
      { passive: false },
    );
    window.addEventListener("keydown", (e) => {
      if (e.target instanceof HTMLSelectElement || e.target instanceof HTMLInputElement) return;
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      const k = e.key.toLowerCase();
      if (MOVE_KEYS.has(k)) {
        this.keys.add(k);
        e.preventDefault();
      } else if (k === "g" || k === "l" || k === "c") {
        if (!this.renderer) return;
        const m = this.renderer.modes;
        if (k === "g") m.wireframe = !m.wireframe;
        if (k === "l") m.colourByLevel = !m.colourByLevel;
        if (k === "c") m.noColour = !m.noColour;
        this.dirty = true;
      } else if (k === "h") {
        $("panel").hidden = !$("panel").hidden;
      }
      if (e.key === "Shift") this.fast = true;
    });
    window.addEventListener("keyup", (e) => {
      this.keys.delete(e.key.toLowerCase());
      if (e.key === "Shift") this.fast = false;
    });
    window.addEventListener("blur", () => {
      this.keys.clear();
      this.fast = false;
    });
  }

  /** Applies this frame's input to the shot; returns whether the view moved. */
  fly(dt) {
    const shot = this.shot;
    let moved = false;
    const cssHeight = this.canvas.clientHeight || this.canvas.height;
    const degPerPx = shot.fovDeg / Math.max(cssHeight, 1);
    if (this.pendingDrag) {
      const [dx, dy] = this.pendingDrag;
      this.pendingDrag = null;
      if (dx !== 0 || dy !== 0) {
        moved = true;
        if (this.drag?.orbit || (this.drag === null && this.lastDragOrbit)) this.orbit(dx * degPerPx, dy * degPerPx);
        else this.look(dx * degPerPx, dy * degPerPx);
      }
    }
    this.lastDragOrbit = this.drag ? this.drag.orbit : false;
    if (this.pendingWheel) {
      shot.heightM = clampHeight(shot.heightM * Math.exp(this.pendingWheel * 0.0015), this.world);
      this.pendingWheel = 0;
      moved = true;
    }
    if (this.keys.size > 0 && dt > 0) {
      const k = this.keys;
      const fast = this.fast ? 5 : 1;
      const fwd = (k.has("w") || k.has("arrowup") ? 1 : 0) - (k.has("s") || k.has("arrowdown") ? 1 : 0);
      const right = (k.has("d") || k.has("arrowright") ? 1 : 0) - (k.has("a") || k.has("arrowleft") ? 1 : 0);
      const vertical = (k.has("e") ? 1 : 0) - (k.has("q") ? 1 : 0);
      if (fwd !== 0 || right !== 0) {
        this.move(fwd * shot.heightM * fast * dt, right * shot.heightM * fast * dt);
        moved = true;
      }
      if (vertical !== 0) {
        shot.heightM = clampHeight(shot.heightM * Math.exp(vertical * fast * dt), this.world);
        moved = true;
      }
    }
    return moved;
  }

  look(dHeading, dPitch) {
    const shot = this.shot;
    shot.headingDeg = wrap(shot.headingDeg + dHeading);
    shot.pitchDeg = Math.max(-90, Math.min(90, shot.pitchDeg - dPitch));
  }

  /** The camera's eye, forward direction and local frame for the current shot. */
  pose() {
    const view = shotView(this.shot, this.world, this.ground, [1, 1]);
    return { eye: view.eye, forward: normalizeOr(sub(view.target, view.eye), [0, 0, -1]) };
  }

  /** Orbits the point of the ground in the middle of the view. */
  orbit(dHeading, dPitch) {
    const { eye, forward } = this.pose();
    const pivot = groundHit(this.world, eye, forward, this.ground);
    if (!pivot) {
      this.look(dHeading, dPitch);
      return;
    }
    const dist = length(sub(pivot, eye));
    const frame = localFrame(this.world, pivot);
    // Heading and pitch of the view direction in the pivot's frame, turned.
    const h0 = Math.atan2(dot(forward, frame.east), dot(forward, frame.north));
    const p0 = Math.asin(Math.max(-1, Math.min(1, dot(forward, frame.up))));
    const h = h0 - (dHeading * Math.PI) / 180;
    const p = Math.max(-Math.PI / 2, Math.min(-0.01, p0 + (dPitch * Math.PI) / 180));
    const horiz = add(scale(frame.north, Math.cos(h)), scale(frame.east, Math.sin(h)));
    const f = add(scale(horiz, Math.cos(p)), scale(frame.up, Math.sin(p)));
    const newEye = sub(pivot, scale(f, dist));
    this.placeEye(newEye, f);
  }

  /** Moves the camera `forward` metres along its heading and `right` metres across. */
  move(forward, right) {
    const { eye, forward: f } = this.pose();
    const frame = localFrame(this.world, eye);
    let horiz = sub(f, scale(frame.up, dot(f, frame.up)));
    if (length(horiz) < 1e-9) {
      // Looking straight up or down: the heading from the shot.
      const h = (this.shot.headingDeg * Math.PI) / 180;
      horiz = add(scale(frame.north, Math.cos(h)), scale(frame.east, Math.sin(h)));
    }
    horiz = normalizeOr(horiz, frame.north);
    const side = cross(horiz, frame.up);
    const step = add(scale(horiz, forward), scale(side, right));
    let newEye = add(eye, step);
    let newForward = f;
    if (this.world.geometry.kind === "planet") {
      newEye = scale(normalizeOr(newEye, frame.up), length(eye));
      // Carry the view direction along (parallel transport on the sphere).
      const up2 = normalizeOr(newEye, frame.up);
      const axis = cross(frame.up, up2);
      const s = length(axis);
      const c = dot(frame.up, up2);
      if (s > 1e-15) newForward = rotate(f, scale(axis, 1 / s), Math.atan2(s, c));
    }
    const heightM = this.shot.heightM;
    const shot = shotFromEye(this.world, newEye, newForward, this.ground, this.shot);
    shot.heightM = heightM;
    this.shot = shot;
  }

  /** Puts the camera at `eye` looking along `forward`; heights from the cut under it. */
  placeEye(eye, forward) {
    const up = this.world.geometry.kind === "planar" ? [0, 0, 1] : normalizeOr(eye, [0, 0, 1]);
    const g = this.renderer.surfaceHeightM(add(eye, scale(up, 0)));
    if (g !== null) this.ground = g;
    const shot = shotFromEye(this.world, eye, forward, this.ground, this.shot);
    shot.heightM = clampHeight(shot.heightM, this.world);
    this.shot = shot;
  }
}

const MOVE_KEYS = new Set(["w", "a", "s", "d", "q", "e", "arrowup", "arrowdown", "arrowleft", "arrowright"]);

function wrap(deg) {
  const w = deg % 360;
  return w < 0 ? w + 360 : w;
}

function clampHeight(h, world) {
  const top = world.geometry.kind === "planet" ? 20 * world.geometry.radiusM : 1e7;
  return Math.max(1, Math.min(top, h));
}

/** Rodrigues rotation of `v` about unit `axis` by `angle`. */
function rotate(v, axis, angle) {
  const c = Math.cos(angle);
  const s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(axis, v), s)), scale(axis, dot(axis, v) * (1 - c)));
}

/** Up, north and east at a point (scene.rs conventions: planar north is -y). */
function localFrame(world, x) {
  if (world.geometry.kind === "planar") return { up: [0, 0, 1], north: [0, -1, 0], east: [1, 0, 0] };
  const up = normalizeOr(x, [0, 0, 1]);
  let north = normalizeOr(sub([0, 0, 1], scale(up, up[2])), [0, 0, 0]);
  if (length(north) === 0) north = [1, 0, 0];
  return { up, north, east: cross(up, north) };
}

/** Where a ray meets the level surface at height `groundM` (plane or sphere), or null. */
function groundHit(world, eye, f, groundM) {
  if (world.geometry.kind === "planar") {
    if (f[2] >= -1e-6) return null;
    const t = (groundM - eye[2]) / f[2];
    return t > 0 ? add(eye, scale(f, t)) : null;
  }
  const r = world.geometry.radiusM + groundM;
  const b = dot(eye, f);
  const c = dot(eye, eye) - r * r;
  const disc = b * b - c;
  if (disc < 0) return null;
  const t = -b - Math.sqrt(disc);
  return t > 0 ? add(eye, scale(f, t)) : null;
}

/** The highest height of the roots' grids (renderer.rs `for_session`: the tint's top). */
function rootTop(meta, world) {
  const ch = meta.channels && meta.channels[0];
  let top = -Infinity;
  const visit = (g) => {
    if (Array.isArray(g) && g.length && Array.isArray(g[0])) g.forEach(visit);
    else if (g && typeof g.length === "number") {
      for (let k = 0; k < g.length; k++) {
        const h = world.valueOffsetM + g[k] * world.valueScaleM;
        if (h > top) top = h;
      }
    }
  };
  if (ch && ch.roots) visit(ch.roots);
  return top;
}

/** The first ground guess (scene.rs: the top of the session's height range). */
function initialGround(session, meta, world) {
  const range = session.heightRange?.();
  if (range && Number.isFinite(range[0]) && Number.isFinite(range[1])) return Math.max(range[0], range[1]);
  const top = rootTop(meta, world);
  return Number.isFinite(top) ? top : 0;
}

function bytes(n) {
  if (!Number.isFinite(n)) return "-";
  if (n < 1024) return `${Math.round(n)} B`;
  if (n < 1048576) return `${(n / 1024).toFixed(1)} KiB`;
  return `${(n / 1048576).toFixed(2)} MiB`;
}

function metres(m) {
  if (!Number.isFinite(m)) return "-";
  return Math.abs(m) >= 10000 ? `${(m / 1000).toFixed(1)} km` : `${m.toFixed(1)} m`;
}

/** A default view of a repository: the whole raster, or the planet from afar. */
function defaultShotFor(entry, meta) {
  const shot = parseViewQuery("").shot;
  if (entry.domain === "sphere") {
    shot.place = { latLon: [20, 10] };
    shot.heightM = 2.5 * (meta.radius_m || 6371000);
    shot.pitchDeg = -90;
  } else {
    const world = worldFrame(meta);
    const w = world.geometry.extentFine[0] * world.geometry.metresPerFine;
    const h = world.geometry.extentFine[1] * world.geometry.metresPerFine;
    shot.place = { uv: [0.5, 0.85] };
    shot.heightM = Math.max(w, h) * 0.35;
    shot.pitchDeg = -45;
  }
  return shot;
}

// ---- the page -----------------------------------------------------------------------

async function main() {
  let query;
  try {
    query = parseViewQuery(location.search);
  } catch (e) {
    report(e);
    query = parseViewQuery("");
  }
  const viewer = new Viewer($("canvas"));
  api.fullQuality = () => viewer.full;
  api.stats = () => ({ ...(viewer.figures || {}) });
  api.view = () => (viewer.shot ? { repo: viewer.repo, colour: viewer.colour, shot: { ...viewer.shot }, query: formatViewQuery(viewer.repo, viewer.colour, viewer.shot, viewer.packs) } : null);
  api.readPixels = () => readPixels(viewer);
  api.clientStats = () => (viewer.session ? viewer.session.stats() : null);
  api.checkCut = () => (viewer.session ? viewer.session.checkCut() : null);

  if (query.pack) {
    // A repository file by ranges: no server listing, one terrain.
    for (const id of ["repo", "colour"]) $(id).disabled = true;
    const packs = { pack: query.pack, colourPack: query.colourPack, given: query.shot };
    $("repo").append(new Option(query.pack.split("/").pop() || query.pack, ""));
    const tolerance = $("tolerance");
    const hasShot = query.hasPlace || query.hasHeight;
    tolerance.value = String(Math.log2(query.shot.tolerancePx));
    $("tolerance-value").textContent = `${query.shot.tolerancePx} px`;
    tolerance.addEventListener("input", () => {
      const px = 2 ** Number(tolerance.value);
      $("tolerance-value").textContent = `${px < 1 ? px.toFixed(2) : px.toFixed(1)} px`;
      if (viewer.shot) {
        viewer.shot.tolerancePx = px;
        viewer.urlDirty = true;
        viewer.restart();
      }
    });
    try {
      await viewer.open(null, null, hasShot ? query.shot : null, { fromUrl: hasShot, packs });
    } catch (e) {
      report(e);
      resolveReady({ ok: false, error: api.errors.at(-1) });
    }
    return;
  }

  const { repositories } = await getJson("/repos");
  const elevation = repositories.filter((r) => r.attribute !== "colour");
  const colours = repositories.filter((r) => r.attribute === "colour");
  const repoSelect = $("repo");
  for (const r of elevation) {
    const o = document.createElement("option");
    o.value = r.name;
    o.textContent = `${r.name} (${r.domain === "sphere" ? "planet" : "planar"})`;
    repoSelect.append(o);
  }
  if (elevation.length === 0) throw new Error("this server serves no elevation repository");

  const fillColours = async (repo, selected) => {
    const select = $("colour");
    select.length = 1;
    const meta = await metadata(repo);
    for (const c of colours) {
      let ok = false;
      try {
        ok = coloursMatch(meta, await metadata(c.name));
      } catch {
        ok = false;
      }
      if (!ok) continue;
      const o = document.createElement("option");
      o.value = c.name;
      o.textContent = c.name;
      select.append(o);
    }
    select.value = selected && [...select.options].some((o) => o.value === selected) ? selected : "";
  };

  const tolerance = $("tolerance");
  const showTolerance = (px) => {
    $("tolerance-value").textContent = `${px < 1 ? px.toFixed(2) : px.toFixed(1)} px`;
  };

  let repo = query.repo;
  let fromUrl = Boolean(repo);
  if (repo && !elevation.some((r) => r.name === repo)) {
    report(new Error(`no elevation repository ${JSON.stringify(repo)} on this server`));
    resolveReady({ ok: false, error: api.errors.at(-1) });
    return;
  }
  if (!repo) repo = elevation[0].name;
  repoSelect.value = repo;
  const meta = await metadata(repo);
  let shot = query.shot;
  if (!query.hasPlace && !query.hasHeight) {
    const size = shot.size;
    const tol = shot.tolerancePx;
    shot = defaultShotFor(elevation.find((r) => r.name === repo), meta);
    shot.size = size;
    shot.tolerancePx = tol;
    fromUrl = false;
  }
  tolerance.value = String(Math.log2(shot.tolerancePx));
  showTolerance(shot.tolerancePx);
  await fillColours(repo, query.colour);
  if (query.colour && $("colour").value !== query.colour) {
    throw new Error(`${query.colour} is not a colour layer for ${repo}`);
  }

  const openSelected = async (newShot, isFromUrl) => {
    try {
      await viewer.open(repoSelect.value, $("colour").value || null, newShot, { fromUrl: isFromUrl });
    } catch (e) {
      report(e);
      resolveReady({ ok: false, error: api.errors.at(-1) });
    }
  };
  repoSelect.addEventListener("change", async () => {
    const name = repoSelect.value;
    const m = await metadata(name);
    await fillColours(name, null);
    const s = defaultShotFor(elevation.find((r) => r.name === name), m);
    s.size = viewer.fixedSize;
    s.tolerancePx = viewer.shot ? viewer.shot.tolerancePx : 1;
    await openSelected(s, false);
  });
  $("colour").addEventListener("change", async () => {
    const s = viewer.shot ? { ...viewer.shot } : defaultShotFor(elevation.find((r) => r.name === repoSelect.value), meta);
    await openSelected(s, false);
  });
  tolerance.addEventListener("input", () => {
    const px = 2 ** Number(tolerance.value);
    showTolerance(px);
    if (viewer.shot) {
      viewer.shot.tolerancePx = px;
      viewer.urlDirty = true;
      viewer.restart();
    }
  });
  await openSelected(shot, fromUrl);
}

/** The last drawn frame, read from the offscreen target: `{width, height, rgbaBase64}`
 *  (RGBA bytes, rows top to bottom). For tests; not used in normal operation. */
function readPixels(viewer) {
  const r = viewer.renderer;
  if (!r || !r.target) return null;
  const gl = viewer.gl;
  const { w, h, fb } = r.target;
  const data = new Uint8Array(w * h * 4);
  gl.bindFramebuffer(gl.READ_FRAMEBUFFER, fb);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, data);
  gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
  const out = new Uint8Array(w * h * 4);
  for (let y = 0; y < h; y++) out.set(data.subarray((h - 1 - y) * w * 4, (h - y) * w * 4), y * w * 4);
  let binary = "";
  for (let k = 0; k < out.length; k += 32768) binary += String.fromCharCode.apply(null, out.subarray(k, k + 32768));
  return { width: w, height: h, rgbaBase64: btoa(binary) };
}

main().catch((e) => {
  report(e);
  resolveReady({ ok: false, error: api.errors.at(-1) });
});
