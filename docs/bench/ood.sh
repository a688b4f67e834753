#!/usr/bin/env bash
# The out-of-distribution families (SPEC §13): the shipped generalist and the reference pilot on
# each, 25 deployments a track.
#   docs/bench/ood.sh [path/to/dronerace] [out-dir]        (from the repository root)
# Writes <out>/ood.csv (family,tracks,controller,success,s_pw,mean_lap).
set -euo pipefail
bin=${1:-target/release/dronerace}
out=${2:-runs/ood}
mkdir -p "$out"
csv="$out/ood.csv"
echo "family,tracks,controller,success,s_pw,mean_lap" > "$csv"
for family in many-gates steep tight races; do
  "$bin" tracks ood --family "$family" --out "$out/$family" >/dev/null
  for who in generalist pilot; do
    policy=()
    [ "$who" = generalist ] && policy=(--policy policies/generalist.bin)
    "$bin" eval "${policy[@]}" --tracks "$out/$family" --out "$out/eval" >/dev/null 2>&1
    python3 -c "import json; r=json.load(open('$out/eval/eval.json')); print(f\"$family,{len(r['tracks'])},$who,{r['success_rate']:.4f},{r['s_pw']:.4f},{r['mean_lap'] or ''}\")" >> "$csv"
    tail -1 "$csv"
  done
done
