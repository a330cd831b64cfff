#!/usr/bin/env python3
"""The HAC paper's reference implementation (github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC-,
commit e240257, TensorFlow, used unmodified) trained on its own MuJoCo model with one of its own
example designs, to tell whether a figure of this project's HAC is the algorithm's or this code's
(docs/RESULTS.md, "The reference code on 2-level UR5").

The reference was written for mujoco_py, TensorFlow 1 and numpy 1. What this driver adds, and
nothing else:
- a `mujoco_py` module over the maintained `mujoco` bindings (`load_model_from_path`, `MjSim`
  with `model`, `data` and `step()`, the same `mj_step` mujoco_py called);
- the model files copied into the run directory with two edits newer MuJoCo requires and that
  change no physics: the top-level `<default class="all">` nested inside a plain `<default>`,
  and the `<size njmax nconmax>` element (contact buffer sizes) removed;
- numpy 1's `np.copy` of a ragged list (a 1-D object array), which the reference's replay relies
  on and numpy 2 refuses;
- TensorFlow sessions on one thread each, so that two runs share two cores;
- with `--no-contacts`, MuJoCo's contacts turned off (an experiment: the reference's UR5 arm
  rests on a floor plane, which this project's ur5-reacher does not have);
- seeds: `np.random.seed(SEED)` and `tf.set_random_seed(SEED)` before the agent is built;
- the reference's own schedule (`run_HAC.py`: a test round of 100 greedy episodes, then 50
  training episodes, repeated) with a CSV row per test round, its per-step printing silenced;
  with `--train-only`, its training-only schedule (no test rounds);
- with `--stats-every N`, each level's critic statistics on a replay batch every N training
  episodes (OUT/stats.csv), read through the reference's own graph;
- with `--gated-actor`, an experiment on the reference's actor step (its gradients all computed
  before any is applied).

    git clone https://github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC- /tmp/hac-reference
    pip install tensorflow-cpu mujoco
    python3 crates/agent/examples/hac_reference_run.py --code /tmp/hac-reference \
        --design example_designs/UR5_LAY_2_design_agent_and_env.py --seed 0 --episodes 900 \
        --out runs/reference-ur5-2l-s0

Writes OUT/curve.csv (round, training episodes before the round, greedy successes of 100, wall
seconds) and one line per round on stderr; with `--stats-every`, OUT/stats.csv (training
episodes, level, the critic's mean Q at a replay batch's actions, the actor's loss, and the
shares of each at exactly -H). The statistics draw their batch from the reference's random
stream, so a run with them is another run of its seed. Not run by any test.
"""
import argparse
import builtins
import importlib.util
import itertools
import os
import sys
import time
import types

from reference_models import copy_models

ap = argparse.ArgumentParser()
ap.add_argument("--code", required=True, help="checkout of the reference implementation")
ap.add_argument("--design", required=True, help="design file, relative to --code")
ap.add_argument("--seed", type=int, required=True)
ap.add_argument("--episodes", type=int, default=900, help="training episodes (whole rounds of 50)")
ap.add_argument("--out", required=True, help="run directory (the reference works in its cwd)")
ap.add_argument(
    "--no-contacts",
    action="store_true",
    help="turn MuJoCo's contacts off (the UR5 model's arm then falls through its floor)",
)
ap.add_argument(
    "--train-only",
    action="store_true",
    help="no test rounds: train --episodes episodes (the reference's own --train_only schedule)",
)
ap.add_argument(
    "--stats-every",
    type=int,
    default=0,
    metavar="N",
    help="every N training episodes, write each level's critic statistics on a replay batch to "
    "stats.csv",
)
ap.add_argument(
    "--gated-actor",
    action="store_true",
    help="an experiment: every level's actor step computes all its gradients before it applies "
    "any (the reference's step may apply a layer's update before the layers below have read it)",
)
args = ap.parse_args()
code = os.path.abspath(args.code)
design_path = os.path.join(code, args.design)
os.makedirs(args.out, exist_ok=True)
os.chdir(args.out)

# The model files, with the two edits newer MuJoCo needs.
copy_models(code, "mujoco_files")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import tensorflow.compat.v1 as tf  # noqa: E402

shim = types.ModuleType("mujoco_py")


def load_model_from_path(path):
    model = mujoco.MjModel.from_xml_path(path)
    if args.no_contacts:
        model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return model


class MjSim:
    def __init__(self, model):
        self.model = model
        self.data = mujoco.MjData(model)

    def step(self):
        mujoco.mj_step(self.model, self.data)


def _no_viewer(_sim):
    raise RuntimeError("this driver runs without a viewer")


shim.load_model_from_path = load_model_from_path
shim.MjSim = MjSim
shim.MjViewer = _no_viewer
sys.modules["mujoco_py"] = shim

_np_copy = np.copy


def _copy(a, *rest, **kw):
    try:
        return _np_copy(a, *rest, **kw)
    except ValueError:
        out = np.empty(len(a), dtype=object)
        for i, x in enumerate(a):
            out[i] = x
        return out


np.copy = _copy

tf.disable_v2_behavior()
_session = tf.Session
tf.Session = lambda *a, **kw: _session(
    config=tf.ConfigProto(intra_op_parallelism_threads=1, inter_op_parallelism_threads=1)
)

sys.path.insert(0, code)
np.random.seed(args.seed)
tf.set_random_seed(args.seed)
spec = importlib.util.spec_from_file_location("design", design_path)
design = importlib.util.module_from_spec(spec)
spec.loader.exec_module(design)

flags = types.SimpleNamespace(
    retrain=True, test=False, show=False, train_only=False, verbose=False
)
builtins.print = lambda *a, **kw: None
agent, env = design.design_agent_and_env(flags)

if args.gated_actor:
    # The reference's actor step passes `tf.gradients` straight to `apply_gradients`, so within
    # its one `session.run` the Adam update of a layer may run before the backward pass through
    # that layer has read its weights. Passing the gradients through `tf.tuple` first makes
    # every update wait for all of them (a new Adam per actor, its slots initialised here).
    with agent.sess.graph.as_default():
        known = {v.name for v in tf.global_variables()}
        for i, layer in enumerate(agent.layers):
            actor = layer.actor
            adam = tf.train.AdamOptimizer(actor.learning_rate, name=f"GatedAdam{i}")
            actor.train = adam.apply_gradients(zip(tf.tuple(actor.policy_gradient), actor.weights))
        fresh = [v for v in tf.global_variables() if v.name not in known]
        agent.sess.run(tf.variables_initializer(fresh))

stats = None
if args.stats_every > 0:
    stats = open("stats.csv", "w")
    stats.write("train_episodes,level,mean_q,actor_loss,saturated,saturated_at_policy\n")


def write_stats(episodes):
    """Each level's critic on one replay batch (the reference's own sampling): its mean Q at the
    stored actions, the actor's loss (-mean Q at the policy's actions), and the share of those
    two at exactly -H in float32, where the critic's slope is zero."""
    for i, layer in enumerate(agent.layers):
        if layer.replay_buffer.size < layer.batch_size:
            continue
        states, actions, _, _, goals, _ = layer.replay_buffer.get_batch()
        critic = layer.critic

        def q(a):
            feed = {critic.state_ph: states, critic.goal_ph: goals, critic.action_ph: a}
            return agent.sess.run(critic.infer, feed_dict=feed)

        stored, policy = q(actions), q(layer.actor.get_action(states, goals))
        stats.write(
            f"{episodes},{i},{stored.mean():.5f},{-policy.mean():.5f},"
            f"{(stored <= critic.q_limit).mean():.4f},{(policy <= critic.q_limit).mean():.4f}\n"
        )
    stats.flush()


def train(episodes):
    global trained
    for e in range(episodes):
        agent.train(env, e)
        trained += 1
        if stats is not None and trained % args.stats_every == 0:
            write_stats(trained)


start = time.time()
trained = 0
if args.train_only:
    train(args.episodes)
    sys.exit(0)
curve = open("curve.csv", "w")
curve.write("round,train_episodes,successes_of_100,wall_s\n")
for round_index in itertools.count():
    agent.FLAGS.test = True
    successes = sum(1 for e in range(100) if agent.train(env, e))
    agent.FLAGS.test = False
    wall = time.time() - start
    curve.write(f"{round_index},{trained},{successes},{wall:.1f}\n")
    curve.flush()
    sys.stderr.write(
        f"seed {args.seed} round {round_index} after {trained} training episodes: "
        f"{successes}% ({wall:.0f} s)\n"
    )
    if trained >= args.episodes:
        break
    train(agent.other_params["num_exploration_episodes"])
