"""Which kinds of track a controller fails: tracks binned by the hardest leg of their shape.

    dronerace tracks generate --seed 8000100 --count 300 --out val300
    dronerace eval --policy P --tracks val300 --runs 10 --out EV_P
    dronerace eval --controller pilot --tracks val300 --runs 10 --out EV_PILOT
    python3 docs/notebook/scripts/track_shapes.py val300 EV_PILOT EV_P ...

For each leg from gate a to the next gate b (horizontal plane), three shapes, and each track
keeps its worst leg:
- `ahead`: cosine between a's facing and the way to b (below 0: b lies behind a, a hairpin);
- `entry`: cosine between the way to b and b's facing (below −0.5: b faces back against the way
  in, more than 120° off, so the line must loop round it);
- `spacing`: the closest two consecutive gates (m, 3-D).
Prints, per bin, how many tracks and the share of them each evaluation flies (≥ 50 % of its
deployments). Standard library only (Python ≥ 3.11 for tomllib).
"""
import glob
import json
import math
import sys
import tomllib

BINS = {
    "ahead": [-1.01, -0.5, 0.0, 0.5, 1.01],
    "entry": [-1.01, -0.5, 0.0, 0.5, 1.01],
    "spacing": [0.0, 3.0, 4.0, 5.0, 99.0],
}


def shape(path):
    """A track's name and the worst of each shape over its legs."""
    track = tomllib.load(open(path, "rb"))
    gates = track["gate"]
    worst = {"ahead": 1.0, "entry": 1.0, "spacing": math.inf}
    for i, a in enumerate(gates):
        b = gates[(i + 1) % len(gates)]
        d = [b["position"][k] - a["position"][k] for k in range(3)]
        horizontal = max(math.hypot(d[0], d[1]), 1e-9)

        def along(yaw_deg):
            yaw = math.radians(yaw_deg)
            return (d[0] * math.cos(yaw) + d[1] * math.sin(yaw)) / horizontal

        worst["ahead"] = min(worst["ahead"], along(a["yaw_deg"]))
        worst["entry"] = min(worst["entry"], along(b["yaw_deg"]))
        worst["spacing"] = min(worst["spacing"], math.sqrt(sum(x * x for x in d)))
    return track["name"], worst


def flown(eval_dir):
    """Track name → flown (≥ 50 % of deployments succeed) in one evaluation."""
    report = json.load(open(f"{eval_dir}/eval.json"))
    return {t["track"]: t["success_rate"] >= 0.5 for t in report["tracks"]}


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    shapes = dict(shape(p) for p in sorted(glob.glob(f"{sys.argv[1]}/*.toml")))
    evals = [(e, flown(e)) for e in sys.argv[2:]]
    print("columns: " + ", ".join(e for e, _ in evals))
    print(f"all tracks n={len(shapes):3d} " + " ".join(f"{100 * sum(f.get(n, False) for n in shapes) / len(shapes):5.1f}%" for _, f in evals))
    for key, edges in BINS.items():
        print(f"worst {key}")
        for lo, hi in zip(edges, edges[1:]):
            names = [n for n, s in shapes.items() if lo <= s[key] < hi]
            if names:
                shares = " ".join(f"{100 * sum(f.get(n, False) for n in names) / len(names):5.1f}%" for _, f in evals)
                print(f"  [{lo:5.2f}, {hi:5.2f}) n={len(names):3d} {shares}")


if __name__ == "__main__":
    main()
