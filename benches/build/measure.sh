#!/usr/bin/env bash
# Measures `quincunx build` and `quincunx verify` on the shared datasets and prints one
# JSON object per run (build summary + verify report). Usage, from the repository root:
#   benches/build/measure.sh [shared-data-dir] > benches/build/results.jsonl
# Figures in docs/building.md come from this script.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
# QUINCUNX_PREBUILT=1: the release binaries are there already (.ci/run reuses its test build).
[[ -n "${QUINCUNX_PREBUILT:-}" ]] || cargo build --release -q -p quincunx-repo-tools
q="${CARGO_TARGET_DIR:-target}/release/quincunx"
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT

run() {
    local name="$1" source="$2"
    shift 2
    local built verified
    built="$("$q" build "$source" -o "$out/$name" --json "$@")"
    verified="$("$q" verify "$out/$name" --source "$source" --json)"
    printf '{"run":"%s","args":"%s","build":%s,"verify":%s}\n' "$name" "$*" "$built" "$verified"
    rm -rf "${out:?}/$name"
}

korea="$data/korea_srtm3_4097.json"
run korea_lossless "$korea" --lossless
run korea_max_error_1m "$korea" --max-error-m 1
run korea_rms_1m "$korea" --rms-m 1
run korea_rms_9m "$korea" --rms-m 9
run korea_out_of_core_32mb "$korea" --max-error-m 1 --memory-budget-mb 32
run korea_lossless_out_of_core_32mb "$korea" --lossless --memory-budget-mb 32
run korea_rms_9m_out_of_core_32mb "$korea" --rms-m 9 --memory-budget-mb 32
run bmng_colour_rms_4_out_of_core_128mb "$data/bmng_global_5400x2700.jpg" --colour --rms-m 4 --memory-budget-mb 128
run etopo5_planet_lossless "$data/etopo5_global.json" --planet --lossless
run etopo5_planet_rms_9m "$data/etopo5_global.json" --planet --rms-m 9
run bmng_planet_colour_max_8 "$data/bmng_global_5400x2700.jpg" --planet --colour --max-error-m 8
run gsi_colour_lossless "$data/fixture_gsi_color_256.jpg" --colour --lossless
run colorado_float_max_error_0.1m "$data/fixture_colorado_ned_10m.json" --max-error-m 0.1
