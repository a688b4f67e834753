#!/usr/bin/env bash
# Whole vision PPO iterations of experiments/vision/from-student.toml with nothing, the
# convolutions or the whole encoder frozen (`ppo.frozen`), one after the other on this machine:
# each runs the task controller, the learner and 2 actor processes for `iterations` iterations
# (no validation, no critic warm-up, so every iteration trains the layers it may) and prints
# its progress lines, which give env-steps/s and the collection and update seconds.
#
#   docs/bench/frozen_layers.sh [path/to/dronerace] [iterations] [out-dir]
set -eu
root=$(cd "$(dirname "$0")/../.." && pwd)
bin=${1:-$root/target/release/dronerace}
iterations=${2:-2}
out=${3:-$(mktemp -d)}
mkdir -p "$out"
[ -x "$bin" ] || { echo "no dronerace binary at $bin (cargo build --release first)"; exit 1; }
for frozen in encoder convolutions nothing; do
  config="$out/$frozen.toml"
  sed -e "s/^frozen = .*/frozen = \"$frozen\"/" \
      -e 's/^critic_warmup_iterations = .*/critic_warmup_iterations = 0/' \
      -e "s#^init_from = \"#init_from = \"$root/#" \
      -e 's/^every = .*/every = 0/' \
      "$root/experiments/vision/from-student.toml" > "$config"
  echo "== frozen = $frozen"
  "$bin" train --config "$config" --out "$out/$frozen" --iterations "$iterations" 2>&1 | grep '^iter'
done
