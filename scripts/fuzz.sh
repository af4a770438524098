#!/usr/bin/env bash
# The fuzz targets (fuzz/) under libFuzzer with AddressSanitizer and UBSan (DESIGN.md section 9):
# configures a clang 14 build in build-fuzz whose every target carries the sanitizer flags, builds
# each <reader>_fuzz, and runs it for FUZZ_SECONDS (default 600) on its committed seeds
# (fuzz/corpus/<reader>) and regression inputs, adding new inputs to a scratch corpus
# (build-fuzz/corpus/<reader>) only. Prints each target's executions, coverage (edges, features)
# and crashes. A crash's input goes to fuzz/findings/; the script then exits 1 naming it.
# Usage: scripts/fuzz.sh [READER...]   (default: every target; FUZZ_BUILD, JOBS as for make)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${FUZZ_BUILD:-$root/build-fuzz}
seconds=${FUZZ_SECONDS:-600}
jobs=${JOBS:-$(nproc)}
findings=$root/fuzz/findings

if ! command -v clang++-14 >/dev/null; then
  echo "fuzz: clang++-14 not found; install clang-14 and libclang-rt-14-dev (scripts/install-deps.sh)" >&2
  exit 1
fi
probe=$(mktemp -d)
trap 'rm -rf "$probe"' EXIT
echo 'extern "C" int LLVMFuzzerTestOneInput(const unsigned char*, unsigned long) { return 0; }' > "$probe/probe.cpp"
if ! clang++-14 -fsanitize=fuzzer,address,undefined "$probe/probe.cpp" -o "$probe/probe" 2> "$probe/log"; then
  echo "fuzz: clang++-14 cannot link a libFuzzer target (libclang-rt-14-dev missing?):" >&2
  cat "$probe/log" >&2
  exit 1
fi

readers=("$@")
if ((${#readers[@]} == 0)); then
  readers=($(sed -n '/^set(PILLARSEG_FUZZ_READERS/,/)/p' "$root/fuzz/CMakeLists.txt" |
             sed 's/set(PILLARSEG_FUZZ_READERS//; s/)//'))
fi

# Every library is instrumented for coverage (fuzzer-no-link) and sanitized; assertions stay on.
# -Wno-unknown-warning-option: the GCC-only warning flags of cmake/Warnings.cmake and core/eigen.hpp;
# fuzz/clang14_compat.hpp: std::source_location, which clang 14 with libstdc++ 12 lacks.
flags="-fsanitize=address,undefined,fuzzer-no-link -fno-sanitize-recover=undefined -fno-omit-frame-pointer"
flags+=" -Wno-unknown-warning-option -include $root/fuzz/clang14_compat.hpp"
cmake -S "$root" -B "$build" -DCMAKE_CXX_COMPILER=clang++-14 -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_FLAGS="$flags" -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O2 -g" \
  -DPILLARSEG_FUZZ=ON -DPILLARSEG_TESTS=ON -DPILLARSEG_BENCH=OFF -DPILLARSEG_CUDA=OFF >/dev/null
echo "fuzz: building ${#readers[@]} targets in $build (log: $build/build.log)"
if ! cmake --build "$build" -j "$jobs" --target "${readers[@]/%/_fuzz}" > "$build/build.log" 2>&1; then
  grep -E -m20 'error|Error' "$build/build.log" >&2 || tail -20 "$build/build.log" >&2
  exit 1
fi

mkdir -p "$findings"
export ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:allocator_may_return_null=0}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}
export LSAN_OPTIONS=${LSAN_OPTIONS:-suppressions=$root/fuzz/lsan.supp}
summary=()
failed=()
for reader in "${readers[@]}"; do
  scratch=$build/corpus/$reader
  log=$build/fuzz-$reader.log
  mkdir -p "$scratch"
  echo "== $reader: ${seconds} s"
  status=0
  "$build/fuzz/${reader}_fuzz" -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=30 \
    -print_final_stats=1 -artifact_prefix="$findings/$reader-" \
    "$scratch" "$root/fuzz/corpus/$reader" "$root/fuzz/regressions/$reader" > "$log" 2>&1 || status=$?
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$log" | tail -1)
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  ft=$(grep -o 'ft: [0-9]*' "$log" | tail -1 | cut -d' ' -f2)
  artifact=$(sed -n 's/.*Test unit written to \(.*\)$/\1/p' "$log" | tail -1)
  crashes=0
  if ((status != 0)); then
    crashes=1
    failed+=("$reader: ${artifact:-no input saved} (log $log)")
    grep -m1 -E 'ERROR: (AddressSanitizer|libFuzzer|LeakSanitizer)|runtime error:|fuzz harness:|terminate called' "$log" || true
  fi
  summary+=("$(printf '%-14s %12s %8s %8s %8s %8s' "$reader" "${execs:-?}" "${rate:-?}" "${cov:-?}" "${ft:-?}" "$crashes")")
done

printf '\n%-14s %12s %8s %8s %8s %8s\n' target executions exec/s edges features crashes
printf '%s\n' "${summary[@]}"
if ((${#failed[@]} > 0)); then
  echo
  echo "fuzz: ${#failed[@]} target(s) found a crash; minimise the input, fix, and commit it to fuzz/regressions/<reader>/ (fuzz/regressions/README.md):"
  printf '  %s\n' "${failed[@]}"
  exit 1
fi
