#!/usr/bin/env bash
# The main job on a disk that fills up: the run directory on a small tmpfs, filled to the last
# byte once the run has written a few checkpoints. The learner must stop the run with an
# error naming the failed writes (no restart loop), leave every checkpoint readable and no
# temporary file behind, lose no acknowledged task report, and resume once space is freed.
# Needs root (mount). BENCHMARKS.md, "Reliability", has the figures.
#
#   docs/bench/full_disk.sh target/release/dronerace [OUT_DIR]
set -u
bin=$(realpath "$1")
out=${2:-/tmp/dronerace-full-disk}
mkdir -p "$out"
disk=$(mktemp -d)
mount -t tmpfs -o size=96m tmpfs "$disk"
trap 'umount "$disk"; rmdir "$disk"' EXIT
run=$disk/run
cat > "$out/config.toml" <<'EOF'
checkpoint_every = 5
[eval]
every = 0
EOF
rows() { [ -f "$run/metrics.csv" ] && echo $(($(wc -l < "$run/metrics.csv") - 1)) || echo 0; }
start=$(date +%s)
"$bin" train --config "$out/config.toml" --out "$run" --iterations 400 > "$out/train.log" 2>&1 &
train=$!
while [ "$(rows)" -lt 20 ] && kill -0 $train 2>/dev/null; do sleep 1; done
filled_at=$(rows)
dd if=/dev/zero of="$disk/filler" bs=64k 2> /dev/null   # until the disk is full
echo "disk filled at iteration $filled_at: $(df -h "$disk" | tail -1)"
wait $train
status=$?
stopped=$(( $(date +%s) - start ))
echo "train exited with $status after ${stopped} s at iteration $(rows)"
grep -E "checkpoints in a row|checkpoint not written|error:" "$out/train.log" | tail -4
echo "temporary files left: $(find "$run" -name '*.tmp' | wc -l)"
readable=0; total=0
for ckpt in "$run"/checkpoints/*.bin; do
  total=$((total + 1))
  "$bin" export "$ckpt" --out "$out/probe.bin" > /dev/null 2>&1 && readable=$((readable + 1))
done
echo "checkpoints readable: $readable of $total"
rm -f "$disk/filler"
"$bin" train --resume "$run" --iterations 10 > "$out/resume.log" 2>&1
echo "resume exited with $? and ran to iteration $(rows)"
echo "acknowledged reports lost (log lines): $(grep -c 'acknowledged reports lost' "$out/train.log" "$out/resume.log" | awk -F: '{s += $2} END {print s}')"
