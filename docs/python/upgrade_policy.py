#!/usr/bin/env python3
"""Rewrite a dronerace policy file of format 2 as format 3 (the one dronerace reads now).

    python3 docs/python/upgrade_policy.py OLD.bin NEW.bin

Format 3 holds the observation layout as one object, `architecture.observation` = {frame,
line_points, line_spacing, gate_sight}; format 2 held its fields flat, beside options since removed
(obstacle gates, proximity readings, a privileged critic), which must be off for the file to convert.
Only the metadata changes: every tensor is copied byte for byte, so the policy acts exactly as before.
Standard library only (no numpy): it reads and writes the safetensors layout that dronerace writes,
with its `crc32` metadata entry (policy/src/safetensors.rs).
"""
import json
import struct
import sys
import zlib

REMOVED_OFF = {"obstacle_gates": 0, "proximity_gates": 0, "privileged_critic": False}
DROPPED = ("obstacle_order", "proximity_range")
LAYOUT_DEFAULTS = {"frame": "world", "line_points": 0, "line_spacing": 2.5, "gate_sight": "all"}


def compact(value):
    """JSON as serde_json writes it: no spaces, non-ASCII kept, keys in the order given."""
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False)


def checksum(metadata, entries, data):
    """dronerace's crc32: every metadata key and value, each tensor's name, dtype and shape
    (Rust's `[a, b]`), each followed by a zero byte, then the tensor bytes."""
    crc = 0
    for key in sorted(metadata):
        for field in (key, metadata[key]):
            crc = zlib.crc32(field.encode() + b"\0", crc)
    for name in sorted(entries):
        entry = entries[name]
        shape = "[" + ", ".join(str(d) for d in entry["shape"]) + "]"
        for field in (name, entry["dtype"], shape):
            crc = zlib.crc32(field.encode() + b"\0", crc)
    return f"{zlib.crc32(data, crc):08x}"


def header(metadata, entries):
    """The header dronerace writes: `__metadata__` (keys sorted) first, then the tensors in name
    order, each entry's keys sorted, padded with spaces to a multiple of 8 bytes."""
    parts = ['{"__metadata__":' + compact({k: metadata[k] for k in sorted(metadata)})]
    for name in sorted(entries):
        entry = entries[name]
        parts.append(compact(name) + ":" + compact({k: entry[k] for k in sorted(entry)}))
    text = (",".join(parts) + "}").encode()
    text += b" " * (-(8 + len(text)) % 8)
    return struct.pack("<Q", len(text)) + text


def upgrade_architecture(old):
    """Format 2's flat architecture as format 3's, or an error naming what cannot convert."""
    new = {k: old[k] for k in ("observation_dim", "action_dim", "hidden", "negative_slope")}
    for key, off in REMOVED_OFF.items():
        if old.get(key, off) != off:
            raise ValueError(f"architecture.{key} = {old[key]}: an option removed from dronerace; this policy needs the commit 4f9e33d")
    layout = dict(LAYOUT_DEFAULTS)
    if "observation_frame" in old:
        layout["frame"] = old["observation_frame"]
    for key in ("line_points", "line_spacing", "gate_sight"):
        if key in old:
            layout[key] = old[key]
    new["observation"] = layout
    new["agent"] = old.get("agent", "state")
    if "vision_previous_action" in old:
        new["vision_previous_action"] = old["vision_previous_action"]
    frames = old.get("frame_stack", {}).get("frames", 1)
    if frames != 1:
        raise ValueError(f"architecture.frame_stack sees {frames} frames: an option removed from dronerace; this policy needs the commit 2482eeb")
    known = set(new) | set(REMOVED_OFF) | set(DROPPED) | {"observation_frame", "line_points", "line_spacing", "gate_sight", "frame_stack"}
    unknown = set(old) - known
    if unknown:
        raise ValueError(f"architecture fields {sorted(unknown)} are not format 2's")
    return new


def upgrade(data):
    """The bytes of a format-2 policy file (or checkpoint) as format 3."""
    (length,) = struct.unpack("<Q", data[:8])
    raw = json.loads(data[8 : 8 + length])
    metadata = raw.pop("__metadata__")
    if metadata.get("format") != "dronerace-policy":
        raise ValueError("not a dronerace policy file")
    if metadata.get("format_version") != "2":
        raise ValueError(f"format {metadata.get('format_version')}, not 2")
    tensors = data[8 + length :]
    stored = metadata.pop("crc32")
    if header(dict(metadata, crc32=stored), raw) != data[: 8 + length] or checksum(metadata, raw, tensors) != stored:
        raise ValueError("the file is altered (its header or checksum is not as dronerace wrote it)")
    metadata["architecture"] = compact(upgrade_architecture(json.loads(metadata["architecture"])))
    metadata["format_version"] = "3"
    metadata["crc32"] = checksum(metadata, raw, tensors)
    return header(metadata, raw) + tensors


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__.splitlines()[2].strip())
    source, target = sys.argv[1:]
    with open(source, "rb") as f:
        data = f.read()
    try:
        upgraded = upgrade(data)
    except ValueError as e:
        sys.exit(f"{source}: {e}")
    with open(target, "wb") as f:
        f.write(upgraded)
    print(f"{source} → {target}: format 3")


if __name__ == "__main__":
    main()
