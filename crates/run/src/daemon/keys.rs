//! The keys of the daemons' tables, generated from their clap definitions; do not edit. The
//! `hac` binary links both daemons and checks both tables against their definitions; a daemon's
//! own binary checks the other daemon's table against this list. `cargo test -p hac-cli --test
//! integration config::` fails while the list is out of date; `HAC_BLESS=1` on that command rewrites it.

/// `[learner]`.
pub const LEARNER: &[&str] = &[
    "algo",
    "listen",
    "out",
    "overwrite",
    "max_message_bytes",
    "max_batch_transitions",
    "publish_every_updates",
    "max_weights_lag",
    "episodes_in_flight",
    "turn_lease",
    "forget_actors_after",
    "error_buffer_episodes",
    "learner_threads",
    "grace_period",
    "drain_timeout",
    "metrics_listen",
    "max_actor_messages_per_second",
    "token_file",
    "tls_cert",
    "tls_key",
    "checkpoint_every",
    "keep_checkpoints",
    "checkpoint_replay",
    "resume",
    "durable_interval",
    "shm",
    "shm_max_actors",
    "shm_window",
];

/// `[actor]`.
pub const ACTOR: &[&str] = &[
    "learner",
    "id",
    "role",
    "eval_every",
    "max_episodes",
    "batch_transitions",
    "window",
    "lockstep",
    "weights_timeout",
    "give_up_after",
    "flush_timeout",
    "status_listen",
    "metrics_listen",
    "token_file",
    "tls_ca",
    "tls_domain",
    "tls_cert",
    "tls_key",
    "transport",
    "shm_overflow",
];
