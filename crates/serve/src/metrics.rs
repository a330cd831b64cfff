//! What the learner exposes to Prometheus ([`learner_metrics`]), in the exposition format and
//! with the naming conventions of [`hac_transport::metrics`], which also serves it over HTTP
//! ([`serve_metrics`](hac_transport::metrics::serve_metrics)).

use hac_learner::Learner;
use hac_transport::grpc::role_name;
use hac_transport::metrics::{Exposition, Kind};

/// The learner's metrics now.
pub fn learner_metrics(learner: &Learner) -> String {
    use Kind::{Counter, Gauge};
    let status = learner.status();
    let run = learner.run_config();
    let mut m = Exposition::new();
    let levels = run.levels.to_string();
    m.family(
        "hac_learner_info",
        Gauge,
        "The run this learner serves (always 1).",
    )
    .sample(
        "hac_learner_info",
        &[
            ("env", &run.env),
            ("levels", &levels),
            ("algo", run.algo.name()),
            ("run_config_digest", &status.run_config_digest),
        ],
        1.0,
    );
    m.single(
        "hac_learner_uptime_seconds",
        Gauge,
        "Seconds since the learner started.",
        status.uptime.as_secs_f64(),
    );
    m.single(
        "hac_learner_run_finished",
        Gauge,
        "1 once the run is over (the learner drains), else 0.",
        f64::from(u8::from(status.finished)),
    );
    m.single(
        "hac_learner_weights_version",
        Gauge,
        "The newest weights version published.",
        status.weights_version as f64,
    );
    m.single(
        "hac_learner_episode_budget",
        Gauge,
        "Training episodes the run is budgeted for.",
        run.episodes as f64,
    );
    for (name, help, value) in [
        (
            "hac_learner_ingest_messages_total",
            "Ingest messages that reached the learner core, valid or not.",
            status.messages,
        ),
        (
            "hac_learner_batches_ingested_total",
            "Transition batches stored.",
            status.batches,
        ),
        (
            "hac_learner_transitions_ingested_total",
            "Transitions stored, every level.",
            status.transitions,
        ),
        (
            "hac_learner_episodes_ingested_total",
            "Training episodes ingested.",
            status.episodes,
        ),
        (
            "hac_learner_episode_successes_total",
            "Training episodes ingested that reached their goal.",
            status.successes,
        ),
        (
            "hac_learner_env_steps_total",
            "Primitive environment steps of the training episodes ingested.",
            status.env_steps,
        ),
        (
            "hac_learner_duplicates_total",
            "Resent messages already stored, acknowledged and dropped.",
            status.duplicates,
        ),
        (
            "hac_learner_actor_rate_limit_waits_total",
            "Ingest messages held back by the per-actor message rate limit.",
            status.throttled,
        ),
        (
            "hac_learner_turns_granted_total",
            "Episode turns granted to trainers (--episodes-in-flight).",
            status.turns.granted,
        ),
        (
            "hac_learner_turns_expired_total",
            "Episode turns whose lease ran out before their episode arrived.",
            status.turns.expired,
        ),
    ] {
        m.single(name, Counter, help, value as f64);
    }
    m.single(
        "hac_learner_turns_waiting",
        Gauge,
        "Trainers waiting for an episode turn now.",
        status.turns.waiting as f64,
    );
    m.single(
        "hac_learner_actor_rate_limit_wait_seconds_total",
        Counter,
        "Time ingest streams were held back by the per-actor message rate limit.",
        status.throttled_for.as_secs_f64(),
    );
    m.family(
        "hac_learner_rejected_total",
        Counter,
        "Refused inputs by reason.",
    );
    for &(reason, count) in &status.rejected {
        m.sample(
            "hac_learner_rejected_total",
            &[("reason", reason.name())],
            count as f64,
        );
    }

    let level_names: Vec<String> = (0..status.levels.len()).map(|l| l.to_string()).collect();
    let per_level = |m: &mut Exposition,
                     name: &str,
                     kind: Kind,
                     help: &str,
                     f: &dyn Fn(usize) -> Option<f64>| {
        m.family(name, kind, help);
        for (level, label) in level_names.iter().enumerate() {
            if let Some(value) = f(level) {
                m.sample(name, &[("level", label)], value);
            }
        }
    };
    let levels = &status.levels;
    per_level(
        &mut m,
        "hac_learner_updates_total",
        Counter,
        "Updates done per level.",
        &|l| Some(levels[l].updates as f64),
    );
    m.family(
        "hac_learner_replay_size",
        Gauge,
        "Transitions stored in replay, per level and shard.",
    );
    for (level, l) in levels.iter().enumerate() {
        for (shard, &len) in l.shard_lens.iter().enumerate() {
            m.sample(
                "hac_learner_replay_size",
                &[
                    ("level", &level_names[level]),
                    ("shard", &shard.to_string()),
                ],
                len as f64,
            );
        }
    }
    per_level(
        &mut m,
        "hac_learner_replay_capacity",
        Gauge,
        "Transitions a level's replay holds at most.",
        &|l| Some(levels[l].replay_capacity as f64),
    );
    per_level(
        &mut m,
        "hac_learner_replay_inserted_total",
        Counter,
        "Transitions ever inserted into a level's replay.",
        &|l| Some(levels[l].transitions_inserted as f64),
    );
    per_level(
        &mut m,
        "hac_learner_critic_loss",
        Gauge,
        "The last update's critic loss (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.critic_loss)),
    );
    per_level(
        &mut m,
        "hac_learner_actor_loss",
        Gauge,
        "The last update's actor loss (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.actor_loss)),
    );
    per_level(
        &mut m,
        "hac_learner_mean_q",
        Gauge,
        "The last update's mean Q of the sampled batch (absent before the first update).",
        &|l| levels[l].last.map(|u| f64::from(u.mean_q)),
    );
    per_level(
        &mut m,
        "hac_learner_update_deficit",
        Gauge,
        "Updates owed to the episodes ingested (rate limiter).",
        &|l| Some(levels[l].limiter.deficit),
    );
    per_level(
        &mut m,
        "hac_learner_trainer_wait_seconds_total",
        Counter,
        "Time the level's trainer waited for an update to be owed.",
        &|l| Some(levels[l].limiter.trainer_blocked.as_secs_f64()),
    );
    per_level(
        &mut m,
        "hac_learner_ingest_waits_total",
        Counter,
        "Ingest admission checks that found no room (backpressure).",
        &|l| Some(levels[l].limiter.ingest_refused as f64),
    );
    per_level(
        &mut m,
        "hac_learner_diverged_updates_total",
        Counter,
        "Updates undone because they diverged (non-finite or exploding loss or weights).",
        &|l| Some(levels[l].diverged_updates as f64),
    );
    per_level(
        &mut m,
        "hac_learner_ingest_wait_seconds_total",
        Counter,
        "Time ingest waited for room (backpressure).",
        &|l| Some(levels[l].limiter.ingest_blocked.as_secs_f64()),
    );

    m.family("hac_learner_actors", Gauge, "Registered actors by role.");
    for role in [
        hac_proto::ActorRole::Trainer,
        hac_proto::ActorRole::Evaluator,
    ] {
        let n = status.actors.iter().filter(|a| a.role == role).count();
        m.sample("hac_learner_actors", &[("role", role_name(role))], n as f64);
    }
    type ActorField = fn(&hac_learner::RegisteredActor) -> f64;
    let actor_families: [(&str, Kind, &str, ActorField); 6] = [
        (
            "hac_learner_actor_episodes_total",
            Counter,
            "Training episodes ingested from an actor's current incarnation.",
            |a| a.episodes as f64,
        ),
        (
            "hac_learner_actor_env_steps_total",
            Counter,
            "Environment steps ingested from an actor's current incarnation.",
            |a| a.env_steps as f64,
        ),
        (
            "hac_learner_actor_transitions_total",
            Counter,
            "Transitions stored from an actor's current incarnation.",
            |a| a.transitions as f64,
        ),
        (
            "hac_learner_actor_last_seen_seconds",
            Gauge,
            "Seconds since the learner last heard from an actor.",
            |a| a.last_seen_ago.as_secs_f64(),
        ),
        (
            "hac_learner_actor_weights_lag",
            Gauge,
            "Weights versions an actor is behind the newest.",
            |a| a.weights_lag as f64,
        ),
        (
            "hac_learner_actor_undurable_messages",
            Gauge,
            "Messages of an actor stored (acknowledged) and not yet durable in the write-ahead log.",
            |a| a.stored_through.saturating_sub(a.durable_through) as f64,
        ),
    ];
    for (name, kind, help, field) in actor_families {
        m.family(name, kind, help);
        for a in &status.actors {
            m.sample(
                name,
                &[("actor", &a.actor_id), ("role", role_name(a.role))],
                field(a),
            );
        }
    }

    let (evaluations, last) = learner.recent_curve(1);
    if let Some(wal) = &status.wal {
        m.single(
            "hac_learner_wal_bytes",
            Gauge,
            "Bytes of the write-ahead log on disk (what came after the newest checkpoint).",
            wal.bytes as f64,
        );
        m.single(
            "hac_learner_wal_commits_total",
            Counter,
            "Commits (fsyncs) of the write-ahead log.",
            wal.commits as f64,
        );
        m.single(
            "hac_learner_wal_undurable_records",
            Gauge,
            "Records appended to the write-ahead log and not yet committed.",
            wal.appended.saturating_sub(wal.committed) as f64,
        );
    }
    m.single(
        "hac_learner_evaluations_total",
        Counter,
        "Evaluations (greedy test rounds) on the learning curve.",
        evaluations as f64,
    );
    if let Some(last) = last.first() {
        m.single(
            "hac_learner_last_evaluation_success_ratio",
            Gauge,
            "Success rate of the latest evaluation, 0 to 1.",
            f64::from(last.success_rate),
        );
        m.single(
            "hac_learner_last_evaluation_episodes",
            Gauge,
            "Training episodes the latest evaluated weights were trained on.",
            last.episodes as f64,
        );
    }
    m.finish()
}
