"""Checks the Python package against the Rust side; run by tests/python_package.rs, which
writes what the Rust side did (not a pytest module: it needs those files).

    python against_rust.py vecenv REFERENCE.json
        RaceVecEnv flies the actions sim::VecEnv (training's environment) flew and gets the same
        observations, rewards, terminations and truncations — one step later for an environment
        after each of its resets, as next-step autoreset inserts the reset step.
    python against_rust.py eval POLICY TRACK EVAL_JSON TRAJECTORY_DIR
        `dronerace eval`'s deployments: a Racer fed each recorded state builds the observation on
        which Policy.act gives the recorded action, with the recorded target gate and laps; and
        dronerace.evaluate with Policy.act as a Python callable flies the same laps.
"""

import csv
import json
import pathlib
import sys

import numpy as np

import dronerace


def check_vecenv(reference_path):
    ref = json.loads(pathlib.Path(reference_path).read_text())
    n, steps = ref["num_envs"], len(ref["actions"])
    as_array = lambda key: np.array(ref[key], dtype=np.float32)
    actions, observations, final_observations = as_array("actions"), as_array("observations"), as_array("final_observations")
    rewards = as_array("rewards")
    terminated, truncated = np.array(ref["terminated"]), np.array(ref["truncated"])
    envs = dronerace.RaceVecEnv(n, tracks=ref["tracks"], seed=ref["seed"], switching="none")
    obs, _ = envs.reset(seed=ref["seed"])
    assert np.array_equal(obs, np.array(ref["initial_observations"], dtype=np.float32)), "first observations"
    k = np.zeros(n, dtype=int)  # the Rust step each environment flies next
    resetting = np.zeros(n, dtype=bool)
    resets = 0
    while (k < steps).any():
        row = np.stack([actions[min(k[i], steps - 1)][i] for i in range(n)])
        obs, rew, term, trunc, _ = envs.step(row)
        for i in range(n):
            if k[i] >= steps:
                continue
            if resetting[i]:
                # The reset step: the first observation of the episode Rust began at step k - 1.
                assert np.array_equal(obs[i], observations[k[i] - 1][i]) and rew[i] == 0 and not (term[i] or trunc[i]), (i, k[i])
                resetting[i] = False
                resets += 1
                continue
            t = k[i]
            done = terminated[t][i] or truncated[t][i]
            expected = final_observations[t][i] if done else observations[t][i]
            assert np.array_equal(obs[i], expected), f"env {i} step {t}: observation"
            assert (rew[i], term[i], trunc[i]) == (rewards[t][i], terminated[t][i], truncated[t][i]), f"env {i} step {t}"
            resetting[i] = done
            k[i] += 1
    assert resets > 0, "the actions ended no episode: autoreset was not exercised"
    print(f"vecenv: {n} environments x {steps} steps identical, {resets} resets")


def check_eval(policy_path, track, eval_json, trajectory_dir):
    policy = dronerace.Policy.load(policy_path)
    track = dronerace.tracks.load(track)
    report = json.loads(pathlib.Path(eval_json).read_text())
    recorded = sorted(pathlib.Path(trajectory_dir).glob("*.csv"))
    runs = report["config"]["runs"]
    assert len(recorded) == runs, (len(recorded), runs)
    largest = 0.0
    for path in recorded:
        racer = dronerace.Racer(track, policy=policy)
        with path.open() as f:
            rows = list(csv.DictReader(f))
        for step, row in enumerate(rows):
            value = lambda *keys: [float(row[key]) for key in keys]
            obs = racer.observe(value("x", "y", "z"), value("vx", "vy", "vz"), value("qw", "qx", "qy", "qz"), value("p", "q", "r"))
            assert (racer.target_gate, racer.laps) == (int(float(row["target_gate"])), int(float(row["laps"]))), (path.name, step)
            if row["a0"] == "":
                break  # the state after the last step
            flown = np.array(value("a0", "a1", "a2", "a3"), dtype=np.float32)
            acted = policy.act(obs[None, :])[0]
            largest = max(largest, float(np.abs(acted - flown).max()))
            assert np.allclose(acted, flown, atol=1e-5), (path.name, step, acted, flown)
            racer.acted(flown)
    from_python = dronerace.evaluate(policy.act, [track], runs=runs, steps=report["config"]["steps"], seed=report["config"]["seed"])
    laps = lambda r: [d["lap_times"] for d in r["tracks"][0]["deployments"]]
    assert laps(from_python) == laps(report), (laps(from_python), laps(report))
    print(f"eval: {runs} deployments, {sum(len(l) for l in laps(report))} laps as dronerace eval; largest action difference {largest:.2e}")


if __name__ == "__main__":
    command, *args = sys.argv[1:]
    {"vecenv": check_vecenv, "eval": check_eval}[command](*args)
