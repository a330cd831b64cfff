#!/usr/bin/env python3
"""The public PyTorch port of HIRO (github.com/watakandai/hiro_pytorch, commit 5a92a28, used
unmodified) trained on a Python transcription of this project's pendulum, to tell whether a loss
of `--algo hiro` on the pendulum is the algorithm's or this code's (docs/RESULTS.md, "HIRO on the
pendulum: the public port of HIRO").

The pendulum is the one docs/ENVIRONMENTS.md defines (hinge at 0.6 m, 0.5 m massless pole, 1 kg
sphere of radius 0.05 m, damping 0.1, torque in [-2, 2], dt 0.002 s semi-implicit Euler, 10 steps
per action; state `[cos q, sin q, qdot]`; goal `[q, qdot]` within 9.5 degrees and 0.6 rad/s;
starts anywhere but near upright; training goals near upright, the test goal upright and still;
-1 per step, 0 at the step that reaches the goal, which ends the episode; 1000 actions).

The port runs as its `main.py` trains (its Trainer loop, its defaults: 2,500 random steps
first, 0.1 scale on the high level's rewards, exploration noise 1.0 absolute, networks 300 x
300, the Huber loss), with its subgoal space taken as the state's first coordinates as the port
does: here the whole state `[cos q, sin q, qdot]`, bounded by `[1, 1, 15]`. What the driver
adds: the environment, a stub for the port's tensorboard import, the port's batched low-level
policy given back its action axis for a 1-D action, and test rounds of greedy episodes against
the test goal.

    git clone https://github.com/watakandai/hiro_pytorch /tmp/hiro_pytorch
    pip install torch numpy
    PYTHONPATH=/tmp/hiro_pytorch python3 crates/agent/examples/hiro_port_pendulum.py 0 300

usage: hiro_port_pendulum.py SEED EPISODES [--warmup N] [--scale R] [--test-every N]
       [--test-episodes N]; prints a CSV row per test round. Not run by any test.
"""
import math
import sys
import types
import time
import argparse

import numpy as np
import torch

# The port's utils import tensorboard for its logger; this driver logs itself.
tb = types.ModuleType("torch.utils.tensorboard")
tb.SummaryWriter = object
sys.modules["torch.utils.tensorboard"] = tb

import hiro.models as models  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("seed", type=int)
ap.add_argument("episodes", type=int)
ap.add_argument("--warmup", type=int, default=2500)
ap.add_argument("--scale", type=float, default=0.1)
ap.add_argument("--test-every", type=int, default=50)
ap.add_argument("--test-episodes", type=int, default=50)
args = ap.parse_args()

torch.set_num_threads(1)
np.random.seed(args.seed)
torch.manual_seed(args.seed)

# --- the pendulum, as the project defines it -----------------------------------------------
L, M, R, B, G = 0.5, 1.0, 0.05, 0.1, 9.81
I = M * (L * L + 0.4 * R * R)
MGL = M * G * L
DT, SUBSTEPS, MAX_TORQUE, MAX_ACTIONS = 0.002, 10, 2.0, 1000
THRESH = (math.radians(9.5), 0.6)


def wrap(q):
    q = math.fmod(q + math.pi, 2 * math.pi)
    if q < 0:
        q += 2 * math.pi
    return q - math.pi


class Space:
    def __init__(self, high):
        self.high = np.array(high, dtype=np.float64)
        self.low = -self.high

    def sample(self):
        return np.random.uniform(self.low, self.high)


class Pendulum:
    state_dim, action_dim = 3, 1
    action_space = Space([MAX_TORQUE])

    def __init__(self, rng):
        self.rng = rng
        self.evaluate = False

    def obs(self):
        return np.array([math.cos(self.q), math.sin(self.q), self.qdot], dtype=np.float32).astype(np.float64)

    def reset(self):
        self.q = wrap(self.rng.uniform(math.pi / 4, 7 * math.pi / 4))
        self.qdot = self.rng.uniform(-0.05, 0.05)
        if self.evaluate:
            self.goal = np.array([0.0, 0.0])
        else:
            a = math.radians(16)
            self.goal = np.array([self.rng.uniform(-a, a), self.rng.uniform(-0.6, 0.6)])
        self.t = 0
        return {"observation": self.obs(), "desired_goal": self.goal.copy()}

    def reached(self):
        s = self.obs()
        q = math.atan2(s[1], s[0])
        qd = max(-15.0, min(15.0, s[2]))
        return abs(q - self.goal[0]) < THRESH[0] and abs(qd - self.goal[1]) < THRESH[1]

    def step(self, a):
        u = float(np.clip(np.asarray(a, dtype=np.float64).reshape(-1)[0], -MAX_TORQUE, MAX_TORQUE))
        for _ in range(SUBSTEPS):
            qdd = (MGL * math.sin(self.q) - B * self.qdot + u) / I
            self.qdot += DT * qdd
            self.q = wrap(self.q + DT * self.qdot)
        self.t += 1
        ok = self.reached()
        done = ok or self.t >= MAX_ACTIONS
        return {"observation": self.obs(), "desired_goal": self.goal.copy()}, (0.0 if ok else -1.0), done, {"ok": ok}


# --- the port's agent: its subgoal space is the state's first coordinates --------------------
SUB_HIGH = np.array([1.0, 1.0, 15.0])


class PendulumSubgoalSpace(Space):
    def __init__(self, dim):
        super().__init__(SUB_HIGH[:dim])
        self.shape = (dim, 1)


class PendulumSubgoal:
    def __init__(self, dim=3):
        self.action_space = PendulumSubgoalSpace(dim)
        self.action_dim = dim


models.Subgoal = PendulumSubgoal

agent = models.HiroAgent(
    state_dim=3, action_dim=1, goal_dim=2, subgoal_dim=3,
    scale_low=np.array([MAX_TORQUE]), start_training_steps=args.warmup,
    model_save_freq=10**9, model_path="/tmp/hiro_port_pendulum_model", buffer_size=200000,
    batch_size=100, buffer_freq=10, train_freq=10, reward_scaling=args.scale,
    policy_freq_high=2, policy_freq_low=2)

# The port squeezes the low level's actions, which drops the action axis of a 1-D action in the
# correction's batched call; give it back there (single states are unaffected).
_low_policy = agent.low_con.policy


def _policy(state, goal, to_numpy=True):
    out = _low_policy(state, goal, to_numpy)
    return out.reshape(-1, 1) if np.ndim(state) > 1 else out.reshape(-1)


_low_noisy = agent.low_con.policy_with_noise


def _policy_with_noise(state, goal, to_numpy=True):
    return _low_noisy(state, goal, to_numpy).reshape(-1)


agent.low_con.policy = _policy
agent.low_con.policy_with_noise = _policy_with_noise

env = Pendulum(np.random.RandomState(args.seed))
test_env = Pendulum(np.random.RandomState(10_000 + args.seed))
test_env.evaluate = True


def test_round():
    wins = 0
    for _ in range(args.test_episodes):
        obs = test_env.reset()
        agent.set_final_goal(obs["desired_goal"])
        s, done, step = obs["observation"], False, 0
        while not done:
            # the port's own greedy step (no noise, no random warm-up)
            _, _, s, done = agent.step(s, test_env, step)
            step += 1
            agent.end_step()
        wins += test_env.reached()
    return 100.0 * wins / args.test_episodes


start = time.time()
global_step = 0
print("episode,steps,train_successes,test_success,seconds", flush=True)
succ = 0
for e in range(1, args.episodes + 1):
    obs = env.reset()
    agent.set_final_goal(obs["desired_goal"])
    s, done, step = obs["observation"], False, 0
    while not done:
        # the port's Trainer.train loop
        a, r, n_s, done = agent.step(s, env, step, global_step, explore=True)
        agent.append(step, s, a, n_s, r, done)
        agent.train(global_step)
        s = n_s
        step += 1
        global_step += 1
        agent.end_step()
    succ += env.reached()
    agent.end_episode(e)
    if e % args.test_every == 0:
        saved = (agent.sg, agent.n_sg)
        t = test_round()
        agent.sg, agent.n_sg = saved
        print(f"{e},{global_step},{succ},{t:.1f},{time.time() - start:.0f}", flush=True)
