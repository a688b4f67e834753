"""Which tracks two controllers fly: the tracks both fly, only one flies, neither flies.

    dronerace eval --policy P --tracks val100 --runs 10 --out ev-policy
    dronerace eval --controller pilot --tracks val100 --runs 10 --out ev-pilot
    python3 docs/notebook/scripts/compare_tracks.py ev-policy/eval.json ev-pilot/eval.json [--prefix test-]

A track counts as flown when at least half of its deployments succeed (a deterministic policy
flies a track in all of them or in none, nearly always). `--prefix` keeps only the tracks
whose names start with it, e.g. the generated tracks of `tracks testset`.
"""
import argparse
import json
import math


def flown(path, prefix):
    """{track name: flown?} of one eval.json, for the tracks whose names start with `prefix`."""
    tracks = json.load(open(path))["tracks"]
    return {t["track"]: t["success_rate"] >= 0.5 for t in tracks if t["track"].startswith(prefix)}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first")
    parser.add_argument("second")
    parser.add_argument("--prefix", default="")
    args = parser.parse_args()
    a, b = flown(args.first, args.prefix), flown(args.second, args.prefix)
    if a.keys() != b.keys():
        raise SystemExit(f"the two reports cover different tracks ({len(a)} and {len(b)})")
    n = len(a)
    both = [t for t in a if a[t] and b[t]]
    first_only = [t for t in a if a[t] and not b[t]]
    second_only = [t for t in a if b[t] and not a[t]]
    for name, count in [("first", len(both) + len(first_only)), ("second", len(both) + len(second_only))]:
        p = count / n
        # The binomial standard error of a fraction of n tracks: how far another draw of n
        # tracks from the same generator would typically move it.
        print(f"{name} flies {count} of {n} tracks ({100 * p:.1f} % ± {100 * math.sqrt(p * (1 - p) / n):.1f})")
    print(f"both {len(both)}, first only {len(first_only)}, second only {len(second_only)}, "
          f"neither {n - len(both) - len(first_only) - len(second_only)}")
    print("first only:", " ".join(first_only) or "–")
    print("second only:", " ".join(second_only) or "–")


if __name__ == "__main__":
    main()
