"""How close a policy's deployments pass the gate frames: the clearance left before a crash.

    dronerace eval --policy P --tracks ts --out EV --trajectories TRJ
    python3 docs/notebook/scripts/clearance.py TRJ ts [--eval EV/eval.json]

For every deployment (one CSV of TRJ, `<t>-<track>-<run>.csv`, t = the track's index in the
sorted track directory) the smallest distance between the drone's centre and any gate frame over
the flight, minus SPEC §2's collision radius (0.15 m): the clearance, 0 at a crash on a frame.
Between two logged steps (20 ms) the position is interpolated with the cubic Hermite curve of
the logged positions and velocities at 16 points. The frame is SPEC §4's four bars (opening
1.5 m, outer 2.0 m, depth 0.1 m). Prints, over the deployments that succeeded (from --eval, else
every deployment that completed a lap and did not end on a frame), the clearance's quantiles and
the share under 5, 10 and 20 cm, then per track. Needs numpy.
"""
import argparse
import csv
import json
import math
import os
import tomllib
from collections import defaultdict

import numpy as np

RADIUS = 0.15
HALF_OPENING, HALF_OUTER, HALF_DEPTH = 0.75, 1.0, 0.05
# The four bars of a frame in gate-local (x, y, z): (min corner, max corner).
BARS = [
    ((-HALF_DEPTH, -HALF_OUTER, HALF_OPENING), (HALF_DEPTH, HALF_OUTER, HALF_OUTER)),  # top
    ((-HALF_DEPTH, -HALF_OUTER, -HALF_OUTER), (HALF_DEPTH, HALF_OUTER, -HALF_OPENING)),  # bottom
    ((-HALF_DEPTH, HALF_OPENING, -HALF_OPENING), (HALF_DEPTH, HALF_OUTER, HALF_OPENING)),  # left
    ((-HALF_DEPTH, -HALF_OUTER, -HALF_OPENING), (HALF_DEPTH, -HALF_OPENING, HALF_OPENING)),  # right
]
SUBSTEPS = 16


def gates(track_file):
    """[(centre, rotation world ← gate)] of a track file."""
    with open(track_file, "rb") as f:
        track = tomllib.load(f)
    out = []
    for g in track["gate"]:
        yaw = math.radians(g["yaw_deg"])
        c, s = math.cos(yaw), math.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out.append((np.array(g["position"], dtype=float), rotation))
    return out


def path(rows):
    """Positions along the flight, Hermite-interpolated between the logged steps."""
    p = np.array([[float(r["x"]), float(r["y"]), float(r["z"])] for r in rows])
    v = np.array([[float(r["vx"]), float(r["vy"]), float(r["vz"])] for r in rows])
    if len(p) < 2:
        return p
    dt = float(rows[1]["t"]) - float(rows[0]["t"])
    s = np.linspace(0.0, 1.0, SUBSTEPS, endpoint=False)[:, None, None]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    inner = h00 * p[:-1] + h10 * dt * v[:-1] + h01 * p[1:] + h11 * dt * v[1:]
    return np.concatenate([inner.transpose(1, 0, 2).reshape(-1, 3), p[-1:]])


def clearance(points, track_gates):
    """Smallest distance from `points` to any frame bar, minus the collision radius."""
    best = np.inf
    for centre, rotation in track_gates:
        local = (points - centre) @ rotation  # rows: world → gate-local
        for lo, hi in BARS:
            d = np.maximum(np.maximum(np.array(lo) - local, local - np.array(hi)), 0.0)
            best = min(best, float(np.sqrt((d**2).sum(axis=1)).min()))
    return best - RADIUS


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trajectories")
    parser.add_argument("tracks")
    parser.add_argument("--eval", help="eval.json of the same evaluation: which deployments succeeded")
    args = parser.parse_args()
    track_files = sorted(f for f in os.listdir(args.tracks) if f.endswith(".toml"))
    succeeded = None
    if args.eval:
        report = json.load(open(args.eval))
        succeeded = {(i, k) for i, t in enumerate(report["tracks"]) for k, d in enumerate(t["deployments"]) if d["success"]}
    per_track = defaultdict(list)
    for name in sorted(os.listdir(args.trajectories)):
        index, rest = name.split("-", 1)
        track, run = rest.rsplit("-", 1)
        i, k = int(index), int(run.removesuffix(".csv"))
        with open(os.path.join(args.trajectories, name)) as f:
            rows = list(csv.DictReader(f))
        if succeeded is not None and (i, k) not in succeeded:
            continue
        if succeeded is None and int(rows[-1]["laps"]) < 1:
            continue
        c = clearance(path(rows), gates(os.path.join(args.tracks, track_files[i])))
        if succeeded is None and c <= 1e-3:
            continue
        per_track[track].append(c)
    every = np.array([c for cs in per_track.values() for c in cs])
    if len(every) == 0:
        raise SystemExit("no successful deployment")
    q = np.quantile(every, [0.05, 0.25, 0.5, 0.75])
    print(f"{len(every)} successful deployments, clearance (m): 5 % {q[0]:.3f}, 25 % {q[1]:.3f}, "
          f"median {q[2]:.3f}, 75 % {q[3]:.3f}")
    for cm in (5, 10, 20):
        print(f"  under {cm} cm: {np.mean(every < cm / 100):.1%}")
    print("| track | successes | median clearance (m) | smallest |")
    print("|---|---:|---:|---:|")
    for track, cs in sorted(per_track.items(), key=lambda kv: float(np.median(kv[1]))):
        print(f"| {track} | {len(cs)} | {np.median(cs):.3f} | {min(cs):.3f} |")


if __name__ == "__main__":
    main()
