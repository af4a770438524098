#!/usr/bin/env python3
"""The rows of the paper's Table I and our figures beside them (make table1, scripts/table1.sh).

configs/table1/paper_table1.tsv is the plan and the paper's figures in one: a row per Table I
row, naming the run config that produces it (configs/table1/RUN.yaml), the ground truth it is
evaluated on, the paper's mode and method, what `pillarseg eval` calls the method, and the
paper's mIoU and 12 class IoUs in %.

Usage:
  table1_format.py runs TSV          the run configs to train, one a line, in table order
  table1_format.py evals TSV         "RUN EVAL" a line: each evaluation (EVAL: sparse or dense)
  table1_format.py table TSV --reports DIR --runs DIR [--data-note TEXT]
      Table I in Markdown: Mode | Method | mIoU | 12 classes, each cell "ours (paper)" in %,
      from DIR/RUN.EVAL.json (pillarseg eval --report) and the epochs in DIR/RUN/config.yaml.
Standard library only. Exits 1 with a message naming the file on a missing or mismatched report.
"""
import argparse
import json
import math
import re
import sys
from pathlib import Path

CLASSES = ["vehicle", "person", "two-wheel", "rider", "road", "sidewalk", "other-ground",
           "building", "object", "vegetation", "trunk", "terrain"]
KEYS = ["run", "eval", "mode", "method", "pillarseg_method", "mIoU"] + CLASSES


def fail(message):
    sys.exit(f"table1_format.py: {message}")


def read_plan(path):
    """The TSV's rows as dicts; '#' lines are comments."""
    lines = [l for l in Path(path).read_text().splitlines() if l.strip() and not l.startswith("#")]
    if not lines or lines[0].split("\t") != KEYS:
        fail(f"{path}: the header must be the tab-separated columns {' '.join(KEYS)}")
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        cells = line.split("\t")
        if len(cells) != len(KEYS):
            fail(f"{path}: row {n} has {len(cells)} columns, expected {len(KEYS)}")
        row = dict(zip(KEYS, cells))
        if row["eval"] not in ("sparse", "dense"):
            fail(f"{path}: row {n}: eval must be sparse or dense, got '{row['eval']}'")
        for key in ["mIoU"] + CLASSES:
            try:
                row[key] = float(row[key])
            except ValueError:
                fail(f"{path}: row {n}: {key} is not a number: '{row[key]}'")
        rows.append(row)
    return rows


def percent(v):
    return "n/a" if v is None or math.isnan(v) else f"{100.0 * v:.1f}"


def read_report(path, row):
    """pillarseg eval's JSON report (engine/eval/metrics.cpp json()), checked against the row."""
    if not path.exists():
        fail(f"{path}: no report (pillarseg eval --report) for Table I row {row['mode']}, {row['method']}")
    try:
        report = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        fail(f"{path}: not valid JSON: {e}")
    for key, want in (("mode", row["mode"]), ("method", row["pillarseg_method"])):
        if report.get(key) != want:
            fail(f"{path}: {key} is '{report.get(key)}', but this Table I row needs '{want}' "
                 f"(is configs/table1/{row['run']}.yaml the right model?)")
    missing = [c for c in CLASSES if c not in report.get("iou", {})]
    if missing or "miou" not in report:
        fail(f"{path}: no IoU for {', '.join(missing or ['miou'])}")
    return report


def epochs_of(run_dir):
    """train.epochs of the run's config, as trained (RUN/config.yaml)."""
    text = (run_dir / "config.yaml").read_text() if (run_dir / "config.yaml").exists() else ""
    m = re.search(r"^train:\n(?:[ \t].*\n|\n)*?[ \t]+epochs:[ \t]*(\d+)", text, re.M)
    return int(m.group(1)) if m else None


def ordering(names_and_scores):
    """'A > B = C': the methods by score (in %, to the table's 0.1), best first; n/a last."""
    def shown(v):
        return None if v is None or math.isnan(v) else round(v, 1)
    ranked = sorted(names_and_scores, key=lambda ns: (shown(ns[1]) is None, -(shown(ns[1]) or 0)))
    text = ranked[0][0]
    for (_, before), (name, score) in zip(ranked, ranked[1:]):
        text += (" = " if shown(before) == shown(score) else " > ") + name
    return text


def table(args):
    rows = read_plan(args.tsv)
    reports = [read_report(Path(args.reports) / f"{r['run']}.{r['eval']}.json", r) for r in rows]
    epochs = {r["run"]: epochs_of(Path(args.runs) / r["run"]) for r in rows}
    if None in epochs.values():
        fail(f"no train.epochs in {Path(args.runs)}/RUN/config.yaml for "
             f"{', '.join(run for run, e in epochs.items() if e is None)}")
    distinct = sorted(set(epochs.values()))
    plural = lambda e: f"{e} epoch" + ("" if e == 1 else "s")
    epochs_note = (plural(distinct[0]) if len(distinct) == 1 else
                   ", ".join(f"{run} {plural(e)}" for run, e in epochs.items()))
    out = ["# Table I on the simulator (make table1)", ""]
    out.append(
        f"Simulated data at the small CPU size (configs/table1/: 0.4 m cells, C = 32, Q = 8, base "
        f"width 16; {args.data_note + ', ' if args.data_note else ''}{epochs_note}), so the absolute "
        f"figures are not the paper's: it trained on SemanticKITTI at 0.1 m (C = 64, Q = 16, base "
        f"width 64, 30 epochs). Compare the ordering of the rows. Each cell: ours (paper), in %.")
    out.append("")
    out.append("| Mode | Method | mIoU | " + " | ".join(CLASSES) + " |")
    out.append("|---|---|---:|" + "---:|" * len(CLASSES))
    for row, report in zip(rows, reports):
        cells = [row["mode"], row["method"], f"**{percent(report['miou'])}** ({row['mIoU']:.1f})"]
        cells += [f"{percent(report['iou'][c])} ({row[c]:.1f})" for c in CLASSES]
        out.append("| " + " | ".join(cells) + " |")
    out.append("")
    out.append("Methods by mIoU, best first:")
    out.append("")
    for mode in dict.fromkeys(r["mode"] for r in rows):
        group = [(r, rep) for r, rep in zip(rows, reports) if r["mode"] == mode]
        ours = ordering([(r["method"], None if rep["miou"] is None else 100 * rep["miou"])
                         for r, rep in group])
        paper = ordering([(r["method"], r["mIoU"]) for r, _ in group])
        same = "the same order" if ours == paper else "a different order"
        out.append(f"- {mode}: ours {ours}; paper {paper} ({same})")
    print("\n".join(out))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    for name in ("runs", "evals"):
        sub.add_parser(name).add_argument("tsv")
    t = sub.add_parser("table")
    t.add_argument("tsv")
    t.add_argument("--reports", required=True, help="folder of RUN.EVAL.json reports")
    t.add_argument("--runs", required=True, help="folder of the run directories RUN/")
    t.add_argument("--data-note", default="", help="the data set, for the note above the table")
    args = p.parse_args()
    if args.command == "runs":
        print("\n".join(dict.fromkeys(r["run"] for r in read_plan(args.tsv))))
    elif args.command == "evals":
        print("\n".join(f"{r['run']} {r['eval']}" for r in read_plan(args.tsv)))
    else:
        table(args)


if __name__ == "__main__":
    main()
