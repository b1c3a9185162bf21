// The viewer's camera: views named the way `quincunx render` names them (a place, a
// height above the streamed terrain, heading, pitch, field of view), the projection and
// the per-frame uniforms, all in float64 on the host (JS numbers) and split into exact
// integer limbs and small float32 remainders for the shader.
//
// Ports render/src/scene.rs (`Place`, `Shot::view`), render/src/camera.rs (`Camera`,
// `frame_uniforms`, `default_light`, `limbs`) and render/src/domain.rs (`WorldFrame`),
// with glam's `look_to_rh` and `perspective_infinite_reverse_rh`. Same parameters, same
// camera: the browser test compares this viewer's pictures with `quincunx render`'s.
//
// Vectors are plain arrays [x, y, z]; matrices are column-major Float64Array(16).

/**
 * The equal-angle map from the cube [-1, 1]^3 (any scale) to the unit sphere
 * (quincunx-diamond `sphere::cube_to_unit_sphere`; the shader evaluates the same map).
 */
export function cubeToUnitSphere(p) {
  const big = Math.max(Math.abs(p[0]), Math.abs(p[1]), Math.abs(p[2]));
  if (big === 0 || !p.every((x) => Number.isFinite(x))) return [p[0], p[1], p[2]];
  const q = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    const x = p[k] / big;
    q[k] = Math.abs(p[k]) === big ? Math.sign(x) : Math.tan((Math.PI / 4) * x);
  }
  const norm = Math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
  return [q[0] / norm, q[1] / norm, q[2] / norm];
}

/** Inverse of `cubeToUnitSphere`: a direction to the cube [-1, 1]^3. */
export function unitSphereToCube(q) {
  const big = Math.max(Math.abs(q[0]), Math.abs(q[1]), Math.abs(q[2]));
  if (big === 0 || !q.every((x) => Number.isFinite(x))) return [q[0], q[1], q[2]];
  const p = [0, 0, 0];
  for (let k = 0; k < 3; k++) {
    p[k] = Math.abs(q[k]) === big ? Math.sign(q[k]) : Math.atan(q[k] / big) / (Math.PI / 4);
  }
  return p;
}

/** Near plane (metres): reversed Z with an infinite far plane. */
export const NEAR_M = 0.05;
/** Limb size of split integers (`hi * LIMB + lo`, `0 <= lo < LIMB`). */
export const LIMB = 65536;

// ---- vectors (float64) ------------------------------------------------------------

export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const cross = (a, b) => [
  a[1] * b[2] - a[2] * b[1],
  a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0],
];
export const length = (a) => Math.sqrt(dot(a, a));

/** glam `normalize_or`: `a` normalised, or `fallback` when that is not finite. */
export function normalizeOr(a, fallback) {
  const rcp = 1 / length(a);
  return Number.isFinite(rcp) && rcp > 0 ? scale(a, rcp) : fallback;
}

/** glam `any_orthonormal_vector` (`a` normalised). */
function anyOrthonormal(a) {
  const sign = a[2] < 0 || Object.is(a[2], -0) ? -1 : 1;
  const k = -1 / (sign + a[2]);
  const b = a[0] * a[1] * k;
  return [b, sign + a[1] * a[1] * k, -a[1]];
}

const radians = (deg) => (deg * Math.PI) / 180;
const degrees = (rad) => (rad * 180) / Math.PI;

// ---- the world frame (render/src/domain.rs) ----------------------------------------

/**
 * A repository's geometry as the shader sees it (`WorldFrame`):
 * `{geometry: {kind: "planar", metresPerFine, extentFine: [x, y]} |
 *             {kind: "planet", radiusM, halfSideFine},
 *   valueScaleM, valueOffsetM, n, colourN}`.
 * Fine units: planar id units times N; planets the sample units of `vertex_position` in
 * the domain `m + log2 N` (half side `2^m * 2 N^2`).
 */
export function worldFrame(meta, colourN = 0) {
  const ch = (meta.channels && meta.channels[0]) || {};
  const valueScaleM = Number.isFinite(ch.value_scale) ? ch.value_scale : 1;
  const valueOffsetM = Number.isFinite(ch.value_offset) ? ch.value_offset : 0;
  const n = meta.n;
  let geometry;
  if (meta.domain === "sphere") {
    geometry = { kind: "planet", radiusM: meta.radius_m, halfSideFine: 2 ** meta.m * 2 * n * n };
  } else {
    geometry = {
      kind: "planar",
      metresPerFine: planarSpacingM(meta) / n,
      extentFine: [(meta.extent[0] - 1) * n, (meta.extent[1] - 1) * n],
    };
  }
  return { geometry, valueScaleM, valueOffsetM, n, colourN };
}

const EARTH_RADIUS_M = 6_371_008.8;

/** Metres between samples of a planar repository (client-core/src/open.rs `planar_world`). */
export function planarSpacingM(meta) {
  const g = meta.georef;
  if (!g) return 1;
  const rows = meta.extent[1];
  const node = g.registration === "node" || g.registration === "Node";
  const intervals = Math.max(node ? rows - 1 : rows, 1);
  const crs = g.crs || "";
  const geographic =
    crs.includes("4326") ||
    ((crs === "" || crs.toLowerCase().includes("lat")) &&
      [g.west, g.east].every((v) => Math.abs(v) <= 360) &&
      [g.north, g.south].every((v) => Math.abs(v) <= 90));
  const perRow = Math.abs(g.north - g.south) / intervals;
  const spacing = geographic ? radians(perRow) * EARTH_RADIUS_M : perRow;
  return Number.isFinite(spacing) && spacing > 0 ? spacing : 1;
}

/** Whether every fine point fits an i32 (planar extents below 2^30). */
export function isNarrow(world) {
  const g = world.geometry;
  return g.kind === "planar" && g.extentFine.every((e) => e >= 0 && e < 2 ** 30);
}

/** World position (metres) of fine point `p` at integer height `v` (`WorldFrame::point`). */
export function worldPoint(world, p, v) {
  const h = world.valueOffsetM + v * world.valueScaleM;
  const g = world.geometry;
  if (g.kind === "planar") return [p[0] * g.metresPerFine, p[1] * g.metresPerFine, h];
  return scale(cubeToUnitSphere(p), g.radiusM + h);
}

/** The cube point (fine units) in the direction of `eye`, or `eye` in fine units. */
export function anchor(world, eye) {
  const g = world.geometry;
  if (g.kind === "planar") return [eye[0] / g.metresPerFine, eye[1] / g.metresPerFine, 0];
  return scale(unitSphereToCube(normalizeOr(eye, [0, 0, 1])), g.halfSideFine);
}

/** Height above the datum (metres) of a world point. */
export function heightOf(world, x) {
  return world.geometry.kind === "planar" ? x[2] : length(x) - world.geometry.radiusM;
}

/** The local up at `x`. */
export function upAt(world, x) {
  return world.geometry.kind === "planar" ? [0, 0, 1] : normalizeOr(x, [0, 0, 1]);
}

// ---- shots (render/src/scene.rs) ---------------------------------------------------

/**
 * A named view (`Shot`): `{place: {uv: [u, v]} | {latLon: [lat, lon]}, heightM,
 * headingDeg, pitchDeg, fovDeg, size: [w, h] | null, tolerancePx}`.
 */
export function defaultShot() {
  return {
    place: { uv: [0.5, 0.5] },
    heightM: 1000,
    headingDeg: 0,
    pitchDeg: -90,
    fovDeg: 60,
    size: null,
    tolerancePx: 1,
  };
}

/** Checks a shot's numbers (`Shot::validate`); returns an error message or null. */
export function validateShot(shot) {
  const p = shot.place;
  if (p.uv && !p.uv.every(Number.isFinite)) return "uv must be finite";
  if (p.latLon) {
    const [lat, lon] = p.latLon;
    if (!(Number.isFinite(lat) && Number.isFinite(lon) && Math.abs(lat) <= 90 && Math.abs(lon) <= 360)) {
      return "lat_lon: latitude in -90..=90, longitude in -360..=360";
    }
  }
  if (!(Number.isFinite(shot.heightM) && shot.heightM > 0 && shot.heightM <= 1e10)) {
    return "height_m must be above 0 and at most 1e10";
  }
  if (!(Number.isFinite(shot.fovDeg) && shot.fovDeg > 0.5 && shot.fovDeg < 179)) {
    return "fov_deg must be within 0.5..179";
  }
  if (!(Number.isFinite(shot.tolerancePx) && shot.tolerancePx > 0)) return "tolerance_px must be positive";
  if (!(Number.isFinite(shot.headingDeg) && Number.isFinite(shot.pitchDeg))) {
    return "heading_deg and pitch_deg must be finite";
  }
  if (!(shot.pitchDeg >= -90 && shot.pitchDeg <= 90)) return "pitch_deg must be within -90..=90";
  return null;
}

/** The point on the ground (height 0) under the camera, the local up and north. */
export function shotGround(shot, world) {
  const g = world.geometry;
  if (shot.place.uv && g.kind === "planar") {
    const [u, v] = shot.place.uv;
    const x = u * g.extentFine[0] * g.metresPerFine;
    const y = v * g.extentFine[1] * g.metresPerFine;
    // Row 0 is the north edge: north is -y.
    return { base: [x, y, 0], up: [0, 0, 1], north: [0, -1, 0] };
  }
  if (shot.place.latLon && g.kind === "planet") {
    const [la, lo] = shot.place.latLon.map(radians);
    const up = [Math.cos(la) * Math.cos(lo), Math.cos(la) * Math.sin(lo), Math.sin(la)];
    let north = normalizeOr(sub([0, 0, 1], scale(up, up[2])), [0, 0, 0]);
    if (north[0] === 0 && north[1] === 0 && north[2] === 0) {
      // At a pole: north along the prime meridian's direction of travel.
      const s = up[2] < 0 || Object.is(up[2], -0) ? -1 : 1;
      north = [-Math.cos(lo) * s, -Math.sin(lo) * s, 0];
    }
    return { base: scale(up, g.radiusM), up, north };
  }
  throw new Error(
    shot.place.uv
      ? "uv places a camera over a planar repository; this one is a planet (use lat_lon)"
      : "lat_lon places a camera over a planet; this repository is planar (use uv)",
  );
}

/**
 * The client view with the camera `heightM` above `groundM` (`Shot::view`):
 * `{eye, target, up, fovYRad, viewportPx, tolerancePx}`.
 */
export function shotView(shot, world, groundM, viewportPx) {
  const { base, up, north } = shotGround(shot, world);
  const east = cross(up, north);
  const h = radians(shot.headingDeg);
  const p = radians(shot.pitchDeg);
  const horiz = add(scale(north, Math.cos(h)), scale(east, Math.sin(h)));
  const forward = add(scale(horiz, Math.cos(p)), scale(up, Math.sin(p)));
  const camUp = add(scale(horiz, -Math.sin(p)), scale(up, Math.cos(p)));
  const eye = add(base, scale(up, groundM + shot.heightM));
  return {
    eye,
    target: add(eye, scale(forward, Math.max(shot.heightM, 1))),
    up: camUp,
    fovYRad: radians(shot.fovDeg),
    viewportPx,
    tolerancePx: shot.tolerancePx,
  };
}

/**
 * The shot whose camera stands at `eye` looking along `forward`, `groundM` being the
 * surface height under it (the inverse of `shotView`, for flying and the URL).
 */
export function shotFromEye(world, eye, forward, groundM, template) {
  const g = world.geometry;
  const shot = { ...template };
  let up;
  let north;
  if (g.kind === "planar") {
    shot.place = { uv: [eye[0] / (g.extentFine[0] * g.metresPerFine), eye[1] / (g.extentFine[1] * g.metresPerFine)] };
    shot.heightM = eye[2] - groundM;
    up = [0, 0, 1];
    north = [0, -1, 0];
  } else {
    const d = normalizeOr(eye, [0, 0, 1]);
    const lat = degrees(Math.asin(Math.max(-1, Math.min(1, d[2]))));
    const lon = degrees(Math.atan2(d[1], d[0]));
    shot.place = { latLon: [lat, lon] };
    shot.heightM = length(eye) - g.radiusM - groundM;
    ({ up, north } = shotGround(shot, world));
  }
  const east = cross(up, north);
  const f = normalizeOr(forward, scale(up, -1));
  const s = Math.max(-1, Math.min(1, dot(f, up)));
  shot.pitchDeg = degrees(Math.asin(s));
  const hx = dot(f, east);
  const hy = dot(f, north);
  if (Math.abs(hx) + Math.abs(hy) > 1e-12) shot.headingDeg = wrapDeg(degrees(Math.atan2(hx, hy)));
  return shot;
}

/** An angle in degrees brought into [0, 360). */
export function wrapDeg(a) {
  const w = a % 360;
  return w < 0 ? w + 360 : w;
}

// ---- the camera (render/src/camera.rs) ---------------------------------------------

/** The camera of a view (`Camera::from_view`). */
export function cameraFromView(view) {
  return {
    eye: view.eye,
    forward: sub(view.target, view.eye),
    up: view.up,
    fovYRad: view.fovYRad,
    viewportPx: view.viewportPx,
  };
}

/** Column-major 4x4 product `a * b`. */
function mul4(a, b) {
  const out = new Float64Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  }
  return out;
}

/** The view rotation (camera at the origin), glam `look_to_rh(0, f, up)`. */
export function rotation(camera) {
  const f = normalizeOr(camera.forward, [0, 0, -1]);
  let up = normalizeOr(camera.up, [0, 0, 1]);
  const fu = cross(f, up);
  if (dot(fu, fu) < 1e-24) up = anyOrthonormal(f);
  const s = normalizeOr(cross(f, up), [1, 0, 0]);
  const u = cross(s, f);
  // glam: s = f.cross(up).normalize() (no fallback); the guard above makes it safe.
  return Float64Array.from([s[0], u[0], -f[0], 0, s[1], u[1], -f[1], 0, s[2], u[2], -f[2], 0, 0, 0, 0, 1]);
}

/** Reversed-Z perspective with an infinite far plane (glam `perspective_infinite_reverse_rh`). */
export function projection(camera) {
  const [w, h] = camera.viewportPx;
  const aspect = Math.max(w, 1) / Math.max(h, 1);
  const f = 1 / Math.tan(0.5 * camera.fovYRad);
  return Float64Array.from([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, 0, -1, 0, 0, NEAR_M, 0]);
}

/** Clip space from camera-relative world metres. */
export function clipFromRel(camera) {
  return mul4(projection(camera), rotation(camera));
}

/** Pixel position (x right, y down) and depth of a world point; null behind the camera. */
export function project(camera, world) {
  const m = clipFromRel(camera);
  const r = sub(world, camera.eye);
  const c = [0, 1, 2, 3].map((row) => m[row] * r[0] + m[4 + row] * r[1] + m[8 + row] * r[2] + m[12 + row]);
  if (c[3] <= 0) return null;
  const [w, h] = camera.viewportPx;
  return [(c[0] / c[3] * 0.5 + 0.5) * w, (0.5 - (c[1] / c[3]) * 0.5) * h, c[2] / c[3]];
}

/** Splits an integer (exact in float64) into limbs `[hi, lo]`, `0 <= lo < LIMB`. */
export function limbs(x) {
  const hi = Math.floor(x / LIMB);
  const lo = x - hi * LIMB;
  return [Math.max(-2147483648, Math.min(2147483647, hi)), lo];
}

/**
 * Lighting (`Lighting`): `lightDir` null picks one from the camera; `tintM` [low, high]
 * is the height range the tint spans.
 */
export function defaultLighting() {
  return { lightDir: null, ambient: 0.35, tintM: null };
}

/** The default light: from the north-west, 50 degrees up (`default_light`). */
export function defaultLight(world, eye) {
  if (world.geometry.kind === "planar") return normalizeOr([-0.45, -0.45, 0.77], [0, 0, 1]);
  const up = normalizeOr(eye, [0, 0, 1]);
  const east = normalizeOr(cross([0, 0, 1], up), [1, 0, 0]);
  const north = cross(up, east);
  return normalizeOr(add(sub(scale(up, 0.77), scale(east, 0.45)), scale(north, 0.45)), [0, 0, 1]);
}

/**
 * The uniforms of one frame (`frame_uniforms`): typed arrays ready for `uniform*v`.
 * Float fields round to float32 exactly as Rust's `as f32`.
 */
export function frameUniforms(world, camera, lighting) {
  const clip = Float32Array.from(clipFromRel(camera));
  const a = anchor(world, camera.eye);
  const narrow = isNarrow(world);
  const cell = a.map((c) => (narrow ? Math.max(-1073741824, Math.min(1073741824, Math.floor(c))) : Math.floor(c)));
  const frac = [a[0] - cell[0], a[1] - cell[1], a[2] - cell[2]];
  const split = cell.map((c) => (narrow ? [c | 0, 0] : limbs(c)));
  const scaleM = world.valueScaleM !== 0 ? world.valueScaleM : 1;
  const g = world.geometry;
  let kind;
  let camDir;
  let cosAc;
  let tanC;
  let heightsY;
  let heightM;
  if (g.kind === "planar") {
    kind = 0;
    camDir = [0, 0, 0, g.metresPerFine];
    cosAc = [1, 1, 1, 0];
    tanC = [0, 0, 0, 1];
    heightsY = world.valueOffsetM;
    heightM = camera.eye[2];
  } else {
    kind = 1;
    const s = g.halfSideFine;
    const k = Math.PI / 4 / s;
    const t = a.map((c) => Math.tan(k * c));
    const cs = a.map((c) => Math.cos(k * c));
    const tl = length(t);
    camDir = [t[0] / tl, t[1] / tl, t[2] / tl, 0];
    cosAc = [cs[0], cs[1], cs[2], k];
    tanC = [t[0], t[1], t[2], tl];
    heightsY = g.radiusM + world.valueOffsetM;
    heightM = length(camera.eye) - g.radiusM;
  }
  const vc = (heightM - world.valueOffsetM) / scaleM;
  const vcInt = Math.max(-(2 ** 30), Math.min(2 ** 30, Math.floor(vc)));
  const light = normalizeOr(lighting.lightDir || defaultLight(world, camera.eye), [0, 0, 1]);
  let clipFlag = 0;
  let rect = [0, 0, 0, 0];
  if (g.kind === "planar") {
    const e = g.extentFine.map((x) => x * g.metresPerFine);
    clipFlag = 1;
    rect = [-camera.eye[0], -camera.eye[1], e[0] - camera.eye[0], e[1] - camera.eye[1]];
  }
  const tint = lighting.tintM || [0, 3000];
  return {
    clipFromRel: clip,
    camHi: Int32Array.from([split[0][0], split[1][0], split[2][0], kind]),
    camLo: Int32Array.from([split[0][1], split[1][1], split[2][1], world.n]),
    camFrac: Float32Array.from([frac[0], frac[1], frac[2], vc - vcInt]),
    camDir: Float32Array.from(camDir),
    cosAc: Float32Array.from(cosAc),
    tanC: Float32Array.from(tanC),
    light: Float32Array.from([light[0], light[1], light[2], lighting.ambient]),
    heights: Float32Array.from([scaleM, heightsY, tint[0], tint[1]]),
    ints: Int32Array.from([vcInt, world.colourN, 0, clipFlag]),
    raster: Float32Array.from([0, 0, world.valueOffsetM, 0]),
    rect: Float32Array.from(rect),
  };
}

// ---- the URL -----------------------------------------------------------------------

/**
 * The view a URL's query names: `{repo, colour, pack, colourPack, shot, hasPlace}`
 * (`pack`, `colour_pack`: URLs of repository files read by ranges; unknown or malformed
 * numbers throw an Error naming the parameter).
 */
export function parseViewQuery(search) {
  const q = new URLSearchParams(search);
  const shot = defaultShot();
  const num = (name) => {
    const s = q.get(name);
    if (s === null) return null;
    const v = Number(s);
    if (s.trim() === "" || !Number.isFinite(v)) throw new Error(`${name}=${s} is not a number`);
    return v;
  };
  const pair = (name) => {
    const s = q.get(name);
    if (s === null) return null;
    const parts = s.split(",");
    const v = parts.map((t) => Number(t));
    if (parts.length !== 2 || parts.some((t) => t.trim() === "") || !v.every(Number.isFinite)) {
      throw new Error(`${name}=${s} is not two numbers A,B`);
    }
    return v;
  };
  const uv = pair("uv");
  const latLon = pair("lat_lon");
  if (uv && latLon) throw new Error("give uv (planar) or lat_lon (planets), not both");
  if (uv) shot.place = { uv };
  if (latLon) shot.place = { latLon };
  for (const [name, key] of [
    ["height_m", "heightM"],
    ["heading_deg", "headingDeg"],
    ["pitch_deg", "pitchDeg"],
    ["fov_deg", "fovDeg"],
    ["tolerance_px", "tolerancePx"],
  ]) {
    const v = num(name);
    if (v !== null) shot[key] = v;
  }
  const size = q.get("size");
  if (size !== null) {
    const m = /^(\d{1,5})x(\d{1,5})$/.exec(size.trim());
    if (!m || +m[1] < 1 || +m[2] < 1) throw new Error(`size=${size} is not WxH`);
    shot.size = [+m[1], +m[2]];
  }
  return {
    repo: q.get("repo"),
    colour: q.get("colour") || q.get("color") || null,
    pack: q.get("pack") || null,
    colourPack: q.get("colour_pack") || q.get("color_pack") || null,
    shot,
    hasPlace: Boolean(uv || latLon),
    hasHeight: q.has("height_m"),
  };
}

/** Rounds `x` to `digits` decimals, as a short string. */
function fmt(x, digits) {
  const s = x.toFixed(digits);
  return s.includes(".") ? s.replace(/0+$/, "").replace(/\.$/, "") : s;
}

/** The query string of a view (the inverse of `parseViewQuery`, rounded sensibly). */
export function formatViewQuery(repo, colour, shot, packs = null) {
  const parts = [];
  if (packs?.pack) {
    parts.push(`pack=${encodeURIComponent(packs.pack)}`);
    if (packs.colourPack) parts.push(`colour_pack=${encodeURIComponent(packs.colourPack)}`);
  } else {
    parts.push(`repo=${encodeURIComponent(repo)}`);
    if (colour) parts.push(`colour=${encodeURIComponent(colour)}`);
  }
  if (shot.place.uv) parts.push(`uv=${shot.place.uv.map((x) => fmt(x, 7)).join(",")}`);
  else parts.push(`lat_lon=${shot.place.latLon.map((x) => fmt(x, 7)).join(",")}`);
  const hDigits = shot.heightM >= 100 ? 1 : 3;
  parts.push(`height_m=${fmt(shot.heightM, hDigits)}`);
  if (shot.headingDeg !== 0) parts.push(`heading_deg=${fmt(shot.headingDeg, 2)}`);
  parts.push(`pitch_deg=${fmt(shot.pitchDeg, 2)}`);
  if (shot.fovDeg !== 60) parts.push(`fov_deg=${fmt(shot.fovDeg, 2)}`);
  if (shot.tolerancePx !== 1) parts.push(`tolerance_px=${fmt(shot.tolerancePx, 3)}`);
  if (shot.size) parts.push(`size=${shot.size[0]}x${shot.size[1]}`);
  return parts.join("&");
}
