#!/usr/bin/env bash
# make demo: the main job on the built-in default data. Simulates a small SemanticKITTI-format
# data set, builds its ground truth, trains a small PillarSegNet on the CPU, evaluates it on a
# sequence it never saw (Sparse Eval and Dense Eval), and on the real labelled SemanticKITTI scan
# in ../shared/data when it is there (PILLARSEG_SHARED_DATA: another data directory), and renders
# PNGs (the training curves too).
# Usage: scripts/demo.sh PILLARSEG_BINARY OUT_DIR
set -euo pipefail
bin=${1:?usage: demo.sh PILLARSEG_BINARY OUT_DIR}
out=${2:?usage: demo.sh PILLARSEG_BINARY OUT_DIR}
here=$(cd "$(dirname "$0")/.." && pwd)
config="${DEMO_CONFIG:-$here/configs/small_cpu.yaml}"  # DEMO_CONFIG: another run config
data="$out/data" cache="$out/cache" run="$out/run" pictures="$out/pictures"
mkdir -p "$out" "$pictures"

step() { printf '\n== %s\n' "$*"; }

if [[ ! -d "$data/sequences/08" || ! -d "$data/sequences/12" ]]; then
  # Twelve short streets (1.5 s of driving each), 180 training scans: more layouts than 8 of 15
  # scored higher on the real scan and on simulated validation (docs/simulator.md).
  step "1/6 simulate: 12 training sequences of 15 scans (00-07, 09-12) and a validation sequence of 20 scans (08)"
  rm -rf "$data"
  "$bin" simulate --out "$data" --sequences 8 --scans 15 --seed 1
  "$bin" simulate --out "$data" --sequences 4 --scans 15 --seed 1 --first-sequence 9
  "$bin" simulate --out "$data" --sequences 1 --scans 20 --seed 2 --first-sequence 8
else
  step "1/6 simulate: reusing $data"
fi
"$bin" info --data "$data"

step "2/6 ground truth of the validation sequence (sparse and dense, cached) and pictures of scan 10"
"$bin" gt --data "$data" --sequence 8 --mode sparse --cache "$cache"
"$bin" gt --data "$data" --sequence 8 --mode dense --cache "$cache"
"$bin" gt --data "$data" --sequence 8 --scan 10 --mode sparse --cache "$cache" --out "$pictures/gt_sparse_08_000010.png"
"$bin" gt --data "$data" --sequence 8 --scan 10 --mode dense --cache "$cache" --out "$pictures/gt_dense_08_000010.png"
"$bin" observability --data "$data" --sequence 8 --scan 10 --out "$pictures/observability_08_000010.png"

step "3/6 train $(basename "$config") on the CPU"
if [[ -f "$run/checkpoint.safetensors" ]]; then
  "$bin" train --data "$data" --config "$config" --out "$run" --cache "$cache" --resume
else
  "$bin" train --data "$data" --config "$config" --out "$run" --cache "$cache"
fi

# Its one line names the PNGs and the directory; the validation charts need eval.every_epochs.
step "4/6 plot the training curves (loss, learning rate, gradient norm, validation)"
"$bin" plot "$run"

step "5/6 evaluate on sequence 08 (never seen in training)"
"$bin" eval --data "$data" --weights "$run/checkpoint.safetensors" --mode sparse --cache "$cache" \
  --report "$out/eval_sparse.json"
"$bin" eval --data "$data" --weights "$run/checkpoint.safetensors" --mode dense --cache "$cache" \
  --report "$out/eval_dense.json"

# The real labelled SemanticKITTI scan beside the repository (../shared, or PILLARSEG_SHARED_DATA):
# the simulator's model on real data it never saw. Its ground-truth cache goes under $out, never
# into the shared data.
real="${PILLARSEG_SHARED_DATA:-$here/../shared/data}/semantickitti"
real_miou=""
if [[ -f "$real/sequences/99/velodyne/000000.bin" && -f "$real/sequences/99/labels/000000.label" ]]; then
  # As the config evaluates (its eval.flips: the mean of mirrored copies), and in one pass.
  "$bin" eval --data "$real" --sequences 99 --weights "$run/checkpoint.safetensors" --mode sparse \
    --cache "$out/cache_real" --report "$out/eval_real_sparse.json"
  "$bin" eval --data "$real" --sequences 99 --weights "$run/checkpoint.safetensors" --mode sparse --flips 1 \
    --cache "$out/cache_real" --report "$out/eval_real_sparse_one_pass.json" > /dev/null
  miou() { sed -n 's/^ *"miou": \([-0-9.eE+]*\),$/\1/p' "$1" | awk '{ printf "%.1f", 100 * $1 }'; }
  real_miou="$(miou "$out/eval_real_sparse.json")% (one pass: $(miou "$out/eval_real_sparse_one_pass.json")%)"
  echo
  echo "real SemanticKITTI scan (never seen): Sparse Eval mIoU ${real_miou}"
else
  echo "no real labelled scan at $real/sequences/99 (set PILLARSEG_SHARED_DATA): real-data evaluation skipped"
fi

step "6/6 render points, observability, prediction and ground truth (the paper's Fig. 3 panels)"
for scan in 0 10 19; do
  "$bin" render --data "$data" --sequence 8 --scan "$scan" --weights "$run/checkpoint.safetensors" \
    --mode dense --mask-unobserved --cache "$cache" --out "$pictures/panels_08_$(printf %06d "$scan").png"
done
"$bin" infer --weights "$run/checkpoint.safetensors" --scan "$data/sequences/08/velodyne/000010.bin" \
  --out "$pictures/infer_08_000010" --probabilities

step "done"
echo "data:        $data"
echo "checkpoint:  $run/checkpoint.safetensors (metrics log: $run/metrics.jsonl)"
echo "curves:      $run/plots"
echo "evaluation:  $out/eval_sparse.json, $out/eval_dense.json"
if [[ -n "$real_miou" ]]; then
  echo "real scan:   $out/eval_real_sparse.json (real SemanticKITTI scan (never seen): Sparse Eval mIoU ${real_miou})"
fi
echo "pictures:    $pictures"
