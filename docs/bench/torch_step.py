"""One PPO gradient step in PyTorch, shaped like `dronerace bench learner`.

Actor 40 -> H -> H -> 4 and critic 40 -> H -> H -> 1 (LeakyReLU 0.01), a state-independent
log-std, clipped surrogate + 0.5 * value loss, backward, global-norm clip 0.5, Adam (eps 1e-5,
weight decay 1e-5). Gaussian data. Prints the median step time and GFLOP/s (forward+backward
multiply-adds counted as 3x the forward, the same rule for both programs).

    python docs/bench/torch_step.py --hidden 512 --samples 24000 --repeats 5 --threads 2 [--bf16]

--bf16 runs the forward pass (and so the backward's products) under
torch.autocast("cpu", dtype=torch.bfloat16): bf16 products, f32 parameters and Adam.
"""
import contextlib
import argparse, statistics, time

import torch
from torch import nn


def mlp(i, h, o):
    return nn.Sequential(nn.Linear(i, h), nn.LeakyReLU(0.01), nn.Linear(h, h), nn.LeakyReLU(0.01), nn.Linear(h, o))


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--hidden", type=int, default=512)
    p.add_argument("--samples", type=int, default=24000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--bf16", action="store_true", help="mixed precision: bf16 products under autocast")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    obs_dim, act_dim, h, n = 40, 4, a.hidden, a.samples
    actor, critic = mlp(obs_dim, h, act_dim), mlp(obs_dim, h, 1)
    log_std = nn.Parameter(torch.full((act_dim,), -0.5))
    params = list(actor.parameters()) + list(critic.parameters()) + [log_std]
    opt = torch.optim.Adam(params, lr=3e-4, eps=1e-5, weight_decay=1e-5)
    obs, act = torch.randn(n, obs_dim), torch.randn(n, act_dim)
    old_logp, adv, ret = torch.randn(n), torch.randn(n), torch.randn(n)

    cast = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if a.bf16 else contextlib.nullcontext

    def step():
        with cast():  # the forward pass; its products' backward runs in the same precision
            mean = actor(obs).float()
            v = critic(obs).squeeze(-1).float()
        std = log_std.exp()
        logp = (-((act - mean) ** 2) / (2 * std ** 2) - log_std - 0.9189385332046727).sum(-1)
        ratio = (logp - old_logp).exp()
        a_n = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg = -torch.min(a_n * ratio, a_n * ratio.clamp(0.8, 1.2)).mean()
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
    macs = n * 2 * (obs_dim * h + h * h) + n * h * (act_dim + 1)
    gflops = 3 * 2 * macs / med / 1e9
    print(f"torch {torch.__version__}{' bf16-autocast' if a.bf16 else ''} hidden {h} samples {n} threads {a.threads}: "
          f"step median {med * 1e3:.1f} ms (min {min(times) * 1e3:.1f}, max {max(times) * 1e3:.1f}), {gflops:.1f} GFLOP/s")


if __name__ == "__main__":
    main()
