//! [`train_embedded`]: the whole system in one process, the same learner and actor code as a
//! distributed run, connected by the in-process transport.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use hac_actor::{ActorError, ActorOptions, ActorSummary, TrainerState, run_actor};
use hac_agent::{Agent, RoundReport, RunConfig};
use hac_learner::{
    BestWeights, Learner, LearnerCheckpoint, LearnerOptions, LearnerStatus, StartError,
};

use crate::InProcess;

/// Why an embedded run failed.
#[derive(Debug, thiserror::Error)]
pub enum EmbeddedError {
    #[error(transparent)]
    Start(#[from] StartError),
    #[error(transparent)]
    Actor(#[from] ActorError),
}

/// What an embedded run produced.
#[derive(Debug)]
pub struct EmbeddedRun {
    pub agent: Agent,
    /// One point per test round.
    pub curve: Vec<RoundReport>,
    /// The weights of the best test round (none if no round was evaluated).
    pub best: Option<Arc<BestWeights>>,
    pub status: LearnerStatus,
    pub actor: ActorSummary,
    /// The run's whole state as it stopped, when asked for ([`train_embedded_from`]).
    pub saved: Option<SavedRun>,
}

/// An embedded run's whole state between two episodes: the learner's checkpoint, with its
/// replay, and the trainer's. [`train_embedded_from`] continues from it exactly.
#[derive(Debug, Clone, PartialEq)]
pub struct SavedRun {
    pub checkpoint: LearnerCheckpoint,
    pub trainer: TrainerState,
}

/// Trains `run` with one learner and one lockstep trainer actor in this process: the paper's
/// schedule exactly (`exploration_episodes` training episodes with `updates_per_episode`
/// updates per level after each, then a round of `test_episodes` greedy episodes), with the
/// levels training in parallel on their own threads. Results depend only on the config and
/// seed. Calls `on_round` after each test round; stops at `run.episodes`, when a round reaches
/// `run.stop_at`, or (between episodes, without a last test round) when `interrupt` is set.
/// The learner runs with [`LearnerOptions::for_run`]; see [`train_embedded_with`].
pub fn train_embedded(
    run: &RunConfig,
    interrupt: &AtomicBool,
    on_round: impl FnMut(&RoundReport),
) -> Result<EmbeddedRun, EmbeddedError> {
    train_embedded_with(run, LearnerOptions::for_run(run), interrupt, on_round)
}

/// [`train_embedded`] with the learner's `options` (its thread budget, say: the weights, and so
/// the run, do not depend on it).
pub fn train_embedded_with(
    run: &RunConfig,
    options: LearnerOptions,
    interrupt: &AtomicBool,
    on_round: impl FnMut(&RoundReport),
) -> Result<EmbeddedRun, EmbeddedError> {
    train_embedded_from(run, options, None, false, interrupt, on_round)
}

/// [`train_embedded_with`], continuing from `from` (the state an earlier embedded run of the
/// same config stopped in, whose checkpoint holds its replay, made ready for `run` by
/// [`LearnerCheckpoint::continue_as`] when the budget grew) when given, and returning the final
/// state in [`EmbeddedRun::saved`] when `keep_state`. A run continued from the state saved at
/// its end, or after an interrupt, gives the same curve and weights, bit for bit, as the run
/// that was never stopped.
pub fn train_embedded_from(
    run: &RunConfig,
    options: LearnerOptions,
    from: Option<&SavedRun>,
    keep_state: bool,
    interrupt: &AtomicBool,
    mut on_round: impl FnMut(&RoundReport),
) -> Result<EmbeddedRun, EmbeddedError> {
    let learner = match from {
        Some(saved) => Learner::resume(run.clone(), options, &saved.checkpoint)?,
        None => Learner::start(run.clone(), options)?,
    };
    let learner = Arc::new(learner);
    let mut link = InProcess::new(learner.clone());
    let options = ActorOptions {
        lockstep: true,
        eval_every_episodes: Some(run.agent.exploration_episodes.max(1) as u64),
        max_episodes: Some(run.episodes),
        transports: vec!["in-process".into()],
        resume: from.map(|saved| saved.trainer.clone()),
        ..ActorOptions::trainer("embedded-0")
    };
    // A continued run's earlier rounds were reported by the process that played them.
    let mut seen = from.map_or(0, |saved| saved.checkpoint.curve().len());
    let actor = run_actor(&mut link, &options, interrupt, |_| {
        let curve = learner.curve();
        for report in &curve[seen..] {
            on_round(report);
        }
        seen = curve.len();
    });
    drop(link);
    learner.finish("embedded run over");
    let learner = Arc::into_inner(learner).expect("the in-process link was the only other owner");
    let finished = learner.shutdown();
    let actor = actor?;
    let saved = match (keep_state, &actor.trainer_state) {
        (true, Some(trainer)) => Some(SavedRun {
            checkpoint: finished.checkpoint(true),
            trainer: trainer.clone(),
        }),
        _ => None,
    };
    Ok(EmbeddedRun {
        agent: finished.agent,
        curve: finished.curve,
        best: finished.best,
        status: finished.status,
        actor,
        saved,
    })
}
