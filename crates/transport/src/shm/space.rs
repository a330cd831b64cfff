//! Room in the shared-memory file system, checked before anything is mapped: tmpfs reserves no
//! pages when a segment is created, so without this check a full `/dev/shm` shows only later, as
//! SIGBUS on the first write to a page it cannot supply.

use std::path::Path;

use super::ShmError;

/// Where iceoryx2 keeps its segments on Linux.
pub const SHM_DIR: &str = "/dev/shm";

/// iceoryx2's bookkeeping per chunk and segment, generously: the estimate must not fall short.
const CHUNK_OVERHEAD: u64 = 256;
const SEGMENT_OVERHEAD: u64 = 1 << 20;

/// Bytes of a data segment of `chunks` chunks of `payload` bytes each (for
/// [`check_free_space`]).
pub fn segment_bytes(chunks: usize, payload: usize) -> u64 {
    chunks as u64
        * (payload as u64)
            .next_multiple_of(64)
            .saturating_add(CHUNK_OVERHEAD)
        + SEGMENT_OVERHEAD
}

/// Fails with [`ShmError::NoSpace`] unless the file system at `dir` has `needed` bytes free.
/// `what` names who needs them and `lower` what to lower instead of raising the size, for the
/// message. A file system that cannot be queried passes (iceoryx2 reports its own errors).
pub fn check_free_space(
    dir: &Path,
    needed: u64,
    what: &'static str,
    lower: &'static str,
) -> Result<(), ShmError> {
    let Ok(stats) = rustix::fs::statvfs(dir) else {
        return Ok(());
    };
    let free = stats.f_bavail.saturating_mul(stats.f_frsize);
    if free >= needed {
        return Ok(());
    }
    let mib = |bytes: u64| bytes.div_ceil(1 << 20);
    Err(ShmError::NoSpace {
        what,
        dir: dir.display().to_string(),
        needed_mib: mib(needed),
        free_mib: free >> 20,
        total_mib: stats.f_blocks.saturating_mul(stats.f_frsize) >> 20,
        lower,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn too_little_room_is_a_clear_error() {
        let err = check_free_space(
            Path::new(SHM_DIR),
            u64::MAX / 2,
            "the learner's shared memory",
            "lower --shm-max-actors",
        )
        .expect_err("no file system has 8 EiB free");
        let text = err.to_string();
        assert!(
            text.starts_with("the learner's shared memory needs about 8796093022208 MiB"),
            "{text}"
        );
        for hint in [
            "/dev/shm",
            "--shm-size",
            "medium: Memory",
            "sizeLimit",
            "lower --shm-max-actors",
        ] {
            assert!(text.contains(hint), "{hint} in {text}");
        }
        assert!(check_free_space(Path::new(SHM_DIR), 1, "x", "y").is_ok());
    }

    #[test]
    fn segments_are_estimated_above_their_payload() {
        let bytes = segment_bytes(34, 40_000);
        assert!(bytes > 34 * 40_000, "{bytes}");
        assert!(bytes < 34 * 40_000 * 2, "{bytes}");
    }
}
