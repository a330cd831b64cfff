#!/usr/bin/env python3
"""The update `cargo bench -p hac-nn --bench update` and `hac bench update` time, written in
PyTorch, for a side-by-side comparison on the same machine (docs/RESULTS.md, "Learner updates
on several threads").

One HAC level update as hac-nn's `LevelLearner::update` does it, pendulum level 0 of 2 by
default (state 3, goal 2, action 1), batch 1024, hidden layers 3 x 64, no target networks:

- critic step: y = clamp(r + gamma * (1 - terminal) * Q(s', g, pi(s', g)), -H, 0), held
  constant; minimise the mean squared error of Q(s, g, a) to y; one Adam step;
- actor step: minimise -mean Q(s, g, pi(s, g)) through the just-updated critic (its parameters
  fixed); one Adam step.

The actor's output is tanh * half range + offset; the critic's is -H * sigmoid(x + q_offset),
q_offset = -ln(H / 0.067 - 1). Float32, on the CPU, with `torch.set_num_threads(t)` for each
thread count asked for. Needs PyTorch (`pip install torch`); not run by any test.

    python3 crates/nn/benches/pytorch_update.py --threads 1,2 --seconds 5
"""

import argparse
import json
import math
import time

import torch
from torch import nn


def mlp(sizes):
    layers = []
    for i, (a, b) in enumerate(zip(sizes, sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class Actor(nn.Module):
    def __init__(self, state, goal, action, hidden, half_range):
        super().__init__()
        self.net = mlp([state + goal, *hidden, action])
        self.half_range = half_range

    def forward(self, s, g):
        return torch.tanh(self.net(torch.cat([s, g], dim=1))) * self.half_range


class Critic(nn.Module):
    def __init__(self, state, goal, action, hidden, horizon):
        super().__init__()
        self.net = mlp([state + goal + action, *hidden, 1])
        self.horizon = horizon
        self.q_offset = -math.log(horizon / 0.067 - 1.0)

    def forward(self, s, g, a):
        x = self.net(torch.cat([s, g, a], dim=1))
        return -self.horizon * torch.sigmoid(x + self.q_offset)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--state", type=int, default=3)
    p.add_argument("--goal", type=int, default=2)
    p.add_argument("--action", type=int, default=1)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--hidden", default="64,64,64")
    p.add_argument("--horizon", type=float, default=20.0)
    p.add_argument("--gamma", type=float, default=0.98)
    p.add_argument("--threads", default="1,2")
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    hidden = [int(h) for h in args.hidden.split(",")]

    torch.manual_seed(1)
    n = args.batch
    s = torch.rand(n, args.state) * 2 - 1
    s2 = torch.rand(n, args.state) * 2 - 1
    g = torch.rand(n, args.goal) * 2 - 1
    a = torch.rand(n, args.action) * 2 - 1
    reached = (torch.rand(n, 1) < 0.2).float()
    r = reached - 1.0
    terminal = reached

    rows = []
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        torch.manual_seed(1)
        actor = Actor(args.state, args.goal, args.action, hidden, 2.0)
        critic = Critic(args.state, args.goal, args.action, hidden, args.horizon)
        actor_opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
        critic_opt = torch.optim.Adam(critic.parameters(), lr=1e-3)

        def update():
            with torch.no_grad():
                q_next = critic(s2, g, actor(s2, g))
                y = (r + args.gamma * (1.0 - terminal) * q_next).clamp(-args.horizon, 0.0)
            critic_loss = ((critic(s, g, a) - y) ** 2).mean()
            critic_opt.zero_grad(set_to_none=True)
            critic_loss.backward()
            critic_opt.step()
            for param in critic.parameters():
                param.requires_grad_(False)
            actor_loss = -critic(s, g, actor(s, g)).mean()
            actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            actor_opt.step()
            for param in critic.parameters():
                param.requires_grad_(True)

        warm = time.perf_counter()
        while time.perf_counter() - warm < 0.5:
            update()
        start = time.perf_counter()
        updates = 0
        while updates == 0 or time.perf_counter() - start < args.seconds:
            update()
            updates += 1
        ms = (time.perf_counter() - start) * 1e3 / updates
        rows.append({"threads": threads, "updates": updates, "ms_per_update": ms})

    report = {"torch": torch.__version__, "batch": n, "hidden": hidden, "rows": rows}
    if args.json:
        print(json.dumps(report))
        return
    print(f"PyTorch {torch.__version__}, batch {n}, hidden {args.hidden}")
    print("| threads | ms/update |")
    print("| --- | --- |")
    for row in rows:
        print(f"| {row['threads']} | {row['ms_per_update']:.3f} |")


if __name__ == "__main__":
    main()
