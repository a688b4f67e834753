"""dronerace from Python: the Rust simulator as a gymnasium vector environment, racetracks,
trained policies, the flight-stack racer and evaluation.

    import dronerace
    envs = dronerace.RaceVecEnv(96, seed=0)          # generated tracks, adaptive switching
    obs, infos = envs.reset(seed=0)
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())

    policy = dronerace.Policy.load("policies/generalist.bin")
    report = dronerace.evaluate(policy, ["Figure8"], runs=10)
"""

import gymnasium

from dronerace import tracks
from dronerace._core import Policy, Racer, Track
from dronerace.env import RaceEnv, RaceVecEnv
from dronerace.evaluation import evaluate

__all__ = ["Policy", "RaceEnv", "RaceVecEnv", "Racer", "Track", "evaluate", "tracks"]

# `gymnasium.make("dronerace/Race-v0", track="Figure8")`: one environment on one track.
if "dronerace/Race-v0" not in gymnasium.registry:
    gymnasium.register(id="dronerace/Race-v0", entry_point="dronerace.env:RaceEnv")
