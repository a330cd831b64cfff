//! Durable acknowledgements in the learner core: a learner with a write-ahead log, killed (its
//! log stopped without committing what waited for the next commit, as `kill -9` would) and
//! resumed from its checkpoint and log, has exactly what it said was durable, recognises its
//! actors' incarnations, and stores their resends of everything after their durable watermark
//! once.

use std::path::PathBuf;
use std::time::Duration;

use hac_agent::RunConfig;
use hac_core::{Batch, Rng};
use hac_learner::{Learner, LearnerCheckpoint, LearnerOptions, Stored, WalOptions};
use hac_proto::{
    ActorRole, DecodedBatch, IngestItem, IngestMessage, PreviousIncarnation, Registration,
};

use crate::common;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hac-durable-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// A log committed only when the test says so (`sync_wal`), so that what is durable at the
/// "kill" is exactly known.
fn options(run: &RunConfig, dir: &std::path::Path) -> LearnerOptions {
    LearnerOptions {
        wal: Some(WalOptions {
            commit_bytes: usize::MAX,
            max_pending_bytes: usize::MAX,
            ..WalOptions::new(dir.join("wal"), Duration::from_secs(3600))
        }),
        ..LearnerOptions::for_run(run)
    }
}

fn registration(id: &str) -> Registration {
    Registration {
        actor_id: id.into(),
        role: ActorRole::Trainer,
        hostname: "localhost".into(),
        transports: vec!["test".into()],
    }
}

/// An actor's messages, by sequence (index 0 is sequence 1): per episode a batch of `len`
/// transitions per level and the episode's end, with seeded values.
fn messages(learner: &Learner, episodes: usize, seed: u64) -> Vec<IngestItem> {
    let mut data = Rng::seed_from(seed);
    let mut items = Vec::new();
    for episode in 0..episodes {
        let len = 3 + episode % 4;
        for level in 0..learner.dims().len() {
            let mut batch = Batch::zeros(learner.dims()[level], len);
            for field in [
                &mut batch.states,
                &mut batch.next_states,
                &mut batch.goals,
                &mut batch.actions,
            ] {
                field.iter_mut().for_each(|v| *v = data.uniform(-1.0, 1.0));
            }
            batch
                .rewards
                .iter_mut()
                .for_each(|r| *r = if data.unit() < 0.5 { 0.0 } else { -1.0 });
            items.push(IngestItem::Batch(DecodedBatch {
                level,
                weights_version: 1,
                batch,
            }));
        }
        items.push(IngestItem::Episode {
            env_steps: len as u64,
            success: episode % 3 == 0,
            weights_version: 1,
        });
    }
    items
}

fn transitions(items: &[IngestItem]) -> u64 {
    items
        .iter()
        .map(|i| match i {
            IngestItem::Batch(b) => b.batch.len as u64,
            IngestItem::Episode { .. } => 0,
        })
        .sum()
}

fn episodes(items: &[IngestItem]) -> u64 {
    items
        .iter()
        .filter(|i| matches!(i, IngestItem::Episode { .. }))
        .count() as u64
}

/// Sends sequences `from..=to` of `items` as `actor`'s `incarnation`.
fn send(
    learner: &Learner,
    actor: &str,
    incarnation: u64,
    items: &[IngestItem],
    from: u64,
    to: u64,
) -> Vec<Stored> {
    (from..=to)
        .map(|sequence| {
            learner
                .ingest(&IngestMessage {
                    actor_id: actor.into(),
                    incarnation,
                    sequence,
                    item: items[sequence as usize - 1].clone(),
                })
                .unwrap()
        })
        .collect()
}

fn stored_through(learner: &Learner, actor: &str) -> (u64, u64, u64) {
    let status = learner.status();
    let a = status.actors.iter().find(|a| a.actor_id == actor).unwrap();
    (a.incarnation, a.stored_through, a.durable_through)
}

/// The counters and replay of `learner` hold exactly the messages `a[..a_through]` and
/// `b[..b_through]`, each once.
fn holds_exactly(learner: &Learner, a: &[IngestItem], b: &[IngestItem]) {
    let status = learner.status();
    assert_eq!(status.transitions, transitions(a) + transitions(b));
    assert_eq!(status.episodes, episodes(a) + episodes(b));
    assert_eq!(
        status.batches,
        (a.len() + b.len()) as u64 - episodes(a) - episodes(b)
    );
    let inserted: u64 = status.levels.iter().map(|l| l.transitions_inserted).sum();
    assert_eq!(
        inserted, status.transitions,
        "replay holds each transition once"
    );
}

#[test]
fn a_killed_learner_resumes_with_everything_durable_and_stores_resends_once() {
    let dir = scratch("resume");
    let run = common::small_run(1000, 2);
    let first = Learner::start(run.clone(), options(&run, &dir)).unwrap();
    let a_items = messages(&first, 12, 1);
    let b_items = messages(&first, 6, 2);
    let a = first.register(registration("a")).unwrap().incarnation;
    let b = first.register(registration("b")).unwrap().incarnation;

    // Before the checkpoint, between it and the last commit, and after the last commit.
    send(&first, "a", a, &a_items, 1, 12);
    send(&first, "b", b, &b_items, 1, 6);
    let checkpoint = first.checkpoint(true).unwrap();
    let checkpoint = LearnerCheckpoint::from_files(&checkpoint.to_files().into_iter().collect())
        .expect("the checkpoint reads back");
    assert!(checkpoint.wal_lsn() > 0);
    send(&first, "a", a, &a_items, 13, 24);
    send(&first, "b", b, &b_items, 7, 12);
    assert!(first.sync_wal(Duration::from_secs(10)));
    assert_eq!(stored_through(&first, "a"), (a, 24, 24));
    send(&first, "a", a, &a_items, 25, 30);
    send(&first, "b", b, &b_items, 13, 15);
    // Acknowledged, not durable.
    assert_eq!(stored_through(&first, "a"), (a, 30, 24));
    assert_eq!(stored_through(&first, "b"), (b, 15, 12));
    first.simulate_crash();
    drop(first.shutdown());

    let second = Learner::resume(run.clone(), options(&run, &dir), &checkpoint).unwrap();
    // Exactly what was durable: nothing lost, nothing twice.
    holds_exactly(&second, &a_items[..24], &b_items[..12]);
    assert_eq!(stored_through(&second, "a"), (a, 24, 24));
    assert_eq!(stored_through(&second, "b"), (b, 12, 12));

    // The actors register again naming their incarnations and resend what is not durable for
    // them: b from its watermark, a from a little before (an ack it missed), as links do.
    let previous = |incarnation, resend_from| {
        Some(PreviousIncarnation {
            incarnation,
            resend_from,
        })
    };
    let again = second.register_again(registration("a"), previous(a, 23));
    assert_eq!(again.unwrap().incarnation, a, "the incarnation is kept");
    let again = second.register_again(registration("b"), previous(b, 13));
    assert_eq!(again.unwrap().incarnation, b);
    let stored = send(&second, "a", a, &a_items, 23, 30);
    assert_eq!(stored[..2], [Stored::Duplicate, Stored::Duplicate]);
    assert!(stored[2..].iter().all(|s| *s == Stored::New));
    send(&second, "b", b, &b_items, 13, 15);
    holds_exactly(&second, &a_items[..30], &b_items[..15]);
    assert_eq!(second.status().duplicates, 2);

    // Killed again without a new checkpoint: the log holds both processes' records after the
    // checkpoint's cut, in one sequence.
    assert!(second.sync_wal(Duration::from_secs(10)));
    send(&second, "a", a, &a_items, 31, 33);
    second.simulate_crash();
    drop(second.shutdown());
    let third = Learner::resume(run.clone(), options(&run, &dir), &checkpoint).unwrap();
    holds_exactly(&third, &a_items[..30], &b_items[..15]);
    assert_eq!(stored_through(&third, "a"), (a, 30, 30));

    // An actor that holds nothing before a sequence the learner lacks is not kept: a fresh
    // incarnation above the one it named, numbered from 1 again.
    let fresh = third
        .register_again(registration("b"), previous(b, 40))
        .unwrap();
    assert!(fresh.incarnation > a.max(b), "{}", fresh.incarnation);
    third.finish("test over");
    drop(third.shutdown());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_learner_killed_before_its_first_checkpoint_starts_from_its_log() {
    let dir = scratch("no-checkpoint");
    let run = common::small_run(1000, 1);
    let first = Learner::start(run.clone(), options(&run, &dir)).unwrap();
    let items = messages(&first, 5, 3);
    let a = first.register(registration("a")).unwrap().incarnation;
    send(&first, "a", a, &items, 1, 10);
    assert!(first.sync_wal(Duration::from_secs(10)));
    send(&first, "a", a, &items, 11, 15);
    first.simulate_crash();
    drop(first.shutdown());

    let second = Learner::start(run.clone(), options(&run, &dir)).unwrap();
    holds_exactly(&second, &items[..10], &[]);
    assert_eq!(stored_through(&second, "a"), (a, 10, 10));
    // A newcomer never gets an incarnation the log holds.
    let b = second.register(registration("b")).unwrap().incarnation;
    assert!(b > a);
    second.finish("test over");
    drop(second.shutdown());
    let _ = std::fs::remove_dir_all(&dir);
}
