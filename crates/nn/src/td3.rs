//! TD3 (Fujimoto, van Hoof and Meger, *Addressing Function Approximation Error in Actor-Critic
//! Methods*, ICML 2018): the learner of both of HIRO's levels.
//!
//! Against HAC's level learner ([`crate::LevelLearner`]): two critics, unbounded (HIRO's rewards
//! are distances and sums of -1 over `c` steps, with no attempt budget to bound them); target
//! networks for the actor and both critics, moved by Polyak averaging; a target that bootstraps
//! from the smaller of the two target critics at a smoothed target action; and an actor updated
//! every `policy_delay`-th critic update only. The next goal can differ from the goal (HIRO's
//! low level: the goal moves with the state), so [`Td3Learner::update`] takes it apart.

use hac_core::hiro::CriticLoss;
use hac_core::{Batch, Bounds, LevelDims, Rng};

use crate::checkpoint::{TensorReader, TensorWriter};
use crate::kernels::copy_rows;
use crate::learner::{UpdateStats, check_actor, check_widths, divergence};
use crate::{ActorNet, Adam, Diverged, LearnerBackup, Mlp, MlpGrads, MlpWorkspace, NnError};

/// Value of the `format` metadata entry of a TD3 learner checkpoint (distinct from
/// [`crate::LevelLearner`]'s, whose files hold one critic).
const FORMAT: &str = "hac-nn/td3-learner";

/// What a TD3 learner needs to know (defaults: [`Td3Config::reference`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Td3Config {
    /// Widths of the level's state, goal and action.
    pub dims: LevelDims,
    /// Bounds of the level's output.
    pub action_bounds: Bounds,
    /// Discount factor.
    pub gamma: f32,
    /// Hidden layer widths, shared by actor and critics.
    pub hidden: Vec<usize>,
    /// Adam step size of the actor.
    pub actor_lr: f32,
    /// Adam step size of each critic.
    pub critic_lr: f32,
    /// Polyak rate of the target networks.
    pub tau: f32,
    /// Standard deviation of the target policy's smoothing noise, as a fraction of each action
    /// dimension's half range.
    pub policy_noise: f32,
    /// The smoothing noise is clipped to this fraction of the half range.
    pub noise_clip: f32,
    /// The actor and the targets move once per this many critic updates.
    pub policy_delay: u64,
    /// What each critic minimises against the target.
    pub critic_loss: CriticLoss,
}

impl Td3Config {
    /// The critics' layer widths, `[state + goal + action, hidden.., 1]`.
    fn critic_sizes(&self) -> Vec<usize> {
        let d = self.dims;
        [&[d.state + d.goal + d.action], self.hidden.as_slice(), &[1]].concat()
    }

    /// The HIRO paper's TD3 settings for a level with `dims` and `action_bounds`: gamma 0.99,
    /// actor lr 1e-4, critic lr 1e-3, tau 0.005, smoothing noise 0.2 clipped to 0.5 (of the half
    /// range), actor every 2nd critic update, critics on the mean squared error; hidden layers
    /// as given.
    pub fn reference(dims: LevelDims, action_bounds: Bounds, hidden: Vec<usize>) -> Self {
        Self {
            dims,
            action_bounds,
            gamma: 0.99,
            hidden,
            actor_lr: 1e-4,
            critic_lr: 1e-3,
            tau: 0.005,
            policy_noise: 0.2,
            noise_clip: 0.5,
            policy_delay: 2,
            critic_loss: CriticLoss::Mse,
        }
    }
}

/// Learns one level's actor and twin critics with TD3. Owns every buffer an update needs.
#[derive(Debug, Clone)]
pub struct Td3Learner {
    config: Td3Config,
    actor: ActorNet,
    target_actor: ActorNet,
    critics: [Mlp; 2],
    target_critics: [Mlp; 2],
    actor_opt: Adam,
    critic_opts: [Adam; 2],
    actor_ws: MlpWorkspace,
    critic_ws: MlpWorkspace,
    actor_grads: MlpGrads,
    critic_grads: MlpGrads,
    /// The critics' regression targets for the current batch.
    y: Vec<f32>,
    /// The actor loss of the last actor step.
    last_actor_loss: f32,
}

impl Td3Learner {
    /// A freshly initialised learner: the actor, then the two critics, draw their weights from
    /// `rng`; the targets start as copies.
    pub fn new(config: Td3Config, rng: &mut Rng) -> Self {
        let d = config.dims;
        let actor = ActorNet::new(d, &config.action_bounds, &config.hidden, rng);
        let sizes: Vec<usize> = std::iter::once(d.state + d.goal + d.action)
            .chain(config.hidden.iter().copied())
            .chain(std::iter::once(1))
            .collect();
        let critics = [Mlp::new(&sizes, rng), Mlp::new(&sizes, rng)];
        let (target_actor, target_critics) = (actor.clone(), critics.clone());
        Self::assemble(config, [actor, target_actor], [critics, target_critics])
    }

    /// A learner of the given networks (`[actor, target]`, `[critics, targets]`) with fresh
    /// optimisers and buffers.
    fn assemble(config: Td3Config, actors: [ActorNet; 2], critics: [[Mlp; 2]; 2]) -> Self {
        let [actor, target_actor] = actors;
        let [critics, target_critics] = critics;
        let lens = |m: &Mlp| m.tensors().map(<[f32]>::len).collect::<Vec<_>>();
        Self {
            actor_opt: Adam::new(config.actor_lr, lens(actor.mlp())),
            critic_opts: [
                Adam::new(config.critic_lr, lens(&critics[0])),
                Adam::new(config.critic_lr, lens(&critics[1])),
            ],
            actor_ws: MlpWorkspace::new(actor.mlp(), 0),
            critic_ws: MlpWorkspace::new(&critics[0], 0),
            actor_grads: MlpGrads::new(actor.mlp()),
            critic_grads: MlpGrads::new(&critics[0]),
            y: Vec::new(),
            last_actor_loss: 0.0,
            target_actor,
            target_critics,
            actor,
            critics,
            config,
        }
    }

    /// The configuration the learner was built from.
    pub fn config(&self) -> &Td3Config {
        &self.config
    }

    /// The current actor.
    pub fn actor(&self) -> &ActorNet {
        &self.actor
    }

    /// The greedy action `pi(state, goal)`, written into `out`.
    pub fn act(&mut self, state: &[f32], goal: &[f32], out: &mut [f32]) {
        self.actor.act(state, goal, out);
    }

    /// Critic updates done so far.
    pub fn updates(&self) -> u64 {
        self.critic_opts[0].steps()
    }

    /// One TD3 update on `batch`: both critics regress on
    /// `y = r + gamma (1 - terminal) min_k Q'_k(s', g', clip(pi'(s', g') + eps))`, with `eps` the
    /// clipped smoothing noise drawn from `rng` and `g'` = `next_goals` (the batch's goals when
    /// `None`); every `policy_delay`-th update the actor then ascends `Q_1(s, g, pi(s, g))` and
    /// the targets move toward the networks.
    ///
    /// Panics if the batch is empty, of another level's dimensions, or `next_goals` is short.
    pub fn update(
        &mut self,
        batch: &Batch,
        next_goals: Option<&[f32]>,
        rng: &mut Rng,
    ) -> UpdateStats {
        let d = self.config.dims;
        assert_eq!(
            batch.dims, d,
            "td3: batch dimensions differ from the level's"
        );
        let n = batch.len;
        assert!(n > 0, "td3: empty batch");
        let next_goals = next_goals.unwrap_or(&batch.goals);
        assert!(
            next_goals.len() >= n * d.goal,
            "td3: next goals of fewer samples"
        );
        self.actor_ws.set_batch(n);
        self.critic_ws.set_batch(n);
        self.y.resize(n, 0.0);
        let mean_target = self.set_targets(batch, &next_goals[..n * d.goal], rng);
        let (critic_loss, mean_q) = self.critic_steps(batch);
        if self
            .updates()
            .is_multiple_of(self.config.policy_delay.max(1))
        {
            self.last_actor_loss = self.actor_step(batch);
            let tau = self.config.tau;
            self.target_actor
                .mlp_mut()
                .polyak_toward(self.actor.mlp(), tau);
            for (t, c) in self.target_critics.iter_mut().zip(&self.critics) {
                t.polyak_toward(c, tau);
            }
        }
        UpdateStats {
            critic_loss,
            actor_loss: self.last_actor_loss,
            mean_q,
            mean_target,
        }
    }

    /// [`update`](Self::update), undone if it diverged: when a statistic is not finite or a
    /// parameter of the actor or of either critic is not finite or above
    /// [`crate::PARAMETER_LIMIT`] (the rules of [`crate::LevelLearner::update_or_undo`]), the
    /// learner is put back as it was before (networks, targets, optimisers and their step
    /// counts, the last actor loss) and the error says what was wrong. `rng` is not put back:
    /// the smoothing noise drawn stays drawn. `backup` is scratch space kept between calls.
    ///
    /// Healthy updates are bit-identical to [`update`](Self::update)'s.
    pub fn update_or_undo(
        &mut self,
        batch: &Batch,
        next_goals: Option<&[f32]>,
        rng: &mut Rng,
        backup: &mut LearnerBackup,
    ) -> Result<UpdateStats, Diverged> {
        self.save(backup);
        let stats = self.update(batch, next_goals, rng);
        let networks = [
            ("actor parameter", self.actor.mlp()),
            ("critic parameter", &self.critics[0]),
            ("critic parameter", &self.critics[1]),
        ];
        match divergence(&stats, networks) {
            None => Ok(stats),
            Some(diverged) => {
                self.restore(backup);
                Err(diverged)
            }
        }
    }

    /// Copies everything an update changes into `backup`: the three step counts (actor, then
    /// each critic's optimiser), then the actor, both critics, the three optimisers' moments,
    /// the target actor, both target critics and the last actor loss. Allocates nothing once
    /// `backup` has held this learner's state.
    pub fn save(&self, backup: &mut LearnerBackup) {
        let (actor_steps, actor_moments) = self.actor_opt.state();
        let (steps_0, moments_0) = self.critic_opts[0].state();
        let (steps_1, moments_1) = self.critic_opts[1].state();
        let slices = self
            .actor
            .mlp()
            .tensors()
            .chain(self.critics.iter().flat_map(Mlp::tensors))
            .chain(actor_moments)
            .chain(moments_0)
            .chain(moments_1)
            .chain(self.target_actor.mlp().tensors())
            .chain(self.target_critics.iter().flat_map(Mlp::tensors))
            .chain(std::iter::once(std::slice::from_ref(&self.last_actor_loss)));
        backup.fill([actor_steps, steps_0, steps_1], slices);
    }

    /// Puts back what [`save`](Self::save) copied into `backup`.
    ///
    /// Panics if `backup` was saved from a learner of another shape or kind (a
    /// [`crate::LevelLearner`]'s holds two step counts, not three).
    pub fn restore(&mut self, backup: &LearnerBackup) {
        let (actor_steps, actor_moments) = self.actor_opt.state_mut();
        let [opt_0, opt_1] = &mut self.critic_opts;
        let (steps_0, moments_0) = opt_0.state_mut();
        let (steps_1, moments_1) = opt_1.state_mut();
        let mut slices: Vec<&mut [f32]> = self.actor.mlp_mut().tensors_mut().collect();
        slices.extend(self.critics.iter_mut().flat_map(Mlp::tensors_mut));
        slices.extend(actor_moments);
        slices.extend(moments_0);
        slices.extend(moments_1);
        slices.extend(self.target_actor.mlp_mut().tensors_mut());
        slices.extend(self.target_critics.iter_mut().flat_map(Mlp::tensors_mut));
        slices.push(std::slice::from_mut(&mut self.last_actor_loss));
        backup.put_back(&mut [actor_steps, steps_0, steps_1], &mut slices);
    }

    /// The learner's whole state as a safetensors file (format tag `hac-nn/td3-learner`): the
    /// actor (`actor.*`, laid out as in [`ActorNet::to_safetensors`]) and target actor
    /// (`target_actor.*`); the critics and target critics (`critic.{k}.{l}.weight` as `[out,
    /// in]` and `critic.{k}.{l}.bias`, `target_critic.{k}.*`, `k` 0 or 1, `l` the layer); the
    /// optimisers' moments (`actor_adam.*`, `critic_adam.{k}.*`) with their step counts as
    /// metadata; and the loss of the last actor step (`last_actor_loss`, one value, which
    /// updates between actor steps report).
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut out = TensorWriter::default();
        out.meta("format".into(), FORMAT);
        self.actor.write("actor.", &mut out);
        self.target_actor.write("target_actor.", &mut out);
        for k in 0..2 {
            self.critics[k].write(&format!("critic.{k}."), &mut out);
            self.target_critics[k].write(&format!("target_critic.{k}."), &mut out);
            self.critic_opts[k].write(&format!("critic_adam.{k}."), &mut out);
        }
        self.actor_opt.write("actor_adam.", &mut out);
        out.add(
            "last_actor_loss".into(),
            &[1],
            std::slice::from_ref(&self.last_actor_loss),
        );
        out.finish()
    }

    /// Restores a learner saved by [`Td3Learner::to_safetensors`]. Every network in the file
    /// must have the architecture and (actors) the bounds `config` describes, else the error
    /// ([`NnError::Mismatch`]) names the network and the property that differs; the
    /// hyperparameters (learning rates, gamma, tau, noise, delay) come from `config`.
    pub fn from_safetensors(config: Td3Config, bytes: &[u8]) -> Result<Self, NnError> {
        let file = TensorReader::new(bytes)?;
        file.expect_format(FORMAT)?;
        let (d, bounds, hidden) = (config.dims, &config.action_bounds, &config.hidden);
        let read_actor = |name: &str| -> Result<ActorNet, NnError> {
            let actor = ActorNet::read(&format!("{name}."), &file)?;
            check_actor(name, d, bounds, hidden, &actor)?;
            Ok(actor)
        };
        let actors = [read_actor("actor")?, read_actor("target_actor")?];
        let critic_sizes = config.critic_sizes();
        let read_critic = |name: String| -> Result<Mlp, NnError> {
            let mlp = Mlp::read(&format!("{name}."), &file)?;
            check_widths(&name, &critic_sizes, &mlp)?;
            Ok(mlp)
        };
        let critics = [
            [
                read_critic("critic.0".into())?,
                read_critic("critic.1".into())?,
            ],
            [
                read_critic("target_critic.0".into())?,
                read_critic("target_critic.1".into())?,
            ],
        ];
        let mut learner = Self::assemble(config, actors, critics);
        learner.actor_opt.read("actor_adam.", &file)?;
        for (k, opt) in learner.critic_opts.iter_mut().enumerate() {
            opt.read(&format!("critic_adam.{k}."), &file)?;
        }
        file.read_into(
            "last_actor_loss",
            std::slice::from_mut(&mut learner.last_actor_loss),
        )?;
        Ok(learner)
    }

    /// Sets `self.y` to the clipped double-Q targets; returns their mean.
    fn set_targets(&mut self, batch: &Batch, next_goals: &[f32], rng: &mut Rng) -> f32 {
        let d = self.config.dims;
        let n = batch.len;
        let rows = d.state + d.goal + d.action;
        self.target_actor.fill_input(
            &mut self.actor_ws,
            &batch.next_states[..n * d.state],
            next_goals,
        );
        self.target_actor.forward_batch(&mut self.actor_ws);
        let input = self.critic_ws.input_mut();
        copy_rows(input, rows, 0, &batch.next_states[..n * d.state], d.state);
        copy_rows(input, rows, d.state, next_goals, d.goal);
        let action_row = d.state + d.goal;
        self.target_actor
            .write_actions(&self.actor_ws, input, rows, action_row);
        smooth(
            input,
            rows,
            action_row,
            &self.config.action_bounds,
            self.config.policy_noise,
            self.config.noise_clip,
            rng,
        );
        self.target_critics[0].forward(&mut self.critic_ws);
        self.y.copy_from_slice(self.critic_ws.output());
        self.target_critics[1].forward(&mut self.critic_ws);
        let gamma = self.config.gamma;
        let mut sum = 0.0;
        for (((y, &q2), &r), &terminal) in self
            .y
            .iter_mut()
            .zip(self.critic_ws.output())
            .zip(&batch.rewards)
            .zip(&batch.terminals)
        {
            *y = r + gamma * (1.0 - terminal) * y.min(q2);
            sum += *y;
        }
        sum / n as f32
    }

    /// One Adam step on each critic's loss against `self.y` (the mean over the batch of
    /// [`Td3Config::critic_loss`]); returns the mean of the two critics' losses and the first
    /// critic's mean `Q`, both from before the steps.
    fn critic_steps(&mut self, batch: &Batch) -> (f32, f32) {
        let d = self.config.dims;
        let n = batch.len;
        let rows = d.state + d.goal + d.action;
        let input = self.critic_ws.input_mut();
        copy_rows(input, rows, 0, &batch.states[..n * d.state], d.state);
        copy_rows(input, rows, d.state, &batch.goals[..n * d.goal], d.goal);
        copy_rows(
            input,
            rows,
            d.state + d.goal,
            &batch.actions[..n * d.action],
            d.action,
        );
        let inv_n = 1.0 / n as f32;
        let critic_loss = self.config.critic_loss;
        let (mut loss, mut mean_q) = (0.0, 0.0);
        for k in 0..2 {
            let critic = &mut self.critics[k];
            critic.forward(&mut self.critic_ws);
            let (mut loss_sum, mut q_sum) = (0.0, 0.0);
            let (q, dq) = self.critic_ws.output_and_grad_mut();
            for ((dq, &q), &y) in dq.iter_mut().zip(q).zip(&self.y) {
                let (value, slope) = critic_loss.value_and_slope(q - y);
                loss_sum += value;
                q_sum += q;
                *dq = slope * inv_n;
            }
            critic.backward(&mut self.critic_ws, Some(&mut self.critic_grads), 0..0);
            self.critic_opts[k].step(critic.tensors_mut().zip(self.critic_grads.tensors()));
            loss += 0.5 * loss_sum * inv_n;
            if k == 0 {
                mean_q = q_sum * inv_n;
            }
        }
        (loss, mean_q)
    }

    /// One Adam step on the actor's loss `-mean Q_1(s, g, pi(s, g))`; returns that loss from
    /// before the step. Runs after [`Td3Learner::critic_steps`], whose state and goal rows of
    /// the critics' input it reuses.
    fn actor_step(&mut self, batch: &Batch) -> f32 {
        let d = self.config.dims;
        let n = batch.len;
        let rows = d.state + d.goal + d.action;
        self.actor.fill_input(
            &mut self.actor_ws,
            &batch.states[..n * d.state],
            &batch.goals[..n * d.goal],
        );
        self.actor.forward_batch(&mut self.actor_ws);
        let action_row = d.state + d.goal;
        self.actor
            .write_actions(&self.actor_ws, self.critic_ws.input_mut(), rows, action_row);
        let critic = &self.critics[0];
        critic.forward(&mut self.critic_ws);
        let inv_n = 1.0 / n as f32;
        let mut q_sum = 0.0;
        let (q, dq) = self.critic_ws.output_and_grad_mut();
        for (dq, &q) in dq.iter_mut().zip(q) {
            q_sum += q;
            *dq = -inv_n;
        }
        critic.backward(&mut self.critic_ws, None, action_row..rows);
        self.actor_ws
            .output_grad_mut()
            .copy_from_slice(self.critic_ws.input_grad());
        self.actor
            .backward_batch(&mut self.actor_ws, &mut self.actor_grads, None, None);
        let grads = self.actor_grads.tensors();
        self.actor_opt
            .step(self.actor.mlp_mut().tensors_mut().zip(grads));
        -q_sum * inv_n
    }
}

/// Target policy smoothing: adds `clip(N(0, (noise h_d)^2), -clip h_d, clip h_d)` to the action
/// rows `row..` of the column-major `rows x batch` matrix `input` (`h_d` the half range of
/// dimension `d`), then clips each action to `bounds`.
fn smooth(
    input: &mut [f32],
    rows: usize,
    row: usize,
    bounds: &Bounds,
    noise: f32,
    clip: f32,
    rng: &mut Rng,
) {
    for column in input.chunks_exact_mut(rows) {
        let action = &mut column[row..row + bounds.dim()];
        for (d, a) in action.iter_mut().enumerate() {
            let h = bounds.half_range(d);
            let eps = (noise * h * rng.normal()).clamp(-clip * h, clip * h);
            *a = (*a + eps).clamp(bounds.low[d], bounds.high[d]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DIMS: LevelDims = LevelDims {
        state: 2,
        goal: 1,
        action: 1,
    };

    fn config() -> Td3Config {
        Td3Config::reference(DIMS, Bounds::symmetric(&[2.0]), vec![16, 16])
    }

    fn batch(n: usize, rng: &mut Rng) -> Batch {
        let mut b = Batch::zeros(DIMS, n);
        for v in b
            .states
            .iter_mut()
            .chain(&mut b.next_states)
            .chain(&mut b.goals)
            .chain(&mut b.actions)
        {
            *v = rng.uniform(-1.0, 1.0);
        }
        for (j, (r, t)) in b.rewards.iter_mut().zip(&mut b.terminals).enumerate() {
            *r = -rng.unit();
            *t = if j % 3 == 0 { 1.0 } else { 0.0 };
        }
        b
    }

    /// `Q'_k` of the target critic `k` at the columns `input` (`rows x n`).
    fn q(mlp: &Mlp, input: &[f32], n: usize) -> Vec<f32> {
        let mut ws = MlpWorkspace::new(mlp, n);
        ws.input_mut().copy_from_slice(input);
        mlp.forward(&mut ws);
        ws.output().to_vec()
    }

    /// The target actor's actions at `(s', g')`, one per sample.
    fn target_actions(l: &Td3Learner, b: &Batch) -> Vec<f32> {
        let mut ws = MlpWorkspace::new(l.target_actor.mlp(), b.len);
        l.target_actor.fill_input(&mut ws, &b.next_states, &b.goals);
        l.target_actor.forward_batch(&mut ws);
        let mut out = vec![0.0; b.len];
        l.target_actor.write_actions(&ws, &mut out, 1, 0);
        out
    }

    /// The critic input `[s', g', a']` for the given target actions.
    fn next_input(b: &Batch, actions: &[f32]) -> Vec<f32> {
        let mut input = vec![0.0; 4 * b.len];
        copy_rows(&mut input, 4, 0, &b.next_states, 2);
        copy_rows(&mut input, 4, 2, &b.goals, 1);
        copy_rows(&mut input, 4, 3, actions, 1);
        input
    }

    #[test]
    fn the_target_is_the_smaller_target_critic_at_the_smoothed_action() {
        let mut rng = Rng::seed_from(1);
        let mut l = Td3Learner::new(config(), &mut rng);
        // Lift the first target critic far above the second: the minimum is the second's.
        if let Some(bias) = l.target_critics[0].tensors_mut().last() {
            bias[0] += 50.0;
        }
        let b = batch(12, &mut rng);
        let mut noise_rng = Rng::seed_from(9);
        l.critic_ws.set_batch(b.len);
        l.actor_ws.set_batch(b.len);
        l.y.resize(b.len, 0.0);
        l.set_targets(&b, &b.goals, &mut noise_rng.clone());

        // The same noise, drawn again: the smoothed action, clipped noise, clipped to bounds.
        let mut smoothed = target_actions(&l, &b);
        let mu = smoothed.clone();
        for a in &mut smoothed {
            let eps = (0.2 * 2.0 * noise_rng.normal()).clamp(-1.0, 1.0);
            *a = (*a + eps).clamp(-2.0, 2.0);
        }
        for (s, m) in smoothed.iter().zip(&mu) {
            assert!((s - m).abs() <= 1.0 + 1e-6, "noise beyond its clip");
        }
        assert!(smoothed.iter().zip(&mu).any(|(s, m)| s != m), "no noise");
        let input = next_input(&b, &smoothed);
        let (q1, q2) = (
            q(&l.target_critics[0], &input, b.len),
            q(&l.target_critics[1], &input, b.len),
        );
        for j in 0..b.len {
            assert!(q1[j] > q2[j]);
            let want = b.rewards[j] + 0.99 * (1.0 - b.terminals[j]) * q2[j];
            assert!(
                (l.y[j] - want).abs() < 1e-5,
                "sample {j}: {} vs {want}",
                l.y[j]
            );
        }
        // Terminal samples do not bootstrap.
        assert_eq!(l.y[0], b.rewards[0]);
    }

    #[test]
    fn the_target_bootstraps_at_the_next_goal_when_given() {
        let mut rng = Rng::seed_from(2);
        let mut cfg = config();
        cfg.policy_noise = 0.0;
        let mut l = Td3Learner::new(cfg, &mut rng);
        let b = batch(8, &mut rng);
        let next_goals: Vec<f32> = b.goals.iter().map(|g| g + 0.7).collect();
        l.critic_ws.set_batch(b.len);
        l.actor_ws.set_batch(b.len);
        l.y.resize(b.len, 0.0);
        l.set_targets(&b, &next_goals, &mut rng);
        let mut shifted = b.clone();
        shifted.goals.clone_from(&next_goals);
        let input = next_input(&shifted, &target_actions(&l, &shifted));
        let (q1, q2) = (
            q(&l.target_critics[0], &input, b.len),
            q(&l.target_critics[1], &input, b.len),
        );
        for j in 0..b.len {
            let want = b.rewards[j] + 0.99 * (1.0 - b.terminals[j]) * q1[j].min(q2[j]);
            assert!((l.y[j] - want).abs() < 1e-5);
        }
    }

    #[test]
    fn the_actor_and_the_targets_move_every_second_update() {
        let mut rng = Rng::seed_from(3);
        let mut l = Td3Learner::new(config(), &mut rng);
        let b = batch(32, &mut rng);
        let actor0: Vec<f32> = l.actor.mlp().tensors().flatten().copied().collect();
        let target0: Vec<f32> = l.target_critics[1].tensors().flatten().copied().collect();
        let critic0: Vec<f32> = l.critics[1].tensors().flatten().copied().collect();
        let snapshot = |m: &Mlp| m.tensors().flatten().copied().collect::<Vec<f32>>();
        l.update(&b, None, &mut rng);
        assert_eq!(snapshot(l.actor.mlp()), actor0, "the actor waits");
        assert_eq!(snapshot(&l.target_critics[1]), target0, "the targets wait");
        assert_ne!(snapshot(&l.critics[1]), critic0, "both critics learn");
        l.update(&b, None, &mut rng);
        assert_ne!(snapshot(l.actor.mlp()), actor0);
        assert_ne!(snapshot(&l.target_critics[1]), target0);
        assert_eq!(l.updates(), 2);
    }

    #[test]
    fn a_huber_critic_weighs_every_sample_beyond_the_delta_alike() {
        // Two batches that differ only in how far below the critics' outputs their targets
        // lie (about 50 and about 500 below, with per-sample spread): every error exceeds the
        // Huber delta, so each sample's slope is +1 in both and three updates leave the same
        // networks. The squared error weighs each sample by its error, and they part.
        let run = |loss: CriticLoss, offset: f32| {
            let mut rng = Rng::seed_from(9);
            let mut cfg = config();
            cfg.critic_loss = loss;
            let mut l = Td3Learner::new(cfg, &mut rng);
            let mut b = batch(32, &mut rng);
            for (j, r) in b.rewards.iter_mut().enumerate() {
                *r = offset * (1.0 + 0.01 * j as f32);
            }
            let mut stats = Vec::new();
            for _ in 0..3 {
                stats.push(l.update(&b, None, &mut rng));
            }
            let weights: Vec<f32> = l.critics[0].tensors().flatten().copied().collect();
            (weights, stats)
        };
        let (near, near_stats) = run(CriticLoss::Huber, -50.0);
        let (far, far_stats) = run(CriticLoss::Huber, -500.0);
        assert_eq!(
            near, far,
            "Huber: beyond the delta only the error's sign counts"
        );
        // Its loss is the mean of |Q - y| - 1/2, and the first update's targets differ by the
        // rewards alone: 450 (1 + 0.01 j) on average over j = 0..31, that is 519.75.
        let gap = far_stats[0].critic_loss - near_stats[0].critic_loss;
        assert!((gap - 519.75).abs() < 0.1, "Huber loss gap {gap}");
        let (near, _) = run(CriticLoss::Mse, -50.0);
        let (far, far_stats) = run(CriticLoss::Mse, -500.0);
        assert_ne!(
            near, far,
            "the squared error weighs samples by their errors"
        );
        assert!(
            far_stats[0].critic_loss > 200_000.0,
            "{}",
            far_stats[0].critic_loss
        );
    }

    #[test]
    fn learns_a_one_step_task() {
        // Reward -|a - s_0| and every transition terminal: Q is the reward and the best action
        // copies the state's first coordinate.
        let mut rng = Rng::seed_from(4);
        let mut cfg = config();
        cfg.actor_lr = 1e-3;
        let mut l = Td3Learner::new(cfg, &mut rng);
        let mut b = Batch::zeros(DIMS, 64);
        let mut policy = l.actor.clone();
        let error = |policy: &mut ActorNet| {
            let mut worst = 0.0f32;
            for k in 0..21 {
                let s = -1.0 + 0.1 * k as f32;
                let mut a = [0.0];
                policy.act(&[s, 0.3], &[0.0], &mut a);
                worst = worst.max((a[0] - s).abs());
            }
            worst
        };
        let before = error(&mut policy);
        for _ in 0..3000 {
            for j in 0..b.len {
                let s = rng.uniform(-1.0, 1.0);
                let a = rng.uniform(-2.0, 2.0);
                b.states[2 * j] = s;
                b.states[2 * j + 1] = 0.3;
                b.goals[j] = 0.0;
                b.actions[j] = a;
                b.rewards[j] = -(a - s).abs();
                b.terminals[j] = 1.0;
            }
            b.next_states.clone_from(&b.states);
            l.update(&b, None, &mut rng);
        }
        let mut policy = l.actor.clone();
        let after = error(&mut policy);
        assert!(before > 0.3, "an untrained actor already copies: {before}");
        assert!(
            after < 0.15,
            "worst error after training {after} (before {before})"
        );
    }

    /// Random batches with a next goal that moves with the state, as HIRO's low level's does.
    fn batches(count: usize, rng: &mut Rng) -> Vec<(Batch, Vec<f32>)> {
        (0..count)
            .map(|_| {
                let b = batch(32, rng);
                let next_goals = b.goals.iter().map(|g| g - 0.1).collect();
                (b, next_goals)
            })
            .collect()
    }

    #[test]
    fn checkpoint_round_trip_continues_bit_identically() {
        let mut rng = Rng::seed_from(5);
        let data = batches(7, &mut rng);
        let mut learner = Td3Learner::new(config(), &mut rng);
        // 3 updates: the file is written between an actor step and a critic-only update, so the
        // restored learner must know both the step counts and the last actor loss.
        for (b, g) in &data[..3] {
            learner.update(b, Some(g), &mut rng);
        }
        let bytes = learner.to_safetensors();
        let mut restored = Td3Learner::from_safetensors(config(), &bytes).unwrap();
        assert_eq!(restored.to_safetensors(), bytes, "the file round-trips");
        assert_eq!(restored.updates(), 3);
        let mut restored_rng = rng.clone();
        for (b, g) in &data[3..] {
            assert_eq!(
                learner.update(b, Some(g), &mut rng),
                restored.update(b, Some(g), &mut restored_rng)
            );
        }
        assert_eq!(learner.to_safetensors(), restored.to_safetensors());
        let weights = |l: &Td3Learner| {
            let mut all: Vec<u32> = l
                .actor
                .mlp()
                .tensors()
                .flatten()
                .map(|v| v.to_bits())
                .collect();
            for m in l.critics.iter().chain(&l.target_critics) {
                all.extend(m.tensors().flatten().map(|v| v.to_bits()));
            }
            all
        };
        assert_eq!(weights(&learner), weights(&restored));
    }

    #[test]
    fn a_checkpoint_of_other_dimensions_is_refused_naming_what_differs() {
        let mut rng = Rng::seed_from(6);
        let bytes = Td3Learner::new(config(), &mut rng).to_safetensors();
        let mismatch = |cfg: Td3Config| match Td3Learner::from_safetensors(cfg, &bytes) {
            Err(NnError::Mismatch {
                what,
                expected,
                found,
            }) => (what, expected, found),
            Err(e) => panic!("not a mismatch: {e}"),
            Ok(_) => panic!("accepted"),
        };
        let wider_state = Td3Config::reference(
            LevelDims { state: 3, ..DIMS },
            Bounds::symmetric(&[2.0]),
            vec![16, 16],
        );
        assert_eq!(
            mismatch(wider_state),
            (
                "actor layer widths".into(),
                "[4, 16, 16, 1]".into(),
                "[3, 16, 16, 1]".into()
            )
        );
        // The same input width split otherwise between state and goal.
        let split = Td3Config::reference(
            LevelDims {
                state: 1,
                goal: 2,
                action: 1,
            },
            Bounds::symmetric(&[2.0]),
            vec![16, 16],
        );
        let (what, ..) = mismatch(split);
        assert_eq!(what, "actor (state, goal, action) widths");
        let hidden = Td3Config::reference(DIMS, Bounds::symmetric(&[2.0]), vec![16, 8]);
        assert_eq!(mismatch(hidden).0, "actor layer widths");
        let bounds = Td3Config::reference(DIMS, Bounds::symmetric(&[1.0]), vec![16, 16]);
        assert_eq!(mismatch(bounds).0, "actor output (scale, offset)");

        // A critic that differs alone is named.
        let mut other = Td3Learner::new(config(), &mut rng);
        other.target_critics[1] = Mlp::new(&[4, 16, 9, 1], &mut rng);
        let (what, expected, found) =
            match Td3Learner::from_safetensors(config(), &other.to_safetensors()) {
                Err(NnError::Mismatch {
                    what,
                    expected,
                    found,
                }) => (what, expected, found),
                other => panic!("{other:?}"),
            };
        assert_eq!(
            (what.as_str(), expected.as_str(), found.as_str()),
            (
                "target_critic.1 layer widths",
                "[4, 16, 16, 1]",
                "[4, 16, 9, 1]"
            )
        );

        // Another kind of file is refused by its format tag.
        let level = hac_level(Some(0.005), &mut rng);
        assert!(matches!(
            Td3Learner::from_safetensors(config(), &level.to_safetensors()),
            Err(NnError::Metadata { .. })
        ));
        assert!(matches!(
            Td3Learner::from_safetensors(config(), &bytes[..bytes.len() / 2]),
            Err(NnError::Format(_))
        ));
    }

    #[test]
    fn a_diverged_update_is_undone_and_healthy_ones_match_update() {
        let mut rng = Rng::seed_from(7);
        let data = batches(6, &mut rng);
        let mut guarded = Td3Learner::new(config(), &mut rng);
        let mut plain = guarded.clone();
        let (mut guarded_rng, mut plain_rng) = (rng.clone(), rng.clone());
        let mut backup = LearnerBackup::default();
        for (b, g) in &data[..3] {
            let stats = guarded
                .update_or_undo(b, Some(g), &mut guarded_rng, &mut backup)
                .unwrap();
            assert_eq!(stats, plain.update(b, Some(g), &mut plain_rng));
        }
        assert_eq!(guarded.to_safetensors(), plain.to_safetensors());

        // A NaN reward reaches the targets; a huge one blows up the critics.
        for (reward, what) in [(f32::NAN, "critic loss"), (1e30, "critic loss")] {
            let mut poison = data[3].0.clone();
            poison.rewards[5] = reward;
            let before = guarded.to_safetensors();
            let steps = (guarded.actor_opt.steps(), guarded.updates());
            let e = guarded
                .update_or_undo(&poison, Some(&data[3].1), &mut rng, &mut backup)
                .unwrap_err();
            assert_eq!(e.what, what, "{e}");
            assert_eq!(guarded.to_safetensors(), before, "undone to the last byte");
            assert_eq!(
                (guarded.actor_opt.steps(), guarded.updates()),
                steps,
                "step counts"
            );
            assert_eq!(guarded.critic_opts[1].steps(), steps.1);
        }

        // An exploding actor step: a learning rate of 1e30, on the 4th update, which moves the
        // actor (every 2nd does).
        let mut exploding = guarded.clone();
        let lens: Vec<usize> = exploding.actor.mlp().tensors().map(<[f32]>::len).collect();
        exploding.actor_opt = Adam::new(1e30, lens);
        *exploding.actor_opt.state_mut().0 = guarded.actor_opt.steps();
        let before = exploding.to_safetensors();
        let e = exploding
            .update_or_undo(&data[3].0, Some(&data[3].1), &mut rng, &mut backup)
            .unwrap_err();
        assert!(
            e.what == "actor parameter" && (!e.value.is_finite() || e.value.abs() > 1e6),
            "{e}"
        );
        assert_eq!(exploding.to_safetensors(), before);

        // ... and the guarded learner goes on as if the poison never came.
        for (b, g) in &data[3..] {
            let stats = guarded
                .update_or_undo(b, Some(g), &mut guarded_rng, &mut backup)
                .unwrap();
            assert_eq!(stats, plain.update(b, Some(g), &mut plain_rng));
        }
        assert_eq!(guarded.to_safetensors(), plain.to_safetensors());
    }

    /// A HAC level learner of this module's dimensions and widths.
    fn hac_level(target_tau: Option<f32>, rng: &mut Rng) -> crate::LevelLearner {
        crate::LevelLearner::new(
            crate::LearnerConfig {
                dims: DIMS,
                action_bounds: Bounds::symmetric(&[2.0]),
                horizon: 10.0,
                gamma: 0.99,
                hidden: vec![16, 16],
                actor_lr: 1e-3,
                critic_lr: 1e-3,
                target_tau,
                actor_preactivation_l2: 0.0,
                exact_critic_slope: false,
                saturating_tanh: false,
            },
            rng,
        )
    }

    #[test]
    #[should_panic(expected = "backup of another shape")]
    fn a_level_learners_backup_is_refused() {
        let mut rng = Rng::seed_from(8);
        let level = hac_level(None, &mut rng);
        let mut backup = LearnerBackup::default();
        level.save(&mut backup);
        Td3Learner::new(config(), &mut rng).restore(&backup);
    }
}
