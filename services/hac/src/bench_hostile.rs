//! `hac bench hostile`: a learner under attack, measured from outside.
//!
//! A real `hac learner` child process (this binary, on an ephemeral loopback port) serves honest
//! `hac actor` child processes while hostile clients, built from the wire contract alone (raw
//! protobuf bytes over tonic), send it what an attacker or a broken client would: the poison
//! batch (every value 3e38), NaN and infinity, values outside the task's boxes, impossible
//! rewards and terminals, wrong levels and shapes, oversized batches and strings, ids with
//! control characters, stale
//! incarnations, unknown actors, sequence gaps, duplicates, undecodable bytes on every RPC,
//! evaluations from trainers, weights watches from strangers, and byte-level mutations of valid
//! messages. Each input's answer (OK, or the refusal's reason) is tallied per kind against what
//! the kind must get. Meanwhile a watcher checks every published weights version for non-finite
//! values, and the learner's resident memory is sampled every second.
//!
//! Two modes:
//! - **attack** (the default): 2 honest trainers and an evaluator train the task to `--stop-at`
//!   while `--clients` hostile clients attack for up to `--seconds`; the report says whether and
//!   when the run reached the target.
//! - **fuzz** (`--inputs N`): honest trainers keep the learner training while the hostile
//!   clients send N inputs; then the trainers stop, the ingest throughput of an honest gRPC
//!   sender is measured on the same learner for `--throughput-seconds`, and the learner is
//!   stopped with SIGTERM. The trainers run `--lockstep` (each episode waits for the updates it
//!   earned): free-running trainers keep ingest at the rate limiter's bound, where every ingest
//!   message, hostile ones too, waits for training to catch up, and the inputs would crawl.
//!
//! Either way the learner must never crash, never publish a non-finite weight, and account for
//! every ingest message exactly once (stored, duplicate, or refused).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use hac_core::Rng;
use hac_proto::pb;
use hac_transport::grpc::REJECT_REASON_KEY;
use prost::Message as _;
use prost::bytes::{Buf as _, BufMut as _};
use serde::Serialize;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::codegen::http::uri::PathAndQuery;
use tonic::transport::Channel;

use crate::bench_connections::{LearnerProcess, read_status};
use crate::bench_grpc::{client, register};

/// `hac bench hostile` settings.
#[derive(Debug, Clone)]
pub struct HostileBench {
    pub env: String,
    pub levels: usize,
    pub seed: u64,
    /// Attack mode: the success rate the run must reach; its episode budget.
    pub stop_at: f64,
    pub episodes: u64,
    /// Attack mode: the longest attack (the attack also ends when the run does).
    pub seconds: f64,
    /// Fuzz mode: hostile inputs in all.
    pub inputs: Option<u64>,
    /// Concurrent hostile clients, each with its own connection and registered identity.
    pub clients: usize,
    /// Honest trainer processes.
    pub trainers: usize,
    /// Fuzz mode: seconds of the honest throughput measurement after the inputs.
    pub throughput_seconds: f64,
    /// Where the learner's run directory and the logs go (kept); a temporary directory
    /// (removed) if not given.
    pub dir: Option<PathBuf>,
    pub json: bool,
}

/// What a kind of input must get.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Expect {
    Refused,
    Accepted,
    /// Byte-level mutations and in-box noise: either answer is right, but never an internal
    /// error or a dropped connection.
    Either,
}

/// The hostile inputs, each one request (an ingest stream carries one message).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
enum Kind {
    /// A batch whose every value is 3e38: finite, impossible.
    Poison,
    /// One NaN or infinity among plausible values.
    NotFinite,
    /// States far outside the task's box.
    OutOfBox,
    /// A reward no level can produce.
    BadReward,
    /// A terminal flag other than 0 and 1.
    BadTerminal,
    /// A level the run does not have.
    WrongLevel,
    /// A field one value short of its count.
    WrongShape,
    /// More transitions than the learner's batch limit.
    Oversized,
    /// An episode summary claiming u64::MAX environment steps.
    HugeEpisode,
    /// The previous incarnation of a registered identity.
    StaleIncarnation,
    /// An identity never registered.
    UnknownActor,
    /// A sequence number ahead of the next expected.
    SequenceGap,
    /// A 64 KiB actor id.
    LongId,
    /// A resend of an acknowledged message: acknowledged as a duplicate, not stored again.
    Duplicate,
    /// A batch of small in-box values from a registered trainer: indistinguishable from a bad
    /// policy's data.
    InBoxNoise,
    /// A valid ingest message with random bytes changed, cut off or appended.
    MutatedIngest,
    /// Undecodable bytes to each unary and server-streaming RPC.
    GarbageUnary,
    /// A valid unary request with random bytes changed.
    MutatedUnary,
    /// Registration with a 64 KiB host name.
    LongHostname,
    /// Registration with a newline and a forged log line in the actor id.
    ControlCharacterId,
    /// A fresh identity registered (accepted: the registry is pruned of silent actors).
    NewIdentity,
    /// An evaluation reported by a trainer.
    EvaluationFromTrainer,
    /// An evaluation claiming more successes than episodes.
    ImpossibleEvaluation,
    /// A turn asked for by an identity never registered.
    TurnFromStranger,
    /// A weights watch by an identity never registered.
    WatchFromStranger,
    /// GetStatus, as any client may.
    Status,
}

impl Kind {
    const ALL: [Kind; 26] = [
        Kind::Poison,
        Kind::NotFinite,
        Kind::OutOfBox,
        Kind::BadReward,
        Kind::BadTerminal,
        Kind::WrongLevel,
        Kind::WrongShape,
        Kind::Oversized,
        Kind::HugeEpisode,
        Kind::StaleIncarnation,
        Kind::UnknownActor,
        Kind::SequenceGap,
        Kind::LongId,
        Kind::Duplicate,
        Kind::InBoxNoise,
        Kind::MutatedIngest,
        Kind::GarbageUnary,
        Kind::MutatedUnary,
        Kind::LongHostname,
        Kind::ControlCharacterId,
        Kind::NewIdentity,
        Kind::EvaluationFromTrainer,
        Kind::ImpossibleEvaluation,
        Kind::TurnFromStranger,
        Kind::WatchFromStranger,
        Kind::Status,
    ];

    fn expect(self) -> Expect {
        match self {
            Kind::Duplicate | Kind::NewIdentity | Kind::Status => Expect::Accepted,
            Kind::InBoxNoise | Kind::MutatedIngest | Kind::MutatedUnary => Expect::Either,
            _ => Expect::Refused,
        }
    }

    fn name(self) -> String {
        serde_json::to_value(self)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default()
    }
}

/// Answers to one kind of input.
#[derive(Debug, Clone, Default, Serialize)]
pub struct KindReport {
    pub kind: String,
    pub sent: u64,
    /// By answer: `ok`, or the refusal's reason (its gRPC code where it names none).
    pub answers: BTreeMap<String, u64>,
    /// Answers the kind must not get: OK where a refusal is due or the other way round, and any
    /// internal error, unknown error or dropped connection.
    pub wrong: u64,
}

/// One reading of the learner's memory.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MemorySample {
    pub at_s: f64,
    pub rss_kib: u64,
}

/// `hac bench hostile` result.
#[derive(Debug, Clone, Serialize)]
pub struct HostileReport {
    pub mode: &'static str,
    pub env: String,
    pub levels: usize,
    pub seed: u64,
    pub trainers: usize,
    pub clients: usize,
    pub hostile_inputs: u64,
    pub hostile_seconds: f64,
    pub hostile_inputs_per_s: f64,
    pub kinds: Vec<KindReport>,
    pub wrong_answers: u64,
    /// The learner exited by itself with success (attack mode), or on SIGTERM (fuzz mode).
    pub learner_exit: String,
    pub learner_crashed: bool,
    pub weights_versions_checked: u64,
    pub weights_non_finite: u64,
    pub diverged_updates: u64,
    pub peak_rss_kib: u64,
    pub first_rss_kib: u64,
    pub last_rss_kib: u64,
    pub memory: Vec<MemorySample>,
    /// Attack mode: the target, the best test round, and when it was first reached.
    pub stop_at: Option<f64>,
    pub best_success: Option<f64>,
    pub episodes_to_90: Option<u64>,
    pub episodes: u64,
    pub wall_time_s: f64,
    /// Fuzz mode: an honest sender's gRPC ingest rate after the inputs.
    pub throughput_transitions_per_s: Option<f64>,
    /// Ingest messages that reached the learner core; messages stored; duplicates.
    pub messages: u64,
    pub stored: u64,
    pub duplicates: u64,
    /// Refusals by reason, on every RPC.
    pub refused: BTreeMap<String, u64>,
    pub accounts: Vec<Account>,
    pub exactly_once: bool,
}

/// Bytes as they are, both ways: requests no protobuf encoder would make, answers undecoded.
#[derive(Debug, Clone, Copy, Default)]
struct Raw;

impl Codec for Raw {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = Raw;
    type Decoder = Raw;

    fn encoder(&mut self) -> Raw {
        Raw
    }

    fn decoder(&mut self) -> Raw {
        Raw
    }
}

impl Encoder for Raw {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), tonic::Status> {
        dst.put_slice(&item);
        Ok(())
    }
}

impl Decoder for Raw {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
        let bytes = src.copy_to_bytes(src.remaining());
        Ok(Some(bytes.to_vec()))
    }
}

/// What a hostile client learned at registration.
#[derive(Debug, Clone)]
struct Run {
    dims: Vec<pb::LevelDims>,
    max_batch: usize,
}

/// The answer to one input: `Ok` or the refusal.
type Answer = Result<(), tonic::Status>;

/// One hostile client: its connection, its registered trainer identity and that identity's
/// sequence numbering.
struct Hostile {
    grpc: tonic::client::Grpc<Channel>,
    id: String,
    incarnation: u64,
    /// The next sequence the learner expects from this identity.
    next: u64,
    run: Run,
    rng: Rng,
    strangers: u64,
    account: Account,
}

/// What one hostile identity had stored, by its own count of the acknowledgements it got.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Account {
    pub actor_id: String,
    /// Messages stored (the last sequence acknowledged as new), their transitions, and resends
    /// acknowledged as duplicates.
    pub stored_through: u64,
    pub transitions: u64,
    pub duplicates: u64,
    /// The learner's status for the identity at the end: its counts must be these.
    pub learner_stored_through: u64,
    pub learner_transitions: u64,
    pub learner_duplicates: u64,
}

/// A registration of `actor_id` in `role` over gRPC.
fn registration(actor_id: String, role: pb::ActorRole) -> pb::RegisterRequest {
    pb::RegisterRequest {
        actor_id,
        role: role.into(),
        transports: vec!["grpc".into()],
        ..Default::default()
    }
}

/// A batch of `count` level-`level` transitions of values within `+-scale`, rewards -1, none
/// terminal.
fn random_batch(
    rng: &mut Rng,
    dims: pb::LevelDims,
    level: usize,
    count: usize,
    scale: f32,
) -> pb::TransitionBatch {
    let mut values = |n: u32| -> Vec<f32> {
        (0..n as usize * count)
            .map(|_| rng.uniform(-scale, scale))
            .collect()
    };
    pb::TransitionBatch {
        level: level as u32,
        weights_version: 1,
        count: count as u32,
        states: values(dims.state),
        actions: values(dims.action),
        rewards: vec![-1.0; count],
        next_states: values(dims.state),
        goals: values(dims.goal),
        terminals: vec![0; count],
        extra: Vec::new(),
    }
}

const INGEST: &str = "/hac.v1.Learner/Ingest";
const UNARY: [&str; 6] = [
    "/hac.v1.Learner/Register",
    "/hac.v1.Learner/WatchWeights",
    "/hac.v1.Learner/ReportEvaluation",
    "/hac.v1.Learner/AwaitTurn",
    "/hac.v1.Status/GetStatus",
    "/hac.v1.Status/WatchStatus",
];

impl Hostile {
    async fn connect(url: &str, index: usize, seed: u64) -> Result<Self> {
        let channel = Channel::from_shared(url.to_string())?
            .connect()
            .await
            .with_context(|| format!("connecting to {url}"))?;
        let mut typed = pb::learner_client::LearnerClient::new(channel.clone());
        let id = format!("hostile-{index}");
        let response = typed
            .register(registration(id.clone(), pb::ActorRole::Trainer))
            .await
            .context("registering a hostile client")?
            .into_inner();
        let grpc = tonic::client::Grpc::new(channel)
            .max_decoding_message_size(64 << 20)
            .max_encoding_message_size(64 << 20);
        Ok(Self {
            grpc,
            id: id.clone(),
            incarnation: response.incarnation,
            next: 1,
            run: Run {
                dims: response.levels,
                max_batch: response.max_batch_transitions as usize,
            },
            rng: Rng::seed_from(seed ^ (index as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)),
            strangers: 0,
            account: Account {
                actor_id: id,
                ..Account::default()
            },
        })
    }

    /// Sends one input of `kind`; its answer.
    async fn send(&mut self, kind: Kind) -> Result<Answer> {
        match kind {
            Kind::Poison => {
                let mut batch = self.batch(0.1);
                for field in [
                    &mut batch.states,
                    &mut batch.actions,
                    &mut batch.rewards,
                    &mut batch.next_states,
                    &mut batch.goals,
                ] {
                    field.fill(3e38);
                }
                self.ingest_batch(batch).await
            }
            Kind::NotFinite => {
                let mut batch = self.batch(0.1);
                let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY][self.rng.below(3)];
                let i = self.rng.below(batch.states.len());
                batch.states[i] = bad;
                self.ingest_batch(batch).await
            }
            Kind::OutOfBox => {
                let mut batch = self.batch(0.1);
                let i = self.rng.below(batch.next_states.len());
                batch.next_states[i] = 1e6;
                self.ingest_batch(batch).await
            }
            Kind::BadReward => {
                let mut batch = self.batch(0.1);
                batch.rewards[0] = 0.5;
                self.ingest_batch(batch).await
            }
            Kind::BadTerminal => {
                let mut batch = self.batch(0.1);
                batch.terminals[0] = 2 + self.rng.below(200) as u8;
                self.ingest_batch(batch).await
            }
            Kind::WrongLevel => {
                let mut batch = self.batch(0.1);
                batch.level = self.run.dims.len() as u32 + self.rng.below(1000) as u32;
                self.ingest_batch(batch).await
            }
            Kind::WrongShape => {
                let mut batch = self.batch(0.1);
                match self.rng.below(3) {
                    0 => batch.states.pop(),
                    1 => batch.goals.pop(),
                    _ => batch.rewards.pop(),
                };
                self.ingest_batch(batch).await
            }
            Kind::Oversized => {
                let count = self.run.max_batch + 1 + self.rng.below(64);
                let batch = self.batch_of(0, count, 0.1);
                self.ingest_batch(batch).await
            }
            Kind::HugeEpisode => {
                let item = pb::ingest_request::Item::Episode(pb::EpisodeSummary {
                    env_steps: u64::MAX,
                    success: true,
                    weights_version: 1,
                });
                let request = self.request(self.next, item);
                self.ingest(request.encode_to_vec()).await
            }
            Kind::StaleIncarnation => {
                let batch = self.batch(0.1);
                let mut request = self.request(self.next, pb::ingest_request::Item::Batch(batch));
                request.incarnation = self.incarnation.saturating_sub(1);
                self.ingest(request.encode_to_vec()).await
            }
            Kind::UnknownActor => {
                let batch = self.batch(0.1);
                let mut request = self.request(1, pb::ingest_request::Item::Batch(batch));
                request.actor_id = self.stranger();
                self.ingest(request.encode_to_vec()).await
            }
            Kind::SequenceGap => {
                let batch = self.batch(0.1);
                let sequence = self.next + 2 + self.rng.below(1000) as u64;
                let request = self.request(sequence, pb::ingest_request::Item::Batch(batch));
                self.ingest(request.encode_to_vec()).await
            }
            Kind::LongId => {
                let batch = self.batch(0.1);
                let mut request = self.request(1, pb::ingest_request::Item::Batch(batch));
                request.actor_id = "x".repeat(64 << 10);
                self.ingest(request.encode_to_vec()).await
            }
            Kind::Duplicate => {
                if self.next == 1 {
                    // Nothing acknowledged yet to resend: store one first.
                    let batch = self.batch(0.1);
                    let answer = self.ingest_batch(batch).await?;
                    if answer.is_err() {
                        return Ok(answer);
                    }
                }
                let sequence = 1 + self.rng.below((self.next - 1) as usize) as u64;
                let batch = self.batch(0.1);
                let request = self.request(sequence, pb::ingest_request::Item::Batch(batch));
                self.ingest(request.encode_to_vec()).await
            }
            Kind::InBoxNoise => {
                let batch = self.batch(0.3);
                self.ingest_batch(batch).await
            }
            Kind::MutatedIngest => {
                let batch = self.batch(0.1);
                let request = self.request(self.next, pb::ingest_request::Item::Batch(batch));
                let mut bytes = request.encode_to_vec();
                self.mutate(&mut bytes);
                self.ingest(bytes).await
            }
            Kind::GarbageUnary => {
                let path = UNARY[self.rng.below(UNARY.len())];
                let len = 1 + self.rng.below(256);
                let bytes: Vec<u8> = (0..len).map(|_| self.rng.next_u64() as u8 | 0x07).collect();
                self.unary(path, bytes).await
            }
            Kind::MutatedUnary => {
                let i = self.rng.below(UNARY.len());
                let mut bytes = self.valid_unary(i);
                self.mutate(&mut bytes);
                self.unary(UNARY[i], bytes).await
            }
            Kind::LongHostname => {
                let request = pb::RegisterRequest {
                    hostname: "h".repeat(64 << 10),
                    ..registration(self.stranger(), pb::ActorRole::Trainer)
                };
                self.unary(UNARY[0], request.encode_to_vec()).await
            }
            Kind::ControlCharacterId => {
                let id = format!(
                    "{}\n2026-01-01T00:00:00Z  INFO hac_learner: run finished",
                    self.stranger()
                );
                let request = registration(id, pb::ActorRole::Trainer);
                self.unary(UNARY[0], request.encode_to_vec()).await
            }
            Kind::NewIdentity => {
                let request = registration(self.stranger(), pb::ActorRole::Trainer);
                self.unary(UNARY[0], request.encode_to_vec()).await
            }
            Kind::EvaluationFromTrainer => {
                let report = self.evaluation(10, 10);
                self.unary(UNARY[2], report.encode_to_vec()).await
            }
            Kind::ImpossibleEvaluation => {
                let report = self.evaluation(1, 1000);
                self.unary(UNARY[2], report.encode_to_vec()).await
            }
            Kind::TurnFromStranger => {
                let request = pb::TurnRequest {
                    actor_id: self.stranger(),
                    incarnation: 1,
                    wait_ms: u32::MAX,
                };
                self.unary(UNARY[3], request.encode_to_vec()).await
            }
            Kind::WatchFromStranger => {
                let request = pb::WatchWeightsRequest {
                    actor_id: self.stranger(),
                    incarnation: 1,
                    min_version: 0,
                };
                self.unary(UNARY[1], request.encode_to_vec()).await
            }
            Kind::Status => {
                let request = pb::GetStatusRequest {
                    max_evaluations: self.rng.below(4) as u32,
                };
                self.unary(UNARY[4], request.encode_to_vec()).await
            }
        }
    }

    /// This identity's report of a test round of weights version 1.
    fn evaluation(&self, episodes: u32, successes: u32) -> pb::EvaluationReport {
        pb::EvaluationReport {
            actor_id: self.id.clone(),
            incarnation: self.incarnation,
            weights_version: 1,
            episodes,
            successes,
            learner_start: 0,
        }
    }

    /// A name no one registered.
    fn stranger(&mut self) -> String {
        self.strangers += 1;
        format!("{}-stranger-{}", self.id, self.strangers)
    }

    /// A decodable request for `UNARY[i]`.
    fn valid_unary(&mut self, i: usize) -> Vec<u8> {
        match i {
            0 => registration(self.stranger(), pb::ActorRole::Evaluator).encode_to_vec(),
            1 => pb::WatchWeightsRequest {
                actor_id: self.id.clone(),
                incarnation: self.incarnation,
                min_version: 0,
            }
            .encode_to_vec(),
            2 => self.evaluation(10, 3).encode_to_vec(),
            3 => pb::TurnRequest {
                actor_id: self.id.clone(),
                incarnation: self.incarnation,
                wait_ms: 10,
            }
            .encode_to_vec(),
            _ => pb::GetStatusRequest { max_evaluations: 1 }.encode_to_vec(),
        }
    }

    /// Changes, cuts or appends random bytes.
    fn mutate(&mut self, bytes: &mut Vec<u8>) {
        for _ in 0..1 + self.rng.below(4) {
            match self.rng.below(4) {
                0 | 1 if !bytes.is_empty() => {
                    let i = self.rng.below(bytes.len());
                    bytes[i] = self.rng.next_u64() as u8;
                }
                2 if !bytes.is_empty() => {
                    let keep = self.rng.below(bytes.len());
                    bytes.truncate(keep);
                }
                _ => {
                    let n = 1 + self.rng.below(16);
                    bytes.extend((0..n).map(|_| self.rng.next_u64() as u8));
                }
            }
        }
    }

    /// A level-0 batch of up to 64 transitions of values within `+-scale`, rewards -1.
    fn batch(&mut self, scale: f32) -> pb::TransitionBatch {
        let count = 1 + self.rng.below(64);
        self.batch_of(0, count, scale)
    }

    fn batch_of(&mut self, level: usize, count: usize, scale: f32) -> pb::TransitionBatch {
        random_batch(&mut self.rng, self.run.dims[level], level, count, scale)
    }

    fn request(&self, sequence: u64, item: pb::ingest_request::Item) -> pb::IngestRequest {
        pb::IngestRequest {
            actor_id: self.id.clone(),
            incarnation: self.incarnation,
            sequence,
            item: Some(item),
        }
    }

    async fn ingest_batch(&mut self, batch: pb::TransitionBatch) -> Result<Answer> {
        let request = self.request(self.next, pb::ingest_request::Item::Batch(batch));
        self.ingest(request.encode_to_vec()).await
    }

    /// One message on a fresh ingest stream; OK once it is acknowledged. A stored message
    /// advances this identity's numbering.
    async fn ingest(&mut self, bytes: Vec<u8>) -> Result<Answer> {
        self.grpc
            .ready()
            .await
            .context("the learner's connection")?;
        let stream = tokio_stream::once(bytes.clone());
        let response = self
            .grpc
            .streaming(
                tonic::Request::new(stream),
                PathAndQuery::from_static(INGEST),
                Raw,
            )
            .await;
        let mut acks = match response {
            Ok(response) => response.into_inner(),
            Err(status) => return Ok(Err(status)),
        };
        let mut acked_through = 0;
        loop {
            match acks.message().await {
                Ok(Some(ack)) => {
                    let ack = pb::IngestAck::decode(ack.as_slice())
                        .context("the learner sent an undecodable ack")?;
                    acked_through = acked_through.max(ack.acked_through);
                }
                Ok(None) => break,
                Err(status) => return Ok(Err(status)),
            }
        }
        // Accepted: what the learner took it for is what the bytes decode to (a mutation may
        // have changed any field), stored if it was this identity's next message, else a
        // duplicate.
        let request = pb::IngestRequest::decode(bytes.as_slice())
            .context("the learner accepted a message that does not decode")?;
        if request.actor_id == self.id && request.incarnation == self.incarnation {
            if request.sequence == self.next {
                if acked_through < self.next {
                    bail!(
                        "{}: message {} stored but acknowledged through {acked_through}",
                        self.id,
                        self.next
                    );
                }
                self.next += 1;
                self.account.stored_through = request.sequence;
                if let Some(pb::ingest_request::Item::Batch(batch)) = &request.item {
                    self.account.transitions += u64::from(batch.count);
                }
            } else if request.sequence < self.next {
                self.account.duplicates += 1;
            }
        }
        Ok(Ok(()))
    }

    /// A unary call (or the first message of a server stream) with `bytes` as the request.
    async fn unary(&mut self, path: &'static str, bytes: Vec<u8>) -> Result<Answer> {
        self.grpc
            .ready()
            .await
            .context("the learner's connection")?;
        let path = PathAndQuery::from_static(path);
        if path.path().starts_with("/hac.v1.Learner/WatchWeights")
            || path.path().starts_with("/hac.v1.Status/WatchStatus")
        {
            let response = self
                .grpc
                .server_streaming(tonic::Request::new(bytes), path, Raw)
                .await;
            return Ok(match response {
                Ok(response) => response.into_inner().message().await.map(drop),
                Err(status) => Err(status),
            });
        }
        Ok(self
            .grpc
            .unary(tonic::Request::new(bytes), path, Raw)
            .await
            .map(drop))
    }
}

/// The answer's name: `ok`, the refusal's reason, or its gRPC code.
fn answer_name(answer: &Answer) -> String {
    match answer {
        Ok(()) => "ok".into(),
        Err(status) => match status
            .metadata()
            .get(REJECT_REASON_KEY)
            .and_then(|v| v.to_str().ok())
        {
            Some(reason) => reason.to_string(),
            None => format!("{:?}", status.code()),
        },
    }
}

fn is_wrong(kind: Kind, answer: &Answer) -> bool {
    if let Err(status) = answer
        && matches!(
            status.code(),
            Code::Internal | Code::Unknown | Code::Unavailable | Code::DataLoss
        )
    {
        return true;
    }
    // Once the run is over every ingest is refused as `finished`: right for any input.
    if answer_name(answer) == "finished" {
        return false;
    }
    match kind.expect() {
        Expect::Refused => answer.is_ok(),
        Expect::Accepted => answer.is_err(),
        Expect::Either => false,
    }
}

/// Tallies shared by the hostile clients.
#[derive(Default)]
struct Tally {
    kinds: Mutex<BTreeMap<Kind, KindReport>>,
    inputs: AtomicU64,
}

impl Tally {
    fn record(&self, kind: Kind, answer: &Answer) {
        let mut kinds = self.kinds.lock().expect("no panics while held");
        let report = kinds.entry(kind).or_insert_with(|| KindReport {
            kind: kind.name(),
            ..KindReport::default()
        });
        report.sent += 1;
        *report.answers.entry(answer_name(answer)).or_default() += 1;
        if is_wrong(kind, answer) {
            report.wrong += 1;
        }
    }
}

/// A hostile client: inputs of every kind in a seeded random order until `stop`, or until the
/// shared budget of `inputs` is spent.
async fn attack(
    url: String,
    index: usize,
    seed: u64,
    budget: Option<u64>,
    stop: Arc<AtomicBool>,
    tally: Arc<Tally>,
) -> Result<Account> {
    let mut hostile = Hostile::connect(&url, index, seed).await?;
    while !stop.load(Ordering::Relaxed) {
        let n = tally.inputs.fetch_add(1, Ordering::Relaxed);
        if budget.is_some_and(|b| n >= b) {
            tally.inputs.fetch_sub(1, Ordering::Relaxed);
            break;
        }
        let kind = Kind::ALL[hostile.rng.below(Kind::ALL.len())];
        let answer = hostile
            .send(kind)
            .await
            .with_context(|| format!("{}: {kind:?}", hostile.id))?;
        tally.record(kind, &answer);
    }
    Ok(hostile.account)
}

/// The watcher's connection (kept open while it watches) and its weights stream.
type Watch = (
    pb::learner_client::LearnerClient<tonic::transport::Channel>,
    tonic::codec::Streaming<pb::Weights>,
);

/// Registers as an evaluator and opens a weights watch: from then on the run has an evaluator,
/// so a trainer's evaluation is refused.
async fn open_watch(url: &str) -> Result<Watch> {
    let mut client = client(url).await?;
    let id = "hostile-bench-watcher".to_string();
    let incarnation = client
        .register(registration(id.clone(), pb::ActorRole::Evaluator))
        .await?
        .into_inner()
        .incarnation;
    let stream = client
        .watch_weights(pb::WatchWeightsRequest {
            actor_id: id,
            incarnation,
            min_version: 0,
        })
        .await?
        .into_inner();
    Ok((client, stream))
}

/// Checks every float of every weights version on the watch (see [`open_watch`]). Stops the
/// attack (`finished`) once the learner announces the end of the run; runs while `watching`.
async fn watch_weights(
    (_client, mut stream): Watch,
    watching: Arc<AtomicBool>,
    finished: Arc<AtomicBool>,
) -> Result<(u64, u64)> {
    let (mut versions, mut non_finite) = (0u64, 0u64);
    while watching.load(Ordering::Relaxed) {
        let next = tokio::time::timeout(Duration::from_millis(500), stream.message()).await;
        let weights = match next {
            Err(_) => continue,
            Ok(Ok(Some(weights))) => weights,
            // The learner finished or stopped.
            Ok(Ok(None) | Err(_)) => break,
        };
        versions += 1;
        for level in &weights.levels {
            non_finite += non_finite_floats(&level.actor_safetensors)?;
        }
        if weights.run_finished {
            finished.store(true, Ordering::Relaxed);
        }
    }
    Ok((versions, non_finite))
}

/// Non-finite values in a safetensors file whose tensors are all f32 (as the learner writes
/// them): an 8-byte header length, the JSON header, then the data.
fn non_finite_floats(bytes: &[u8]) -> Result<u64> {
    let header: [u8; 8] = bytes
        .get(..8)
        .and_then(|b| b.try_into().ok())
        .context("a weights file shorter than its header length")?;
    let start = 8usize.saturating_add(u64::from_le_bytes(header) as usize);
    let data = bytes
        .get(start..)
        .context("a weights file shorter than its header")?;
    Ok(data
        .chunks_exact(4)
        .filter(|c| !f32::from_le_bytes([c[0], c[1], c[2], c[3]]).is_finite())
        .count() as u64)
}

/// The honest sender of the throughput phase: level-0 batches of 1024 in-box transitions,
/// `window` in flight; transitions acknowledged per second.
async fn throughput(url: String, seconds: f64, dims: pb::LevelDims) -> Result<f64> {
    let mut client = client(&url).await?;
    let id = "hostile-bench-throughput";
    let incarnation = register(&mut client, id).await?;
    let count = 1024usize;
    let batch = random_batch(&mut Rng::seed_from(7), dims, 0, count, 0.1);
    let window = 64u64;
    let (tx, rx) = tokio::sync::mpsc::channel::<pb::IngestRequest>(window as usize);
    let mut acks = client.ingest(ReceiverStream::new(rx)).await?.into_inner();
    let acked = Arc::new(AtomicU64::new(0));
    let notify = Arc::new(tokio::sync::Notify::new());
    let receiver = {
        let (acked, notify) = (acked.clone(), notify.clone());
        tokio::spawn(async move {
            while let Some(ack) = acks.message().await? {
                acked.store(ack.acked_through, Ordering::Relaxed);
                notify.notify_one();
            }
            anyhow::Ok(())
        })
    };
    let t0 = Instant::now();
    let until = t0 + Duration::from_secs_f64(seconds);
    let mut sequence = 0u64;
    while Instant::now() < until {
        if sequence - acked.load(Ordering::Relaxed) >= window {
            notify.notified().await;
            continue;
        }
        sequence += 1;
        let request = pb::IngestRequest {
            actor_id: id.into(),
            incarnation,
            sequence,
            item: Some(pb::ingest_request::Item::Batch(batch.clone())),
        };
        if tx.send(request).await.is_err() {
            bail!("the throughput sender's stream closed");
        }
    }
    drop(tx);
    receiver.await.context("the ack reader panicked")??;
    let elapsed = t0.elapsed().as_secs_f64();
    let acked = acked.load(Ordering::Relaxed);
    if acked != sequence {
        bail!("the throughput sender sent {sequence} batches, {acked} were acknowledged");
    }
    Ok(acked as f64 * count as f64 / elapsed)
}

/// `hac actor` children, killed if still running when dropped.
struct Actors(Vec<(String, Child)>);

impl Actors {
    fn spawn(&mut self, url: &str, id: &str, extra: &[&str], logs: &Path) -> Result<()> {
        let exe = std::env::current_exe().context("locating the hac binary")?;
        let log = std::fs::File::create(logs.join(format!("{id}.log")))?;
        let child = Command::new(exe)
            .args(["actor", "--learner", url, "--id", id])
            .args(extra)
            .env_remove("HAC_CONFIG")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .context("starting `hac actor`")?;
        self.0.push((id.to_string(), child));
        Ok(())
    }

    fn kill_all(&mut self) {
        for (_, child) in &mut self.0 {
            if child.try_wait().ok().flatten().is_none() {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
    }
}

impl Drop for Actors {
    fn drop(&mut self) {
        self.kill_all();
    }
}

/// Runs the bench; see the module docs.
pub fn run(bench: &HostileBench) -> Result<HostileReport> {
    if bench.clients == 0 && bench.inputs.is_some() {
        bail!("--inputs needs hostile clients (--clients at least 1)");
    }
    if bench.inputs.is_none() && bench.trainers == 0 {
        bail!("an attack needs honest trainers (--trainers at least 1)");
    }
    let fuzz = bench.inputs.is_some();
    let (dir, keep) = match &bench.dir {
        Some(dir) => (dir.clone(), true),
        None => (
            std::env::temp_dir().join(format!("hac-bench-hostile-{}", std::process::id())),
            false,
        ),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let out = dir.join("run");
    let mut args: Vec<String> = [
        "--env",
        &bench.env,
        "--levels",
        &bench.levels.to_string(),
        "--seed",
        &bench.seed.to_string(),
        "--checkpoint-every",
        "30",
    ]
    .map(String::from)
    .to_vec();
    if fuzz {
        args.extend(["--episodes".into(), "1000000000".into()]);
    } else {
        args.extend([
            "--episodes".into(),
            bench.episodes.to_string(),
            "--stop-at".into(),
            bench.stop_at.to_string(),
            // Time to read every hostile identity's counts after the run ends.
            "--grace-period".into(),
            "5".into(),
        ]);
    }
    let log = std::fs::File::create(dir.join("learner.log"))?;
    let (mut learner, url) = LearnerProcess::spawn(&args, &out, keep, log.into())?;
    let pid = learner.pid();
    eprintln!("learner {pid} on {url}; logs and run in {}", dir.display());

    let mut actors = Actors(Vec::new());
    if !fuzz {
        actors.spawn(&url, "honest-evaluator", &["--role", "evaluator"], &dir)?;
    }
    // Fuzz: the trainers play in lockstep with training (the paper's schedule), so that ingest
    // is never held back for the learner to catch up and the inputs go at the learner's pace.
    let trainer_flags: &[&str] = if fuzz { &["--lockstep"] } else { &[] };
    for i in 0..bench.trainers {
        actors.spawn(&url, &format!("honest-trainer-{i}"), trainer_flags, &dir)?;
    }

    // `attack_stop` ends the hostile clients (time up, budget spent, or the run over);
    // `watching` the weights check and the memory samples, once the learner is gone.
    let attack_stop = Arc::new(AtomicBool::new(false));
    let watching = Arc::new(AtomicBool::new(true));
    let t0 = Instant::now();
    let sampler = {
        let watching = watching.clone();
        std::thread::spawn(move || {
            let mut samples = Vec::new();
            while watching.load(Ordering::Relaxed) {
                match read_status(pid) {
                    Ok((rss, _, _)) => samples.push(MemorySample {
                        at_s: t0.elapsed().as_secs_f64(),
                        rss_kib: rss,
                    }),
                    Err(_) => break,
                }
                std::thread::sleep(Duration::from_secs(1));
            }
            samples
        })
    };

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the bench runtime")?;
    let tally = Arc::new(Tally::default());
    // The watcher is the run's evaluator from the first hostile input on: a trainer's
    // evaluation is refused only while the run has one (the honest evaluator, in attack mode,
    // may not have registered yet).
    let watch = runtime
        .block_on(open_watch(&url))
        .context("the weights watcher")?;
    let watcher = runtime.spawn(watch_weights(watch, watching.clone(), attack_stop.clone()));
    let hostile_t0 = Instant::now();
    let clients: Vec<_> = (0..bench.clients)
        .map(|i| {
            runtime.spawn(attack(
                url.clone(),
                i,
                bench.seed,
                bench.inputs,
                attack_stop.clone(),
                tally.clone(),
            ))
        })
        .collect();

    // Attack: until the run ends (the attack stops at `--seconds` or when the learner announces
    // the end); fuzz: until the budget is spent. A learner that exits before is a crash.
    let mut status = None;
    let mut polled = Instant::now();
    let mut printed = Instant::now();
    let mut hostile_seconds = None;
    let mut exit = None;
    loop {
        std::thread::sleep(Duration::from_millis(100));
        if let Some(code) = learner.try_wait()? {
            exit = Some(code);
            break;
        }
        let elapsed = hostile_t0.elapsed();
        if hostile_seconds.is_none()
            && (attack_stop.load(Ordering::Relaxed)
                || (!fuzz && elapsed.as_secs_f64() >= bench.seconds)
                || clients.iter().all(|c| c.is_finished()))
        {
            hostile_seconds = Some(elapsed.as_secs_f64());
            attack_stop.store(true, Ordering::Relaxed);
            if fuzz {
                break;
            }
        }
        if elapsed > Duration::from_secs(3600) {
            break;
        }
        if polled.elapsed() >= Duration::from_secs(2) {
            polled = Instant::now();
            let now = runtime.block_on(async {
                tokio::time::timeout(Duration::from_secs(2), learner_status(&url)).await
            });
            if let Ok(Ok(now)) = now {
                status = Some(now);
            }
        }
        if printed.elapsed() >= Duration::from_secs(10) {
            printed = Instant::now();
            let (episodes, last) = status.as_ref().map_or((0, 0.0), |s| {
                let last = s.evaluations.last().map_or(0.0, |e| e.success_rate);
                (s.episodes, last)
            });
            eprintln!(
                "{:.0} s: {} hostile inputs; {episodes} episodes ingested, last test round {:.0}%",
                elapsed.as_secs_f64(),
                tally.inputs.load(Ordering::Relaxed),
                100.0 * last
            );
        }
    }
    let hostile_seconds = hostile_seconds.unwrap_or_else(|| hostile_t0.elapsed().as_secs_f64());
    attack_stop.store(true, Ordering::Relaxed);
    let mut client_errors = Vec::new();
    let mut accounts = Vec::new();
    for client in clients {
        match runtime.block_on(client) {
            Ok(Ok(account)) => accounts.push(account),
            Ok(Err(e)) => client_errors.push(format!("{e:#}")),
            Err(e) => client_errors.push(format!("a hostile client panicked: {e}")),
        }
    }
    // Every hostile identity's counts as the learner has them, while it still serves (an
    // attacked run's learner serves its grace period after the end).
    if let Ok(Ok(now)) = runtime.block_on(async {
        tokio::time::timeout(Duration::from_secs(2), learner_status(&url)).await
    }) {
        status = Some(now);
    }
    for account in &mut accounts {
        let seen = status
            .as_ref()
            .and_then(|s| s.actors.iter().find(|a| a.actor_id == account.actor_id));
        if let Some(seen) = seen {
            account.learner_stored_through = seen.stored_through;
            account.learner_transitions = seen.transitions;
            account.learner_duplicates = seen.duplicates;
        }
    }

    let mut throughput_transitions_per_s = None;
    if exit.is_none() && fuzz {
        // The honest trainers stop, then the throughput phase on the same learner.
        actors.kill_all();
        if bench.throughput_seconds > 0.0 {
            let dims = hac_envs::make(&bench.env)?
                .spec()
                .level_dims(0, bench.levels);
            let dims = pb::LevelDims {
                state: dims.state as u32,
                goal: dims.goal as u32,
                action: dims.action as u32,
            };
            // The trainers catch up with what the honest actors sent before it.
            std::thread::sleep(Duration::from_secs(2));
            throughput_transitions_per_s =
                Some(runtime.block_on(throughput(url.clone(), bench.throughput_seconds, dims))?);
        }
        if let Ok(now) = runtime.block_on(learner_status(&url)) {
            status = Some(now);
        }
        exit = Some(learner.terminate()?);
    }
    watching.store(false, Ordering::Relaxed);
    let (versions, non_finite) = runtime
        .block_on(watcher)
        .context("the weights watcher panicked")?
        .context("watching the weights")?;
    let memory = sampler.join().unwrap_or_default();
    drop(actors);
    let exit = match exit {
        Some(exit) => exit,
        None => {
            learner.terminate()?;
            bail!("the run did not finish within an hour");
        }
    };
    let diverged_updates = status.as_ref().map_or(0, |s| {
        s.level_status.iter().map(|l| l.diverged_updates).sum()
    });

    let summary: serde_json::Value = std::fs::read_to_string(out.join("summary.json"))
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or(serde_json::Value::Null);
    let count = |key: &str| summary[key].as_u64().unwrap_or(0);
    let refused: BTreeMap<String, u64> = summary["rejected"]
        .as_object()
        .into_iter()
        .flatten()
        .filter_map(|(k, v)| Some((k.clone(), v.as_u64()?)))
        .filter(|(_, v)| *v > 0)
        .collect();
    let messages = count("messages");
    let stored = count("batches") + count("episodes_ingested");
    let duplicates = count("duplicates");
    // Every transition counted at ingest went into replay once, and each hostile identity's
    // stored messages, transitions and duplicates are exactly those its acknowledgements told
    // it (refusals are counted for every RPC, so they do not add up to ingest messages).
    let exactly_once = !summary.is_null()
        && count("transitions") == count("transitions_in_replay")
        && accounts.len() == bench.clients
        && accounts.iter().all(|a| {
            a.stored_through == a.learner_stored_through
                && a.transitions == a.learner_transitions
                && a.duplicates == a.learner_duplicates
        });

    let kinds: Vec<KindReport> = tally
        .kinds
        .lock()
        .expect("no panics while held")
        .values()
        .cloned()
        .collect();
    let hostile_inputs = kinds.iter().map(|k| k.sent).sum();
    let peak_rss_kib = memory.iter().map(|s| s.rss_kib).max().unwrap_or(0);
    let report = HostileReport {
        mode: if fuzz { "fuzz" } else { "attack" },
        env: bench.env.clone(),
        levels: bench.levels,
        seed: bench.seed,
        trainers: bench.trainers,
        clients: bench.clients,
        hostile_inputs,
        hostile_seconds,
        hostile_inputs_per_s: hostile_inputs as f64 / hostile_seconds.max(1e-9),
        wrong_answers: kinds.iter().map(|k| k.wrong).sum(),
        kinds,
        learner_exit: exit.to_string(),
        learner_crashed: !exit.success(),
        weights_versions_checked: versions,
        weights_non_finite: non_finite,
        diverged_updates,
        peak_rss_kib,
        first_rss_kib: memory.first().map_or(0, |s| s.rss_kib),
        last_rss_kib: memory.last().map_or(0, |s| s.rss_kib),
        memory,
        stop_at: (!fuzz).then_some(bench.stop_at),
        best_success: summary["best_success"].as_f64(),
        episodes_to_90: summary["episodes_to_90"].as_u64(),
        episodes: count("episodes"),
        wall_time_s: summary["wall_time_s"].as_f64().unwrap_or(0.0),
        throughput_transitions_per_s,
        messages,
        stored,
        duplicates,
        refused,
        accounts,
        exactly_once,
    };
    if !keep {
        let _ = std::fs::remove_dir_all(&dir);
    }
    if !client_errors.is_empty() {
        bail!(
            "hostile clients failed (the learner's connection broke?): {}\n{}",
            client_errors.join("; "),
            serde_json::to_string(&report).unwrap_or_default()
        );
    }
    Ok(report)
}

async fn learner_status(url: &str) -> Result<pb::LearnerStatus> {
    let mut client = pb::status_client::StatusClient::connect(url.to_string())
        .await?
        .max_decoding_message_size(64 << 20);
    let status = client
        .get_status(pb::GetStatusRequest { max_evaluations: 1 })
        .await?
        .into_inner();
    match status.node {
        Some(pb::node_status::Node::Learner(learner)) => Ok(learner),
        _ => bail!("{url} is not a learner"),
    }
}

/// Runs the bench and prints its report; fails if the learner crashed, published a non-finite
/// weight, lost count of a message, answered an input wrongly, or (attack) missed the target.
pub fn run_and_print(bench: &HostileBench) -> Result<()> {
    let report = run(bench)?;
    if bench.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    let mut failures = Vec::new();
    if report.learner_crashed {
        failures.push(format!("the learner crashed ({})", report.learner_exit));
    }
    if report.weights_non_finite > 0 {
        failures.push(format!(
            "{} non-finite weights published",
            report.weights_non_finite
        ));
    }
    if report.wrong_answers > 0 {
        failures.push(format!("{} wrong answers", report.wrong_answers));
    }
    if !report.exactly_once {
        failures.push("ingest accounting is not exactly once".into());
    }
    if let (Some(target), best) = (report.stop_at, report.best_success.unwrap_or(0.0))
        && best < target
    {
        failures.push(format!(
            "the run did not reach {:.0}% (best {:.1}%)",
            100.0 * target,
            100.0 * best
        ));
    }
    if !failures.is_empty() {
        bail!("{}", failures.join("; "));
    }
    Ok(())
}

fn print_report(r: &HostileReport) {
    outln!(
        "{} on {} ({} levels, seed {}): {} honest trainers, {} hostile clients",
        r.mode,
        r.env,
        r.levels,
        r.seed,
        r.trainers,
        r.clients
    );
    outln!(
        "hostile inputs: {} in {:.1} s ({:.0}/s); wrong answers: {}",
        r.hostile_inputs,
        r.hostile_seconds,
        r.hostile_inputs_per_s,
        r.wrong_answers
    );
    outln!();
    outln!("| input | sent | wrong | answers |");
    outln!("| --- | ---: | ---: | --- |");
    for k in &r.kinds {
        let answers: Vec<String> = k.answers.iter().map(|(a, n)| format!("{a} {n}")).collect();
        outln!(
            "| {} | {} | {} | {} |",
            k.kind,
            k.sent,
            k.wrong,
            answers.join(", ")
        );
    }
    outln!();
    outln!(
        "learner: exit {}{}; weights versions checked {}, non-finite values {}; updates undone \
         {}",
        r.learner_exit,
        if r.learner_crashed { " (CRASHED)" } else { "" },
        r.weights_versions_checked,
        r.weights_non_finite,
        r.diverged_updates
    );
    outln!(
        "memory (VmRSS): first {:.1} MiB, peak {:.1} MiB, last {:.1} MiB ({} samples)",
        r.first_rss_kib as f64 / 1024.0,
        r.peak_rss_kib as f64 / 1024.0,
        r.last_rss_kib as f64 / 1024.0,
        r.memory.len()
    );
    let refused: Vec<String> = r.refused.iter().map(|(k, n)| format!("{k} {n}")).collect();
    outln!(
        "ingest: {} messages reached the learner core, {} stored, {} duplicates; refusals on \
         every RPC: {}",
        r.messages,
        r.stored,
        r.duplicates,
        refused.join(", ")
    );
    for a in &r.accounts {
        outln!(
            "{}: acknowledged {} messages, {} transitions, {} duplicates; the learner has {}, \
             {}, {}",
            a.actor_id,
            a.stored_through,
            a.transitions,
            a.duplicates,
            a.learner_stored_through,
            a.learner_transitions,
            a.learner_duplicates
        );
    }
    outln!(
        "accounting: {}",
        if r.exactly_once {
            "exactly once"
        } else {
            "NOT exactly once"
        }
    );
    if let Some(target) = r.stop_at {
        outln!(
            "run: {} episodes in {:.1} s; best success {:.1}% (target {:.0}%); 90% after {}",
            r.episodes,
            r.wall_time_s,
            100.0 * r.best_success.unwrap_or(0.0),
            100.0 * target,
            r.episodes_to_90
                .map_or("never".to_string(), |e| format!("{e} episodes"))
        );
    }
    if let Some(t) = r.throughput_transitions_per_s {
        outln!(
            "honest gRPC ingest after the inputs: {:.2}M transitions/s",
            t / 1e6
        );
    }
}
