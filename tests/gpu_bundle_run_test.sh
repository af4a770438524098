#!/usr/bin/env bash
# The GPU bundle's run.sh without a GPU (CTest gpu_bundle_run, after gpu_bundle packed BUNDLE):
# --only chooses the stages, a bad stage or argument is refused, the smoke stage's table comes
# first in the report and names the missing device, and the summary is written.
# Usage: gpu_bundle_run_test.sh BUNDLE_DIR WORK_DIR
set -euo pipefail
bundle=${1:?usage: gpu_bundle_run_test.sh BUNDLE_DIR WORK_DIR}
work=${2:?usage: gpu_bundle_run_test.sh BUNDLE_DIR WORK_DIR}
rm -rf "$work"
mkdir -p "$work"
fail() { echo "FAIL: $*"; exit 1; }

# Refusals: exit 2 and a message naming what was wrong.
set +e
message=$(OUT=$work/bad "$bundle/run.sh" --only smoke,nonsense 2>&1); rc=$?
set -e
((rc == 2)) || fail "--only smoke,nonsense exited $rc, expected 2"
[[ $message == *"unknown stage 'nonsense'"* ]] || fail "--only smoke,nonsense said: $message"
set +e
message=$(OUT=$work/bad "$bundle/run.sh" --fast 2>&1); rc=$?
set -e
((rc == 2)) || fail "--fast exited $rc, expected 2"
[[ $message == *"unknown argument '--fast'"* ]] || fail "--fast said: $message"
[[ ! -e $work/bad/report.md ]] || fail "a refused call wrote a report"

# The smoke stage alone, here without a GPU.
OUT=$work/smoke "$bundle/run.sh" --only smoke 120 > "$work/smoke.out" 2>&1 || fail "run.sh --only smoke exited non-zero"
report=$work/smoke/report.md
[[ -f $report ]] || fail "no report.md"
first_section=$(grep -m1 '^## ' "$report")
[[ $first_section == "## Smoke"* ]] || fail "the report's first section is '$first_section', not the smoke table"
grep -q '^| device | NONE' "$report" || grep -q '^| device | NVIDIA' "$report" || fail "the smoke table has no device row"
rows=$(grep -c '^| test_.*_gpu |' "$report" || true)
binaries=$(ls "$bundle"/bin/test_*_gpu | wc -l)
((rows == binaries)) || fail "the smoke table has $rows test rows for $binaries test binaries"
grep -q '^| full-size bench' "$report" || fail "the smoke table has no bench row"
grep -q '^Stages run: smoke\.' "$report" || fail "no summary naming the stages run"
for other in "## Tests" "## compute-sanitizer" "## Kernel benchmarks" "## pillarseg bench" "## Training"; do
  ! grep -q "^$other" "$report" || fail "--only smoke also ran '$other'"
done

# A killed call still ends its report with the summary.
OUT=$work/killed "$bundle/run.sh" --only tests 120 > /dev/null 2>&1 &
pid=$!
for _ in $(seq 50); do
  [[ -s $work/killed/tests.log ]] && break
  sleep 0.1
done
kill -TERM "$pid" 2>/dev/null || true
wait "$pid" || true
grep -q 'Stopped by a signal' "$work/killed/report.md" || fail "a killed call's report does not say it was stopped"
grep -q '^## Summary' "$work/killed/report.md" || fail "a killed call's report has no summary"
echo "gpu_bundle_run: --only, refusals, smoke table first, summary on a kill: all as expected"
