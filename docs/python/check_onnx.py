"""Run an exported policy (`dronerace export --format onnx`) with ONNX Runtime and compare its
actions with dronerace's on the same observations.

    pip install onnxruntime numpy
    python docs/python/check_onnx.py policy.onnx observations.json expected.json [--tolerance 1e-5]

`observations.json` is a list of raw observations, `expected.json` the list of actions dronerace
took on them. Prints the largest difference; exits non-zero above the tolerance.
"""
import argparse, json, sys

import numpy as np
import onnxruntime as ort


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("model")
    p.add_argument("observations")
    p.add_argument("expected")
    p.add_argument("--tolerance", type=float, default=1e-5)
    a = p.parse_args()
    session = ort.InferenceSession(a.model, providers=["CPUExecutionProvider"])
    observations = np.asarray(json.load(open(a.observations)), dtype=np.float32)
    expected = np.asarray(json.load(open(a.expected)), dtype=np.float32)
    (actions,) = session.run(["action"], {"observation": observations})
    worst = float(np.max(np.abs(actions - expected)))
    print(f"{len(observations)} observations: largest |onnxruntime - dronerace| = {worst:.3g}")
    sys.exit(0 if worst <= a.tolerance else 1)


if __name__ == "__main__":
    main()
