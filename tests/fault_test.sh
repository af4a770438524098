#!/usr/bin/env bash
# Fault tests (DESIGN.md section 9): what a killed process, two writers at once and a full file
# system leave behind. The kills are SIGKILL at named points (PILLARSEG_FAULT, core/fault.hpp)
# and at times; a killed run is resumed with the same command and must end with the checkpoint
# and best checkpoint an uninterrupted run writes, byte for byte, and logs (metrics.jsonl, the
# TensorBoard events) with each step once and the same values.
#
# Usage: tests/fault_test.sh BIN WORK MODE [MPIRUN]
#   train      kills inside a step, inside the checkpoint and best-checkpoint writes, inside the
#              first checkpoint write (resume then starts the run), two kills in a row, kills at
#              three times; with MPIRUN, a rank killed inside a step and rank 0 inside the
#              checkpoint write under `mpirun -np 2`
#   gt         `pillarseg gt` killed inside a cache write and rerun; damaged entries (cut short,
#              a flipped payload byte, another key) recomputed; two gt processes on one cache at
#              once, and one of two held at its first write and killed while the other runs:
#              the cache ends byte-identical to one clean gt's
#   disk-full  a run directory and a cache on a small tmpfs (a mount namespace of its own:
#              unshare; exit 77, skipped, where neither root nor user namespaces allow it):
#              writes to a full file system fail naming the file and "no space", the previous
#              checkpoint and cache entries stay as they were, and the run resumes once there is
#              space
set -euo pipefail
bin=$(realpath "$1") work=$2 mode=$3 mpirun=${4:-}
here=$(cd "$(dirname "$0")" && pwd)
logs=(python3 "$here/support/run_logs.py")
source "$here/support/tiny_run_config.sh"
fail() { echo "FAIL: $*" >&2; exit 1; }

if [[ $mode == disk-full && -z ${PILLARSEG_FAULT_IN_NAMESPACE:-} ]]; then
  # A mount namespace of our own for the tmpfs: as root directly, else as a user namespace's root.
  for how in "unshare --mount --propagation private" "unshare --user --map-root-user --mount"; do
    if $how true 2> /dev/null; then
      PILLARSEG_FAULT_IN_NAMESPACE=1 exec $how "$0" "$@"
    fi
  done
  echo "SKIP: cannot make a mount namespace for a tmpfs (not root, no user namespaces)"
  exit 77
fi

rm -rf "$work" && mkdir -p "$work" && cd "$work"
"$bin" simulate --out data --sequences 1 --scans 6 --seed 7 --points-per-scan 30000 > /dev/null
"$bin" simulate --out data --sequences 1 --scans 2 --seed 7 --first-sequence 8 --points-per-scan 30000 > /dev/null
# 3 epochs of 3 steps (batch 2 of 6 scans), validation and best.safetensors every epoch.
tiny_run_config sparse 3 2 > run.yaml

train() {  # RUN [--resume]: one process, one thread (the same bits every run)
  local run=$1
  shift
  "$bin" --threads 1 train --data data --config run.yaml --out "$run" --cache cache "$@"
}
# RUN against the reference REF: checkpoints byte-identical, each step logged once with the same
# values, the same TensorBoard scalars, no temporary file left.
same_run() {
  local run=$1 ref=$2 what=$3
  cmp -s "$run/checkpoint.safetensors" "$ref/checkpoint.safetensors" || fail "$what: the final checkpoint differs"
  cmp -s "$run/best.safetensors" "$ref/best.safetensors" || fail "$what: best.safetensors differs"
  diff <("${logs[@]}" metrics "$run/metrics.jsonl") <("${logs[@]}" metrics "$ref/metrics.jsonl") > /dev/null ||
    fail "$what: metrics.jsonl differs from the uninterrupted run's (a step twice, or missing?)"
  diff <("${logs[@]}" events "$run/events.out.tfevents.0.pillarseg") \
       <("${logs[@]}" events "$ref/events.out.tfevents.0.pillarseg") > /dev/null ||
    fail "$what: the TensorBoard scalars differ from the uninterrupted run's"
  if find "$run" -name '*.tmp-*' | grep -q .; then fail "$what: temporary files left: $(find "$run" -name '*.tmp-*')"; fi
  echo "ok: $what"
}
# Runs "$@" with PILLARSEG_FAULT=$1 and checks that it died of SIGKILL at that point.
killed_at() {
  local point=$1
  shift
  local rc=0
  PILLARSEG_FAULT=$point "$@" > /dev/null 2> fault.log || rc=$?
  ((rc == 137)) || { cat fault.log >&2; fail "PILLARSEG_FAULT=$point: expected a SIGKILL (exit 137), got $rc"; }
  grep -q "PILLARSEG_FAULT: killing process" fault.log || fail "PILLARSEG_FAULT=$point: no kill message"
}
tree_digest() { (cd "$1" && find . -type f ! -name '*.tmp-*' -print0 | sort -z | xargs -0 -r sha1sum); }

case $mode in
train)
  train ref > /dev/null 2>&1 || fail "the uninterrupted run failed"
  grep -c '"type": "step"' ref/metrics.jsonl | grep -qx 9 || fail "the reference run did not log 9 steps"
  # How many times the run wrote best.safetensors: the eval lines whose epoch is the best epoch.
  bests() { grep -cE '"type": "eval", "epoch": ([0-9]+),.*"best_epoch": \1,' "$1/metrics.jsonl"; }
  n_best=$(bests ref)

  # Each named point: kill there, resume with the same command.
  for point in step:5 step:9 write:checkpoint.safetensors:1 write:checkpoint.safetensors:2 \
               write:best.safetensors:1 "write:best.safetensors:$n_best" "write:*:4"; do
    run=killed_${point//[:*]/_}
    killed_at "$point" train "$run"
    train "$run" --resume > /dev/null 2>&1 || fail "resume after $point failed"
    same_run "$run" ref "killed at $point, resumed"
  done
  killed_at step:2 train chain
  killed_at step:5 train chain --resume
  killed_at write:checkpoint.safetensors:1 train chain --resume
  train chain --resume > /dev/null 2>&1 || fail "resume after three kills failed"
  same_run chain ref "killed three times, resumed"
  grep -c '"type": "step"' chain/metrics.jsonl | grep -qx 9 || fail "chain: not 9 step lines"

  # Kills at times: a third, half and four fifths of the uninterrupted run's wall time.
  start=$(date +%s.%N)
  train timing_ref > /dev/null 2>&1
  wall=$(awk -v a="$start" -v b="$(date +%s.%N)" 'BEGIN { print b - a }')
  for fraction in 0.33 0.5 0.8; do
    run=timed_$fraction
    rc=0
    timeout -s KILL "$(awk -v w="$wall" -v f="$fraction" 'BEGIN { printf "%.2f", w * f }')" "$bin" --threads 1 train --data data --config run.yaml \
      --out "$run" --cache cache > /dev/null 2>&1 || rc=$?
    ((rc == 137 || rc == 0)) || fail "timed run $fraction: exit $rc"
    train "$run" --resume > /dev/null 2>&1 || fail "resume of the run killed at $fraction of its time failed"
    same_run "$run" ref "killed at ${fraction} of the run's time (exit $rc), resumed"
  done

  if [[ -n $mpirun ]]; then
    # Under AddressSanitizer (make asan) OpenMPI's plugins, unloaded at exit, leave allocations
    # LeakSanitizer cannot attribute: no leak check for the MPI runs (every other run keeps it).
    export ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_leaks=0"
    mpi=("$mpirun" --allow-run-as-root --oversubscribe -np 2 "$bin" --threads 1 train --data data --config run.yaml
         --cache cache)
    "${mpi[@]}" --out mpi_ref > /dev/null 2>&1 || fail "the uninterrupted 2-rank run failed"
    for point in step:4@1 write:checkpoint.safetensors:2@0 "write:best.safetensors:$(bests mpi_ref)@0"; do
      run=mpi_${point//[:*@]/_}
      rc=0
      PILLARSEG_FAULT=$point "${mpi[@]}" --out "$run" > /dev/null 2> fault.log || rc=$?
      ((rc != 0)) || fail "mpirun with PILLARSEG_FAULT=$point succeeded"
      grep -q "PILLARSEG_FAULT: killing process" fault.log || fail "mpirun with PILLARSEG_FAULT=$point: no kill"
      if pgrep -f -- "--out $run" > /dev/null; then fail "a rank of the killed run $run is still running"; fi
      "${mpi[@]}" --out "$run" --resume > /dev/null 2>&1 || fail "the 2-rank resume after $point failed"
      same_run "$run" mpi_ref "2 ranks, killed at $point (mpirun exit $rc), resumed"
    done
  fi
  ;;

gt)
  gt() { "$bin" --threads 1 gt --data data --sequence 0 --mode dense --cache "$1"; }
  gt ref_cache > /dev/null 2>&1 || fail "gt failed"
  ref=$(tree_digest ref_cache)
  entries=$(find ref_cache -name '*.psc' | wc -l)
  ((entries >= 12)) || fail "the reference cache holds $entries entries"

  for hit in 1 5 11; do
    killed_at "write:*:$hit" gt killed_$hit
    gt killed_$hit > /dev/null 2>&1 || fail "gt after a kill at cache write $hit failed"
    [[ $(tree_digest killed_$hit) == "$ref" ]] || fail "gt killed at write $hit and rerun: the cache differs"
    if find killed_$hit -name '*.tmp-*' | grep -q .; then fail "gt killed at write $hit: temporaries left after the rerun"; fi
    echo "ok: gt killed at cache write $hit, rerun"
  done

  # Damaged entries: cut short, a payload byte flipped, the header's key changed. Each is a miss
  # (never trusted), recomputed and rewritten.
  cp -r ref_cache damaged
  mapfile -t victims < <(find damaged -path '*/gt-dense/*.psc' | sort | head -3)
  truncate -s 100 "${victims[0]}"
  python3 - "${victims[1]}" "${victims[2]}" <<'PY'
import sys
flip, other_key = sys.argv[1], sys.argv[2]
data = bytearray(open(flip, "rb").read())
data[-1] ^= 0x40
open(flip, "wb").write(data)
data = bytearray(open(other_key, "rb").read())
data[data.index(b"frame=") + 6] ^= 0x01
open(other_key, "wb").write(data)
PY
  out=$(gt damaged 2>&1) || fail "gt on damaged entries failed: $out"
  grep -q "computed 3, already cached $((6 - 3))" <<< "$out" || fail "gt did not recompute the 3 damaged maps: $out"
  [[ $(tree_digest damaged) == "$ref" ]] || fail "the damaged entries were not rewritten"
  echo "ok: damaged entries recomputed ($(grep -o 'computed [0-9]*, already cached [0-9]*' <<< "$out"))"

  # Two processes on one cache directory at once.
  gt shared > a.log 2>&1 & a=$!
  gt shared > b.log 2>&1 & b=$!
  wait $a || fail "the first of two concurrent gt failed: $(cat a.log)"
  wait $b || fail "the second of two concurrent gt failed: $(cat b.log)"
  [[ $(tree_digest shared) == "$ref" ]] || fail "two concurrent gt: the cache differs"
  if find shared -name '*.tmp-*' | grep -q .; then fail "two concurrent gt: temporaries left"; fi
  echo "ok: two gt processes on one cache"
  # One of two killed while the other runs: the survivor's entries are complete; a rerun removes
  # what the killed one left. The one to be killed is held (SIGSTOP) at its first write, with bytes
  # of that entry on disk, while the other runs through the whole cache; then it is killed. (Started
  # together, the second could write every entry before the first wrote any.)
  PILLARSEG_FAULT_STOP=1 PILLARSEG_FAULT="write:*:1" "$bin" --threads 1 gt --data data --sequence 0 \
    --mode dense --cache shared_kill > a.log 2>&1 & a=$!
  state=
  for ((i = 0; i < 600; ++i)); do
    state=$(awk '{print $3}' "/proc/$a/stat" 2> /dev/null) || break
    [[ $state == T ]] && break
    sleep 0.1
  done
  [[ $state == T ]] || fail "the gt to be held did not stop at its first write: $(cat a.log)"
  find shared_kill -name '*.tmp-*' | grep -q . || fail "the held gt left no partial entry on disk"
  gt shared_kill > b.log 2>&1 || fail "the surviving gt failed: $(cat b.log)"
  kill -KILL "$a"
  rc=0
  wait "$a" 2> /dev/null || rc=$?
  ((rc == 137)) || fail "the held gt, killed, exited $rc"
  [[ $(tree_digest shared_kill) == "$ref" ]] || fail "one of two gt killed: the cache differs"
  gt shared_kill > /dev/null 2>&1
  if find shared_kill -name '*.tmp-*' | grep -q .; then fail "the rerun left the killed gt's temporaries"; fi
  echo "ok: one of two gt processes killed"
  ;;

disk-full)
  train ref > /dev/null 2>&1 || fail "the uninterrupted run failed"
  mkdir fs
  mount -t tmpfs -o size=8m tmpfs fs || { echo "SKIP: cannot mount a tmpfs here"; exit 77; }
  trap 'umount fs 2> /dev/null || true' EXIT
  fill() {  # leave about $1 KiB free on fs
    rm -f fs/filler
    local free_kib
    free_kib=$(df -k --output=avail fs | tail -1)
    if ((free_kib > $1)); then
      fallocate -l $(((free_kib - $1) * 1024)) fs/filler 2> /dev/null ||
        dd if=/dev/zero of=fs/filler bs=1k count=$((free_kib - $1)) 2> /dev/null || true
    fi
  }
  expect_no_space() {  # WHAT FILE LOG: a non-zero exit whose message names FILE and says "no space"
    grep -qi "no space" "$3" || { cat "$3" >&2; fail "$1: the message does not say 'no space'"; }
    grep -q "$2" "$3" || { cat "$3" >&2; fail "$1: the message does not name $2"; }
    echo "ok: $1: $(grep -i 'error' "$3" | head -1)"
  }
  ckpt_kib=$(( $(stat -c %s ref/checkpoint.safetensors) / 1024 ))

  # One epoch fits; then the file system is full.
  train fs/run --epochs-now 1 > /dev/null 2>&1 || fail "the first epoch on the tmpfs failed"
  cp fs/run/checkpoint.safetensors epoch1.safetensors
  cp fs/run/metrics.jsonl epoch1.jsonl
  fill 0
  rc=0
  train fs/run --resume > full.log 2>&1 || rc=$?
  ((rc != 0)) || fail "training on a full file system succeeded"
  expect_no_space "resume on a full file system" "fs/run/metrics.jsonl" full.log
  cmp -s fs/run/checkpoint.safetensors epoch1.safetensors || fail "the full file system changed the checkpoint"
  cmp -s fs/run/metrics.jsonl epoch1.jsonl || fail "the full file system changed metrics.jsonl"
  # Room for the logs, not for the next checkpoint.
  fill $((ckpt_kib / 2))
  rc=0
  train fs/run --resume > half.log 2>&1 || rc=$?
  ((rc != 0)) || fail "training without room for its checkpoint succeeded"
  expect_no_space "a checkpoint on a full file system" "safetensors" half.log
  cmp -s fs/run/checkpoint.safetensors epoch1.safetensors || fail "the failed write changed the checkpoint"
  if find fs/run -name '*.tmp-*' | grep -q .; then fail "a failed write left its temporary file"; fi
  rm -f fs/filler
  train fs/run --resume > /dev/null 2>&1 || fail "resume once there is space failed"
  same_run fs/run ref "full file system, then resumed"

  # The ground-truth cache: sparse entries fit, then dense ones find the file system full.
  rm -rf fs/run
  "$bin" --threads 1 gt --data data --sequence 0 --mode sparse --cache fs/cache > /dev/null 2>&1 ||
    fail "gt sparse on the tmpfs failed"
  before=$(tree_digest fs/cache)
  fill 0
  rc=0
  "$bin" --threads 1 gt --data data --sequence 0 --mode dense --cache fs/cache > gt_full.log 2>&1 || rc=$?
  ((rc != 0)) || fail "gt on a full file system succeeded"
  expect_no_space "gt on a full file system" ".psc" gt_full.log
  [[ $(tree_digest fs/cache) == "$before" ]] || fail "the full file system changed the cached entries"
  if find fs/cache -name '*.tmp-*' | grep -q .; then fail "gt on a full file system left temporaries"; fi
  ;;
*)
  fail "mode '$mode': expected train, gt or disk-full"
  ;;
esac
echo "fault test $mode: passed"
