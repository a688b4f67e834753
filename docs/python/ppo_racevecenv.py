"""PPO in PyTorch on dronerace.RaceVecEnv, in CleanRL's single-file style (ppo_continuous_action):
what a Python user writes to train on the Rust environments. Not part of the test suite.

The recipe is the cpu profile's (SPEC §10 as dronerace trains it): 96 environments x 250 steps
a rollout, 5 epochs of 4,000-sample minibatches, separate 256x256 LeakyReLU actor and critic,
state-independent log std from -0.5, Adam 3e-4 linearly annealed, gamma 0.99, lambda 0.95,
clip 0.2, value clip off, entropy 0, max grad norm 0.5, observations normalised by running
statistics. One track (Figure8) by default; `--track generated` trains on generated tracks
with the task controller's adaptive switching, as the thesis' generalist.

    pip install ./python torch
    python docs/python/ppo_racevecenv.py --total-steps 10000000 --out runs/ppo-python
        # writes progress.csv (steps, seconds, SPS, return, laps per episode) and the policy

Each iteration prints env steps, SPS (collection + update), mean episodic return and laps.
"""

import argparse
import csv
import pathlib
import time

import numpy as np
import torch
from torch import nn

import dronerace


class RunningNorm:
    """Running mean and variance of observations (Welford, batched), clipped to +-10 after."""

    def __init__(self, dim):
        self.mean, self.var, self.count = np.zeros(dim), np.ones(dim), 1e-4

    def update(self, x):
        batch_mean, batch_var, n = x.mean(0), x.var(0), len(x)
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        self.var = (self.var * self.count + batch_var * n + delta**2 * self.count * n / total) / total
        self.count = total

    def __call__(self, x):
        return np.clip((x - self.mean) / np.sqrt(self.var + 1e-8), -10.0, 10.0).astype(np.float32)


def mlp(inputs, outputs, hidden=256):
    return nn.Sequential(nn.Linear(inputs, hidden), nn.LeakyReLU(0.2), nn.Linear(hidden, hidden), nn.LeakyReLU(0.2),
                         nn.Linear(hidden, outputs))


class Agent(nn.Module):
    def __init__(self, obs_dim, act_dim):
        super().__init__()
        self.actor, self.critic = mlp(obs_dim, act_dim), mlp(obs_dim, 1)
        self.log_std = nn.Parameter(torch.full((act_dim,), -0.5))

    def dist(self, obs):
        return torch.distributions.Normal(self.actor(obs), self.log_std.exp())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--track", default="Figure8", help="a library name, a track file, or 'generated'")
    parser.add_argument("--total-steps", type=int, default=10_000_000)
    parser.add_argument("--num-envs", type=int, default=96)
    parser.add_argument("--num-steps", type=int, default=250)
    parser.add_argument("--minibatch", type=int, default=4000)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--out", default="runs/ppo-python")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    tracks = None if args.track == "generated" else args.track
    envs = dronerace.RaceVecEnv(args.num_envs, tracks=tracks, seed=args.seed, rollout_steps=args.num_steps)
    n, obs_dim = args.num_envs, envs.single_observation_space.shape[0]
    agent = Agent(obs_dim, 4)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)
    norm = RunningNorm(obs_dim)
    gamma, lam, clip = 0.99, 0.95, 0.2
    buf_obs = np.zeros((args.num_steps, n, obs_dim), np.float32)
    buf_act = np.zeros((args.num_steps, n, 4), np.float32)
    buf_logp, buf_rew, buf_val = (np.zeros((args.num_steps, n), np.float32) for _ in range(3))
    buf_done = np.zeros((args.num_steps, n), np.float32)  # the step before began a new episode
    # Next-step autoreset: a step after an episode's end only resets (reward 0); it is masked out.
    buf_valid = np.ones((args.num_steps, n), np.float32)

    raw, _ = envs.reset(seed=args.seed)
    norm.update(raw)
    obs, starting = norm(raw), np.zeros(n, bool)
    iterations = args.total_steps // (n * args.num_steps)
    started, steps = time.time(), 0
    with (out / "progress.csv").open("w", newline="") as f:
        log = csv.writer(f)
        log.writerow(["iteration", "env_steps", "seconds", "sps", "episodic_return", "laps_per_episode", "episodes"])
        for iteration in range(1, iterations + 1):
            for g in optimizer.param_groups:
                g["lr"] = args.lr * (1.0 - (iteration - 1) / iterations)
            returns, laps = [], []
            for t in range(args.num_steps):
                with torch.no_grad():
                    o = torch.from_numpy(obs)
                    dist = agent.dist(o)
                    action = dist.sample()
                    buf_logp[t] = dist.log_prob(action).sum(-1).numpy()
                    buf_val[t] = agent.critic(o).squeeze(-1).numpy()
                buf_obs[t], buf_act[t] = obs, action.numpy()
                buf_valid[t] = ~starting
                raw, reward, terminated, truncated, infos = envs.step(np.clip(buf_act[t], -1.0, 1.0))
                buf_rew[t] = reward
                # A truncated episode is bootstrapped from its last observation's value.
                if truncated.any():
                    with torch.no_grad():
                        last = agent.critic(torch.from_numpy(norm(raw[truncated]))).squeeze(-1).numpy()
                    buf_rew[t, truncated] += gamma * last
                buf_done[t] = terminated | truncated
                starting = terminated | truncated
                if "episode" in infos:
                    ended = infos["_episode"]
                    returns += infos["episode"]["r"][ended].tolist()
                    laps += infos["episode"]["laps"][ended].tolist()
                norm.update(raw)
                obs = norm(raw)
                steps += n
            with torch.no_grad():
                next_value = agent.critic(torch.from_numpy(obs)).squeeze(-1).numpy()
            advantages = np.zeros_like(buf_rew)
            gae = np.zeros(n, np.float32)
            for t in reversed(range(args.num_steps)):
                value_next = next_value if t == args.num_steps - 1 else buf_val[t + 1]
                # After an episode's end, the next row is a reset step: cut there.
                not_done = 1.0 - buf_done[t]
                delta = buf_rew[t] + gamma * value_next * not_done - buf_val[t]
                gae = delta + gamma * lam * not_done * gae
                # A reset step carries nothing: its advantage does not flow into the step before.
                gae = gae * buf_valid[t]
                advantages[t] = gae
            targets = advantages + buf_val
            valid = buf_valid.reshape(-1).astype(bool)
            b_obs = torch.from_numpy(buf_obs.reshape(-1, obs_dim)[valid])
            b_act = torch.from_numpy(buf_act.reshape(-1, 4)[valid])
            b_logp = torch.from_numpy(buf_logp.reshape(-1)[valid])
            b_adv = torch.from_numpy(advantages.reshape(-1)[valid])
            b_ret = torch.from_numpy(targets.reshape(-1)[valid])
            for _ in range(args.epochs):
                order = torch.randperm(len(b_obs))
                for start in range(0, len(order), args.minibatch):
                    idx = order[start:start + args.minibatch]
                    dist = agent.dist(b_obs[idx])
                    ratio = (dist.log_prob(b_act[idx]).sum(-1) - b_logp[idx]).exp()
                    adv = (b_adv[idx] - b_adv[idx].mean()) / (b_adv[idx].std() + 1e-8)
                    policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip)).mean()
                    value_loss = 0.5 * (agent.critic(b_obs[idx]).squeeze(-1) - b_ret[idx]).pow(2).mean()
                    optimizer.zero_grad()
                    (policy_loss + 0.5 * value_loss).backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
                    optimizer.step()
            seconds = time.time() - started
            mean_return = float(np.mean(returns)) if returns else float("nan")
            mean_laps = float(np.mean(laps)) if laps else float("nan")
            log.writerow([iteration, steps, round(seconds, 1), round(steps / seconds), round(mean_return, 2), round(mean_laps, 3),
                          len(returns)])
            f.flush()
            print(f"iter {iteration:4d} | {steps:>10d} steps | {steps / seconds:7.0f} SPS | return {mean_return:8.2f} | "
                  f"laps/ep {mean_laps:5.2f}", flush=True)
    torch.save({"agent": agent.state_dict(), "obs_mean": norm.mean, "obs_var": norm.var}, out / "agent.pt")


if __name__ == "__main__":
    main()
