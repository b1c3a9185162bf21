#!/usr/bin/env python3
"""Summarises benches/serving/results.jsonl: medians per (target, run) and the ratios the
issue's bar asks for. Usage: benches/serving/summarize.py [results.jsonl]"""
import json
import statistics
import sys
from collections import defaultdict

path = sys.argv[1] if len(sys.argv) > 1 else "benches/serving/results.jsonl"
runs = defaultdict(list)
idle = {}
for line in open(path):
    line = line.strip()
    if not line:
        continue
    r = json.loads(line)
    if r["run"].startswith("idle"):
        idle[r["target"]] = r
    else:
        runs[(r["target"], r["run"])].append(r)

def med(key, target, run):
    values = [x["report"][key] for x in runs[(target, run)]]
    return statistics.median(values) if values else float("nan")

def per_cpu(target, run):
    values = [x["report"]["requests"] / x["server_cpu_s"] for x in runs[(target, run)] if x["server_cpu_s"] > 0]
    return statistics.median(values) if values else float("nan")

print("| run | target | runs | req/s (median) | p50 ms | p99 ms | errors | requests per server CPU-second |")
print("|---|---|---|---|---|---|---|---|")
for (target, run) in sorted(runs, key=lambda k: (k[1], k[0])):
    n = len(runs[(target, run)])
    errors = sum(x["report"]["errors"] for x in runs[(target, run)])
    print(f"| {run} | {target} | {n} | {med('rps', target, run):,.0f} | {med('p50_ms', target, run):.2f} | "
          f"{med('p99_ms', target, run):.2f} | {errors} | {per_cpu(target, run):,.0f} |")
print()
q1, n1 = med("rps", "quincunx", "c256_d1"), med("rps", "nginx", "c256_d1")
q16 = med("rps", "quincunx", "c256_d16")
print(f"- 256 connections, no pipelining: quincunx / nginx = {q1 / n1:.2f}x (bar >= 1.0x)")
print(f"- depth 16 / no pipelining (quincunx) = {q16 / q1:.2f}x (bar >= 2x)")
for target, r in sorted(idle.items()):
    print(f"- {target}: {r['report'].get('idle_open')} idle connections held, RSS {r['rss_before_mb']} MB before, "
          f"{r['rss_held_mb']} MB while held")
