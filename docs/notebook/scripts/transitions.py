#!/usr/bin/env python3
"""Which gate-to-gate legs a controller crashes on, by the leg's geometry.

    dronerace eval --policy P --tracks val100 --runs 10 --out ev
    python3 docs/notebook/scripts/transitions.py val100 ev/eval.json

A leg is the way from gate k-1 to gate k. Every deployment attempts the legs it reaches (the
gates it passed, and the one it was flying to when it crashed); a crash counts against the leg
whose gate was the target then, whichever frame it hit. Printed: crash rate per attempted leg,
binned by the leg's horizontal length, height change, change of gate heading, and the bearing
of the displacement against gate k's normal (above 90°: gate k-1 stands in front of gate k, so
the way in is round its frame). Standard library only (Python 3.11+).
"""
import collections
import json
import math
import pathlib
import sys
import tomllib


def legs(gates):
    """(k, horizontal length, height change, heading change °, bearing °) of every leg."""
    for k, b in enumerate(gates):
        a = gates[k - 1]
        (ax, ay, az), (bx, by, bz) = a["position"], b["position"]
        yaw_a, yaw_b = math.radians(a["yaw_deg"]), math.radians(b["yaw_deg"])
        turn = abs((yaw_b - yaw_a + math.pi) % (2 * math.pi) - math.pi)
        bearing = abs((math.atan2(by - ay, bx - ax) - yaw_b + math.pi) % (2 * math.pi) - math.pi)
        yield k, math.hypot(bx - ax, by - ay), bz - az, math.degrees(turn), math.degrees(bearing)


def main(track_dir, report):
    tracks = {}
    for path in pathlib.Path(track_dir).glob("*.toml"):
        track = tomllib.loads(path.read_text())
        tracks[track["name"]] = track["gate"]
    rows = []
    for result in json.loads(pathlib.Path(report).read_text())["tracks"]:
        gates = tracks[result["track"]]
        attempts, crashes = collections.Counter(), collections.Counter()
        for d in result["deployments"]:
            for i in range(d["gates_passed"] + (0 if d["success"] else 1)):
                attempts[i % len(gates)] += 1
            if not d["success"] and d.get("crash"):
                crashes[d["target"]] += 1
        for k, length, climb, turn, bearing in legs(gates):
            if attempts[k]:
                rows.append((attempts[k], crashes[k], {"length m": length, "|height change| m": abs(climb), "heading change °": turn, "bearing °": bearing}))
    bins = {
        "length m": [0, 4, 6, 8, 10, 13, 99],
        "|height change| m": [0, 0.5, 1, 2, 3, 9],
        "heading change °": [0, 30, 60, 90, 120, 150, 181],
        "bearing °": [0, 30, 60, 90, 120, 181],
    }
    for feature, edges in bins.items():
        print(feature)
        for lo, hi in zip(edges, edges[1:]):
            chosen = [(a, c) for a, c, f in rows if lo <= f[feature] < hi]
            tried = sum(a for a, _ in chosen)
            if tried:
                print(f"  [{lo:5g}, {hi:5g})  legs {len(chosen):4d}  attempts {tried:6d}  crashes {100 * sum(c for _, c in chosen) / tried:5.1f} %")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
