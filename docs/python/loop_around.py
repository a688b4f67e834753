#!/usr/bin/env python3
"""Success by how many loop-around gates a track has, and by how sharp its sharpest one is.

    dronerace tracks generate --seed 8000000 --count 100 --out val100
    dronerace eval --policy P --tracks val100 --runs 10 --out ev
    python3 docs/python/loop_around.py val100 ev/eval.json [more reports …]

A loop-around gate faces the drone as it leaves the previous gate: the previous gate's centre
lies in front of it (on the side a pass leaves by), so the only way through is round its frame.
For each report (a `dronerace eval` eval.json, or an experiment run's test.json, whose
`fresh_validation` is read, or an older one's `final_validation`), the mean success over the tracks with none, one, and two or more
such gates; then over the tracks with no loop-around gate, with none sharper than 120° (the way in
from the previous gate 90–120° off the gate's normal) and with a sharper one. Tracks are matched by name, or by the seed that ends a generated track's name
(`val-8000000` in a run's validation, `informed-8000000` in the generated files).
Standard library only (Python 3.11+).
"""
import json
import math
import pathlib
import re
import sys
import tomllib


def loop_around_gates(track):
    """Number of gates whose front faces the previous gate's centre (horizontal plane)."""
    gates = track["gate"]
    count = 0
    for i, gate in enumerate(gates):
        previous = gates[i - 1]["position"]
        x, y = gate["position"][0], gate["position"][1]
        yaw = math.radians(gate["yaw_deg"])
        if (previous[0] - x) * math.cos(yaw) + (previous[1] - y) * math.sin(yaw) > 0:
            count += 1
    return count


def sharpest_entry_deg(track):
    """Largest angle (deg, horizontal plane) between a gate's normal and the way in from the
    previous gate's centre; above 90° the gate is a loop-around gate."""
    gates = track["gate"]
    sharpest = 0.0
    for i, gate in enumerate(gates):
        previous = gates[i - 1]["position"]
        dx, dy = gate["position"][0] - previous[0], gate["position"][1] - previous[1]
        yaw = math.radians(gate["yaw_deg"])
        cos = (dx * math.cos(yaw) + dy * math.sin(yaw)) / max(math.hypot(dx, dy), 1e-9)
        sharpest = max(sharpest, math.degrees(math.acos(max(-1.0, min(1.0, cos)))))
    return sharpest


def seed_key(name):
    """The number a generated track's name ends with, or the whole name."""
    match = re.search(r"(\d+)$", name)
    return match.group(1) if match else name


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    loops, sharpest = {}, {}
    for path in pathlib.Path(sys.argv[1]).glob("*.toml"):
        track = tomllib.loads(path.read_text())
        loops[seed_key(track["name"])] = loop_around_gates(track)
        sharpest[seed_key(track["name"])] = sharpest_entry_deg(track)
    groupings = [
        (loops, {"none": lambda n: n == 0, "one": lambda n: n == 1, "two or more": lambda n: n >= 2}),
        (sharpest, {"no loop-around": lambda a: a <= 90, "90-120°": lambda a: 90 < a <= 120, "sharper": lambda a: a > 120}),
    ]
    for values, groups in groupings:
        print("tracks: " + ", ".join(f"{g} {sum(1 for v in values.values() if test(v))}" for g, test in groups.items()))
    for report_path in sys.argv[2:]:
        report = json.loads(pathlib.Path(report_path).read_text())
        report = report.get("fresh_validation") or report.get("final_validation") or report
        success = {seed_key(t["track"]): t["success_rate"] for t in report["tracks"]}
        missing = set(loops) - set(success)
        if missing:
            sys.exit(f"{report_path}: no result for {len(missing)} of the tracks, e.g. {sorted(missing)[0]}")
        cells = []
        for values, groups in groupings:
            for g, test in groups.items():
                rates = [success[k] for k, v in values.items() if test(v)]
                cells.append(f"{g} {100 * sum(rates) / len(rates):.0f} %" if rates else f"{g} –")
        print(f"{report_path}: " + ", ".join(cells))


if __name__ == "__main__":
    main()
