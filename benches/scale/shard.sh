#!/usr/bin/env bash
# Sharded build against one build: the single in-memory and out-of-core builds, then N
# shards (one after another, so each is timed alone on this machine; on a cluster they
# run at once) and the merge. `korea` is korea_srtm3_4097 at max error 2 m, `etopo5` the
# ETOPO5 planet at max error 10 m. Prints one JSON object; from the repository root:
#   benches/scale/shard.sh [shared-data-dir] [shards] [budget-mb] [korea|etopo5] \
#       [face-side] >> benches/scale/shard.jsonl
# Figures in docs/building.md ("Sharded builds") come from this script.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
data="${1:-../shared/data}"
shards="${2:-4}"
budget="${3:-40}"
what="${4:-korea}"
cargo build --release -q -p quincunx-repo-tools
q="${CARGO_TARGET_DIR:-target}/release/quincunx"
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
case "$what" in
    korea) name=korea_srtm3_4097 rate=(--max-error-m 2) ;;
    etopo5) name=etopo5_global rate=(--planet --max-error-m 10 ${5:+--face-side "$5"}) ;;
    *) echo "unknown source $what: give korea or etopo5" >&2; exit 2 ;;
esac
src="$data/$name.json"
in_memory="$("$q" build "$src" "${rate[@]}" -o "$out/in_memory" --json)"
single="$("$q" build "$src" "${rate[@]}" --memory-budget-mb "$budget" -o "$out/single" --json)"
parts=()
for ((k = 0; k < shards; k++)); do
    parts+=("$("$q" build "$src" "${rate[@]}" --memory-budget-mb "$budget" \
        --shard "$k/$shards" -o "$out/part$k" --json)")
done
merged="$("$q" merge "$out"/part* -o "$out/merged" --json)"
printf '{"source":"%s","rate":"%s","budget_mb":%s,"shards":%s,"in_memory":%s,"single":%s,"parts":[%s],"merge":%s}\n' \
    "$name" "${rate[*]}" "$budget" "$shards" "$in_memory" "$single" "$(IFS=,; echo "${parts[*]}")" "$merged"
