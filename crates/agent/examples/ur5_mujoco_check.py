#!/usr/bin/env python3
"""ur5-reacher against MuJoCo under control (docs/RESULTS.md, "The two codes side by side").

Drives this project's ur5-reacher (`hac env rollout`) and MuJoCo with the HAC reference
implementation's `ur5.xml` (github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC-, contacts off,
as the task has none) through the same action sequences from the same state, and prints the
largest joint-angle and joint-speed differences. Sequences: uniform random actions (twice), uniform
random actions each held for 20 actions, and bang-bang at the control bounds; 200 actions of 15
physics steps each.

    pip install mujoco
    cargo build --release -p hac-cli
    python3 crates/agent/examples/ur5_mujoco_check.py --code /tmp/hac-reference

The model is copied with the two edits MuJoCo 4 requires and that change no physics
(`reference_models.py`, as for hac_reference_run.py). Not run by any test.
"""
import argparse
import json
import os
import subprocess
import tempfile

import mujoco
import numpy as np
from reference_models import copy_models

ap = argparse.ArgumentParser()
ap.add_argument("--code", required=True, help="checkout of the reference implementation")
ap.add_argument("--hac", default="target/release/hac", help="the hac binary")
ap.add_argument("--actions", type=int, default=200)
ap.add_argument("--seed", type=int, default=1)
args = ap.parse_args()

BOUNDS = np.array([3.15, 5.0, 3.15])
START = [0.3, 0.00322757851, -0.127944547]
FRAMES = 15


def load_model():
    files = os.path.join(tempfile.mkdtemp(), "mujoco_files")
    copy_models(args.code, files)
    model = mujoco.MjModel.from_xml_path(os.path.join(files, "ur5.xml"))
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return model


def mujoco_states(model, actions):
    data = mujoco.MjData(model)
    data.qpos[:] = START
    data.qvel[:] = 0
    states = []
    for a in actions:
        data.ctrl[:] = a
        for _ in range(FRAMES):
            mujoco.mj_step(model, data)
        states.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(states)


def project_states(actions):
    lines = "".join(json.dumps([float(x) for x in a]) + "\n" for a in actions)
    command = [args.hac, "env", "rollout", "--env", "ur5-reacher", "--state",
               json.dumps(START + [0, 0, 0])]
    out = subprocess.run(command, input=lines, capture_output=True, text=True, check=True).stdout
    rows = [json.loads(line)["state"] for line in out.splitlines() if line.startswith("{")]
    return np.array(rows[1:])  # the first row is the initial state


model = load_model()
rng = np.random.default_rng(args.seed)
n = args.actions
sequences = [
    ("uniform", rng.uniform(-BOUNDS, BOUNDS, (n, 3))),
    ("uniform", rng.uniform(-BOUNDS, BOUNDS, (n, 3))),
    ("held 20", np.repeat(rng.uniform(-BOUNDS, BOUNDS, (-(-n // 20), 3)), 20, 0)[:n]),
    ("bang-bang", np.sign(rng.uniform(-1, 1, (n, 3))) * BOUNDS),
]
for name, actions in sequences:
    reference, ours = mujoco_states(model, actions), project_states(actions)
    angle = np.abs((ours[:, :3] - reference[:, :3] + np.pi) % (2 * np.pi) - np.pi)
    speed = np.abs(ours[:, 3:] - reference[:, 3:])
    print(f"{name:9s}: largest |angle difference| after 10 / 50 / {n} actions "
          f"{angle[:10].max():.4f} / {angle[:50].max():.4f} / {angle.max():.4f} rad; "
          f"largest |speed difference| {speed.max():.3f} rad/s")
