#!/usr/bin/env python3
"""Per-diamond bounds from measured departures (`QUINCUNX_BOUND_DUMP` lines
`level|id|quanta|child|child...`): each diamond's own measured departure from the
full-resolution decode, raised to its children's (monotone up the DAG, as the refiner
needs). Prints `id|quanta` lines, the format `QUINCUNX_ORACLE` reads."""
import sys

rows = {}
for line in open(sys.argv[1]):
    level, ident, quanta, *kids = line.rstrip("\n").split("|")
    rows[ident] = (int(level), float(quanta), [k for k in kids if k])
bound = {}
for ident, (level, quanta, kids) in sorted(rows.items(), key=lambda kv: -kv[1][0]):
    bound[ident] = max([quanta] + [bound.get(k, 0.0) for k in kids])
for ident, quanta in bound.items():
    print(f"{ident}|{quanta}")
