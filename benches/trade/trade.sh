#!/usr/bin/env bash
# The trade study of docs/trade.md: `quincunx trade` (its defaults: 1920x1080, tolerances
# 0.5-8 px, a 4 Mbit/s and 100 ms link, 3 runs per tolerance) on korea RMS 9 m and max
# error 2 m, the ETOPO5 planet with Blue Marble colour (and its numerical extremes) and
# the bundled repositories, against one `quincunx serve` on this machine.
# Appends one JSON line per study (the report plus `utc` and `git_rev`) to
# benches/trade/trade.jsonl and draws docs/images/trade/trade-*.png (the shared data) and
# docs/images/trade/bundled/trade-*.png (the bundled repositories).
#   benches/trade/trade.sh [LABEL...]      (default: every study)
# Environment: DATA (default ../shared/data), REPOS (where the repositories are built
# when absent, default /work/data), PORT (18400).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${DATA:-../shared/data}"
repos="${REPOS:-/work/data}"
port="${PORT:-18400}"
cargo build --release -q -p quincunx-repo-tools
bin="${CARGO_TARGET_DIR:-target}/release/quincunx"
mkdir -p "$repos"

# name source build-flags...
need() {
    local name=$1 source=$2
    shift 2
    if ! "$bin" info "$repos/$name" >/dev/null 2>&1; then
        if [ ! -f "$source" ]; then
            echo "SKIP trade bench: neither $repos/$name nor $source" >&2
            exit 0
        fi
        rm -rf "$repos/$name"
        "$bin" build "$source" --output "$repos/$name" "$@" >&2
    fi
}
need korea9 "$data/korea_srtm3_4097.json" --rms-m 9
need korea2 "$data/korea_srtm3_4097.json" --max-error-m 2
need etopo9 "$data/etopo5_global.json" --planet --rms-m 9
need bmng8 "$data/bmng_global_5400x2700.jpg" --colour --planet --rms-m 8
# Four texels per elevation grid edge instead of two (docs/trade.md, "Bytes on the planet").
need bmng8d129 "$data/bmng_global_5400x2700.jpg" --colour --planet --rms-m 8 --diamond-size 129
# The bundled repositories, as `quincunx demo` builds them.
need korea data/korea_srtm3_1025.json --rms-m 2
need earth data/etopo20_global.json --planet --max-error-m 2
need earth_colour data/bmng_global_1080x540.jpg --colour --planet --rms-m 4

"$bin" serve --addr "127.0.0.1:$port" --log warn \
    --repo "korea9=$repos/korea9" --repo "korea2=$repos/korea2" \
    --repo "etopo9=$repos/etopo9" --repo "bmng8=$repos/bmng8" \
    --repo "bmng8d129=$repos/bmng8d129" \
    --repo "korea=$repos/korea" --repo "earth=$repos/earth" \
    --repo "earth_colour=$repos/earth_colour" >&2 &
server_pid=$!
plots="$(mktemp -d)"
trap 'kill $server_pid 2>/dev/null; wait 2>/dev/null; rm -rf "$plots"' EXIT
for _ in $(seq 100); do
    (exec 3<>/dev/tcp/127.0.0.1/"$port") 2>/dev/null && break
    sleep 0.1
done
mkdir -p "$plots/shared" "$plots/bundled" "$plots/other"
# Each chart group starts from the latest recorded report of each of its studies, so a
# run of some studies redraws the charts with the others' lines as last measured.
python3 - "$plots" <<'PY'
import json, re, sys
groups = {
    "korea RMS 9 m": "shared",
    "ETOPO5 planet RMS 9 m + Blue Marble": "shared",
    "korea max 2 m": "shared",
    "bundled korea crop": "bundled",
    "bundled ETOPO20 planet + colour": "bundled",
}
latest = {}
for line in open("benches/trade/trade.jsonl"):
    report = json.loads(line)
    if report.get("label") in groups:
        latest[report["label"]] = report
for label, report in latest.items():
    name = re.sub(r"[^A-Za-z0-9+_-]", "_", label)
    with open(f"{sys.argv[1]}/{groups[label]}/{name}.json", "w") as f:
        json.dump(report, f)
PY
rev="$(git rev-parse --short HEAD)"
[ -z "$(git status --porcelain --untracked-files=no)" ] || rev="$rev+dirty"

# label plot-group trade-flags...
study() {
    local label=$1 group=$2
    shift 2
    if [ "${#wanted[@]}" -gt 0 ] && ! printf '%s\n' "${wanted[@]}" | grep -qxF "$label"; then
        return
    fi
    echo "trade: $label" >&2
    local out
    out="$(mktemp)"
    "$bin" trade --url "http://127.0.0.1:$port" --label "$label" --json \
        --plot "$plots/$group" "$@" >"$out"
    python3 - "$out" "$rev" >>benches/trade/trade.jsonl <<'PY'
import datetime, json, sys
report = json.load(open(sys.argv[1]))
line = {
    "utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%MZ"),
    "git_rev": sys.argv[2],
    **report,
}
print(json.dumps(line))
PY
    rm -f "$out"
}
wanted=("$@")
planet_path=benches/trade/planet-jumps.json
study "korea RMS 9 m" shared --repo korea9
study "ETOPO5 planet RMS 9 m + Blue Marble" shared --repo etopo9 --colour bmng8 \
    --path "$planet_path"
study "ETOPO5 + Blue Marble diamond size 129, 512 MB GPU budget" other --repo etopo9 \
    --colour bmng8d129 --path "$planet_path" --gpu-budget-mb 512 --tolerances 1
study "korea max 2 m" shared --repo korea2
study "ETOPO5 extremes" other --repo etopo9 --colour bmng8 --path extremes --runs 1
study "bundled korea crop" bundled --repo korea
study "bundled ETOPO20 planet + colour" bundled --repo earth --colour earth_colour \
    --path "$planet_path"
for group in shared bundled; do
    dest=docs/images/trade
    [ "$group" = bundled ] && dest=docs/images/trade/bundled
    if compgen -G "$plots/$group/*.png" >/dev/null; then
        cp "$plots/$group"/trade-*.png "$dest/"
    fi
done
