#!/usr/bin/env bash
# Colour layers streamed with their elevation (`quincunx fly --color`), side by side with
# the elevation alone in the same run: the planet (etopo5_global at rms 9 m with the
# 5400x2700 Blue Marble at rms 4 levels, 33x33 and 65x65 diamonds: the colour is two
# levels shallower, so it is refined procedurally below them) and the planar GSI pair
# (bundled). Jump flights, 1 px, 100 ms RTT, 4 Mbit/s and 300 kbit/s.
# Prints one JSON object per run (the `quincunx fly --json` summary).
#   benches/streaming/colour.sh [shared-data-dir] > benches/streaming/colour.jsonl
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
for f in etopo5_global.json bmng_global_5400x2700.jpg; do
    if [ ! -f "$data/$f" ]; then
        echo "SKIP colour streaming bench: $data/$f absent" >&2
        exit 0
    fi
done
cargo build --release -q -p quincunx-repo-tools
bin="${CARGO_TARGET_DIR:-target}/release"
work="${WORK:-${CARGO_TARGET_DIR:-target}/streaming-bench}"
mkdir -p "$work"
build() { # name, input, flags...
    local name="$1" input="$2"; shift 2
    if ! "$bin/quincunx" info "$work/$name" >/dev/null 2>&1; then
        "$bin/quincunx" build "$input" -o "$work/$name" "$@" --overwrite >&2
    fi
}
build earth_rms9 "$data/etopo5_global.json" --planet --rms-m 9
build bmng_rms4 "$data/bmng_global_5400x2700.jpg" --planet --colour --rms-m 4
build gsi data/fixture_gsi_dem_256.json --max-error-m 0.05
build gsi_colour data/fixture_gsi_color_256.jpg --colour --rms-m 4
"$bin/quincunx" serve --addr 127.0.0.1:18191 --repo "earth_rms9=$work/earth_rms9" \
    --repo "bmng_rms4=$work/bmng_rms4" --repo "gsi=$work/gsi" \
    --repo "gsi_colour=$work/gsi_colour" --log warn >&2 &
server_pid=$!
trap 'kill $server_pid 2>/dev/null; wait 2>/dev/null' EXIT
for _ in $(seq 100); do
    (exec 3<>/dev/tcp/127.0.0.1/18191) 2>/dev/null && break
    sleep 0.1
done
fly() { # repo, link, extra flags...
    local repo="$1" link="$2"; shift 2
    "$bin/quincunx" fly --url http://127.0.0.1:18191 --repo "$repo" --path jump \
        --link "$link" --check-every 10 --json --allow-unfinished "$@"
}
for link in 4000,100 300,100; do
    fly earth_rms9 "$link"
    fly earth_rms9 "$link" --color bmng_rms4
done
fly earth_rms9 4000,100 --color bmng_rms4 --procedural-noise 2
fly gsi 4000,100 --spacing-m 5
fly gsi 4000,100 --spacing-m 5 --color gsi_colour
