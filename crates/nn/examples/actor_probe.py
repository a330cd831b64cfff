"""Reads one level's actor from a run's weights file and reports where its pre-tanh outputs sit
and what its last Adam step did to them (docs/RESULTS.md, `saturating_tanh`).

The level file (`RUN/weights/level{i}.safetensors`, layout in docs/CHECKPOINTS.md) keeps the
actor's layers and its Adam moments. The actor is evaluated at random inputs drawn uniformly from
the given state and goal boxes; the last step is recovered from the moments as
`lr * m_hat / (sqrt(v_hat) + 1e-8)` (the update hac-nn applies), and the outputs before it are
compared with the outputs after it.

    python3 crates/nn/examples/actor_probe.py runs/ur5-reacher-2l-seed1/weights/level1.safetensors \
        --state-low=-3.14,-3.14,-3.14,-2,-2,-2 --state-high=3.14,3.14,3.14,2,2,2 \
        --goal-low=-3.14,-3.14,-3.14 --goal-high=3.14,3.14,3.14

Needs only NumPy. `--circle I,J` draws state columns I and J as the cosine and sine of one
uniform angle (cartpole's `[x, cos q, sin q, xdot, qdot]`: `--circle 1,2`).
"""
import argparse

import numpy as np

from safetensors_f32 import hac_nn_metadata, read_safetensors

TF_EDGE = 7.9073896  # TensorFlow's float tanh is exactly +-1 from here (saturating_tanh)
LIBM_EDGE = 9.01  # libm's tanhf rounds to +-1 from about here


def floats(text):
    return np.array([float(x) for x in text.split(",")])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("weights")
    for k in ("state-low", "state-high", "goal-low", "goal-high"):
        p.add_argument(f"--{k}", type=floats, required=True)
    p.add_argument("--circle", help="state columns I,J drawn as cos and sin of one angle")
    p.add_argument("--samples", type=int, default=4000)
    p.add_argument("--lr", type=float, default=1e-3, help="the run's actor_lr")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()

    tensors, metadata = read_safetensors(a.weights)
    t = {k: v.astype(np.float64) for k, v in tensors.items()}
    meta = hac_nn_metadata(metadata)
    rng = np.random.default_rng(a.seed)
    states = rng.uniform(a.state_low, a.state_high, (a.samples, len(a.state_low)))
    if a.circle:
        i, j = map(int, a.circle.split(","))
        q = rng.uniform(-np.pi, np.pi, a.samples)
        states[:, i], states[:, j] = np.cos(q), np.sin(q)
    goals = rng.uniform(a.goal_low, a.goal_high, (a.samples, len(a.goal_low)))
    x = np.concatenate([states, goals], 1)

    layers = 1 + max(int(k.split(".")[2]) for k in t if k.startswith("actor.layers."))
    params = [t[f"actor.layers.{l}.{w}"] for l in range(layers) for w in ("weight", "bias")]
    steps = int(meta["actor_adam.steps"])
    b1, b2, eps = 0.9, 0.999, 1e-8
    ratios, deltas = [], []
    for i, w in enumerate(params):
        m = t[f"actor_adam.m.{i}"].reshape(w.shape) / (1 - b1**steps)
        v = t[f"actor_adam.v.{i}"].reshape(w.shape) / (1 - b2**steps)
        r = m / (np.sqrt(v) + eps)
        ratios.append(np.median(np.abs(r)))
        deltas.append(a.lr * r)

    def pre(ps):
        h = x
        for l in range(layers):
            h = h @ ps[2 * l].T + ps[2 * l + 1]
            if l < layers - 1:
                h = np.maximum(h, 0.0)
        return h

    now = pre(params)
    moved = now - pre([w + d for w, d in zip(params, deltas)])  # before the step: w + lr * r
    mag = np.abs(now)
    print(f"{a.weights}: {steps} Adam steps, saturating_tanh = {meta.get('actor.saturating_tanh', 'false')}")
    print("median |m_hat| / sqrt(v_hat) per tensor:", " ".join(f"{r:.4f}" for r in ratios))
    print(f"pre-tanh outputs at {a.samples} inputs: median |x| {np.median(mag):.2f}, largest {mag.max():.1f}")
    bands = [
        (f"|x| < {TF_EDGE:.2f}", mag < TF_EDGE),
        (f"{TF_EDGE:.2f} <= |x| < {LIBM_EDGE}", (mag >= TF_EDGE) & (mag < LIBM_EDGE)),
        (f"|x| >= {LIBM_EDGE}", mag >= LIBM_EDGE),
    ]
    for name, band in bands:
        k = int(band.sum())
        if k == 0:
            print(f"  {name}: none")
            continue
        out = np.mean(np.sign(moved[band]) == np.sign(now[band]))
        print(
            f"  {name}: {k / band.size:.1%} of outputs; the last step moved {out:.0%} of them "
            f"outward, median |dx| {np.median(np.abs(moved[band])):.2e}"
        )


if __name__ == "__main__":
    main()
