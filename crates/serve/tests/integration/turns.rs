//! Trainers under episode turns (a learner with `episodes_in_flight`), over the in-process
//! transport: several trainers share the turns, with one episode in flight they train what one
//! trainer alone does, bit for bit, and a turn naming weights that never come (a
//! learner restarted from an earlier checkpoint in between) is asked for again instead of
//! waited on forever. And over gRPC: an actor whose link registered again reports the incarnation
//! it ended under.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use hac_actor::{ActorOptions, run_actor};
use hac_agent::RunConfig;
use hac_learner::{Learner, LearnerOptions, Published};
use hac_proto::{ActorRole, Admission, IngestItem, Registration, WeightsSnapshot};
use hac_serve::InProcess;
use hac_serve::grpc::{ServerOptions, serve};
use hac_transport::grpc::{GrpcLink, GrpcLinkOptions};
use hac_transport::{
    ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, LinkStats, WeightsSource,
};

fn learner(episodes_in_flight: u32) -> Arc<Learner> {
    learner_of(episodes_in_flight, 1000, 1)
}

fn learner_of(episodes_in_flight: u32, episodes: u64, replay_shards: usize) -> Arc<Learner> {
    let mut agent = hac_envs::make("pendulum").unwrap().default_config(2);
    agent.batch_size = 16;
    agent.updates_per_episode = 2;
    agent.hidden_layers = vec![8];
    let run = RunConfig {
        env: "pendulum".into(),
        levels: 2,
        seed: 4,
        episodes,
        stop_at: None,
        replay_shards,
        max_actions: None,
        subgoal_bounds: None,
        agent,
        tabular: None,
        hiro: None,
        algo: Default::default(),
    };
    let options = LearnerOptions {
        episodes_in_flight,
        ..LearnerOptions::for_run(&run)
    };
    Arc::new(Learner::start(run, options).unwrap())
}

fn trainer(id: &str, episodes: u64) -> ActorOptions {
    ActorOptions {
        max_episodes: Some(episodes),
        transports: vec!["in-process".into()],
        ..ActorOptions::trainer(id)
    }
}

/// Runs one in-process trainer per id on `learner`, each for `each` episodes, all at once, and
/// returns the episodes each played.
fn play_trainers(learner: &Arc<Learner>, ids: &[&str], each: u64) -> Vec<u64> {
    let handles: Vec<_> = ids
        .iter()
        .map(|&id| {
            let mut link = InProcess::new(learner.clone());
            let options = trainer(id, each);
            std::thread::spawn(move || {
                run_actor(&mut link, &options, &AtomicBool::new(false), |_| {}).unwrap()
            })
        })
        .collect();
    handles
        .into_iter()
        .map(|h| h.join().unwrap().episodes)
        .collect()
}

#[test]
fn three_trainers_share_one_turn_and_each_plays_its_episodes() {
    let learner = learner(1);
    for played in play_trainers(&learner, &["a", "b", "c"], 4) {
        assert_eq!(played, 4);
    }
    let status = learner.status();
    assert_eq!(status.episodes, 12);
    assert_eq!(status.turns.granted, 12, "one turn per episode");
    assert_eq!(status.turns.held, 0);
}

/// The run's weights once `trainers` trainers, `each` episodes apiece, have trained a learner
/// with one episode in flight and three replay shards to its budget (all their episodes).
fn trained_by(trainers: &[&str], each: u64) -> Vec<Vec<u8>> {
    let learner = learner_of(1, trainers.len() as u64 * each, 3);
    let played = play_trainers(&learner, trainers, each);
    assert_eq!(played, vec![each; trainers.len()]);
    let deadline = Instant::now() + Duration::from_secs(60);
    while !learner.is_finished() {
        assert!(Instant::now() < deadline, "the budget was never trained");
        std::thread::sleep(Duration::from_millis(10));
    }
    let status = learner.status();
    assert_eq!(status.episodes, trainers.len() as u64 * each);
    assert!(status.levels.iter().all(|l| l.updates > 0), "it trained");
    learner.weights().latest().unwrap().levels.clone()
}

#[test]
fn with_one_episode_in_flight_the_run_is_the_same_whichever_trainers_play_it() {
    // Each episode draws from the run seed's streams of its index, and batches go round the
    // replay shards in the order stored: one trainer or three, interleaved however their
    // threads are scheduled, train the same networks bit for bit.
    let alone = trained_by(&["a"], 12);
    let three = trained_by(&["a", "b", "c"], 4);
    assert!(
        alone == three,
        "one trainer and three trained different networks"
    );
    let six = trained_by(&["a", "b", "c", "d", "e", "f"], 2);
    assert!(
        alone == six,
        "one trainer and six trained different networks"
    );
}

/// The in-process link, except that its first turn names more trained episodes than the
/// learner will ever have published (as a learner that has since restarted from an earlier
/// checkpoint would have).
struct FirstTurnFromAnotherLearner {
    inner: InProcess,
    stale_turns: u32,
}

impl IngestSink for FirstTurnFromAnotherLearner {
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        self.inner.send(item)
    }

    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError> {
        self.inner.flush(timeout)
    }
}

impl WeightsSource for FirstTurnFromAnotherLearner {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        self.inner.weights()
    }

    fn learner_version(&self) -> u64 {
        self.inner.learner_version()
    }
}

impl ActorLink for FirstTurnFromAnotherLearner {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        self.inner.register(registration)
    }

    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        let turn = self.inner.await_turn(wait)?;
        if let Some(turn) = turn
            && self.stale_turns == 0
        {
            self.stale_turns += 1;
            return Ok(Some(GrantedTurn {
                trained: 1_000_000,
                ..turn
            }));
        }
        Ok(turn)
    }

    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        self.inner.report_evaluation(report)
    }
}

#[test]
fn a_turn_naming_weights_that_never_come_is_asked_for_again() {
    let learner = learner(1);
    let mut link = FirstTurnFromAnotherLearner {
        inner: InProcess::new(learner.clone()),
        stale_turns: 0,
    };
    let started = Instant::now();
    let summary = run_actor(&mut link, &trainer("a", 2), &AtomicBool::new(false), |_| {}).unwrap();
    assert_eq!(summary.episodes, 2);
    assert_eq!(link.stale_turns, 1);
    assert!(
        started.elapsed() >= Duration::from_secs(5),
        "it waited for the named weights first"
    );
    assert_eq!(learner.status().episodes, 2);
}

/// A gRPC link whose actor id is registered again by someone else once its first message is
/// stored: the link finds its incarnation superseded at the second and registers again.
struct SupersededOnce {
    inner: GrpcLink,
    learner: Arc<Learner>,
    sent: u32,
}

const WAIT: Duration = Duration::from_secs(30);

impl IngestSink for SupersededOnce {
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        self.inner.send(item)?;
        self.sent += 1;
        match self.sent {
            // The first message stored under the first incarnation, then the id taken over.
            1 => {
                self.inner.flush(WAIT)?;
                self.learner
                    .register(Registration {
                        actor_id: "a".into(),
                        role: ActorRole::Trainer,
                        hostname: "elsewhere".into(),
                        transports: vec!["grpc".into()],
                    })
                    .unwrap();
            }
            // Refused as stale, registered again, resent and acknowledged.
            2 => self.inner.flush(WAIT)?,
            _ => {}
        }
        Ok(())
    }

    fn flush(&mut self, timeout: Duration) -> Result<(), LinkError> {
        self.inner.flush(timeout)
    }
}

impl WeightsSource for SupersededOnce {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        self.inner.weights()
    }

    fn learner_version(&self) -> u64 {
        self.inner.learner_version()
    }
}

impl ActorLink for SupersededOnce {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        self.inner.register(registration)
    }

    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        self.inner.await_turn(wait)
    }

    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        self.inner.report_evaluation(report)
    }

    fn stats(&self) -> Option<Arc<LinkStats>> {
        self.inner.stats()
    }
}

#[test]
fn an_actor_that_registered_again_reports_its_current_incarnation() {
    let learner = learner(0);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = runtime.spawn(serve(
        learner.clone(),
        listener,
        ServerOptions::default(),
        async {
            let _ = stopped.await;
        },
    ));
    let mut link = SupersededOnce {
        inner: GrpcLink::connect(&url, GrpcLinkOptions::default()).unwrap(),
        learner: learner.clone(),
        sent: 0,
    };
    let mut options = trainer("a", 2);
    options.transports = vec!["grpc".into()];
    let summary = run_actor(&mut link, &options, &AtomicBool::new(false), |_| {}).unwrap();
    // 1 at first, 2 for the other registration, 3 when the link registered again.
    assert_eq!(link.inner.incarnation(), 3);
    assert_eq!(summary.incarnation, 3, "{summary:?}");
    assert_eq!(summary.episodes, 2);

    drop(link);
    learner.finish("test over");
    let _ = stop.send(());
    runtime.block_on(server).unwrap().unwrap();
}
