#!/usr/bin/env python3
"""Open a dronerace policy file or checkpoint with the `safetensors` package and act with it in numpy.

    pip install numpy safetensors
    python3 docs/python/open_policy.py policies/generalist.bin          # what is inside
    python3 docs/python/open_policy.py POLICY --check expected.json      # compare with dronerace

The layout (see policy/src/blob.rs): layer i of the actor is `x @ actor.<i>.weight + actor.<i>.bias`,
LeakyReLU between layers and none after the last; its output is the action mean (the critic the same,
output the value). Observations are raw SB observations (SPEC §5), normalised first with
`clip((x - normalizer.mean) / sqrt(normalizer.var + epsilon), -clip, clip)`.
"""
import argparse
import json
import sys

import numpy as np
from safetensors import safe_open


def load(path):
    """Metadata and policy tensors (a checkpoint's other sections are left out)."""
    with safe_open(path, framework="np") as f:
        metadata = f.metadata()
        tensors = {name: f.get_tensor(name) for name in f.keys() if not name.startswith("section.")}
    if metadata.get("format") != "dronerace-policy":
        sys.exit(f"{path}: not a dronerace policy (format {metadata.get('format')!r})")
    return metadata, tensors


def act(metadata, tensors, observations):
    """Deterministic action means and values for raw observations of shape [n, observation_dim]."""
    architecture = json.loads(metadata["architecture"])
    normalizer = json.loads(metadata["normalizer"])
    scale = np.sqrt(tensors["normalizer.var"] + normalizer["epsilon"])
    x = np.clip((observations - tensors["normalizer.mean"]) / scale, -normalizer["clip"], normalizer["clip"])
    layers = len(architecture["hidden"]) + 1

    def mlp(net):
        h = x
        for i in range(layers):
            h = h @ tensors[f"{net}.{i}.weight"].astype(np.float64) + tensors[f"{net}.{i}.bias"]
            if i < layers - 1:
                h = np.where(h > 0, h, architecture["negative_slope"] * h)
        return h

    return mlp("actor"), mlp("critic")[:, 0]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", help="policy file or checkpoint")
    parser.add_argument("--check", help="JSON with observations, means and values computed by dronerace")
    parser.add_argument("--tolerance", type=float, default=1e-4)
    args = parser.parse_args()
    metadata, tensors = load(args.policy)
    print(f"{args.policy}: policy version {metadata['policy_version']}, architecture {metadata['architecture']}")
    for name, t in sorted(tensors.items()):
        print(f"  {name:20} {t.dtype} {list(t.shape)}")
    if args.check:
        with open(args.check) as f:
            expected = json.load(f)
        means, values = act(metadata, tensors, np.asarray(expected["observations"], dtype=np.float64))
        error = max(np.abs(means - np.asarray(expected["means"])).max(), np.abs(values - np.asarray(expected["values"])).max())
        print(f"largest difference from dronerace: {error:.2e} (tolerance {args.tolerance:g})")
        if not error <= args.tolerance:
            sys.exit(1)


if __name__ == "__main__":
    main()
