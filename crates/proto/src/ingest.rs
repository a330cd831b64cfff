//! The ingest stream: `pb::IngestRequest` <-> [`IngestMessage`].

use hac_core::{BatchRef, LevelDims};

use crate::{DecodedBatch, WireError, check_actor_id, decode_batch, pb};

/// One message of an actor's ingest stream. `(actor_id, incarnation, sequence)` identifies it
/// for exactly-once storage; sequences start at 1 per incarnation, and incarnations are never 0.
#[derive(Debug, Clone, PartialEq)]
pub struct IngestMessage {
    pub actor_id: String,
    pub incarnation: u64,
    pub sequence: u64,
    pub item: IngestItem,
}

/// What an ingest message carries.
// An episode summary carries the batch variant's 224 bytes of room (its seven vectors' headers,
// not their contents): a few KiB for an actor's whole window of unacknowledged messages, against
// a box per batch.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum IngestItem {
    Batch(DecodedBatch),
    /// A finished training episode, sent after its last batch (the rate limiter counts these).
    Episode {
        env_steps: u64,
        success: bool,
        weights_version: u64,
    },
}

/// An ingest message borrowed from where it lies: an [`IngestMessage`] ([`IngestMessage::view`]),
/// or a packed message in shared memory ([`unpack_ingest`](crate::unpack_ingest)), read in place.
/// This is what the learner ingests; its batch is not checked yet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IngestRef<'a> {
    pub actor_id: &'a str,
    pub incarnation: u64,
    pub sequence: u64,
    pub item: IngestItemRef<'a>,
}

/// What an [`IngestRef`] carries.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum IngestItemRef<'a> {
    Batch {
        level: usize,
        weights_version: u64,
        batch: BatchRef<'a>,
    },
    Episode {
        env_steps: u64,
        success: bool,
        weights_version: u64,
    },
}

impl IngestMessage {
    pub fn view(&self) -> IngestRef<'_> {
        IngestRef {
            actor_id: &self.actor_id,
            incarnation: self.incarnation,
            sequence: self.sequence,
            item: self.item.view(),
        }
    }
}

impl IngestItem {
    pub fn view(&self) -> IngestItemRef<'_> {
        match self {
            Self::Batch(decoded) => IngestItemRef::Batch {
                level: decoded.level,
                weights_version: decoded.weights_version,
                batch: decoded.batch.view(),
            },
            &Self::Episode {
                env_steps,
                success,
                weights_version,
            } => IngestItemRef::Episode {
                env_steps,
                success,
                weights_version,
            },
        }
    }
}

/// Validates an ingest request: the identifying fields are set (the actor id within
/// [`MAX_ACTOR_ID_BYTES`](crate::MAX_ACTOR_ID_BYTES)), an item is present, and a batch passes
/// [`decode_batch`] against `dims` and `max_count`. Moves the id and the item out of `msg`
/// (nothing is copied); on error the id is left in place, so that the refusal can name the actor.
pub fn decode_ingest(
    msg: &mut pb::IngestRequest,
    dims: &[LevelDims],
    max_count: usize,
) -> Result<IngestMessage, WireError> {
    check_actor_id("ingest_request.actor_id", &msg.actor_id)?;
    if msg.incarnation == 0 {
        return Err(WireError::missing("ingest_request.incarnation"));
    }
    if msg.sequence == 0 {
        return Err(WireError::missing("ingest_request.sequence"));
    }
    let item = match msg.item.take().ok_or(WireError::NoIngestItem)? {
        pb::ingest_request::Item::Batch(batch) => {
            IngestItem::Batch(decode_batch(batch, dims, max_count)?)
        }
        pb::ingest_request::Item::Episode(episode) => IngestItem::Episode {
            env_steps: episode.env_steps,
            success: episode.success,
            weights_version: episode.weights_version,
        },
    };
    Ok(IngestMessage {
        actor_id: std::mem::take(&mut msg.actor_id),
        incarnation: msg.incarnation,
        sequence: msg.sequence,
        item,
    })
}

impl From<IngestMessage> for pb::IngestRequest {
    fn from(msg: IngestMessage) -> Self {
        let item = match msg.item {
            IngestItem::Batch(batch) => pb::ingest_request::Item::Batch(batch.into()),
            IngestItem::Episode {
                env_steps,
                success,
                weights_version,
            } => pb::ingest_request::Item::Episode(pb::EpisodeSummary {
                env_steps,
                success,
                weights_version,
            }),
        };
        Self {
            actor_id: msg.actor_id,
            incarnation: msg.incarnation,
            sequence: msg.sequence,
            item: Some(item),
        }
    }
}

#[cfg(test)]
mod tests {
    use hac_core::Batch;
    use proptest::prelude::*;
    use prost::Message;

    use super::*;

    /// An expected error message and the change to a valid message that provokes it.
    type Case<M> = (&'static str, fn(&mut M));

    const DIMS: [LevelDims; 2] = [
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
    ];

    fn batch_message(len: usize) -> IngestMessage {
        let mut batch = Batch::zeros(DIMS[1], len);
        batch.rewards.fill(-1.0);
        IngestMessage {
            actor_id: "actor-0".into(),
            incarnation: 3,
            sequence: 1,
            item: IngestItem::Batch(DecodedBatch {
                level: 1,
                weights_version: 9,
                batch,
            }),
        }
    }

    fn through_the_wire(msg: IngestMessage) -> Result<IngestMessage, WireError> {
        let bytes = pb::IngestRequest::from(msg).encode_to_vec();
        let mut decoded =
            pb::IngestRequest::decode(bytes.as_slice()).expect("prost decodes its own bytes");
        decode_ingest(&mut decoded, &DIMS, 64)
    }

    proptest! {
        #[test]
        fn episodes_round_trip(
            env_steps in any::<u64>(),
            success in any::<bool>(),
            weights_version in any::<u64>(),
            incarnation in 1u64..,
            sequence in 1u64..,
        ) {
            let msg = IngestMessage {
                actor_id: "a".into(),
                incarnation,
                sequence,
                item: IngestItem::Episode { env_steps, success, weights_version },
            };
            prop_assert_eq!(through_the_wire(msg.clone()).expect("valid"), msg);
        }
    }

    #[test]
    fn batches_round_trip() {
        let msg = batch_message(5);
        assert_eq!(through_the_wire(msg.clone()).expect("valid"), msg);
    }

    #[test]
    fn identifying_fields_are_required() {
        let cases: [Case<IngestMessage>; 3] = [
            ("missing field ingest_request.actor_id", |m| {
                m.actor_id.clear()
            }),
            ("missing field ingest_request.incarnation", |m| {
                m.incarnation = 0
            }),
            ("missing field ingest_request.sequence", |m| m.sequence = 0),
        ];
        for (expected, mutate) in cases {
            let mut msg = batch_message(2);
            mutate(&mut msg);
            let err = through_the_wire(msg).expect_err("a field is missing");
            assert!(matches!(err, WireError::MissingField { .. }));
            assert_eq!(err.to_string(), expected);
        }
    }

    #[test]
    fn a_request_without_an_item_is_refused() {
        let mut msg = pb::IngestRequest::from(batch_message(2));
        msg.item = None;
        let err = decode_ingest(&mut msg, &DIMS, 64).expect_err("no item");
        assert_eq!(err.to_string(), "ingest request has no item");
    }

    #[test]
    fn a_long_actor_id_is_refused_and_a_refused_message_keeps_its_id() {
        let mut msg = pb::IngestRequest::from(batch_message(2));
        msg.actor_id = "x".repeat(300);
        let err = decode_ingest(&mut msg, &DIMS, 64).expect_err("an id above the limit");
        assert_eq!(
            err.to_string(),
            "ingest_request.actor_id is 300 bytes, above the limit of 256 bytes"
        );

        let mut msg = pb::IngestRequest::from(batch_message(65));
        decode_ingest(&mut msg, &DIMS, 64).expect_err("too large");
        assert_eq!(msg.actor_id, "actor-0");
    }

    #[test]
    fn the_batch_inside_is_validated() {
        let err = through_the_wire(batch_message(65)).expect_err("too large");
        assert_eq!(err.to_string(), "batch.count 65 above the limit 64");
    }
}
