//! One HAC level's learner: actor, critic, their optimisers, optional target networks, and the
//! DDPG-style update of docs/ALGORITHM.md ("Learning, per level").

use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvError, SyncSender, TryRecvError};
use std::sync::{Arc, Condvar, Mutex, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hac_core::{AgentConfig, Batch, Bounds, EnvSpec, LevelDims, Rng};

use crate::checkpoint::{TensorReader, TensorWriter};
use crate::mlp::{MlpTransposed, add_assign, transpose_weights};
use crate::{ActorNet, Adam, CriticNet, Mlp, MlpGrads, MlpWorkspace, NnError};

/// Value of the `format` metadata entry of a learner checkpoint.
const FORMAT: &str = "hac-nn/level-learner";

/// What one level's learner needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnerConfig {
    /// Widths of the level's state, goal and action (its output).
    pub dims: LevelDims,
    /// Bounds of the level's output: primitive actions at level 0, subgoals above.
    pub action_bounds: Bounds,
    /// H: the level's attempt budget, which bounds its values to `[-H, 0]`.
    pub horizon: f32,
    /// Discount factor.
    pub gamma: f32,
    /// Hidden layer widths, shared by actor and critic.
    pub hidden: Vec<usize>,
    /// Adam step size of the actor.
    pub actor_lr: f32,
    /// Adam step size of the critic.
    pub critic_lr: f32,
    /// Polyak rate of target networks; `None` (the reference's setting) bootstraps from the
    /// online networks.
    pub target_tau: Option<f32>,
    /// Weight of the mean square of the actor's pre-`tanh` outputs in its loss; 0 (the paper's
    /// loss) leaves it out.
    pub actor_preactivation_l2: f32,
    /// The critic's slope from its pre-sigmoid output (see [`CriticNet`]); `false` is the
    /// reference's rounding.
    pub exact_critic_slope: bool,
    /// The actor's `tanh` reads exactly `+-1` from `|x| >= 7.9074` on (see
    /// [`ActorNet::with_saturating_tanh`]).
    pub saturating_tanh: bool,
}

impl LearnerConfig {
    /// Level `level`'s configuration in a hierarchy described by `agent` on `spec`.
    pub fn for_level(agent: &AgentConfig, spec: &EnvSpec, level: usize) -> Self {
        Self {
            dims: spec.level_dims(level, agent.levels),
            action_bounds: spec.level_action_bounds(level).clone(),
            horizon: agent.horizon as f32,
            gamma: agent.gamma,
            hidden: agent.hidden_layers.clone(),
            actor_lr: agent.actor_lr,
            critic_lr: agent.critic_lr,
            target_tau: agent.target_tau,
            actor_preactivation_l2: agent.actor_preactivation_l2,
            exact_critic_slope: agent.exact_critic_slope,
            saturating_tanh: agent.saturating_tanh,
        }
    }

    /// The floating-point operations of one [`LevelLearner::update`] on `batch` samples,
    /// counted from the layer shapes as the update does its matrix products (2 per
    /// multiply-add; the element-wise work, a few operations per activation, is left out):
    ///
    /// - targets: actor and critic forward on the next states;
    /// - critic step: critic forward, then backward with weight gradients and input gradients
    ///   for every layer but the first;
    /// - actor step: actor and critic forward, critic backward without weight gradients but
    ///   with input gradients down to the action rows of its first layer, then actor backward
    ///   with weight gradients and input gradients for every layer but the first.
    pub fn update_flops(&self, batch: usize) -> u64 {
        // Multiply-adds per sample of one product with every layer of `sizes`, and the same
        // without the first layer.
        let macs = |sizes: &[usize]| sizes.windows(2).map(|w| w[0] * w[1]).sum::<usize>();
        let above_first = |sizes: &[usize]| macs(&sizes[1..]);
        let (actor, critic) = (self.actor_sizes(), self.critic_sizes());
        let forward = 2 * macs(&actor) + 3 * macs(&critic);
        let critic_step_backward = macs(&critic) + above_first(&critic);
        let action_grad = above_first(&critic) + self.dims.action * critic[1];
        let actor_backward = macs(&actor) + above_first(&actor);
        let per_sample = forward + critic_step_backward + action_grad + actor_backward;
        2 * per_sample as u64 * batch as u64
    }

    fn actor_sizes(&self) -> Vec<usize> {
        let d = self.dims;
        [vec![d.state + d.goal], self.hidden.clone(), vec![d.action]].concat()
    }

    fn critic_sizes(&self) -> Vec<usize> {
        let d = self.dims;
        [
            vec![d.state + d.goal + d.action],
            self.hidden.clone(),
            vec![1],
        ]
        .concat()
    }
}

/// What one [`LevelLearner::update`] measured, each a mean over the batch.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct UpdateStats {
    /// Squared error of `Q(s, g, a)` against the target, before the critic step.
    pub critic_loss: f32,
    /// `-Q(s, g, pi(s, g))` with the updated critic, before the actor step.
    pub actor_loss: f32,
    /// `Q(s, g, a)` before the critic step.
    pub mean_q: f32,
    /// The target `y`.
    pub mean_target: f32,
}

/// The largest parameter magnitude an update may leave: far beyond what a healthy network of
/// this size holds (its weights start below 1 and Adam moves each by about the learning rate
/// per update), so reaching it means the update exploded.
pub const PARAMETER_LIMIT: f32 = 1e6;

/// An update that was undone: what was wrong after it.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("the update diverged ({what} = {value:e}); it was undone")]
pub struct Diverged {
    /// `critic loss`, `actor loss`, `mean Q`, `mean target`, `actor parameter` or
    /// `critic parameter`.
    pub what: &'static str,
    /// The first offending value.
    pub value: f32,
}

/// A copy of everything an update changes (networks, optimiser moments and step counts, target
/// networks), so that a diverged update can be undone: of a [`LevelLearner`] (two optimisers)
/// or of a [`crate::Td3Learner`] (three). Keep one per level and reuse it: after the first save,
/// saving allocates nothing.
#[derive(Debug, Clone, Default)]
pub struct LearnerBackup {
    /// Every saved value, slice after slice in the learner's fixed order.
    values: Vec<f32>,
    /// The optimisers' step counts, in the learner's fixed order.
    steps: Vec<u64>,
}

impl LearnerBackup {
    /// Replaces the backup's contents by `steps` and the concatenation of `slices`; allocates
    /// only when growing past an earlier size.
    pub(crate) fn fill<'a>(
        &mut self,
        steps: impl IntoIterator<Item = u64>,
        slices: impl IntoIterator<Item = &'a [f32]>,
    ) {
        self.steps.clear();
        self.steps.extend(steps);
        self.values.clear();
        for slice in slices {
            self.values.extend_from_slice(slice);
        }
    }

    /// Copies what [`fill`](Self::fill) stored back into `steps` and `slices`, which must have
    /// the saved shape (checked before anything is written).
    ///
    /// Panics if the backup was saved from a learner of another shape.
    pub(crate) fn put_back(&self, steps: &mut [&mut u64], slices: &mut [&mut [f32]]) {
        let len: usize = slices.iter().map(|s| s.len()).sum();
        assert!(
            steps.len() == self.steps.len() && len == self.values.len(),
            "learner: backup of another shape ({} step counts and {} values saved, {} and {} to \
             restore)",
            self.steps.len(),
            self.values.len(),
            steps.len(),
            len
        );
        for (to, &from) in steps.iter_mut().zip(&self.steps) {
            **to = from;
        }
        let mut at = 0;
        for slice in slices {
            let n = slice.len();
            slice.copy_from_slice(&self.values[at..at + n]);
            at += n;
        }
    }
}

/// What is wrong after an update that produced `stats` and left `networks` (each named by what
/// [`Diverged::what`] reports for it), if anything: the first statistic that is not finite, else
/// the first parameter that is not finite or above [`PARAMETER_LIMIT`] in magnitude.
pub(crate) fn divergence<'a>(
    stats: &UpdateStats,
    networks: impl IntoIterator<Item = (&'static str, &'a Mlp)>,
) -> Option<Diverged> {
    let statistics = [
        ("critic loss", stats.critic_loss),
        ("actor loss", stats.actor_loss),
        ("mean Q", stats.mean_q),
        ("mean target", stats.mean_target),
    ];
    if let Some(&(what, value)) = statistics.iter().find(|(_, v)| !v.is_finite()) {
        return Some(Diverged { what, value });
    }
    for (what, mlp) in networks {
        let bad = mlp
            .tensors()
            .flatten()
            .find(|v| !v.is_finite() || v.abs() > PARAMETER_LIMIT);
        if let Some(&value) = bad {
            return Some(Diverged { what, value });
        }
    }
    None
}

/// Slowly-moving copies of actor and critic that the target `y` bootstraps from.
#[derive(Debug, Clone)]
struct Targets {
    actor: ActorNet,
    critic: CriticNet,
    tau: f32,
}

/// The most chunks an update cuts its minibatch into, and so the most threads it can use. Each
/// chunk's gradient is computed on its own, possibly on another thread, and the chunk gradients
/// are summed in chunk order. The number of chunks depends on the minibatch's size alone (see
/// [`MIN_CHUNK_SAMPLES`]), not on the number of threads, so neither do the weights: they are
/// bit-identical for any [`LevelLearner::set_threads`].
pub const GRADIENT_CHUNKS: usize = 8;

/// The fewest samples of a chunk (but for a minibatch of fewer): a minibatch of `n` samples is
/// cut into `n / MIN_CHUNK_SAMPLES` chunks, at least 1 and at most [`GRADIENT_CHUNKS`] (the
/// reference's 1024 into 4). Smaller chunks would let more threads share an update, but each
/// costs a little on its own (its matrix products repack the weights, and its gradient is added
/// to the others), which a single thread pays too.
pub const MIN_CHUNK_SAMPLES: usize = 256;

/// The number of chunks of a minibatch of `len` samples.
fn chunk_count(len: usize) -> usize {
    (len / MIN_CHUNK_SAMPLES).clamp(1, GRADIENT_CHUNKS)
}

/// The samples of chunk `k` of `chunks` in a minibatch of `len` samples.
fn chunk_samples(k: usize, chunks: usize, len: usize) -> Range<usize> {
    k * len / chunks..(k + 1) * len / chunks
}

/// A batch's fields, checked to hold `len` samples and cut to exactly that.
#[derive(Debug, Clone, Copy)]
struct Fields<'a> {
    len: usize,
    states: &'a [f32],
    next_states: &'a [f32],
    goals: &'a [f32],
    actions: &'a [f32],
    rewards: &'a [f32],
    terminals: &'a [f32],
}

impl<'a> Fields<'a> {
    fn new(batch: &'a Batch) -> Self {
        let len = batch.len;
        assert!(len > 0, "learner: empty batch");
        let field = |values: &'a [f32], dim: usize, name: &str| {
            assert!(
                values.len() >= len * dim,
                "learner: batch field `{name}` holds fewer than {len} samples"
            );
            &values[..len * dim]
        };
        let d = batch.dims;
        Self {
            len,
            states: field(&batch.states, d.state, "states"),
            next_states: field(&batch.next_states, d.state, "next_states"),
            goals: field(&batch.goals, d.goal, "goals"),
            actions: field(&batch.actions, d.action, "actions"),
            rewards: field(&batch.rewards, 1, "rewards"),
            terminals: field(&batch.terminals, 1, "terminals"),
        }
    }

    /// The samples `samples` of these fields, which have widths `d`.
    fn part(&self, d: LevelDims, samples: Range<usize>) -> Self {
        let (a, b) = (samples.start, samples.end);
        Self {
            len: samples.len(),
            states: &self.states[a * d.state..b * d.state],
            next_states: &self.next_states[a * d.state..b * d.state],
            goals: &self.goals[a * d.goal..b * d.goal],
            actions: &self.actions[a * d.action..b * d.action],
            rewards: &self.rewards[a..b],
            terminals: &self.terminals[a..b],
        }
    }
}

/// The minibatch of the update under way, copied so that worker threads can read it. Its
/// buffers only grow, so copying a minibatch no larger than an earlier one allocates nothing.
#[derive(Debug, Clone, Default)]
struct BatchCopy {
    len: usize,
    states: Vec<f32>,
    next_states: Vec<f32>,
    goals: Vec<f32>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminals: Vec<f32>,
}

impl BatchCopy {
    fn set(&mut self, from: &Fields<'_>) {
        self.len = from.len;
        let pairs = [
            (&mut self.states, from.states),
            (&mut self.next_states, from.next_states),
            (&mut self.goals, from.goals),
            (&mut self.actions, from.actions),
            (&mut self.rewards, from.rewards),
            (&mut self.terminals, from.terminals),
        ];
        for (to, from) in pairs {
            to.clear();
            to.extend_from_slice(from);
        }
    }

    fn fields(&self) -> Fields<'_> {
        Fields {
            len: self.len,
            states: &self.states,
            next_states: &self.next_states,
            goals: &self.goals,
            actions: &self.actions,
            rewards: &self.rewards,
            terminals: &self.terminals,
        }
    }
}

/// Everything an update changes: the networks, the transposes kept of their weights, the target
/// networks and both optimisers, with the buffers of the summed gradients. The learner keeps
/// one; each of its worker threads keeps a copy of its own, which it changes by the same steps
/// on the same gradients, so that every copy stays bit-identical to the learner's while no core
/// writes what another reads (see [`Pool`]).
#[derive(Debug, Clone)]
struct Nets {
    actor: ActorNet,
    critic: CriticNet,
    /// The transposed weights of `actor` and `critic` that their backward passes read, brought
    /// up to date wherever the weights change: each chunk of each part would otherwise copy
    /// them again.
    actor_t: MlpTransposed,
    critic_t: MlpTransposed,
    targets: Option<Targets>,
    actor_opt: Adam,
    critic_opt: Adam,
    /// The gradients summed over the chunks.
    actor_grads: MlpGrads,
    critic_grads: MlpGrads,
}

/// A thread's scratch buffers for the chunks it runs: the networks' workspaces, the critic's
/// targets and the actor's pre-activations. Each thread (the learner's own and each worker)
/// keeps one and runs its chunks through it one after the other, so an update's activations
/// take one chunk's room per thread instead of one per chunk: a quarter, on one thread, for the
/// reference's 1024 samples in 4 chunks, which keeps them in a core's L2 cache. Nothing in it
/// outlives a chunk's part: every buffer is written before it is read.
#[derive(Debug, Clone)]
struct Scratch {
    actor_ws: MlpWorkspace,
    critic_ws: MlpWorkspace,
    /// The critic's regression targets for the chunk's samples.
    y: Vec<f32>,
    /// The actor's pre-activations in the actor step, kept only for the penalty.
    actor_pre: Vec<f32>,
}

impl Scratch {
    fn new(actor: &ActorNet, critic: &CriticNet) -> Self {
        Self {
            actor_ws: MlpWorkspace::new(actor.mlp(), 0),
            critic_ws: MlpWorkspace::new(critic.mlp(), 0),
            y: Vec::new(),
            actor_pre: Vec::new(),
        }
    }

    /// The samples of chunk `k` of `chunks` (`at`) of the minibatch `all`, whose fields have
    /// widths `dims`, with the workspaces sized for them.
    fn take_chunk<'a>(
        &mut self,
        dims: LevelDims,
        all: &Fields<'a>,
        (k, chunks): (usize, usize),
    ) -> Fields<'a> {
        let samples = all.part(dims, chunk_samples(k, chunks, all.len));
        self.actor_ws.set_batch(samples.len);
        self.critic_ws.set_batch(samples.len);
        samples
    }
}

/// One chunk's results of the critic part: its gradient and sums, read after the part by the
/// critic's optimiser steps (every thread's) and the update's statistics.
#[derive(Debug, Clone)]
struct CriticChunk {
    grads: MlpGrads,
    /// Sums over the chunk's samples of the target, of the critic's squared error and of `Q`
    /// before the critic step.
    target_sum: f32,
    sq_err_sum: f32,
    q_sum: f32,
}

/// One chunk's results of the actor part.
#[derive(Debug, Clone)]
struct ActorChunk {
    grads: MlpGrads,
    /// The sum over the chunk's samples of `Q(s, g, pi(s, g))`.
    policy_q_sum: f32,
}

/// The chunks' results, one lock per chunk and part: each chunk of a part is written by one
/// thread, then read by all. The two parts' results are apart so that a thread still summing
/// one part's gradients never holds up another that has gone on to write the next part's.
#[derive(Debug)]
struct Chunks {
    critic: Box<[RwLock<CriticChunk>]>,
    actor: Box<[RwLock<ActorChunk>]>,
}

impl Chunks {
    fn new(actor: &ActorNet, critic: &CriticNet) -> Self {
        let critic_chunk = || CriticChunk {
            grads: MlpGrads::new(critic.mlp()),
            target_sum: 0.0,
            sq_err_sum: 0.0,
            q_sum: 0.0,
        };
        let actor_chunk = || ActorChunk {
            grads: MlpGrads::new(actor.mlp()),
            policy_q_sum: 0.0,
        };
        Self {
            critic: (0..GRADIENT_CHUNKS)
                .map(|_| RwLock::new(critic_chunk()))
                .collect(),
            actor: (0..GRADIENT_CHUNKS)
                .map(|_| RwLock::new(actor_chunk()))
                .collect(),
        }
    }
}

/// Locks a chunk to change it: each chunk of a part goes to one thread. A lock is poisoned
/// only by a panic in an update, which the learner's owner has seen already (the thread that
/// started that update panicked too).
fn write<T>(chunk: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    chunk
        .write()
        .expect("learner: a chunk was left by a panicked update")
}

/// Locks a chunk to read its results, beside other readers.
fn read<T>(chunk: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    chunk
        .read()
        .expect("learner: a chunk was left by a panicked update")
}

/// One optimiser step of `mlp` by `opt` from the gradients of `chunks`, tensor by tensor: the
/// tensor's gradient summed over the chunks in chunk order into `grads`, the Adam step, and the
/// kept transpose in `transposes` refreshed. Each chunk is locked once, for reading, so every
/// thread reads the chunks at the same time.
fn optimiser_step<C>(
    mlp: &mut Mlp,
    grads: &mut MlpGrads,
    opt: &mut Adam,
    transposes: &mut MlpTransposed,
    chunks: &[RwLock<C>],
    chunk_grads: impl Fn(&C) -> &MlpGrads,
) {
    let guards: [Option<RwLockReadGuard<'_, C>>; GRADIENT_CHUNKS] =
        std::array::from_fn(|k| chunks.get(k).map(read));
    let sizes = opt.begin_step();
    for i in 0..mlp.tensor_count() {
        let sum = grads.tensor_mut(i);
        for (k, chunk) in guards.iter().flatten().enumerate() {
            let g = chunk_grads(chunk).tensor(i);
            if k == 0 {
                sum.copy_from_slice(g);
            } else {
                add_assign(sum, g);
            }
        }
        let (m, v) = opt.moments_mut(i);
        sizes.apply(mlp.tensor_mut(i), sum, m, v);
        if let Some(shape) = mlp.weight_shape(i) {
            let wt = transposes.tensor_mut(i);
            if !wt.is_empty() {
                transpose_weights(mlp.tensor_mut(i), shape, wt);
            }
        }
    }
}

impl Nets {
    /// Fresh optimisers and transposes for `actor` and `critic`, and target networks copied
    /// from them when `config` has them.
    fn new(config: &LearnerConfig, actor: ActorNet, critic: CriticNet) -> Self {
        let lens = |m: &Mlp| m.tensors().map(<[f32]>::len).collect::<Vec<_>>();
        Self {
            targets: config.target_tau.map(|tau| Targets {
                actor: actor.clone(),
                critic: critic.clone(),
                tau,
            }),
            actor_opt: Adam::new(config.actor_lr, lens(actor.mlp())),
            critic_opt: Adam::new(config.critic_lr, lens(critic.mlp())),
            actor_grads: MlpGrads::new(actor.mlp()),
            critic_grads: MlpGrads::new(critic.mlp()),
            actor_t: MlpTransposed::new(actor.mlp()),
            critic_t: MlpTransposed::new(critic.mlp()),
            actor,
            critic,
        }
    }

    /// The critic part of chunks `run` of the `of` chunks of the minibatch `all`, one after the
    /// other through `scratch`: each chunk's targets and critic gradient, into `chunks.critic`.
    fn critic_part(
        &self,
        config: &LearnerConfig,
        scratch: &mut Scratch,
        chunks: &Chunks,
        all: &Fields<'_>,
        (run, of): (Range<usize>, usize),
    ) {
        for k in run {
            let out = &mut write(&chunks.critic[k]);
            let samples = scratch.take_chunk(config.dims, all, (k, of));
            self.set_targets(config, scratch, out, &samples);
            self.critic_gradient(config, scratch, out, &samples, all.len);
        }
    }

    /// The actor part of chunks `run` of the `of` chunks of the minibatch `all`: each chunk's
    /// actor gradient through the updated critic, into `chunks.actor`.
    fn actor_part(
        &self,
        config: &LearnerConfig,
        scratch: &mut Scratch,
        chunks: &Chunks,
        all: &Fields<'_>,
        (run, of): (Range<usize>, usize),
    ) {
        for k in run {
            let out = &mut write(&chunks.actor[k]);
            let samples = scratch.take_chunk(config.dims, all, (k, of));
            self.actor_gradient(config, scratch, out, &samples, all.len);
        }
    }

    /// Sets `scratch.y` to the clipped bootstrap targets of `samples`, and `out.target_sum`.
    fn set_targets(
        &self,
        config: &LearnerConfig,
        scratch: &mut Scratch,
        out: &mut CriticChunk,
        samples: &Fields<'_>,
    ) {
        let exact = config.exact_critic_slope;
        let (actor, critic) = match &self.targets {
            Some(t) => (&t.actor, &t.critic),
            None => (&self.actor, &self.critic),
        };
        let Scratch {
            actor_ws,
            critic_ws,
            y,
            ..
        } = scratch;
        actor.fill_input(actor_ws, samples.next_states, samples.goals);
        actor.forward_batch(actor_ws);
        critic.fill_state_goal(critic_ws, samples.next_states, samples.goals);
        let (rows, action_row) = (critic.mlp().input_dim(), critic.action_rows().start);
        actor.write_actions(actor_ws, critic_ws.input_mut(), rows, action_row);
        critic.forward_batch(critic_ws, exact);

        let (h, gamma) = (config.horizon, config.gamma);
        y.resize(samples.len, 0.0);
        let mut sum = 0.0;
        for (((y, &q), &r), &terminal) in y
            .iter_mut()
            .zip(critic_ws.output())
            .zip(samples.rewards)
            .zip(samples.terminals)
        {
            *y = (r + gamma * (1.0 - terminal) * q).clamp(-h, 0.0);
            sum += *y;
        }
        out.target_sum = sum;
    }

    /// Sets `out.grads` to this chunk's part of the gradient of the critic's mean squared error
    /// to `scratch.y` over a minibatch of `len` samples, and the chunk's sums of squared errors
    /// and of `Q`.
    fn critic_gradient(
        &self,
        config: &LearnerConfig,
        scratch: &mut Scratch,
        out: &mut CriticChunk,
        samples: &Fields<'_>,
        len: usize,
    ) {
        let exact = config.exact_critic_slope;
        let critic = &self.critic;
        let ws = &mut scratch.critic_ws;
        critic.fill_state_goal(ws, samples.states, samples.goals);
        critic.fill_actions(ws, samples.actions);
        critic.forward_batch(ws, exact);
        let inv_n = 1.0 / len as f32;
        let (mut sq_err_sum, mut q_sum) = (0.0, 0.0);
        let (q, dq) = ws.output_and_grad_mut();
        for ((dq, &q), &y) in dq.iter_mut().zip(q).zip(&scratch.y) {
            let err = q - y;
            sq_err_sum += err * err;
            q_sum += q;
            *dq = 2.0 * err * inv_n;
        }
        critic.backward_batch(ws, Some(&mut out.grads), false, Some(&self.critic_t));
        (out.sq_err_sum, out.q_sum) = (sq_err_sum, q_sum);
    }

    /// Sets `out.grads` to this chunk's part of the gradient of the actor's loss
    /// `-mean Q(s, g, pi(s, g))` over a minibatch of `len` samples, which reaches the actor
    /// through the critic's action input, and the chunk's sum of `Q`.
    ///
    /// With `actor_preactivation_l2 = c > 0` the loss also holds `c` times the mean square of
    /// the actor's pre-`tanh` outputs (not part of the returned value). Where the critic is flat
    /// (its pre-sigmoid output beyond about 100, where even its exact slope underflows to 0) and
    /// the actor sits at a corner of its bounds, the first term's gradient is exactly zero and
    /// only this one moves the actor.
    fn actor_gradient(
        &self,
        config: &LearnerConfig,
        scratch: &mut Scratch,
        out: &mut ActorChunk,
        samples: &Fields<'_>,
        len: usize,
    ) {
        let exact = config.exact_critic_slope;
        let (actor, critic) = (&self.actor, &self.critic);
        let c = config.actor_preactivation_l2;
        let Scratch {
            actor_ws,
            critic_ws,
            actor_pre,
            ..
        } = scratch;
        actor.fill_input(actor_ws, samples.states, samples.goals);
        critic.fill_state_goal(critic_ws, samples.states, samples.goals);
        if c > 0.0 {
            actor.forward_batch_keeping_pre(actor_ws, actor_pre);
        } else {
            actor.forward_batch(actor_ws);
        }
        let (rows, action_row) = (critic.mlp().input_dim(), critic.action_rows().start);
        actor.write_actions(actor_ws, critic_ws.input_mut(), rows, action_row);
        critic.forward_batch(critic_ws, exact);
        let inv_n = 1.0 / len as f32;
        let mut q_sum = 0.0;
        let (q, dq) = critic_ws.output_and_grad_mut();
        for (dq, &q) in dq.iter_mut().zip(q) {
            q_sum += q;
            *dq = -inv_n;
        }
        critic.backward_batch(critic_ws, None, true, Some(&self.critic_t));
        actor_ws
            .output_grad_mut()
            .copy_from_slice(critic_ws.input_grad());
        let penalty = (c > 0.0).then_some((actor_pre.as_slice(), c, len));
        actor.backward_batch(actor_ws, &mut out.grads, penalty, Some(&self.actor_t));
        out.policy_q_sum = q_sum;
    }

    /// The critic's optimiser step from the first `count` chunks' gradients.
    fn step_critic(&mut self, chunks: &Chunks, count: usize) {
        let mlp = self.critic.mlp_mut();
        let chunks = &chunks.critic[..count];
        let (grads, opt, t) = (
            &mut self.critic_grads,
            &mut self.critic_opt,
            &mut self.critic_t,
        );
        optimiser_step(mlp, grads, opt, t, chunks, |c| &c.grads);
    }

    /// The actor's optimiser step from the first `count` chunks' gradients.
    fn step_actor(&mut self, chunks: &Chunks, count: usize) {
        let mlp = self.actor.mlp_mut();
        let chunks = &chunks.actor[..count];
        let (grads, opt, t) = (
            &mut self.actor_grads,
            &mut self.actor_opt,
            &mut self.actor_t,
        );
        optimiser_step(mlp, grads, opt, t, chunks, |c| &c.grads);
    }

    /// The target networks' Polyak step toward the networks, when there are target networks.
    fn polyak(&mut self) {
        if let Some(t) = &mut self.targets {
            t.actor.mlp_mut().polyak_toward(self.actor.mlp(), t.tau);
            t.critic.mlp_mut().polyak_toward(self.critic.mlp(), t.tau);
        }
    }
}

/// How long a thread of a multi-threaded update waits for the others by spinning before it
/// parks (sleeps in the kernel until woken). The serial part between two updates' chunk parts
/// takes about 50-100 microseconds, so a worker that parked sooner (after 50 us, as it once
/// did) was asleep at the start of every update and paid a wake-up, which is slow on a virtual
/// machine. Measured with `hac bench update` on 2-vCPU hosts (docs/RESULTS.md, "Where the
/// second thread's time goes" and the section after it), median 2-thread update over
/// alternated rounds: on an Intel Xeon, 1.34 ms spinning up to 1 ms against 1.65 ms parking
/// after 50 us; on an AMD EPYC, 1.07 ms against 1.06 ms. Yielding the core between polls
/// instead of spinning (tried) was level with spinning on the Intel host (1.33 ms) and slower
/// on the AMD one (1.13 ms against 1.08 over 16 rounds, with a slow tail). Bounded, so that an
/// idle learner's workers sleep.
const SPIN_BEFORE_PARKING: Duration = Duration::from_millis(1);

/// `rx.recv()`, spinning up to [`SPIN_BEFORE_PARKING`] before parking.
fn recv_spinning<T>(rx: &Receiver<T>) -> Result<T, RecvError> {
    let start = Instant::now();
    loop {
        match rx.try_recv() {
            Ok(message) => return Ok(message),
            Err(TryRecvError::Disconnected) => return Err(RecvError),
            Err(TryRecvError::Empty) if start.elapsed() >= SPIN_BEFORE_PARKING => {
                return rx.recv();
            }
            Err(TryRecvError::Empty) => std::hint::spin_loop(),
        }
    }
}

/// The learner's threads can no longer meet at the [`Gate`]: one of them panicked, or the
/// learner is stopping its workers.
#[derive(Debug)]
struct Stopped;

/// Where the threads of an update wait for each other: after the critic part (whose gradients
/// every thread's critic step sums) and after the actor part. Each thread counts the times it
/// has passed; the `p`-th pass lets a thread through once all `threads` have arrived `p` times.
/// A waiting thread spins up to [`SPIN_BEFORE_PARKING`], then sleeps until the last to arrive
/// wakes it.
#[derive(Debug)]
struct Gate {
    threads: u64,
    /// Arrivals since the gate was made, by all threads.
    arrived: AtomicU64,
    stopped: AtomicBool,
    lock: Mutex<()>,
    wake: Condvar,
}

impl Gate {
    fn new(threads: usize) -> Self {
        Self {
            threads: threads as u64,
            arrived: AtomicU64::new(0),
            stopped: AtomicBool::new(false),
            lock: Mutex::new(()),
            wake: Condvar::new(),
        }
    }

    /// Arrives for the `pass`-th time (from 1) and returns once every thread has.
    fn pass(&self, pass: u64) -> Result<(), Stopped> {
        if self.stopped.load(Ordering::Acquire) {
            return Err(Stopped);
        }
        let all = pass * self.threads;
        if self.arrived.fetch_add(1, Ordering::AcqRel) + 1 == all {
            self.wake_all();
            return Ok(());
        }
        let start = Instant::now();
        while self.arrived.load(Ordering::Acquire) < all {
            if self.stopped.load(Ordering::Acquire) {
                return Err(Stopped);
            }
            if start.elapsed() >= SPIN_BEFORE_PARKING {
                // Checked again under the lock, which the last to arrive takes before waking
                // the sleepers: it cannot wake them between the check and the sleep.
                let mut guard = self.lock.lock().unwrap_or_else(PoisonError::into_inner);
                while self.arrived.load(Ordering::Acquire) < all
                    && !self.stopped.load(Ordering::Acquire)
                {
                    guard = self
                        .wake
                        .wait(guard)
                        .unwrap_or_else(PoisonError::into_inner);
                }
                break;
            }
            std::hint::spin_loop();
        }
        if self.stopped.load(Ordering::Acquire) && self.arrived.load(Ordering::Acquire) < all {
            return Err(Stopped);
        }
        Ok(())
    }

    /// Stops the gate: every thread waiting at it, or coming to it, gets [`Stopped`].
    fn stop(&self) {
        self.stopped.store(true, Ordering::Release);
        self.wake_all();
    }

    fn wake_all(&self) {
        drop(self.lock.lock().unwrap_or_else(PoisonError::into_inner));
        self.wake.notify_all();
    }
}

/// Stops its gate if the worker thread that holds it panics, so that the others do not wait
/// for it forever.
struct StopOnPanic(Arc<Gate>);

impl Drop for StopOnPanic {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.stop();
        }
    }
}

/// What a worker thread is sent.
enum Job {
    /// An update of the minibatch `batch` cut into `of` chunks, the run `chunks` of them the
    /// worker's: the critic part on those chunks, the gate, the critic's optimiser step, the
    /// actor part, the gate, the actor's step and the Polyak step, all on its own copy.
    Update {
        batch: Arc<BatchCopy>,
        chunks: Range<usize>,
        of: usize,
    },
    /// The learner's state changed outside an update (a restore): the worker's copy is
    /// replaced.
    Copy(Box<Nets>),
}

/// A worker thread of a level's learner, waiting for jobs.
struct Worker {
    jobs: SyncSender<Job>,
    thread: JoinHandle<()>,
}

/// The worker threads of one learner: they live as long as it (or until its thread count
/// changes), so an update starts no thread.
///
/// Each worker keeps its own copy of everything an update changes ([`Nets`]) and takes every
/// optimiser step itself, whole, on the summed gradients of all the chunks: the threads share
/// the chunk parts, and each reads the others' chunk gradients, but no thread writes a weight,
/// moment or transpose that another reads. Sharing the steps instead, tensor by tensor, made
/// each core write lines the other had just read (the networks, their transposes), and
/// between distant cores those writes made the steps 3-4 times as slow (docs/RESULTS.md, "What
/// the slow mode slows"). It also halves the meetings per update, from four hand-offs to the
/// two passes of the [`Gate`].
struct Pool {
    workers: Vec<Worker>,
    gate: Arc<Gate>,
    /// The learner's passes of the gate so far.
    passes: u64,
    /// The workers' copies are out of date: they get the learner's before the next update.
    stale: bool,
}

impl Pool {
    /// Starts `workers` threads for the updates of a learner configured by `config`, each with
    /// its own copy of `nets` and its own scratch, reading and writing `chunks`.
    fn new(workers: usize, chunks: &Arc<Chunks>, config: &LearnerConfig, nets: &Nets) -> Self {
        let gate = Arc::new(Gate::new(workers + 1));
        let workers = (0..workers)
            .map(|_| {
                let (jobs, job_rx) = mpsc::sync_channel::<Job>(1);
                let chunks = Arc::clone(chunks);
                let stop_on_panic = StopOnPanic(Arc::clone(&gate));
                let (config, nets) = (config.clone(), nets.clone());
                let thread = std::thread::Builder::new()
                    .name("learner-worker".into())
                    .spawn(move || work(&job_rx, &chunks, &stop_on_panic.0, &config, nets))
                    .expect("learner: spawning a worker thread");
                Worker { jobs, thread }
            })
            .collect();
        Self {
            workers,
            gate,
            passes: 0,
            stale: false,
        }
    }

    /// The learner's next pass of the gate.
    fn pass(&mut self) {
        self.passes += 1;
        self.gate
            .pass(self.passes)
            .expect("learner: a worker thread panicked");
    }
}

impl Drop for Pool {
    fn drop(&mut self) {
        // Workers waiting at the gate for an update the learner abandoned (it panicked) stop.
        self.gate.stop();
        for Worker { jobs, thread } in self.workers.drain(..) {
            drop(jobs);
            // A worker that panicked did so in an update, whose caller panicked with it.
            let _ = thread.join();
        }
    }
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool")
            .field("workers", &self.workers.len())
            .finish()
    }
}

/// A worker thread's life: the jobs from `jobs`, on its own copy `nets` of what an update
/// changes, meeting the other threads at `gate`, until the learner lets go of the channel or
/// stops the gate.
fn work(
    jobs: &Receiver<Job>,
    chunks: &Chunks,
    gate: &Gate,
    config: &LearnerConfig,
    mut nets: Nets,
) {
    let mut scratch = Scratch::new(&nets.actor, &nets.critic);
    let mut passes = 0;
    while let Ok(job) = recv_spinning(jobs) {
        let (batch, run, of) = match job {
            Job::Copy(copy) => {
                nets = *copy;
                continue;
            }
            Job::Update { batch, chunks, of } => (batch, chunks, of),
        };
        let all = batch.fields();
        nets.critic_part(config, &mut scratch, chunks, &all, (run.clone(), of));
        passes += 1;
        if gate.pass(passes).is_err() {
            break;
        }
        nets.step_critic(chunks, of);
        nets.actor_part(config, &mut scratch, chunks, &all, (run, of));
        // The minibatch is let go before the gate, after which the learner may copy the next
        // one in.
        drop(batch);
        passes += 1;
        if gate.pass(passes).is_err() {
            break;
        }
        nets.step_actor(chunks, of);
        nets.polyak();
    }
}

/// Waits at the gate of `pool` until every worker has finished its share of the part under
/// way, adding the wait to `timing` (nothing to wait for on one thread).
fn meet(pool: &mut Option<Pool>, timing: &mut UpdateTiming) {
    if let Some(pool) = pool {
        let own_done = Instant::now();
        pool.pass();
        timing.waiting += own_done.elapsed();
    }
}

/// Learns one level's actor and critic from minibatches. Owns every buffer an update needs, so
/// updates at a steady batch size allocate nothing in this crate.
///
/// An update cuts its minibatch into chunks (by its size alone, see [`MIN_CHUNK_SAMPLES`]) and
/// sums their gradients in a fixed order; with [`LevelLearner::set_threads`] the chunks are
/// shared among that many threads (the caller's and workers started once), with bit-identical
/// results.
#[derive(Debug)]
pub struct LevelLearner {
    config: LearnerConfig,
    nets: Nets,
    /// The minibatch of the update under way, copied in so that the workers can read it; they
    /// let it go before the update's last pass of the gate.
    batch: Arc<BatchCopy>,
    /// The chunks' results.
    chunks: Arc<Chunks>,
    /// The scratch of the calling thread's chunks (each worker keeps its own).
    scratch: Scratch,
    pool: Option<Pool>,
    /// Where the updates' time went, since the learner was built or the timing reset.
    timing: UpdateTiming,
}

/// Where a learner's update time went ([`LevelLearner::timing`]), summed over `updates`
/// updates: the share no second thread can take (everything outside the chunk parts) bounds
/// what more threads can give, and `waiting` shows how evenly the threads finish.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UpdateTiming {
    /// Updates timed.
    pub updates: u64,
    /// Their whole time.
    pub total: Duration,
    /// Of `total`, the parts shared among the threads: the two chunk parts (critic, then
    /// actor), from handing the chunks out to the last one done. The rest is serial: copying
    /// the minibatch in, the chunks' statistics, the two optimiser steps (which every thread
    /// takes whole, on its own copy of the networks) and the target networks' Polyak step.
    pub parallel: Duration,
    /// Of `parallel`, the calling thread idle after its own share, waiting for the workers'
    /// (zero on one thread).
    pub waiting: Duration,
    /// Of the serial time, the two optimiser steps: summing the chunks' gradients, Adam,
    /// refreshing the kept transposes.
    pub steps: Duration,
}

impl UpdateTiming {
    /// The serial time: `total - parallel`.
    pub fn serial(&self) -> Duration {
        self.total.saturating_sub(self.parallel)
    }
}

impl Clone for LevelLearner {
    /// An independent copy of everything an update reads and changes, which updates on the
    /// calling thread (it starts no worker; [`LevelLearner::set_threads`] gives it more): a
    /// checkpoint's snapshot is a clone that never updates. Scratch buffers are not copied.
    fn clone(&self) -> Self {
        Self::with_nets(self.config.clone(), self.nets.clone())
    }
}

impl LevelLearner {
    /// A freshly initialised learner: the actor, then the critic, draw their weights from `rng`.
    /// It updates on the calling thread until [`set_threads`](Self::set_threads) says otherwise.
    ///
    /// Panics if the bounds do not match `dims.action`, a width is zero, or `horizon <= 0.067`.
    pub fn new(config: LearnerConfig, rng: &mut Rng) -> Self {
        let actor = ActorNet::new(config.dims, &config.action_bounds, &config.hidden, rng)
            .with_saturating_tanh(config.saturating_tanh);
        let critic = CriticNet::new(config.dims, config.horizon, &config.hidden, rng);
        Self::assemble(config, actor, critic)
    }

    fn assemble(config: LearnerConfig, actor: ActorNet, critic: CriticNet) -> Self {
        let nets = Nets::new(&config, actor, critic);
        Self::with_nets(config, nets)
    }

    /// A learner on `nets`, with fresh buffers, updating on the calling thread.
    fn with_nets(config: LearnerConfig, nets: Nets) -> Self {
        Self {
            chunks: Arc::new(Chunks::new(&nets.actor, &nets.critic)),
            scratch: Scratch::new(&nets.actor, &nets.critic),
            nets,
            config,
            batch: Arc::default(),
            pool: None,
            timing: UpdateTiming::default(),
        }
    }

    /// Where this learner's updates spent their time since it was built (a clone starts
    /// from zero) or [`reset_timing`](Self::reset_timing) was last called. The timers cost a
    /// few clock reads per update.
    pub fn timing(&self) -> UpdateTiming {
        self.timing
    }

    /// Starts [`timing`](Self::timing) again from zero.
    pub fn reset_timing(&mut self) {
        self.timing = UpdateTiming::default();
    }

    /// Shares each update among `threads` threads: the caller's and `threads - 1` workers that
    /// this learner starts now and keeps (at most [`GRADIENT_CHUNKS`] in all; more would have
    /// nothing to do), each with a copy of the networks and optimisers. The weights do not
    /// depend on it.
    ///
    /// Panics if `threads` is 0.
    pub fn set_threads(&mut self, threads: usize) {
        assert!(threads > 0, "learner: at least one thread updates");
        let threads = threads.min(GRADIENT_CHUNKS);
        if threads != self.threads() {
            self.pool = None;
            self.pool = (threads > 1)
                .then(|| Pool::new(threads - 1, &self.chunks, &self.config, &self.nets));
        }
    }

    /// The number of threads an update uses (see [`set_threads`](Self::set_threads)).
    pub fn threads(&self) -> usize {
        self.pool.as_ref().map_or(1, |p| p.workers.len() + 1)
    }

    /// The configuration the learner was built from.
    pub fn config(&self) -> &LearnerConfig {
        &self.config
    }

    /// The current actor; clone it to hand the policy to a rollout or ship its weights.
    pub fn actor(&self) -> &ActorNet {
        &self.nets.actor
    }

    /// The current critic.
    pub fn critic(&self) -> &CriticNet {
        &self.nets.critic
    }

    /// Updates done so far.
    pub fn updates(&self) -> u64 {
        self.nets.actor_opt.steps()
    }

    /// The greedy action `pi(state, goal)`, written into `out`.
    pub fn act(&mut self, state: &[f32], goal: &[f32], out: &mut [f32]) {
        self.nets.actor.act(state, goal, out);
    }

    /// One critic step, then one actor step, on `batch`.
    ///
    /// Critic: regress `Q(s, g, a)` on `y = r + gamma (1 - terminal) Q(s', g, pi(s', g))` (target
    /// networks when enabled), clipped to `[-H, 0]` and held constant. Actor: minimise
    /// `-mean Q(s, g, pi(s, g))` under the just-updated critic, whose parameters stay fixed.
    ///
    /// Each gradient is the sum, in chunk order, of the gradients of the minibatch's chunks (see
    /// [`MIN_CHUNK_SAMPLES`]), computed on as many threads as [`set_threads`](Self::set_threads)
    /// gave.
    ///
    /// Panics if the batch is empty, its dimensions are not this level's, or a field is short.
    pub fn update(&mut self, batch: &Batch) -> UpdateStats {
        assert_eq!(
            batch.dims, self.config.dims,
            "learner: batch dimensions differ from the level's"
        );
        let start = Instant::now();
        let fields = Fields::new(batch);
        let n = fields.len;
        Arc::get_mut(&mut self.batch)
            .expect("learner: a worker thread still holds the minibatch")
            .set(&fields);
        let chunks = chunk_count(n);
        let inv_n = 1.0 / n as f32;
        // The chunks go to the first threads, a run of consecutive ones each; with fewer chunks
        // than threads the last threads have none but still take the optimiser steps.
        let busy = self.threads().min(chunks);
        let share =
            |t: usize| (t * chunks / busy).min(chunks)..((t + 1) * chunks / busy).min(chunks);
        if let Some(pool) = &mut self.pool {
            for (t, worker) in pool.workers.iter().enumerate() {
                if pool.stale {
                    let copy = Job::Copy(Box::new(self.nets.clone()));
                    worker
                        .jobs
                        .send(copy)
                        .expect("learner: a worker thread has stopped");
                }
                let job = Job::Update {
                    batch: Arc::clone(&self.batch),
                    chunks: share(t + 1),
                    of: chunks,
                };
                worker
                    .jobs
                    .send(job)
                    .expect("learner: a worker thread has stopped");
            }
            pool.stale = false;
        }

        let parallel = Instant::now();
        let all = self.batch.fields();
        let (config, scratch) = (&self.config, &mut self.scratch);
        let own = (share(0), chunks);
        self.nets
            .critic_part(config, scratch, &self.chunks, &all, own.clone());
        meet(&mut self.pool, &mut self.timing);
        let mut took = parallel.elapsed();
        let (mut target_sum, mut sq_err_sum, mut q_sum) = (0.0, 0.0, 0.0);
        for chunk in &self.chunks.critic[..chunks] {
            let chunk = read(chunk);
            target_sum += chunk.target_sum;
            sq_err_sum += chunk.sq_err_sum;
            q_sum += chunk.q_sum;
        }
        let step = Instant::now();
        self.nets.step_critic(&self.chunks, chunks);
        let mut steps = step.elapsed();

        let parallel = Instant::now();
        let (config, scratch) = (&self.config, &mut self.scratch);
        self.nets
            .actor_part(config, scratch, &self.chunks, &all, own);
        meet(&mut self.pool, &mut self.timing);
        took += parallel.elapsed();
        let policy_q_sum: f32 = self.chunks.actor[..chunks]
            .iter()
            .map(|chunk| read(chunk).policy_q_sum)
            .sum();
        let step = Instant::now();
        self.nets.step_actor(&self.chunks, chunks);
        steps += step.elapsed();
        self.nets.polyak();

        self.timing.updates += 1;
        self.timing.total += start.elapsed();
        self.timing.parallel += took;
        self.timing.steps += steps;
        UpdateStats {
            critic_loss: sq_err_sum * inv_n,
            actor_loss: -policy_q_sum * inv_n,
            mean_q: q_sum * inv_n,
            mean_target: target_sum / n as f32,
        }
    }

    /// [`update`](Self::update), undone if it diverged: when a statistic is not finite or a
    /// parameter is not finite or above [`PARAMETER_LIMIT`], the learner is put back as it was
    /// before (networks, optimisers and their step counts, targets) and the error says what
    /// was wrong. `backup` is scratch space kept between calls.
    ///
    /// Healthy updates are bit-identical to [`update`](Self::update)'s.
    pub fn update_or_undo(
        &mut self,
        batch: &Batch,
        backup: &mut LearnerBackup,
    ) -> Result<UpdateStats, Diverged> {
        self.save(backup);
        let stats = self.update(batch);
        match self.divergence(&stats) {
            None => Ok(stats),
            Some(diverged) => {
                self.restore(backup);
                Err(diverged)
            }
        }
    }

    /// What is wrong after an update that produced `stats`, if anything.
    fn divergence(&self, stats: &UpdateStats) -> Option<Diverged> {
        divergence(
            stats,
            [
                ("actor parameter", self.nets.actor.mlp()),
                ("critic parameter", self.nets.critic.mlp()),
            ],
        )
    }

    /// Everything an update changes, as mutable slices in a fixed order, and the two step
    /// counts.
    fn state_mut(&mut self) -> ([&mut u64; 2], Vec<&mut [f32]>) {
        let nets = &mut self.nets;
        let (actor_steps, actor_moments) = nets.actor_opt.state_mut();
        let (critic_steps, critic_moments) = nets.critic_opt.state_mut();
        let mut slices: Vec<&mut [f32]> = nets.actor.mlp_mut().tensors_mut().collect();
        slices.extend(nets.critic.mlp_mut().tensors_mut());
        slices.extend(actor_moments);
        slices.extend(critic_moments);
        if let Some(t) = &mut nets.targets {
            slices.extend(t.actor.mlp_mut().tensors_mut());
            slices.extend(t.critic.mlp_mut().tensors_mut());
        }
        ([actor_steps, critic_steps], slices)
    }

    /// Copies everything an update changes into `backup`.
    pub fn save(&self, backup: &mut LearnerBackup) {
        let model = &self.nets;
        let (actor_steps, actor_moments) = model.actor_opt.state();
        let (critic_steps, critic_moments) = model.critic_opt.state();
        let targets = model
            .targets
            .iter()
            .flat_map(|t| t.actor.mlp().tensors().chain(t.critic.mlp().tensors()));
        let slices = model
            .actor
            .mlp()
            .tensors()
            .chain(model.critic.mlp().tensors())
            .chain(actor_moments)
            .chain(critic_moments)
            .chain(targets);
        backup.fill([actor_steps, critic_steps], slices);
    }

    /// Puts back what [`save`](Self::save) copied into `backup`.
    ///
    /// Panics if `backup` was saved from a learner of another shape (or kind).
    pub fn restore(&mut self, backup: &LearnerBackup) {
        let (mut steps, mut slices) = self.state_mut();
        backup.put_back(&mut steps, &mut slices);
        let nets = &mut self.nets;
        nets.actor_t.refresh(nets.actor.mlp());
        nets.critic_t.refresh(nets.critic.mlp());
        if let Some(pool) = &mut self.pool {
            pool.stale = true;
        }
    }

    /// The learner's whole state as a safetensors file: actor (`actor.*`, laid out as in
    /// [`ActorNet::to_safetensors`]), critic (`critic.*`), both optimisers (`actor_adam.*`,
    /// `critic_adam.*`) and, when enabled, the target networks (`target_actor.*`,
    /// `target_critic.*`).
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut out = TensorWriter::default();
        out.meta("format".into(), FORMAT);
        let nets = &self.nets;
        nets.actor.write("actor.", &mut out);
        nets.critic.write("critic.", &mut out);
        nets.actor_opt.write("actor_adam.", &mut out);
        nets.critic_opt.write("critic_adam.", &mut out);
        if let Some(t) = &nets.targets {
            t.actor.write("target_actor.", &mut out);
            t.critic.write("target_critic.", &mut out);
        }
        out.finish()
    }

    /// Restores a learner saved by [`LevelLearner::to_safetensors`]. The file's networks must
    /// have the architecture, bounds and horizon that `config` describes; its hyperparameters
    /// (learning rates, gamma, tau, the actor's `tanh`) come from `config`.
    pub fn from_safetensors(config: LearnerConfig, bytes: &[u8]) -> Result<Self, NnError> {
        let file = TensorReader::new(bytes)?;
        file.expect_format(FORMAT)?;
        let saturating = config.saturating_tanh;
        let actor = ActorNet::read("actor.", &file)?.with_saturating_tanh(saturating);
        let critic = CriticNet::read("critic.", &file)?;
        check_matches(&config, &actor, &critic)?;
        let mut learner = Self::assemble(config, actor, critic);
        let nets = &mut learner.nets;
        nets.actor_opt.read("actor_adam.", &file)?;
        nets.critic_opt.read("critic_adam.", &file)?;
        if let Some(t) = &mut nets.targets {
            t.actor = ActorNet::read("target_actor.", &file)?.with_saturating_tanh(saturating);
            t.critic = CriticNet::read("target_critic.", &file)?;
            check_matches(&learner.config, &t.actor, &t.critic)?;
        }
        Ok(learner)
    }
}

/// Whether networks read from a file are the ones `config` describes.
fn check_matches(
    config: &LearnerConfig,
    actor: &ActorNet,
    critic: &CriticNet,
) -> Result<(), NnError> {
    check_actor(
        "actor",
        config.dims,
        &config.action_bounds,
        &config.hidden,
        actor,
    )?;
    check_widths("critic", &config.critic_sizes(), critic.mlp())?;
    if critic.dims() != config.dims {
        return Err(mismatch(
            "critic (state, goal, action) widths",
            format!("{:?}", config.dims),
            format!("{:?}", critic.dims()),
        ));
    }
    if critic.horizon() != config.horizon {
        return Err(mismatch(
            "critic horizon",
            config.horizon.to_string(),
            critic.horizon().to_string(),
        ));
    }
    Ok(())
}

/// A [`NnError::Mismatch`]: the file's `what` is `found` where the configuration says
/// `expected`.
pub(crate) fn mismatch(what: &str, expected: String, found: String) -> NnError {
    NnError::Mismatch {
        what: what.into(),
        expected,
        found,
    }
}

/// Whether the network `name` read from a file has the layer widths `expected`
/// (`[input, hidden.., output]`).
pub(crate) fn check_widths(name: &str, expected: &[usize], mlp: &Mlp) -> Result<(), NnError> {
    let found = mlp.sizes();
    if found != expected {
        return Err(mismatch(
            &format!("{name} layer widths"),
            format!("{expected:?}"),
            format!("{found:?}"),
        ));
    }
    Ok(())
}

/// Whether the actor `name` read from a file is one for a level with `dims`, acting within
/// `bounds` through hidden layers `hidden`: its layer widths, its split of the input into state
/// and goal, and its output scale and offset.
pub(crate) fn check_actor(
    name: &str,
    dims: LevelDims,
    bounds: &Bounds,
    hidden: &[usize],
    actor: &ActorNet,
) -> Result<(), NnError> {
    let sizes = [&[dims.state + dims.goal], hidden, &[dims.action]].concat();
    check_widths(name, &sizes, actor.mlp())?;
    if actor.dims() != dims {
        return Err(mismatch(
            &format!("{name} (state, goal, action) widths"),
            format!("{dims:?}"),
            format!("{:?}", actor.dims()),
        ));
    }
    let scale: Vec<f32> = (0..bounds.dim()).map(|d| bounds.half_range(d)).collect();
    let offset: Vec<f32> = (0..bounds.dim()).map(|d| bounds.offset(d)).collect();
    if actor.output_scale() != scale || actor.output_offset() != offset {
        return Err(mismatch(
            &format!("{name} output (scale, offset)"),
            format!("({scale:?}, {offset:?})"),
            format!("({:?}, {:?})", actor.output_scale(), actor.output_offset()),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::uniform_vec;

    const DIMS: LevelDims = LevelDims {
        state: 3,
        goal: 2,
        action: 2,
    };

    fn config(target_tau: Option<f32>) -> LearnerConfig {
        LearnerConfig {
            dims: DIMS,
            action_bounds: Bounds::new(vec![-2.0, 0.0], vec![2.0, 1.0]),
            horizon: 10.0,
            gamma: 0.98,
            hidden: vec![32, 32],
            actor_lr: 1e-3,
            critic_lr: 1e-3,
            target_tau,
            actor_preactivation_l2: 0.0,
            exact_critic_slope: false,
            saturating_tanh: false,
        }
    }

    /// A batch of HAC-like transitions whose outcome is a function of the goal, so that a critic
    /// can learn it: the -H penalty, or reward 0 and terminal, or reward -1.
    fn random_batch(rng: &mut Rng, len: usize) -> Batch {
        let mut b = Batch::zeros(DIMS, len);
        b.states = uniform_vec(rng, DIMS.state * len, 1.0);
        b.next_states = uniform_vec(rng, DIMS.state * len, 1.0);
        b.goals = uniform_vec(rng, DIMS.goal * len, 1.0);
        b.actions = uniform_vec(rng, DIMS.action * len, 1.0);
        for (j, g) in b.goals.chunks_exact(DIMS.goal).enumerate() {
            (b.rewards[j], b.terminals[j]) = if g[1] < -0.8 {
                (-10.0, 1.0)
            } else if g[0] > 0.4 {
                (0.0, 1.0)
            } else {
                (-1.0, 0.0)
            };
        }
        b
    }

    #[test]
    fn a_diverged_update_is_undone_and_healthy_ones_match_update() {
        for tau in [None, Some(0.05)] {
            let mut rng = Rng::seed_from(5);
            let mut guarded = LevelLearner::new(config(tau), &mut rng);
            let mut plain = guarded.clone();
            let mut backup = LearnerBackup::default();
            for _ in 0..5 {
                let batch = random_batch(&mut rng, 64);
                let stats = guarded.update_or_undo(&batch, &mut backup).unwrap();
                assert_eq!(stats, plain.update(&batch));
            }
            assert_eq!(guarded.to_safetensors(), plain.to_safetensors());

            // A NaN reaches the loss.
            let mut poison = random_batch(&mut rng, 64);
            poison.states[7] = f32::NAN;
            let before = guarded.to_safetensors();
            let e = guarded.update_or_undo(&poison, &mut backup).unwrap_err();
            assert!(e.value.is_nan(), "{e}");
            assert_eq!(guarded.to_safetensors(), before, "undone to the last byte");
            assert_eq!(guarded.updates(), 5);

            // An exploding step: the same learner with a learning rate of 1e30.
            let mut exploding = guarded.clone();
            let lens: Vec<usize> = exploding
                .actor()
                .mlp()
                .tensors()
                .map(<[f32]>::len)
                .collect();
            exploding.nets.actor_opt = Adam::new(1e30, lens);
            let before = exploding.to_safetensors();
            let e = exploding
                .update_or_undo(&random_batch(&mut rng, 64), &mut backup)
                .unwrap_err();
            assert!(
                e.what.ends_with("parameter")
                    && (!e.value.is_finite() || e.value.abs() > PARAMETER_LIMIT),
                "{e}"
            );
            assert_eq!(exploding.to_safetensors(), before);

            // ... and the guarded learner goes on as if the poison never came.
            let batch = random_batch(&mut rng, 64);
            assert_eq!(
                guarded.update_or_undo(&batch, &mut backup).unwrap(),
                plain.update(&batch)
            );
            assert_eq!(guarded.to_safetensors(), plain.to_safetensors());
        }
    }

    #[test]
    fn critic_loss_falls_on_a_fixed_batch() {
        let mut rng = Rng::seed_from(31);
        let mut learner = LevelLearner::new(config(None), &mut rng);
        let batch = random_batch(&mut rng, 256);
        let first = learner.update(&batch);
        let mut last = first;
        for _ in 0..300 {
            last = learner.update(&batch);
        }
        assert!(
            last.critic_loss < 0.2 * first.critic_loss,
            "critic loss {} -> {}",
            first.critic_loss,
            last.critic_loss
        );
        // The untrained critic is optimistic; the targets are clipped to [-H, 0].
        assert!((first.mean_q + 0.067).abs() < 0.01, "{first:?}");
        assert!((-10.0..=0.0).contains(&last.mean_target));
        assert_eq!(learner.updates(), 301);
    }

    /// `mean Q(s, g, pi(s, g))` over the batch, with the learner's current actor and critic.
    fn policy_value(learner: &LevelLearner, batch: &Batch) -> f32 {
        let (actor, critic) = (learner.actor(), learner.critic());
        let mut actor_ws = MlpWorkspace::new(actor.mlp(), batch.len);
        let mut critic_ws = MlpWorkspace::new(critic.mlp(), batch.len);
        actor.fill_input(&mut actor_ws, &batch.states, &batch.goals);
        actor.forward_batch(&mut actor_ws);
        critic.fill_state_goal(&mut critic_ws, &batch.states, &batch.goals);
        let rows = critic.mlp().input_dim();
        actor.write_actions(
            &actor_ws,
            critic_ws.input_mut(),
            rows,
            critic.action_rows().start,
        );
        critic.forward_batch(&mut critic_ws, false);
        critic_ws.output().iter().sum::<f32>() / batch.len as f32
    }

    #[test]
    fn actor_step_raises_the_updated_critics_value() {
        let mut rng = Rng::seed_from(36);
        let mut learner = LevelLearner::new(config(None), &mut rng);
        let batch = random_batch(&mut rng, 128);
        for _ in 0..20 {
            learner.update(&batch);
        }
        let stats = learner.update(&batch);
        // `actor_loss` was measured with the critic the actor step used (the final one), so the
        // (small, first-order) actor step must have raised this value.
        let value = policy_value(&learner, &batch);
        assert!(
            value > -stats.actor_loss,
            "mean Q(s, g, pi(s, g)) went from {} to {value}",
            -stats.actor_loss
        );
    }

    #[test]
    fn actor_climbs_the_critic() {
        // A one-step task: every transition is terminal with reward -2 - |a - c|^2, so the best
        // action is c whatever the state and goal. (The -2 keeps values away from 0, where the
        // critic's sigmoid is flat and learns slowly.)
        let best = [1.0, 0.25];
        let mut rng = Rng::seed_from(32);
        // A slower actor lets the critic learn the curvature before the actor commits to a
        // direction (a saturated tanh would stop it there).
        let slow_actor = LearnerConfig {
            actor_lr: 1e-4,
            ..config(None)
        };
        let mut learner = LevelLearner::new(slow_actor, &mut rng);
        // The state and goal play no part in this task: leaving them at zero spares the critic
        // learning to ignore them.
        let mut batch = Batch::zeros(DIMS, 256);
        for _ in 0..1000 {
            for (j, a) in batch.actions.chunks_exact_mut(2).enumerate() {
                a[0] = rng.uniform(-2.0, 2.0);
                a[1] = rng.uniform(0.0, 1.0);
                let sq_dist: f32 = a.iter().zip(best).map(|(a, c)| (a - c).powi(2)).sum();
                batch.rewards[j] = -2.0 - sq_dist;
                batch.terminals[j] = 1.0;
            }
            learner.update(&batch);
        }

        let mut action = [0.0; 2];
        learner.act(&[0.0; 3], &[0.0; 2], &mut action);
        let dist = action
            .iter()
            .zip(best)
            .map(|(a, c)| (a - c).powi(2))
            .sum::<f32>()
            .sqrt();
        assert!(dist < 0.3, "action {action:?}, best {best:?}");
    }

    /// A learner whose actor outputs sit at the corner `(2, 1)` of its bounds with pre-activations
    /// of about 40 (tanh rounds to 1), and whose critic reads exactly `-H` everywhere with a slope
    /// that underflows to 0 (its output bias of 1000 far up the sigmoid): the failure the paper's
    /// loss cannot leave.
    fn stuck_at_a_corner(actor_preactivation_l2: f32) -> LevelLearner {
        let mut rng = Rng::seed_from(35);
        let mut learner = LevelLearner::new(
            LearnerConfig {
                actor_preactivation_l2,
                ..config(None)
            },
            &mut rng,
        );
        let actor_bias = learner.nets.actor.mlp_mut().tensors_mut().last().unwrap();
        actor_bias.fill(40.0);
        let critic_bias = learner.nets.critic.mlp_mut().tensors_mut().last().unwrap();
        critic_bias.fill(1000.0);
        learner
    }

    fn mean_action(learner: &mut LevelLearner, batch: &Batch) -> [f32; 2] {
        let mut sum = [0.0; 2];
        let mut a = [0.0; 2];
        for (s, g) in batch
            .states
            .chunks_exact(DIMS.state)
            .zip(batch.goals.chunks_exact(DIMS.goal))
        {
            learner.act(s, g, &mut a);
            sum[0] += a[0];
            sum[1] += a[1];
        }
        sum.map(|v| v / batch.len as f32)
    }

    #[test]
    fn a_saturated_actor_on_a_flat_critic_stays_stuck_without_the_penalty() {
        let mut rng = Rng::seed_from(36);
        let batch = random_batch(&mut rng, 64);
        let mut learner = stuck_at_a_corner(0.0);
        let actor = learner.actor().mlp().clone();
        for _ in 0..50 {
            let stats = learner.update(&batch);
            assert_eq!(stats.actor_loss, 10.0, "the critic reads exactly -H");
        }
        assert_eq!(mean_action(&mut learner, &batch), [2.0, 1.0]);
        assert!(
            learner
                .actor()
                .mlp()
                .tensors()
                .zip(actor.tensors())
                .all(|(a, b)| a == b),
            "a zero gradient moves nothing"
        );
    }

    #[test]
    fn the_preactivation_penalty_pulls_a_saturated_actor_off_the_corner() {
        let mut rng = Rng::seed_from(36);
        let batch = random_batch(&mut rng, 64);
        let mut learner = stuck_at_a_corner(1e-3);
        // Adam moves each parameter by about the learning rate per step whatever the gradient's
        // size, so even a small weight brings the pre-activations from 40 towards 0 within a
        // few thousand steps; the critic stays flat, so the penalty is all that acts.
        for _ in 0..5000 {
            learner.update(&batch);
        }
        let [a0, a1] = mean_action(&mut learner, &batch);
        // The bounds are [-2, 2] x [0, 1]: the middle is (0, 0.5).
        assert!(
            a0.abs() < 1.0 && (a1 - 0.5).abs() < 0.25,
            "mean action ({a0}, {a1})"
        );
    }

    #[test]
    fn target_networks_follow_by_polyak_averaging() {
        let mut rng = Rng::seed_from(33);
        let tau = 0.1;
        let mut learner = LevelLearner::new(config(Some(tau)), &mut rng);
        let before = learner.critic().mlp().clone();
        learner.update(&random_batch(&mut rng, 64));
        let targets = learner.nets.targets.as_ref().expect("targets enabled");
        let after = learner.critic().mlp();
        for ((t, old), new) in targets
            .critic
            .mlp()
            .tensors()
            .zip(before.tensors())
            .zip(after.tensors())
        {
            for ((t, old), new) in t.iter().zip(old).zip(new) {
                assert!((t - (old + tau * (new - old))).abs() < 1e-6);
            }
        }
        assert_ne!(targets.actor.mlp(), learner.actor().mlp());
    }

    #[test]
    fn same_seed_gives_bit_identical_learners() {
        for tau in [None, Some(0.05)] {
            let run = |seed: u64| {
                let mut learner = LevelLearner::new(config(tau), &mut Rng::seed_from(seed));
                let mut data = Rng::seed_from(99);
                for _ in 0..5 {
                    learner.update(&random_batch(&mut data, 128));
                }
                learner.to_safetensors()
            };
            assert_eq!(run(7), run(7));
            assert_ne!(run(7), run(8));
        }
    }

    /// A learner's whole state after `updates` updates on minibatches of `len` samples, with
    /// `threads` threads.
    fn trained(config: LearnerConfig, threads: usize, updates: usize, len: usize) -> Vec<u8> {
        let mut learner = LevelLearner::new(config, &mut Rng::seed_from(41));
        learner.set_threads(threads);
        assert_eq!(learner.threads(), threads);
        let mut data = Rng::seed_from(42);
        let mut stats = Vec::new();
        for _ in 0..updates {
            stats.push(learner.update(&random_batch(&mut data, len)));
        }
        let mut state = learner.to_safetensors();
        // The statistics too, bit for bit.
        for s in stats {
            for v in [s.critic_loss, s.actor_loss, s.mean_q, s.mean_target] {
                state.extend(v.to_bits().to_le_bytes());
            }
        }
        state
    }

    #[test]
    fn the_saturating_tanh_reaches_the_actor_its_weights_and_a_restore() {
        let cfg = LearnerConfig {
            saturating_tanh: true,
            ..config(Some(0.05))
        };
        let learner = LevelLearner::new(cfg.clone(), &mut Rng::seed_from(1));
        assert!(learner.actor().saturating_tanh());
        let published = ActorNet::from_safetensors(&learner.actor().to_safetensors()).unwrap();
        assert!(published.saturating_tanh());
        let bytes = learner.to_safetensors();
        let restored = LevelLearner::from_safetensors(cfg.clone(), &bytes).unwrap();
        assert!(restored.actor().saturating_tanh());
        assert_eq!(restored.to_safetensors(), bytes);
        // On a restore the configuration decides, as for the other hyperparameters.
        let plain = LearnerConfig {
            saturating_tanh: false,
            ..cfg
        };
        let restored = LevelLearner::from_safetensors(plain, &bytes).unwrap();
        assert!(!restored.actor().saturating_tanh());
    }

    #[test]
    fn weights_are_bit_identical_for_any_thread_count() {
        let with_everything = LearnerConfig {
            actor_preactivation_l2: 1e-3,
            exact_critic_slope: true,
            saturating_tanh: true,
            ..config(Some(0.05))
        };
        for cfg in [config(None), with_everything] {
            // 8 chunks of 256; 5 uneven chunks; a single chunk.
            for len in [2048, 1300, 100] {
                let one = trained(cfg.clone(), 1, 6, len);
                for threads in [2, 3] {
                    assert!(
                        one == trained(cfg.clone(), threads, 6, len),
                        "{threads} threads, batch {len}, {cfg:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_gate_lets_threads_through_together_and_a_stop_frees_a_waiter() {
        let gate = Arc::new(Gate::new(3));
        let arrivals = Arc::new(AtomicU64::new(0));
        let threads: Vec<_> = (0..3)
            .map(|_| {
                let (gate, arrivals) = (Arc::clone(&gate), Arc::clone(&arrivals));
                std::thread::spawn(move || {
                    for pass in 1..=200 {
                        arrivals.fetch_add(1, Ordering::SeqCst);
                        gate.pass(pass).expect("nobody stops this gate");
                        // No thread gets through before every thread has arrived.
                        assert!(arrivals.load(Ordering::SeqCst) >= 3 * pass, "pass {pass}");
                    }
                })
            })
            .collect();
        for thread in threads {
            thread.join().unwrap();
        }

        // A thread waiting for one that never comes, asleep by now, is freed by a stop.
        let gate = Arc::new(Gate::new(2));
        let waiter = std::thread::spawn({
            let gate = Arc::clone(&gate);
            move || gate.pass(1)
        });
        std::thread::sleep(3 * SPIN_BEFORE_PARKING);
        gate.stop();
        assert!(waiter.join().unwrap().is_err());
        // And a thread that comes to a stopped gate does not wait.
        assert!(gate.pass(1).is_err());
    }

    /// Each worker keeps its own copy of the networks and optimisers: it must follow the
    /// learner's through batches of changing size (threads with no chunk of their own still take
    /// the steps) and through a restore, which changes the learner's state outside an update.
    #[test]
    fn worker_copies_follow_changing_batches_and_restores() {
        let run = |threads: usize| {
            let mut learner = LevelLearner::new(config(Some(0.05)), &mut Rng::seed_from(44));
            learner.set_threads(threads);
            let mut data = Rng::seed_from(45);
            let mut backup = LearnerBackup::default();
            for (i, len) in [1024, 100, 2048, 600, 1024, 1300].into_iter().enumerate() {
                if i == 2 {
                    learner.save(&mut backup);
                }
                learner.update(&random_batch(&mut data, len));
                if i == 3 {
                    learner.restore(&backup);
                }
            }
            learner.to_safetensors()
        };
        let one = run(1);
        for threads in [2, 4] {
            assert!(one == run(threads), "{threads} threads");
        }
    }

    #[test]
    fn chunked_gradients_sum_to_the_whole_batch_gradient() {
        let cfg = LearnerConfig {
            actor_preactivation_l2: 1e-2,
            ..config(Some(0.05))
        };
        let mut rng = Rng::seed_from(43);
        let mut learner = LevelLearner::new(cfg, &mut rng);
        // Move the networks away from their initial values first.
        for _ in 0..5 {
            learner.update(&random_batch(&mut rng, 256));
        }
        let batch = random_batch(&mut rng, 203);
        let all = Fields::new(&batch);
        let (cfg, nets) = (&learner.config, &learner.nets);
        let mut scratch = Scratch::new(&nets.actor, &nets.critic);
        let whole = Chunks::new(&nets.actor, &nets.critic);
        nets.critic_part(cfg, &mut scratch, &whole, &all, (0..1, 1));
        let whole_y = scratch.y.clone();
        nets.actor_part(cfg, &mut scratch, &whole, &all, (0..1, 1));
        let (whole_critic, whole_actor) = (read(&whole.critic[0]), read(&whole.actor[0]));
        // The chunks run one after the other through one scratch, as on a thread; the actor part
        // starts after the last chunk's critic part has left its rows in the scratch.
        let chunks = Chunks::new(&nets.actor, &nets.critic);
        let mut y = Vec::new();
        for k in 0..GRADIENT_CHUNKS {
            nets.critic_part(
                cfg,
                &mut scratch,
                &chunks,
                &all,
                (k..k + 1, GRADIENT_CHUNKS),
            );
            y.extend_from_slice(&scratch.y);
        }
        nets.actor_part(
            cfg,
            &mut scratch,
            &chunks,
            &all,
            (0..GRADIENT_CHUNKS, GRADIENT_CHUNKS),
        );
        let critic_chunks: Vec<CriticChunk> =
            chunks.critic.iter().map(|c| read(c).clone()).collect();
        let actor_chunks: Vec<ActorChunk> = chunks.actor.iter().map(|c| read(c).clone()).collect();
        let (mut critic_sum, mut actor_sum) = (
            critic_chunks[0].grads.clone(),
            actor_chunks[0].grads.clone(),
        );
        for (c, a) in critic_chunks[1..].iter().zip(&actor_chunks[1..]) {
            critic_sum.add(&c.grads);
            actor_sum.add(&a.grads);
        }
        let pairs = [
            ("critic", &critic_sum, &whole_critic.grads),
            ("actor", &actor_sum, &whole_actor.grads),
        ];
        for (what, sum, whole) in pairs {
            for (t, (got, want)) in sum.tensors().zip(whole.tensors()).enumerate() {
                let scale = want.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                for (g, w) in got.iter().zip(want) {
                    assert!(
                        (g - w).abs() <= 1e-4 * scale,
                        "{what} tensor {t}: {g} vs {w} (largest {scale})"
                    );
                }
            }
        }
        assert_eq!(y, whole_y, "targets are per sample");
        let sum = |f: fn(&CriticChunk) -> f32| critic_chunks.iter().map(f).sum::<f32>();
        let policy_q_sum = actor_chunks.iter().map(|c| c.policy_q_sum).sum::<f32>();
        for (what, got, want) in [
            ("targets", sum(|c| c.target_sum), whole_critic.target_sum),
            (
                "squared errors",
                sum(|c| c.sq_err_sum),
                whole_critic.sq_err_sum,
            ),
            ("Q", sum(|c| c.q_sum), whole_critic.q_sum),
            ("policy Q", policy_q_sum, whole_actor.policy_q_sum),
        ] {
            assert!(
                (got - want).abs() <= 1e-4 * want.abs().max(1.0),
                "{what}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn a_clone_updates_on_one_thread_and_continues_identically() {
        let mut rng = Rng::seed_from(44);
        let mut learner = LevelLearner::new(config(Some(0.05)), &mut rng);
        learner.set_threads(3);
        learner.update(&random_batch(&mut rng, 64));
        let mut copy = learner.clone();
        assert_eq!(copy.threads(), 1);
        assert_eq!(copy.to_safetensors(), learner.to_safetensors());
        for _ in 0..3 {
            let batch = random_batch(&mut rng, 900);
            assert_eq!(learner.update(&batch), copy.update(&batch));
        }
        assert_eq!(learner.to_safetensors(), copy.to_safetensors());
        learner.set_threads(100);
        assert_eq!(learner.threads(), GRADIENT_CHUNKS);
    }

    #[test]
    fn timing_splits_each_update_into_its_serial_and_parallel_parts() {
        let mut rng = Rng::seed_from(45);
        let mut learner = LevelLearner::new(config(Some(0.05)), &mut rng);
        let batch = random_batch(&mut rng, 1024);
        for _ in 0..3 {
            learner.update(&batch);
        }
        let one = learner.timing();
        assert_eq!(one.updates, 3);
        assert!(
            one.parallel > Duration::ZERO && one.parallel <= one.total,
            "{one:?}"
        );
        assert_eq!(one.serial(), one.total - one.parallel);
        // On one thread nobody is waited for.
        assert_eq!(one.waiting, Duration::ZERO, "{one:?}");

        // A clone starts from zero; a reset goes back to zero.
        let mut copy = learner.clone();
        assert_eq!(copy.timing(), UpdateTiming::default());
        copy.set_threads(2);
        copy.update(&batch);
        let two = copy.timing();
        assert_eq!(two.updates, 1);
        assert!(
            two.waiting <= two.parallel && two.parallel <= two.total,
            "{two:?}"
        );
        copy.reset_timing();
        assert_eq!(copy.timing(), UpdateTiming::default());
        // The timers change no number.
        learner.update(&batch);
        assert_eq!(learner.to_safetensors(), copy.to_safetensors());
    }

    #[test]
    fn update_flops_count_the_products_of_the_reference_network() {
        // Pendulum's level 0 at the reference size: actor 5-64-64-64-1, critic 6-64-64-64-1.
        let cfg = LearnerConfig {
            dims: LevelDims {
                state: 3,
                goal: 2,
                action: 1,
            },
            action_bounds: Bounds::symmetric(&[2.0]),
            hidden: vec![64, 64, 64],
            ..config(None)
        };
        let actor = 5 * 64 + 2 * 64 * 64 + 64;
        let critic = 6 * 64 + 2 * 64 * 64 + 64;
        let hidden_and_out = 2 * 64 * 64 + 64;
        let macs = 2 * actor + 3 * critic // forward passes
            + critic + hidden_and_out // critic step backward
            + hidden_and_out + 64 // action gradient
            + actor + hidden_and_out; // actor backward
        assert_eq!(macs, 85_120);
        assert_eq!(cfg.update_flops(1024), 2 * 85_120 * 1024);
    }

    #[test]
    fn checkpoint_round_trip_continues_identically() {
        let mut rng = Rng::seed_from(34);
        let mut learner = LevelLearner::new(config(Some(0.05)), &mut rng);
        for _ in 0..3 {
            learner.update(&random_batch(&mut rng, 64));
        }
        let bytes = learner.to_safetensors();
        let mut restored = LevelLearner::from_safetensors(config(Some(0.05)), &bytes).unwrap();
        assert_eq!(restored.to_safetensors(), bytes);
        for _ in 0..2 {
            let batch = random_batch(&mut rng, 64);
            assert_eq!(learner.update(&batch), restored.update(&batch));
        }
        assert_eq!(learner.to_safetensors(), restored.to_safetensors());
    }

    #[test]
    fn checkpoint_for_another_level_is_rejected() {
        let mut rng = Rng::seed_from(35);
        let bytes = LevelLearner::new(config(None), &mut rng).to_safetensors();

        let wider = LearnerConfig {
            hidden: vec![32, 48],
            ..config(None)
        };
        let other_bounds = LearnerConfig {
            action_bounds: Bounds::symmetric(&[1.0, 1.0]),
            ..config(None)
        };
        let other_horizon = LearnerConfig {
            horizon: 5.0,
            ..config(None)
        };
        for (what, cfg) in [
            ("hidden", wider),
            ("bounds", other_bounds),
            ("horizon", other_horizon),
        ] {
            let err = LevelLearner::from_safetensors(cfg, &bytes).expect_err(what);
            assert!(matches!(err, NnError::Mismatch { .. }), "{what}: {err}");
        }
        // Target networks asked for but not saved.
        assert!(matches!(
            LevelLearner::from_safetensors(config(Some(0.05)), &bytes),
            Err(NnError::MissingTensor(_))
        ));
        assert!(matches!(
            LevelLearner::from_safetensors(config(None), &bytes[..bytes.len() / 2]),
            Err(NnError::Format(_))
        ));
        let actor_file = LevelLearner::new(config(None), &mut rng)
            .actor()
            .to_safetensors();
        assert!(matches!(
            LevelLearner::from_safetensors(config(None), &actor_file),
            Err(NnError::Metadata { .. })
        ));
    }
}
