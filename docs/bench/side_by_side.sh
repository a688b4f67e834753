#!/usr/bin/env bash
# One PPO gradient step, dronerace (burn) against PyTorch, on this machine, in one run.
# Alternates the two programs so that both see the same machine state, and prints the ratio of
# whole-step times (forward + backward + optimiser) for the paper and cpu profile shapes.
#
#   docs/bench/side_by_side.sh [path/to/dronerace] [rounds]          (from the repository root)
#   TORCH_BF16=1 docs/bench/side_by_side.sh ...   # the PyTorch side in bf16 (mixed precision)
#   PRECISION=bf16 TORCH_BF16=1 docs/bench/side_by_side.sh ...   # both sides, for a binary whose `bench learner` takes --precision
#
# PyTorch comes from a virtual environment at $BENCH_VENV (default ~/.cache/dronerace-bench-venv),
# created on first use with `pip install torch numpy` (a large download, a few minutes).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
bin=${1:-target/release/dronerace}
rounds=${2:-3}
venv=${BENCH_VENV:-$HOME/.cache/dronerace-bench-venv}
[ -x "$bin" ] || { echo "no dronerace binary at $bin (cargo build --release first)"; exit 1; }
if ! "$venv/bin/python" -c "import torch" 2>/dev/null; then
  echo "creating $venv with PyTorch (first use only)"
  python3 -m venv "$venv" && "$venv/bin/pip" install -q torch numpy
fi
threads=$(nproc)
ours() { # profile samples -> whole-step milliseconds
  "$bin" bench learner --profile "$1" --samples "$2" --repeats 5 ${PRECISION:+--precision $PRECISION} 2>/dev/null | tail -1 |
    sed -E 's/.*forward ([0-9.]+) ms, backward ([0-9.]+) ms, optimiser ([0-9.]+) ms.*/\1 \2 \3/' |
    awk '{printf "%.1f", $1 + $2 + $3}'
}
theirs() { # hidden samples -> median step milliseconds
  "$venv/bin/python" "$here/torch_step.py" --hidden "$1" --samples "$2" --repeats 5 --threads "$threads" ${TORCH_BF16:+--bf16} |
    sed -E 's/.*step median ([0-9.]+) ms.*/\1/'
}
echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $threads threads"
for shape in "paper 512 24000" "paper 512 4096" "cpu 256 4000"; do  # widths = the profiles' (cpu: 256×256)
  set -- $shape
  for r in $(seq "$rounds"); do
    a=$(ours "$1" "$3"); b=$(theirs "$2" "$3")
    awk -v p="$1" -v n="$3" -v a="$a" -v b="$b" -v r="$r" \
      'BEGIN { printf "%-5s %6d samples round %d: dronerace %8.1f ms  torch %8.1f ms  torch/dronerace %.2f\n", p, n, r, a, b, b / a }'
  done
done
