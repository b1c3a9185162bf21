#!/bin/sh
# Builds the browser's WebAssembly module, web-demo/js/quincunx.wasm, from the
# quincunx-web crate (the Rust decoder and client core). The module is committed, so the
# server and the tests need no wasm toolchain; `--check` rebuilds it and fails if the
# build differs from the committed file (.ci/run does this).
#
# Needs rustup and the pinned toolchain below with its wasm32 target. No wasm-bindgen:
# the ABI is plain numbers and byte buffers (web/src/abi.rs, web-demo/js/wasm.mjs).
#
# The bytes depend only on the sources, Cargo.lock, [profile.wasm] and the toolchain: not
# on the checkout's path, the target directory, the cargo home or the caller's
# environment. The toolchain is pinned because every release changes the code generated
# and std's panic locations name its commit (/rustc/<hash>/...). To move to a new Rust,
# change `toolchain`, run this script and commit the module with the change.
set -eu

toolchain=1.95.0
target=wasm32-unknown-unknown

case "${1:-}" in
'' | --check) ;;
*)
  echo "usage: web-demo/build-wasm.sh [--check]" >&2
  exit 2
  ;;
esac

# A relative CARGO_TARGET_DIR means the caller's directory, not the repository root.
if [ -n "${CARGO_TARGET_DIR:-}" ]; then
  case "$CARGO_TARGET_DIR" in
  /*) ;;
  *) CARGO_TARGET_DIR=$(pwd -P)/$CARGO_TARGET_DIR ;;
  esac
  export CARGO_TARGET_DIR
fi
# The physical path: the one cargo hands rustc (getcwd), so the one to remap.
root=$(cd "$(dirname "$0")/.." && pwd -P)
cd "$root"

if ! command -v rustup >/dev/null 2>&1; then
  echo "web-demo/build-wasm.sh: rustup not found (https://rustup.rs)" >&2
  exit 1
fi
# Never download a toolchain behind the caller's back: say what is missing.
if ! RUSTUP_AUTO_INSTALL=0 rustup run "$toolchain" rustc --version >/dev/null 2>&1; then
  echo "web-demo/build-wasm.sh: Rust $toolchain (with its $target target) is not installed:" >&2
  echo "  rustup toolchain install $toolchain --profile minimal --target $target" >&2
  exit 1
fi
if ! RUSTUP_AUTO_INSTALL=0 rustup target list --installed --toolchain "$toolchain" |
  grep -qx "$target"; then
  echo "web-demo/build-wasm.sh: the $target target of Rust $toolchain is not installed:" >&2
  echo "  rustup target add --toolchain $toolchain $target" >&2
  exit 1
fi
cargo() {
  RUSTUP_AUTO_INSTALL=0 rustup run "$toolchain" cargo "$@"
}

# The target directory cargo would use (CARGO_TARGET_DIR, build.target-dir or ./target);
# the module gets its own subdirectory, since its flags differ from every other build's.
target_dir=$(cargo metadata --locked --no-deps --format-version 1 |
  sed -n 's/.*"target_directory":"\([^"]*\)".*/\1/p')
if [ -z "$target_dir" ]; then
  echo "web-demo/build-wasm.sh: cargo metadata names no target directory" >&2
  exit 1
fi
wasm_dir=$target_dir/wasm

# Absolute paths reach the module through panic locations (file!()): the registry's
# sources, the workspace (members are relative already; this catches anything else) and
# OUT_DIR. Each is remapped to a fixed name, in its given and its physical spelling; rustc
# applies the last matching remap, so the target directory (often inside the root) wins.
us=$(printf '\037')
flags=
remap() {
  flags="$flags${flags:+$us}--remap-path-prefix=$1=$2"
  if physical=$(cd "$1" 2>/dev/null && pwd -P) && [ "$physical" != "$1" ]; then
    flags="$flags$us--remap-path-prefix=$physical=$2"
  fi
}
remap "${CARGO_HOME:-${HOME:?}/.cargo}" /cargo
remap "$root" /quincunx
remap "$target_dir" /target

# The caller's environment must not change the bytes: CARGO_ENCODED_RUSTFLAGS outranks
# RUSTFLAGS and every configured rustflags; profile overrides (release too, which [profile.wasm]
# inherits), incremental builds and a substituted rustc are dropped.
for name in $(env | sed -n 's/^\(CARGO_PROFILE_[A-Za-z0-9_]*\)=.*/\1/p'); do
  unset "$name"
done
unset RUSTC RUSTFLAGS
CARGO_INCREMENTAL=0
CARGO_ENCODED_RUSTFLAGS=$flags
export CARGO_INCREMENTAL CARGO_ENCODED_RUSTFLAGS

cargo build --locked --quiet --profile wasm --target "$target" -p quincunx-web \
  --target-dir "$wasm_dir"
built=$wasm_dir/$target/wasm/quincunx_web.wasm
out=$root/web-demo/js/quincunx.wasm
if [ "${1:-}" = "--check" ]; then
  if cmp -s "$built" "$out"; then
    echo "web-demo/js/quincunx.wasm is up to date ($(wc -c <"$out") bytes, Rust $toolchain)"
  else
    echo "web-demo/js/quincunx.wasm differs from a build of the sources (Rust $toolchain):" \
      "run web-demo/build-wasm.sh and commit the module" >&2
    exit 1
  fi
else
  cp "$built" "$out"
  echo "wrote web-demo/js/quincunx.wasm ($(wc -c <"$out") bytes, Rust $toolchain)"
fi
