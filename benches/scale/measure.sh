#!/usr/bin/env bash
# The scale benchmark (issue 22, item 4): for each face side, generates the seeded
# synthetic mosaic (ETOPO5 + fractal detail, one-degree raw int16 tiles between 56S and
# 60N: repo-tools/examples/scale_mosaic.rs) at the cube's resolution, builds it as a
# sparse planet at a 2 m error bound, and prints one JSON line: generation, tile bytes,
# the build summary (read/resample, encode and write seconds, peak RSS), the repository's
# bytes and the process's peak RSS as /usr/bin/time saw it. Usage, from the repository root:
#   benches/scale/measure.sh [shared-data-dir] [face side ...] >> benches/scale/results.jsonl
# Default face sides: 2048 4096. The issue's planet is face side 32768 (6.4 G cube
# samples, 5.6 G tile samples); a build of it in core would need about 300 GB.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
shift || true
sides=("$@")
[ ${#sides[@]} -gt 0 ] || sides=(2048 4096)
cargo build --release -q -p quincunx-repo-tools --bin quincunx --example scale_mosaic
target="${CARGO_TARGET_DIR:-target}/release"
work="$(mktemp -d "${SCALE_WORK:-/tmp}/quincunx-scale.XXXXXX")"
trap 'rm -rf "$work"' EXIT
for side in "${sides[@]}"; do
    per_degree=$(( (side + 89) / 90 ))  # at least the cube's samples per degree
    tiles="$work/tiles"
    generated="$("$target/examples/scale_mosaic" "$data/etopo5_global.json" "$tiles" "$per_degree")"
    tile_bytes="$(du -sb "$tiles" | cut -f1)"
    /usr/bin/time -f '%M' -o "$work/rss" "$target/quincunx" build "$tiles" --planet \
        --face-side "$side" --max-error-m 2 --json -o "$work/planet" > "$work/build.json"
    printf '{"face_side":%d,"per_degree":%d,"generate":%s,"tile_bytes":%d,"build":%s,"repository_bytes":%d,"time_peak_rss_kb":%d}\n' \
        "$side" "$per_degree" "$generated" "$tile_bytes" "$(cat "$work/build.json")" \
        "$(du -sb "$work/planet" | cut -f1)" "$(cat "$work/rss")"
    rm -rf "$tiles" "$work/planet"
done
