#!/usr/bin/env bash
# make table1: every row of the paper's Table I on the simulator, at the small CPU size.
# Simulates a data set once (reused when present), trains the seven models of configs/table1/
# (an interrupted run resumes from its checkpoint, a finished one is skipped), evaluates each
# Sparse Train model on sparse and on dense ground truth and each Dense Train model on dense
# (11 rows from 7 trainings, as configs/table1/paper_table1.tsv lists them), and prints Table I
# with the paper's figures beside ours; the same goes to OUT_DIR/table1.md. At the defaults
# (make demo's data set and model, 16 epochs) about 35 minutes on 2 CPU cores (AMD EPYC Zen 4, 2026-12-02).
# Usage: scripts/table1.sh PILLARSEG_BINARY OUT_DIR
# Environment, for a quick run (a changed value needs a fresh OUT_DIR):
#   TABLE1_EPOCHS     train every model this many epochs instead of its config's
#   TABLE1_SCANS      scans per training sequence (8 sequences; default 15, as make demo)
#   TABLE1_VAL_SCANS  scans of the validation sequence 08 (default 20, as make demo)
set -euo pipefail
usage="usage: table1.sh PILLARSEG_BINARY OUT_DIR"
bin=${1:?$usage}
out=${2:?$usage}
here=$(cd "$(dirname "$0")/.." && pwd)
plan="$here/configs/table1/paper_table1.tsv"
format=(python3 "$here/scripts/table1_format.py")

fail() { echo "table1.sh: $*" >&2; exit 1; }
step() { printf '\n== %s\n' "$*"; }
count() { if (($1 == 1)); then echo "1 $2"; else echo "$1 $2s"; fi; }  # N WORD: "1 scan", "2 scans"
whole_number() {  # NAME VALUE: VALUE must be an integer >= 1
  [[ $2 =~ ^[1-9][0-9]*$ ]] || fail "$1 must be a whole number >= 1, got '$2'"
}

scans=${TABLE1_SCANS:-15} val_scans=${TABLE1_VAL_SCANS:-20} epochs=${TABLE1_EPOCHS:-}
whole_number TABLE1_SCANS "$scans"
whole_number TABLE1_VAL_SCANS "$val_scans"
[[ -z $epochs ]] || whole_number TABLE1_EPOCHS "$epochs"
[[ -x $bin ]] || fail "no pillarseg binary at '$bin' (make build first)"
command -v python3 >/dev/null || fail "python3 is needed to read the plan and format the table"

data="$out/data" cache="$out/cache" configs="$out/configs" runs="$out/runs" reports="$out/reports"
mkdir -p "$out" "$configs" "$runs" "$reports"
runs_text=$("${format[@]}" runs "$plan")
evals_text=$("${format[@]}" evals "$plan")
mapfile -t trainings <<< "$runs_text"
mapfile -t evaluations <<< "$evals_text"
((${#trainings[@]} > 0)) || fail "$plan lists no runs"

# The data set, described by the parameters it was simulated with: a rerun reuses it only if
# they are the same (the runs already trained on it would otherwise mix two data sets).
simulation="training: 8 sequences (00-07) of $scans scans, seed 1; validation: sequence 08 of $val_scans scans, seed 2"
stamp="$data/table1_simulation.txt"
if [[ -f $stamp ]]; then
  [[ $(cat "$stamp") == "$simulation" ]] ||
    fail "$data holds '$(cat "$stamp")', but TABLE1_SCANS/TABLE1_VAL_SCANS ask for '$simulation': use another OUT_DIR, or remove $out to start over"
  step "simulate: reusing $data ($simulation)"
else
  step "simulate: $simulation"
  rm -rf "$data"
  "$bin" simulate --out "$data" --sequences 8 --scans "$scans" --seed 1
  "$bin" simulate --out "$data" --sequences 1 --scans "$val_scans" --seed 2 --first-sequence 8
  echo "$simulation" > "$stamp"
fi

# The run configs as trained: configs/table1/RUN.yaml, with train.epochs replaced by
# TABLE1_EPOCHS when it is set. A copy changes only when its text does (the trainer resumes a
# run only with the config text it started with).
for run in "${trainings[@]}"; do
  source_config="$here/configs/table1/$run.yaml"
  [[ -f $source_config ]] || fail "$plan names run '$run', but there is no $source_config"
  if [[ -n $epochs ]]; then
    [[ $(grep -c '^  epochs: [0-9]*$' "$source_config") == 1 ]] ||
      fail "$source_config: expected one '  epochs: N' line under train: to apply TABLE1_EPOCHS to"
    sed "s/^  epochs: [0-9]*$/  epochs: $epochs/" "$source_config" > "$configs/$run.yaml.tmp"
  else
    cp "$source_config" "$configs/$run.yaml.tmp"
  fi
  if cmp -s "$configs/$run.yaml.tmp" "$configs/$run.yaml"; then
    rm "$configs/$run.yaml.tmp"
  else
    mv "$configs/$run.yaml.tmp" "$configs/$run.yaml"
  fi
done

n=0
for run in "${trainings[@]}"; do
  n=$((n + 1))
  config="$configs/$run.yaml" dir="$runs/$run"
  if [[ -f $dir/checkpoint.safetensors ]] && ! cmp -s "$dir/config.yaml" "$config"; then
    fail "$dir was trained with another config than $config (TABLE1_EPOCHS changed, or configs/table1/$run.yaml did): remove $dir to retrain it, or use another OUT_DIR"
  fi
  if [[ -f $dir/finished && -f $dir/checkpoint.safetensors ]]; then
    step "train $n/${#trainings[@]} $run: finished before, skipped ($dir)"
    continue
  fi
  if [[ -f $dir/checkpoint.safetensors ]]; then
    step "train $n/${#trainings[@]} $run: resuming $dir"
    "$bin" train --data "$data" --config "$config" --out "$dir" --cache "$cache" --resume
  else
    step "train $n/${#trainings[@]} $run"
    "$bin" train --data "$data" --config "$config" --out "$dir" --cache "$cache"
  fi
  date -u +%FT%TZ > "$dir/finished"
done

n=0
for evaluation in "${evaluations[@]}"; do
  n=$((n + 1))
  read -r run mode <<< "$evaluation"
  weights="$runs/$run/checkpoint.safetensors" report="$reports/$run.$mode.json"
  if [[ $report -nt $weights ]]; then
    step "evaluate $n/${#evaluations[@]} $run on $mode ground truth: done before ($report)"
    continue
  fi
  step "evaluate $n/${#evaluations[@]} $run on $mode ground truth (sequence 08)"
  "$bin" eval --data "$data" --weights "$weights" --mode "$mode" --cache "$cache" --report "$report"
done

step "Table I"
"${format[@]}" table "$plan" --reports "$reports" --runs "$runs" \
  --data-note "8 training sequences of $(count "$scans" scan), validation sequence 08 of $(count "$val_scans" scan)" \
  > "$out/table1.md.tmp"
mv "$out/table1.md.tmp" "$out/table1.md"
echo
cat "$out/table1.md"
echo
echo "table: $out/table1.md (reports: $reports, runs: $runs)"
