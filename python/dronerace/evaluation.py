"""Evaluation as `dronerace eval` runs it (SPEC §9): deployments from perturbed starts, success
(at least one lap, no crash), S_pw and how each deployment ended."""

import json

import numpy as np

from dronerace import _core


def evaluate(policy, tracks, runs=25, steps=1000, seed=0):
    """Evaluates `policy` — a `dronerace.Policy` or a callable from a float32 array of state
    observations (n x observation_dim) to n x 4 actions, called once per step with every
    deployment still flying — on `tracks` (a list of `Track`s, library names or paths).

    Returns `dronerace eval`'s report as a dict: `success_rate`, `s_pw`, `mean_lap`,
    `fastest_lap`, `outcomes`, and per track its deployments (`success`, `lap_times`, `crash`, …).
    """
    if isinstance(tracks, (str, _core.Track)):
        tracks = [tracks]
    if isinstance(policy, _core.Policy):
        text = _core.evaluate_policy(policy, list(tracks), runs=runs, steps=steps, seed=seed)
    elif callable(policy):
        def act(observations):
            return np.ascontiguousarray(policy(observations), dtype=np.float32)

        name = getattr(policy, "__name__", type(policy).__name__)
        text = _core.evaluate_callable(act, list(tracks), runs=runs, steps=steps, seed=seed, name=name)
    else:
        raise TypeError(f"policy: a dronerace.Policy or a callable, not {type(policy).__name__}")
    return json.loads(text)
