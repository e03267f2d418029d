#!/usr/bin/env bash
# A profile-guided build of the volgrad binary (PGO): built once with instrumentation, run on the
# repository's scenes (renders, the joint and DRT gradients, an optimisation with alpha and one
# without), then built again with the counts those runs recorded, so that the compiler lays out
# and inlines the hot loops by how they run. Same results, bit for bit; how much faster is in
# docs/speed.md. Takes about 2.5 times a plain release build.
#
#   scripts/build-pgo.sh                          # writes target/pgo/release/volgrad
#   scripts/build-pgo.sh --no-default-features    # the same without MPI (cargo's flags pass on)
#
# Needs the Rust toolchain's llvm-profdata (`rustup component add llvm-tools`, tried here if it
# is missing) and the system libraries of a plain build (scripts/setup.sh). RUSTFLAGS you set are
# kept; cargo's `build.rustflags` from a config file is not (RUSTFLAGS replaces it).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
pgo=$root/target/pgo
case $root in
  *[[:space:]]*)
    echo "error: cargo splits RUSTFLAGS at spaces; build from a path without them, not '$root'" >&2
    exit 1
    ;;
esac

profdata_tool() {
  local sysroot
  sysroot=$(rustc --print sysroot) || return 0
  find "$sysroot/lib/rustlib" -name llvm-profdata -type f -print -quit 2>/dev/null || true
}
profdata=$(profdata_tool)
if [ -z "$profdata" ]; then
  echo "llvm-profdata not found: adding the toolchain's llvm-tools" >&2
  rustup component add llvm-tools >&2 || true
  profdata=$(profdata_tool)
fi
if [ -z "$profdata" ]; then
  echo "error: PGO needs the toolchain's llvm-profdata: 'rustup component add llvm-tools' did not provide it" >&2
  exit 1
fi

echo "1/3 building with instrumentation" >&2
RUSTFLAGS="${RUSTFLAGS:-} -Cprofile-generate=$pgo/profiles" \
  cargo build --release --bin volgrad --target-dir "$pgo/instrumented" "$@"
# Cleared after the build: its build scripts and proc-macros are instrumented too, and what they
# wrote while compiling is not volgrad's profile.
rm -rf "$pgo/profiles"

echo "2/3 running the training workload" >&2
volgrad=$pgo/instrumented/release/volgrad
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
unset LLVM_PROFILE_FILE # would send the counts elsewhere
run() { "$volgrad" "$@" -q --force; }
run render scenes/cloud.toml --spp 16 -o "$scratch/cloud.exr"
run render scenes/smoke.toml --spp 16 -o "$scratch/smoke.exr"
run render scenes/fire.toml --spp 8 -o "$scratch/fire.exr"
run grad scenes/cloud.toml --estimator joint --loss mean --spp 4 -o "$scratch/joint.vdb"
run grad scenes/smoke.toml --estimator drt --loss mean --spp 4 -o "$scratch/drt.vdb"
run optimize scenes/inverse/quick.toml --iterations 20 --out "$scratch/quick"
run optimize scenes/capture/plume.toml --iterations 4 --out "$scratch/plume"

echo "3/3 building with the profile" >&2
"$profdata" merge -o "$pgo/volgrad.profdata" "$pgo/profiles"
RUSTFLAGS="${RUSTFLAGS:-} -Cprofile-use=$pgo/volgrad.profdata -Cllvm-args=-pgo-warn-missing-function=false" \
  cargo build --release --bin volgrad --target-dir "$pgo" "$@"
echo "built $pgo/release/volgrad" >&2
