//! The learner core without a transport: registration, exactly-once ingest, rejections by
//! reason, weights publication and the end of a run.

use std::time::Duration;

use hac_agent::RunConfig;
use hac_core::Batch;
use hac_learner::{IngestError, Learner, LearnerOptions, RejectReason, Stored};
use hac_proto::{ActorRole, DecodedBatch, Evaluation, IngestItem, IngestMessage, Registration};

use crate::common;
use common::rejected;

fn run(episodes: u64) -> RunConfig {
    common::small_run(episodes, 2)
}

fn start(episodes: u64) -> Learner {
    let config = run(episodes);
    let options = LearnerOptions::for_run(&config);
    Learner::start(config, options).unwrap()
}

fn registration(id: &str, role: ActorRole) -> Registration {
    Registration {
        actor_id: id.into(),
        role,
        hostname: "localhost".into(),
        transports: vec!["grpc".into()],
    }
}

fn batch(learner: &Learner, level: usize, len: usize) -> IngestItem {
    let mut batch = Batch::zeros(learner.dims()[level], len);
    batch.rewards.fill(-1.0);
    IngestItem::Batch(DecodedBatch {
        level,
        weights_version: 1,
        batch,
    })
}

fn episode() -> IngestItem {
    IngestItem::Episode {
        env_steps: 10,
        success: false,
        weights_version: 1,
    }
}

fn msg(id: &str, incarnation: u64, sequence: u64, item: IngestItem) -> IngestMessage {
    IngestMessage {
        actor_id: id.into(),
        incarnation,
        sequence,
        item,
    }
}

fn stored(learner: &Learner) -> u64 {
    learner
        .status()
        .levels
        .iter()
        .map(|l| l.transitions_inserted)
        .sum()
}

#[test]
fn registration_hands_out_fresh_incarnations_and_the_run() {
    let learner = start(100);
    let a = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap();
    let b = learner
        .register(registration("b", ActorRole::Trainer))
        .unwrap();
    let a2 = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap();
    assert!(a.incarnation >= 1 && b.incarnation > a.incarnation && a2.incarnation > b.incarnation);
    assert_ne!(
        a.seed, a2.seed,
        "a new incarnation gets fresh random streams"
    );
    assert_ne!(a.seed, b.seed);
    let config = RunConfig::from_toml(&a.run_config_toml, "admission").unwrap();
    assert_eq!(config, run(100));
    assert_eq!(a.run_config_digest.len(), 64);
    assert_eq!(a.levels, learner.dims());
    assert!(
        learner
            .register(registration("", ActorRole::Trainer))
            .is_err()
    );
    learner.shutdown();
}

#[test]
fn every_message_is_stored_once_and_resends_count_as_duplicates() {
    let learner = start(100);
    let inc = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    for seq in 1..=5 {
        let r = learner.ingest(&msg("a", inc, seq, batch(&learner, 0, 3)));
        assert_eq!(r.unwrap(), Stored::New);
    }
    // A reconnecting actor resends what it has no ack for.
    for seq in 3..=5 {
        let r = learner.ingest(&msg("a", inc, seq, batch(&learner, 0, 3)));
        assert_eq!(r.unwrap(), Stored::Duplicate);
    }
    let status = learner.status();
    assert_eq!(status.messages, 8);
    assert_eq!(status.duplicates, 3);
    assert_eq!(status.transitions, 15);
    assert_eq!(stored(&learner), 15, "received = stored + duplicates");
    // One actor alone still spreads over both shards.
    assert_eq!(status.levels[0].shard_lens, [9, 6]);
    learner.shutdown();
}

#[test]
fn a_status_taken_during_ingest_adds_up() {
    let learner = start(100);
    let actors: Vec<(String, u64)> = ["a", "b"]
        .iter()
        .map(|id| {
            let inc = learner
                .register(registration(id, ActorRole::Trainer))
                .unwrap()
                .incarnation;
            (id.to_string(), inc)
        })
        .collect();
    let batches = 2000;
    std::thread::scope(|scope| {
        for (id, inc) in &actors {
            let learner = &learner;
            scope.spawn(move || {
                for seq in 1..=batches {
                    let level = (seq % 2) as usize;
                    let r = learner.ingest(&msg(id, *inc, seq, batch(learner, level, 3)));
                    assert_eq!(r.unwrap(), Stored::New);
                }
            });
        }
        // Statuses taken while both actors insert: the per-level totals are one cut with the
        // run's total and batch count, whenever the status is taken.
        loop {
            let s = learner.status();
            let per_level: u64 = s.levels.iter().map(|l| l.transitions_inserted).sum();
            assert_eq!(per_level, s.transitions, "{s:?}");
            assert_eq!(s.transitions, 3 * s.batches, "{s:?}");
            for l in &s.levels {
                assert_eq!(l.shard_lens.iter().sum::<usize>(), l.replay_len, "{l:?}");
            }
            if s.batches == 2 * batches {
                break;
            }
        }
    });
    learner.shutdown();
}

#[test]
fn bad_messages_are_refused_by_reason_and_store_nothing() {
    let learner = start(100);
    let inc = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    learner
        .ingest(&msg("a", inc, 1, batch(&learner, 0, 2)))
        .unwrap();

    let mut nan = batch(&learner, 0, 2);
    if let IngestItem::Batch(b) = &mut nan {
        b.batch.states[1] = f32::NAN;
    }
    let mut short = batch(&learner, 1, 2);
    if let IngestItem::Batch(b) = &mut short {
        b.batch.goals.pop();
    }
    let cases: Vec<(IngestMessage, RejectReason)> = vec![
        (msg("a", inc, 2, nan), RejectReason::NotFinite),
        (msg("a", inc, 2, short), RejectReason::InvalidBatch),
        (
            msg("a", inc, 2, {
                let mut b = batch(&learner, 0, 2);
                if let IngestItem::Batch(d) = &mut b {
                    d.level = 2;
                }
                b
            }),
            RejectReason::LevelOutOfRange,
        ),
        (
            msg("a", inc, 2, batch(&learner, 0, 5000)),
            RejectReason::Oversized,
        ),
        (
            msg("nobody", 1, 1, batch(&learner, 0, 2)),
            RejectReason::UnknownActor,
        ),
        (
            msg("a", inc + 7, 2, batch(&learner, 0, 2)),
            RejectReason::StaleIncarnation,
        ),
        (
            msg("a", inc, 4, batch(&learner, 0, 2)),
            RejectReason::SequenceGap,
        ),
    ];
    for (m, reason) in cases {
        let before = rejected(&learner, reason);
        let e = learner.ingest(&m).unwrap_err();
        assert_eq!(e.reason(), reason, "{e}");
        assert_eq!(rejected(&learner, reason), before + 1, "{e}");
    }
    assert_eq!(stored(&learner), 2, "only the first, valid batch is stored");
    // The actor carries on where it was.
    learner
        .ingest(&msg("a", inc, 2, batch(&learner, 0, 2)))
        .unwrap();
    assert_eq!(stored(&learner), 4);

    // Evaluators send no transitions.
    let ev = learner
        .register(registration("eval", ActorRole::Evaluator))
        .unwrap()
        .incarnation;
    let e = learner
        .ingest(&msg("eval", ev, 1, batch(&learner, 0, 2)))
        .unwrap_err();
    assert!(matches!(e, IngestError::WrongRole(_)), "{e}");
    learner.shutdown();
}

#[test]
fn a_re_registered_actor_starts_a_new_sequence_and_its_old_incarnation_is_refused() {
    let learner = start(100);
    let old = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    learner
        .ingest(&msg("a", old, 1, batch(&learner, 0, 2)))
        .unwrap();
    let new = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let e = learner
        .ingest(&msg("a", old, 2, batch(&learner, 0, 2)))
        .unwrap_err();
    assert!(matches!(e, IngestError::StaleIncarnation { .. }), "{e}");
    assert_eq!(
        learner
            .ingest(&msg("a", new, 1, batch(&learner, 0, 2)))
            .unwrap(),
        Stored::New
    );
    assert_eq!(stored(&learner), 4);
    learner.shutdown();
}

#[test]
fn weights_cover_each_episode_once_its_updates_are_done_and_the_budget_ends_the_run() {
    let learner = start(3);
    let first = learner.weights().latest().expect("version 1 at start");
    assert_eq!((first.version, first.episodes), (1, 0));
    let inc = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let mut seq = 0;
    for e in 1..=3u64 {
        for level in 0..2 {
            seq += 1;
            learner
                .ingest(&msg("a", inc, seq, batch(&learner, level, 4)))
                .unwrap();
        }
        seq += 1;
        learner.ingest(&msg("a", inc, seq, episode())).unwrap();
        let w = learner
            .weights()
            .wait_for(Duration::from_secs(30), |w| w.episodes >= e)
            .expect("the episode's updates finish");
        assert_eq!(w.episodes, e);
        let status = learner.status();
        for level in &status.levels {
            assert_eq!(level.updates, 3 * e, "3 updates per episode: {level:?}");
        }
    }
    // No evaluator: the run is over once the budget's updates are done. The snapshot that
    // finishes the run follows the one that covers the last episode (the trainer that publishes
    // the one then finishes the run), so wait for it rather than read the latest at once.
    let last = learner
        .weights()
        .wait_for(Duration::from_secs(30), |w| w.run_finished)
        .expect("the budget's last updates finish the run");
    assert_eq!(last.episodes, 3, "{last:?}");
    assert!(learner.is_finished());
    let e = learner
        .ingest(&msg("a", inc, seq + 1, episode()))
        .unwrap_err();
    assert!(matches!(e, IngestError::Finished), "{e}");
    // Evaluations still land on the curve, at the episodes of the version they used.
    learner
        .report_evaluation(&Evaluation {
            actor_id: "a".into(),
            incarnation: inc,
            weights_version: last.version,
            episodes: 4,
            successes: 1,
            learner_start: 0,
        })
        .unwrap();
    let e = learner
        .report_evaluation(&Evaluation {
            actor_id: "a".into(),
            incarnation: inc,
            weights_version: 999,
            episodes: 4,
            successes: 1,
            learner_start: 0,
        })
        .unwrap_err();
    assert!(matches!(e, IngestError::UnknownWeightsVersion(999)), "{e}");
    // Weights of another learner process (one that ran before a restart) are refused by
    // reason; this one's are accepted.
    let start = last.learner_start;
    assert_ne!(start, 0);
    let report = |learner_start| Evaluation {
        actor_id: "a".into(),
        incarnation: inc,
        weights_version: last.version,
        episodes: 4,
        successes: 1,
        learner_start,
    };
    let e = learner.report_evaluation(&report(start ^ 1)).unwrap_err();
    assert!(matches!(e, IngestError::StaleWeights { .. }), "{e}");
    assert_eq!(rejected(&learner, RejectReason::StaleWeights), 1);
    learner.report_evaluation(&report(start)).unwrap();
    let finished = learner.shutdown();
    assert_eq!(finished.curve.len(), 2);
    assert_eq!(finished.curve[0].episodes, 3);
    assert_eq!(finished.curve[0].success_rate, 0.25);
    assert_eq!(finished.agent.levels().len(), 2);
}

#[test]
fn invalid_options_are_refused_by_name() {
    let config = run(10);
    let mut options = LearnerOptions::for_run(&config);
    options.error_buffer_episodes = 0.5;
    let e = Learner::start(config.clone(), options).unwrap_err();
    assert!(e.to_string().contains("error_buffer_episodes"), "{e}");
    let mut options = LearnerOptions::for_run(&config);
    options.max_batch_transitions = 0;
    let e = Learner::start(config, options).unwrap_err();
    assert!(e.to_string().contains("max_batch_transitions"), "{e}");
}

#[test]
fn status_knows_each_actors_transport_version_lag_and_rates() {
    let learner = start(1000);
    let trainer = learner
        .register(registration("t", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let evaluator = learner
        .register(registration("e", ActorRole::Evaluator))
        .unwrap()
        .incarnation;
    learner.set_actor_transport("t", "grpc");
    learner.set_actor_transport("nobody", "grpc");
    learner
        .ingest(&msg("t", trainer, 1, batch(&learner, 0, 8)))
        .unwrap();
    learner.ingest(&msg("t", trainer, 2, episode())).unwrap();
    let newest = learner.republish();
    learner
        .report_evaluation(&Evaluation {
            actor_id: "e".into(),
            incarnation: evaluator,
            weights_version: newest,
            episodes: 2,
            successes: 1,
            learner_start: 0,
        })
        .unwrap();
    std::thread::sleep(Duration::from_millis(20));
    let status = learner.status();
    let [e, t] = status.actors.as_slice() else {
        panic!("two actors: {:?}", status.actors);
    };
    assert_eq!((t.actor_id.as_str(), t.transport), ("t", "grpc"));
    assert_eq!(e.transport, "", "set by the transport, not guessed");
    assert_eq!(t.weights_version, 1);
    assert_eq!(t.weights_lag, status.weights_version - 1);
    // An evaluator's version comes from its reports.
    assert_eq!(e.weights_version, newest);
    assert_eq!(e.weights_lag, status.weights_version - newest);
    assert!(t.env_steps_per_s > 0.0, "{t:?}");
    assert!(status.rates.transitions_per_s > 0.0, "{:?}", status.rates);
    assert!(status.rates.episodes_per_s > 0.0);
    assert!(status.rates.window > Duration::ZERO);
    assert_eq!(
        (status.throttled, status.throttled_for),
        (0, Duration::ZERO)
    );
    assert_eq!(learner.throttle("t"), Duration::ZERO, "no limit configured");
}

#[test]
fn the_message_rate_limit_is_per_actor_and_survives_reregistration() {
    let config = run(1000);
    let mut options = LearnerOptions::for_run(&config);
    options.max_actor_messages_per_second = Some(2.0);
    let learner = Learner::start(config.clone(), options).unwrap();
    learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap();
    learner
        .register(registration("b", ActorRole::Trainer))
        .unwrap();
    // A burst of 2, then the third waits (up to) half a second.
    assert_eq!(learner.throttle("a"), Duration::ZERO);
    assert_eq!(learner.throttle("a"), Duration::ZERO);
    let wait = learner.throttle("a");
    assert!(
        wait > Duration::ZERO && wait <= Duration::from_millis(500),
        "{wait:?}"
    );
    // Another actor has its own bucket; an unknown one is left to ingest to refuse.
    assert_eq!(learner.throttle("b"), Duration::ZERO);
    assert_eq!(learner.throttle("nobody"), Duration::ZERO);
    // Registering again does not refill the bucket.
    learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap();
    let again = learner.throttle("a");
    assert!(again > Duration::ZERO);
    let status = learner.status();
    assert_eq!(status.throttled, 2);
    assert_eq!(status.throttled_for, wait + again);

    let mut options = LearnerOptions::for_run(&config);
    options.max_actor_messages_per_second = Some(0.0);
    let e = Learner::start(config, options).unwrap_err();
    assert!(
        e.to_string().contains("max_actor_messages_per_second"),
        "{e}"
    );
}

/// A batch of `len` transitions at `level` whose `field` holds `value` everywhere.
fn batch_with(learner: &Learner, level: usize, field: &str, value: f32) -> IngestItem {
    let mut item = batch(learner, level, 8);
    if let IngestItem::Batch(b) = &mut item {
        let values = match field {
            "states" => &mut b.batch.states,
            "next_states" => &mut b.batch.next_states,
            "goals" => &mut b.batch.goals,
            "actions" => &mut b.batch.actions,
            _ => &mut b.batch.rewards,
        };
        values.fill(value);
    }
    item
}

#[test]
fn finite_but_impossible_values_are_refused_by_meaning() {
    // The poison batch of the robustness review (3e38 everywhere: finite, so it passed the
    // shape checks, and its first forward pass made every weight NaN) and its milder kin.
    let learner = start(100);
    let inc = learner
        .register(registration("hostile", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let cases = [
        (0, "states", 3e38),
        (0, "states", 1e30),
        (1, "next_states", -50.0),
        (0, "goals", 1e6),
        (1, "goals", 4.0),
        (0, "actions", 2.5),
        (1, "actions", -20.0),
        (0, "rewards", -1e20),
        (1, "rewards", -0.5),
    ];
    for (level, field, value) in cases {
        let e = learner
            .ingest(&msg(
                "hostile",
                inc,
                1,
                batch_with(&learner, level, field, value),
            ))
            .unwrap_err();
        assert!(matches!(e, IngestError::OutOfRange { .. }), "{field}: {e}");
        assert_eq!(e.reason(), RejectReason::OutOfRange);
        let text = e.to_string();
        assert!(
            text.contains("hostile") && text.contains(&format!("batch.{field}[0]")),
            "{text}"
        );
    }
    assert_eq!(
        rejected(&learner, RejectReason::OutOfRange),
        cases.len() as u64
    );
    assert_eq!(stored(&learner), 0);
    // Values at the edge of what the task produces pass, and sequence 1 was never used up.
    learner
        .ingest(&msg(
            "hostile",
            inc,
            1,
            batch_with(&learner, 0, "next_states", 1.0),
        ))
        .unwrap();
    learner
        .ingest(&msg(
            "hostile",
            inc,
            2,
            batch_with(&learner, 1, "rewards", -32.0),
        ))
        .unwrap();
    assert_eq!(stored(&learner), 16);
    learner.shutdown();
}

#[test]
fn an_episode_longer_than_the_budget_is_refused_and_counters_stay_exact() {
    let learner = start(100);
    let inc = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let long = IngestItem::Episode {
        env_steps: u64::MAX,
        success: false,
        weights_version: 1,
    };
    let e = learner.ingest(&msg("a", inc, 1, long)).unwrap_err();
    assert!(
        matches!(e, IngestError::EpisodeTooLong { max: 1000, .. }),
        "{e}"
    );
    learner.ingest(&msg("a", inc, 1, episode())).unwrap();
    let status = learner.status();
    assert_eq!((status.episodes, status.env_steps), (1, 10));
    assert_eq!(status.actors[0].env_steps, 10);
    learner.shutdown();
}

#[test]
fn trainers_report_evaluations_only_while_no_evaluator_is_registered() {
    let learner = start(100);
    let trainer = learner
        .register(registration("t", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let report = |id: &str, incarnation| Evaluation {
        actor_id: id.into(),
        incarnation,
        weights_version: 1,
        learner_start: 0,
        episodes: 10,
        successes: 10,
    };
    // Alone, a trainer evaluates itself (`--eval-every`).
    learner.report_evaluation(&report("t", trainer)).unwrap();
    let evaluator = learner
        .register(registration("e", ActorRole::Evaluator))
        .unwrap()
        .incarnation;
    let e = learner
        .report_evaluation(&report("t", trainer))
        .unwrap_err();
    assert!(matches!(e, IngestError::TrainerEvaluation(_)), "{e}");
    assert_eq!(e.reason(), RejectReason::WrongRole);
    assert_eq!(
        learner.curve().len(),
        1,
        "the refused report is not on the curve"
    );
    learner.report_evaluation(&report("e", evaluator)).unwrap();
    assert_eq!(learner.curve().len(), 2);
    learner.shutdown();
}

#[test]
fn a_learner_whose_updates_explode_publishes_only_finite_weights_and_says_why() {
    // A learning rate of 1e30 makes every update explode: each is undone, and after ten in a
    // row the learner reports trouble (servers go NOT_SERVING) instead of publishing NaN.
    let mut config = run(100);
    config.agent.critic_lr = 1e30;
    config.agent.actor_lr = 1e30;
    let options = LearnerOptions::for_run(&config);
    let learner = Learner::start(config, options).unwrap();
    let inc = learner
        .register(registration("a", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    let mut seq = 0;
    let mut send = |item| {
        seq += 1;
        learner.ingest(&msg("a", inc, seq, item)).unwrap();
    };
    for _ in 0..6 {
        let mut item = batch(&learner, 0, 8);
        if let IngestItem::Batch(b) = &mut item {
            // Varied inputs, so that gradients are not all zero.
            for (i, s) in b.batch.states.iter_mut().enumerate() {
                *s = ((i % 7) as f32 - 3.0) / 3.0;
            }
        }
        send(item);
        send(batch(&learner, 1, 8));
        send(episode());
    }
    let trouble = learner
        .trouble()
        .wait_for(Duration::from_secs(20), |t| t.is_some())
        .expect("trouble is reported");
    let why = (*trouble).clone().unwrap();
    assert!(why.contains("diverged and were undone"), "{why}");
    let status = learner.status();
    assert!(
        status.levels.iter().any(|l| l.diverged_in_a_row >= 10),
        "{status:?}"
    );
    let weights = learner.weights().latest().unwrap();
    for level in &weights.levels {
        let actor = hac_nn::ActorNet::from_safetensors(level).unwrap();
        assert!(actor.mlp().tensors().flatten().all(|v| v.is_finite()));
    }
    learner.shutdown();
}

#[test]
fn actors_not_heard_from_are_forgotten() {
    let config = run(100);
    let mut options = LearnerOptions::for_run(&config);
    options.forget_actors_after = Duration::from_millis(300);
    let learner = Learner::start(config, options).unwrap();
    for i in 0..200 {
        learner
            .register(registration(&format!("gone-{i}"), ActorRole::Trainer))
            .unwrap();
    }
    let alive = learner
        .register(registration("alive", ActorRole::Trainer))
        .unwrap()
        .incarnation;
    assert_eq!(learner.status().actors.len(), 201);
    for seq in 1..=4 {
        std::thread::sleep(Duration::from_millis(100));
        learner
            .ingest(&msg("alive", alive, seq, episode()))
            .unwrap();
    }
    let ids: Vec<String> = learner
        .status()
        .actors
        .into_iter()
        .map(|a| a.actor_id)
        .collect();
    assert_eq!(ids, ["alive"]);
    // A forgotten actor is unknown, and registers again.
    let e = learner.ingest(&msg("gone-0", 1, 1, episode())).unwrap_err();
    assert!(matches!(e, IngestError::UnknownActor(_)), "{e}");
    learner
        .register(registration("gone-0", ActorRole::Trainer))
        .unwrap();
    assert_eq!(learner.status().actors.len(), 2);
    learner.shutdown();
}
