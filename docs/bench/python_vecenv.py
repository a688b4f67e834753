"""Env-steps/s of dronerace.RaceVecEnv from Python, as `dronerace bench sim` measures the Rust
side: 96 environments on the library tracks (round robin), the agents' training environments,
uniform random actions (64 batches drawn beforehand, cycled), only the step calls timed.

    python docs/bench/python_vecenv.py --envs 96 --steps 3000 [--obs vision]
    dronerace bench sim --envs 96 --steps 3000 [--obs vision]     # the same, from Rust

The Python figure includes what a Python user pays per step: the action array's conversion,
the infos dict, and the interpreter around the call.
"""

import argparse
import time

import numpy as np

import dronerace


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=96)
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--obs", choices=["state", "vision"], default="state")
    parser.add_argument("--rounds", type=int, default=1, help="timed rounds (each prints its figure)")
    args = parser.parse_args()
    names = dronerace.tracks.library_names()
    tracks = [names[i % len(names)] for i in range(args.envs)]
    envs = dronerace.RaceVecEnv(args.envs, tracks=tracks, seed=0, switching="none", observation=args.obs)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1.0, 1.0, size=(args.envs, 4)).astype(np.float32) for _ in range(64)]
    envs.reset(seed=0)
    for _ in range(100):  # warm up the thread pool and caches
        envs.step(actions[0])
    for _ in range(args.rounds):
        episodes, seconds = 0, 0.0
        for k in range(args.steps):
            started = time.perf_counter()
            _, _, _, _, infos = envs.step(actions[k % len(actions)])
            seconds += time.perf_counter() - started
            if "_episode" in infos:
                episodes += int(infos["_episode"].sum())
        rate = args.envs * args.steps / seconds
        print(f"python RaceVecEnv: random actions, {args.obs} observations, {args.envs} envs x {args.steps} steps: "
              f"{rate:.0f} env-steps/s, {episodes} episodes ended, {seconds:.2f} s")


if __name__ == "__main__":
    main()
