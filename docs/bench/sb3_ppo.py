"""Stable-Baselines3 PPO with the paper profile (SPEC §10) on this machine.

What a user would run instead of `dronerace train --config docs/bench/paper-spec-ppo.toml --in-process`: 96
environments × 250 steps per iteration, whole-rollout minibatch, 10 epochs, separate 512×512
LeakyReLU actor and critic, log std −0.5, Adam eps 1e-5, clip 0.2, max grad norm 0.5. The
environment is a trivial one with the race env's shapes (40 observations, 4 actions in [−1, 1])
and almost no arithmetic per step, so SB3's figure is an upper bound for SB3 on the real task.
Prints, per iteration, env-steps/s, the collection time and the update time.

    python sb3_ppo.py --iterations 6 --threads 2
"""
import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv


class Trivial(gym.Env):
    """40 numbers in, 4 actions out, a reward and a reset every 1,500 steps."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (40,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        self.x = self.np_random.standard_normal(40).astype(np.float32)
        return self.x, {}

    def step(self, action):
        self.t += 1
        self.x[:4] += 0.01 * action
        return self.x, float(-np.square(action).sum()), False, self.t >= 1500, {}


class Timer(BaseCallback):
    """Times each rollout (collection) and each update (the gap between rollouts)."""

    def _on_training_start(self):
        self.mark = time.perf_counter()
        self.update_start = None
        self.iteration = 0
        self.samples = self.model.n_steps * self.training_env.num_envs

    def _on_rollout_start(self):
        now = time.perf_counter()
        if self.update_start is not None:
            update = now - self.update_start
            total = now - self.mark
            print(f"iteration {self.iteration}: {self.samples / total:,.0f} env-steps/s, "
                  f"collection {self.collect:.2f} s, update {update:.2f} s", flush=True)
        self.mark = now

    def _on_rollout_end(self):
        self.update_start = time.perf_counter()
        self.collect = self.update_start - self.mark
        self.iteration += 1

    def _on_step(self):
        return True


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--iterations", type=int, default=6)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    env = DummyVecEnv([Trivial for _ in range(96)])
    model = PPO(
        "MlpPolicy", env, n_steps=250, batch_size=24000, n_epochs=10, learning_rate=3e-4,
        gamma=0.995, gae_lambda=0.95, clip_range=0.2, ent_coef=0.0, vf_coef=0.5, max_grad_norm=0.5,
        policy_kwargs=dict(net_arch=dict(pi=[512, 512], vf=[512, 512]), activation_fn=torch.nn.LeakyReLU,
                           log_std_init=-0.5, optimizer_kwargs=dict(eps=1e-5, weight_decay=1e-5)),
        device="cpu", verbose=0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    model.learn(total_timesteps=24000 * (a.iterations + 1), callback=Timer())


if __name__ == "__main__":
    main()
