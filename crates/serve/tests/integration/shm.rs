//! Shared memory between a learner and its actors, for real (iceoryx2 in `/dev/shm`, in one
//! process): exactly-once storage through the learner's own checks, weights to late joiners,
//! refusals as precise as gRPC's, a full window that blocks, two runs that never meet, a
//! learner restart, messages held until durable and resent to a learner resumed from its
//! write-ahead log, and the fallback to gRPC.

use crate::common;

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use common::{episode, localhost, rejected, runtime};

use hac_agent::RunConfig;
use hac_core::Batch;
use hac_learner::{Learner, LearnerOptions, RejectReason, WalOptions};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, Registration};
use hac_serve::grpc::{ServerOptions, serve};
use hac_serve::shm::{ShmServer, ShmServerOptions};
use hac_transport::grpc::{GrpcLink, GrpcLinkOptions};
use hac_transport::shm::{Namespace, Overflow, ShmLink, ShmLinkOptions, ShmMode};
use hac_transport::{ActorLink, IngestSink, LinkError, WeightsSource};
use tokio::sync::oneshot;

const WAIT: Duration = Duration::from_secs(30);

fn start_learner(seed: u64) -> Arc<Learner> {
    let run = run_config(seed);
    let options = LearnerOptions::for_run(&run);
    Arc::new(Learner::start(run, options).unwrap())
}

fn run_config(seed: u64) -> RunConfig {
    let mut agent = hac_envs::make("mountain-car").unwrap().default_config(2);
    agent.test_episodes = 2;
    RunConfig {
        env: "mountain-car".into(),
        levels: 2,
        seed,
        episodes: 1000,
        stop_at: None,
        replay_shards: 2,
        max_actions: None,
        subgoal_bounds: None,
        agent,
        tabular: None,
        hiro: None,
        algo: Default::default(),
    }
}

/// A learner with a write-ahead log in `dir` that commits only when the test says so
/// (`sync_wal`), so that what is durable is exactly known; started again on the same `dir`, it
/// replays the log (a learner killed before its first checkpoint).
fn start_logged_learner(dir: &Path) -> Arc<Learner> {
    let run = run_config(0);
    let options = LearnerOptions {
        wal: Some(WalOptions {
            commit_bytes: usize::MAX,
            max_pending_bytes: usize::MAX,
            ..WalOptions::new(dir.join("wal"), Duration::from_secs(3600))
        }),
        ..LearnerOptions::for_run(&run)
    };
    Arc::new(Learner::start(run, options).unwrap())
}

/// A learner served over gRPC and (optionally) shared memory, as the daemon does.
struct Served {
    learner: Arc<Learner>,
    addr: SocketAddr,
    shm: Option<ShmServer>,
    stop: Option<oneshot::Sender<()>>,
    done: Option<tokio::task::JoinHandle<Result<(), tonic::transport::Error>>>,
}

impl Served {
    fn start(
        runtime: &tokio::runtime::Runtime,
        learner: Arc<Learner>,
        addr: SocketAddr,
        shm: Option<ShmServerOptions>,
    ) -> Self {
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind(addr))
            .unwrap();
        let addr = listener.local_addr().unwrap();
        let shm = shm.map(|options| {
            let namespace = Namespace::for_run(&learner.status().run_config_digest, addr);
            ShmServer::start(learner.clone(), namespace, options).unwrap()
        });
        let options = ServerOptions {
            shm_offer: shm.as_ref().map(ShmServer::offer),
            drain_timeout: Duration::from_secs(2),
            ..ServerOptions::default()
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let done = runtime.spawn(serve(learner.clone(), listener, options, async {
            let _ = stopped.await;
        }));
        Self {
            learner,
            addr,
            shm,
            stop: Some(stop),
            done: Some(done),
        }
    }

    fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    fn stop(mut self, runtime: &tokio::runtime::Runtime) {
        if let Some(shm) = self.shm.take() {
            shm.stop();
        }
        let _ = self.stop.take().unwrap().send(());
        let done = self.done.take().unwrap();
        runtime
            .block_on(async { tokio::time::timeout(WAIT, done).await })
            .expect("the server drains in time")
            .unwrap()
            .unwrap();
    }
}

fn grpc_options() -> GrpcLinkOptions {
    GrpcLinkOptions {
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        give_up_after: Duration::from_secs(30),
        jitter_seed: 7,
        ..GrpcLinkOptions::default()
    }
}

fn link(served: &Served, mode: ShmMode) -> ShmLink {
    let options = ShmLinkOptions {
        mode,
        window: 64,
        max_batch_transitions: 64,
        give_up_after: Duration::from_secs(30),
        ..ShmLinkOptions::default()
    };
    ShmLink::connect(&served.url(), grpc_options(), options).unwrap()
}

fn registration(actor_id: &str) -> Registration {
    Registration {
        actor_id: actor_id.into(),
        role: ActorRole::Trainer,
        hostname: "test".into(),
        transports: vec!["grpc".into(), "shm".into()],
    }
}

/// A valid batch of `len` transitions for `level`, its rewards marked with `mark`.
fn batch_item(learner: &Learner, level: usize, len: usize, mark: f32) -> IngestItem {
    let mut batch = Batch::zeros(learner.dims()[level], len);
    batch.rewards.fill(mark);
    batch.terminals[len - 1] = 1.0;
    IngestItem::Batch(DecodedBatch {
        level,
        weights_version: 1,
        batch,
    })
}

fn shm_options() -> ShmServerOptions {
    ShmServerOptions {
        max_actors: 4,
        window: 8,
        ..ShmServerOptions::default()
    }
}

#[test]
fn batches_over_shared_memory_are_stored_exactly_once_and_weights_reach_late_joiners() {
    let runtime = runtime();
    let served = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let learner = served.learner.clone();
    let mut link = link(&served, ShmMode::Require);
    let admission = link.register(&registration("a")).unwrap();
    assert!(link.uses_shm());
    assert!(admission.shm.is_some());
    // Offered only to actors that ask for it.
    let mut grpc_only = GrpcLink::connect(&served.url(), grpc_options()).unwrap();
    let plain = grpc_only
        .register(&Registration {
            transports: vec!["grpc".into()],
            ..registration("g")
        })
        .unwrap();
    assert_eq!(plain.shm, None);
    drop(grpc_only);
    // The window is the learner's buffer (8), not the link's 64.
    for i in 0..40 {
        link.send(batch_item(&learner, i % 2, 16, -1.0)).unwrap();
        if i % 10 == 9 {
            link.send(episode()).unwrap();
        }
    }
    link.flush(WAIT).unwrap();
    let status = learner.status();
    assert_eq!(
        (status.batches, status.episodes, status.duplicates),
        (40, 4, 0)
    );
    assert_eq!(status.transitions, 40 * 16);
    assert_eq!(
        status.levels.iter().map(|l| l.replay_len).sum::<usize>(),
        40 * 16
    );
    assert_eq!(link.acked_through(), 44);
    assert_eq!(link.unacked(), 0);

    // Joined after version 1 was published: the history brings it.
    let first = link
        .weights()
        .wait_for(WAIT, |_| true)
        .expect("the current weights");
    assert!(first.version >= 1);
    let newer = learner.republish();
    let got = link
        .weights()
        .wait_for(WAIT, |w| w.version >= newer)
        .expect("the new version");
    assert_eq!(got.levels.len(), 2);
    assert!(got.levels.iter().all(|l| !l.is_empty()));

    learner.finish("test over");
    let last = link.weights().wait_for(WAIT, |w| w.run_finished);
    assert!(last.is_some(), "the final snapshot arrives");
    link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    assert!(matches!(link.flush(WAIT), Err(LinkError::Finished)));
    drop(link);
    served.stop(&runtime);
}

#[test]
fn a_bad_batch_is_refused_as_precisely_as_over_grpc() {
    let runtime = runtime();
    let served = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let learner = served.learner.clone();
    let mut link = link(&served, ShmMode::Require);
    link.register(&registration("a")).unwrap();
    link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    link.send(batch_item(&learner, 0, 4, f32::NAN)).unwrap();
    // Sent after the refused one: not read (the gRPC stream would have ended).
    link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    let err = link.flush(WAIT).expect_err("refused");
    let LinkError::Refused(message) = err else {
        panic!("expected a refusal, got {err:?}")
    };
    assert!(
        message.contains("message 2") && message.contains("not_finite"),
        "{message}"
    );
    let status = learner.status();
    assert_eq!((status.batches, status.messages), (1, 2));
    assert_eq!(rejected(&learner, RejectReason::NotFinite), 1);
    drop(link);

    // An evaluator may not send transitions: `wrong_role`, as over gRPC.
    let mut evaluator = self::link(&served, ShmMode::Require);
    evaluator
        .register(&Registration {
            role: ActorRole::Evaluator,
            ..registration("e")
        })
        .unwrap();
    evaluator.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    let err = evaluator.flush(WAIT).expect_err("refused");
    assert!(err.to_string().contains("wrong_role"), "{err}");
    assert_eq!(rejected(&learner, RejectReason::WrongRole), 1);
    drop(evaluator);
    learner.finish("test over");
    served.stop(&runtime);
}

#[test]
fn two_runs_on_one_host_never_see_each_others_data() {
    let runtime = runtime();
    // The same config (same digest) on two addresses: two namespaces.
    let one = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let two = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let (mut a, mut b) = (link(&one, ShmMode::Require), link(&two, ShmMode::Require));
    a.register(&registration("same-id")).unwrap();
    b.register(&registration("same-id")).unwrap();
    assert_ne!(a.namespace(), b.namespace());
    for _ in 0..5 {
        a.send(batch_item(&one.learner, 0, 8, -1.0)).unwrap();
    }
    for _ in 0..3 {
        b.send(batch_item(&two.learner, 1, 8, -1.0)).unwrap();
    }
    a.flush(WAIT).unwrap();
    b.flush(WAIT).unwrap();
    let (s1, s2) = (one.learner.status(), two.learner.status());
    assert_eq!(
        (s1.batches, s1.levels[0].replay_len, s1.levels[1].replay_len),
        (5, 40, 0)
    );
    assert_eq!(
        (s2.batches, s2.levels[0].replay_len, s2.levels[1].replay_len),
        (3, 0, 24)
    );
    assert_eq!(s1.messages + s2.messages, 8, "nothing crossed over");
    // Weights too: each link holds its own learner's.
    let v = two.learner.republish();
    assert!(b.weights().wait_for(WAIT, |w| w.version == v).is_some());
    std::thread::sleep(Duration::from_millis(200));
    assert!(a.weights().latest().is_some_and(|w| w.version < v));
    drop((a, b));
    for served in [one, two] {
        served.learner.finish("test over");
        served.stop(&runtime);
    }
}

#[test]
fn a_full_window_blocks_until_the_learner_reads_again_and_nothing_is_stored_twice() {
    let runtime = runtime();
    let learner = start_learner(0);
    let mut served = Served::start(&runtime, learner.clone(), localhost(), Some(shm_options()));
    let namespace = Namespace::for_run(&learner.status().run_config_digest, served.addr);
    let mut link = link(&served, ShmMode::Require);
    link.register(&registration("a")).unwrap();
    link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    link.flush(WAIT).unwrap();

    // The learner stops reading shared memory: the window (8) fills, then `send` blocks.
    served.shm.take().unwrap().stop();
    for _ in 0..8 {
        link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    }
    let (sent_tx, sent_rx) = std::sync::mpsc::channel();
    let item = batch_item(&learner, 0, 4, -1.0);
    let sender = std::thread::spawn(move || {
        let result = link.send(item);
        let _ = sent_tx.send(());
        (link, result)
    });
    assert!(
        sent_rx.recv_timeout(Duration::from_millis(700)).is_err(),
        "the ninth send waits for room"
    );
    // It reads again (a new subscriber): the link sends its window again; stored once.
    served.shm = Some(ShmServer::start(learner.clone(), namespace, shm_options()).unwrap());
    sent_rx.recv_timeout(WAIT).expect("room once acks arrive");
    let (mut link, result) = sender.join().unwrap();
    result.unwrap();
    link.flush(WAIT).unwrap();
    let status = learner.status();
    assert_eq!(status.batches, 10);
    assert_eq!(status.transitions, 40);
    assert_eq!(link.incarnation(), 1);
    drop(link);
    learner.finish("test over");
    served.stop(&runtime);
}

#[test]
fn two_actors_streaming_at_once_are_both_stored() {
    // Both send as fast as their windows allow for 2 s. The learner's subscriber finds the
    // first actor's next message waiting nearly every time it looks, so reading one message at
    // a time in the subscriber's order served that actor alone (one trainer stuck at 0 stored
    // in 3 of 9 starts of two real trainers); rounds of one message per actor share it.
    let runtime = runtime();
    let served = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let learner = served.learner.clone();
    let until = std::time::Instant::now() + Duration::from_secs(2);
    let senders: Vec<_> = ["a", "b"]
        .into_iter()
        .map(|id| {
            let mut link = link(&served, ShmMode::Require);
            link.register(&registration(id)).unwrap();
            let item = batch_item(&learner, 0, 16, -1.0);
            std::thread::spawn(move || {
                let mut sent = 0u64;
                while std::time::Instant::now() < until {
                    link.send(item.clone()).unwrap();
                    // Episodes earn updates, which the learner's rate limiter waits for: the
                    // learner, not the actors, sets the pace, as in a run.
                    link.send(episode()).unwrap();
                    sent += 2;
                }
                link.flush(WAIT).unwrap();
                (link, sent)
            })
        })
        .collect();
    let mut links = Vec::new();
    for sender in senders {
        let (link, sent) = sender.join().unwrap();
        assert_eq!(link.acked_through(), sent);
        links.push((link, sent));
    }
    let (a, b) = (
        stored_through(&learner, "a").1,
        stored_through(&learner, "b").1,
    );
    eprintln!("stored in 2 s: a {a}, b {b}");
    assert_eq!((a, b), (links[0].1, links[1].1));
    // Neither waited for the other: each stored at least a quarter of the total (60:40 here;
    // 87:13 before the rounds).
    assert!(4 * a.min(b) >= a + b, "a {a}, b {b}");
    drop(links);
    learner.finish("test over");
    served.stop(&runtime);
}

#[test]
fn with_the_drop_policy_a_full_window_drops_batches_and_counts_them() {
    let runtime = runtime();
    let learner = start_learner(0);
    let mut served = Served::start(&runtime, learner.clone(), localhost(), Some(shm_options()));
    let options = ShmLinkOptions {
        mode: ShmMode::Require,
        overflow: Overflow::Drop,
        max_batch_transitions: 64,
        ..ShmLinkOptions::default()
    };
    let mut link = ShmLink::connect(&served.url(), grpc_options(), options).unwrap();
    link.register(&registration("a")).unwrap();
    served.shm.take().unwrap().stop();
    for _ in 0..11 {
        link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    }
    assert_eq!(link.unacked(), 8);
    assert_eq!(link.dropped(), (3, 12));
    drop(link);
    learner.finish("test over");
    served.stop(&runtime);
}

#[test]
fn a_shm_link_resends_to_a_restarted_learner_under_a_new_incarnation() {
    let runtime = runtime();
    let first = Served::start(&runtime, start_learner(0), localhost(), Some(shm_options()));
    let addr = first.addr;
    let old = first.learner.clone();
    let mut link = link(&first, ShmMode::Require);
    link.register(&registration("a")).unwrap();
    for _ in 0..3 {
        link.send(batch_item(&old, 0, 4, -1.0)).unwrap();
    }
    link.flush(WAIT).unwrap();

    // The learner goes away; the actor keeps sending into its window.
    old.finish("restart");
    first.stop(&runtime);
    for _ in 0..4 {
        link.send(batch_item(&old, 1, 4, -1.0)).unwrap();
    }
    assert_eq!(link.unacked(), 4);

    // The same run again on the same address: the same namespace, a learner that does not know
    // the actor. The link resends, is asked to register, and resends under the new incarnation.
    let second_learner = start_learner(0);
    second_learner.register(registration("other")).unwrap();
    let second = Served::start(&runtime, second_learner.clone(), addr, Some(shm_options()));
    link.flush(WAIT).unwrap();
    let status = second_learner.status();
    assert_eq!(status.batches, 4);
    assert_eq!(status.levels[1].replay_len, 16);
    assert!(link.uses_shm());
    assert_eq!(
        link.incarnation(),
        2,
        "the new learner's second registration"
    );
    assert_eq!(rejected(&second_learner, RejectReason::UnknownActor), 1);
    assert_eq!(
        old.status().batches,
        3,
        "nothing went to the old learner twice"
    );
    drop(link);
    second_learner.finish("test over");
    second.stop(&runtime);
}

/// `actor`'s incarnation, stored-through and durable-through sequences on `learner`.
fn stored_through(learner: &Learner, actor: &str) -> (u64, u64, u64) {
    let status = learner.status();
    let a = status.actors.iter().find(|a| a.actor_id == actor).unwrap();
    (a.incarnation, a.stored_through, a.durable_through)
}

#[test]
fn messages_are_held_until_durable_and_a_resumed_learner_gets_the_rest_once() {
    let dir = std::env::temp_dir().join(format!("hac-shm-durable-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let runtime = runtime();
    let first = Served::start(
        &runtime,
        start_logged_learner(&dir),
        localhost(),
        Some(shm_options()),
    );
    let addr = first.addr;
    let learner = first.learner.clone();
    let mut link = link(&first, ShmMode::Require);
    let incarnation = link.register(&registration("a")).unwrap().incarnation;
    let stats = link.stats().unwrap();
    // 12 messages (more than the window of 8): acknowledged, not durable, so all held.
    for i in 0..12 {
        link.send(batch_item(&learner, i % 2, 4, -1.0)).unwrap();
    }
    link.flush(WAIT).unwrap();
    assert_eq!((link.acked_through(), link.durable_through()), (12, 0));
    assert_eq!((link.unacked(), link.held()), (0, 12));
    assert_eq!((stats.unacked(), stats.undurable()), (0, 12));
    assert!(matches!(
        link.flush_durable(Duration::from_millis(300)),
        Err(LinkError::TimedOut(12))
    ));
    // The log commits: the learner says so without any new message, and the link lets go.
    assert!(learner.sync_wal(WAIT));
    link.flush_durable(WAIT).unwrap();
    assert_eq!((link.durable_through(), link.held()), (12, 0));
    assert_eq!(stats.undurable(), 0);
    assert_eq!(
        (stats.sent_transitions(), stats.durable_transitions()),
        (48, 48)
    );

    // Six more, acknowledged and not durable when the learner dies as kill -9 would have it.
    for i in 0..6 {
        link.send(batch_item(&learner, i % 2, 4, 0.0)).unwrap();
    }
    link.flush(WAIT).unwrap();
    assert_eq!((link.acked_through(), link.held()), (18, 6));
    assert_eq!(stored_through(&learner, "a"), (incarnation, 18, 12));
    learner.simulate_crash();
    first.stop(&runtime);

    // Resumed from its log on the same address (the same namespace): it has what was durable.
    let second = Served::start(
        &runtime,
        start_logged_learner(&dir),
        addr,
        Some(shm_options()),
    );
    let resumed = second.learner.clone();
    assert_eq!(stored_through(&resumed, "a"), (incarnation, 12, 12));
    // The actor sends on before it notices the restart: the learner lacks 13..=18, the link
    // registers again naming its incarnation, keeps it, and resends from 13.
    for i in 0..2 {
        link.send(batch_item(&resumed, i % 2, 4, -1.0)).unwrap();
    }
    link.flush(WAIT).unwrap();
    assert!(resumed.sync_wal(WAIT));
    link.flush_durable(WAIT).unwrap();
    assert!(link.uses_shm());
    assert_eq!(link.incarnation(), incarnation, "the incarnation is kept");
    assert_eq!((link.durable_through(), link.held()), (20, 0));
    assert_eq!(stored_through(&resumed, "a"), (incarnation, 20, 20));
    let status = resumed.status();
    // Every message once: 12 replayed from the log, 8 over shared memory after the restart
    // (and the counts of the replayed ones restored).
    assert_eq!((status.batches, status.transitions), (20, 80));
    assert_eq!(
        status
            .levels
            .iter()
            .map(|l| l.transitions_inserted)
            .sum::<u64>(),
        80
    );
    // Only a gap can have been refused (the actor's send after the restart, if the learner saw
    // it before the resend), and nothing stored twice.
    let refused: u64 = status.rejected.iter().map(|(_, n)| n).sum();
    eprintln!(
        "after the restart: {refused} refused, {} duplicates",
        status.duplicates
    );
    assert_eq!(refused, rejected(&resumed, RejectReason::SequenceGap));
    assert_eq!(
        status.messages,
        20 + status.duplicates + refused,
        "{status:?}"
    );
    assert_eq!(
        (stats.sent_transitions(), stats.durable_transitions()),
        (80, 80)
    );
    drop(link);
    resumed.finish("test over");
    second.stop(&runtime);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn auto_falls_back_to_grpc_when_the_learner_serves_no_shared_memory() {
    let runtime = runtime();
    let served = Served::start(&runtime, start_learner(0), localhost(), None);
    let learner = served.learner.clone();
    let mut link = link(&served, ShmMode::Prefer);
    let admission = link.register(&registration("a")).unwrap();
    assert!(admission.shm.is_none());
    assert!(!link.uses_shm());
    for _ in 0..5 {
        link.send(batch_item(&learner, 0, 4, -1.0)).unwrap();
    }
    link.flush(WAIT).unwrap();
    assert_eq!(learner.status().batches, 5);
    assert!(
        link.weights().wait_for(WAIT, |_| true).is_some(),
        "weights over gRPC"
    );

    let mut required = self::link(&served, ShmMode::Require);
    let err = required.register(&registration("b")).expect_err("no shm");
    assert!(err.to_string().contains("start it with --shm"), "{err}");
    drop((link, required));
    learner.finish("test over");
    served.stop(&runtime);
}
