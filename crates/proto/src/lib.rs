//! HAC's wire contract: the `hac.v1` gRPC code generated from `proto/hac/v1/*.proto`, and the
//! conversions between its messages and the core types. This is the only crate that knows prost
//! and tonic's codegen; everything above it works with the domain types below, and every message
//! coming in is validated here, with a [`WireError`] that names the offending field.
//!
//! - [`pb`]: the generated messages, the `Learner` and `Status` clients and servers.
//! - [`FILE_DESCRIPTOR_SET`]: the compiled protos, for the gRPC reflection service.
//! - `batch`: transition batches ([`decode_batch`], [`decode_batch_into`], [`encode_batch`],
//!   [`encode_batch_into`]), checked against the run's [`LevelDims`](hac_core::LevelDims).
//! - `ingest`: the ingest stream's messages ([`IngestMessage`], [`IngestItem`], [`decode_ingest`]),
//!   and their borrowed form [`IngestRef`], which the learner ingests.
//! - `packed`: the shared-memory form of ingest messages and weights ([`pack_ingest`],
//!   [`unpack_ingest`] reading a batch in place, [`pack_weights`], [`unpack_weights`]).
//! - `weights`: [`WeightsSnapshot`], the [`WeightsWatch`] request, and [`BestWeights`] (the
//!   snapshot behind a run's best test round).
//! - `published`: [`Published`], the latest weights as a learner publishes them and a link
//!   delivers them to an actor.
//! - `reject`: [`RejectReason`], why an input was refused (status counts, metrics, and the
//!   `hac-reject-reason` metadata).
//! - `learner`: [`Registration`], [`Admission`] (with the per-level dimensions and the
//!   [`ShmOffer`]), [`Evaluation`].
//! - `limits`: the length limits on the strings of every request message
//!   ([`MAX_ACTOR_ID_BYTES`], [`MAX_HOSTNAME_BYTES`], [`MAX_TRANSPORTS`],
//!   [`MAX_TRANSPORT_NAME_BYTES`]), [`check_actor_id`], and [`Clipped`], an id as echoed in errors
//!   and logs.
//! - `error`: [`WireError`].
//!
//! Conversions follow one pattern: `TryFrom<pb::X>` for what comes in, `From<X> for pb::X` for
//! what goes out; batches, which need the run's dimensions to be checked, use functions instead.

mod batch;
mod error;
mod ingest;
mod learner;
mod limits;
mod packed;
mod published;
mod reject;
mod weights;

pub use batch::{
    BatchHeader, DecodedBatch, check_batch, decode_batch, decode_batch_into, encode_batch,
    encode_batch_into,
};
pub use error::WireError;
pub use ingest::{IngestItem, IngestItemRef, IngestMessage, IngestRef, decode_ingest};
pub use learner::{ActorRole, Admission, Evaluation, PreviousIncarnation, Registration, ShmOffer};
pub use limits::{
    Clipped, ECHO_BYTES, MAX_ACTOR_ID_BYTES, MAX_HOSTNAME_BYTES, MAX_TRANSPORT_NAME_BYTES,
    MAX_TRANSPORTS, check_actor_id,
};
pub use packed::{
    PACKED_ALIGNMENT, max_packed_ingest_len, pack_ingest, pack_weights, packed_ingest_identity,
    packed_ingest_len, packed_weights_len, unpack_ingest, unpack_weights,
};
pub use published::Published;
pub use reject::RejectReason;
pub use weights::{BestWeights, WeightsSnapshot, WeightsWatch};

/// The generated `hac.v1` package: messages, `learner_client`/`learner_server`,
/// `status_client`/`status_server`.
pub mod pb {
    tonic::include_proto!("hac.v1");
}

/// The serialized `FileDescriptorSet` of the three protos, for `tonic-reflection`.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("hac_v1_descriptor");

#[cfg(test)]
mod tests {
    use prost::Message;
    use prost_types::FileDescriptorSet;

    use super::FILE_DESCRIPTOR_SET;

    #[test]
    fn the_descriptor_set_lists_the_three_files_and_both_services() {
        let set = FileDescriptorSet::decode(FILE_DESCRIPTOR_SET).expect("a valid descriptor set");
        let mut files: Vec<&str> = set.file.iter().map(|f| f.name()).collect();
        files.sort_unstable();
        assert_eq!(
            files,
            [
                "hac/v1/learner.proto",
                "hac/v1/status.proto",
                "hac/v1/transitions.proto"
            ]
        );
        assert!(set.file.iter().all(|f| f.package() == "hac.v1"));

        let mut services: Vec<String> = set
            .file
            .iter()
            .flat_map(|f| {
                f.service
                    .iter()
                    .map(move |s| format!("{}.{}", f.package(), s.name()))
            })
            .collect();
        services.sort_unstable();
        assert_eq!(services, ["hac.v1.Learner", "hac.v1.Status"]);
        let learner = set
            .file
            .iter()
            .flat_map(|f| &f.service)
            .find(|s| s.name() == "Learner")
            .expect("the Learner service");
        let methods: Vec<&str> = learner.method.iter().map(|m| m.name()).collect();
        assert_eq!(
            methods,
            [
                "Register",
                "Ingest",
                "WatchWeights",
                "ReportEvaluation",
                "AwaitTurn"
            ]
        );
    }
}
