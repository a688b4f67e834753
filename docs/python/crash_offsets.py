#!/usr/bin/env python3
"""Where gate-frame crashes happen relative to the gate the drone was flying to.

    dronerace eval --policy P --tracks ts --out ev
    python3 docs/python/crash_offsets.py ev/eval.json ts

An experiment run's `test.json` works too (its `best.bin`'s test deployments).

For every deployment that ended on a gate frame, the crashed gate's index minus the target's,
taken round the track into -N/2..N/2: 0 is the target itself, -1 the gate just passed, +2 and
+3 gates further along the lap that stand in the way (the observation of SPEC §5 shows only the
target and +1). Standard library only (Python 3.11+).
"""
import collections
import json
import pathlib
import sys
import tomllib


def gate_counts(track_dir):
    """Track name -> number of gates, from a directory of track files."""
    counts = {}
    for path in pathlib.Path(track_dir).glob("*.toml"):
        track = tomllib.loads(path.read_text())
        counts[track["name"]] = len(track["gate"])
    return counts


def crash_offsets(report, counts):
    """Counter of (crashed gate - target gate) over the report's gate-frame crashes."""
    offsets = collections.Counter()
    for track in report["tracks"]:
        n = counts[track["track"]]
        for deployment in track["deployments"]:
            crash = deployment.get("crash")
            if isinstance(crash, dict) and "gate" in crash:
                offset = (crash["gate"] - deployment["target"]) % n
                offsets[offset - n if offset > n // 2 else offset] += 1
    return offsets


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    report = json.loads(pathlib.Path(sys.argv[1]).read_text())
    report = report.get("best_policy", report)  # an experiment run's test.json
    offsets = crash_offsets(report, gate_counts(sys.argv[2]))
    print(f"{sum(offsets.values())} gate-frame crashes; crashed gate - target gate:")
    for offset, count in sorted(offsets.items()):
        print(f"  {offset:+d}: {count}")


if __name__ == "__main__":
    main()
