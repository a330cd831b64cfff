//! Registration and evaluation reports: the learner service's unary messages.

use std::borrow::Cow;

use hac_core::LevelDims;

use crate::limits::check_len;
use crate::{
    MAX_HOSTNAME_BYTES, MAX_TRANSPORT_NAME_BYTES, MAX_TRANSPORTS, WireError, check_actor_id, pb,
};

/// What an actor process does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ActorRole {
    /// Runs training episodes with the behaviour policy and streams transitions.
    Trainer,
    /// Runs greedy test episodes only and reports success rates.
    Evaluator,
}

/// An actor introducing itself (`pb::RegisterRequest`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Registration {
    /// Stable, operator-chosen name, unique among live actors.
    pub actor_id: String,
    pub role: ActorRole,
    /// Host name as the actor sees it; empty if unknown (then no shared memory is offered).
    pub hostname: String,
    /// Transports the actor can use, e.g. "grpc", "shm"; unknown names are the learner's to skip.
    pub transports: Vec<String>,
}

/// A link registering again names the incarnation its messages are numbered under
/// (`pb::RegisterRequest.previous_incarnation` and `resend_from`): a learner that knows the actor
/// under it with every sequence before `resend_from` stored keeps it; otherwise it answers with a
/// fresh incarnation above it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PreviousIncarnation {
    /// Never 0.
    pub incarnation: u64,
    /// The oldest sequence the actor still holds and resends first (at least 1).
    pub resend_from: u64,
}

impl PreviousIncarnation {
    /// The previous incarnation a registration request names, if any.
    pub fn of_request(msg: &pb::RegisterRequest) -> Option<Self> {
        (msg.previous_incarnation != 0).then(|| Self {
            incarnation: msg.previous_incarnation,
            resend_from: msg.resend_from.max(1),
        })
    }

    /// Puts it into a registration request.
    pub fn into_request(self, msg: &mut pb::RegisterRequest) {
        msg.previous_incarnation = self.incarnation;
        msg.resend_from = self.resend_from;
    }
}

/// The learner's answer to a [`Registration`] (`pb::RegisterResponse`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Admission {
    /// Fresh for every registration, never 0.
    pub incarnation: u64,
    /// The run's resolved configuration as TOML (the learner is its single source of truth).
    pub run_config_toml: String,
    /// SHA-256 of `run_config_toml`, hex.
    pub run_config_digest: String,
    /// Seed of the actor's random streams.
    pub seed: u64,
    /// Dimensions of each level, level 0 first; at least one level.
    pub levels: Vec<LevelDims>,
    /// Largest number of transitions the learner accepts in one batch, at least 1.
    pub max_batch_transitions: usize,
    /// Actors refuse to act on weights more than this many versions behind the newest they know.
    pub max_weights_lag: u64,
    /// Shared memory served to actors on the learner's host, if any.
    pub shm: Option<ShmOffer>,
    /// Episode turns: at most this many training episodes in flight over all actors, trainers
    /// asking for a turn before each episode; 0 for none.
    pub episodes_in_flight: u32,
    /// Extra values per transition of each level ([`hac_core::Transition::extra`]), level 0
    /// first; empty when no level has any (HAC).
    pub extra_widths: Vec<usize>,
}

impl Admission {
    /// Extra values per transition of `level` (0 where [`extra_widths`](Self::extra_widths)
    /// says nothing).
    pub fn extra_width(&self, level: usize) -> usize {
        self.extra_widths.get(level).copied().unwrap_or(0)
    }
}

/// Shared memory (iceoryx2) the learner serves beside gRPC to actors on its own host.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ShmOffer {
    /// The run's service namespace: every service is named `hac/<namespace>/...`.
    pub namespace: String,
    /// The learner's host identity (boot id and host name); only an actor with the same identity
    /// shares its memory.
    pub host: String,
}

/// Results of greedy test episodes (`pb::EvaluationReport`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Evaluation {
    pub actor_id: String,
    pub incarnation: u64,
    pub weights_version: u64,
    /// At least 1.
    pub episodes: u32,
    /// At most `episodes`.
    pub successes: u32,
    /// The evaluated weights' `learner_start` (0: not checked).
    pub learner_start: u64,
}

impl From<ActorRole> for pb::ActorRole {
    fn from(role: ActorRole) -> Self {
        match role {
            ActorRole::Trainer => Self::Trainer,
            ActorRole::Evaluator => Self::Evaluator,
        }
    }
}

impl TryFrom<pb::RegisterRequest> for Registration {
    type Error = WireError;

    fn try_from(msg: pb::RegisterRequest) -> Result<Self, WireError> {
        check_actor_id("register_request.actor_id", &msg.actor_id)?;
        check_len(
            "register_request.hostname",
            &msg.hostname,
            MAX_HOSTNAME_BYTES,
        )?;
        if msg.transports.len() > MAX_TRANSPORTS {
            return Err(WireError::TooMany {
                field: "register_request.transports",
                count: msg.transports.len(),
                limit: MAX_TRANSPORTS,
            });
        }
        for (index, transport) in msg.transports.iter().enumerate() {
            if let Err(e) = check_len("", transport, MAX_TRANSPORT_NAME_BYTES) {
                return Err(e.in_field(format!("register_request.transports[{index}]")));
            }
        }
        Ok(Self {
            role: role_from_pb(msg.role)?,
            actor_id: msg.actor_id,
            hostname: msg.hostname,
            transports: msg.transports,
        })
    }
}

impl From<Registration> for pb::RegisterRequest {
    fn from(registration: Registration) -> Self {
        Self {
            actor_id: registration.actor_id,
            role: pb::ActorRole::from(registration.role).into(),
            hostname: registration.hostname,
            transports: registration.transports,
            previous_incarnation: 0,
            resend_from: 0,
        }
    }
}

fn role_from_pb(value: i32) -> Result<ActorRole, WireError> {
    match pb::ActorRole::try_from(value) {
        Ok(pb::ActorRole::Trainer) => Ok(ActorRole::Trainer),
        Ok(pb::ActorRole::Evaluator) => Ok(ActorRole::Evaluator),
        Ok(pb::ActorRole::Unspecified) => Err(WireError::missing("register_request.role")),
        Err(_) => Err(WireError::UnknownEnum {
            field: "register_request.role",
            value,
        }),
    }
}

/// Every dimension must be positive.
impl TryFrom<pb::LevelDims> for LevelDims {
    type Error = WireError;

    fn try_from(msg: pb::LevelDims) -> Result<Self, WireError> {
        level_dims_from_pb(msg, || Cow::Borrowed("level_dims"))
    }
}

/// # Panics
/// If a dimension exceeds `u32::MAX`.
impl From<LevelDims> for pb::LevelDims {
    fn from(dims: LevelDims) -> Self {
        let wire = |dim: usize| u32::try_from(dim).expect("a level dimension fits the wire's u32");
        Self {
            state: wire(dims.state),
            goal: wire(dims.goal),
            action: wire(dims.action),
        }
    }
}

fn level_dims_from_pb(
    msg: pb::LevelDims,
    prefix: impl Fn() -> Cow<'static, str>,
) -> Result<LevelDims, WireError> {
    for (name, dim) in [
        ("state", msg.state),
        ("goal", msg.goal),
        ("action", msg.action),
    ] {
        if dim == 0 {
            return Err(WireError::Zero {
                field: Cow::Owned(format!("{}.{name}", prefix())),
            });
        }
    }
    Ok(LevelDims {
        state: msg.state as usize,
        goal: msg.goal as usize,
        action: msg.action as usize,
    })
}

impl TryFrom<pb::RegisterResponse> for Admission {
    type Error = WireError;

    fn try_from(msg: pb::RegisterResponse) -> Result<Self, WireError> {
        if msg.incarnation == 0 {
            return Err(WireError::missing("register_response.incarnation"));
        }
        if msg.run_config_toml.is_empty() {
            return Err(WireError::missing("register_response.run_config_toml"));
        }
        if msg.run_config_digest.is_empty() {
            return Err(WireError::missing("register_response.run_config_digest"));
        }
        if msg.levels.is_empty() {
            return Err(WireError::missing("register_response.levels"));
        }
        if msg.max_batch_transitions == 0 {
            return Err(WireError::zero("register_response.max_batch_transitions"));
        }
        if !msg.extra_widths.is_empty() && msg.extra_widths.len() != msg.levels.len() {
            return Err(WireError::NotPerLevel {
                field: "register_response.extra_widths",
                len: msg.extra_widths.len(),
                levels: msg.levels.len(),
            });
        }
        let levels = msg
            .levels
            .into_iter()
            .enumerate()
            .map(|(level, dims)| {
                level_dims_from_pb(dims, || {
                    Cow::Owned(format!("register_response.levels[{level}]"))
                })
            })
            .collect::<Result<_, _>>()?;
        let shm = match (msg.shm_namespace.is_empty(), msg.shm_host.is_empty()) {
            (true, _) => None,
            (false, true) => return Err(WireError::missing("register_response.shm_host")),
            (false, false) => Some(ShmOffer {
                namespace: msg.shm_namespace,
                host: msg.shm_host,
            }),
        };
        Ok(Self {
            incarnation: msg.incarnation,
            run_config_toml: msg.run_config_toml,
            run_config_digest: msg.run_config_digest,
            seed: msg.seed,
            levels,
            max_batch_transitions: msg.max_batch_transitions as usize,
            max_weights_lag: msg.max_weights_lag,
            shm,
            episodes_in_flight: msg.episodes_in_flight,
            extra_widths: msg.extra_widths.iter().map(|&w| w as usize).collect(),
        })
    }
}

/// # Panics
/// If `max_batch_transitions` or a dimension exceeds `u32::MAX`.
impl From<Admission> for pb::RegisterResponse {
    fn from(admission: Admission) -> Self {
        let (shm_namespace, shm_host) = admission
            .shm
            .map_or_else(Default::default, |offer| (offer.namespace, offer.host));
        Self {
            incarnation: admission.incarnation,
            run_config_toml: admission.run_config_toml,
            run_config_digest: admission.run_config_digest,
            seed: admission.seed,
            levels: admission.levels.into_iter().map(Into::into).collect(),
            max_batch_transitions: u32::try_from(admission.max_batch_transitions)
                .expect("max_batch_transitions fits the wire's u32"),
            max_weights_lag: admission.max_weights_lag,
            shm_namespace,
            shm_host,
            episodes_in_flight: admission.episodes_in_flight,
            extra_widths: admission
                .extra_widths
                .iter()
                .map(|&w| u32::try_from(w).expect("an extra width fits the wire's u32"))
                .collect(),
        }
    }
}

impl TryFrom<pb::EvaluationReport> for Evaluation {
    type Error = WireError;

    fn try_from(msg: pb::EvaluationReport) -> Result<Self, WireError> {
        check_actor_id("evaluation_report.actor_id", &msg.actor_id)?;
        if msg.incarnation == 0 {
            return Err(WireError::missing("evaluation_report.incarnation"));
        }
        if msg.episodes == 0 {
            return Err(WireError::zero("evaluation_report.episodes"));
        }
        if msg.successes > msg.episodes {
            return Err(WireError::SuccessesAboveEpisodes {
                successes: msg.successes,
                episodes: msg.episodes,
            });
        }
        Ok(Self {
            actor_id: msg.actor_id,
            incarnation: msg.incarnation,
            weights_version: msg.weights_version,
            episodes: msg.episodes,
            successes: msg.successes,
            learner_start: msg.learner_start,
        })
    }
}

impl From<Evaluation> for pb::EvaluationReport {
    fn from(evaluation: Evaluation) -> Self {
        Self {
            actor_id: evaluation.actor_id,
            incarnation: evaluation.incarnation,
            weights_version: evaluation.weights_version,
            episodes: evaluation.episodes,
            successes: evaluation.successes,
            learner_start: evaluation.learner_start,
        }
    }
}

#[cfg(test)]
mod tests {
    use prost::Message;

    use super::*;

    /// An expected error message and the change to a valid message that provokes it.
    type Case<M> = (&'static str, fn(&mut M));

    fn admission() -> Admission {
        Admission {
            incarnation: 1,
            run_config_toml: "[env]\nname = \"pendulum\"\n".into(),
            run_config_digest: "ab12".into(),
            seed: 42,
            levels: vec![
                LevelDims {
                    state: 3,
                    goal: 2,
                    action: 1,
                },
                LevelDims {
                    state: 3,
                    goal: 2,
                    action: 2,
                },
            ],
            max_batch_transitions: 4096,
            max_weights_lag: 2,
            shm: Some(ShmOffer {
                namespace: "0123abcd-127.0.0.1-50051".into(),
                host: "boot/node-1".into(),
            }),
            episodes_in_flight: 2,
            extra_widths: vec![0, 124],
        }
    }

    fn registration() -> Registration {
        Registration {
            actor_id: "actor-7".into(),
            role: ActorRole::Evaluator,
            hostname: "node-1".into(),
            transports: vec!["grpc".into(), "shm".into()],
        }
    }

    fn evaluation() -> Evaluation {
        Evaluation {
            actor_id: "eval-0".into(),
            incarnation: 5,
            weights_version: 12,
            episodes: 10,
            successes: 7,
            learner_start: 99,
        }
    }

    fn wire<M: Message + Default>(msg: M) -> M {
        M::decode(msg.encode_to_vec().as_slice()).expect("prost decodes its own bytes")
    }

    #[test]
    fn messages_round_trip() {
        let a = admission();
        assert_eq!(
            Admission::try_from(wire(pb::RegisterResponse::from(a.clone()))).unwrap(),
            a
        );
        let r = registration();
        assert_eq!(
            Registration::try_from(wire(pb::RegisterRequest::from(r.clone()))).unwrap(),
            r
        );
        let e = evaluation();
        assert_eq!(
            Evaluation::try_from(wire(pb::EvaluationReport::from(e.clone()))).unwrap(),
            e
        );
        let dims = a.levels[1];
        assert_eq!(
            LevelDims::try_from(pb::LevelDims::from(dims)).unwrap(),
            dims
        );
    }

    #[test]
    fn an_admission_without_shared_memory_round_trips_and_a_half_offer_is_refused() {
        let a = Admission {
            shm: None,
            ..admission()
        };
        let msg = wire(pb::RegisterResponse::from(a.clone()));
        assert!(msg.shm_namespace.is_empty() && msg.shm_host.is_empty());
        assert_eq!(Admission::try_from(msg).unwrap(), a);

        let mut msg = pb::RegisterResponse::from(admission());
        msg.shm_host.clear();
        let err = Admission::try_from(msg).unwrap_err();
        assert_eq!(err.to_string(), "missing field register_response.shm_host");
    }

    #[test]
    fn extra_widths_are_one_per_level_or_none() {
        let a = Admission {
            extra_widths: Vec::new(),
            ..admission()
        };
        let back = Admission::try_from(wire(pb::RegisterResponse::from(a.clone()))).unwrap();
        assert_eq!((back.extra_width(0), back.extra_width(1)), (0, 0));
        assert_eq!(admission().extra_width(1), 124);
        let mut msg = pb::RegisterResponse::from(admission());
        msg.extra_widths.pop();
        assert_eq!(
            Admission::try_from(msg).unwrap_err().to_string(),
            "register_response.extra_widths has 1 entries, expected one per level (2)"
        );
    }

    #[test]
    fn zero_dimensions_are_refused() {
        let err = LevelDims::try_from(pb::LevelDims {
            state: 3,
            goal: 0,
            action: 1,
        })
        .expect_err("zero goal");
        assert_eq!(err.to_string(), "level_dims.goal is 0");

        let mut msg = pb::RegisterResponse::from(admission());
        msg.levels[1].action = 0;
        let err = Admission::try_from(msg).expect_err("zero action");
        assert_eq!(err.to_string(), "register_response.levels[1].action is 0");
    }

    #[test]
    fn admissions_need_their_fields() {
        let cases: [Case<pb::RegisterResponse>; 5] = [
            ("missing field register_response.incarnation", |m| {
                m.incarnation = 0
            }),
            ("missing field register_response.run_config_toml", |m| {
                m.run_config_toml.clear()
            }),
            ("missing field register_response.run_config_digest", |m| {
                m.run_config_digest.clear()
            }),
            ("missing field register_response.levels", |m| {
                m.levels.clear()
            }),
            ("register_response.max_batch_transitions is 0", |m| {
                m.max_batch_transitions = 0
            }),
        ];
        for (expected, mutate) in cases {
            let mut msg = pb::RegisterResponse::from(admission());
            mutate(&mut msg);
            assert_eq!(Admission::try_from(msg).unwrap_err().to_string(), expected);
        }
    }

    #[test]
    fn registrations_need_an_actor_and_a_known_role() {
        let mut msg = pb::RegisterRequest::from(registration());
        msg.actor_id.clear();
        let err = Registration::try_from(msg).unwrap_err();
        assert_eq!(err.to_string(), "missing field register_request.actor_id");

        let mut msg = pb::RegisterRequest::from(registration());
        msg.role = pb::ActorRole::Unspecified.into();
        let err = Registration::try_from(msg).unwrap_err();
        assert_eq!(err.to_string(), "missing field register_request.role");

        let mut msg = pb::RegisterRequest::from(registration());
        msg.role = 9;
        let err = Registration::try_from(msg).unwrap_err();
        assert_eq!(err.to_string(), "register_request.role has unknown value 9");
    }

    #[test]
    fn every_string_of_a_registration_has_a_length_limit() {
        let cases: [Case<pb::RegisterRequest>; 4] = [
            (
                "register_request.actor_id is 1048576 bytes, above the limit of 256 bytes",
                |m| m.actor_id = "a".repeat(1 << 20),
            ),
            (
                "register_request.hostname is 256 bytes, above the limit of 255 bytes",
                |m| m.hostname = "h".repeat(256),
            ),
            (
                "register_request.transports has 9 entries, above the limit of 8",
                |m| m.transports = vec!["grpc".into(); 9],
            ),
            (
                "register_request.transports[1] is 33 bytes, above the limit of 32 bytes",
                |m| m.transports[1] = "t".repeat(33),
            ),
        ];
        for (expected, mutate) in cases {
            let mut msg = pb::RegisterRequest::from(registration());
            mutate(&mut msg);
            assert_eq!(
                Registration::try_from(msg).unwrap_err().to_string(),
                expected
            );
        }
        // At the limits: accepted.
        let mut msg = pb::RegisterRequest::from(registration());
        msg.actor_id = "a".repeat(crate::MAX_ACTOR_ID_BYTES);
        msg.hostname = "h".repeat(MAX_HOSTNAME_BYTES);
        msg.transports = vec!["t".repeat(MAX_TRANSPORT_NAME_BYTES); MAX_TRANSPORTS];
        assert!(Registration::try_from(msg).is_ok());
    }

    #[test]
    fn evaluations_are_consistent() {
        let cases: [Case<pb::EvaluationReport>; 5] = [
            ("missing field evaluation_report.actor_id", |m| {
                m.actor_id.clear()
            }),
            (
                "evaluation_report.actor_id is 257 bytes, above the limit of 256 bytes",
                |m| m.actor_id = "e".repeat(257),
            ),
            ("missing field evaluation_report.incarnation", |m| {
                m.incarnation = 0
            }),
            ("evaluation_report.episodes is 0", |m| {
                m.episodes = 0;
                m.successes = 0;
            }),
            ("evaluation_report.successes 11 above episodes 10", |m| {
                m.successes = 11
            }),
        ];
        for (expected, mutate) in cases {
            let mut msg = pb::EvaluationReport::from(evaluation());
            mutate(&mut msg);
            assert_eq!(Evaluation::try_from(msg).unwrap_err().to_string(), expected);
        }
    }
}
