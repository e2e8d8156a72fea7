#!/usr/bin/env bash
# Builds the fuzz targets on the stable toolchain and runs each over its corpus.
#
#   fuzz/run.sh [SECONDS] [TARGET...]     (default: 60 s each, every target)
#
# The mutations follow libFuzzer's seed, 1 unless FUZZ_SEED says otherwise: with the same code
# a run explores the same inputs in the same order (a slower machine stops earlier in that
# sequence), so a clean run in CI is reproducible; a campaign uses other seeds.
#
# The targets are compiled with libFuzzer's coverage instrumentation (the flags cargo-fuzz
# passes, without AddressSanitizer: the readers are safe Rust) plus debug assertions and
# overflow checks, so nothing beyond a C++ compiler and the toolchain is needed. Each target
# starts from the corpus kept in fuzz/corpus/TARGET, which it reads but never changes: new
# inputs go to a scratch folder, dropped at the end. A crash, a hang (`-timeout`), a single
# allocation above 512 MiB or a resident size above 2 GiB fails the run; the input that caused
# it is kept in fuzz/artifacts/TARGET/ and named on stderr (replay it by running the target's
# binary on that file, then add it to tests/fuzz_regressions.rs).
set -euo pipefail
cd "$(dirname "$0")"
seconds=${1:-60}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(x3p gsf sdf_binary sdf_ascii sur gwy metropro opd plu al3d tmd vk4 vk6 lext frt datx opdx spm plux png_pcal npy tiff exr profile)
fi
triple=$(rustc -vV | sed -n 's/^host: //p')
export RUSTFLAGS="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 \
-Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table \
-Cllvm-args=-sanitizer-coverage-trace-compares --cfg fuzzing -Cdebug-assertions -Coverflow-checks"
# --target keeps the flags off build scripts and proc macros, as cargo-fuzz does.
cargo build --release --locked --quiet --bins --target "$triple"
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
failed=()
for t in "${targets[@]}"; do
  mkdir -p "artifacts/$t" "$scratch/$t"
  # A zip must be whole: x3p inputs keep their length and also start from the reference
  # files in profilometry/ (the kept corpus holds only zips under 8 kB), and so do datx
  # inputs (an HDF5 file's chunks and heaps lie anywhere in it); the others are cut at 4 kB
  # (every header field fits, and short inputs run a hundred times faster); lext inputs keep
  # 16 kB (a TIFF's IFDs and strips lie anywhere, and the kept seeds are 7 and 8 kB).
  len=4096
  extra=()
  if [ "$t" = lext ]; then
    len=16384
  fi
  if [ "$t" = x3p ] || [ "$t" = datx ]; then
    len=400000
    extra=(../profilometry)
  fi
  if "${CARGO_TARGET_DIR:-target}/$triple/release/$t" "$scratch/$t" "corpus/$t" "${extra[@]}" \
    -seed="${FUZZ_SEED:-1}" -max_total_time="$seconds" \
    -max_len="$len" -timeout=10 -malloc_limit_mb=512 -rss_limit_mb=2048 \
    -artifact_prefix="artifacts/$t/" -print_final_stats=1 >"$scratch/$t.log" 2>&1; then
    runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$scratch/$t.log")
    echo "fuzz $t: ${runs:-?} runs in ${seconds} s, no failure"
  else
    failed+=("$t")
    echo "fuzz $t: FAILED" >&2
    grep -E "^==[0-9]+==|SUMMARY|Test unit written|panicked" "$scratch/$t.log" >&2 || tail -20 "$scratch/$t.log" >&2
  fi
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzzing found failures in: ${failed[*]} (inputs in fuzz/artifacts/)" >&2
  exit 1
fi
