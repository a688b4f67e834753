#!/usr/bin/env python3
"""Count the tracks on which another gate stands near the straight line between two consecutive gates.

    dronerace tracks generate --seed 1000 --count 300 --out gen
    python3 docs/notebook/scripts/gates_in_the_way.py gen [--within 1.75]

A policy that cuts straight from gate to gate, and sees only the target gate and the one after it
(SPEC §5), can fly into such a gate's frame without any warning in its observation. A gate's frame
reaches 1.0 m from its centre (outer half size), so a segment passing within ~1.75 m of a centre
leaves a 0.15 m collision sphere little room. Standard library only (Python 3.11+).
"""
import argparse
import math
import pathlib
import tomllib


def distance_to_segment(p, a, b):
    ab = [b[k] - a[k] for k in range(3)]
    ap = [p[k] - a[k] for k in range(3)]
    t = max(0.0, min(1.0, sum(x * y for x, y in zip(ab, ap)) / sum(x * x for x in ab)))
    return math.dist(p, [a[k] + t * ab[k] for k in range(3)])


def gates_in_the_way(centres, within):
    """(segment start, segment end, gate) for every gate within `within` m of a segment it is not an end of."""
    n = len(centres)
    found = []
    for i in range(n):
        j = (i + 1) % n
        for g in range(n):
            if g not in (i, j) and distance_to_segment(centres[g], centres[i], centres[j]) < within:
                found.append((i, j, g))
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tracks", type=pathlib.Path, help="directory of track files")
    parser.add_argument("--within", type=float, default=1.75, help="metres from a gate centre")
    args = parser.parse_args()
    files = sorted(args.tracks.glob("*.toml"))
    if not files:
        raise SystemExit(f"no track files in {args.tracks}")
    blocked = 0
    for f in files:
        track = tomllib.loads(f.read_text())
        found = gates_in_the_way([g["position"] for g in track["gate"]], args.within)
        if found:
            blocked += 1
            print(f"{track['name']}: " + ", ".join(f"g{i}->g{j} passes g{g}" for i, j, g in found))
    print(f"{blocked} of {len(files)} tracks ({100 * blocked / len(files):.0f} %) have a gate within {args.within} m of a straight inter-gate segment")


if __name__ == "__main__":
    main()
