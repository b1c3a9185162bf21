#!/usr/bin/env python3
"""Medians of benches/hosting/hosting.jsonl: per repository and source, the median over
runs of each flight's median and largest time to full quality after a jump, requests per
jump, bytes fetched, and fetched / needed bytes (needed: the blobs' bytes; the rest is
opening, directories, gaps and checksums). Ratios of range reads (nginx: "ranges"; a
private bucket with signed requests: "s3") to the server's.
   benches/hosting/summary.py benches/hosting/hosting.jsonl"""
import json
import statistics
import sys

rows = [json.loads(line) for line in open(sys.argv[1]) if line.strip()]
by = {}
for r in rows:
    by.setdefault((r["repo"], r["source"]), []).append(r)


def med(xs):
    return statistics.median(xs) if xs else float("nan")


out = {}
for (repo, source), rs in sorted(by.items()):
    jumps = len(rs[0]["jumps"])
    f = {
        "runs": len(rs),
        "ttfq_p50_s": med([r["time_to_full_quality_s_p50"] for r in rs]),
        "ttfq_max_s": med([r["time_to_full_quality_s_max"] for r in rs]),
        "requests_per_jump": med([r["requests"] / jumps for r in rs]),
        "bytes_fetched": med([r["bytes_fetched"] for r in rs]),
        "overhead_bytes": med([r.get("overhead_bytes", 0) for r in rs]),
        "fetched_over_needed": med(
            [r["bytes_fetched"] / (r["bytes_fetched"] - r.get("overhead_bytes", 0)) for r in rs]
        ),
        "link_bytes_down": med([r.get("link_bytes_down", 0) for r in rs]),
        "cracks": sum(r["cracks"] for r in rs),
        "fetch_errors": sum(r["fetch_errors"] for r in rs),
        "jumps_unfinished": sum(r["jumps_unfinished"] for r in rs),
    }
    out[(repo, source)] = f
    print(json.dumps({"repo": repo, "source": source, **f}))
for (repo, source), f in out.items():
    if source not in ("ranges", "s3"):
        continue
    base = repo[: -len(".pack")] if repo.endswith(".pack") else repo
    s = out.get((base, "serve"))
    if s:
        print(json.dumps({
            "repo": base,
            "source": source,
            "ranges_over_serve_ttfq_p50": f["ttfq_p50_s"] / s["ttfq_p50_s"],
            "ranges_over_serve_ttfq_max": f["ttfq_max_s"] / s["ttfq_max_s"],
            "ranges_over_serve_bytes": f["bytes_fetched"] / s["bytes_fetched"],
            "ranges_over_serve_requests": f["requests_per_jump"] / s["requests_per_jump"],
        }))
