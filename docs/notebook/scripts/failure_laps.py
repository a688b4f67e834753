#!/usr/bin/env python3
"""In which lap failed deployments end, and the crash hazard of each lap.

    dronerace eval --policy P --tracks ts --out ev
    python3 docs/notebook/scripts/failure_laps.py ev/eval.json [more eval.json …]

For each report: deployments that succeeded, crashed before finishing lap 1, crashed in a later
lap, or flew no lap; then the hazard of lap k — of the deployments that started lap k, the
fraction that crashed in it. A policy whose failures sit in lap 1 fails a track's hardest
manoeuvre the first time it meets it (and flies it ever after once through); one whose hazard is
the same every lap fails by chance, so more laps mean more failures. Standard library only.
"""
import collections
import json
import sys


def lap_outcomes(report):
    """(Counter of outcomes, {lap k: (started, crashed)}) over every deployment of a report."""
    outcomes = collections.Counter()
    started, crashed = collections.Counter(), collections.Counter()
    for track in report["tracks"]:
        for deployment in track["deployments"]:
            laps = len(deployment["lap_times"])
            for k in range(1, laps + 2):
                started[k] += 1
            if deployment["success"]:
                outcomes["success"] += 1
            elif deployment["crash"] is None:
                outcomes["no lap"] += 1
            else:
                crashed[laps + 1] += 1
                outcomes["crash in lap 1" if laps == 0 else "crash in a later lap"] += 1
    return outcomes, {k: (started[k], crashed[k]) for k in sorted(started)}


def main(paths):
    for path in paths:
        with open(path) as f:
            outcomes, laps = lap_outcomes(json.load(f))
        total = sum(outcomes.values())
        shares = ", ".join(f"{name} {n / total:.1%}" for name, n in sorted(outcomes.items()))
        hazard = "  ".join(f"lap {k}: {c / s:.3f} of {s}" for k, (s, c) in laps.items() if s)
        print(f"{path}: {total} deployments — {shares}\n  crash hazard by lap — {hazard}")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
