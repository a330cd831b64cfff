//! Episode turns (`episodes_in_flight`): at most that many training episodes played or waiting
//! to be trained on at once, granted in the order asked, used up by the episode, released by a
//! new registration, refused by reason, and ended by the end of the run.

use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

use hac_agent::RunConfig;
use hac_core::Batch;
use hac_learner::{
    IngestError, InvalidOption, Learner, LearnerOptions, RejectReason, StartError, Turn,
};
use hac_proto::{ActorRole, DecodedBatch, IngestItem, IngestMessage, Registration};

use crate::common;
use common::rejected;

fn run() -> RunConfig {
    common::small_run(1000, 1)
}

fn start(episodes_in_flight: u32) -> Arc<Learner> {
    let config = run();
    let options = LearnerOptions {
        episodes_in_flight,
        ..LearnerOptions::for_run(&config)
    };
    Arc::new(Learner::start(config, options).unwrap())
}

/// Registers `id` and returns its incarnation.
fn register(learner: &Learner, id: &str, role: ActorRole) -> u64 {
    learner
        .register(Registration {
            actor_id: id.into(),
            role,
            hostname: "localhost".into(),
            transports: vec!["in-process".into()],
        })
        .unwrap()
        .incarnation
}

/// One training episode of `id`: a batch per level large enough to train on, then the summary.
/// `sequence` is the last sequence used; returns the new one.
fn play(learner: &Learner, id: &str, incarnation: u64, sequence: u64) -> u64 {
    let mut items: Vec<IngestItem> = (0..2)
        .map(|level| {
            let mut batch = Batch::zeros(learner.dims()[level], 8);
            batch.rewards.fill(-1.0);
            IngestItem::Batch(DecodedBatch {
                level,
                weights_version: 1,
                batch,
            })
        })
        .collect();
    items.push(IngestItem::Episode {
        env_steps: 10,
        success: false,
        weights_version: 1,
    });
    let mut sequence = sequence;
    for item in items {
        sequence += 1;
        learner
            .ingest(&IngestMessage {
                actor_id: id.into(),
                incarnation,
                sequence,
                item,
            })
            .unwrap();
    }
    sequence
}

const NOW: Duration = Duration::ZERO;
const LONG: Duration = Duration::from_secs(10);

#[test]
fn one_turn_at_a_time_in_the_order_asked_each_with_weights_trained_on_every_episode_before() {
    let learner = start(1);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    let c = register(&learner, "c", ActorRole::Trainer);

    let granted = learner.await_turn("a", a, NOW).unwrap();
    assert_eq!(
        granted,
        Turn {
            granted: true,
            episodes: 0,
            episode: Some(0),
        }
    );
    // Asking again while holding the turn returns it; nobody else gets one meanwhile.
    assert_eq!(learner.await_turn("a", a, NOW).unwrap(), granted);
    let t0 = Instant::now();
    assert_eq!(
        learner
            .await_turn("b", b, Duration::from_millis(50))
            .unwrap(),
        Turn {
            granted: false,
            episodes: 0,
            episode: None,
        }
    );
    assert!(t0.elapsed() >= Duration::from_millis(50), "it waited");

    // b asks first, then c; both wait while a plays.
    let ask = |id: &'static str, incarnation: u64| {
        let learner = learner.clone();
        thread::spawn(move || {
            let turn = learner.await_turn(id, incarnation, LONG).unwrap();
            (turn, Instant::now())
        })
    };
    let b_waits = ask("b", b);
    thread::sleep(Duration::from_millis(50));
    let c_waits = ask("c", c);
    thread::sleep(Duration::from_millis(50));
    assert!(!b_waits.is_finished() && !c_waits.is_finished());

    // a's episode uses its turn; b's comes once every level has trained on it (published).
    play(&learner, "a", a, 0);
    let (b_turn, b_at) = b_waits.join().unwrap();
    assert!(b_turn.granted);
    assert_eq!(
        b_turn.episodes, 1,
        "the weights to play with cover a's episode"
    );
    assert_eq!(b_turn.episode, Some(1), "the run's second episode");
    assert!(learner.weights().latest().unwrap().episodes >= 1);
    thread::sleep(Duration::from_millis(100));
    assert!(!c_waits.is_finished(), "c waits for b's episode");

    play(&learner, "b", b, 0);
    let (c_turn, c_at) = c_waits.join().unwrap();
    assert!(c_turn.granted && c_at > b_at);
    assert_eq!(c_turn.episodes, 2);
    assert_eq!(c_turn.episode, Some(2));
}

#[test]
fn asking_again_after_a_call_timed_out_keeps_the_place_in_line() {
    let learner = start(1);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    let c = register(&learner, "c", ActorRole::Trainer);
    assert!(learner.await_turn("a", a, NOW).unwrap().granted);
    // b asks first, gives up after 20 ms; c asks (and waits); b asks again.
    assert!(
        !learner
            .await_turn("b", b, Duration::from_millis(20))
            .unwrap()
            .granted
    );
    let ask = |id: &'static str, incarnation: u64| {
        let learner = learner.clone();
        thread::spawn(move || learner.await_turn(id, incarnation, LONG).unwrap())
    };
    let c_waits = ask("c", c);
    thread::sleep(Duration::from_millis(50));
    let b_waits = ask("b", b);
    thread::sleep(Duration::from_millis(50));
    assert_eq!(learner.status().turns.waiting, 2);
    play(&learner, "a", a, 0);
    assert!(b_waits.join().unwrap().granted, "b's place is ahead of c's");
    thread::sleep(Duration::from_millis(100));
    assert!(!c_waits.is_finished(), "c waits for b's episode");
    play(&learner, "b", b, 0);
    assert!(c_waits.join().unwrap().granted);
}

#[test]
fn a_limit_of_two_lets_two_trainers_play_at_once() {
    let learner = start(2);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    let c = register(&learner, "c", ActorRole::Trainer);
    // Each turn is for an episode of its own: the streams of two episodes in flight differ.
    assert_eq!(learner.await_turn("a", a, NOW).unwrap().episode, Some(0));
    assert_eq!(learner.await_turn("b", b, NOW).unwrap().episode, Some(1));
    assert!(
        !learner
            .await_turn("c", c, Duration::from_millis(20))
            .unwrap()
            .granted
    );
    play(&learner, "a", a, 0);
    // a's episode is in flight until trained on; then c may go, for the episode after b's.
    let c_turn = learner.await_turn("c", c, LONG).unwrap();
    assert!(c_turn.granted);
    assert_eq!(c_turn.episode, Some(2));
}

#[test]
fn registering_again_releases_the_turn_of_the_earlier_incarnation() {
    let learner = start(1);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    assert!(learner.await_turn("a", a, NOW).unwrap().granted);
    assert!(!learner.await_turn("b", b, NOW).unwrap().granted);
    let a2 = register(&learner, "a", ActorRole::Trainer);
    assert!(learner.await_turn("b", b, NOW).unwrap().granted);

    // The old incarnation is refused, counted, and holds nothing.
    let err = learner.await_turn("a", a, NOW).unwrap_err();
    assert!(matches!(err, IngestError::StaleIncarnation { .. }), "{err}");
    assert_eq!(rejected(&learner, RejectReason::StaleIncarnation), 1);
    assert!(!learner.await_turn("a", a2, NOW).unwrap().granted);
}

#[test]
fn a_turn_whose_episode_never_comes_expires_after_its_lease() {
    let config = run();
    let options = LearnerOptions {
        episodes_in_flight: 1,
        turn_lease: Duration::from_millis(200),
        ..LearnerOptions::for_run(&config)
    };
    let learner = Learner::start(config, options).unwrap();
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    let t0 = Instant::now();
    assert!(learner.await_turn("a", a, NOW).unwrap().granted);
    // a never plays (it died): b gets the turn once the lease has run out, not before.
    assert!(learner.await_turn("b", b, LONG).unwrap().granted);
    assert!(t0.elapsed() >= Duration::from_millis(200));
    let turns = learner.status().turns;
    assert_eq!((turns.granted, turns.expired, turns.held), (2, 1, 1));
}

#[test]
fn unknown_actors_and_evaluators_are_refused_by_reason() {
    let learner = start(1);
    let err = learner.await_turn("ghost", 1, NOW).unwrap_err();
    assert_eq!(err.to_string(), "unknown actor `ghost`: register first");
    assert_eq!(rejected(&learner, RejectReason::UnknownActor), 1);

    let e = register(&learner, "eval", ActorRole::Evaluator);
    let err = learner.await_turn("eval", e, NOW).unwrap_err();
    assert!(matches!(err, IngestError::WrongRole(_)), "{err}");
    assert_eq!(rejected(&learner, RejectReason::WrongRole), 1);
}

#[test]
fn the_end_of_the_run_wakes_every_waiter() {
    let learner = start(1);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    assert!(learner.await_turn("a", a, NOW).unwrap().granted);
    let waiter = {
        let learner = learner.clone();
        thread::spawn(move || learner.await_turn("b", b, LONG))
    };
    thread::sleep(Duration::from_millis(50));
    let t0 = Instant::now();
    learner.finish("test over");
    let result = waiter.join().unwrap();
    assert!(matches!(result, Err(IngestError::Finished)), "{result:?}");
    assert!(t0.elapsed() < Duration::from_secs(2));
}

#[test]
fn without_turns_every_call_is_granted_at_once() {
    let learner = start(0);
    let a = register(&learner, "a", ActorRole::Trainer);
    let b = register(&learner, "b", ActorRole::Trainer);
    for _ in 0..3 {
        assert!(learner.await_turn("a", a, NOW).unwrap().granted);
        assert!(learner.await_turn("b", b, NOW).unwrap().granted);
    }
    assert_eq!(learner.options().episodes_in_flight, 0);
}

#[test]
fn a_limit_above_1024_is_refused_by_name() {
    let config = run();
    let options = LearnerOptions {
        episodes_in_flight: 1025,
        ..LearnerOptions::for_run(&config)
    };
    let err = Learner::start(config, options).unwrap_err();
    assert!(
        matches!(
            err,
            StartError::Options(InvalidOption::EpisodesInFlight(1025))
        ),
        "{err}"
    );
}
