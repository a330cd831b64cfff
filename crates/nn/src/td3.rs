//! TD3 (Fujimoto, van Hoof and Meger, *Addressing Function Approximation Error in Actor-Critic
//! Methods*, ICML 2018): the learner of both of HIRO's levels.
//!
//! Against HAC's level learner ([`crate::LevelLearner`]): two critics, unbounded (HIRO's rewards
//! are distances and sums of -1 over `c` steps, with no attempt budget to bound them); target
//! networks for the actor and both critics, moved by Polyak averaging; a target that bootstraps
//! from the smaller of the two target critics at a smoothed target action; and an actor updated
//! every `policy_delay`-th critic update only. The next goal can differ from the goal (HIRO's
//! low level: the goal moves with the state), so [`Td3Learner::update`] takes it apart.

use hac_core::{Batch, Bounds, LevelDims, Rng};

use crate::kernels::copy_rows;
use crate::learner::UpdateStats;
use crate::{ActorNet, Adam, Mlp, MlpGrads, MlpWorkspace};

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
}

impl Td3Config {
    /// The HIRO paper's TD3 settings for a level with `dims` and `action_bounds`: gamma 0.99,
    /// actor lr 1e-4, critic lr 1e-3, tau 0.005, smoothing noise 0.2 clipped to 0.5 (of the half
    /// range), actor every 2nd critic update; hidden layers as given.
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
            target_actor: actor.clone(),
            target_critics: critics.clone(),
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

    /// One Adam step on each critic's mean squared error to `self.y`; returns the mean of the
    /// two errors and the first critic's mean `Q`, both from before the steps.
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
        let (mut loss, mut mean_q) = (0.0, 0.0);
        for k in 0..2 {
            let critic = &mut self.critics[k];
            critic.forward(&mut self.critic_ws);
            let (mut sq_err_sum, mut q_sum) = (0.0, 0.0);
            let (q, dq) = self.critic_ws.output_and_grad_mut();
            for ((dq, &q), &y) in dq.iter_mut().zip(q).zip(&self.y) {
                let err = q - y;
                sq_err_sum += err * err;
                q_sum += q;
                *dq = 2.0 * err * inv_n;
            }
            critic.backward(&mut self.critic_ws, Some(&mut self.critic_grads), 0..0);
            self.critic_opts[k].step(critic.tensors_mut().zip(self.critic_grads.tensors()));
            loss += 0.5 * sq_err_sum * inv_n;
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
            .backward_batch(&mut self.actor_ws, &mut self.actor_grads, None);
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
}
