#!/usr/bin/env bash
# The 4 Mbit/s, 100 ms jump flights of measure.sh (QUICK=1) flown by two quincunx
# binaries, alternating, three rounds each against one server: OLD, a build from before
# the client core split (8bb4280), and NEW. Repositories from measure.sh's work dir.
#   OLD=<binary> [NEW=<binary>] [WORK=<dir>] benches/streaming/core-split.sh > core-split.jsonl
set -euo pipefail
work="${WORK:-target/streaming-bench}"
new="${NEW:-target/release/quincunx}"
old="${OLD:?a quincunx binary built before the split}"
"$new" serve --addr 127.0.0.1:18191 --repo "korea_rms9=$work/korea_rms9" --repo "earth_rms9=$work/earth_rms9" --log warn --max-connections-per-ip 0 >/dev/null 2>&1 &
pid=$!
trap 'kill $pid 2>/dev/null' EXIT
sleep 2
for round in 1 2 3; do
  for which in old new; do
    bin=$old; [ $which = new ] && bin=$new
    for repo in korea_rms9 earth_rms9; do
      "$bin" fly --url http://127.0.0.1:18191 --repo $repo --path jump --link 4000,100 --transport pipelined --tolerance-px 1 --package-factor 2 --check-every 10 --json --allow-unfinished \
        | python3 -c "import json,sys; d=json.load(sys.stdin); d['build']='$which'; d['round']=$round; print(json.dumps(d))"
    done
  done
done
