// quincunx terrain: one shader for planar and planet repositories.
//
// Every vertex is rebuilt from exact integers: its patch's affine map in fine units (the
// repository's id units times N, 64-bit, split into 16-bit limbs `hi * 65536 + lo`), its
// grid index and its integer height. The camera is split the same way once per frame.
// A vertex's camera-relative position is a function of those integers and the frame
// uniforms alone, computed with the same arithmetic in every patch, so two patches that
// share a vertex produce the same bits (no cracks), and only small numbers ever reach f32
// (no jitter near the camera). See docs/rendering.md, "Precision".

struct Frame {
    clip_from_rel: mat4x4<f32>,
    // Camera anchor in fine units: integer limbs; w of cam_hi = kind (0 planar, 1 planet),
    // w of cam_lo = N.
    cam_hi: vec4<i32>,
    cam_lo: vec4<i32>,
    // Fractional part of the anchor; w = fractional part of the camera height (samples).
    cam_frac: vec4<f32>,
    // Planet: unit direction of the camera (G(c)); w = metres per fine unit (planar).
    cam_dir: vec4<f32>,
    // Planet: cos(a c_k); w = a = pi / (4 S), S = cube half side in fine units.
    cos_ac: vec4<f32>,
    // Planet: T(c) = tan(a c_k); w = |T(c)|.
    tan_c: vec4<f32>,
    // Light direction (world, towards the light); w = ambient share.
    light: vec4<f32>,
    // x = metres per height sample, y = radius + height offset (planet) or height offset
    // (planar), z, w = tint range low, high (metres).
    heights: vec4<f32>,
    // x = integer part of the camera height (samples), y = Nc (colour grid size, 0 none),
    // z, w unused.
    ints: vec4<i32>,
    // z = height offset (metres); x, y, w unused.
    raster: vec4<f32>,
    // Planar raster bounds relative to the eye (metres): x0, y0, x1, y1.
    rect: vec4<f32>,
}


// Pipeline constants: the domain and the grid size are fixed per renderer, so the
// compiler drops the other domain's code and divides by a constant.
override PLANET: bool = false;
override GRID_N: u32 = 32u;
// Drawing modes, one pipeline each (llvmpipe pays for untaken uniform branches): the
// colour layer (compiled out without one, or when switched off), colour by level, grid
// lines, and an sRGB target (linear output).
override COLOUR: bool = false;
override LEVELS: bool = false;
override WIREFRAME: bool = false;
override SRGB: bool = false;
// Planar repositories whose fine extent is below 2^30 use plain i32 positions (the record
// then holds whole values in the high fields and zeros in the low ones).
override NARROW: bool = false;

@group(0) @binding(0) var<uniform> frame: Frame;
@group(0) @binding(1) var<storage, read> colours: array<u32>;

// Vertex inputs: the grid vertex's height, and its patch's record (per instance; the
// instance index is the slot). The record holds the affine map in limbs: `xy` =
// (base hi x, y, base lo x, y), `e1`, `e2` likewise, `z` = (base hi, base lo, e1 hi, e1 lo)
// of z, `zi` = (e2 hi z, e2 lo z, level, flags). The plane reads no z.
struct PlanarIn {
    @builtin(vertex_index) vertex_index: u32,
    @builtin(instance_index) slot: u32,
    @location(0) v: i32,
    @location(1) xy: vec4<i32>,
    @location(2) e1: vec4<i32>,
    @location(3) e2: vec4<i32>,
    @location(5) zi: vec4<i32>,
}

struct PlanetIn {
    @builtin(vertex_index) vertex_index: u32,
    @builtin(instance_index) slot: u32,
    @location(0) v: i32,
    @location(1) xy: vec4<i32>,
    @location(2) e1: vec4<i32>,
    @location(3) e2: vec4<i32>,
    @location(4) z: vec4<i32>,
    @location(5) zi: vec4<i32>,
}

struct VertexIn {
    vertex_index: u32,
    slot: u32,
    v: i32,
    xy: vec4<i32>,
    e1: vec4<i32>,
    e2: vec4<i32>,
    z: vec4<i32>,
    zi: vec4<i32>,
}

fn planar_in(p: PlanarIn) -> VertexIn {
    return VertexIn(p.vertex_index, p.slot, p.v, p.xy, p.e1, p.e2, vec4<i32>(0), p.zi);
}

fn planet_in(p: PlanetIn) -> VertexIn {
    return VertexIn(p.vertex_index, p.slot, p.v, p.xy, p.e1, p.e2, p.z, p.zi);
}

struct VertexOut {
    @builtin(position) @invariant clip: vec4<f32>,
    // Camera-relative position (metres) and height (metres).
    @location(0) rel_h: vec4<f32>,
    @location(1) grid: vec2<f32>,
    @location(2) @interpolate(flat) slot: u32,
    // Level (bits 0-7) and flags (bit 8: has colour) of the patch.
    @location(3) @interpolate(flat) info: u32,
}

// sin(x) for |x| <= pi/2 with full relative precision for small x (driver sin() may only
// promise an absolute error).
fn sin_small(x: vec3<f32>) -> vec3<f32> {
    let x2 = x * x;
    let p = -2.5052108e-8 + x2 * 1.6059043e-10;
    let q = 2.7557319e-6 + x2 * p;
    let r = -1.9841270e-4 + x2 * q;
    let s = 8.3333333e-3 + x2 * r;
    let t = -1.6666667e-1 + x2 * s;
    return x + x * x2 * t;
}

// cos(x) for |x| <= pi/4.
fn cos_small(x: vec3<f32>) -> vec3<f32> {
    let x2 = x * x;
    let p = 2.4801587e-5 + x2 * (-2.7557319e-7 + x2 * 2.0876757e-9);
    let q = -1.3888889e-3 + x2 * p;
    let r = 4.1666667e-2 + x2 * q;
    let s = -0.5 + x2 * r;
    return 1.0 + x2 * s;
}

// Clip positions written by `vs_capture` (precision measurements read them back).
@group(1) @binding(0) var<storage, read_write> captured: array<vec4<f32>>;

@vertex
fn vs_planar(input: PlanarIn) -> VertexOut {
    return vertex(planar_in(input));
}

@vertex
fn vs_planet(input: PlanetIn) -> VertexOut {
    return vertex(planet_in(input));
}

// The same vertex computation, its clip position stored at the vertex's index: what the
// rasteriser receives, read back instead of drawn.
@vertex
fn capture_planar(input: PlanarIn) -> @builtin(position) vec4<f32> {
    let out = vertex(planar_in(input));
    captured[input.vertex_index] = out.clip;
    return vec4<f32>(2.0, 2.0, 0.5, 1.0);
}

@vertex
fn capture_planet(input: PlanetIn) -> @builtin(position) vec4<f32> {
    let out = vertex(planet_in(input));
    captured[input.vertex_index] = out.clip;
    return vec4<f32>(2.0, 2.0, 0.5, 1.0);
}

fn vertex(input: VertexIn) -> VertexOut {
    let nv = GRID_N + 1u;
    let slot = input.slot;
    let local = input.vertex_index - slot * (nv * nv);
    let row = local / nv;
    let i = i32(row);
    let j = i32(local - row * nv);
    let v = input.v;

    let dh = (f32(v - frame.ints.x) - frame.cam_frac.w) * frame.heights.x;
    var rel: vec3<f32>;
    if PLANET {
        // The vertex in fine units, exactly: limbs normalised to lo in [0, 65536).
        let base_hi = vec3<i32>(input.xy.xy, input.z.x);
        let base_lo = vec3<i32>(input.xy.zw, input.z.y);
        let e1_hi = vec3<i32>(input.e1.xy, input.z.z);
        let e1_lo = vec3<i32>(input.e1.zw, input.z.w);
        let e2_hi = vec3<i32>(input.e2.xy, input.zi.x);
        let e2_lo = vec3<i32>(input.e2.zw, input.zi.y);
        let lo_sum = base_lo + i * e1_lo + j * e2_lo;
        let hi = base_hi + i * e1_hi + j * e2_hi + (lo_sum >> vec3<u32>(16u));
        let lo = lo_sum & vec3<i32>(0xFFFF);
        // Relative to the camera anchor: exact integers, then one rounding.
        let d = vec3<f32>(hi - frame.cam_hi.xyz) * 65536.0
            + vec3<f32>(lo - frame.cam_lo.xyz) - frame.cam_frac.xyz;
        // G(p) - G(c) for the equal-angle cube map G(p) = T(p) / |T(p)|,
        // T_k = tan(a p_k), without cancellation:
        // T(p) - T(c) = sin(a (p - c)) / (cos(a c) cos(a p)).
        let h = frame.heights.y + f32(v) * frame.heights.x;
        let a = frame.cos_ac.w;
        let pf = vec3<f32>(hi) * 65536.0 + vec3<f32>(lo);
        let dt = sin_small(a * d) / (frame.cos_ac.xyz * cos_small(a * pf));
        let tc = frame.tan_c.xyz;
        let ntc = frame.tan_c.w;
        let tp = tc + dt;
        let ntp = length(tp);
        let grow = (2.0 * dot(tc, dt) + dot(dt, dt)) / (ntp + ntc);
        let dg = dt / ntp - tc * (grow / (ntp * ntc));
        rel = h * dg + dh * frame.cam_dir.xyz;
    } else {
        // The same on the plane, in two dimensions.
        var d: vec2<f32>;
        if NARROW {
            // Exact in i32; the camera anchor is whole in cam_hi.
            let p = input.xy.xy + i * input.e1.xy + j * input.e2.xy;
            d = vec2<f32>(p - frame.cam_hi.xy) - frame.cam_frac.xy;
        } else {
            let lo_sum = input.xy.zw + i * input.e1.zw + j * input.e2.zw;
            let hi = input.xy.xy + i * input.e1.xy + j * input.e2.xy
                + (lo_sum >> vec2<u32>(16u));
            let lo = lo_sum & vec2<i32>(0xFFFF);
            d = vec2<f32>(hi - frame.cam_hi.xy) * 65536.0
                + vec2<f32>(lo - frame.cam_lo.xy) - frame.cam_frac.xy;
        }
        let m = frame.cam_dir.w;
        rel = vec3<f32>(d * m, dh);
    }

    var out: VertexOut;
    out.clip = frame.clip_from_rel * vec4<f32>(rel, 1.0);
    out.rel_h = vec4<f32>(rel, frame.raster.z + f32(v) * frame.heights.x);
    out.grid = vec2<f32>(f32(i), f32(j));
    out.slot = slot;
    out.info = (u32(input.zi.z) & 0xFFu) | ((u32(input.zi.w) & 1u) << 8u);
    return out;
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let lo = c / 12.92;
    let hi = pow((c + 0.055) / 1.055, vec3<f32>(2.4));
    return select(hi, lo, c <= vec3<f32>(0.04045));
}

// Elevation tint (display-referred): sea below 0, then green, ochre, brown, white.
// Land fades in over the first 2 m above 0, so a lossy flat sea (values scattered around
// 0) reads as shallow water rather than as blotches of land.
fn tint(h: f32) -> vec3<f32> {
    let t_sea = clamp(-h / 6000.0, 0.0, 1.0);
    let sea = mix(vec3<f32>(0.36, 0.56, 0.74), vec3<f32>(0.07, 0.16, 0.36), sqrt(t_sea));
    let shore = smoothstep(0.0, 2.0, h);
    if shore <= 0.0 {
        return sea;
    }
    return mix(sea, land(h), shore);
}

fn land(h: f32) -> vec3<f32> {
    let t = clamp((h - frame.heights.z) / max(frame.heights.w - frame.heights.z, 1.0), 0.0, 1.0);
    let c0 = vec3<f32>(0.30, 0.52, 0.28);
    let c1 = vec3<f32>(0.72, 0.68, 0.42);
    let c2 = vec3<f32>(0.52, 0.38, 0.26);
    let c3 = vec3<f32>(0.94, 0.94, 0.94);
    if t < 0.35 {
        return mix(c0, c1, t / 0.35);
    } else if t < 0.75 {
        return mix(c1, c2, (t - 0.35) / 0.4);
    }
    return mix(c2, c3, (t - 0.75) / 0.25);
}

fn unpack_rgb(word: u32) -> vec3<f32> {
    // Three signed 10-bit fields Y, Co, Cg; the inverse YCoCg-R lifting in integers.
    let w = bitcast<i32>(word);
    let y = (w << 22u) >> 22u;
    let co = (w << 12u) >> 22u;
    let cg = (w << 2u) >> 22u;
    let t = y - (cg >> 1u);
    let g = cg + t;
    let b = t - (co >> 1u);
    let r = b + co;
    return clamp(vec3<f32>(f32(r), f32(g), f32(b)) / 255.0, vec3<f32>(0.0), vec3<f32>(1.0));
}

fn colour_at(slot: u32, grid: vec2<f32>) -> vec3<f32> {
    let nc = u32(frame.ints.y);
    let n = f32(GRID_N);
    let ncf = f32(nc);
    let x = clamp(grid.x * ncf / n, 0.0, ncf);
    let y = clamp(grid.y * ncf / n, 0.0, ncf);
    let ci = min(u32(floor(x)), nc - 1u);
    let cj = min(u32(floor(y)), nc - 1u);
    let fx = x - f32(ci);
    let fy = y - f32(cj);
    let ncv = nc + 1u;
    let base = slot * ncv * ncv;
    let c00 = unpack_rgb(colours[base + ci * ncv + cj]);
    let c11 = unpack_rgb(colours[base + (ci + 1u) * ncv + cj + 1u]);
    // The grid's triangles split each cell along i = j, as the geometry does.
    if fx >= fy {
        let c10 = unpack_rgb(colours[base + (ci + 1u) * ncv + cj]);
        return c00 + fx * (c10 - c00) + fy * (c11 - c10);
    }
    let c01 = unpack_rgb(colours[base + ci * ncv + cj + 1u]);
    return c00 + fy * (c01 - c00) + fx * (c11 - c01);
}

fn level_colour(level: i32) -> vec3<f32> {
    let k = f32(level) * 0.618034;
    let hue = k - floor(k);
    let r = abs(hue * 6.0 - 3.0) - 1.0;
    let g = 2.0 - abs(hue * 6.0 - 2.0);
    let b = 2.0 - abs(hue * 6.0 - 4.0);
    return mix(vec3<f32>(0.5), clamp(vec3<f32>(r, g, b), vec3<f32>(0.0), vec3<f32>(1.0)), 0.7);
}

// What the plain mode reads (no colour layer, no wireframe, no level colours): fewer
// varyings to interpolate, the others are dropped when the stages are linked.
struct PlainIn {
    @builtin(position) clip: vec4<f32>,
    @location(0) rel_h: vec4<f32>,
}

// Lit terrain at a camera-relative position with derivatives `dx`, `dy`.
fn lit(rel: vec3<f32>, dx: vec3<f32>, dy: vec3<f32>, base: vec3<f32>) -> vec3<f32> {
    var nrm = normalize(cross(dx, dy));
    if dot(nrm, rel) > 0.0 {
        nrm = -nrm;
    }
    let ambient = frame.light.w;
    var c = base * (ambient + (1.0 - ambient) * max(dot(nrm, frame.light.xyz), 0.0));
    if SRGB {
        c = srgb_to_linear(c);
    }
    return c;
}

fn outside_raster(rel: vec3<f32>) -> bool {
    let r = frame.rect;
    return !PLANET && (rel.x < r.x || rel.y < r.y || rel.x > r.z || rel.y > r.w);
}

@fragment
fn fs_plain(in: PlainIn) -> @location(0) vec4<f32> {
    return plain_colour(in);
}

fn plain_colour(in: PlainIn) -> vec4<f32> {
    let rel = in.rel_h.xyz;
    let dx = dpdx(rel);
    let dy = dpdy(rel);
    if outside_raster(rel) {
        discard;
    }
    return vec4<f32>(lit(rel, dx, dy, tint(in.rel_h.w)), 1.0);
}

// Backends without clip control (wgpu's GL backend: naga rewrites clip z to 2z - w, and
// the window depth is (z/w + 1) / 2 with an absolute spacing of about 6e-8, below which
// `near / distance` rounds to the clear value 0 at planet distances): the fragment stage
// writes the reversed-Z depth itself, `near / w` (`position.w` is 1 / clip w, interpolated
// linearly in screen space as Vulkan interpolates z / w), so the stored value and its
// relative precision are those of clip control. See docs/rendering.md, "Depth".
struct DepthOut {
    @location(0) colour: vec4<f32>,
    @builtin(frag_depth) depth: f32,
}

fn reversed_z(position: vec4<f32>) -> f32 {
    // Clip z of the reversed-Z, infinite-far projection is the near plane distance.
    return frame.clip_from_rel[3].z * position.w;
}

@fragment
fn fs_plain_depth(in: PlainIn) -> DepthOut {
    return DepthOut(plain_colour(in), reversed_z(in.clip));
}

@fragment
fn fs_main_depth(in: VertexOut) -> DepthOut {
    return DepthOut(main_colour(in), reversed_z(in.clip));
}

@fragment
fn fs_main(in: VertexOut) -> @location(0) vec4<f32> {
    return main_colour(in);
}

fn main_colour(in: VertexOut) -> vec4<f32> {
    // Derivatives first, in uniform control flow. The face normal of each triangle comes
    // from the same camera-relative positions the rasteriser used.
    let rel = in.rel_h.xyz;
    let dx = dpdx(rel);
    let dy = dpdy(rel);
    let g = in.grid;
    // Grid-line widths only for the wireframe (a constant branch: derivatives allowed).
    var gw = vec2<f32>(1.0);
    var gd = 1.0;
    if WIREFRAME {
        gw = fwidth(g);
        gd = fwidth(g.x - g.y);
    }
    if outside_raster(rel) {
        discard;
    }
    var base: vec3<f32>;
    if LEVELS {
        base = level_colour(i32(in.info & 0xFFu));
    } else if COLOUR && (in.info & 256u) != 0u {
        base = colour_at(in.slot, g);
    } else {
        base = tint(in.rel_h.w);
    }
    var c = lit(rel, dx, dy, base);
    if WIREFRAME {
        let f = abs(g - round(g)) / max(gw, vec2<f32>(1e-6));
        let e = abs((g.x - g.y) - round(g.x - g.y)) / max(gd, 1e-6);
        let line = 1.0 - clamp(min(min(f.x, f.y), e), 0.0, 1.0);
        c = mix(c, vec3<f32>(0.05, 0.05, 0.05), line * 0.8);
    }
    return vec4<f32>(c, 1.0);
}
