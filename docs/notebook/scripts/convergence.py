"""How fast a fine-tuned run converges against the same track trained from scratch.

    python3 docs/notebook/scripts/convergence.py SCRATCH_RUN FINETUNE_RUN [--window 20] [--share 0.9]

Thesis §3.4.4 measures fine-tuning by the iterations it needs to converge. Both run
directories' metrics.csv give the training return per iteration: scratch's plateau is its
mean return over the last 100 iterations, and a run has converged at the first iteration
where the mean return of the last `window` iterations reaches `share` of that plateau.
validation.csv (the run's own track, `eval.library`) adds the first validation with every
deployment successful. Prints one markdown row per run.
"""

import argparse
import csv
import math
import os


def read_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def returns(run):
    rows = read_rows(os.path.join(run, "metrics.csv"))
    return [(int(r["iteration"]), float(r["charts/episodic_return"])) for r in rows if r["charts/episodic_return"]]


def converged_at(series, level, window):
    """First iteration whose trailing `window`-iteration mean return reaches `level`."""
    for i in range(window - 1, len(series)):
        mean = sum(v for _, v in series[i - window + 1 : i + 1]) / window
        if mean >= level:
            return series[i][0]
    return None


def validations(run):
    """The rows of a run's validation.csv, oldest first (none without the file)."""
    path = os.path.join(run, "validation.csv")
    return read_rows(path) if os.path.exists(path) else []


def first_full_success(rows):
    """Iteration of the first validation with every deployment successful, or None."""
    return next((int(r["iteration"]) for r in rows if float(r["success"]) >= 1.0), None)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scratch")
    parser.add_argument("finetune")
    parser.add_argument("--window", type=int, default=20)
    parser.add_argument("--share", type=float, default=0.9)
    args = parser.parse_args()

    runs = [(name, returns(run), validations(run)) for name, run in (("scratch", args.scratch), ("fine-tuned", args.finetune))]
    scratch, scratch_validations = runs[0][1], runs[0][2]
    tail = scratch[-100:]
    plateau = sum(v for _, v in tail) / len(tail)
    level = args.share * plateau
    scratch_at = converged_at(scratch, level, args.window)
    print(f"scratch plateau (mean return, last {len(tail)} iterations) {plateau:.1f}; level {level:.1f}")
    if first_full_success(scratch_validations) is None:
        print("note: scratch never flew its track in every validation deployment, so its plateau is not a converged run's")
    print("| run | iterations to the level | share of scratch's | mean return, last 100 | first 100 % validation | last validation lap (s) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, series, rows in runs:
        at = converged_at(series, level, args.window)
        share = f"{100 * at / scratch_at:.0f} %" if at is not None and scratch_at else "–"
        last = series[-100:]
        full = first_full_success(rows)
        lap = float(rows[-1]["mean_lap"]) if rows else math.nan
        print(
            f"| {name} | {at if at is not None else 'never'} | {share} | {sum(v for _, v in last) / len(last):.1f} "
            f"| {full if full is not None else 'never'} | {lap:.2f} |"
        )


if __name__ == "__main__":
    main()
