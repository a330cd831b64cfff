//! [`InProcess`]: an [`ActorLink`] that calls a [`Learner`] in the same process.

use std::sync::Arc;
use std::time::Duration;

use hac_learner::{IngestError, Learner, RegisterError, RoomError};
use hac_proto::Published;
use hac_proto::{Admission, Evaluation, IngestItem, IngestMessage, Registration, WeightsSnapshot};
use hac_transport::{ActorLink, EvaluationOf, GrantedTurn, IngestSink, LinkError, WeightsSource};

/// Direct calls into a shared [`Learner`]: registration as is, each item ingested synchronously
/// after waiting for room (the learner's backpressure), weights read from the learner's own
/// cell.
#[derive(Debug)]
pub struct InProcess {
    learner: Arc<Learner>,
    actor_id: String,
    incarnation: u64,
    sequence: u64,
}

impl InProcess {
    /// A link to `learner`; nothing is sent before [`register`](ActorLink::register).
    pub fn new(learner: Arc<Learner>) -> Self {
        Self {
            learner,
            actor_id: String::new(),
            incarnation: 0,
            sequence: 0,
        }
    }
}

fn refused(e: IngestError) -> LinkError {
    match e {
        IngestError::Finished => LinkError::Finished,
        e => LinkError::Refused(e.to_string()),
    }
}

impl IngestSink for InProcess {
    fn send(&mut self, item: IngestItem) -> Result<(), LinkError> {
        if self.incarnation == 0 {
            return Err(LinkError::Refused("send before register".into()));
        }
        loop {
            match self.learner.wait_for_room(Duration::from_secs(1)) {
                Ok(()) => break,
                Err(RoomError::TimedOut) => continue,
                Err(RoomError::Finished) => return Err(LinkError::Finished),
            }
        }
        self.sequence += 1;
        let msg = IngestMessage {
            actor_id: self.actor_id.clone(),
            incarnation: self.incarnation,
            sequence: self.sequence,
            item,
        };
        self.learner.ingest(&msg).map(|_| ()).map_err(refused)
    }

    fn flush(&mut self, _timeout: Duration) -> Result<(), LinkError> {
        Ok(())
    }
}

impl WeightsSource for InProcess {
    fn weights(&self) -> &Published<WeightsSnapshot> {
        self.learner.weights()
    }

    fn learner_version(&self) -> u64 {
        self.learner.weights().latest().map_or(0, |w| w.version)
    }
}

impl ActorLink for InProcess {
    fn register(&mut self, registration: &Registration) -> Result<Admission, LinkError> {
        let admission = self
            .learner
            .register(registration.clone())
            .map_err(|e| match e {
                RegisterError::Finished => LinkError::Finished,
                e => LinkError::Refused(e.to_string()),
            })?;
        self.actor_id = registration.actor_id.clone();
        self.incarnation = admission.incarnation;
        self.sequence = 0;
        self.learner
            .set_actor_transport(&self.actor_id, self.transport());
        Ok(admission)
    }

    fn await_turn(&mut self, wait: Duration) -> Result<Option<GrantedTurn>, LinkError> {
        let turn = self
            .learner
            .await_turn(&self.actor_id, self.incarnation, wait)
            .map_err(refused)?;
        Ok(turn.granted.then_some(GrantedTurn {
            trained: turn.episodes,
            episode: turn.episode,
        }))
    }

    /// The learner in this process cannot restart: a report is on the curve or refused.
    fn report_evaluation(&mut self, report: &EvaluationOf) -> Result<bool, LinkError> {
        self.learner
            .report_evaluation(&Evaluation {
                actor_id: self.actor_id.clone(),
                incarnation: self.incarnation,
                weights_version: report.weights_version,
                episodes: report.episodes,
                successes: report.successes,
                learner_start: report.learner_start,
            })
            .map_err(refused)?;
        Ok(true)
    }

    fn transport(&self) -> &'static str {
        "in-process"
    }
}
