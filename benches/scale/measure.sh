#!/usr/bin/env bash
# The scale benchmark (issue 22, item 4): for each face side, generates the seeded
# synthetic mosaic (ETOPO5 + fractal detail, one-degree raw int16 tiles between 56S and
# 60N: repo-tools/examples/scale_mosaic.rs) at the cube's resolution, builds it as a
# sparse planet at a 2 m error bound within a memory budget (out of core when the
# in-memory estimate exceeds it), and prints one JSON line: generation, tile bytes, the
# build summary (encode and write seconds, each encoder phase's seconds and sampled peak
# RSS, scratch bytes), the repository's bytes and the process's peak RSS as /usr/bin/time
# saw it. Usage, from the repository root:
#   benches/scale/measure.sh [shared-data-dir] [face side ...] >> benches/scale/results.jsonl
# Default face sides: 2048 4096. The issue's planet is face side 32768 (6.4 G cube
# samples, 5.6 G tile samples, 11 GB of tiles). Environment: SCALE_BUDGET_MB (default
# 4096); SCALE_TILES, a directory whose <side>/tiles and <side>/generate.json are used
# instead of generating (the 32768 tiles take 8-17 minutes to write); SCALE_WORK, where
# the tiles, the scratch files and the repository go (default /tmp).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
shift || true
sides=("$@")
[ ${#sides[@]} -gt 0 ] || sides=(2048 4096)
# QUINCUNX_PREBUILT=1: the release binaries are there already (.ci/run reuses its test build).
[[ -n "${QUINCUNX_PREBUILT:-}" ]] || cargo build --release -q -p quincunx-repo-tools --bin quincunx --example scale_mosaic
target="${CARGO_TARGET_DIR:-target}/release"
work="$(mktemp -d "${SCALE_WORK:-/tmp}/quincunx-scale.XXXXXX")"
trap 'rm -rf "$work"' EXIT
budget="${SCALE_BUDGET_MB:-4096}"
for side in "${sides[@]}"; do
    per_degree=$(( (side + 89) / 90 ))  # at least the cube's samples per degree
    if [ -n "${SCALE_TILES:-}" ] && [ -f "$SCALE_TILES/$side/generate.json" ]; then
        tiles="$SCALE_TILES/$side/tiles"
        generated="$(cat "$SCALE_TILES/$side/generate.json")"
    else
        tiles="$work/tiles"
        generated="$("$target/examples/scale_mosaic" "$data/etopo5_global.json" "$tiles" "$per_degree")"
    fi
    tile_bytes="$(du -sb "$tiles" | cut -f1)"
    /usr/bin/time -f '%M' -o "$work/rss" "$target/quincunx" build "$tiles" --planet \
        --face-side "$side" --max-error-m 2 --memory-budget-mb "$budget" --json \
        -o "$work/planet" > "$work/build.json"
    printf '{"face_side":%d,"per_degree":%d,"budget_mb":%d,"generate":%s,"tile_bytes":%d,"build":%s,"repository_bytes":%d,"time_peak_rss_kb":%d}\n' \
        "$side" "$per_degree" "$budget" "$generated" "$tile_bytes" "$(cat "$work/build.json")" \
        "$(du -sb "$work/planet" | cut -f1)" "$(cat "$work/rss")"
    rm -rf "$work/tiles" "$work/planet"
done
