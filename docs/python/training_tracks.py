#!/usr/bin/env python3
"""Write the tracks a run's environments were training on as track files.

    python3 docs/python/training_tracks.py RUN/taskctl.snapshot train-tracks
    dronerace eval --policy RUN/checkpoints/ckpt-N.bin --tracks train-tracks --out ev

The task controller's snapshot (`DRTASKS` then JSON) holds every environment's current track.
Evaluating a policy on them beside the validation and test sets separates memorising (it flies
the tracks it trained on, not new ones) from under-fitting (it fails both). Standard library
only (Python 3.11+).
"""
import json
import math
import pathlib
import sys


def snapshot_tracks(path):
    """The current track of every environment slot, in slot order, duplicates dropped."""
    raw = pathlib.Path(path).read_bytes()
    if not raw.startswith(b"DRTASKS"):
        sys.exit(f"{path}: not a task-controller snapshot (no DRTASKS header)")
    state, _ = json.JSONDecoder().raw_decode(raw[raw.index(b"{"):].decode("utf-8", "replace"))
    seen, tracks = set(), []
    for slot in state["slots"]:
        track = slot["track"]
        if track["name"] not in seen:
            seen.add(track["name"])
            tracks.append(track)
    return tracks


def track_file(track):
    """A track as the TOML track-file format writes it (yaw in degrees)."""
    vec = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"
    lines = [f'name = "{track["name"]}"', ""]
    for gate in track["gates"]:
        lines += ["[[gate]]", f"position = {vec(gate['position'])}", f"yaw_deg = {math.degrees(gate['yaw'])!r}", ""]
    start = track["start"]
    lines += ["[start]", f"position = {vec(start['position'])}", f"yaw_deg = {math.degrees(start['yaw'])!r}", ""]
    arena = track["arena"]
    lines += ["[arena]", f"min = {vec(arena['min'])}", f"max = {vec(arena['max'])}", ""]
    return "\n".join(lines)


def main():
    if len(sys.argv) != 3:
        sys.exit("usage: training_tracks.py RUN/taskctl.snapshot OUT_DIR")
    out = pathlib.Path(sys.argv[2])
    out.mkdir(parents=True, exist_ok=True)
    tracks = snapshot_tracks(sys.argv[1])
    for i, track in enumerate(tracks):
        (out / f"{i:03}-{track['name']}.toml").write_text(track_file(track))
    print(f"wrote {len(tracks)} tracks to {out}")


if __name__ == "__main__":
    main()
