#!/usr/bin/env bash
# What the tightest per-diamond bound would give: the geometric metric with each diamond's
# *measured* departure from the full-resolution decode (made monotone) in place of its
# side-information class, against the class bounds and the sampling metric, side by side.
#
#   [COLOUR_REPO=<colour repository dir>] benches/trade/oracle/run.sh <repository dir> \
#       [trade flags...]
#
# Builds a patched copy of this checkout (oracle.patch: a dump in
# repo-tools/tests/error_bound.rs and a QUINCUNX_ORACLE override in the client's
# refinement, neither part of the product) in a temporary worktree, measures every
# diamond's departure with the bound test's decoder, serves the repository and runs
# `quincunx trade` three ways. Prints one JSON object per way (`oracle.jsonl` holds the runs
# `docs/trade.md` reports).
set -euo pipefail
repo="$(realpath "$1")"; shift
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
work="$(mktemp -d)"
trap 'git -C "$root" worktree remove --force "$work/src" >/dev/null 2>&1 || true; kill "${server:-0}" 2>/dev/null || true' EXIT
git -C "$root" worktree add --detach "$work/src" HEAD >/dev/null
git -C "$work/src" apply "$root/benches/trade/oracle/oracle.patch"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$work/target}"
(cd "$work/src" && cargo build --release --bin quincunx -q \
    && QUINCUNX_BOUND_REPOS="$repo" QUINCUNX_BOUND_DUMP="$work/dump.txt" \
        cargo test --release -q -p quincunx-repo-tools --test error_bound \
        repositories_named_in_the_environment >/dev/null 2>&1 || true)
[[ -s "$work/dump.txt" ]] || { echo "no departures measured" >&2; exit 1; }
python3 "$root/benches/trade/oracle/monotone.py" "$work/dump.txt" >"$work/oracle.txt"
bin="$CARGO_TARGET_DIR/release/quincunx"
port=18093
"$bin" serve --addr "127.0.0.1:$port" --repo "r=$repo" --max-connections-per-ip 0 \
    ${COLOUR_REPO:+--repo "c=$(realpath "$COLOUR_REPO")"} >"$work/serve.log" 2>&1 &
server=$!
sleep 2
url="http://127.0.0.1:$port"
colour=()
if [[ -n "${COLOUR_REPO:-}" ]]; then
    colour=(--colour c)
fi
"$bin" trade --url "$url" --repo r "${colour[@]}" --metrics sampling --label sampling --json "$@"
"$bin" trade --url "$url" --repo r "${colour[@]}" --metrics geometric --label "class bounds" --json "$@"
QUINCUNX_ORACLE="$work/oracle.txt" \
    "$bin" trade --url "$url" --repo r "${colour[@]}" --metrics geometric --label "measured bounds" --json "$@"
