#!/usr/bin/env bash
# The bytes a refactor must not change (issue 26: "a step that moves code keeps every output
# byte-identical"): trains small models on fixed simulated data (augmentation off) on the CPU and
# on the CUDA emulation, in FP32 and BF16, a full-size model for one step, and runs inference on
# one scan in every precision of every backend; prints one sha256 per output (checkpoints, the
# losses and gradient norms of metrics.jsonl, label maps, probabilities), sorted by name, so two
# trees' digests compare with diff.
# Usage: scripts/outputs_digest.sh PILLARSEG_BINARY WORK_DIR DATA_DIR [SCAN]
#   DATA_DIR: simulated with the binary when missing, then reused (so that a change of the
#   simulator does not show as a difference); SCAN: a KITTI .bin (default: the real labelled scan
#   in ../shared, else a simulated one).
set -euo pipefail
bin=$(realpath "${1:?usage: outputs_digest.sh PILLARSEG_BINARY WORK_DIR DATA_DIR [SCAN]}")
work=${2:?usage: outputs_digest.sh PILLARSEG_BINARY WORK_DIR DATA_DIR [SCAN]}
data=${3:?usage: outputs_digest.sh PILLARSEG_BINARY WORK_DIR DATA_DIR [SCAN]}
here=$(cd "$(dirname "$0")/.." && pwd)
real="$here/../shared/data/semantickitti/sequences/99/velodyne/000000.bin"
scan=${4:-}
mkdir -p "$work"
work=$(realpath "$work")
log="$work/log.txt"
: >"$log"
run() { "$bin" "$@" >>"$log" 2>&1 || { echo "failed: pillarseg $*" >&2; tail -20 "$log" >&2; exit 1; }; }

if [[ ! -d "$data/sequences/02" ]]; then
  run simulate --out "$data" --sequences 2 --scans 4 --seed 7
  run simulate --out "$data" --sequences 1 --scans 2 --seed 8 --first-sequence 2
fi
[[ -n "$scan" ]] || { [[ -f "$real" ]] && scan=$real || scan="$data/sequences/02/velodyne/000000.bin"; }

# A small config (the demo's model at 0.5 m cells) and the paper's full-size one, augmentation off.
small="$work/small.yaml" full="$work/full.yaml"
cat >"$small" <<'EOF'
grid: {x: [-50.0, 50.0], y: [-25.0, 25.0], z: [-2.5, 1.5], cell: 0.5, voxel_z: 0.5}
model: {max_points_per_pillar: 20, max_pillars: 0, pillars: true, pillar_channels: 16,
        occupancy: none, base_width: 8, depth: 3, upsampling: bilinear}
train:
  ground_truth: sparse
  loss: ce
  epochs: 2
  batch_size: 2
  seed: 3
  optimizer: {lr: 0.003, weight_decay: 0.01, schedule: onecycle, grad_clip: 10}
  sequences: [0, 1]
eval:
  sequences: [2]
EOF
cat >"$full" <<'EOF'
train:
  ground_truth: sparse
  epochs: 1
  batch_size: 2
  seed: 3
  sequences: [2]
EOF

digest() {  # name file...
  local name=$1
  shift
  printf '%s %s\n' "$(cat "$@" | sha256sum | cut -c1-16)" "$name" >>"$work/digests.unsorted"
}
losses() {  # the training's numbers that do not depend on the clock
  grep -o '"\(loss\|grad_norm\|lr\|miou\)": *[-0-9.eE+naif]*' "$1"
}
: >"$work/digests.unsorted"

train() {  # name config device precision
  local name=$1 config=$2 device=$3 precision=$4
  rm -rf "$work/$name"
  run train --data "$data" --config "$config" --out "$work/$name" --cache "$work/cache_$(basename "$config" .yaml)" \
    --device "$device" --precision "$precision"
  digest "$name/checkpoint" "$work/$name/checkpoint.safetensors"
  losses "$work/$name/metrics.jsonl" >"$work/$name/losses.txt"
  digest "$name/losses" "$work/$name/losses.txt"
}
infer() {  # name weights device precision [env...]
  local name=$1 weights=$2 device=$3 precision=$4
  shift 4
  env "$@" "$bin" infer --weights "$weights" --scan "$scan" --out "$work/infer_$name" --probabilities \
    --no-png --device "$device" --precision "$precision" >>"$log" 2>&1 ||
    { echo "failed: infer $name" >&2; tail -20 "$log" >&2; exit 1; }
  digest "infer/$name/labels" "$work/infer_$name.u8"
  digest "infer/$name/probabilities" "$work/infer_$name.f16"
}

train small_cpu_fp32 "$small" cpu fp32
train small_emu_fp32 "$small" emu fp32
train small_emu_bf16 "$small" emu bf16
train full_cpu_fp32 "$full" cpu fp32
w="$work/small_cpu_fp32/checkpoint.safetensors"
infer small_cpu_fp32 "$w" cpu fp32
infer small_cpu_bf16 "$w" cpu bf16
infer small_cpu_bf16_avx512 "$w" cpu bf16 PILLARSEG_CPU_AMX=0
infer small_emu_fp32 "$w" emu fp32
infer small_emu_bf16 "$w" emu bf16
infer small_emu_fp16 "$w" emu fp16
w="$work/full_cpu_fp32/checkpoint.safetensors"
infer full_cpu_fp32 "$w" cpu fp32
infer full_cpu_bf16 "$w" cpu bf16
sort -k2 "$work/digests.unsorted" >"$work/digests.txt"
rm "$work/digests.unsorted"
cat "$work/digests.txt"
