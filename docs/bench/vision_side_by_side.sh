#!/usr/bin/env bash
# The vision agent's PPO gradient step (SPEC §5: CNN actor on 84×84 images, MLP critic on the
# state), dronerace (burn) against PyTorch on this machine in one run: the CNN companion of
# docs/bench/side_by_side.sh, alternating the two programs and printing the ratio of
# whole-step times (forward + backward + optimiser).
#
#   docs/bench/vision_side_by_side.sh [path/to/dronerace] [rounds] [samples...]
#
# PyTorch comes from the same virtual environment as the shared script ($BENCH_VENV, default
# ~/.cache/dronerace-bench-venv; created on first use with `pip install torch numpy`).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
bin=${1:-target/release/dronerace}
rounds=${2:-3}
shift 2 2>/dev/null || true
samples=${*:-256 1024}
venv=${BENCH_VENV:-$HOME/.cache/dronerace-bench-venv}
[ -x "$bin" ] || { echo "no dronerace binary at $bin (cargo build --release first)"; exit 1; }
if ! "$venv/bin/python" -c "import torch" 2>/dev/null; then
  echo "creating $venv with PyTorch (first use only)"
  python3 -m venv "$venv" && "$venv/bin/pip" install -q torch numpy
fi
threads=$(nproc)
ours() { # profile samples -> whole-step milliseconds
  "$bin" bench learner --agent vision --profile "$1" --samples "$2" --repeats 3 2>/dev/null | tail -1 |
    sed -E 's/.*forward ([0-9.]+) ms, backward ([0-9.]+) ms, optimiser ([0-9.]+) ms.*/\1 \2 \3/' |
    awk '{printf "%.1f", $1 + $2 + $3}'
}
theirs() { # hidden samples -> median step milliseconds
  "$venv/bin/python" "$here/torch_cnn_step.py" --hidden "$1" --samples "$2" --repeats 3 --threads "$threads" |
    sed -E 's/.*step median ([0-9.]+) ms.*/\1/'
}
echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $threads threads"
for n in $samples; do
  for shape in "paper 512" "cpu 256"; do
    set -- $shape
    for r in $(seq "$rounds"); do
      a=$(ours "$1" "$n"); b=$(theirs "$2" "$n")
      awk -v p="$1" -v n="$n" -v a="$a" -v b="$b" -v r="$r" \
        'BEGIN { printf "vision %-5s %6d samples round %d: dronerace %8.1f ms  torch %8.1f ms  torch/dronerace %.2f\n", p, n, r, a, b, b / a }'
    done
  done
done
