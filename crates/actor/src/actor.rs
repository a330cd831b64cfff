//! [`run_actor`]: the actor loop, written against [`ActorLink`] so that the embedded run, the
//! actor daemon and tests run the same code. Its parts take the half of the link they use: the
//! episode sender and the wait for acks an [`IngestSink`], the wait for weights a
//! [`WeightsSource`].

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hac_agent::{RunConfig, RunConfigError, play_episodes};
use hac_core::{Episodes, GaussianExploration, Mode, Rng};
use hac_proto::{ActorRole, Admission, IngestItem, Registration, WeightsSnapshot};
use hac_transport::{ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, WeightsSource};

use crate::{Adder, SnapshotPolicy};

/// How an actor runs. The run's config (environment, levels, hyperparameters) comes from the
/// learner at registration; these are the actor's own settings.
#[derive(Debug, Clone)]
pub struct ActorOptions {
    /// Stable name, unique among live actors (e.g. the pod or host name plus an index).
    pub actor_id: String,
    pub role: ActorRole,
    /// This host's name (the learner offers shared memory to same-host actors).
    pub hostname: String,
    /// Transports this actor can use.
    pub transports: Vec<String>,
    /// Trainers: before each episode, wait until the learner has finished the updates owed for
    /// every episode this actor sent. With one actor this is exactly the paper's schedule
    /// (results do not depend on timing); with many it slows everyone to the learner's pace.
    pub lockstep: bool,
    /// Trainers: run `test_episodes` greedy episodes after every this many training episodes
    /// (and after the last) and report them, as the embedded schedule does. Evaluators:
    /// evaluate whenever the learner has trained this many more episodes [default for
    /// evaluators: the run's `exploration_episodes`].
    pub eval_every_episodes: Option<u64>,
    /// Trainers: stop after this many training episodes [default: when the run finishes].
    pub max_episodes: Option<u64>,
    /// Give up if no usable weights arrive for this long [default: wait as long as it takes].
    pub weights_timeout: Option<Duration>,
    /// Transitions per batch sent (capped by the learner's limit).
    pub batch_transitions: usize,
    /// Trainers: continue from the state a trainer stopped in ([`ActorSummary::trainer_state`])
    /// instead of starting the run's random streams afresh. With the learner resumed from the
    /// checkpoint written at the same point, a lockstep trainer then continues its run exactly.
    pub resume: Option<TrainerState>,
}

impl ActorOptions {
    /// A trainer named `actor_id` with the defaults.
    pub fn trainer(actor_id: impl Into<String>) -> Self {
        Self {
            actor_id: actor_id.into(),
            role: ActorRole::Trainer,
            hostname: String::new(),
            transports: vec!["grpc".into()],
            lockstep: false,
            eval_every_episodes: None,
            max_episodes: None,
            weights_timeout: None,
            batch_transitions: 1024,
            resume: None,
        }
    }

    /// An evaluator named `actor_id` with the defaults.
    pub fn evaluator(actor_id: impl Into<String>) -> Self {
        Self {
            role: ActorRole::Evaluator,
            ..Self::trainer(actor_id)
        }
    }
}

/// How long a trainer granted a turn waits for the weights it names before asking again.
const TURN_WEIGHTS_WAIT: Duration = Duration::from_secs(5);

/// Why the actor stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    #[error(transparent)]
    Link(LinkError),
    #[error(transparent)]
    Config(#[from] RunConfigError),
    #[error("the learner's run config does not match its level dimensions: {0}")]
    Mismatch(String),
    #[error("no usable weights within {0:?}")]
    WeightsTimeout(Duration),
}

/// What the actor did, returned when it stops.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ActorSummary {
    /// The registration the actor ended under (the link may have registered again).
    pub incarnation: u64,
    pub episodes: u64,
    pub env_steps: u64,
    pub successes: u64,
    pub evaluations: u64,
    /// The last weights version the actor acted with.
    pub weights_version: u64,
    /// The learner said the run is over (rather than the actor's own limit or an interrupt).
    pub run_finished: bool,
    /// Weights snapshots the actor could not use (not finite, or not the run's shape) and
    /// skipped, acting on the last usable ones.
    pub unusable_weights: u64,
    /// A trainer's state as it stopped, for [`ActorOptions::resume`] (none for evaluators).
    pub trainer_state: Option<TrainerState>,
}

/// Where a trainer's run stands between two episodes: its counts, the training episodes it
/// last evaluated after, and its random streams (the behaviour policy's, the training
/// episodes', the test rounds'). Plain data, saved beside a checkpoint by `hac train`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainerState {
    pub episodes: u64,
    pub env_steps: u64,
    pub successes: u64,
    pub evaluations: u64,
    pub evaluated_after: Option<u64>,
    pub exploration: Rng,
    pub train: Rng,
    pub test: Rng,
}

/// Set apart the family of an evaluator's test-round streams ([`Rng::stream`]) from that of
/// the training episodes under turns (the run's seed itself).
const TEST_STREAMS: u64 = 0x7e57_7e57_7e57_7e57;

/// One evaluation the actor ran and reported.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvaluationEvent {
    pub weights_version: u64,
    /// Training episodes the evaluated weights had been trained on.
    pub trained_episodes: u64,
    pub success_rate: f32,
}

/// Registers through `link` and runs until the run finishes, `max_episodes` are done or
/// `interrupt` is set (checked between episodes). Calls `on_evaluation` after each reported
/// evaluation.
pub fn run_actor(
    link: &mut dyn ActorLink,
    options: &ActorOptions,
    interrupt: &AtomicBool,
    on_evaluation: impl FnMut(&EvaluationEvent),
) -> Result<ActorSummary, ActorError> {
    let admission = link
        .register(&Registration {
            actor_id: options.actor_id.clone(),
            role: options.role,
            hostname: options.hostname.clone(),
            transports: options.transports.clone(),
        })
        .map_err(ActorError::Link)?;
    let run = RunConfig::from_toml(&admission.run_config_toml, "the learner's run config")?;
    let env = run
        .make_env()
        .map_err(|e| ActorError::Mismatch(e.to_string()))?;
    let spec = env.spec().clone();
    let dims: Vec<_> = (0..run.levels)
        .map(|l| spec.level_dims(l, run.levels))
        .collect();
    if dims != admission.levels {
        return Err(ActorError::Mismatch(format!(
            "config implies {dims:?}, the learner announced {:?}",
            admission.levels
        )));
    }
    let extra_widths = run.extra_widths(&spec);
    if (0..run.levels).any(|l| admission.extra_width(l) != extra_widths[l]) {
        return Err(ActorError::Mismatch(format!(
            "config implies extra values per transition {extra_widths:?}, the learner announced \
             {:?}",
            admission.extra_widths
        )));
    }
    let mut root = Rng::seed_from(admission.seed);
    let mut state = State {
        exploration: GaussianExploration::new(&spec, &run.agent, root.fork()),
        train_rng: root.fork(),
        test_rng: root.fork(),
        evaluated_after: None,
        episodes: Episodes::new(&spec, &run.agent, run.hiro()),
        adder: Adder::with_extra(
            &dims,
            &extra_widths,
            options
                .batch_transitions
                .min(admission.max_batch_transitions),
        ),
        env,
        dims,
        gate: WeightsGate::new(options, &admission),
        summary: ActorSummary {
            incarnation: admission.incarnation,
            ..ActorSummary::default()
        },
        run,
        unusable: None,
        on_evaluation,
    };
    if let (ActorRole::Trainer, Some(from)) = (options.role, &options.resume) {
        state.resume(from);
    }
    let mut actor = Actor {
        link,
        options,
        interrupt,
        s: state,
    };
    let result = match options.role {
        ActorRole::Trainer => actor.train(),
        ActorRole::Evaluator => actor.evaluate_forever(),
    };
    match result {
        Ok(()) => {}
        Err(ActorError::Link(LinkError::Finished)) => actor.s.summary.run_finished = true,
        Err(e) => return Err(e),
    }
    if options.role == ActorRole::Trainer {
        actor.s.summary.trainer_state = Some(actor.s.trainer_state());
    }
    // Links register again by themselves (after a learner restart, or when the id registered
    // elsewhere): the summary names the incarnation the actor ended under, not the first.
    if let Some(stats) = actor.link.stats() {
        actor.s.summary.incarnation = stats.incarnation();
    }
    Ok(actor.s.summary)
}

struct State<F> {
    run: RunConfig,
    env: Box<dyn hac_core::Env>,
    dims: Vec<hac_core::LevelDims>,
    exploration: GaussianExploration,
    train_rng: Rng,
    test_rng: Rng,
    /// The training episodes a trainer last evaluated after.
    evaluated_after: Option<u64>,
    episodes: Episodes,
    adder: Adder,
    gate: WeightsGate,
    summary: ActorSummary,
    /// The last weights version found unusable (reported once).
    unusable: Option<u64>,
    on_evaluation: F,
}

impl<F> State<F> {
    /// Takes up a trainer's state where it stopped.
    fn resume(&mut self, from: &TrainerState) {
        let summary = &mut self.summary;
        summary.episodes = from.episodes;
        summary.env_steps = from.env_steps;
        summary.successes = from.successes;
        summary.evaluations = from.evaluations;
        self.evaluated_after = from.evaluated_after;
        self.exploration.reseed(from.exploration.clone());
        self.train_rng = from.train.clone();
        self.test_rng = from.test.clone();
    }

    fn trainer_state(&self) -> TrainerState {
        let summary = &self.summary;
        TrainerState {
            episodes: summary.episodes,
            env_steps: summary.env_steps,
            successes: summary.successes,
            evaluations: summary.evaluations,
            evaluated_after: self.evaluated_after,
            exploration: self.exploration.rng().clone(),
            train: self.train_rng.clone(),
            test: self.test_rng.clone(),
        }
    }
}

/// How a trainer waits for the weights of its next episode: the one place that chooses among
/// the three ways of keeping an actor's data fresh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WeightsGate {
    /// Weights trained on every episode this actor sent (`lockstep`): with one actor, exactly
    /// the paper's schedule.
    Lockstep,
    /// An episode turn from the learner (`episodes_in_flight` > 0), then the weights it names;
    /// the episode draws from the run seed's streams of the index the turn names. With one
    /// episode in flight, the run is then the same whichever trainers play it. Once the actor's
    /// own episode budget is spent, as `Lag`.
    Turns { max_lag: u64 },
    /// Any weights at most this many versions behind the learner's newest.
    Lag { max_lag: u64 },
}

impl WeightsGate {
    fn new(options: &ActorOptions, admission: &Admission) -> Self {
        let max_lag = admission.max_weights_lag;
        if options.lockstep {
            Self::Lockstep
        } else if admission.episodes_in_flight > 0 {
            Self::Turns { max_lag }
        } else {
            Self::Lag { max_lag }
        }
    }
}

/// The weights a trainer's next episode is played with.
struct NextWeights {
    snapshot: Arc<WeightsSnapshot>,
    /// The learner granted this actor an episode turn for it.
    holding_turn: bool,
    /// The index of the episode the turn is for ([`GrantedTurn::episode`]).
    episode: Option<u64>,
}

struct Actor<'a, F> {
    link: &'a mut dyn ActorLink,
    options: &'a ActorOptions,
    interrupt: &'a AtomicBool,
    s: State<F>,
}

impl<F: FnMut(&EvaluationEvent)> Actor<'_, F> {
    fn interrupted(&self) -> bool {
        self.interrupt.load(Ordering::Relaxed)
    }

    /// [`wait_weights`] from this actor's link, with its interrupt and weights timeout.
    fn wait_weights(
        &self,
        ready: impl Fn(&WeightsSnapshot, u64) -> bool,
    ) -> Result<Option<Arc<WeightsSnapshot>>, ActorError> {
        wait_weights(
            &*self.link,
            self.interrupt,
            self.options.weights_timeout,
            ready,
        )
    }

    /// `snapshot`'s policy. If its weights are unusable (not finite, or not the run's shape),
    /// the current policy is kept and the snapshot is counted and reported once: an actor never
    /// stops over what the learner sends. `None` when there is no current policy to keep.
    fn policy_for(
        &mut self,
        current: Option<SnapshotPolicy>,
        snapshot: &WeightsSnapshot,
    ) -> Option<SnapshotPolicy> {
        match current {
            Some(p) if p.version() == snapshot.version => Some(p),
            _ if self.s.unusable == Some(snapshot.version) => current,
            _ => match SnapshotPolicy::from_snapshot(snapshot, &self.s.dims) {
                Ok(p) => Some(p),
                Err(error) => {
                    self.s.unusable = Some(snapshot.version);
                    self.s.summary.unusable_weights += 1;
                    tracing::warn!(
                        %error,
                        kept = current.as_ref().map(SnapshotPolicy::version),
                        "unusable weights from the learner: acting on the last usable ones"
                    );
                    current
                }
            },
        }
    }

    /// The weights for the trainer's next episode, after `sent` episodes, as its
    /// [`WeightsGate`] asks; `None` if interrupted first.
    fn next_weights(&mut self, sent: u64) -> Result<Option<NextWeights>, ActorError> {
        let budget_left = self.options.max_episodes.is_none_or(|m| sent < m);
        let snapshot = match self.s.gate {
            WeightsGate::Lockstep => self.wait_weights(|w, _| w.episodes >= sent)?,
            WeightsGate::Turns { .. } if budget_left => {
                return self.wait_turn_and_weights();
            }
            WeightsGate::Turns { max_lag } | WeightsGate::Lag { max_lag } => {
                self.wait_weights(|w, newest| w.version.saturating_add(max_lag) >= newest)?
            }
        };
        Ok(snapshot.map(|snapshot| NextWeights {
            snapshot,
            holding_turn: false,
            episode: None,
        }))
    }

    /// Whether a trainer evaluates before its next episode, after `sent` episodes: every
    /// `eval_every_episodes` and after its last, once per count.
    fn evaluation_due(&self, sent: u64, last_eval: Option<u64>) -> bool {
        let max = self.options.max_episodes;
        self.options.eval_every_episodes.is_some_and(|n| {
            sent > 0
                && (sent.is_multiple_of(n.max(1)) || max == Some(sent))
                && last_eval != Some(sent)
        })
    }

    /// The trainer's loop: weights for the next episode, an evaluation when one is due, the
    /// episode, its transitions to the learner.
    fn train(&mut self) -> Result<(), ActorError> {
        let max = self.options.max_episodes;
        let mut policy: Option<SnapshotPolicy> = None;
        loop {
            let sent = self.s.summary.episodes;
            let Some(NextWeights {
                snapshot,
                holding_turn,
                episode,
            }) = self.next_weights(sent)?
            else {
                return Ok(());
            };
            let Some(mut p) = self.policy_for(policy.take(), &snapshot) else {
                // Nothing usable yet: wait for a newer version.
                let unusable = snapshot.version;
                if self.wait_weights(|w, _| w.version > unusable)?.is_none() {
                    return Ok(());
                }
                continue;
            };
            self.s.summary.weights_version = p.version();
            if self.evaluation_due(sent, self.s.evaluated_after) {
                self.evaluate(&mut p, &snapshot)?;
                self.s.evaluated_after = Some(sent);
            }
            // The evaluation may have finished the run (target reached).
            let finished = snapshot.run_finished
                || self.link.weights().latest().is_some_and(|w| w.run_finished);
            if finished {
                self.s.summary.run_finished = true;
                return Ok(());
            }
            // An interrupt after a turn was granted stops after the episode: the turn is used,
            // not left to its lease while the other trainers wait.
            if max.is_some_and(|m| sent >= m) || (self.interrupted() && !holding_turn) {
                return Ok(());
            }
            self.play_episode(&mut p, episode)?;
            policy = Some(p);
            self.wait_acked()?;
        }
    }

    /// One training episode with `p`, its transitions and its end sent to the learner. Under
    /// episode turns, `episode` is the index the learner gave it: the episode draws from the
    /// run seed's streams of that index instead of from this trainer's own, so that the run does
    /// not depend on which trainer played which episode.
    fn play_episode(
        &mut self,
        p: &mut SnapshotPolicy,
        episode: Option<u64>,
    ) -> Result<(), ActorError> {
        let s = &mut self.s;
        if let Some(index) = episode {
            let mut root = Rng::stream(s.run.seed, index);
            s.exploration.reseed(root.fork());
            s.train_rng = root.fork();
        }
        s.adder.set_weights_version(p.version());
        let outcome = s.episodes.run_episode(
            s.env.as_mut(),
            p,
            &mut s.exploration,
            Mode::Train,
            &mut s.train_rng,
            &mut s.adder,
        );
        send_episode(
            &mut *self.link,
            &mut s.adder,
            IngestItem::Episode {
                env_steps: outcome.steps as u64,
                success: outcome.success,
                weights_version: p.version(),
            },
        )
        .map_err(ActorError::Link)?;
        s.summary.episodes += 1;
        s.summary.env_steps += outcome.steps as u64;
        s.summary.successes += u64::from(outcome.success);
        Ok(())
    }

    /// Waits for the learner to grant this trainer its next episode turn, then for weights
    /// trained on every episode the learner had then (already published when the turn was
    /// granted, so they arrive within milliseconds). If they do not arrive within
    /// [`TURN_WEIGHTS_WAIT`] (the learner restarted from an earlier checkpoint in between and
    /// will never publish them), asks again: the learner answers for the weights it has. The
    /// weights with the turn's episode index; `None` if interrupted first.
    fn wait_turn_and_weights(&mut self) -> Result<Option<NextWeights>, ActorError> {
        loop {
            // Short waits, so that an interrupt is noticed.
            let GrantedTurn { trained, episode } = loop {
                if self.interrupted() {
                    return Ok(None);
                }
                if let Some(turn) = self
                    .link
                    .await_turn(Duration::from_millis(500))
                    .map_err(ActorError::Link)?
                {
                    break turn;
                }
            };
            let granted = Instant::now();
            while granted.elapsed() < TURN_WEIGHTS_WAIT {
                if self.interrupted() {
                    return Ok(None);
                }
                let slice = Duration::from_millis(200);
                if let Some(w) = self
                    .link
                    .weights()
                    .wait_for(slice, |w| w.run_finished || w.episodes >= trained)
                {
                    return Ok(Some(NextWeights {
                        snapshot: w,
                        holding_turn: true,
                        episode,
                    }));
                }
            }
            tracing::info!(
                trained,
                "no weights covering the turn's episodes arrived: asking for the turn again"
            );
        }
    }

    /// [`wait_acked`] on this actor's link.
    fn wait_acked(&mut self) -> Result<(), ActorError> {
        wait_acked(&mut *self.link, self.interrupt)
    }

    /// One test round of the run's `test_episodes` with `policy`, reported to the learner.
    /// `false`: the learner restarted since it published `snapshot` and dropped the report.
    fn evaluate(
        &mut self,
        policy: &mut SnapshotPolicy,
        snapshot: &WeightsSnapshot,
    ) -> Result<bool, ActorError> {
        let s = &mut self.s;
        let episodes = s.run.agent.test_episodes.max(1);
        let mut successes = 0u32;
        let rate = play_episodes(
            &mut s.episodes,
            s.env.as_mut(),
            policy,
            &mut s.exploration,
            &mut s.test_rng,
            episodes,
            Mode::Test,
            |outcome, _, _| successes += u32::from(outcome.success),
        );
        let recorded = self
            .link
            .report_evaluation(&EvaluationOf {
                weights_version: snapshot.version,
                learner_start: snapshot.learner_start,
                episodes: episodes as u32,
                successes,
            })
            .map_err(ActorError::Link)?;
        if recorded {
            s.summary.evaluations += 1;
            (s.on_evaluation)(&EvaluationEvent {
                weights_version: snapshot.version,
                trained_episodes: snapshot.episodes,
                success_rate: rate,
            });
        }
        Ok(recorded)
    }

    fn evaluate_forever(&mut self) -> Result<(), ActorError> {
        let every = self
            .options
            .eval_every_episodes
            .unwrap_or(self.s.run.agent.exploration_episodes as u64)
            .max(1);
        let mut next_at = every;
        // The last weights evaluated, and the learner process a dropped report came from.
        let mut last = (0, 0);
        let mut stale_start = 0;
        loop {
            let Some(snapshot) = self.wait_weights(|w, _| {
                w.episodes >= next_at
                    && (stale_start == 0 || w.learner_start != stale_start)
                    && (w.learner_start, w.version) != last
            })?
            else {
                return Ok(());
            };
            if (snapshot.learner_start, snapshot.version) != last {
                let Some(mut policy) = self.policy_for(None, &snapshot) else {
                    // Reported; evaluate the next version instead.
                    last = (snapshot.learner_start, snapshot.version);
                    continue;
                };
                self.s.summary.weights_version = policy.version();
                // The round's test episodes draw from the run seed's test streams of the
                // episodes the weights were trained on: the same weights get the same round
                // whichever evaluator plays it, in whatever order the actors registered.
                self.s.test_rng = Rng::stream(self.s.run.seed ^ TEST_STREAMS, snapshot.episodes);
                if self.evaluate(&mut policy, &snapshot)? {
                    last = (snapshot.learner_start, snapshot.version);
                    next_at = snapshot.episodes + every;
                    stale_start = 0;
                } else {
                    // Evaluate the restarted learner's weights at the same point instead.
                    stale_start = snapshot.learner_start;
                }
            }
            if snapshot.run_finished {
                self.s.summary.run_finished = true;
                return Ok(());
            }
        }
    }
}

/// Waits for a snapshot from `source` satisfying `ready` (or a final one), in slices so that an
/// interrupt is noticed; `None` if interrupted, [`ActorError::WeightsTimeout`] after `timeout`.
/// `ready` also gets the learner's newest version, read again each slice (it drops when a
/// restarted learner starts counting again).
fn wait_weights(
    source: &dyn WeightsSource,
    interrupt: &AtomicBool,
    timeout: Option<Duration>,
    ready: impl Fn(&WeightsSnapshot, u64) -> bool,
) -> Result<Option<Arc<WeightsSnapshot>>, ActorError> {
    let started = Instant::now();
    loop {
        if interrupt.load(Ordering::Relaxed) {
            return Ok(None);
        }
        let slice = Duration::from_millis(200);
        let newest = source.learner_version();
        if let Some(w) = source
            .weights()
            .wait_for(slice, |w| w.run_finished || ready(w, newest))
        {
            return Ok(Some(w));
        }
        if let Some(limit) = timeout
            && started.elapsed() >= limit
        {
            return Err(ActorError::WeightsTimeout(limit));
        }
    }
}

/// Sends one played episode to `sink`: the transition batches `adder` packed, then `end` (its
/// [`IngestItem::Episode`]).
fn send_episode(
    sink: &mut dyn IngestSink,
    adder: &mut Adder,
    end: IngestItem,
) -> Result<(), LinkError> {
    for item in adder.drain() {
        sink.send(item)?;
    }
    sink.send(end)
}

/// Backpressure in whole episodes: the next episode starts only once the learner has
/// acknowledged this one. When training falls behind, the learner withholds acks and every
/// actor waits here, instead of piling up episodes played with ever staler weights. Returns
/// without waiting longer once `interrupt` is set.
fn wait_acked(sink: &mut dyn IngestSink, interrupt: &AtomicBool) -> Result<(), ActorError> {
    loop {
        match sink.flush(Duration::from_millis(200)) {
            Ok(()) => return Ok(()),
            Err(LinkError::TimedOut(_)) if !interrupt.load(Ordering::Relaxed) => continue,
            Err(LinkError::TimedOut(_)) => return Ok(()),
            Err(e) => return Err(ActorError::Link(e)),
        }
    }
}
