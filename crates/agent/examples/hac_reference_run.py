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
  training episodes, repeated) with a CSV row per test round, its per-step printing silenced.

    git clone https://github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC- /tmp/hac-reference
    pip install tensorflow-cpu mujoco
    python3 crates/agent/examples/hac_reference_run.py --code /tmp/hac-reference \
        --design example_designs/UR5_LAY_2_design_agent_and_env.py --seed 0 --episodes 900 \
        --out runs/reference-ur5-2l-s0

Writes OUT/curve.csv (round, training episodes before the round, greedy successes of 100, wall
seconds) and one line per round on stderr. Not run by any test.
"""
import argparse
import builtins
import importlib.util
import itertools
import os
import re
import shutil
import sys
import time
import types

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
args = ap.parse_args()
code = os.path.abspath(args.code)
design_path = os.path.join(code, args.design)
os.makedirs(args.out, exist_ok=True)
os.chdir(args.out)

# The model files, with the two edits newer MuJoCo needs.
if not os.path.isdir("mujoco_files"):
    shutil.copytree(os.path.join(code, "mujoco_files"), "mujoco_files")
    for name in os.listdir("mujoco_files"):
        if not name.endswith(".xml"):
            continue
        path = os.path.join("mujoco_files", name)
        with open(path) as f:
            xml = f.read()
        if '<default class="all">' in xml:
            xml = xml.replace('<default class="all">', '<default>\n<default class="all">', 1)
            end = xml.index("</default>")
            xml = xml[:end] + "</default>\n" + xml[end:]
        xml = re.sub(r'<size njmax="\d+" nconmax="\d+"\s*/>', "", xml)
        with open(path, "w") as f:
            f.write(xml)

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
curve = open("curve.csv", "w")
curve.write("round,train_episodes,successes_of_100,wall_s\n")
builtins.print = lambda *a, **kw: None
agent, env = design.design_agent_and_env(flags)

start = time.time()
trained = 0
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
    for e in range(agent.other_params["num_exploration_episodes"]):
        agent.train(env, e)
        trained += 1
