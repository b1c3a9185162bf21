#!/usr/bin/env bash
# Measures the quincunx server against nginx serving the same blobs (`quincunx export`)
# on this machine, with `quincunx loadtest` as the client for both, alternating runs.
# Prints one JSON object per run; the summary (medians and ratios) goes to stderr.
#   benches/serving/measure.sh [shared-data-dir] > benches/serving/results.jsonl
# QUICK=1 shortens every run (CI smoke); figures in docs/serving.md come from full runs.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
quick="${QUICK:-0}"
if [ "$quick" = 1 ]; then secs=3; long=5; reps=1; idle_n=2000; else secs=15; long=60; reps=3; idle_n=10000; fi
command -v nginx >/dev/null || [ -x /usr/sbin/nginx ] || { echo "SKIP serving bench: nginx not installed" >&2; exit 0; }
nginx_bin="$(command -v nginx || echo /usr/sbin/nginx)"
# QUINCUNX_PREBUILT=1: the release binaries are there already (.ci/run reuses its test build).
[[ -n "${QUINCUNX_PREBUILT:-}" ]] || cargo build --release -q -p quincunx-repo-tools -p quincunx-server
bin="${CARGO_TARGET_DIR:-target}/release"
work="${WORK:-${CARGO_TARGET_DIR:-target}/serving-bench}"
mkdir -p "$work"
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true

source_grid="$data/korea_srtm3_4097.json"
[ -f "$source_grid" ] || source_grid="data/korea_srtm3_1025.json"
repo="$work/korea"
if ! "$bin/quincunx" info "$repo" >/dev/null 2>&1; then
    "$bin/quincunx" build "$source_grid" -o "$repo" --max-error-m 2 --overwrite >&2
fi
rm -rf "$work/www" && "$bin/quincunx" export "$repo" "$work/www" --name korea >&2
: > "$work/www/__empty"

prefix="$(cd "$work" && pwd)/nginx"
rm -rf "$prefix" && mkdir -p "$prefix"
user=""; [ "$(id -u)" = 0 ] && user="user root;"
sed -e "s|@PREFIX@|$prefix|g" -e "s|@ROOT@|$(cd "$work/www" && pwd)|g" -e "s|@PORT@|18089|g" \
    -e "s|@USER@|$user|g" benches/serving/nginx-static.conf > "$prefix/nginx.conf"
"$nginx_bin" -p "$prefix" -c "$prefix/nginx.conf" -e "$prefix/error.log" &
nginx_pid=$!
"$bin/quincunx-server" --addr 127.0.0.1:18090 --repo "korea=$repo" --max-connections 19000 \
    --max-connections-per-ip 0 --idle-timeout-s 600 --log warn &
server_pid=$!
trap 'kill $server_pid $nginx_pid 2>/dev/null; wait 2>/dev/null' EXIT
for port in 18089 18090; do
    for _ in $(seq 100); do
        (exec 3<>/dev/tcp/127.0.0.1/$port) 2>/dev/null && break
        sleep 0.1
    done
done

# CPU seconds (user + system) of a process and its children threads/workers.
cpu_s() {
    local total=0 pid
    for pid in "$@" $(pgrep -P "$1" 2>/dev/null || true); do
        [ -r "/proc/$pid/stat" ] || continue
        total=$((total + $(awk '{print $14 + $15}' "/proc/$pid/stat")))
    done
    echo "scale=2; $total / $(getconf CLK_TCK)" | bc
}
rss_mb() {
    local total=0 pid
    for pid in "$@" $(pgrep -P "$1" 2>/dev/null || true); do
        [ -r "/proc/$pid/status" ] || continue
        total=$((total + $(awk '/VmRSS/ {print $2}' "/proc/$pid/status")))
    done
    echo "scale=1; $total / 1024" | bc
}
pid_of() { if [ "$1" = nginx ]; then echo $nginx_pid; else echo $server_pid; fi; }
port_of() { if [ "$1" = nginx ]; then echo 18089; else echo 18090; fi; }

run() {
    local target="$1" label="$2" rep="$3"
    shift 3
    local pid before after report
    pid="$(pid_of "$target")"
    before="$(cpu_s "$pid")"
    report="$("$bin/quincunx" loadtest --url "http://127.0.0.1:$(port_of "$target")" --repo korea \
        --json --quiet "$@")"
    after="$(cpu_s "$pid")"
    printf '{"target":"%s","run":"%s","rep":%s,"server_cpu_s":%s,"report":%s}\n' \
        "$target" "$label" "$rep" "$(echo "$after - $before" | bc)" "$report"
}

for rep in $(seq "$reps"); do
    for target in nginx quincunx; do
        run "$target" c256_d1 "$rep" --connections 256 --duration-s "$secs"
    done
done
for rep in $(seq "$reps"); do
    for target in nginx quincunx; do
        run "$target" c256_d16 "$rep" --connections 256 --pipeline-depth 16 --duration-s "$secs"
    done
done
for target in nginx quincunx; do
    run "$target" c1000_d1 1 --connections 1000 --duration-s "$long" --timeout-s 30
done
for target in quincunx nginx; do
    pid="$(pid_of "$target")"
    rss_before="$(rss_mb "$pid")"
    hold=$((secs + 10))
    "$bin/quincunx" loadtest --url "http://127.0.0.1:$(port_of "$target")" --repo korea --idle \
        --connections "$idle_n" --duration-s "$hold" --json --quiet > "$work/idle.json" &
    lt=$!
    sleep $((hold - 3))
    rss_held="$(rss_mb "$pid")"
    wait $lt
    printf '{"target":"%s","run":"idle_%s","rep":1,"rss_before_mb":%s,"rss_held_mb":%s,"report":%s}\n' \
        "$target" "$idle_n" "$rss_before" "$rss_held" "$(cat "$work/idle.json")"
done | tee "$work/idle.jsonl"
