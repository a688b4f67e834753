"""How well a run's validation ranks its checkpoints, against a set it never chose on.

    # a run that keeps the checkpoint of every validation (checkpoint_every = the validation
    # interval, keep_checkpoints ≥ the validations), then each checkpoint flown on the test set:
    for c in RUN/checkpoints/ckpt-*.bin; do
        dronerace eval --policy $c --tracks ts --out EV/$(basename $c .bin); done
    python3 docs/notebook/scripts/selection.py RUN EV [--metric s_pw|success]

Reads RUN/validation.csv (one row per validation track, mean over them = the run's validation
figure) and EV/ckpt-<iteration>/eval.json. Prints each validated iteration's two figures, the
Spearman and Kendall rank correlations over all of them and over the second half of the run
(where checkpoints differ least and selection matters), and what choosing by validation gave
against the final checkpoint and the best possible one; then, per test track, how often the
second half's checkpoints fly it (≥ 50 % of its deployments): tracks every checkpoint flies, none
flies, and those some fly and some do not. Standard library only.
"""
import argparse
import csv
import json
import os
from collections import defaultdict


def validation_means(run):
    """{iteration: (success, S_pw)} averaged over the validation tracks, as the run logs them."""
    rows = defaultdict(list)
    with open(os.path.join(run, "validation.csv")) as f:
        for r in csv.DictReader(f):
            rows[int(r["iteration"])].append((float(r["success"]), float(r["s_pw"])))
    return {it: tuple(sum(v[i] for v in vals) / len(vals) for i in range(2)) for it, vals in rows.items()}


def test_figures(ev):
    """{iteration: (success, S_pw)} of every EV/ckpt-<iteration>/eval.json."""
    out = {}
    for name in os.listdir(ev):
        path = os.path.join(ev, name, "eval.json")
        if name.startswith("ckpt-") and os.path.exists(path):
            d = json.load(open(path))
            out[int(name[len("ckpt-"):])] = (d["success_rate"], d["s_pw"])
    return out


def track_success(ev, iteration):
    """{track: success rate} of EV/ckpt-<iteration>/eval.json."""
    d = json.load(open(os.path.join(ev, f"ckpt-{iteration:09d}", "eval.json")))
    return {t["track"]: t["success_rate"] for t in d["tracks"]}


def ranks(values):
    """Average ranks (ties share the mean of their positions), 1-based."""
    order = sorted(range(len(values)), key=lambda i: values[i])
    r = [0.0] * len(values)
    i = 0
    while i < len(order):
        j = i
        while j + 1 < len(order) and values[order[j + 1]] == values[order[i]]:
            j += 1
        for k in range(i, j + 1):
            r[order[k]] = (i + j) / 2 + 1
        i = j + 1
    return r


def spearman(x, y):
    rx, ry = ranks(x), ranks(y)
    mx, my = sum(rx) / len(rx), sum(ry) / len(ry)
    cov = sum((a - mx) * (b - my) for a, b in zip(rx, ry))
    sx = sum((a - mx) ** 2 for a in rx) ** 0.5
    sy = sum((b - my) ** 2 for b in ry) ** 0.5
    return cov / (sx * sy) if sx and sy else float("nan")


def kendall(x, y):
    """Kendall's tau-b."""
    concordant = discordant = tx = ty = 0
    for i in range(len(x)):
        for j in range(i + 1, len(x)):
            dx, dy = x[i] - x[j], y[i] - y[j]
            if dx == 0 and dy == 0:
                continue
            if dx == 0:
                tx += 1
            elif dy == 0:
                ty += 1
            elif (dx > 0) == (dy > 0):
                concordant += 1
            else:
                discordant += 1
    n = ((concordant + discordant + tx) * (concordant + discordant + ty)) ** 0.5
    return (concordant - discordant) / n if n else float("nan")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("ev")
    parser.add_argument("--metric", choices=["s_pw", "success"], default="s_pw", help="what validation chooses by")
    args = parser.parse_args()
    col = 1 if args.metric == "s_pw" else 0
    val, test = validation_means(args.run), test_figures(args.ev)
    its = sorted(set(val) & set(test))
    if len(its) < 3:
        raise SystemExit(f"only {len(its)} iterations have both a validation and a test figure")
    print("| iteration | validation success / S_pw | test success / S_pw |")
    print("|---:|---:|---:|")
    for it in its:
        print(f"| {it} | {val[it][0]:.1%} / {val[it][1]:.4f} | {test[it][0]:.1%} / {test[it][1]:.4f} |")
    print()
    half = its[len(its) // 2:]
    for label, subset in [("all validations", its), (f"second half (iteration {half[0]} on)", half)]:
        for name, c in [("S_pw", 1), ("success", 0)]:
            v, t = [val[i][c] for i in subset], [test[i][c] for i in subset]
            print(f"{label}, {name}: Spearman {spearman(v, t):+.2f}, Kendall {kendall(v, t):+.2f} (n = {len(subset)})")
    chosen = max(its, key=lambda i: val[i][col])
    final, best = its[-1], max(its, key=lambda i: test[i][col])
    print()
    for label, it in [("chosen by validation", chosen), ("final", final), ("best on the test set (hindsight)", best)]:
        print(f"{label}: iteration {it}, test {test[it][0]:.1%} / {test[it][1]:.4f}")
    flown = defaultdict(int)
    for it in half:
        for track, rate in track_success(args.ev, it).items():
            flown[track] += rate >= 0.5
    counts = sorted(flown.values())
    always, never = sum(c == len(half) for c in counts), sum(c == 0 for c in counts)
    print()
    print(f"test tracks flown by the second half's {len(half)} checkpoints: every one {always}, none {never}, "
          f"some {len(counts) - always - never}; at least one {len(counts) - never} of {len(counts)}")
    print("checkpoints flying each of the 'some' tracks:", [c for c in counts if 0 < c < len(half)])


if __name__ == "__main__":
    main()
