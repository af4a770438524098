#!/usr/bin/env bash
# Data-parallel training on this machine (issue 13): one epoch of the demo's small CPU model
# (configs/small_cpu.yaml: 250 x 125 cells, batch 2) on simulated scans, as 1 process of R
# threads against R ranks of 1 thread (mpirun), the same global batch. Prints the steps per
# second of each (the epoch's steps over its training time, from metrics.jsonl) and their ratio,
# and the largest weight difference after the epoch (tests/mpi_train_test.sh says why they are
# not the same bits).
# Usage: bench/data_parallel.sh PILLARSEG_BINARY WORK_DIR [RANKS=2] [SCANS=40]
set -euo pipefail
bin=$(realpath "$1") work=$2 ranks=${3:-2} scans=${4:-40}
here=$(cd "$(dirname "$0")/.." && pwd)
command -v mpirun > /dev/null || { echo "data_parallel: no mpirun (Debian: openmpi-bin)"; exit 1; }
mkdir -p "$work" && cd "$work"
if [[ ! -d data/sequences/00 ]]; then
  "$bin" simulate --out data --sequences 1 --scans "$scans" --seed 1 > /dev/null
  "$bin" simulate --out data --sequences 1 --scans 4 --seed 2 --first-sequence 8 > /dev/null
fi
# One epoch, no precise BatchNorm (its forwards are not steps), sequence 00 only.
sed -e 's/^  epochs: .*/  epochs: 1/' -e 's/^  precise_bn_batches: .*/  precise_bn_batches: 0/' \
    -e 's/^  sequences: \[0, 1, 2, 3, 4, 5, 6, 7\]/  sequences: [0]/' -e 's/every_epochs: 4/every_epochs: 0/' "$here/configs/small_cpu.yaml" > bench.yaml
rate() {  # run_dir -> steps per second over the epoch's training (first step to last)
  python3 - "$1/metrics.jsonl" <<'PY'
import json, sys
steps = [json.loads(l) for l in open(sys.argv[1]) if '"type": "step"' in l]
print(f"{len(steps) / steps[-1]['elapsed_s']:.3f}")
PY
}
rm -rf single ranks
"$bin" --threads "$ranks" train --data data --config bench.yaml --out single --cache cache > single.log 2>&1
mpirun --allow-run-as-root --oversubscribe -np "$ranks" "$bin" --threads 1 train --data data --config bench.yaml \
  --out ranks --cache cache > ranks.log 2>&1
single=$(rate single) multi=$(rate ranks)
cpu=$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1)
echo "data-parallel training, small CPU model, one epoch of $(grep -c '"type": "step"' single/metrics.jsonl) steps (batch 2), $cpu, $(date -u +%F)"
echo "  1 process x $ranks threads: $single steps/s"
echo "  $ranks ranks x 1 thread:     $multi steps/s ($(python3 -c "print(f'{$multi / $single:.2f}')") x)"
python3 "$here/tests/support/compare_checkpoints.py" single/checkpoint.safetensors ranks/checkpoint.safetensors \
  --exclude optimizer | sed 's/^/  weights after the epoch: /'
