#!/usr/bin/env bash
# The command line end to end on a tiny simulated data set: pillarseg infer over one scan, a
# directory and several files (the same label maps), --device emu for infer, bench, eval and
# train (training's first losses those of the CPU; in bf16 close to them), --precision, and errors
# that name the argument.
# Usage: tests/cli_test.sh PILLARSEG_BINARY WORK_DIR
set -euo pipefail
bin=$1 work=$2
rm -rf "$work"
mkdir -p "$work"
fail() { echo "cli_test: $*"; exit 1; }
run() { "$bin" --threads 2 "$@"; }

run simulate --out "$work/data" --sequences 1 --scans 3 --seed 9 --points-per-scan 30000 > /dev/null 2>&1
cat > "$work/tiny.yaml" <<'YAML'
grid: {x: [-20.0, 20.0], y: [-10.0, 10.0], z: [-2.5, 1.5], cell: 0.4, voxel_z: 0.2}
model: {max_points_per_pillar: 8, pillar_channels: 8, occupancy: 2d, occupancy_channels: 4, base_width: 8, depth: 2}
train: {epochs: 1, batch_size: 2, seed: 1, sequences: [0]}
eval: {sequences: [0]}
YAML
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/cpu" > /dev/null 2>&1
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/emu" --device emu > /dev/null 2>&1
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/emu_bf16" --device emu --precision bf16 \
  > "$work/emu_bf16.log" 2>&1 || { cat "$work/emu_bf16.log"; fail "train --device emu --precision bf16 failed"; }
grep -q 'precision bf16' "$work/emu_bf16.log" || fail "train --precision bf16: precision not logged"
first_loss() { grep -m1 '"type": "step"' "$1/metrics.jsonl" | sed 's/.*"loss": \([0-9.]*\).*/\1/'; }
python3 - "$(first_loss "$work/cpu")" "$(first_loss "$work/emu")" "$(first_loss "$work/emu_bf16")" <<'PY' ||
import sys
cpu, emu, bf16 = map(float, sys.argv[1:])
assert abs(cpu - emu) <= 1e-4 * abs(cpu), ("emu", cpu, emu)
assert abs(cpu - bf16) <= 2e-2 * abs(cpu), ("bf16", cpu, bf16)
print(f"cli_test: first training loss cpu {cpu}, emu {emu}, emu bf16 {bf16}")
PY
  fail "training on emu: first loss differs from the CPU's"
# The event file, read back by TensorBoard itself where it is installed.
python3 - "$work/cpu" <<'PY' || fail "TensorBoard does not read the event file as metrics.jsonl says"
import json, sys
try:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
except ImportError:
    print("cli_test: TensorBoard check skipped: the tensorboard Python package is not installed")
    sys.exit(0)
run = sys.argv[1]
acc = EventAccumulator(run)
acc.Reload()
got = [(e.step, e.value) for e in acc.Scalars("train/loss")]
want = [(r["step"], r["loss"]) for r in map(json.loads, open(run + "/metrics.jsonl")) if r["type"] == "step"]
assert [s for s, _ in got] == [s for s, _ in want], (got, want)
assert all(abs(a - b) <= 1e-5 * abs(b) + 1e-6 for (_, a), (_, b) in zip(got, want)), (got, want)
print(f"cli_test: TensorBoard reads {len(got)} train/loss scalars, those of metrics.jsonl")
PY
weights=$work/cpu/checkpoint.safetensors
velodyne=$work/data/sequences/00/velodyne

run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/one" > /dev/null
run infer --weights "$weights" --scan "$velodyne" --out "$work/dir" --no-png > "$work/dir.log" 2>&1
run infer --weights "$weights" --scan "$velodyne/000002.bin" "$velodyne/000001.bin" --out "$work/two" > /dev/null 2>&1
cmp "$work/one.u8" "$work/dir/000001.u8" || fail "infer over a directory: 000001.u8 differs from the single scan's"
cmp "$work/one.u8" "$work/two/000001.u8" || fail "infer over two files: 000001.u8 differs from the single scan's"
[[ -f $work/one.png && -f $work/two/000002.png && ! -e $work/dir/000001.png ]] || fail "infer: .png files (--no-png)"
[[ $(ls "$work/dir" | wc -l) == 3 ]] || fail "infer over a directory: expected 3 label maps in $work/dir"
grep -q 'scans/s end to end' "$work/dir.log" || fail "infer over a directory: no throughput line"
run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/emu_one" --device emu > /dev/null
run eval --data "$work/data" --weights "$weights" --mode sparse --device emu --report "$work/eval_emu.json" > /dev/null 2>&1
[[ -s $work/eval_emu.json ]] || fail "eval --device emu wrote no report"

run bench --device emu --config "$work/tiny.yaml" --weights "$weights" --scan "$velodyne/000001.bin" --repeat 2 \
  > "$work/bench.log" 2>&1 || { cat "$work/bench.log"; fail "bench --device emu failed"; }
grep -q '^pillars ' "$work/bench.log" || fail "bench --device emu: no pillars stage (gather and decoration on the device)"
grep -q 'pillarize' "$work/bench.log" && fail "bench --device emu: a host pillarize stage"
grep -q '^bytes over the bus per scan' "$work/bench.log" || fail "bench --device emu: no bytes count"

# --precision bf16: the tensor-core convolutions on the emulation (a label map of the same size,
# mostly the FP32 one); on the CPU the AVX512_BF16 micro-kernel where the CPU has it, else one
# warning line and fp32; fp16 on the CPU always falls back; refused by train.
run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/bf16" --device emu --precision bf16 > /dev/null
cmp -s "$work/bf16.u8" "$work/emu_one.u8" && echo "cli_test: note: bf16 and fp32 label maps are identical"
[[ $(stat -c %s "$work/bf16.u8") == $(stat -c %s "$work/emu_one.u8") ]] || fail "infer --precision bf16: label map size"
message=$(run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/cpu_bf16" --precision bf16 2>&1)
if grep -qw avx512_bf16 /proc/cpuinfo && grep -qw avx512bw /proc/cpuinfo && grep -qw avx512vl /proc/cpuinfo; then
  [[ $message != *"running fp32"* ]] || fail "infer --precision bf16 on an AVX512_BF16 CPU fell back: '$message'"
  [[ $(stat -c %s "$work/cpu_bf16.u8") == $(stat -c %s "$work/one.u8") ]] || fail "infer --precision bf16 on the CPU: label map size"
else
  [[ $message == *"--precision bf16: the CPU's BF16 convolutions need AVX512_BF16: "*"running fp32"* ]] ||
    fail "infer --precision bf16 on the CPU: '$message'"
  cmp "$work/cpu_bf16.u8" "$work/one.u8" || fail "infer --precision bf16 on the CPU is not the fp32 label map"
fi
message=$(run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/cpu_fp16" --precision fp16 2>&1)
[[ $message == *"--precision fp16: the CPU backend has no FP16 convolutions"*"running fp32"* ]] ||
  fail "infer --precision fp16 on the CPU: '$message'"
cmp "$work/cpu_fp16.u8" "$work/one.u8" || fail "infer --precision fp16 on the CPU is not the fp32 label map"
run bench --device emu --precision bf16 --config "$work/tiny.yaml" --weights "$weights" --scan "$velodyne/000001.bin" \
  --repeat 1 > "$work/bench_bf16.log" 2>&1 || { cat "$work/bench_bf16.log"; fail "bench --precision bf16 failed"; }
grep -q 'precision bf16' "$work/bench_bf16.log" || fail "bench --precision bf16: precision not reported"

# Errors name the argument and exit 1.
expect_error() {
  local expected=$1
  shift
  set +e
  message=$(run "$@" 2>&1)
  local rc=$?
  set -e
  [[ $rc == 1 ]] || fail "'$*' exited $rc, expected 1: $message"
  [[ $message == *"$expected"* ]] || fail "'$*': '$message' does not say '$expected'"
}
expect_error "--scan $work/none.bin: no such file" infer --weights "$weights" --scan "$work/none.bin" --out "$work/x"
expect_error "is a file" infer --weights "$weights" --scan "$velodyne" --out "$work/one.u8"
expect_error "train --precision bf16: backend cpu trains in fp32 only" train --data "$work/data" \
  --config "$work/tiny.yaml" --out "$work/bf16_run" --precision bf16
[[ ! -e "$work/bf16_run" ]] || fail "train --precision bf16 on the CPU left a run directory"
# A --device outside cpu, cuda, emu: the command line refuses it and names the option.
if message=$(run infer --weights "$weights" --scan "$velodyne" --out "$work/y" --device tpu 2>&1); then
  fail "--device tpu was accepted"
fi
[[ $message == *"--device"* ]] || fail "--device tpu: '$message' does not name --device"
echo "cli_test: infer (one scan, a directory, two files), --device emu (infer, eval, bench, train), --precision and errors pass"
