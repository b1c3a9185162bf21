#!/usr/bin/env bash
# Serverless hosting against `quincunx serve`, side by side in one run: the same flights
# (`quincunx fly --path jump --link 4000,100`, defaults otherwise) read repository files
# from plain nginx with range requests, from a private bucket of an S3-protocol server
# (s3s-fs, `quincunx-s3-server`) with signed requests through `object_store`, and blobs
# from `quincunx serve`, alternating, RUNS times each. korea (korea_srtm3_4097, rms 9 m; and lossless, whose 14,966 blobs
# make a file with tiles) and the ETOPO5 planet (rms 9 m) with the 5400x2700 Blue Marble
# colour (rms 4). Prints one JSON object per flight (the
# `quincunx fly --json` summary plus "source", "run" and the repositories' open figures).
#   benches/hosting/hosting.sh [shared-data-dir] > benches/hosting/hosting.jsonl
# REPOS="korea earth" (default: all three) and SOURCES="serve s3" (default: all three)
# fly a subset.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
runs="${RUNS:-5}"
repos=" ${REPOS:-korea earth korea_lossless} "
sources=" ${SOURCES:-serve ranges s3} "
for f in korea_srtm3_4097.json etopo5_global.json bmng_global_5400x2700.jpg; do
    if [ ! -f "$data/$f" ]; then
        echo "SKIP hosting bench: $data/$f absent" >&2
        exit 0
    fi
done
nginx=/usr/sbin/nginx
command -v nginx >/dev/null && nginx="$(command -v nginx)"
if [ ! -x "$nginx" ]; then
    echo "SKIP hosting bench: nginx not installed" >&2
    exit 0
fi
cargo build --release -q -p quincunx-repo-tools --features object-store
cargo build --release -q -p quincunx-e2e --bin quincunx-s3-server
bin="${CARGO_TARGET_DIR:-target}/release"
work="$(realpath -m "${WORK:-${CARGO_TARGET_DIR:-target}/hosting-bench}")"
mkdir -p "$work/www" "$work/nginx/tmp"
build() { # name, input, flags...
    local name="$1" input="$2"; shift 2
    if ! "$bin/quincunx" info "$work/$name" >/dev/null 2>&1; then
        "$bin/quincunx" build "$input" -o "$work/$name" "$@" --overwrite >&2
    fi
    cp "$work/$name/repository.pack" "$work/www/$name.pack"
}
build korea "$data/korea_srtm3_4097.json" --rms-m 9
build korea_lossless "$data/korea_srtm3_4097.json" --lossless
build earth "$data/etopo5_global.json" --planet --rms-m 9
build bmng "$data/bmng_global_5400x2700.jpg" --planet --colour --rms-m 4
user=""
[ "$(id -u)" = 0 ] && user="user root;"
cat > "$work/nginx/nginx.conf" <<CONF
daemon off; master_process on; worker_processes 1; $user
pid $work/nginx/nginx.pid; error_log $work/nginx/error.log warn;
events { worker_connections 256; }
http {
  client_body_temp_path $work/nginx/tmp/body; proxy_temp_path $work/nginx/tmp/proxy;
  fastcgi_temp_path $work/nginx/tmp/fastcgi; uwsgi_temp_path $work/nginx/tmp/uwsgi;
  scgi_temp_path $work/nginx/tmp/scgi; access_log off;
  server { listen 127.0.0.1:18291; root $work/www; }
}
CONF
"$nginx" -p "$work/nginx" -c "$work/nginx/nginx.conf" -e "$work/nginx/error.log" &
nginx_pid=$!
"$bin/quincunx" serve --addr 127.0.0.1:18292 --repo "korea=$work/korea" \
    --repo "korea_lossless=$work/korea_lossless" \
    --repo "earth=$work/earth" --repo "bmng=$work/bmng" --log warn >&2 &
server_pid=$!
# The bucket: signed requests only (SigV4 with this key pair), the files uploaded by PUT.
rm -rf "$work/s3"
"$bin/quincunx-s3-server" "$work/s3" 127.0.0.1:18293 quincunx bench-access-key \
    bench-secret-key-of-forty-characters-000 \
    $(for f in korea korea_lossless earth bmng; do echo "$f.pack=$work/www/$f.pack"; done) \
    > "$work/s3.log" &
s3_pid=$!
export AWS_ACCESS_KEY_ID=bench-access-key AWS_SECRET_ACCESS_KEY=bench-secret-key-of-forty-characters-000
export AWS_ENDPOINT_URL=http://127.0.0.1:18293 AWS_ALLOW_HTTP=true AWS_REGION=us-east-1
trap 'kill $server_pid $s3_pid 2>/dev/null; "$nginx" -p "$work/nginx" -c "$work/nginx/nginx.conf" -s stop 2>/dev/null; wait 2>/dev/null' EXIT
for port in 18291 18292; do
    for _ in $(seq 100); do
        (exec 3<>/dev/tcp/127.0.0.1/$port) 2>/dev/null && break
        sleep 0.1
    done
done
for _ in $(seq 600); do
    grep -q ready "$work/s3.log" && break
    sleep 0.1
done
fly() { # source, run, url, repo, extra flags...
    local source="$1" run="$2" url="$3" repo="$4"; shift 4
    [[ "$sources" == *" $source "* && "$repos" == *" ${repo%.pack} "* ]] || return 0
    "$bin/quincunx" fly --url "$url" --repo "$repo" --path jump --link 4000,100 --json "$@" \
        | python3 -c "import json,sys; d=json.load(sys.stdin); d['source']='$source'; d['run']=$run; print(json.dumps(d))"
}
for run in $(seq "$runs"); do
    fly serve "$run" http://127.0.0.1:18292 korea
    fly ranges "$run" http://127.0.0.1:18291 korea.pack
    fly s3 "$run" s3://quincunx korea.pack
    fly serve "$run" http://127.0.0.1:18292 earth --color bmng
    fly ranges "$run" http://127.0.0.1:18291 earth.pack --color bmng.pack
    fly s3 "$run" s3://quincunx earth.pack --color bmng.pack
    fly serve "$run" http://127.0.0.1:18292 korea_lossless
    fly ranges "$run" http://127.0.0.1:18291 korea_lossless.pack
    fly s3 "$run" s3://quincunx korea_lossless.pack
done
