//! Length limits on the strings of the request messages, checked wherever a wire message becomes
//! a domain type (the `TryFrom` conversions, [`decode_ingest`](crate::decode_ingest),
//! [`unpack_ingest`](crate::unpack_ingest)): an id is kept in the learner's registry, shown in
//! status and metrics and echoed in errors, so an unbounded one makes every one of those
//! unbounded. Each check is a comparison, made before anything is copied.

use std::borrow::Cow;
use std::fmt;

use crate::WireError;

/// Longest actor id, in bytes (UTF-8): room for a Kubernetes pod name (at most 253) or a
/// host-and-index name.
pub const MAX_ACTOR_ID_BYTES: usize = 256;
/// Longest host name in a registration, in bytes: a DNS name is at most 253.
pub const MAX_HOSTNAME_BYTES: usize = 255;
/// Most transports one registration may list (there are two: "grpc", "shm").
pub const MAX_TRANSPORTS: usize = 8;
/// Longest transport name in a registration, in bytes.
pub const MAX_TRANSPORT_NAME_BYTES: usize = 32;
/// Bytes of an id echoed in an error or a log line before [`Clipped`] cuts it.
pub const ECHO_BYTES: usize = 64;

/// Refuses an empty actor id, one above [`MAX_ACTOR_ID_BYTES`], or one with a control character;
/// `field` names it in the error (`message.actor_id`).
pub fn check_actor_id(field: &'static str, actor_id: &str) -> Result<(), WireError> {
    if actor_id.is_empty() {
        return Err(WireError::missing(field));
    }
    check_len(field, actor_id, MAX_ACTOR_ID_BYTES)
}

/// Refuses `value` if it is longer than `limit` bytes or holds a control character (checked only
/// once the length is: at most `limit` characters are scanned).
pub(crate) fn check_len(field: &'static str, value: &str, limit: usize) -> Result<(), WireError> {
    if value.len() > limit {
        return Err(WireError::TooLong {
            field: Cow::Borrowed(field),
            len: value.len(),
            limit,
        });
    }
    match value.char_indices().find(|(_, c)| c.is_control()) {
        Some((at, c)) => Err(WireError::ControlCharacter {
            field: Cow::Borrowed(field),
            code: c as u32,
            at,
        }),
        None => Ok(()),
    }
}

/// An id as echoed in errors and logs: whole up to [`ECHO_BYTES`], else its first
/// [`ECHO_BYTES`] (cut at a character boundary) and `... (N bytes)`. Formats without allocating.
#[derive(Debug, Clone, Copy)]
pub struct Clipped<'a>(pub &'a str);

impl<'a> Clipped<'a> {
    /// The part shown: the whole id up to [`ECHO_BYTES`], else its longest prefix of at most
    /// [`ECHO_BYTES`] that ends at a character boundary.
    pub fn head(&self) -> &'a str {
        let id = self.0;
        if id.len() <= ECHO_BYTES {
            return id;
        }
        let mut end = ECHO_BYTES;
        while !id.is_char_boundary(end) {
            end -= 1;
        }
        &id[..end]
    }
}

impl fmt::Display for Clipped<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let head = self.head();
        if head.len() == self.0.len() {
            f.write_str(head)
        } else {
            write!(f, "{head}... ({} bytes)", self.0.len())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_checked_against_the_limit() {
        assert!(check_actor_id("x.actor_id", &"a".repeat(MAX_ACTOR_ID_BYTES)).is_ok());
        let err = check_actor_id("x.actor_id", &"a".repeat(MAX_ACTOR_ID_BYTES + 1)).unwrap_err();
        assert_eq!(
            err.to_string(),
            "x.actor_id is 257 bytes, above the limit of 256 bytes"
        );
        let err = check_actor_id("x.actor_id", "").unwrap_err();
        assert_eq!(err.to_string(), "missing field x.actor_id");
    }

    #[test]
    fn ids_with_control_characters_are_refused() {
        // A newline would forge a line in the learner's log; an escape, the operator's terminal.
        for (id, code, at) in [
            ("a\nb", 0x0A, 1),
            ("\u{1b}[2J", 0x1B, 0),
            ("ok\u{7f}", 0x7F, 2),
        ] {
            let err = check_actor_id("x.actor_id", id).unwrap_err();
            assert_eq!(
                err.to_string(),
                format!("x.actor_id has a control character (U+{code:04X}) at byte {at}")
            );
        }
        assert!(check_actor_id("x.actor_id", "pod-7.élan").is_ok());
    }

    #[test]
    fn long_ids_are_clipped_at_a_character_boundary() {
        assert_eq!(Clipped("actor-7").to_string(), "actor-7");
        let exact = "b".repeat(ECHO_BYTES);
        assert_eq!(Clipped(&exact).to_string(), exact);
        let long = "a".repeat(1 << 20);
        assert_eq!(
            Clipped(&long).to_string(),
            format!("{}... (1048576 bytes)", "a".repeat(ECHO_BYTES))
        );
        // A two-byte character straddling the cut is left out whole.
        let straddling = format!("{}é{}", "a".repeat(ECHO_BYTES - 1), "z".repeat(10));
        assert_eq!(
            Clipped(&straddling).to_string(),
            format!("{}... (75 bytes)", "a".repeat(ECHO_BYTES - 1))
        );
    }
}
