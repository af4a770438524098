#!/usr/bin/env bash
# Data-parallel training (DESIGN.md section 8): `mpirun -np 2 pillarseg --threads 1 train` against
# one process of 2 threads on the same global batch (4 scans: 2 per rank), tiny model with the 2D
# occupancy stream, dense ground truth, precise BatchNorm and validation every epoch.
#
# Why not bit for bit: the replicas' sums of float gradients (and the loss coefficients scaled by
# each share of the labelled cells) are added in another order than one process's sums over the
# whole batch, so values differ by float rounding, ~1e-7 relative. The tolerances follow:
# - one step: the first loss to 1e-6 relative (same weights; BatchNorm statistics are summed in
#   double); Adam's first moment (0.1 x the summed gradient) and every weight to 1e-5 relative
#   per tensor (measured ~1e-6), except the conv biases in front of a BatchNorm and those
#   BatchNorms' running means: such a bias has a true gradient of 0 (the BatchNorm takes the mean
#   out), so its computed gradient is rounding noise whose sign Adam's first step turns into
#   +-lr; they may differ by up to 2 lr (lr = 3e-3 here).
# - three epochs: Adam keeps amplifying that noise, so the curves are compared at 1e-4 relative
#   per step (measured ~1e-5).
# The same one-step check on --device emu (the CUDA backend's kernels on the emulation: their
# BatchNorm statistics combined over the ranks on the host, the gradients summed through it).
# The Lovász term (train.loss ce+lovasz) on 2 ranks: each rank's term over its own share,
# weighted 1/2. Exact: two 2-rank runs give the same bytes (the sums' order never depends on timing), and so do
# gradients summed in many small buckets during the backward and in one after it; each
# step is logged once, best.safetensors and the eval lines exist; a rank that fails stops all
# ranks with its message; a batch that does not split over the ranks is refused.
set -euo pipefail
bin=$(realpath "$1") work=$2 mpirun=$3
here=$(cd "$(dirname "$0")" && pwd)
mpi=("$mpirun" --allow-run-as-root --oversubscribe)
# Under AddressSanitizer (make asan) OpenMPI's plugins, unloaded at exit, leave allocations
# LeakSanitizer cannot attribute: no leak check for these runs.
export ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_leaks=0"
compare=(python3 "$here/support/compare_checkpoints.py")
source "$here/support/tiny_run_config.sh"
fail() { echo "FAIL: $*" >&2; exit 1; }
rm -rf "$work" && mkdir -p "$work" && cd "$work"

"$bin" simulate --out data --sequences 1 --scans 8 --seed 5 --points-per-scan 30000 > /dev/null
"$bin" simulate --out data --sequences 1 --scans 3 --seed 5 --first-sequence 8 --points-per-scan 30000 > /dev/null
write_config() {  # epochs scans_per_sequence [TRAIN_LINE ...]
  tiny_run_config dense "$1" 4 "precise_bn_batches: 2" "max_scans_per_sequence: $2" "${@:3}"
}
write_config 1 4 > one_step.yaml
write_config 3 8 > three_epochs.yaml
losses() { grep '"type": "step"' "$1/metrics.jsonl" | sed -E 's/.*"loss": ([0-9.eE+-]+).*/\1/'; }
# Relative agreement of two loss columns: max |a - b| / |a| <= limit.
same_losses() {  # run_a run_b limit
  python3 - "$(losses "$1")" "$(losses "$2")" "$3" <<'PY' || fail "loss curves of $1 and $2 differ beyond $3"
import sys
a, b, limit = [float(x) for x in sys.argv[1].split()], [float(x) for x in sys.argv[2].split()], float(sys.argv[3])
assert len(a) == len(b) and a, f"{len(a)} against {len(b)} steps"
worst = max(abs(x - y) / abs(x) for x, y in zip(a, b))
print(f"{len(a)} steps, largest relative loss difference {worst:.2e} (limit {limit:g})")
sys.exit(0 if worst <= limit else 1)
PY
}
noise='double_conv\.[03]\.bias|double_conv\.[14]\.running_mean|occupancy\.(conv\.bias|norm\.running_mean)'

echo "== one step: 1 process x 2 threads against 2 ranks x 1 thread"
"$bin" --threads 2 train --data data --config one_step.yaml --out single1 --cache cache > /dev/null 2>&1
"${mpi[@]}" -np 2 "$bin" --threads 1 train --data data --config one_step.yaml --out ranks1 --cache cache > /dev/null 2>&1 ||
  fail "mpirun -np 2 train failed"
same_losses single1 ranks1 1e-6
"${compare[@]}" single1/checkpoint.safetensors ranks1/checkpoint.safetensors --only optimizer.exp_avg --exclude exp_avg_sq \
  --max-rel 1e-5 || fail "the summed gradients differ"
"${compare[@]}" single1/checkpoint.safetensors ranks1/checkpoint.safetensors --exclude "optimizer|$noise" --max-rel 1e-5 ||
  fail "the weights after one step differ"
"${compare[@]}" single1/checkpoint.safetensors ranks1/checkpoint.safetensors --exclude "optimizer" --max-abs 6e-3 ||
  fail "a weight moved by more than 2 lr"

echo "== the Lovász term on 2 ranks: each rank ranks its share, its term weighted 1/2"
# The first step's loss is the cross-entropy of the global batch plus the mean of the ranks' two
# terms, each in [0, 1]: without the weight it would be their sum (~1.7 at the start).
sed 's/^  loss: ce$/  loss: ce+lovasz/' one_step.yaml > one_step_lovasz.yaml
grep -q "loss: ce+lovasz" one_step_lovasz.yaml || fail "one_step_lovasz.yaml holds no ce+lovasz"
"${mpi[@]}" -np 2 "$bin" --threads 1 train --data data --config one_step_lovasz.yaml --out ranks1_lovasz --cache cache \
  > lovasz.log 2>&1 || { cat lovasz.log; fail "mpirun -np 2 train with ce+lovasz failed"; }
python3 - "$(losses ranks1 | head -1)" "$(losses ranks1_lovasz | head -1)" <<'PY' || fail "the 2-rank Lovász term is not in (0.05, 1]"
import sys
ce, both = float(sys.argv[1]), float(sys.argv[2])
print(f"first step: cross-entropy {ce:.4f}, with the Lovász term {both:.4f}")
sys.exit(0 if 0.05 < both - ce <= 1.0 + 1e-6 else 1)
PY

echo "== one step on the CUDA backend (on the emulation): synchronised BatchNorm in the kernels"
"$bin" --threads 2 train --device emu --data data --config one_step.yaml --out emu_single1 --cache cache > /dev/null 2>&1
"${mpi[@]}" -np 2 "$bin" --threads 1 train --device emu --data data --config one_step.yaml --out emu_ranks1 --cache cache \
  > emu.log 2>&1 || { cat emu.log; fail "mpirun -np 2 train --device emu failed"; }
same_losses emu_single1 emu_ranks1 1e-6
"${compare[@]}" emu_single1/checkpoint.safetensors emu_ranks1/checkpoint.safetensors --only optimizer.exp_avg \
  --exclude exp_avg_sq --max-rel 1e-5 || fail "the summed gradients differ (emu)"
"${compare[@]}" emu_single1/checkpoint.safetensors emu_ranks1/checkpoint.safetensors --exclude "optimizer|$noise" \
  --max-rel 1e-5 || fail "the weights after one step differ (emu)"

echo "== three epochs with validation"
"$bin" --threads 2 train --data data --config three_epochs.yaml --out single3 --cache cache > /dev/null 2>&1
"${mpi[@]}" -np 2 "$bin" --threads 1 train --data data --config three_epochs.yaml --out ranks3 --cache cache > ranks3.log 2>&1 ||
  { cat ranks3.log; fail "mpirun -np 2 train (three epochs) failed"; }
same_losses single3 ranks3 1e-4
[[ $(grep -c '"type": "step"' ranks3/metrics.jsonl) == 6 && $(grep -c '"type": "eval"' ranks3/metrics.jsonl) == 3 ]] ||
  fail "ranks3/metrics.jsonl should hold 6 step lines and 3 eval lines (rank 0 alone writes it)"
[[ -f ranks3/best.safetensors && -f ranks3/events.out.tfevents.0.pillarseg ]] || fail "no best checkpoint or event file"
grep -q "on each of 2 ranks (2 scans of every batch each)" ranks3.log || fail "the run does not say it is data-parallel"
# The validation's confusion matrices add up over the ranks' shares of the 3 eval scans.
a=$(grep '"type": "eval"' single3/metrics.jsonl | sed -E 's/.*"labelled_cells": ([0-9]+).*/\1/' | tr '\n' ' ')
b=$(grep '"type": "eval"' ranks3/metrics.jsonl | sed -E 's/.*"labelled_cells": ([0-9]+).*/\1/' | tr '\n' ' ')
[[ "$a" == "$b" ]] || fail "validation scored $b labelled cells on 2 ranks, $a in one process"

echo "== the same 2-rank run again: the same bytes"
"${mpi[@]}" -np 2 "$bin" --threads 1 train --data data --config three_epochs.yaml --out ranks3b --cache cache > /dev/null 2>&1
cmp ranks3/checkpoint.safetensors ranks3b/checkpoint.safetensors || fail "two 2-rank runs differ"
cmp ranks3/best.safetensors ranks3b/best.safetensors || fail "two 2-rank runs' best checkpoints differ"

echo "== the gradients summed in buckets during the backward: the same bytes as one sum after it"
# Buckets of at least 52 floats (0.0002 MiB) cut the tiny model's gradients into 11, one per
# convolution weight with the small tensors next to it, each begun as soon as the backward has
# finished it (three_epochs.yaml's default of 4 MiB holds them all: one sum after the backward).
# A bucket begun before its last write would send gradients that later change.
write_config 3 8 "gradient_bucket_mb: 0.0002" > buckets.yaml
"${mpi[@]}" -np 2 "$bin" --threads 1 train --data data --config buckets.yaml --out ranks3_buckets --cache cache \
  > buckets.log 2>&1 || { cat buckets.log; fail "mpirun -np 2 train (small buckets) failed"; }
grep -q "summed over the 2 ranks in 11 buckets of at least 0.0002 MiB" buckets.log ||
  { cat buckets.log; fail "the run does not say it sums in buckets"; }
grep -q "summed over the 2 ranks in 1 bucket after the backward" ranks3.log || fail "ranks3 should sum once"
"${compare[@]}" ranks3/checkpoint.safetensors ranks3_buckets/checkpoint.safetensors --max-abs 0 ||
  fail "summing in buckets changed the weights"
write_config 1 4 "gradient_bucket_mb: 0.0002" > one_step_buckets.yaml
"${mpi[@]}" -np 2 "$bin" --threads 1 train --device emu --data data --config one_step_buckets.yaml \
  --out emu_ranks1_buckets --cache cache > emu_buckets.log 2>&1 || { cat emu_buckets.log; fail "emu buckets failed"; }
"${compare[@]}" emu_ranks1/checkpoint.safetensors emu_ranks1_buckets/checkpoint.safetensors --max-abs 0 ||
  fail "summing in buckets changed the weights (emu)"

echo "== a global batch that does not split over 3 ranks"
if "${mpi[@]}" -np 3 "$bin" --threads 1 train --data data --config three_epochs.yaml --out ranks_odd --cache cache \
  > odd.log 2>&1; then fail "batch 4 on 3 ranks was accepted"; fi
grep -q "batch_size 4 is the global batch and must be a multiple of the 3 ranks" odd.log || { cat odd.log; fail "no clear message"; }
[[ ! -e ranks_odd/checkpoint.safetensors ]] || fail "a refused run wrote a checkpoint"

echo "== a rank that fails stops all ranks with its message"
cp -r data bad_data
truncate -s 1001 bad_data/sequences/00/velodyne/000005.bin  # not a whole number of points
start=$(date +%s)
if timeout 120 "${mpi[@]}" -np 2 "$bin" --threads 1 train --data bad_data --config three_epochs.yaml --out ranks_bad \
  --cache bad_cache > bad.log 2>&1; then fail "training on a damaged scan succeeded"; fi
(( $(date +%s) - start < 100 )) || fail "the ranks did not stop (timeout)"
grep -q "000005.bin" bad.log || { cat bad.log; fail "the failing rank's message does not name the file"; }
echo "mpi_train: all checks passed"
