"""How far a state policy is from mirror symmetry on the states it flies through.

    python3 docs/notebook/scripts/mirror_asymmetry.py TRACKS POLICY [POLICY ...]

Each policy flies the tracks of TRACKS (a directory of track files) deterministically from the
evaluation's starts (nominal vehicle) for 600 steps in 64 environments; on every 10th step's
observations it acts on the observation and on its mirror image (sim::mirror's map, restated
below for the heading frame with line points), and prints the mean absolute difference between
the action on the mirror and the mirror of the action, per action component, in units of the
action range [-1, 1]. A policy that commutes with the reflection scores 0. It also prints the
mean sideways velocity in the heading frame (observation number 7) over the same states: on
tracks of either handedness a symmetric policy's is near 0, one that flies crabbed to one side
has it far from 0, and the mirrors of its states are states it never visits.
"""
import sys

import numpy as np

import dronerace

# sim::mirror: vectors (1, -1, 1), pseudo-vectors (-1, 1, -1); action [thrust, roll, pitch, yaw].
VECTOR, PSEUDO = [1, -1, 1], [-1, 1, -1]
ACTION_SIGNS = np.array([1, -1, 1, -1], dtype=np.float32)


def mirror_map(dim):
    """Source index and sign of each mirrored number, as sim::ObservationLayout::mirror."""
    source, sign = [], []

    def in_place(signs):
        for s in signs:
            source.append(len(source))
            sign.append(s)

    def corners():
        start = len(source)
        for corner in [1, 0, 3, 2]:
            for k, s in enumerate(VECTOR):
                source.append(start + 3 * corner + k)
                sign.append(s)

    in_place(VECTOR)  # attitude column 0
    in_place(PSEUDO)  # attitude column 1
    in_place(VECTOR)  # velocity
    in_place(PSEUDO)  # body rates
    in_place(ACTION_SIGNS)  # previous action
    corners()  # target gate
    corners()  # next gate
    while len(source) < dim:
        in_place(VECTOR)  # racing-line points
    return np.array(source), np.array(sign, dtype=np.float32)


def asymmetry(policy, tracks):
    env = dronerace.RaceVecEnv(64, tracks=tracks, seed=1, randomize=False)
    obs, _ = env.reset(seed=1)
    source, sign = mirror_map(obs.shape[1])
    gaps, sideways = [], []
    for step in range(600):
        actions = policy.act(obs)
        if step % 10 == 0:
            mirrored = obs[:, source] * sign
            gaps.append(np.abs(policy.act(mirrored) - actions * ACTION_SIGNS))
            sideways.append(obs[:, 7])
        obs, *_ = env.step(actions)
    return np.concatenate(gaps).mean(axis=0), np.concatenate(sideways).mean()


def main():
    tracks, policies = sys.argv[1], sys.argv[2:]
    print("| policy | thrust | roll rate | pitch rate | yaw rate | mean sideways velocity (m/s) |")
    print("|---|---:|---:|---:|---:|---:|")
    for path in policies:
        gap, sideways = asymmetry(dronerace.Policy.load(path), tracks)
        print(f"| {path} | " + " | ".join(f"{g:.3f}" for g in gap) + f" | {sideways:+.2f} |")


if __name__ == "__main__":
    main()
