//! Fixtures shared by the serving tests: a mountain-car run, valid ingest items, a gRPC link's
//! quick-retry options, a loopback address and a small runtime. Each test binary uses some.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::time::Duration;

use hac_agent::RunConfig;
use hac_core::Batch;
use hac_learner::{Learner, RejectReason};
use hac_proto::{DecodedBatch, IngestItem};
use hac_transport::grpc::GrpcLinkOptions;

/// Mountain-car, 2 levels, 2 replay shards, 1000 episodes, 2 test episodes per round.
pub fn run_config() -> RunConfig {
    let mut agent = hac_envs::make("mountain-car").unwrap().default_config(2);
    agent.test_episodes = 2;
    RunConfig {
        env: "mountain-car".into(),
        levels: 2,
        seed: 0,
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

/// An episode summary of 10 steps, not a success.
pub fn episode() -> IngestItem {
    IngestItem::Episode {
        env_steps: 10,
        success: false,
        weights_version: 1,
    }
}

/// A valid batch of `len` transitions for `level`.
pub fn batch_item(learner: &Learner, level: usize, len: usize) -> IngestItem {
    let mut batch = Batch::zeros(learner.dims()[level], len);
    batch.rewards.fill(-1.0);
    IngestItem::Batch(DecodedBatch {
        level,
        weights_version: 1,
        batch,
    })
}

/// A gRPC link that retries quickly and gives up after 30 s.
pub fn link_options() -> GrpcLinkOptions {
    GrpcLinkOptions {
        backoff_min: Duration::from_millis(20),
        backoff_max: Duration::from_millis(200),
        give_up_after: Duration::from_secs(30),
        jitter_seed: 7,
        ..GrpcLinkOptions::default()
    }
}

/// Any free loopback port.
pub fn localhost() -> SocketAddr {
    ([127, 0, 0, 1], 0).into()
}

/// A multi-threaded runtime with one worker.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap()
}

/// How many messages the learner refused for `reason`.
pub fn rejected(learner: &Learner, reason: RejectReason) -> u64 {
    learner
        .status()
        .rejected
        .iter()
        .find(|(r, _)| *r == reason)
        .map_or(0, |&(_, n)| n)
}
