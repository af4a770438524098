#!/usr/bin/env bash
# run.sh of the GPU bundle (scripts/gpu_bundle.sh packs it): the whole GPU check on a bare CUDA
# machine in one call of at most 8 minutes, writing report.md and its logs into $OUT (8 files),
# stage by stage, each appending what it measured as it goes (a call killed at its limit still
# returns every figure measured until then, and the summary):
#   smoke            at most 90 s, first: the device, the first test of each *_gpu test binary,
#                    one full-size bench (its table heads the report)
#   tests            every *_gpu test (kernels, CUDA backend, device pipeline against the CPU)
#   sanitizer        compute-sanitizer memcheck, racecheck, synccheck, initcheck over the kernel tests
#   kernels          the kernel benchmarks
#   bench            pillarseg bench --device cuda at full size, every variant
#   ops              the bf16 and int8 networks per op against each op's roofline bound on an H200
#   train            100 training steps on cuda (fp32, bf16) and on cpu
# The files:
#   nvidia-smi.txt   the device, driver and clocks
#   tests.log        the smoke stage's and every *_gpu test's output
#   sanitizer.log    compute-sanitizer over the kernel tests
#   kernels.log      the kernel benchmarks: ours against cuDNN and cuBLAS, the 16-bit training
#                    gradients against our FP32 ones
#   bench.log        pillarseg bench --device cuda at full size (bilinear, transposed, 2D and 3D
#                    occupancy; --conv own, cudnn, cublas; bf16, fp16, int8; 4 flips), and the bf16
#                    and int8 networks per op against each op's roofline bound on an H200
#   train.log        100 steps of the small config on cuda (fp32, bf16) and on cpu, their loss curves
#   environment.txt  the libraries found, the bundle's commit
#   report.md        the figures of all of them, and what failed
# Usage: [OUT=dir] ./run.sh [--only STAGES] [SECONDS]
#   STAGES: a comma-separated list of smoke, tests, sanitizer, kernels, bench, ops, train (default:
#   all, in that order); a second call after a fix reruns only the stages that failed.
#   SECONDS: the time budget, default 470.
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
out=${OUT:-$here/out}
all_stages=smoke,tests,sanitizer,kernels,bench,ops,train
only=$all_stages
budget=470
while (($#)); do
  case $1 in
    --only) only=${2:?run.sh: --only needs a list of stages ($all_stages)}; shift 2 ;;
    --only=*) only=${1#--only=}; shift ;;
    -h|--help) sed -n '2,/^set -uo pipefail/{/^#/p}' "$0"; exit 0 ;;
    *[!0-9]*|'') echo "run.sh: unknown argument '$1' (usage: run.sh [--only STAGES] [SECONDS])" >&2; exit 2 ;;
    *) budget=$1; shift ;;
  esac
done
for stage in ${only//,/ }; do
  [[ ,$all_stages, == *,$stage,* ]] ||
    { echo "run.sh: --only: unknown stage '$stage' (stages: $all_stages)" >&2; exit 2; }
done
wants() { [[ ,$only, == *,$1,* ]]; }
mkdir -p "$out"
start=$(date +%s)
left() { echo $((budget - ($(date +%s) - start))); }
report=$out/report.md
env_log=$out/environment.txt
failures=()
note() { echo "$*" >> "$report"; }
stage_start=$start
begin_stage() {
  stage_start=$(date +%s)
  note "<!-- stage $1 began at +$((stage_start - start)) s -->"
}
end_stage() {
  note "_Stage $1: $(( $(date +%s) - stage_start )) s._"
  note
}
summary() {
  {
    echo "## Summary"
    echo
    echo "Stages run: $only. Total time: $(( $(date +%s) - start )) s."
    if ((${#failures[@]} == 0)); then
      echo "Nothing failed."
    else
      echo "Failed: ${failures[*]}."
    fi
  } >> "$report"
}
# Killed at the call's limit: the summary of what ran still reaches the report.
trap 'note; note "**Stopped by a signal at +$(( $(date +%s) - start )) s.**"; summary; exit 124' TERM INT

# ---- the machine's CUDA libraries ----
cuda_dirs=()
for d in /usr/local/cuda/lib64 /usr/local/cuda/targets/x86_64-linux/lib /usr/local/nvidia/lib64 \
         /usr/lib/x86_64-linux-gnu; do
  [[ -d $d ]] && cuda_dirs+=("$d")
done
# pip wheels (nvidia-cudnn-cu13, nvidia-cublas, ...) hold the libraries in site-packages/nvidia/*/lib.
while read -r d; do cuda_dirs+=("$d"); done < <(find / -xdev -type d -path '*site-packages/nvidia/*/lib' 2>/dev/null | sort -u)
library_path=$here/lib
# The bundle's libstdc++ only where the machine's is older than the binaries need (GCC 12's).
system_cxx=$(ldconfig -p 2>/dev/null | awk '/libstdc\+\+\.so\.6 .*x86-64/ {print $NF; exit}')
if [[ -z $system_cxx ]] || ! grep -q GLIBCXX_3.4.30 "$system_cxx" 2>/dev/null; then
  library_path=$here/lib/cxx:$library_path
fi
for d in "${cuda_dirs[@]}"; do library_path+=":$d"; done
export LD_LIBRARY_PATH=$library_path${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export PATH=$PATH:/usr/local/cuda/bin
{
  echo "bundle commit: $(cat "$here/commit" 2>/dev/null)"
  echo "date: $(date -u +%FT%TZ)"
  echo "host: $(uname -a)"
  echo "cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2-) ($(nproc) threads)"
  ldd --version 2>&1 | head -1
  echo "system libstdc++: ${system_cxx:-none} (the bundle's used: $([[ $LD_LIBRARY_PATH == $here/lib/cxx* ]] && echo yes || echo no))"
  echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
  for lib in libcuda.so.1 libcudart.so.13 libcublas.so.13 libcublasLt.so.13 libcudnn.so.9; do
    found=$(for d in ${LD_LIBRARY_PATH//:/ }; do ls "$d/$lib" 2>/dev/null; done | head -1)
    echo "$lib: ${found:-NOT FOUND}"
  done
  echo "ldd bin/pillarseg:"
  ldd "$here/bin/pillarseg"
} > "$env_log" 2>&1

nvidia-smi > "$out/nvidia-smi.txt" 2>&1 || echo "nvidia-smi failed" >> "$out/nvidia-smi.txt"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv >> "$out/nvidia-smi.txt" 2>&1
gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)

driver=$(nvidia-smi --query-gpu=driver_version --format=csv,noheader 2>/dev/null | head -1)
{
  echo "# GPU check of pillarseg $(cat "$here/commit" 2>/dev/null)"
  echo
  echo "Machine: ${gpu:-no GPU reported} (driver ${driver:-?}); $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | xargs), $(nproc) CPU threads; $(date -u +%F). Stages: $only."
  echo
} > "$report"
tests_log=$out/tests.log
bench_log=$out/bench.log
: > "$tests_log"
: > "$bench_log"
scan=$here/data/sequences/99/velodyne/000000.bin
[[ -f $scan ]] || scan=""
# The steady-state milliseconds of a `pillarseg bench` output.
steady_ms() { sed -n 's/^steady state.*: \([0-9.]*\) ms; stage by stage above: \([0-9.]*\) ms.*/\1/p' "$1"; }

# ---- 0. smoke: at most 90 s, its table first ----
if wants smoke; then
  begin_stage smoke
  note "## Smoke (at most 90 s): the first test of each test binary, one full-size bench"
  note
  note "| check | result | seconds |"
  note "|---|---|---:|"
  smoke_row() { note "| $1 | $2 | $3 |"; }
  if [[ -n $gpu ]]; then smoke_row "device" "$gpu, driver $driver" 0; else smoke_row "device" "NONE (nvidia-smi found no GPU)" 0; failures+=("smoke: no GPU"); fi
  for t in "$here"/bin/test_*_gpu; do
    name=$(basename "$t")
    first=$("$t" --gtest_list_tests 2>/dev/null | awk '/^[^ ]/ {suite=$1} /^  / {print suite $1; exit}')
    [[ -n $first ]] || { smoke_row "$name" "no tests listed" 0; failures+=("smoke $name"); continue; }
    t0=$(date +%s)
    echo "=== smoke $name --gtest_filter=$first" >> "$tests_log"
    timeout 20 "$t" --gtest_color=no --gtest_filter="$first" >> "$tests_log" 2>&1
    rc=$?
    result="passed ($first)"
    ((rc == 0)) || { result="FAILED, exit $rc ($first)"; failures+=("smoke $name"); }
    ((rc == 124)) && result="time limit 20 s ($first)"
    smoke_row "$name" "$result" $(( $(date +%s) - t0 ))
  done
  # The two ceilings every figure is read against: cuBLAS's BF16 GEMM and the copy bandwidth.
  if [[ -x $here/bin/bench_kernels_reference ]]; then
    t0=$(date +%s)
    echo "=== smoke: bench_kernels_reference" >> "$bench_log"
    timeout 30 "$here/bin/bench_kernels_reference" --benchmark_counters_tabular=false > "$out/.smoke" 2>&1
    rc=$?
    cat "$out/.smoke" >> "$bench_log"
    gemm=$(grep -m1 '^CublasGemmBF16' "$out/.smoke" | grep -o 'TFLOP/s=[0-9.]*[kMG]*' | cut -d= -f2)
    copy=$(grep -m1 '^DeviceCopy' "$out/.smoke" | grep -o 'TB/s=[0-9.]*' | cut -d= -f2)
    if ((rc == 0)) && [[ -n $gemm && -n $copy ]]; then
      smoke_row "ceilings: cuBLAS bf16 GEMM 8192^3, 2 GiB device copy" "$gemm TFLOP/s, $copy TB/s (read + written)" $(( $(date +%s) - t0 ))
    else
      smoke_row "ceilings: cuBLAS bf16 GEMM 8192^3, 2 GiB device copy" "FAILED, exit $rc (see bench.log)" $(( $(date +%s) - t0 ))
      failures+=("smoke bench_kernels_reference")
    fi
  fi
  t0=$(date +%s)
  echo "=== smoke: bench bilinear --conv own --repeat 3" >> "$bench_log"
  if timeout 40 "$here/bin/pillarseg" bench --device cuda --repeat 3 ${scan:+--scan "$scan"} > "$out/.smoke" 2>&1; then
    steady=$(steady_ms "$out/.smoke")
    smoke_row "full-size bench, bilinear fp32" "steady state ${steady:-?} ms" $(( $(date +%s) - t0 ))
  else
    smoke_row "full-size bench, bilinear fp32" "FAILED (see bench.log)" $(( $(date +%s) - t0 ))
    failures+=("smoke bench")
  fi
  cat "$out/.smoke" >> "$bench_log"
  rm -f "$out/.smoke"
  note
  end_stage smoke
fi

# ---- 1. the GPU tests ----
if wants tests; then
begin_stage tests
note "## Tests (every *_gpu test)"
note
note "| test | passed | failed | seconds | note |"
note "|---|---:|---:|---:|---|"
for t in "$here"/bin/test_*_gpu; do
  name=$(basename "$t")
  t0=$(date +%s)
  timeout 150 "$t" --gtest_color=no > "$out/.one.log" 2>&1
  rc=$?
  cat "$out/.one.log" >> "$tests_log"
  passed=$(grep -c '^\[       OK \]' "$out/.one.log")
  failed=$(grep -c '^\[  FAILED  \] .*(' "$out/.one.log")
  why=""
  grep -q 'no CUDA device:' "$out/.one.log" && why=$(grep -m1 -o 'no CUDA device:.*' "$out/.one.log")
  ((rc == 124)) && why="time limit (150 s)"
  note "| $name | $passed | $failed | $(( $(date +%s) - t0 )) | $why |"
  if ((rc != 0)); then failures+=("$name exit $rc"); fi
done
rm -f "$out/.one.log"
note
end_stage tests
fi

# ---- 2. compute-sanitizer over the kernel tests ----
if wants sanitizer; then
begin_stage sanitizer
sanitizer_log=$out/sanitizer.log
: > "$sanitizer_log"
note "## compute-sanitizer"
note
if command -v compute-sanitizer > /dev/null; then
  note "| tool | test | result |"
  note "|---|---|---|"
  for tool in memcheck racecheck synccheck initcheck; do
    for t in "$here"/bin/test_kernels_*_gpu; do
      (( $(left) > 240 )) || { note "| $tool | $(basename "$t") | not run: time budget |"; continue; }
      echo "=== $tool $(basename "$t")" >> "$sanitizer_log"
      timeout 60 compute-sanitizer --tool "$tool" --error-exitcode 99 "$t" --gtest_color=no \
        --gtest_filter='-*LauncherChecks*:*Argument*' >> "$sanitizer_log" 2>&1
      rc=$?
      if grep -q 'Device not supported\|not supported on this' "$sanitizer_log"; then
        result="refused the device"
      elif ((rc == 0)); then
        result="clean"
      elif ((rc == 124)); then
        result="time limit (60 s)"
      else
        result="errors (exit $rc)"
        failures+=("compute-sanitizer $tool $(basename "$t")")
      fi
      note "| $tool | $(basename "$t") | $result |"
    done
  done
else
  note "compute-sanitizer not found on PATH."
fi
note
end_stage sanitizer
fi

# ---- 3. kernel benchmarks: ours, cuDNN, cuBLAS ----
if wants kernels; then
begin_stage kernels
# bench_kernels_conv's 16-bit training gradients (every layer, BF16 and FP16: 36 rows beside its
# 132, each filling its layer's tensors) would lengthen its run by about a quarter, which could
# take it past its 90 s (its time on a GPU is not measured yet): here they run in BF16 on the large
# 3x3 layer and the large transposed one only, after those layers' FP32 passes again (for
# fp32_ms/half_ms), in a second run of 8 rows.
kernels_log=$out/kernels.log
: > "$kernels_log"
half_backward='Backward(Data|Weights)(BF16|FP16)/'
for b in "$here"/bin/bench_kernels_*; do
  (( $(left) > 200 )) || break
  echo "=== $(basename "$b")" >> "$kernels_log"
  filter=()
  [[ $(basename "$b") == bench_kernels_conv ]] && filter=(--benchmark_filter="-$half_backward")
  timeout 90 "$b" --benchmark_min_time=0.05s --benchmark_counters_tabular=true ${filter[@]+"${filter[@]}"} \
    >> "$kernels_log" 2>&1 || failures+=("$(basename "$b")")
done
if [[ -x $here/bin/bench_kernels_conv ]] && (( $(left) > 200 )); then
  echo "=== bench_kernels_conv: the 16-bit training gradients (BF16, two layers)" >> "$kernels_log"
  timeout 45 "$here/bin/bench_kernels_conv" --benchmark_min_time=0.05s --benchmark_counters_tabular=true \
    --benchmark_filter='^(Conv2d|ConvTranspose2d)Backward(Data|Weights)(BF16)?/(full_inc_64to64_500x1000|full_up4_128to64_250x500)(/|$)' \
    >> "$kernels_log" 2>&1 || failures+=("bench_kernels_conv (16-bit gradients)")
fi
note "## Kernel benchmarks"
note
note "See kernels.log (ours against cuDNN and cuBLAS per convolution pass and layer; the 16-bit"
note "training gradients of two layers against our FP32 ones)."
note
end_stage kernels
fi

# ---- 4. pillarseg bench --device cuda at full size ----
if wants bench; then
begin_stage bench
note "## pillarseg bench --device cuda (full size, the real scan)"
note
note "| model | conv | steady state ms | stage sum ms | U-Net ms | MB over the bus (host inputs) | against fp32 |"
note "|---|---|---:|---:|---:|---|---|"
run_bench() {
  local label=$1 conv=$2
  shift 2
  (( $(left) > 120 )) || { note "| $label | $conv | not run: time budget | | | | |"; return; }
  echo "=== $label --conv $conv" >> "$bench_log"
  timeout 60 "$here/bin/pillarseg" bench --device cuda --conv "$conv" --repeat 5 ${scan:+--scan "$scan"} "$@" \
    > "$out/.bench" 2>&1
  local rc=$?
  cat "$out/.bench" >> "$bench_log"
  if ((rc != 0)); then
    failures+=("bench $label $conv")
    note "| $label | $conv | failed (exit $rc) | | | | |"
    return
  fi
  local steady staged unet bytes agreement
  steady=$(steady_ms "$out/.bench")
  staged=$(sed -n 's/^steady state.*stage by stage above: \([0-9.]*\) ms.*/\1/p' "$out/.bench")
  unet=$(awk '$1 == "U-Net" {print $2}' "$out/.bench")
  bytes=$(sed -n 's/^bytes over the bus per scan: \([0-9.]*\) MB.*: \([0-9.]*\) MB.*/\1 (\2)/p' "$out/.bench")
  agreement=$(sed -n 's/^[a-z0-9]* against fp32: arg-max agreement \([0-9.]*%\).*largest probability difference \([0-9.]*\)/\1, max |dp| \2/p' "$out/.bench")
  note "| $label | $conv | $steady | $staged | $unet | $bytes | ${agreement:--} |"
}
run_bench "bilinear" own
run_bench "bilinear" cudnn
run_bench "bilinear" cublas
run_bench "transposed" own --transposed
run_bench "bilinear, bf16 tensor cores" own --precision bf16
run_bench "bilinear, fp16 tensor cores" own --precision fp16
run_bench "bilinear, int8 tensor cores (scales from the scan)" own --precision int8
run_bench "transposed, bf16 tensor cores" own --transposed --precision bf16
run_bench "pillar + 2D occupancy" own --config "$here/configs/pillar_2d_sparse.yaml"
run_bench "pillar + 3D occupancy" own --config "$here/configs/pillar_3d_sparse.yaml"
run_bench "bilinear, bf16, 4 flips (4 passes)" own --precision bf16 --flips 4
rm -f "$out/.bench"
note
end_stage bench
fi

# ---- 5. the bf16 and int8 networks op by op ----
# The bf16 network (then, time left, the int8 one) op by op (the device waits after every op)
# beside each op's roofline bound on an H200 (the machine lent to this project;
# engine/model/roofline.cpp): what share of the bound each op reaches.
run_ops() {
  local precision=$1
  (( $(left) > 120 )) || return 0
  echo "=== bilinear $precision --ops --roofline h200" >> "$bench_log"
  if timeout 60 "$here/bin/pillarseg" bench --device cuda --precision "$precision" --repeat 3 ${scan:+--scan "$scan"} \
      --ops --roofline h200 > "$out/.ops" 2>&1; then
    note "### The $precision network per op against its roofline bound on an H200"
    note
    note '```'
    sed -n '/^the network per op/,/^roofline bound/p' "$out/.ops" >> "$report"
    note '```'
  else
    failures+=("bench --ops $precision")
    note "bench --ops --precision $precision failed: see bench.log"
  fi
  cat "$out/.ops" >> "$bench_log"
  rm -f "$out/.ops"
  note
}
if wants ops && (( $(left) > 120 )); then
  begin_stage ops
  run_ops bf16
  run_ops int8
  end_stage ops
fi

# ---- 6. 100 training steps on cuda (fp32, bf16) and on cpu ----
if wants train; then
begin_stage train
train_log=$out/train.log
: > "$train_log"
note "## Training: 100 steps of configs/small_cpu.yaml on cuda (fp32 and bf16) and on cpu"
note
work=$(mktemp -d)
if (( $(left) > 60 )); then
  "$here/bin/pillarseg" simulate --out "$work/data" --sequences 1 --scans 200 --seed 3 >> "$train_log" 2>&1
  sed -e 's/^  epochs: [0-9]*$/  epochs: 1/' -e 's/precise_bn_batches: 8/precise_bn_batches: 0/' -e 's/every_epochs: 4/every_epochs: 0/' \
      -e 's/^  average_epochs: [0-9]*$/  average_epochs: 0/' \
      -e 's/sequences: \[0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12\]/sequences: [0]/' "$here/configs/small_cpu.yaml" > "$work/check.yaml"
  for run in cuda cuda_bf16 cpu; do
    precision=fp32
    [[ $run == cuda_bf16 ]] && precision=bf16
    timeout $(( $(left) > 30 ? $(left) - 20 : 10 )) "$here/bin/pillarseg" train --data "$work/data" \
      --config "$work/check.yaml" --out "$work/run_$run" --device "${run%_bf16}" --precision "$precision" \
      >> "$train_log" 2>&1 || failures+=("train on $run")
  done
  python3 - "$work" >> "$report" 2>> "$train_log" <<'PY' || note "(loss comparison failed: see train.log)"
import json, sys
work = sys.argv[1]
def steps(device):
    out = []
    for line in open(f"{work}/run_{device}/metrics.jsonl"):
        r = json.loads(line)
        if r.get("type") == "step":
            out.append(r)
    return out
gpu, cpu = steps("cuda"), steps("cpu")
n = min(len(gpu), len(cpu))
d = [abs(g["loss"] - c["loss"]) / max(abs(c["loss"]), 1e-9) for g, c in zip(gpu, cpu)]
print(f"{n} steps compared. Loss: step 1 cuda {gpu[0]['loss']:.5f} / cpu {cpu[0]['loss']:.5f}; "
      f"step {n} cuda {gpu[n-1]['loss']:.5f} / cpu {cpu[n-1]['loss']:.5f}.")
print(f"Relative loss difference: first 10 steps at most {max(d[:10]):.2e}, all {n} at most {max(d):.2e}; "
      f"mean of the last 10: cuda {sum(g['loss'] for g in gpu[n-10:n])/10:.4f}, cpu {sum(c['loss'] for c in cpu[n-10:n])/10:.4f}.")
tg = gpu[n-1]["elapsed_s"] / n
tc = cpu[n-1]["elapsed_s"] / n
print(f"Time per step (elapsed / steps, data preparation included): cuda {1e3*tg:.1f} ms, cpu {1e3*tc:.1f} ms.")
try:
    bf = steps("cuda_bf16")
    m = min(len(bf), len(gpu))
    db = [abs(b["loss"] - g["loss"]) / max(abs(g["loss"]), 1e-9) for b, g in zip(bf, gpu)]
    print(f"bf16 training (tensor cores, FP32 master weights) against fp32 on cuda, {m} steps: step 1 "
          f"{bf[0]['loss']:.5f} / {gpu[0]['loss']:.5f}, relative difference first 10 at most {max(db[:10]):.2e}; "
          f"mean of the last 10: bf16 {sum(b['loss'] for b in bf[m-10:m])/10:.4f}, fp32 "
          f"{sum(g['loss'] for g in gpu[m-10:m])/10:.4f}; time per step {1e3*bf[m-1]['elapsed_s']/m:.1f} ms.")
except (OSError, IndexError, ZeroDivisionError) as e:
    print(f"bf16 training: no result ({e})")
print()
PY
else
  note "not run: time budget"
fi
rm -rf "$work"
note
end_stage train
fi

summary
cat "$report"
