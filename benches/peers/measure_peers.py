#!/usr/bin/env python3
"""Measure peer compressors on one elevation grid (raw file + JSON sidecar).

Usage:
    python3 benches/peers/measure_peers.py <sidecar.json> [--json out.json] [--quick]

Needs: pip install imagecodecs numpy

What it measures (see benches/peers/README.md for the method):
  * lossless bits/sample (JPEG-XL, JPEG 2000 5/3, JPEG-LS, HTJ2K, LERC, pcodec,
    zstd-19 on 2D Lorenzo residuals),
  * bits/sample at RMS targets (default 1 m and 9 m) for JPEG 2000 9/7
    (OpenJPEG), SPERR (PWE), SZ3 (abs), ZFP (accuracy), LERC (float32
    maxZerror) and JPEG-LS near-lossless -- both by bisection to the lossiest
    setting whose measured RMS <= target, and by interpolation in log(RMS)
    between the two measured points nearest the target on either side,
  * bits/sample with a guaranteed max error <= 1 m (JPEG-LS near, SZ3 abs,
    LERC maxZerror, SPERR PWE; for int grids also "+round": bound k+0.49
    raw steps and output rounded to integers), verified on the valid samples,
  * single-thread decode speed (median of >= 5 timed decode calls).

bits/sample are over ALL samples (width*height); errors are over VALID
samples only (nodata excluded); nodata samples are filled before coding.
"""

import os

# One thread everywhere, before any codec library is loaded.
for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import datetime
import gc
import json
import math
import platform
import statistics
import sys
import time

import numpy as np

try:
    import imagecodecs as ic
except ImportError:  # pragma: no cover
    sys.exit("needs imagecodecs: pip install imagecodecs numpy")


# --------------------------------------------------------------------------
# Loading and filling
# --------------------------------------------------------------------------

def load_grid(sidecar_path):
    with open(sidecar_path) as f:
        meta = json.load(f)
    base = os.path.dirname(os.path.abspath(sidecar_path))
    raw_path = os.path.join(base, meta.get("file") or (meta["name"] + (".i16" if meta["dtype"] == "int16" else ".f32")))
    dtype = {"int16": "<i2", "float32": "<f4"}[meta["dtype"]]
    h, w = int(meta["height"]), int(meta["width"])
    raw = np.fromfile(raw_path, dtype=dtype)
    if raw.size != w * h:
        sys.exit(f"{raw_path}: {raw.size} samples, sidecar says {w}x{h}")
    raw = raw.reshape(h, w).astype(np.dtype(dtype).newbyteorder("="))
    nodata = meta.get("nodata")
    if meta["dtype"] == "float32":
        valid = np.isfinite(raw)
    elif nodata is None:
        valid = np.ones(raw.shape, bool)
    else:
        valid = raw != int(nodata)
    return meta, raw_path, raw, valid


def fill_nodata(raw, valid, max_iter=100000):
    """Fill invalid samples with the mean of their valid (or already filled)
    4-neighbours, iterated inwards until every hole is filled. Int grids get
    the mean rounded to the nearest integer. Returns (filled, iterations)."""
    filled = raw.astype(np.float64)
    known = valid.copy()
    filled[~known] = 0.0
    it = 0
    while not known.all() and it < max_iter:
        it += 1
        s = np.zeros_like(filled)
        c = np.zeros(filled.shape, np.int32)
        kv = np.where(known, filled, 0.0)
        ki = known.astype(np.int32)
        s[1:, :] += kv[:-1, :]; c[1:, :] += ki[:-1, :]
        s[:-1, :] += kv[1:, :]; c[:-1, :] += ki[1:, :]
        s[:, 1:] += kv[:, :-1]; c[:, 1:] += ki[:, :-1]
        s[:, :-1] += kv[:, 1:]; c[:, :-1] += ki[:, 1:]
        new = (~known) & (c > 0)
        if not new.any():  # no valid sample at all: fall back to 0
            break
        filled[new] = s[new] / c[new]
        known |= new
    filled[~known] = 0.0
    if raw.dtype.kind == "i":
        info = np.iinfo(raw.dtype)
        filled = np.clip(np.rint(filled), info.min, info.max).astype(raw.dtype)
    else:
        filled = filled.astype(raw.dtype)
    filled[valid] = raw[valid]
    return filled, it


# --------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------

class Ctx:
    """Everything the codecs need about the grid."""

    def __init__(self, meta, raw, valid, filled, quick):
        self.meta = meta
        self.valid = valid
        self.n = raw.size
        self.scale = float(meta.get("vertical_scale") or 1.0)
        self.offset = float(meta.get("vertical_offset") or 0.0)
        self.is_int = raw.dtype.kind == "i"
        self.filled = filled                       # raw units, nodata filled
        # reference heights in metres, valid samples only
        self.ref_m = raw[valid].astype(np.float64) * self.scale + self.offset
        # float32 metres (what float codecs see)
        self.f32 = (filled.astype(np.float64) * self.scale + self.offset).astype(np.float32)
        if self.is_int:
            self.umin = int(filled.min())
            # uint16 offset copy for codecs that want unsigned input
            self.u16 = (filled.astype(np.int32) - self.umin).astype(np.uint16)
        self.quick = quick
        self.timing_runs = 5 if quick else 7

    def metres(self, dec, kind):
        """Decoded array -> float64 metres at the valid samples."""
        d = dec[self.valid].astype(np.float64)
        if kind == "raw":
            return d * self.scale + self.offset
        if kind == "u16":
            return (d + self.umin) * self.scale + self.offset
        if kind == "m":
            return d
        raise ValueError(kind)

    def errors(self, dec, kind):
        e = self.metres(dec, kind) - self.ref_m
        return float(np.sqrt(np.mean(e * e))), float(np.max(np.abs(e)))

    def bps(self, nbytes):
        return nbytes * 8.0 / self.n


def time_decode(fn, runs):
    """Median wall time of `runs` calls of fn() (only the call is timed)."""
    fn()  # warm-up (page faults, lazy init)
    ts = []
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for _ in range(runs):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
    finally:
        if gc_was:
            gc.enable()
    return statistics.median(ts), ts


def log(*a):
    print(*a, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------
# Lossless codecs
# --------------------------------------------------------------------------

def lorenzo_zstd_encode(x, level):
    """2D Lorenzo residual (x - W - N + NW), zigzag, byte planes, zstd."""
    x = x.astype(np.int32)
    r = x.copy()
    r[1:, :] -= x[:-1, :]
    r[:, 1:] -= x[:, :-1]
    r[1:, 1:] += x[:-1, :-1]
    z = ((r << 1) ^ (r >> 31)).astype(np.uint32)
    wide = int(z.max()) >= 1 << 16
    z = z.astype(np.uint32 if wide else np.uint16)
    planes = z.view(np.uint8).reshape(-1, z.itemsize).T.copy()
    header = np.array([x.shape[0], x.shape[1], z.itemsize], np.uint32).tobytes()
    return header + ic.zstd_encode(planes.tobytes(), level)


def lorenzo_zstd_decode(buf, dtype):
    h, w, isz = np.frombuffer(buf[:12], np.uint32)
    planes = np.frombuffer(ic.zstd_decode(buf[12:]), np.uint8).reshape(isz, -1)
    z = planes.T.copy().view(np.uint32 if isz == 4 else np.uint16).reshape(h, w).astype(np.int32)
    r = (z >> 1) ^ -(z & 1)
    return np.cumsum(np.cumsum(r, axis=0, dtype=np.int32), axis=1, dtype=np.int32).astype(dtype)


def lossless_codecs(ctx):
    """(name, description, input kind, encode(), decode(bytes)) for this grid."""
    out = []
    if ctx.is_int:
        b, u = ctx.filled, ctx.u16
        out += [
            ("jpegxl", "JPEG-XL lossless, effort 7, uint16 input (raw - min)", "u16",
             lambda: ic.jpegxl_encode(u, lossless=True, effort=7, numthreads=1),
             lambda e: ic.jpegxl_decode(e, numthreads=1)),
            ("j2k_53", "JPEG 2000 reversible 5/3 (OpenJPEG), signed int16 input, defaults (no tiles)", "raw",
             lambda: ic.jpeg2k_encode(b, reversible=True, numthreads=1),
             lambda e: ic.jpeg2k_decode(e, numthreads=1)),
            ("jpegls", "JPEG-LS lossless (CharLS), uint16 input (raw - min)", "u16",
             lambda: ic.jpegls_encode(u, 0),
             lambda e: ic.jpegls_decode(e)),
            ("htj2k", "HTJ2K reversible (OpenJPH), signed int16 input", "raw",
             lambda: ic.htj2k_encode(b, reversible=True),
             lambda e: ic.htj2k_decode(e)),
            ("zstd19_lorenzo", "zstd-19 on zigzagged 2D Lorenzo residuals, byte planes (decode time includes numpy un-shuffle + 2D cumsum)", "raw",
             lambda: lorenzo_zstd_encode(b, 19),
             lambda e: lorenzo_zstd_decode(e, b.dtype)),
            ("pcodec", "pcodec (default level) on the int16 samples", "raw",
             lambda: ic.pcodec_encode(b),
             lambda e: ic.pcodec_decode(e, b.shape, b.dtype)),
            ("lerc", "LERC lossless on int16 (maxZerror 0)", "raw",
             lambda: ic.lerc_encode(b, 0),
             lambda e: ic.lerc_decode(e)),
        ]
    else:
        f = ctx.filled
        out += [
            ("lerc", "LERC lossless on float32 (maxZerror 0)", "f",
             lambda: ic.lerc_encode(f, 0), lambda e: ic.lerc_decode(e)),
            ("pcodec", "pcodec (default level) on float32", "f",
             lambda: ic.pcodec_encode(f), lambda e: ic.pcodec_decode(e, f.shape, f.dtype)),
        ]
    return out


def run_lossless(ctx):
    res = []
    for name, desc, kind, enc_fn, dec_fn in lossless_codecs(ctx):
        try:
            t0 = time.perf_counter()
            enc = bytes(enc_fn())
            te = time.perf_counter() - t0
            dec = dec_fn(enc)
            ref = ctx.u16 if kind == "u16" else ctx.filled
            exact = bool(np.array_equal(dec.reshape(ref.shape), ref))
            td, ts = time_decode(lambda: dec_fn(enc), ctx.timing_runs)
            r = dict(codec=name, description=desc, bytes=len(enc), bits_per_sample=ctx.bps(len(enc)),
                     lossless_verified=exact, encode_s=te, decode_s_median=td,
                     decode_msps=ctx.n / td / 1e6, decode_runs_s=ts)
            log(f"  lossless {name}: {r['bits_per_sample']:.3f} b/s, exact={exact}, decode {r['decode_msps']:.1f} MS/s")
        except Exception as ex:  # keep going: report what did not work
            r = dict(codec=name, description=desc, error=f"{type(ex).__name__}: {ex}")
            log(f"  lossless {name}: FAILED {r['error']}")
        res.append(r)
    return res


# --------------------------------------------------------------------------
# Lossy codecs: a knob u where larger u = lossier
# --------------------------------------------------------------------------

class Lossy:
    def __init__(self, name, desc, param_name, kind, u_to_param, enc, dec, out_kind,
                 sweep_full, sweep_quick, integer, u_lo, u_hi, ext_step):
        self.name, self.desc, self.param_name = name, desc, param_name
        self.u_to_param, self.enc, self.dec, self.out_kind = u_to_param, enc, dec, out_kind
        self.sweep_full, self.sweep_quick = sweep_full, sweep_quick
        self.integer, self.u_lo, self.u_hi, self.ext_step = integer, u_lo, u_hi, ext_step
        self.kind = kind
        self.points = {}   # u -> dict(result, _enc bytes)

    def param(self, u):
        return self.u_to_param(u)

    def evaluate(self, ctx, u):
        u = int(u) if self.integer else float(round(u, 6))
        if u in self.points:
            return self.points[u]
        p = self.param(u)
        t0 = time.perf_counter()
        enc = bytes(self.enc(p))
        te = time.perf_counter() - t0
        t0 = time.perf_counter()
        dec = self.dec(enc)
        td = time.perf_counter() - t0
        rms, mx = ctx.errors(dec, self.out_kind)
        pt = dict(u=u, param=p, bytes=len(enc), bits_per_sample=ctx.bps(len(enc)), rms_m=rms,
                  max_err_m=mx, encode_s=te, decode_s_once=td, _enc=enc)
        self.points[u] = pt
        log(f"    {self.name} {self.param_name}={p:g}: {pt['bits_per_sample']:.4f} b/s rms {rms:.4f} max {mx:.3f}")
        return pt

    def clamp(self, u):
        return min(max(u, self.u_lo), self.u_hi)


def lossy_codecs(ctx):
    out = []
    f = ctx.f32
    if ctx.is_int:
        b, u16 = ctx.filled, ctx.u16
        # JPEG 2000 9/7: imagecodecs' `level` is OpenJPEG's fixed-quality PSNR
        # target in dB (peak 2^16-1 for 16-bit samples). u = -PSNR.
        out.append(Lossy(
            "j2k_97", "JPEG 2000 irreversible 9/7 (OpenJPEG), signed int16 input, one quality layer set by "
            "PSNR (imagecodecs level), defaults otherwise (no tiles, 64x64 code blocks)",
            "psnr_db", "linear", lambda uu: -uu,
            lambda p: ic.jpeg2k_encode(b, p, reversible=False, numthreads=1),
            lambda e: ic.jpeg2k_decode(e, numthreads=1), "raw",
            sweep_full=[-110, -104, -98, -92, -86, -80, -74, -68, -62],
            sweep_quick=[-104, -96, -88, -80, -72, -64],
            integer=False, u_lo=-140, u_hi=-20, ext_step=8))
        # JPEG-LS near-lossless: u = NEAR (raw units)
        out.append(Lossy(
            "jpegls_near", "JPEG-LS near-lossless (CharLS), uint16 input (raw - min), NEAR in raw units",
            "near", "int", lambda uu: int(uu),
            lambda p: ic.jpegls_encode(u16, p), lambda e: ic.jpegls_decode(e), "u16",
            sweep_full=[0, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48],
            sweep_quick=[0, 1, 2, 4, 8, 16, 32],
            integer=True, u_lo=0, u_hi=255, ext_step=32))
    # float32-metre codecs; u = log2(bound)
    out.append(Lossy(
        "sperr_pwe", "SPERR point-wise-error mode on float32 metres (tolerance = PWE bound, m)",
        "pwe_m", "log", lambda uu: 2.0 ** uu,
        lambda p: ic.sperr_encode(f, p, "pwe", numthreads=1),
        lambda e: ic.sperr_decode(e, numthreads=1), "m",
        sweep_full=[-1, 0, 1, 2, 3, 4, 5, 6, 7, 8], sweep_quick=[-1, 1, 3, 5, 7],
        integer=False, u_lo=-12, u_hi=14, ext_step=2))
    out.append(Lossy(
        "sz3_abs", "SZ3 absolute error bound on float32 metres (bound, m)",
        "abs_m", "log", lambda uu: 2.0 ** uu,
        lambda p: ic.sz3_encode(f, "abs", abs=p),
        lambda e: ic.sz3_decode(e, f.shape, f.dtype), "m",
        sweep_full=[-1, 0, 1, 2, 3, 4, 5, 6, 7], sweep_quick=[-1, 1, 3, 5, 7],
        integer=False, u_lo=-12, u_hi=14, ext_step=2))
    out.append(Lossy(
        "zfp_acc", "ZFP fixed-accuracy on float32 metres (tolerance 2^k m; ZFP only uses the power of two)",
        "tolerance_m", "int", lambda uu: 2.0 ** int(uu),
        lambda p: ic.zfp_encode(f, p, mode="a", numthreads=1),
        lambda e: ic.zfp_decode(e, numthreads=1), "m",
        sweep_full=[-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9], sweep_quick=[-1, 1, 3, 5, 7, 9],
        integer=True, u_lo=-12, u_hi=16, ext_step=2))
    out.append(Lossy(
        "lerc_f32", "LERC on float32 metres (maxZerror, m)",
        "maxzerror_m", "log", lambda uu: 2.0 ** uu,
        lambda p: ic.lerc_encode(f, p), lambda e: ic.lerc_decode(e), "m",
        sweep_full=[-1, 0, 1, 2, 3, 4, 5, 6, 7], sweep_quick=[-1, 1, 3, 5, 7],
        integer=False, u_lo=-12, u_hi=14, ext_step=2))
    return out


def bracket(c, target):
    """(a, b): a = lossiest evaluated u with rms <= target below b,
    b = least lossy evaluated u with rms > target. Either may be None."""
    us = sorted(c.points)
    bad = [u for u in us if c.points[u]["rms_m"] > target]
    b = bad[0] if bad else None
    ok = [u for u in us if c.points[u]["rms_m"] <= target and (b is None or u < b)]
    a = ok[-1] if ok else None
    return a, b


def solve_target(ctx, c, target, iters):
    """Bisection to the lossiest setting with measured RMS <= target."""
    for _ in range(6):  # extend the sweep if the target is outside it
        a, b = bracket(c, target)
        if a is None and c.clamp(min(c.points) - c.ext_step) < min(c.points):
            c.evaluate(ctx, c.clamp(min(c.points) - c.ext_step))
        elif b is None and c.clamp(max(c.points) + c.ext_step) > max(c.points):
            c.evaluate(ctx, c.clamp(max(c.points) + c.ext_step))
        else:
            break
    for _ in range(iters):
        a, b = bracket(c, target)
        if a is None or b is None:
            break
        if c.integer:
            if b - a <= 1:
                break
            m = (a + b) // 2
        else:
            if b - a < (0.02 if c.kind == "linear" else 0.01):
                break
            m = (a + b) / 2.0
        c.evaluate(ctx, m)


def best_under(c, target):
    ok = [p for p in c.points.values() if p["rms_m"] <= target]
    return min(ok, key=lambda p: p["bytes"]) if ok else None


def interp_bits(c, target):
    """bits/sample interpolated linearly in log(RMS) between the measured
    points nearest the target from below and from above (by RMS)."""
    pts = [p for p in c.points.values() if p["rms_m"] > 0]
    lo = [p for p in pts if p["rms_m"] <= target]
    hi = [p for p in pts if p["rms_m"] > target]
    if not lo or not hi:
        return None
    p1 = max(lo, key=lambda p: (p["rms_m"], -p["bytes"]))
    p2 = min(hi, key=lambda p: (p["rms_m"], p["bytes"]))
    if p1["rms_m"] == target:
        return dict(bits_per_sample=p1["bits_per_sample"], rms_lo=p1["rms_m"], rms_hi=p2["rms_m"])
    t = (math.log(target) - math.log(p1["rms_m"])) / (math.log(p2["rms_m"]) - math.log(p1["rms_m"]))
    return dict(bits_per_sample=p1["bits_per_sample"] + t * (p2["bits_per_sample"] - p1["bits_per_sample"]),
                rms_lo=p1["rms_m"], rms_hi=p2["rms_m"])


def public(p):
    return {k: v for k, v in p.items() if not k.startswith("_")}


def run_lossy(ctx, targets, interp_targets, iters):
    results = {}
    codecs = lossy_codecs(ctx)
    for c in codecs:
        log(f"  lossy {c.name}")
        r = dict(codec=c.name, description=c.desc, param_name=c.param_name)
        try:
            for u in (c.sweep_quick if ctx.quick else c.sweep_full):
                c.evaluate(ctx, u)
            r["sweep_only"] = [public(p) for p in sorted(c.points.values(), key=lambda p: p["u"])]
            r["targets"] = {}
            for t in targets:
                solve_target(ctx, c, t, iters)
                best = best_under(c, t)
                e = dict(target_rms_m=t)
                if best is None:
                    e["bisection"] = None
                    e["note"] = "no setting reached the target"
                else:
                    bb = public(best)
                    td, ts = time_decode(lambda: c.dec(best["_enc"]), ctx.timing_runs)
                    bb.update(decode_s_median=td, decode_msps=ctx.n / td / 1e6, decode_runs_s=ts)
                    e["bisection"] = bb
                    log(f"   -> RMS<={t}: {c.param_name}={best['param']:g} {best['bits_per_sample']:.4f} b/s "
                        f"rms {best['rms_m']:.4f} decode {bb['decode_msps']:.1f} MS/s")
                e["interpolated"] = interp_bits(c, t)
                r["targets"][str(t)] = e
            r["interp_only"] = {str(t): interp_bits(c, t) for t in interp_targets}
            r["all_points"] = [public(p) for p in sorted(c.points.values(), key=lambda p: p["u"])]
            del r["sweep_only"]
        except Exception as ex:
            r["error"] = f"{type(ex).__name__}: {ex}"
            log(f"  lossy {c.name}: FAILED {r['error']}")
        results[c.name] = r
        # free encoded streams
        for p in c.points.values():
            p.pop("_enc", None)
    return results


# --------------------------------------------------------------------------
# Guaranteed max error
# --------------------------------------------------------------------------

def run_maxerr(ctx, bound):
    f = ctx.f32
    cases = []
    if ctx.is_int:
        near = int(math.floor(bound / ctx.scale + 1e-9))
        u16 = ctx.u16
        cases.append(("jpegls_near", f"near={near} (raw units)", "u16",
                      lambda: ic.jpegls_encode(u16, near), lambda e: ic.jpegls_decode(e)))
    cases += [
        ("sz3_abs", f"abs={bound:g} m", "m",
         lambda: ic.sz3_encode(f, "abs", abs=bound), lambda e: ic.sz3_decode(e, f.shape, f.dtype)),
        ("lerc_f32", f"maxZerror={bound:g} m", "m",
         lambda: ic.lerc_encode(f, bound), lambda e: ic.lerc_decode(e)),
        ("sperr_pwe", f"pwe={bound:g} m", "m",
         lambda: ic.sperr_encode(f, bound, "pwe", numthreads=1), lambda e: ic.sperr_decode(e, numthreads=1)),
    ]
    if ctx.is_int:
        # Integer-aware variant: the source heights are integers (raw units), so a float
        # codec bound just under (k + 0.5) raw steps followed by rounding the output to the
        # nearest integer still guarantees max error <= k steps. Rounding is part of the
        # timed decode.
        k = int(math.floor(bound / ctx.scale + 1e-9))
        be = (k + 0.49) * ctx.scale
        sc, off, dt = ctx.scale, ctx.offset, ctx.filled.dtype
        info = np.iinfo(dt)

        def to_raw(d):
            return np.clip(np.rint((d - off) / sc), info.min, info.max).astype(dt)
        cases += [
            ("sz3_abs+round", f"abs={be:g} m, output rounded to integer raw", "raw",
             lambda: ic.sz3_encode(f, "abs", abs=be), lambda e: to_raw(ic.sz3_decode(e, f.shape, f.dtype))),
            ("lerc_f32+round", f"maxZerror={be:g} m, output rounded to integer raw", "raw",
             lambda: ic.lerc_encode(f, be), lambda e: to_raw(ic.lerc_decode(e))),
            ("sperr_pwe+round", f"pwe={be:g} m, output rounded to integer raw", "raw",
             lambda: ic.sperr_encode(f, be, "pwe", numthreads=1),
             lambda e: to_raw(ic.sperr_decode(e, numthreads=1))),
        ]
    res = []
    for name, setting, kind, enc_fn, dec_fn in cases:
        try:
            enc = bytes(enc_fn())
            dec = dec_fn(enc)
            rms, mx = ctx.errors(dec, kind)
            td, ts = time_decode(lambda: dec_fn(enc), ctx.timing_runs)
            r = dict(codec=name, setting=setting, bound_m=bound, bytes=len(enc),
                     bits_per_sample=ctx.bps(len(enc)), rms_m=rms, max_err_m=mx,
                     bound_held=bool(mx <= bound),
                     # float32 metres can overshoot by a rounding step of the float32 input/output
                     bound_held_within_f32_rounding=bool(mx <= bound + 4 * np.spacing(np.float32(np.abs(ctx.ref_m).max()))),
                     decode_s_median=td,
                     decode_msps=ctx.n / td / 1e6, decode_runs_s=ts)
            log(f"  max<= {bound}: {name} {r['bits_per_sample']:.4f} b/s max {mx:.4f} held={r['bound_held']}")
        except Exception as ex:
            r = dict(codec=name, setting=setting, error=f"{type(ex).__name__}: {ex}")
            log(f"  max<= {bound}: {name} FAILED {r['error']}")
        res.append(r)
    return res


# --------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------

def versions():
    v = {"imagecodecs": ic.__version__, "numpy": np.__version__, "python": platform.python_version()}
    for n in ("jpeg2k", "jpegls", "jpegxl", "htj2k", "lerc", "sz3", "zfp", "sperr", "pcodec", "zstd"):
        try:
            v[n] = getattr(ic, n + "_version")()
        except Exception as ex:
            v[n] = f"unavailable ({type(ex).__name__})"
    return v


def machine():
    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    la = os.getloadavg() if hasattr(os, "getloadavg") else None
    return dict(cpu=model, logical_cpus=os.cpu_count(), system=platform.platform(), loadavg_at_start=la)


def fmt(x, nd=3):
    return "—" if x is None else f"{x:.{nd}f}"


def markdown(rep):
    L = []
    ds = rep["dataset"]
    L.append(f"## {ds['name']} ({ds['width']}x{ds['height']} {ds['dtype']}, {ds['n_nodata']} nodata; "
             f"{rep['mode']} run {rep['date']}, imagecodecs {rep['versions']['imagecodecs']})")
    L.append("")
    L.append(f"Fill: {rep['method']['fill']}. bits/sample over all {ds['n_samples']} samples; "
             f"errors over {ds['n_valid']} valid samples, in metres. Decode MS/s = million samples/s, "
             f"one thread, median of {rep['method']['timing_runs']} decode calls.")
    L.append("")
    L.append("### Lossless")
    L.append("")
    L.append("| codec | bits/sample | verified | decode MS/s | encode s |")
    L.append("|---|---|---|---|---|")
    for r in sorted(rep["lossless"], key=lambda r: r.get("bits_per_sample", 1e9)):
        if "error" in r:
            L.append(f"| {r['codec']} | failed: {r['error']} | | | |")
        else:
            L.append(f"| {r['codec']} | {r['bits_per_sample']:.3f} | {'yes' if r['lossless_verified'] else 'NO'} "
                     f"| {r['decode_msps']:.1f} | {r['encode_s']:.2f} |")
    L.append("")
    tg = rep["method"]["rms_targets_m"]
    L.append("### Lossy at RMS targets")
    L.append("")
    L.append("bisect = lossiest measured setting with RMS <= target (its own bits, RMS, max error and decode "
             "speed); interp = bits interpolated in log(RMS) between the nearest measured points either side.")
    L.append("")
    hdr = "| codec |"
    sep = "|---|"
    for t in tg:
        hdr += f" RMS {t:g} m: setting | bits (bisect) | RMS | max | bits (interp) | decode MS/s |"
        sep += "---|---|---|---|---|---|"
    L.append(hdr)
    L.append(sep)
    for name, r in rep["lossy"].items():
        if "error" in r:
            L.append(f"| {name} | failed: {r['error']} |")
            continue
        row = f"| {name} |"
        for t in tg:
            e = r["targets"][str(t)]
            bb, ip = e["bisection"], e["interpolated"]
            if bb is None:
                row += " — | — | — | — |"
            else:
                row += (f" {r['param_name']}={bb['param']:g} | {bb['bits_per_sample']:.3f} | {bb['rms_m']:.3f} "
                        f"| {bb['max_err_m']:.3g} |")
            row += f" {fmt(ip['bits_per_sample'] if ip else None)} |"
            row += f" {fmt(bb['decode_msps'], 1) if bb else '—'} |"
        L.append(row)
    L.append("")
    it = rep["method"].get("interp_only_targets_m") or []
    if it:
        L.append("### Interpolated only (log-RMS between measured points), bits/sample")
        L.append("")
        L.append("| codec | " + " | ".join(f"RMS {t:g} m" for t in sorted(set(it) | set(tg))) + " |")
        L.append("|---|" + "---|" * len(set(it) | set(tg)))
        for name, r in rep["lossy"].items():
            if "error" in r:
                continue
            vals = []
            for t in sorted(set(it) | set(tg)):
                ip = r["interp_only"].get(str(t)) if str(t) in r["interp_only"] else r["targets"][str(t)]["interpolated"]
                vals.append(fmt(ip["bits_per_sample"] if ip else None))
            L.append(f"| {name} | " + " | ".join(vals) + " |")
        L.append("")
    L.append(f"### Guaranteed max error <= {rep['method']['max_error_bound_m']:g} m")
    L.append("")
    L.append("held: yes = measured max <= bound; f32 = exceeds only by float32 rounding of metre values.")
    L.append("")
    L.append("| codec | setting | bits/sample | measured max | RMS | held | decode MS/s |")
    L.append("|---|---|---|---|---|---|---|")
    for r in rep["max_error"]:
        if "error" in r:
            L.append(f"| {r['codec']} | {r['setting']} | failed: {r['error']} | | | | |")
        else:
            held = 'yes' if r['bound_held'] else ('f32' if r['bound_held_within_f32_rounding'] else 'NO')
            L.append(f"| {r['codec']} | {r['setting']} | {r['bits_per_sample']:.3f} | {r['max_err_m']:.6g} "
                     f"| {r['rms_m']:.3f} | {held} | {r['decode_msps']:.1f} |")
    L.append("")
    return "\n".join(L)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sidecar", help="grid sidecar JSON (raw file named by its 'file' field, same folder)")
    ap.add_argument("--json", help="write the full results here")
    ap.add_argument("--quick", action="store_true", help="sparser sweeps, fewer bisection steps, 5 timing runs")
    ap.add_argument("--targets", default="1,9", help="RMS targets in metres for bisection (default 1,9)")
    ap.add_argument("--interp-targets", default=None,
                    help="extra RMS targets, interpolation only (default 0.5,2,5,20; none with --quick)")
    ap.add_argument("--max-error", type=float, default=1.0, help="guaranteed max-error bound in metres (default 1)")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: lossless,lossy,maxerr")
    args = ap.parse_args()

    t_start = time.perf_counter()
    targets = [float(x) for x in args.targets.split(",") if x]
    if args.interp_targets is None:
        interp_targets = [] if args.quick else [0.5, 2.0, 5.0, 20.0]
    else:
        interp_targets = [float(x) for x in args.interp_targets.split(",") if x]
    interp_targets = [t for t in interp_targets if t not in targets]
    iters = 4 if args.quick else 8
    skip = set(s for s in args.skip.split(",") if s)

    meta, raw_path, raw, valid = load_grid(args.sidecar)
    filled, fill_iters = fill_nodata(raw, valid)
    n_nodata = int((~valid).sum())
    fill_desc = ("none needed (no nodata)" if n_nodata == 0 else
                 f"{n_nodata} nodata samples filled with the mean of their valid 4-neighbours, iterated inwards "
                 f"({fill_iters} passes){', rounded to integer' if raw.dtype.kind == 'i' else ''}")
    ctx = Ctx(meta, raw, valid, filled, args.quick)
    log(f"{meta.get('name')}: {raw.shape[1]}x{raw.shape[0]} {meta['dtype']}, {n_nodata} nodata; fill: {fill_desc}")

    rep = dict(
        dataset=dict(name=meta.get("name"), sidecar=os.path.abspath(args.sidecar), raw_file=raw_path,
                     width=int(meta["width"]), height=int(meta["height"]), dtype=meta["dtype"],
                     nodata=meta.get("nodata"), n_samples=int(raw.size), n_valid=int(valid.sum()),
                     n_nodata=n_nodata, vertical_scale=ctx.scale, vertical_offset=ctx.offset,
                     sha256=meta.get("sha256")),
        date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        mode="quick" if args.quick else "full",
        versions=versions(),
        machine=machine(),
        method=dict(
            fill=fill_desc,
            bits="bits/sample = 8 * compressed bytes / (width*height), all samples incl. nodata",
            errors="metres (raw*vertical_scale+vertical_offset), over valid samples only; float-codec output "
                   "is compared as decoded (not rounded)",
            int_inputs="JPEG 2000 and HTJ2K get signed int16 directly; JPEG-LS and JPEG-XL get uint16 = raw - min; "
                       "SPERR, SZ3, ZFP, LERC-lossy get float32 metres; lossless LERC/pcodec/zstd get int16",
            rms_targets_m=targets,
            interp_only_targets_m=interp_targets,
            target_method=("parameter sweep, then bisection between the bracketing sweep points "
                           f"({iters} steps max) to the lossiest setting whose measured RMS <= target "
                           "(reported with its own measured bits/RMS/max/decode speed); also bits interpolated "
                           "linearly in log(RMS) between the nearest measured points on either side of the target"),
            max_error_bound_m=args.max_error,
            timing_runs=ctx.timing_runs,
            timing=("one warm-up call, then median of N timed calls of the decode function alone "
                    "(bytes -> numpy array), gc disabled; numthreads=1 passed where the codec has it, "
                    "OMP_NUM_THREADS=1"),
        ),
    )
    if "lossless" not in skip:
        log("lossless")
        rep["lossless"] = run_lossless(ctx)
    else:
        rep["lossless"] = []
    if "lossy" not in skip:
        log("lossy")
        rep["lossy"] = run_lossy(ctx, targets, interp_targets, iters)
    else:
        rep["lossy"] = {}
        rep["method"]["rms_targets_m"] = []
        rep["method"]["interp_only_targets_m"] = []
    if "maxerr" not in skip:
        log("guaranteed max error")
        rep["max_error"] = run_maxerr(ctx, args.max_error)
    else:
        rep["max_error"] = []
    rep["wall_time_s"] = time.perf_counter() - t_start

    print(markdown(rep))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rep, fh, indent=1)
            fh.write("\n")
        log(f"wrote {args.json}")
    log(f"total {rep['wall_time_s']:.0f} s")


if __name__ == "__main__":
    main()
