// The viewer's terrain renderer: draws the crack-free cut a client session streams, with
// WebGL2, the way `quincunx render` draws it.
//
// Ports render/src/renderer.rs (retained patches, uploads capped per frame, the drawn cut
// switched once the new one is resident, the shared grid index buffer), terrain.wgsl (as
// GLSL ES 3.00: vertices rebuilt from exact integers, camera-relative, the same tint,
// hillshade and colour layer), render/src/domain.rs (the affine map of a patch in fine
// units) and render/src/ground.rs (`surface_height_m`: the surface under the camera as
// drawn).
//
// - A patch (one half of a diamond in the cut) gets its own vertex buffer holding its
//   (N+1)^2 integer heights, uploaded once per (id, half, generation) and deleted when it
//   leaves the cut; its colour (YCoCg-R, 10 bits a channel) is a small R32UI texture. Its
//   affine map in integer fine units (limbs) is 5 ivec4 uniforms set per draw.
// - Precision: the shader subtracts the camera's exact integer limbs from the vertex's,
//   so only camera-relative numbers reach float32 (render/src/camera.rs).
// - Depth: reversed Z with an infinite far plane into a 32-bit float depth buffer, with
//   `EXT_clip_control` (depth = near / distance, as wgpu stores it) when present, else the
//   same depth written per fragment (`gl_FragDepth = near * gl_FragCoord.w`).

import { NEAR_M, frameUniforms, isNarrow, length, sub, upAt, worldPoint } from "./camera.mjs";
import { indexPatch, surfaceHeightM } from "./ground.mjs";

/** Patches uploaded per frame at most (renderer.rs `max_uploads_per_frame`). */
export const MAX_UPLOADS_PER_FRAME = 512;

/** Whether a half is the lower one (`i >= j`); accepts "lower"/"Lower"/0. */
export function isLowerHalf(half) {
  return half === 0 || half === "lower" || half === "Lower" || half === "L";
}

/** A key for a patch: "id|half" (the client's `patchKey` when given). */
export function defaultPatchKey(id, half) {
  return `${String(id && id.c ? id.c : id)}|${isLowerHalf(half) ? "L" : "U"}`;
}

// ---- the grid's triangles (renderer.rs grid_indices) -------------------------------

/** The lower half's triangles, then the upper half's; cells split along i = j. */
export function gridIndices(n) {
  const nv = n + 1;
  const at = (i, j) => i * nv + j;
  const lower = [];
  const upper = [];
  for (let i = 0; i < n; i++) {
    for (let j = 0; j < n; j++) {
      const a = at(i, j);
      const b = at(i + 1, j);
      const c = at(i + 1, j + 1);
      const d = at(i, j + 1);
      if (i >= j) lower.push(a, b, c);
      if (i > j) lower.push(a, c, d);
      if (i <= j) upper.push(a, c, d);
      if (i < j) upper.push(a, b, c);
    }
  }
  const all = lower.concat(upper);
  return { indices: nv * nv > 65535 ? Uint32Array.from(all) : Uint16Array.from(all), half: lower.length };
}

/** Limbs of a fine coordinate (`limbs`, or whole values when narrow). */
function split(x, narrow) {
  if (narrow) return [x | 0, 0];
  const hi = Math.floor(x / 65536);
  return [hi, x - hi * 65536];
}

/** The per-patch record (`patch_record`): 20 i32 = xy, e1, e2, z, zi. */
function patchRecord(a, level, hasColour, narrow) {
  const s = (v) => v.map((x) => split(x, narrow));
  const b = s(a.base);
  const e1 = s(a.e1);
  const e2 = s(a.e2);
  return Int32Array.from([
    b[0][0], b[1][0], b[0][1], b[1][1],
    e1[0][0], e1[1][0], e1[0][1], e1[1][1],
    e2[0][0], e2[1][0], e2[0][1], e2[1][1],
    b[2][0], b[2][1], e1[2][0], e1[2][1],
    e2[2][0], e2[2][1], level & 0xff, hasColour ? 1 : 0,
  ]);
}

/**
 * YCoCg-R integers packed as three signed 10-bit fields (`pack_colour`): per vertex,
 * each channel's integer scaled back to colour units (`ColourLayer::ycocg`).
 */
export function packColour(grids, scales, nc) {
  const count = (nc + 1) * (nc + 1);
  const out = new Uint32Array(count);
  const f = (x) => (Math.max(-512, Math.min(511, x)) & 0x3ff) >>> 0;
  const [gy, gco, gcg] = grids;
  const [sy, sco, scg] = scales;
  for (let k = 0; k < count; k++) {
    const y = roundHalfAway(sy[1] + gy[k] * sy[0]);
    const co = roundHalfAway(sco[1] + gco[k] * sco[0]);
    const cg = roundHalfAway(scg[1] + gcg[k] * scg[0]);
    out[k] = (f(y) | (f(co) << 10) | (f(cg) << 20)) >>> 0;
  }
  return out;
}

/** Rust's `f64::round` (half away from zero). */
function roundHalfAway(x) {
  return x < 0 ? -Math.round(-x) : Math.round(x);
}

// ---- shaders (terrain.wgsl) --------------------------------------------------------

function vertexSource(defs) {
  return `#version 300 es
${defs}
precision highp float;
precision highp int;

uniform mat4 clip_from_rel;
uniform ivec4 cam_hi;
uniform ivec4 cam_lo;
uniform vec4 cam_frac;
uniform vec4 cam_dir;
uniform vec4 cos_ac;
uniform vec4 tan_c;
uniform vec4 heights;
uniform ivec4 ints;
uniform vec4 raster;
// The patch record: xy, e1, e2, z, zi (renderer.rs PatchGpu).
uniform ivec4 rec[5];

layout(location = 0) in int v;

out vec4 rel_h;
out vec2 grid;
flat out int info;
invariant gl_Position;

vec3 sin_small(vec3 x) {
  vec3 x2 = x * x;
  vec3 p = -2.5052108e-8 + x2 * 1.6059043e-10;
  vec3 q = 2.7557319e-6 + x2 * p;
  vec3 r = -1.9841270e-4 + x2 * q;
  vec3 s = 8.3333333e-3 + x2 * r;
  vec3 t = -1.6666667e-1 + x2 * s;
  return x + x * x2 * t;
}

vec3 cos_small(vec3 x) {
  vec3 x2 = x * x;
  vec3 p = 2.4801587e-5 + x2 * (-2.7557319e-7 + x2 * 2.0876757e-9);
  vec3 q = -1.3888889e-3 + x2 * p;
  vec3 r = 4.1666667e-2 + x2 * q;
  vec3 s = -0.5 + x2 * r;
  return 1.0 + x2 * s;
}

void main() {
  int nv = GRID_N + 1;
  int local = gl_VertexID;
  int i = local / nv;
  int j = local - i * nv;
  float dh = (float(v - ints.x) - cam_frac.w) * heights.x;
  vec3 rel;
#if PLANET
  ivec3 base_hi = ivec3(rec[0].xy, rec[3].x);
  ivec3 base_lo = ivec3(rec[0].zw, rec[3].y);
  ivec3 e1_hi = ivec3(rec[1].xy, rec[3].z);
  ivec3 e1_lo = ivec3(rec[1].zw, rec[3].w);
  ivec3 e2_hi = ivec3(rec[2].xy, rec[4].x);
  ivec3 e2_lo = ivec3(rec[2].zw, rec[4].y);
  ivec3 lo_sum = base_lo + i * e1_lo + j * e2_lo;
  ivec3 hi = base_hi + i * e1_hi + j * e2_hi + (lo_sum >> 16);
  ivec3 lo = lo_sum & ivec3(0xFFFF);
  vec3 d = vec3(hi - cam_hi.xyz) * 65536.0 + vec3(lo - cam_lo.xyz) - cam_frac.xyz;
  // G(p) - G(c) for the equal-angle map without cancellation (terrain.wgsl).
  float h = heights.y + float(v) * heights.x;
  float a = cos_ac.w;
  vec3 pf = vec3(hi) * 65536.0 + vec3(lo);
  vec3 dt = sin_small(a * d) / (cos_ac.xyz * cos_small(a * pf));
  vec3 tc = tan_c.xyz;
  float ntc = tan_c.w;
  vec3 tp = tc + dt;
  float ntp = length(tp);
  float grow = (2.0 * dot(tc, dt) + dot(dt, dt)) / (ntp + ntc);
  vec3 dg = dt / ntp - tc * (grow / (ntp * ntc));
  rel = h * dg + dh * cam_dir.xyz;
#else
  vec2 d;
#if NARROW
  ivec2 p = rec[0].xy + i * rec[1].xy + j * rec[2].xy;
  d = vec2(p - cam_hi.xy) - cam_frac.xy;
#else
  ivec2 lo_sum = rec[0].zw + i * rec[1].zw + j * rec[2].zw;
  ivec2 hi = rec[0].xy + i * rec[1].xy + j * rec[2].xy + (lo_sum >> 16);
  ivec2 lo = lo_sum & ivec2(0xFFFF);
  d = vec2(hi - cam_hi.xy) * 65536.0 + vec2(lo - cam_lo.xy) - cam_frac.xy;
#endif
  rel = vec3(d * cam_dir.w, dh);
#endif
  gl_Position = clip_from_rel * vec4(rel, 1.0);
  rel_h = vec4(rel, raster.z + float(v) * heights.x);
  grid = vec2(float(i), float(j));
  info = (rec[4].z & 0xFF) | ((rec[4].w & 1) << 8);
}
`;
}

function fragmentSource(defs) {
  return `#version 300 es
${defs}
precision highp float;
precision highp int;
precision highp usampler2D;

uniform vec4 light;
uniform vec4 heights;
uniform ivec4 ints;
uniform vec4 rect;
uniform usampler2D colours;

in vec4 rel_h;
in vec2 grid;
flat in int info;
out vec4 frag;

vec3 land(float h) {
  float t = clamp((h - heights.z) / max(heights.w - heights.z, 1.0), 0.0, 1.0);
  vec3 c0 = vec3(0.30, 0.52, 0.28);
  vec3 c1 = vec3(0.72, 0.68, 0.42);
  vec3 c2 = vec3(0.52, 0.38, 0.26);
  vec3 c3 = vec3(0.94, 0.94, 0.94);
  if (t < 0.35) {
    return mix(c0, c1, t / 0.35);
  } else if (t < 0.75) {
    return mix(c1, c2, (t - 0.35) / 0.4);
  }
  return mix(c2, c3, (t - 0.75) / 0.25);
}

// Elevation tint: sea below 0, then green, ochre, brown, white (terrain.wgsl tint).
vec3 tint(float h) {
  float t_sea = clamp(-h / 6000.0, 0.0, 1.0);
  vec3 sea = mix(vec3(0.36, 0.56, 0.74), vec3(0.07, 0.16, 0.36), sqrt(t_sea));
  float shore = smoothstep(0.0, 2.0, h);
  if (shore <= 0.0) {
    return sea;
  }
  return mix(sea, land(h), shore);
}

vec3 unpack_rgb(uint word) {
  // Three signed 10-bit fields Y, Co, Cg; the inverse YCoCg-R lifting in integers.
  int y = int(word << 22u) >> 22;
  int co = int(word << 12u) >> 22;
  int cg = int(word << 2u) >> 22;
  int t = y - (cg >> 1);
  int g = cg + t;
  int b = t - (co >> 1);
  int r = b + co;
  return clamp(vec3(float(r), float(g), float(b)) / 255.0, vec3(0.0), vec3(1.0));
}

uint colour_word(int i, int j) {
  return texelFetch(colours, ivec2(j, i), 0).r;
}

vec3 colour_at(vec2 g) {
  int nc = ints.y;
  float n = float(GRID_N);
  float ncf = float(nc);
  float x = clamp(g.x * ncf / n, 0.0, ncf);
  float y = clamp(g.y * ncf / n, 0.0, ncf);
  int ci = min(int(floor(x)), nc - 1);
  int cj = min(int(floor(y)), nc - 1);
  float fx = x - float(ci);
  float fy = y - float(cj);
  vec3 c00 = unpack_rgb(colour_word(ci, cj));
  vec3 c11 = unpack_rgb(colour_word(ci + 1, cj + 1));
  // The grid's triangles split each cell along i = j, as the geometry does.
  if (fx >= fy) {
    vec3 c10 = unpack_rgb(colour_word(ci + 1, cj));
    return c00 + fx * (c10 - c00) + fy * (c11 - c10);
  }
  vec3 c01 = unpack_rgb(colour_word(ci, cj + 1));
  return c00 + fy * (c01 - c00) + fx * (c11 - c01);
}

vec3 level_colour(int level) {
  float k = float(level) * 0.618034;
  float hue = k - floor(k);
  float r = abs(hue * 6.0 - 3.0) - 1.0;
  float g = 2.0 - abs(hue * 6.0 - 2.0);
  float b = 2.0 - abs(hue * 6.0 - 4.0);
  return mix(vec3(0.5), clamp(vec3(r, g, b), vec3(0.0), vec3(1.0)), 0.7);
}

void main() {
  // Derivatives first, in uniform control flow: the face normal of each triangle from the
  // camera-relative positions the rasteriser used.
  vec3 rel = rel_h.xyz;
  vec3 dx = dFdx(rel);
  vec3 dy = dFdy(rel);
  vec2 g = grid;
#if WIREFRAME
  vec2 gw = fwidth(g);
  float gd = fwidth(g.x - g.y);
#endif
#if !PLANET
  if (rel.x < rect.x || rel.y < rect.y || rel.x > rect.z || rel.y > rect.w) {
    discard;
  }
#endif
  vec3 base;
#if LEVELS
  base = level_colour(info & 0xFF);
#elif COLOUR
  if ((info & 256) != 0) {
    base = colour_at(g);
  } else {
    base = tint(rel_h.w);
  }
#else
  base = tint(rel_h.w);
#endif
  vec3 nrm = normalize(cross(dx, dy));
  if (dot(nrm, rel) > 0.0) {
    nrm = -nrm;
  }
  float ambient = light.w;
  vec3 c = base * (ambient + (1.0 - ambient) * max(dot(nrm, light.xyz), 0.0));
#if WIREFRAME
  vec2 f = abs(g - round(g)) / max(gw, vec2(1e-6));
  float e = abs((g.x - g.y) - round(g.x - g.y)) / max(gd, 1e-6);
  float line = 1.0 - clamp(min(min(f.x, f.y), e), 0.0, 1.0);
  c = mix(c, vec3(0.05), line * 0.8);
#endif
  frag = vec4(c, 1.0);
#if FRAG_DEPTH
  gl_FragDepth = ${NEAR_M.toFixed(6)} * gl_FragCoord.w;
#endif
}
`;
}

function compile(gl, type, source) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
    const log = gl.getShaderInfoLog(s);
    gl.deleteShader(s);
    throw new Error(`shader compilation failed: ${log}`);
  }
  return s;
}

function link(gl, defs) {
  const vs = compile(gl, gl.VERTEX_SHADER, vertexSource(defs));
  const fs = compile(gl, gl.FRAGMENT_SHADER, fragmentSource(defs));
  const p = gl.createProgram();
  gl.attachShader(p, vs);
  gl.attachShader(p, fs);
  gl.bindAttribLocation(p, 0, "v");
  gl.linkProgram(p);
  gl.deleteShader(vs);
  gl.deleteShader(fs);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
    throw new Error(`shader link failed: ${gl.getProgramInfoLog(p)}`);
  }
  const names = [
    "clip_from_rel", "cam_hi", "cam_lo", "cam_frac", "cam_dir", "cos_ac", "tan_c", "light",
    "heights", "ints", "raster", "rect", "rec", "colours",
  ];
  const loc = {};
  for (const n of names) loc[n] = gl.getUniformLocation(p, n);
  return { program: p, loc };
}

// ---- the renderer ------------------------------------------------------------------

/**
 * Draws the cut of one repository (with its optional colour layer).
 * `new TerrainRenderer(gl, {world, colourScales, tintM, clipControl})` (`clipControl`
 * false: the gl_FragDepth path even where EXT_clip_control exists); per frame:
 * `apply(changes)`, `prepare(camera)`, `draw(background)`.
 */
export class TerrainRenderer {
  constructor(gl, { world, colourScales = null, tintM = null, patchKey = defaultPatchKey, clipControl = true }) {
    this.gl = gl;
    this.world = world;
    this.n = world.n;
    this.narrow = isNarrow(world);
    this.colourScales = colourScales;
    this.patchKey = patchKey;
    this.lighting = { lightDir: null, ambient: 0.35, tintM };
    this.modes = { wireframe: false, colourByLevel: false, noColour: false };
    this.background = [135, 170, 210];
    if (world.geometry.kind === "planet" && world.geometry.halfSideFine > 2 ** 52) {
      throw new Error("this planet's fine coordinates exceed 2^52: not supported by the web viewer");
    }

    // Depth: reversed Z into a float depth buffer; clip control where the browser has it.
    this.clipControl = clipControl ? gl.getExtension("EXT_clip_control") : null;
    if (this.clipControl) {
      this.clipControl.clipControlEXT(this.clipControl.LOWER_LEFT_EXT, this.clipControl.ZERO_TO_ONE_EXT);
      this.depthMode = "reversed-Z, EXT_clip_control, f32";
    } else {
      this.depthMode = "reversed-Z, gl_FragDepth, f32";
    }

    const { indices, half } = gridIndices(this.n);
    this.halfIndices = half;
    this.indexType = indices instanceof Uint32Array ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;
    this.indexBytes = indices.BYTES_PER_ELEMENT;
    this.indexBuffer = gl.createBuffer();
    // Bound through each patch's vertex array (ELEMENT_ARRAY_BUFFER binding is VAO state).
    const tmp = gl.createVertexArray();
    gl.bindVertexArray(tmp);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    gl.deleteVertexArray(tmp);

    this.programs = new Map();
    this.target = null;

    /** key -> resident patch {vao, buffer, texture, record, lower, generation, ...} */
    this.drawn = new Map();
    /** key -> patch waiting for its upload */
    this.pending = new Map();
    /** keys of drawn patches that left the cut (dropped once the new cut is resident) */
    this.leaving = new Set();
    /** key -> the current cut's patches with their geometry (surface queries) */
    this.cut = new Map();
    this.uploadsTotal = 0;
    this.uploadBytesTotal = 0;
    this.lastStats = null;
  }

  /** The program for the current modes (compiled on first use). */
  program() {
    const planet = this.world.geometry.kind === "planet";
    const colour = this.world.colourN > 0 && !this.modes.noColour;
    const flags = {
      PLANET: planet,
      NARROW: this.narrow,
      COLOUR: colour,
      LEVELS: this.modes.colourByLevel,
      WIREFRAME: this.modes.wireframe,
      FRAG_DEPTH: !this.clipControl,
    };
    const id = JSON.stringify(flags);
    let p = this.programs.get(id);
    if (!p) {
      const defs = [`#define GRID_N ${this.n}`]
        .concat(Object.entries(flags).map(([k, v]) => `#define ${k} ${v ? 1 : 0}`))
        .join("\n");
      p = link(this.gl, defs);
      this.programs.set(id, p);
    }
    return p;
  }

  /**
   * Records cut changes (`TerrainRenderer::apply`): patches that left stop being drawn
   * once the new cut is resident; patches that entered are queued for upload.
   */
  apply(changes) {
    for (const l of changes.left || []) {
      const key = l.key ?? this.patchKey(l.id, l.half);
      this.cut.delete(key);
      const waiting = this.pending.get(key);
      if (waiting) {
        this.release(waiting.upload);
        this.pending.delete(key);
      }
      if (this.drawn.has(key)) this.leaving.add(key);
    }
    for (const patch of changes.entered || []) {
      const key = patch.key ?? this.patchKey(patch.id, patch.half);
      const lower = isLowerHalf(patch.half);
      // The client's exact affine map of the half (render/src/domain.rs `affine`).
      const affine = patch.affine;
      if (!affine) throw new Error(`patch ${key} is not affine in fine units`);
      const entry = { key, patch, lower, affine, indexed: undefined };
      this.cut.set(key, entry);
      const waiting = this.pending.get(key);
      if (waiting) {
        this.release(waiting.upload);
        this.pending.delete(key);
      }
      const resident = this.drawn.get(key);
      if (resident && resident.generation === patch.generation) {
        this.leaving.delete(key);
        continue;
      }
      this.pending.set(key, entry);
    }
  }

  /**
   * Uploads queued patches (up to the per-frame cap), switches to the new cut once it is
   * resident, and computes the frame's uniforms. Returns the frame's figures.
   */
  prepare(camera) {
    const stats = { uploads: 0, uploadBytes: 0, pending: 0, patches: 0, triangles: 0, current: false };
    const nv2 = (this.n + 1) * (this.n + 1);
    const nc = this.world.colourN;
    for (const entry of this.pending.values()) {
      if (stats.uploads >= MAX_UPLOADS_PER_FRAME) break;
      if (entry.upload) continue;
      entry.upload = this.upload(entry);
      stats.uploads++;
      stats.uploadBytes += nv2 * 4 + 80 + (entry.upload.texture ? (nc + 1) * (nc + 1) * 4 : 0);
    }
    let waiting = 0;
    for (const entry of this.pending.values()) if (!entry.upload) waiting++;
    stats.pending = waiting;
    if (waiting === 0) {
      for (const key of this.leaving) {
        this.release(this.drawn.get(key));
        this.drawn.delete(key);
      }
      this.leaving.clear();
      for (const [key, entry] of this.pending) {
        const old = this.drawn.get(key);
        if (old) this.release(old);
        this.drawn.set(key, entry.upload);
        this.leaving.delete(key);
      }
      this.pending.clear();
    }
    stats.current = waiting === 0;
    this.uniforms = frameUniforms(this.world, camera, this.lighting);
    stats.patches = this.drawn.size;
    stats.triangles = stats.patches * this.n * this.n;
    this.uploadsTotal += stats.uploads;
    this.uploadBytesTotal += stats.uploadBytes;
    this.lastStats = stats;
    return stats;
  }

  upload(entry) {
    const gl = this.gl;
    const { patch, affine, lower } = entry;
    const buffer = gl.createBuffer();
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    const grid = patch.grid instanceof Int32Array ? patch.grid : Int32Array.from(patch.grid);
    gl.bufferData(gl.ARRAY_BUFFER, grid, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribIPointer(0, 1, gl.INT, 4, 0);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.indexBuffer);
    gl.bindVertexArray(null);
    gl.bindBuffer(gl.ARRAY_BUFFER, null);
    let texture = null;
    const nc = this.world.colourN;
    if (nc > 0 && patch.colour && this.colourScales) {
      const words = packColour(patch.colour, this.colourScales, nc);
      texture = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32UI, nc + 1, nc + 1, 0, gl.RED_INTEGER, gl.UNSIGNED_INT, words);
      gl.bindTexture(gl.TEXTURE_2D, null);
    }
    const level = patchLevel(patch);
    return {
      vao,
      buffer,
      texture,
      lower,
      generation: patch.generation,
      record: patchRecord(affine, level, texture !== null, this.narrow),
    };
  }

  release(resident) {
    if (!resident) return;
    const gl = this.gl;
    gl.deleteVertexArray(resident.vao);
    gl.deleteBuffer(resident.buffer);
    if (resident.texture) gl.deleteTexture(resident.texture);
  }

  /** Makes the offscreen target (colour + 32-bit float depth) match the canvas size. */
  ensureTarget(w, h) {
    const gl = this.gl;
    if (this.target && this.target.w === w && this.target.h === h) return this.target;
    if (this.target) {
      gl.deleteFramebuffer(this.target.fb);
      gl.deleteRenderbuffer(this.target.colour);
      gl.deleteRenderbuffer(this.target.depth);
    }
    const fb = gl.createFramebuffer();
    const colour = gl.createRenderbuffer();
    const depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, colour);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA8, w, h);
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT32F, w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, colour);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`framebuffer incomplete (0x${status.toString(16)})`);
    this.target = { fb, colour, depth, w, h };
    return this.target;
  }

  /** Draws the drawn cut into the canvas (`w` x `h` device pixels). */
  draw(w, h) {
    const gl = this.gl;
    const t = this.ensureTarget(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.fb);
    gl.viewport(0, 0, w, h);
    const bg = this.background;
    gl.clearColor(bg[0] / 255, bg[1] / 255, bg[2] / 255, 1);
    gl.clearDepth(0);
    gl.depthMask(true);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const u = this.uniforms;
    if (u && this.drawn.size > 0) {
      const { program, loc } = this.program();
      gl.useProgram(program);
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.GREATER);
      gl.disable(gl.CULL_FACE);
      gl.disable(gl.BLEND);
      gl.uniformMatrix4fv(loc.clip_from_rel, false, u.clipFromRel);
      gl.uniform4iv(loc.cam_hi, u.camHi);
      gl.uniform4iv(loc.cam_lo, u.camLo);
      gl.uniform4fv(loc.cam_frac, u.camFrac);
      gl.uniform4fv(loc.cam_dir, u.camDir);
      gl.uniform4fv(loc.cos_ac, u.cosAc);
      gl.uniform4fv(loc.tan_c, u.tanC);
      gl.uniform4fv(loc.light, u.light);
      gl.uniform4fv(loc.heights, u.heights);
      gl.uniform4iv(loc.ints, u.ints);
      gl.uniform4fv(loc.raster, u.raster);
      gl.uniform4fv(loc.rect, u.rect);
      gl.uniform1i(loc.colours, 0);
      gl.activeTexture(gl.TEXTURE0);
      const upperOffset = this.halfIndices * this.indexBytes;
      let bound = undefined;
      for (const r of this.drawn.values()) {
        gl.bindVertexArray(r.vao);
        gl.uniform4iv(loc.rec, r.record);
        if (loc.colours && r.texture !== bound) {
          gl.bindTexture(gl.TEXTURE_2D, r.texture);
          bound = r.texture;
        }
        gl.drawElements(gl.TRIANGLES, this.halfIndices, this.indexType, r.lower ? 0 : upperOffset);
      }
      gl.bindVertexArray(null);
      gl.bindTexture(gl.TEXTURE_2D, null);
    }
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, t.fb);
    gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
    gl.blitFramebuffer(0, 0, w, h, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.NEAREST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }

  /** Frees every GPU object. */
  dispose() {
    const gl = this.gl;
    if (this.lost) return;
    if (this.clipControl) {
      this.clipControl.clipControlEXT(this.clipControl.LOWER_LEFT_EXT, this.clipControl.NEGATIVE_ONE_TO_ONE_EXT);
    }
    for (const r of this.drawn.values()) this.release(r);
    for (const e of this.pending.values()) this.release(e.upload);
    this.drawn.clear();
    this.pending.clear();
    this.leaving.clear();
    this.cut.clear();
    gl.deleteBuffer(this.indexBuffer);
    for (const p of this.programs.values()) gl.deleteProgram(p.program);
    this.programs.clear();
    if (this.target) {
      gl.deleteFramebuffer(this.target.fb);
      gl.deleteRenderbuffer(this.target.colour);
      gl.deleteRenderbuffer(this.target.depth);
      this.target = null;
    }
  }

  // ---- the surface under a point (ground.rs surface_height_m) -------------------------

  /**
   * Height (metres) of the current cut's surface below `eye` along the local up, where
   * that line meets the patches' triangles as drawn; null outside the data.
   */
  surfaceHeightM(eye) {
    if (!eye.every(Number.isFinite)) return null;
    const world = this.world;
    const cut = this.cut;
    function* patches() {
      for (const entry of cut.values()) {
        if (entry.indexed === undefined) {
          entry.indexed = indexPatch(world, entry.affine, entry.lower, entry.patch.grid);
        }
        yield entry.indexed;
      }
    }
    return surfaceHeightM(world, (f, v) => worldPoint(world, f, v), patches(), eye, upAt(world, eye));
  }
}

/** A patch's level for the level colours: from the client when it says, else its size. */
function patchLevel(patch) {
  if (Number.isInteger(patch.level)) return patch.level;
  const c = patch.corners;
  const d = [0, 1, 2].map((k) => c[2][k] - c[0][k]);
  const d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
  return d2 > 0 ? (64 - Math.round(Math.log2(d2))) & 0xff : 0;
}
