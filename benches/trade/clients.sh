#!/usr/bin/env bash
# Many clients against one server: `quincunx loadtest --mode fly` sweeps the client count
# (each client a real session with its own emulated 4 Mbit/s, 100 ms link, flying the
# seeded `jump` flight over korea at RMS 9 m) against `quincunx serve` on this machine,
# and reports per count the time to full quality, requests/s and the CPU of the server,
# of the load generator and of the whole machine: which of them is the limit.
# Appends one JSON line (the sweep, plus `utc`, `git_rev`, `loadavg_before`, `flags`) to
# benches/trade/clients.jsonl and draws docs/images/trade/clients_*.png.
#   benches/trade/clients.sh
# Environment: REPO (default /work/data/korea9, built from SOURCE if absent), SOURCE
# (default ../shared/data/korea_srtm3_4097.json), SWEEP (default 1,4,16,64,256), PORT
# (18181), PLOT_DIR (docs/images/trade), MIN_AVAILABLE_MB (2048: the run is stopped if
# free memory falls below it; a 1 px korea client holds 60-95 MB).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
repo="${REPO:-/work/data/korea9}"
source_grid="${SOURCE:-../shared/data/korea_srtm3_4097.json}"
sweep="${SWEEP:-1,4,16,64,256}"
port="${PORT:-18181}"
min_mb="${MIN_AVAILABLE_MB:-2048}"
plot_dir="${PLOT_DIR:-docs/images/trade}"
cargo build --release -q -p quincunx-repo-tools
bin="${CARGO_TARGET_DIR:-target}/release/quincunx"
while [ -e "$repo.building" ]; do
    echo "waiting for $repo.building to go" >&2
    sleep 10
done
if ! "$bin" info "$repo" >/dev/null 2>&1; then
    if [ ! -f "$source_grid" ]; then
        echo "SKIP clients bench: neither $repo nor $source_grid" >&2
        exit 0
    fi
    "$bin" build "$source_grid" --output "$repo" --rms-m 9 >&2
fi
# Every client connects from 127.0.0.1: no per-address connection limit.
"$bin" serve --addr "127.0.0.1:$port" --repo "korea=$repo" --max-connections-per-ip 0 \
    --log warn >&2 &
server_pid=$!
load_pid=""
trap 'kill $server_pid ${load_pid} 2>/dev/null; wait 2>/dev/null' EXIT
for _ in $(seq 100); do
    (exec 3<>/dev/tcp/127.0.0.1/"$port") 2>/dev/null && break
    sleep 0.1
done
loadavg_before="$(cut -d' ' -f1-3 /proc/loadavg)"
out="$(mktemp)"
# Checks: every 30th frame and at most 10 % of each flight's time (a korea cut check
# takes 0.3-0.5 s of CPU, which the clients and the server share with the checks).
flags=(--mode fly --repo korea --path jump --link 4000,100 --sweep "$sweep"
    --check-every 30 --check-max-share 0.1)
"$bin" loadtest --url "http://127.0.0.1:$port" "${flags[@]}" --server-pid "$server_pid" \
    --json --plot "$plot_dir" >"$out" &
load_pid=$!
while kill -0 "$load_pid" 2>/dev/null; do
    available=$(awk '/MemAvailable/ {print int($2 / 1024)}' /proc/meminfo)
    if [ "$available" -lt "$min_mb" ]; then
        echo "stopping the load test: $available MB available (< $min_mb)" >&2
        kill "$load_pid"
    fi
    sleep 1
done
status=0
wait "$load_pid" || status=$?
if [ -s "$out" ]; then
    python3 - "$out" "$(git rev-parse --short HEAD)" "$loadavg_before" "${flags[*]}" \
        >>benches/trade/clients.jsonl <<'PY'
import datetime, json, sys
report = json.load(open(sys.argv[1]))
line = {
    "utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    "git_rev": sys.argv[2],
    "loadavg_before": sys.argv[3],
    "flags": sys.argv[4],
    **report,
}
print(json.dumps(line))
PY
fi
rm -f "$out"
exit "$status"
