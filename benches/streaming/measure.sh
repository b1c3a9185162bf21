#!/usr/bin/env bash
# Headless streaming sessions (`quincunx fly`) over an emulated link against our server:
# the issue's streaming bars (time to full quality after a jump, fetch waste, refinement
# time per frame) on korea_srtm3_4097 at two rates (rms 9 m, the paper's mode, and a 2 m
# max-error build), for the three transports and two link rates; and on the planet
# (etopo5_global as an Earth repository at rms 9 m).
# Prints one JSON object per run (the `quincunx fly --json` summary plus `rate`).
#   benches/streaming/measure.sh [shared-data-dir] > benches/streaming/results.jsonl
# QUICK=1 runs only the 4 Mbit/s jump flights of the rms 9 m builds (CI smoke).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
quick="${QUICK:-0}"
source_grid="$data/korea_srtm3_4097.json"
if [ ! -f "$source_grid" ]; then
    echo "SKIP streaming bench: $source_grid absent" >&2
    exit 0
fi
# QUINCUNX_PREBUILT=1: the release binaries are there already (.ci/run reuses its test build).
[[ -n "${QUINCUNX_PREBUILT:-}" ]] || cargo build --release -q -p quincunx-repo-tools
bin="${CARGO_TARGET_DIR:-target}/release"
work="${WORK:-${CARGO_TARGET_DIR:-target}/streaming-bench}"
mkdir -p "$work"
build() { # name, rate flags...
    local name="$1"; shift
    if ! "$bin/quincunx" info "$work/$name" >/dev/null 2>&1; then
        "$bin/quincunx" build "$source_grid" -o "$work/$name" "$@" --overwrite >&2
    fi
}
build korea_rms9 --rms-m 9
[ "$quick" = 1 ] || build korea_max2 --max-error-m 2
planet=()
if [ -f "$data/etopo5_global.json" ]; then
    if ! "$bin/quincunx" info "$work/earth_rms9" >/dev/null 2>&1; then
        "$bin/quincunx" build "$data/etopo5_global.json" --planet -o "$work/earth_rms9" \
            --rms-m 9 --overwrite >&2
    fi
    planet=(--repo "earth_rms9=$work/earth_rms9")
else
    echo "SKIP streaming bench (planet): $data/etopo5_global.json absent" >&2
fi
"$bin/quincunx" serve --addr 127.0.0.1:18190 --repo "korea_rms9=$work/korea_rms9" \
    $([ "$quick" = 1 ] || echo --repo "korea_max2=$work/korea_max2") "${planet[@]}" \
    --log warn >&2 &
server_pid=$!
trap 'kill $server_pid 2>/dev/null; wait 2>/dev/null' EXIT
for _ in $(seq 100); do
    (exec 3<>/dev/tcp/127.0.0.1/18190) 2>/dev/null && break
    sleep 0.1
done
fly() { # repo, path, link, transport[, tolerance[, package factor]]
    "$bin/quincunx" fly --url http://127.0.0.1:18190 --repo "$1" --path "$2" --link "$3" \
        --transport "$4" --tolerance-px "${5:-1}" --package-factor "${6:-2}" \
        --check-every 10 --json --allow-unfinished \
        | python3 -c "import json,sys; d=json.load(sys.stdin); d['transport']='$4'; d['package_factor']=${6:-2}; print(json.dumps(d))"
}
if [ "$quick" = 1 ]; then
    fly korea_rms9 jump 4000,100 pipelined
    [ ${#planet[@]} = 0 ] || fly earth_rms9 jump 4000,100 pipelined
    exit 0
fi
if [ ${#planet[@]} != 0 ]; then
    for link in 4000,100 300,100; do
        fly earth_rms9 jump "$link" pipelined
    done
    for transport in plain h2; do
        fly earth_rms9 jump 4000,100 "$transport"
    done
    fly earth_rms9 jump 300,100 h2
    fly earth_rms9 low-flight 4000,100 pipelined
    fly earth_rms9 approach 4000,100 pipelined
    for link in 4000,100 300,100; do
        fly earth_rms9 jump "$link" pipelined 1 0
    done
fi
for repo in korea_rms9 korea_max2; do
    for link in 4000,100 300,100; do
        fly "$repo" jump "$link" pipelined
    done
    for transport in plain h2; do
        fly "$repo" jump 4000,100 "$transport"
    done
    # HTTP/2's compressed headers on the slow link, where answer heads dominate.
    fly "$repo" jump 300,100 h2
    # Side by side: bare blobs only (no packages), both links.
    for link in 4000,100 300,100; do
        fly "$repo" jump "$link" pipelined 1 0
    done
    fly "$repo" low-flight 4000,100 pipelined
    fly "$repo" approach 4000,100 pipelined
    # The speed/accuracy trade: coarser tolerances.
    for link in 4000,100 300,100; do
        for tolerance in 2 4; do
            fly "$repo" jump "$link" pipelined "$tolerance"
        done
    done
done
