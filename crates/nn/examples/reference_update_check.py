#!/usr/bin/env python3
"""Does hac-nn's update of one HAC level compute what the HAC paper's reference code computes?

From identical initial weights and identical minibatches, five runs of K updates of one level
(critic step, then actor step through the updated critic, as the reference's `Layer.learn`):

- `rust`: hac-nn's `LevelLearner` (the `update_trace` example beside this file), float32,
  PyTorch-style Adam epsilon (`p -= lr * m_hat / (sqrt(v_hat) + eps)`, crates/nn/src/adam.rs);
- `tf`: the reference's own `Actor` and `Critic` classes (github.com/andrew-j-levy/
  Hierarchical-Actor-Critc-HAC-, commit e240257, imported unmodified from --code) driven with
  the three calls of `Layer.learn`, float32, TF1 `AdamOptimizer` (epsilon applied TF1-style:
  `lr_t = lr sqrt(1 - b2^t) / (1 - b1^t)`, `p -= lr_t m / (sqrt(v) + eps)`);
- `tf-gated`: the same, but for one change to the actor's train op: its gradients pass through
  `tf.tuple` before `apply_gradients`, so that all are computed before any is applied. The
  reference's actor takes `tf.gradients` ungated and its variables are TF1 reference variables,
  so within the one `session.run` of `Actor.update` the Adam step of a layer's weights can run
  before the backward product through those weights has read them: the hidden layers' gradients
  are then computed with some layers above already stepped, in an order the executor picks (the
  critic's `minimize` gates per op and is not affected);
- `f64-tf` and `f64-pt`: the same sequence written out here in NumPy float64, with Adam's
  epsilon TF1-style and PyTorch-style: what the update is without float32 rounding, and what the
  epsilon convention alone changes.

Two cases from the reference's 2-level UR5 design: level 0 (state 6, goal 6, action 3 with half
range [3.15, 5, 3.15]) and level 1 (state 6, goal 3, subgoal 6 with half range [2 pi] * 3 +
[4] * 3), H = 25, gamma = 0.98. A pool of 20,000 synthetic transitions shaped like UR5 replay
(angles, speeds, HER terminal rows whose goal is the next state within the thresholds, and at
level 1 subgoal penalties of -H), and K minibatches of 1024 rows drawn from it with replacement,
as the reference's replay does; weights drawn with the reference's initialisation.

Prints, for each case: the critic loss of chosen updates in each run; mean |Q(s, g, a)| and the
mean action on a fixed probe batch (all evaluated in float64 from each run's weights); the first
update's gradients as applied (read back from Adam's first moment, `m = (1 - b1) g` after one
step) against float64; and after 1, 10, 40 and K updates the largest difference of every weight
tensor between runs.

    pip install tensorflow-cpu numpy   # TensorFlow 2, used through tensorflow.compat.v1
    git clone https://github.com/andrew-j-levy/Hierarchical-Actor-Critc-HAC- /tmp/hacref/base
    git -C /tmp/hacref/base checkout e240257
    python3 crates/nn/examples/reference_update_check.py --code /tmp/hacref/base

Options: --updates K (200), --seed (0), --cases (level0 level1), --trace BINARY (a built
`update_trace`; by default `cargo run --release` builds and runs it), --keep DIR (keep the
safetensors files exchanged with it there). Takes 2 to 4 minutes on 2 cores once the example
is built (most of it in TensorFlow and the reference's per-row Python loop). Not run by any
test.
"""
import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import types

import numpy as np

from safetensors_f32 import read_safetensors, write_safetensors

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
BATCH = 1024
HIDDEN = (64, 64, 64)
LR = 1e-3
B1, B2, EPS = 0.9, 0.999, 1e-8
H = 25
GAMMA = 0.98
POOL = 20_000
PROBE = 4096
ANGLE_THRESHOLD = np.deg2rad(10)
SPEED_THRESHOLD = 2.0

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("--code", required=True, help="checkout of the reference implementation")
ap.add_argument("--updates", type=int, default=200, help="K, the number of updates")
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--cases", nargs="+", default=["level0", "level1"], choices=["level0", "level1"])
ap.add_argument("--trace", help="the update_trace binary (default: cargo run --release)")
ap.add_argument("--keep", help="directory to keep the exchanged safetensors files in")
args = ap.parse_args()
CHECKPOINTS = sorted({c for c in (1, 10, 40, 200, args.updates) if c <= args.updates})


# The reference's UR5 environment, as far as its Actor and Critic read it.
ENV = types.SimpleNamespace(
    state_dim=6,
    action_dim=3,
    end_goal_dim=3,
    subgoal_dim=6,
    action_bounds=np.array([3.15, 5.0, 3.15]),
    action_offset=np.zeros(3),
    subgoal_bounds_symmetric=np.array([2 * np.pi] * 3 + [4.0] * 3),
    subgoal_bounds_offset=np.zeros(6),
)
FLAGS = types.SimpleNamespace(layers=2, time_scale=H)
# The UR5 end-goal space (goal_space_train of the reference's design).
END_GOALS = np.array([[-np.pi, np.pi], [-np.pi / 4, 0.0], [-np.pi / 4, np.pi / 4]])


def case_spec(name):
    if name == "level0":
        return dict(layer=0, state=6, goal=6, action=3,
                    scale=ENV.action_bounds, offset=ENV.action_offset)
    return dict(layer=1, state=6, goal=3, action=6,
                scale=ENV.subgoal_bounds_symmetric, offset=ENV.subgoal_bounds_offset)


# --- inputs -------------------------------------------------------------------------------------

def make_pool(spec, rng):
    """POOL transitions shaped like UR5 replay at the given level, float32."""
    angles = rng.uniform(-np.pi, np.pi, (POOL, 3))
    speeds = rng.normal(0.0, 2.0, (POOL, 3))
    next_angles = angles + 0.05 * speeds + rng.normal(0.0, 0.05, (POOL, 3))
    next_speeds = speeds + rng.normal(0.0, 0.5, (POOL, 3))
    states = np.concatenate([angles, speeds], 1)
    next_states = np.concatenate([next_angles, next_speeds], 1)
    scale = spec["scale"]
    actions = rng.uniform(-scale, scale, (POOL, spec["action"])) + spec["offset"]
    kind = rng.uniform(size=POOL)
    achieved = kind < 0.1  # HER rows whose goal the next state reaches: reward 0, terminal
    if spec["layer"] == 0:
        goals = np.concatenate([rng.uniform(-np.pi, np.pi, (POOL, 3)),
                                rng.uniform(-4.0, 4.0, (POOL, 3))], 1)
        near = np.concatenate([next_angles, np.clip(next_speeds, -4, 4)], 1)
        tol = np.array([ANGLE_THRESHOLD] * 3 + [SPEED_THRESHOLD] * 3)
        penalty = np.zeros(POOL, bool)
    else:
        goals = rng.uniform(END_GOALS[:, 0], END_GOALS[:, 1], (POOL, 3))
        near, tol = next_angles, np.array([ANGLE_THRESHOLD] * 3)
        penalty = (kind >= 0.1) & (kind < 0.2)  # subgoal tests that failed: -H, terminal
    goals[achieved] = near[achieved] + rng.uniform(-tol, tol, (achieved.sum(), len(tol)))
    rewards = np.where(achieved, 0.0, np.where(penalty, -float(H), -1.0))
    terminals = (achieved | penalty).astype(float)
    f32 = lambda a: np.asarray(a, np.float32)
    return dict(states=f32(states), actions=f32(actions), rewards=f32(rewards),
                next_states=f32(next_states), goals=f32(goals), terminals=f32(terminals))


def init_mlp(sizes, rng):
    """The reference's `layer` initialisation; weights [in, out] as TensorFlow holds them."""
    params = []
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        bound = 3e-3 if i == len(sizes) - 2 else 1 / fan_in ** 0.5
        params.append(rng.uniform(-bound, bound, (fan_in, fan_out)).astype(np.float32))
        params.append(rng.uniform(-bound, bound, fan_out).astype(np.float32))
    return params


# --- the update in NumPy float64 ----------------------------------------------------------------

def mlp_forward(params, x):
    acts = [x]
    layers = len(params) // 2
    for l in range(layers):
        z = acts[-1] @ params[2 * l] + params[2 * l + 1]
        acts.append(np.maximum(z, 0.0) if l < layers - 1 else z)
    return acts


def mlp_backward(params, acts, dout):
    """Parameter gradients and the input gradient, given d loss / d output."""
    grads = [None] * len(params)
    d = dout
    for l in reversed(range(len(params) // 2)):
        grads[2 * l] = acts[l].T @ d
        grads[2 * l + 1] = d.sum(0)
        dx = d @ params[2 * l].T
        d = dx * (acts[l] > 0) if l > 0 else dx
    return grads, d


class Float64Level:
    """The reference's update sequence in float64, Adam's epsilon TF1-style or PyTorch-style.
    Constants (gamma, the actor's scale, q_offset) are the float32 values both float32 runs use."""

    def __init__(self, spec, actor, critic, adam):
        self.spec, self.adam = spec, adam
        self.scale = np.float32(spec["scale"]).astype(np.float64)
        self.offset = np.float32(spec["offset"]).astype(np.float64)
        self.gamma = float(np.float32(GAMMA))
        self.q_offset = float(np.float32(-np.log(H / 0.067 - 1)))
        self.nets = {"actor": [p.astype(np.float64) for p in actor],
                     "critic": [p.astype(np.float64) for p in critic]}
        self.moments = {k: ([np.zeros_like(p) for p in v], [np.zeros_like(p) for p in v])
                        for k, v in self.nets.items()}
        self.steps = {"actor": 0, "critic": 0}
        self.first_grads = None

    def act(self, s, g, params=None):
        acts = mlp_forward(params or self.nets["actor"], np.concatenate([s, g], 1))
        t = np.tanh(acts[-1])
        return t * self.scale + self.offset, acts, t

    def q(self, s, g, a, params=None):
        acts = mlp_forward(params or self.nets["critic"], np.concatenate([s, g, a], 1))
        sig = 1 / (1 + np.exp(-(acts[-1] + self.q_offset)))
        return -H * sig, acts, sig

    def step(self, net, grads):
        self.steps[net] += 1
        t = self.steps[net]
        ms, vs = self.moments[net]
        for p, g, m, v in zip(self.nets[net], grads, ms, vs):
            m *= B1
            m += (1 - B1) * g
            v *= B2
            v += (1 - B2) * g * g
            if self.adam == "tf":
                p -= LR * np.sqrt(1 - B2 ** t) / (1 - B1 ** t) * m / (np.sqrt(v) + EPS)
            else:
                p -= LR * (m / (1 - B1 ** t)) / (np.sqrt(v / (1 - B2 ** t)) + EPS)

    def update(self, b):
        s, a, r, s2, g, term = (b[k].astype(np.float64) for k in
                                ("states", "actions", "rewards", "next_states", "goals",
                                 "terminals"))
        n, r, term = len(s), r[:, None], term[:, None]
        # Critic: y from the current actor and critic, clipped to [-H, 0].
        q2, _, _ = self.q(s2, g, self.act(s2, g)[0])
        y = np.clip(np.where(term > 0, r, r + self.gamma * q2), -H, 0.0)
        q, acts, sig = self.q(s, g, a)
        loss = np.mean((y - q) ** 2)
        dx = 2 * (q - y) / n * (-H) * sig * (1 - sig)
        critic_grads, _ = mlp_backward(self.nets["critic"], acts, dx)
        self.step("critic", critic_grads)
        # Actor: through the updated critic, gradient -dQ/da / batch_size (the reference divides
        # by its fixed batch size).
        pi, actor_acts, t = self.act(s, g)
        _, acts, sig = self.q(s, g, pi)
        _, dinput = mlp_backward(self.nets["critic"], acts, (-H) * sig * (1 - sig))
        dq_da = dinput[:, -self.spec["action"]:]
        actor_grads, _ = mlp_backward(self.nets["actor"], actor_acts,
                                      -dq_da / BATCH * self.scale * (1 - t * t))
        self.step("actor", actor_grads)
        if self.first_grads is None:
            self.first_grads = dict(actor=actor_grads, critic=critic_grads, dq_da=dq_da,
                                    mean_target=y.mean())
        return loss


# --- the reference in TensorFlow ----------------------------------------------------------------

def run_reference(spec, actor_init, critic_init, batches, gated=False):
    """The reference's Actor and Critic through `Layer.learn`'s three calls per update. With
    `gated`, the actor's train op is rebuilt with its gradients passed through `tf.tuple` first
    (all computed before any is applied); everything else is the reference's."""
    sys.path.insert(0, os.path.abspath(args.code))
    import tensorflow.compat.v1 as tf
    tf.disable_v2_behavior()
    from actor import Actor
    from critic import Critic

    layer = spec["layer"]
    graph = tf.Graph()
    with graph.as_default():
        config = tf.ConfigProto(intra_op_parallelism_threads=1, inter_op_parallelism_threads=1)
        sess = tf.Session(config=config)
        # As the reference's Layer builds them: actor first, then critic.
        actor = Actor(sess, ENV, BATCH, layer, FLAGS)
        critic = Critic(sess, ENV, layer, FLAGS)
        actor_slots = "Adam"
        if gated:
            actor_slots = "GatedAdam"
            optimizer = tf.train.AdamOptimizer(actor.learning_rate, name=actor_slots)
            actor.train = optimizer.apply_gradients(zip(tf.tuple(actor.policy_gradient),
                                                        actor.weights))
        sess.run(tf.global_variables_initializer())
        variables = {v.op.name: v for v in tf.global_variables()}

        def names(net):
            return [f"{net}_{layer}_fc_{i + 1}/{kind}"
                    for i in range(len(HIDDEN) + 1) for kind in ("weights", "biases")]

        for net, init in (("actor", actor_init), ("critic", critic_init)):
            for name, value in zip(names(net), init):
                variables[name].load(value, sess)
        assert [v.op.name for v in actor.weights] == names("actor")
        assert [v.op.name for v in critic.weights] == names("critic")

        def state(net):
            slots = actor_slots if net == "actor" else "Adam"
            return {
                "params": sess.run([variables[n] for n in names(net)]),
                "m": sess.run([variables[f"{n}/{slots}"] for n in names(net)]),
                "v": sess.run([variables[f"{n}/{slots}_1"] for n in names(net)]),
            }

        losses, snapshots, first_dq_da, first_pg = [], {}, None, None
        for u in range(len(batches)):
            b = batches[u]
            # Layer.learn, one update.
            old_states, actions, new_states, goals = (
                b["states"], b["actions"], b["next_states"], b["goals"])
            rewards = b["rewards"].tolist()
            is_terminals = (b["terminals"] > 0).tolist()
            critic.update(old_states, actions, rewards, new_states, goals,
                          actor.get_action(new_states, goals), is_terminals)
            action_derivs = critic.get_gradients(old_states, goals,
                                                 actor.get_action(old_states, goals))
            if u == 0:
                # The actor's gradient evaluated on its own, to compare with what the update
                # applies (read back from Adam's first moment).
                first_dq_da = action_derivs
                first_pg = sess.run(actor.policy_gradient, feed_dict={
                    actor.state_ph: old_states, actor.goal_ph: goals,
                    actor.action_derivs: action_derivs})
            actor.update(old_states, goals, action_derivs)
            losses.append(float(critic.loss_val))
            if u + 1 in CHECKPOINTS:
                snapshots[u + 1] = {"actor": state("actor"), "critic": state("critic")}
        sess.close()
    return dict(losses=np.array(losses), snapshots=snapshots, first_dq_da=first_dq_da,
                first_pg=first_pg)


# --- hac-nn -------------------------------------------------------------------------------------

def run_rust(spec, actor_init, critic_init, batches, workdir):
    tensors = {}
    for net, init in (("actor", actor_init), ("critic", critic_init)):
        for i in range(len(init) // 2):
            tensors[f"{net}.{i}.weight"] = init[2 * i].T  # [out, in]
            tensors[f"{net}.{i}.bias"] = init[2 * i + 1]
    tensors["output_scale"] = np.float32(spec["scale"])
    tensors["output_offset"] = np.float32(spec["offset"])
    for key in ("states", "actions", "rewards", "next_states", "goals", "terminals"):
        tensors[key] = np.stack([b[key] for b in batches])
    path_in = os.path.join(workdir, f"level{spec['layer']}-input.safetensors")
    path_out = os.path.join(workdir, f"level{spec['layer']}-trace.safetensors")
    write_safetensors(path_in, tensors, {
        "horizon": str(H), "gamma": str(GAMMA),
        "checkpoints": ",".join(map(str, CHECKPOINTS))})
    if args.trace:
        command = [os.path.abspath(args.trace)]
    else:
        command = ["cargo", "run", "--release", "--quiet", "-p", "hac-nn", "--example",
                   "update_trace", "--"]
    subprocess.run(command + [path_in, path_out], cwd=REPO, check=True)
    out, _ = read_safetensors(path_out)
    inits = {"actor": actor_init, "critic": critic_init}

    def tensor(n, net, kind, i):
        """Tensor i (weights and biases alternating, as in TensorFlow) of the learner's state
        after n updates: the parameters (`kind` "params"), or Adam's first or second moment."""
        if kind == "params":
            value = out[f"after{n}.{net}.layers.{i // 2}.{('weight', 'bias')[i % 2]}"]
            return value.T if i % 2 == 0 else value  # weights back to [in, out]
        # The moments are flat in the network's own layout, `out x in` column-major: that is
        # [in, out] row-major.
        return out[f"after{n}.{net}_adam.{kind}.{i}"].reshape(inits[net][i].shape)

    count = 2 * (len(HIDDEN) + 1)
    snapshots = {n: {net: {kind: [tensor(n, net, kind, i) for i in range(count)]
                           for kind in ("params", "m", "v")}
                     for net in ("actor", "critic")}
                 for n in CHECKPOINTS}
    return dict(losses=out["critic_loss"].astype(np.float64), snapshots=snapshots,
                mean_target=out["mean_target"])


# --- comparison ---------------------------------------------------------------------------------

def tensor_names():
    return [f"{net}.{i // 2}.{'W' if i % 2 == 0 else 'b'}"
            for net in ("actor", "critic") for i in range(2 * (len(HIDDEN) + 1))]


def flat_params(snapshot):
    return snapshot["actor"]["params"] + snapshot["critic"]["params"]


def probe_stats(level, params):
    """mean |Q(s, g, a)| with the probe's replayed actions, and pi(s, g), in float64."""
    count = 2 * (len(HIDDEN) + 1)
    actor = [np.asarray(p, np.float64) for p in params[:count]]
    critic = [np.asarray(p, np.float64) for p in params[count:]]
    s, g, a = (PROBE_BATCH[k].astype(np.float64) for k in ("states", "goals", "actions"))
    q, _, _ = level.q(s, g, a, critic)
    pi, _, _ = level.act(s, g, actor)
    return np.abs(q).mean(), pi


def fmt(x):
    return f"{x:8.1e}"


def compare(name, spec, runs, level):
    print(f"\n==== {name}: state {spec['state']}, goal {spec['goal']}, action {spec['action']} "
          f"(half range {np.round(spec['scale'], 3).tolist()}), H {H}, gamma {GAMMA}, "
          f"{args.updates} updates of {BATCH} ====")
    labels = list(runs)

    print("\nCritic loss of update n (before its step; the reference's `loss_val`):")
    print("      n " + "".join(f"{k:>14}" for k in labels) + "   rust/tf - 1")
    for n in CHECKPOINTS:
        row = [runs[k]["losses"][n - 1] for k in labels]
        rel = runs["rust"]["losses"][n - 1] / runs["tf"]["losses"][n - 1] - 1
        print(f"  {n:5d} " + "".join(f"{v:14.7g}" for v in row) + f"   {rel:+.1e}")
    for a, b in (("rust", "tf"), ("rust", "f64-pt"), ("tf", "f64-tf"), ("tf-gated", "f64-tf")):
        rel = np.abs(runs[a]["losses"] / runs[b]["losses"] - 1)
        print(f"  largest |{a}/{b} - 1| over all updates: {rel.max():.1e} "
              f"(update {rel.argmax() + 1})")

    print(f"\nProbe batch ({PROBE} rows from the pool): mean |Q(s, g, a)|, mean pi(s, g) per "
          f"dimension, and the largest |pi - pi_tf| over the probe:")
    for n in CHECKPOINTS:
        _, pi_tf = probe_stats(level, flat_params(runs["tf"]["snapshots"][n]))
        for k in labels:
            q, pi = probe_stats(level, flat_params(runs[k]["snapshots"][n]))
            gap = np.abs(pi - pi_tf).max()
            print(f"  after {n:3d} {k:>8}: |Q| {q:.6f}  pi "
                  f"[{', '.join(f'{v:+.4f}' for v in pi.mean(0))}]  |pi - pi_tf| {gap:.1e}")

    print("\nFirst update's gradients as applied (Adam's first moment after one step, "
          "m / (1 - b1)): largest |difference|\nrelative to the tensor's largest |gradient|, "
          "each float32 run against its float64 twin; last column: what the\nreference's actor "
          "step applied against its own gradient evaluated alone, just before, on the same "
          "inputs.")
    one_minus_b1 = np.float64(np.float32(1) - np.float32(B1))
    applied = {k: [np.float64(m) / one_minus_b1 for m in
                   runs[k]["snapshots"][1]["actor"]["m"] + runs[k]["snapshots"][1]["critic"]["m"]]
               for k in ("rust", "tf", "tf-gated")}
    exact = {k: runs[k]["first"]["actor"] + runs[k]["first"]["critic"]
             for k in ("f64-tf", "f64-pt")}
    columns = (("rust", "f64-pt"), ("tf", "f64-tf"), ("tf-gated", "f64-tf"))
    print(f"  {'tensor':<12}{'max |g|':>10}" + "".join(f"{a + '-' + b:>18}" for a, b in columns)
          + f"{'tf applied-alone':>18}")
    count = 2 * (len(HIDDEN) + 1)
    for i, tname in enumerate(tensor_names()):
        scale = np.abs(exact["f64-tf"][i]).max()
        cells = [fmt(np.abs(applied[a][i] - exact[b][i]).max() / scale) for a, b in columns]
        if i < count:
            alone = np.float64(runs["tf"]["first_pg"][i])
            cells.append(fmt(np.abs(applied["tf"][i] - alone).max() / np.abs(alone).max()))
        else:
            cells.append("-")
        print(f"  {tname:<12}{fmt(scale):>10}" + "".join(f"{c:>18}" for c in cells))
    dq, dq64 = runs["tf"]["first_dq_da"], runs["f64-tf"]["first"]["dq_da"]
    print(f"  dQ/da (tf's action_derivs against float64): largest |difference| "
          f"{np.abs(dq - dq64).max() / np.abs(dq64).max():.1e} of max |dQ/da| "
          f"{np.abs(dq64).max():.2e}")
    print(f"  mean critic target: rust {runs['rust']['mean_target'][0]:.8f}, "
          f"float64 {runs['f64-pt']['first']['mean_target']:.8f}")

    pairs = [("rust", "tf"), ("rust", "f64-pt"), ("tf", "f64-tf"), ("tf-gated", "f64-tf"),
             ("f64-tf", "f64-pt")]
    print("\nWeights: largest |difference| of each tensor, and in brackets that relative to the "
          "tensor's largest |entry|;\nlast rows: |difference| / |parameters| over each whole "
          "network.")
    for n in CHECKPOINTS:
        print(f"\n  after {n} update{'s' if n > 1 else ''}")
        print(f"  {'tensor':<12}" + "".join(f"{a + '-' + b:>19}" for a, b in pairs))
        snaps = {k: flat_params(runs[k]["snapshots"][n]) for k in labels}
        for i, tname in enumerate(tensor_names()):
            cells = []
            for a, b in pairs:
                x, y = np.float64(snaps[a][i]), np.float64(snaps[b][i])
                diff = np.abs(x - y).max()
                cells.append(f"{fmt(diff)} ({diff / np.abs(y).max():7.1e})")
            print(f"  {tname:<12}" + "".join(f"{c:>19}" for c in cells))
        for net, part in (("actor", slice(0, count)), ("critic", slice(count, 2 * count))):
            cells = []
            for a, b in pairs:
                x = np.concatenate([np.float64(p).ravel() for p in snaps[a][part]])
                y = np.concatenate([np.float64(p).ravel() for p in snaps[b][part]])
                cells.append(f"{np.linalg.norm(x - y) / np.linalg.norm(y):>19.2e}")
            print(f"  {net:<12}" + "".join(cells))


def main():
    global PROBE_BATCH
    workdir = os.path.abspath(args.keep or tempfile.mkdtemp(prefix="hac-update-check-"))
    os.makedirs(workdir, exist_ok=True)
    for name in args.cases:
        spec = case_spec(name)
        rng = np.random.default_rng([args.seed, spec["layer"]])
        pool = make_pool(spec, rng)
        rows = rng.integers(0, POOL, (args.updates, BATCH))
        batches = [{k: v[r] for k, v in pool.items()} for r in rows]
        PROBE_BATCH = {k: v[rng.integers(0, POOL, PROBE)] for k, v in pool.items()}
        s, g, a = spec["state"], spec["goal"], spec["action"]
        actor_init = init_mlp([s + g, *HIDDEN, a], rng)
        critic_init = init_mlp([s + g + a, *HIDDEN, 1], rng)

        runs = {"rust": run_rust(spec, actor_init, critic_init, batches, workdir)}
        runs["tf"] = run_reference(spec, actor_init, critic_init, batches)
        runs["tf-gated"] = run_reference(spec, actor_init, critic_init, batches, gated=True)
        for adam in ("tf", "pt"):
            level = Float64Level(spec, actor_init, critic_init, adam)
            losses, snapshots = [], {}
            for u, b in enumerate(batches):
                losses.append(level.update(b))
                if u + 1 in CHECKPOINTS:
                    snapshots[u + 1] = {net: {"params": [p.copy() for p in level.nets[net]]}
                                        for net in ("actor", "critic")}
            runs[f"f64-{adam}"] = dict(losses=np.array(losses), snapshots=snapshots,
                                       first=level.first_grads)
        compare(name, spec, runs, level)
    if not args.keep:
        shutil.rmtree(workdir)


if __name__ == "__main__":
    main()
