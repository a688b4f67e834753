"""One PPO gradient step of the vision agent in PyTorch, shaped like
`dronerace bench learner --agent vision` (SPEC §5).

Actor: CNN 32@8x8/4, 64@4x4/2, 64@3x3/1 (LeakyReLU 0.01 after each), flatten, linear -> 128,
LeakyReLU, concatenated with 12 proprioceptive inputs, MLP 140 -> H -> H -> 4. Critic: MLP
40 -> H -> H -> 1. State-independent log-std; clipped surrogate + 0.5 * value loss, backward,
global-norm clip 0.5, Adam (eps 1e-5, weight decay 1e-5). Images drawn from the renderer's
grey levels, the rest Gaussian. Prints the median step time and GFLOP/s (forward + backward
multiply-adds counted as 3x the forward, the same rule as dronerace).

    python torch_cnn_step.py --hidden 512 --samples 256 --repeats 3 --threads 2
"""
import argparse, statistics, time

import torch
from torch import nn


def mlp(i, h, o):
    return nn.Sequential(nn.Linear(i, h), nn.LeakyReLU(0.01), nn.Linear(h, h), nn.LeakyReLU(0.01), nn.Linear(h, o))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--hidden", type=int, default=512)
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    state_dim, proprio_dim, act_dim, h, n = 40, 12, 4, a.hidden, a.samples
    cnn = nn.Sequential(
        nn.Conv2d(1, 32, 8, 4), nn.LeakyReLU(0.01),
        nn.Conv2d(32, 64, 4, 2), nn.LeakyReLU(0.01),
        nn.Conv2d(64, 64, 3, 1), nn.LeakyReLU(0.01),
        nn.Flatten(), nn.Linear(64 * 7 * 7, 128), nn.LeakyReLU(0.01),
    )
    actor, critic = mlp(128 + proprio_dim, h, act_dim), mlp(state_dim, h, 1)
    log_std = nn.Parameter(torch.full((act_dim,), -0.5))
    params = list(cnn.parameters()) + list(actor.parameters()) + list(critic.parameters()) + [log_std]
    opt = torch.optim.Adam(params, lr=3e-4, eps=1e-5, weight_decay=1e-5)
    levels = torch.tensor([0.0, 0.0, 0.0, 0.0, 55 / 255, 155 / 255, 1.0])
    images = levels[torch.randint(0, len(levels), (n, 1, 84, 84))]
    proprio, states, act = torch.randn(n, proprio_dim), torch.randn(n, state_dim), torch.randn(n, act_dim)
    old_logp, adv, ret = torch.randn(n), torch.randn(n), torch.randn(n)

    def step():
        mean = actor(torch.cat([cnn(images), proprio], dim=1))
        std = log_std.exp()
        logp = (-((act - mean) ** 2) / (2 * std ** 2) - log_std - 0.9189385332046727).sum(-1)
        ratio = (logp - old_logp).exp()
        a_n = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = -torch.min(a_n * ratio, a_n * ratio.clamp(0.8, 1.2)).mean()
        v = critic(states).squeeze(-1)
        loss = pg + 0.5 * ((ret - v) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(params, 0.5)
        opt.step()

    step()
    times = []
    for _ in range(a.repeats):
        t = time.perf_counter(); step(); times.append(time.perf_counter() - t)
    med = statistics.median(times)
    conv = 20 * 20 * 32 * 64 + 9 * 9 * 64 * 512 + 7 * 7 * 64 * 576
    macs = n * (conv + 3136 * 128 + (140 * h + h * h + h * act_dim) + (state_dim * h + h * h + h))
    gflops = 3 * 2 * macs / med / 1e9
    print(f"torch {torch.__version__} vision hidden {h} samples {n} threads {a.threads}: "
          f"step median {med * 1e3:.1f} ms (min {min(times) * 1e3:.1f}, max {max(times) * 1e3:.1f}), {gflops:.1f} GFLOP/s")


if __name__ == "__main__":
    main()
