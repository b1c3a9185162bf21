#!/usr/bin/env python3
"""Decode speed of quincunx against OpenJPEG at the same RMS, measured in one run.

Usage (from the repository root; needs `pip install imagecodecs numpy`):
    python3 benches/peers/decode_side_by_side.py ../shared/data/korea_srtm3_4097.json

For each RMS target (1 m and 9 m) it encodes the grid with JPEG 2000 9/7 (OpenJPEG, one
thread) at the PSNR setting that `measure_peers.py` found for that target, times the
decode (median of 7), then runs `rd --rms-m <target> --decode-runs 7` (quincunx: entropy
decoding + synthesis of the whole grid, one thread, median of 7). Both decode into one
preallocated output reused by every run (`out=` / `decode_integers_into`), so neither
median pays for faulting in a fresh output buffer. Run it several times: the two
alternate per target, so both see the same machine load. Prints one JSON object per
target.
"""
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import imagecodecs as ic
import numpy as np

# PSNR settings (imagecodecs `level`) whose decoded RMS is just under each target on
# korea_srtm3_4097 (results-korea_srtm3_4097.json, bisection).
J2K_PSNR = {1.0: 96.757812, 9.0: 77.726562}


def main() -> None:
    sidecar = Path(sys.argv[1])
    meta = json.loads(sidecar.read_text())
    raw = sidecar.with_name(meta.get("file", sidecar.stem + ".i16"))
    if not raw.exists():
        raw = sidecar.with_suffix(".i16")
    w, h = meta["width"], meta["height"]
    grid = np.fromfile(raw, dtype="<i2").reshape(h, w)
    nodata = meta.get("nodata")
    valid = grid != nodata if nodata is not None else np.ones_like(grid, dtype=bool)
    filled = grid.copy()
    if nodata is not None:
        filled[~valid] = int(grid[valid].mean())
    root = Path(__file__).resolve().parents[2]
    subprocess.run(
        ["cargo", "build", "--release", "-q", "-p", "quincunx-codec", "--example", "rd"],
        cwd=root,
        check=True,
    )
    rd = root / "target" / "release" / "examples" / "rd"
    for target, psnr in J2K_PSNR.items():
        enc = ic.jpeg2k_encode(filled, psnr, reversible=False, numthreads=1)
        times = []
        # Into one preallocated output, as `rd` decodes into one reused buffer.
        dec = np.empty_like(filled)
        for _ in range(7):
            t = time.perf_counter()
            ic.jpeg2k_decode(enc, numthreads=1, out=dec)
            times.append(time.perf_counter() - t)
        err = (dec.astype(np.float64) - grid)[valid]
        j2k = {
            "bits_per_sample": 8 * len(enc) / grid.size,
            "rms_m": float(np.sqrt(np.mean(err * err))),
            "decode_msamples_per_s": grid.size / statistics.median(times) / 1e6,
        }
        out = subprocess.run(
            [str(rd), str(sidecar), "--rms-m", str(target), "--decode-runs", "7", "--json"],
            check=True,
            capture_output=True,
            text=True,
        )
        ours = json.loads(out.stdout)
        print(
            json.dumps(
                {
                    "target_rms_m": target,
                    "openjpeg": j2k,
                    "quincunx": {
                        k: ours[k]
                        for k in ("bits_per_sample", "rms_m", "decode_msamples_per_s")
                    },
                    "ratio": ours["decode_msamples_per_s"] / j2k["decode_msamples_per_s"],
                }
            )
        )


if __name__ == "__main__":
    main()
