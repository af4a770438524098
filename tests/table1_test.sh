#!/usr/bin/env bash
# make table1 at its smallest (scripts/table1.sh): 1 epoch, 2 scans per training sequence and 2
# validation scans (with 1 scan a sequence's dense ground truth would be its sparse one), still all
# 7 trainings and 11 evaluations. Checks that the table has Table I's
# 11 rows in the paper's order with the paper's figures beside ours (configs/table1/
# paper_table1.tsv), that our cells are the JSON reports' IoUs, that OUT_DIR/table1.md holds
# the printed table, that a rerun trains and evaluates nothing again, that a run without its end
# mark resumes, and that a bad knob, a changed data size or a changed config is refused with a
# message naming it.
# Usage: tests/table1_test.sh PILLARSEG_BINARY WORK_DIR
set -euo pipefail
bin=$(realpath "$1") work=$2
here=$(cd "$(dirname "$0")/.." && pwd)
table1="$here/scripts/table1.sh"
fail() { echo "FAIL: $*" >&2; exit 1; }
rm -rf "$work" && mkdir -p "$work"
out="$work/out"
quick=(env TABLE1_EPOCHS=1 TABLE1_SCANS=2 TABLE1_VAL_SCANS=2)

"${quick[@]}" "$table1" "$bin" "$out" > "$work/first.log" 2>&1 ||
  { tail -30 "$work/first.log"; fail "the quick table1.sh run failed (log: $work/first.log)"; }
md="$out/table1.md"
[[ -f $md ]] || fail "no $md"
[[ ! -e $md.tmp ]] || fail "$md.tmp left behind"
grep -qF "$(cat "$md")" "$work/first.log" || fail "the printed table differs from $md"
grep -q "^Simulated data at the small CPU size" "$md" || fail "$md does not say what it is"

# 11 data rows, in the paper's order, each with the paper's mIoU and terrain IoU beside ours.
mapfile -t rows < <(grep -E '^\| (Sparse|Dense) Train / (Sparse|Dense) Eval \|' "$md")
((${#rows[@]} == 11)) || fail "expected 11 data rows in $md, found ${#rows[@]}"
i=0
while IFS=$'\t' read -r _ _ mode method _ miou rest; do
  terrain=${rest##*$'\t'}
  row=${rows[i]}
  [[ $row == "| $mode | $method | "* ]] || fail "row $((i + 1)) should be '$mode | $method': $row"
  [[ $row == *" ($miou) |"* && $row == *" ($terrain) |" ]] ||
    fail "row $((i + 1)) ($mode, $method) lacks the paper's mIoU ($miou) or terrain ($terrain): $row"
  i=$((i + 1))
done < <(grep -v '^#' "$here/configs/table1/paper_table1.tsv" | tail -n +2)
((i == 11)) || fail "paper_table1.tsv has $i rows, expected 11"
[[ ${rows[1]} == "| Sparse Train / Sparse Eval | Pillar | **"*"** (55.1) |"* ]] ||
  fail "Pillar, Sparse Train / Sparse Eval: no '(55.1)' beside our mIoU: ${rows[1]}"

# Dense Eval scores the dense ground truth: more labelled cells than the sparse one.
cells() { python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["labelled_cells"])' "$1"; }
sparse_cells=$(cells "$out/reports/pillar_sparse.sparse.json") dense_cells=$(cells "$out/reports/pillar_sparse.dense.json")
((dense_cells > sparse_cells)) || fail "dense eval labelled $dense_cells cells, sparse eval $sparse_cells: expected more"

# Our cells are the reports' figures: Pillar + 3D Occupancy, Sparse Train / Dense Eval (row 8).
expected=$(python3 - "$out/reports/pillar_3d_sparse.dense.json" <<'EOF'
import json, math, sys
r = json.load(open(sys.argv[1]))
pct = lambda v: "n/a" if v is None or math.isnan(v) else f"{100 * v:.1f}"
names = ["vehicle", "person", "two-wheel", "rider", "road", "sidewalk", "other-ground",
         "building", "object", "vegetation", "trunk", "terrain"]
print(" ".join([pct(r["miou"])] + [pct(r["iou"][c]) for c in names]))
EOF
)
got=$(sed -E 's/ \([0-9.]+\) \|/ |/g; s/\*\*//g' <<< "${rows[7]}" | cut -d'|' -f4-16 | tr -s ' |' ' ' | sed 's/^ //; s/ $//')
[[ $got == "$expected" ]] || fail "row 8's figures '$got' are not the report's '$expected'"

# A rerun trains and evaluates nothing again, and prints the same table.
"${quick[@]}" "$table1" "$bin" "$out" > "$work/rerun.log" 2>&1 ||
  { tail -30 "$work/rerun.log"; fail "the rerun failed"; }
skipped=$(grep -c '^== train .*: finished before, skipped' "$work/rerun.log" || true)
reused=$(grep -c '^== evaluate .*: done before' "$work/rerun.log" || true)
((skipped == 7 && reused == 11)) || fail "the rerun skipped $skipped trainings and $reused evaluations, expected 7 and 11"
! grep -q 'training on' "$work/rerun.log" || fail "the rerun trained again"
grep -qF "$(cat "$md")" "$work/rerun.log" || fail "the rerun printed another table than $md"

# A run without its end mark (as if interrupted after its last checkpoint) resumes from it.
rm "$out/runs/pillar_2d_dense/finished"
"${quick[@]}" "$table1" "$bin" "$out" > "$work/resume.log" 2>&1 ||
  { tail -30 "$work/resume.log"; fail "the resuming rerun failed"; }
grep -q '^== train 6/7 pillar_2d_dense: resuming' "$work/resume.log" || fail "pillar_2d_dense did not resume"
[[ -f $out/runs/pillar_2d_dense/finished ]] || fail "pillar_2d_dense has no end mark after resuming"
grep -qF "$(cat "$md")" "$work/resume.log" || fail "the resumed run printed another table than $md"

# Bad knobs and a changed data size fail before any work, naming the cause.
expect_refusal() {  # PATTERN ENV...
  local pattern=$1 log="$work/refused.log"
  shift
  if env "$@" "$table1" "$bin" "$out" > "$log" 2>&1; then fail "table1.sh accepted $*"; fi
  grep -q "$pattern" "$log" || { cat "$log"; fail "table1.sh with $* did not say '$pattern'"; }
}
expect_refusal "TABLE1_EPOCHS must be a whole number >= 1, got 'x'" TABLE1_EPOCHS=x TABLE1_SCANS=2
expect_refusal "TABLE1_SCANS must be a whole number >= 1, got '0'" TABLE1_EPOCHS=1 TABLE1_SCANS=0
expect_refusal "TABLE1_SCANS/TABLE1_VAL_SCANS ask for" TABLE1_EPOCHS=1 TABLE1_SCANS=3 TABLE1_VAL_SCANS=2
expect_refusal "trained with another config" TABLE1_EPOCHS=2 TABLE1_SCANS=2 TABLE1_VAL_SCANS=2
echo "table1_test: 11 rows, paper figures, reports, rerun and refusals OK"
