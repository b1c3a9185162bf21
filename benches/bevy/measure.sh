#!/usr/bin/env bash
# Frame time of the Bevy plugin against render/examples/embed.rs on the same view (the
# bundled korea crop, 960x540, embed's view, after full quality), side by side in one run:
# ROUNDS rounds of embed, the Bevy app with the terrain and the Bevy app without it, each
# 300 timed frames. Appends one JSON line per app and round (with utc and git_rev) to
# benches/bevy/frame.jsonl. Needs xvfb-run and a Vulkan adapter (lavapipe will do).
#   benches/bevy/measure.sh      Environment: ROUNDS (3), PORT (18402)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
rounds="${ROUNDS:-3}"
port="${PORT:-18402}"
cargo build --release -q -p quincunx-repo-tools
cargo build --release -q -p quincunx-render --example embed
cargo build --release -q --ignore-rust-version -p quincunx-bevy --example bench
release="${CARGO_TARGET_DIR:-target}/release"
work="$(mktemp -d)"
"${release}/quincunx" build data/korea_srtm3_1025.json -o "${work}/korea" --rms-m 2 >&2
"${release}/quincunx" serve --addr "127.0.0.1:${port}" --log warn --repo "korea=${work}/korea" >&2 &
server=$!
trap 'kill ${server} 2>/dev/null; wait 2>/dev/null; rm -rf "${work}"' EXIT
for _ in $(seq 100); do
    (exec 3<>/dev/tcp/127.0.0.1/"${port}") 2>/dev/null && break
    sleep 0.1
done
rev="$(git rev-parse --short HEAD)"
[ -z "$(git status --porcelain --untracked-files=no)" ] || rev="${rev}+dirty"
url="http://127.0.0.1:${port}"
xvfb=(xvfb-run -a -s "-screen 0 1280x1024x24")
for round in $(seq "${rounds}"); do
    for app in embed bevy bevy-empty; do
        case "${app}" in
            embed) line="$("${release}/examples/embed" "${url}" korea "${work}/embed.png" 300 | grep '^{')" ;;
            bevy) line="$("${xvfb[@]}" "${release}/examples/bench" "${url}" korea 300 2>/dev/null | grep '^{')" ;;
            bevy-empty) line="$("${xvfb[@]}" "${release}/examples/bench" "${url}" korea 300 --empty 2>/dev/null | grep '^{')" ;;
        esac
        python3 - "${line}" "${rev}" "${round}" >>benches/bevy/frame.jsonl <<'PY'
import datetime, json, sys
line = json.loads(sys.argv[1])
print(json.dumps({"utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%MZ"),
                  "git_rev": sys.argv[2], "round": int(sys.argv[3]), **line}))
PY
        tail -1 benches/bevy/frame.jsonl
    done
done
