#!/usr/bin/env bash
# Whole-iteration training throughput of one or more dronerace binaries, alternated, with the
# resident size of every dronerace process sampled every 0.5 s (docs/notebook/throughput.md).
#
#   docs/bench/throughput.sh OUT_DIR BINARY [BINARY ...]
#
# For each of paper/cpu × in-process/default (learner + actor processes over iceoryx2), runs
# `BINARY train --profile P --iterations N [--in-process]` and prints env-steps/s over
# iterations 4..N (from metrics.csv) and the largest resident size per process role.
set -eu
out=$1; shift
mkdir -p "$out"
for spec in "paper 10 --in-process" "cpu 22 --in-process" "paper 10" "cpu 22"; do
  set -- $spec "$@"
  profile=$1 iters=$2
  mode=""; [ "${3:-}" = "--in-process" ] && { mode=--in-process; shift; }
  shift 2
  for bin in "$@"; do
    name=$(basename "$bin")-$profile-${mode:+in-process}${mode:-processes}
    rm -rf "$out/$name"
    (while sleep 0.5; do ps -eo rss,args | grep -F "$bin" | grep -v -e grep -e "ps -eo"; done) > "$out/$name.rss" 2>/dev/null &
    sampler=$!
    "$bin" train --profile "$profile" --iterations "$iters" $mode --out "$out/$name" > "$out/$name.log" 2>&1
    kill $sampler
    python3 - "$out" "$name" <<'PY'
import collections, csv, re, sys
out, name = sys.argv[1:]
rows = list(csv.DictReader(open(f"{out}/{name}/metrics.csv")))
a, b = rows[2], rows[-1]
sps = (float(b["env_steps"]) - float(a["env_steps"])) / (float(b["wall_seconds"]) - float(a["wall_seconds"]))
rss = collections.defaultdict(int)
for line in open(f"{out}/{name}.rss"):
    kb, _, args = line.strip().partition(" ")
    if kb.isdigit():
        role = re.search(r" (learner|actor|taskctl|train)\b", args)
        rss[role.group(1) if role else "other"] = max(rss[role.group(1) if role else "other"], int(kb))
print(f"{name}: {sps:,.0f} env-steps/s (iterations {int(a['iteration']) + 1}-{b['iteration']}); "
      + ", ".join(f"{k} {v / 1024:.0f} MB" for k, v in sorted(rss.items())))
PY
  done
done
