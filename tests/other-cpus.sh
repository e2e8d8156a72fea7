#!/usr/bin/env bash
# The library's unit tests and the fabrication, metrology and optics commands on other x86-64
# CPUs, emulated by qemu-user, with every output compared byte for byte against this machine's.
#
#   tests/other-cpus.sh [MODEL...]      (default: EPYC-v1 Haswell-v4 Nehalem-v2)
#
# EPYC-v1 is AMD Zen 1 (AVX2 and FMA, no AVX-512), Haswell-v4 an Intel core of the same vector
# width, Nehalem-v2 a CPU without AVX at all (SSE4.2). `qemu-x86_64 -cpu help` lists the others.
# Needs qemu-user (Debian: `apt-get install qemu-user`; QEMU 7.2 or newer emulates AVX2). The
# emulation is slow (about 50x): the unit tests take about a minute a model, the commands a few.
# Prints one line a model and output: "same" or "DIFFERS"; exits 1 when a unit test fails or a
# stage other than the decoder gives other bytes on a CPU with AVX2 and FMA (README,
# Conventions: what is byte-identical across machines). Not run by CI (no qemu there).
set -euo pipefail
cd "$(dirname "$0")/.."
command -v qemu-x86_64 >/dev/null || { echo "qemu-x86_64 not found: apt-get install qemu-user" >&2; exit 2; }
models=("$@")
[ ${#models[@]} -gt 0 ] || models=(EPYC-v1 Haswell-v4 Nehalem-v2)
cargo build --release --quiet
lib=$(cargo test --release --lib --no-run --message-format=json 2>/dev/null |
  sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1)
bin=$PWD/target/release/doefab
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# The commands, each writing under $1 (the same relative path on every CPU, since outputs
# record the paths they were given): the fabrication chain, a synthetic scan of the part, the
# comparison with the design, the pre-compensated next mask, the PSF by the automatic plan.
stages() {
  local run=("${@:2}") out=$1
  "${run[@]}" -q fab --recipe built-in:laser-writer-grayscale -o "$out/fab" 2>/dev/null
  "${run[@]}" -q simulate-scan built-in:paper --depth-scale 0.9 --blur 3um --rotate 0.2deg \
    --noise 5nm --missing 2% -o "$out/scan.x3p"
  "${run[@]}" -q compare "$out/scan.x3p" --design built-in:paper -o "$out/compare" 2>/dev/null
  "${run[@]}" -q precompensate --recipe built-in:laser-writer-grayscale \
    --model "$out/compare/compare.json" -o "$out/precompensate" 2>/dev/null
  "${run[@]}" -q psf -o "$out/psf"
}
digest() { (cd "$1" && find . -type f | LC_ALL=C sort | xargs sha256sum); }

# Whether a model has AVX2 and FMA, as the programs see it (the CPUID that qemu emulates).
cat >"$work/features.rs" <<'RS'
fn main() { print!("{}", is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")); }
RS
rustc -O -o "$work/features" "$work/features.rs"

in_dir() { mkdir -p "$1" && (cd "$1" && stages out "${@:2}"); }
in_dir "$work/native" "$bin"
status=0
for model in "${models[@]}"; do
  run=(qemu-x86_64 -cpu "$model")
  if "${run[@]}" "$lib" -q >"$work/$model-lib.log" 2>&1; then
    echo "$model: unit tests pass"
  else
    echo "$model: unit tests FAIL (log below)"; tail -30 "$work/$model-lib.log"; status=1
  fi
  in_dir "$work/$model" "${run[@]}" "$bin" 2>/dev/null
  avx2=$("${run[@]}" "$work/features")
  while read -r sum file; do
    other=$(cd "$work/$model/out" && sha256sum "$file" | cut -d' ' -f1)
    if [ "$sum" = "$other" ]; then
      echo "$model (AVX2 and FMA: $avx2): $file same"
    else
      echo "$model (AVX2 and FMA: $avx2): $file DIFFERS"
      [ "$avx2" = false ] || status=1
    fi
  done < <(digest "$work/native/out")
done
exit $status
