#!/usr/bin/env bash
# Data-parallel training on this machine (issue 13): one epoch of the demo's small CPU model
# (configs/small_cpu.yaml: 250 x 125 cells, batch 2) on simulated scans, as 1 process of R
# threads against R ranks of 1 thread (mpirun), the same global batch. Prints the steps per
# second of each (the epoch's steps over its training time, from metrics.jsonl) and their ratio,
# and the largest weight difference after the epoch (tests/mpi_train_test.sh says why they are
# not the same bits). The R ranks run twice: the gradients summed once after the backward
# (gradient_bucket_mb: 0) and in 256 KiB buckets begun during it (nine; the same bits; the small
# model's 4.16 MiB of gradients make only two buckets of the default 4 MiB).
# Usage: bench/data_parallel.sh PILLARSEG_BINARY WORK_DIR [RANKS=2] [SCANS=40]
# MPIRUN_ARGS: more mpirun options, e.g. "--mca btl tcp,self --mca btl_tcp_if_include lo" for
# the ranks to talk over TCP instead of shared memory.
set -euo pipefail
bin=$(realpath "$1") work=$2 ranks=${3:-2} scans=${4:-40}
here=$(cd "$(dirname "$0")/.." && pwd)
command -v mpirun > /dev/null || { echo "data_parallel: no mpirun (Debian: openmpi-bin)"; exit 1; }
mkdir -p "$work" && cd "$work"
if [[ ! -d data/sequences/00 ]]; then
  "$bin" simulate --out data --sequences 1 --scans "$scans" --seed 1 > /dev/null
  "$bin" simulate --out data --sequences 1 --scans 4 --seed 2 --first-sequence 8 > /dev/null
fi
# One epoch, no precise BatchNorm (its forwards are not steps) and so no weight averaging,
# sequence 00 only.
sed -e 's/^  epochs: .*/  epochs: 1/' -e 's/^  precise_bn_batches: .*/  precise_bn_batches: 0/' \
    -e 's/^  average_epochs: .*/  average_epochs: 0/' \
    -e 's/^  sequences: \[0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12\]/  sequences: [0]/' -e 's/every_epochs: 4/every_epochs: 0/' "$here/configs/small_cpu.yaml" > bench.yaml
sum_wait() {  # run_dir -> ms per step between the backward's end and the gradient sums' end
  python3 - "$1/metrics.jsonl" <<'PY'
import json, sys
lines = [json.loads(l) for l in open(sys.argv[1])]
steps = sum(1 for l in lines if l["type"] == "step")
print(f"{1000 * sum(l['gradient_sum_wait_s'] for l in lines if l['type'] == 'epoch') / steps:.2f}")
PY
}
rate() {  # run_dir -> steps per second over the epoch's training (first step to last)
  python3 - "$1/metrics.jsonl" <<'PY'
import json, sys
steps = [json.loads(l) for l in open(sys.argv[1]) if '"type": "step"' in l]
print(f"{len(steps) / steps[-1]['elapsed_s']:.3f}")
PY
}
sed -e 's/^  seed: \(.*\)/  seed: \1\n  gradient_bucket_mb: 0/' bench.yaml > after.yaml
sed -e 's/^  seed: \(.*\)/  seed: \1\n  gradient_bucket_mb: 0.25/' bench.yaml > buckets.yaml
grep -q "gradient_bucket_mb: 0.25" buckets.yaml || { echo "data_parallel: no train.seed in the config"; exit 1; }
rm -rf single ranks buckets
"$bin" --threads "$ranks" train --data data --config bench.yaml --out single --cache cache > single.log 2>&1
read -r -a extra <<< "${MPIRUN_ARGS:-}"
mpi=(mpirun --allow-run-as-root --oversubscribe "${extra[@]}" -np "$ranks" "$bin" --threads 1 train --data data
     --cache cache)
"${mpi[@]}" --config after.yaml --out ranks > ranks.log 2>&1
"${mpi[@]}" --config buckets.yaml --out buckets > buckets.log 2>&1
single=$(rate single) multi=$(rate ranks) bucketed=$(rate buckets)
cpu=$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1)
echo "data-parallel training, small CPU model, one epoch of $(grep -c '"type": "step"' single/metrics.jsonl) steps (batch 2), $cpu, $(date -u +%F)"
echo "  1 process x $ranks threads: $single steps/s"
echo "  $ranks ranks x 1 thread:     $multi steps/s ($(python3 -c "print(f'{$multi / $single:.2f}')") x), gradients summed after the backward (waited $(sum_wait ranks) ms a step for the sums)"
echo "  $ranks ranks x 1 thread:     $bucketed steps/s ($(python3 -c "print(f'{$bucketed / $single:.2f}')") x), in 256 KiB buckets during it (waited $(sum_wait buckets) ms a step after the backward)"
python3 "$here/tests/support/compare_checkpoints.py" ranks/checkpoint.safetensors buckets/checkpoint.safetensors \
  --max-abs 0 > /dev/null || { echo "data_parallel: the bucketed run's weights differ"; exit 1; }
python3 "$here/tests/support/compare_checkpoints.py" single/checkpoint.safetensors ranks/checkpoint.safetensors \
  --exclude optimizer | sed 's/^/  weights after the epoch, 1 process against R ranks: /'
# Without the conv biases in front of a BatchNorm and those BatchNorms' running means, whose
# gradients are rounding noise (tests/mpi_train_test.sh).
noise='double_conv\.[03]\.bias|double_conv\.[14]\.running_mean|occupancy\.(conv\.bias|norm\.running_mean)'
python3 "$here/tests/support/compare_checkpoints.py" single/checkpoint.safetensors ranks/checkpoint.safetensors \
  --exclude "optimizer|$noise" | sed 's/^/  the same without the noise tensors: /'
python3 - single/metrics.jsonl ranks/metrics.jsonl <<'PY'
import json, sys
a, b = ([json.loads(l)["loss"] for l in open(p) if '"type": "step"' in l] for p in sys.argv[1:])
print(f"  loss curves: largest relative difference {max(abs(x - y) / x for x, y in zip(a, b)):.2e} over {len(a)} steps "
      f"(first step {abs(a[0] - b[0]) / a[0]:.1e})")
PY
