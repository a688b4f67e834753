#!/usr/bin/env bash
# The robustness table (SPEC §13): the shipped generalist and the reference pilot on the test set,
# nominal and under each disturbance at three levels, then the figure.
#   docs/bench/robustness.sh [path/to/dronerace] [out-dir]        (from the repository root)
# Writes <out>/robustness.csv (disturbance,level,controller,success,s_pw,mean_lap) and
# <out>/robustness.png. Each evaluation is `dronerace eval --tracks <out>/testset [--policy
# policies/generalist.bin] --wind W | --disturbance "..."`, 40 tracks × 25 deployments.
set -euo pipefail
bin=${1:-target/release/dronerace}
out=${2:-runs/robustness}
mkdir -p "$out"
[ -d "$out/testset" ] || "$bin" tracks testset --out "$out/testset" >/dev/null
csv="$out/robustness.csv"
echo "disturbance,level,controller,success,s_pw,mean_lap" > "$csv"
row() { # disturbance level controller flags...
  local name=$1 level=$2 who=$3; shift 3
  local policy=()
  [ "$who" = generalist ] && policy=(--policy policies/generalist.bin)
  "$bin" eval "${policy[@]}" --tracks "$out/testset" --out "$out/eval" "$@" >/dev/null 2>&1
  python3 -c "import json,sys; r=json.load(open('$out/eval/eval.json')); print(f\"$name,$level,$who,{r['success_rate']:.4f},{r['s_pw']:.4f},{r['mean_lap'] or ''}\")" >> "$csv"
  tail -1 "$csv"
}
for who in generalist pilot; do
  for w in 0 1 3 5; do row "wind (m/s)" $w $who --wind $w; done
  for k in 0 1 2 4; do row "estimate noise (× motion capture)" $k $who --disturbance "noise = $k"; done
  for ms in 0 10 20 40; do row "extra latency (ms)" $ms $who --disturbance "latency_ms = $ms"; done
  for pct in 0 5 10 20; do row "thrust loss of every motor (%)" $pct $who --disturbance "thrust_loss = 0.$(printf %02d $pct)"; done
  for pct in 0 5 10 20; do row "thrust loss of one motor (%)" $pct $who --disturbance "thrust_loss = 0.$(printf %02d $pct), thrust_loss_motor = 0"; done
done
"$bin" plot --robustness "$csv" --out "$out/robustness.png"
