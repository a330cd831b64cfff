//! The write-ahead log: every ingest message the learner stored since its newest checkpoint, on
//! disk, so that a learner killed outright loses nothing it said was durable.
//!
//! # What and when
//! [`Wal::append`] copies a stored message (exactly what ingest stored: after every check and
//! admission, never a duplicate or a refused one) with its replay shard into the open *group*, an
//! in-memory buffer, under a short lock of its own; it assigns the record its log sequence number
//! (LSN, consecutive from 1 over the run). A writer thread commits groups: it swaps the open
//! group for an empty one (the buffers are reused, nothing is allocated per message), computes
//! every record's checksum, writes the group to the current segment and `fdatasync`s it, at most
//! every `interval` and at once when the open group holds `commit_bytes` (the size trigger). Only
//! then are the group's messages *durable*: [`Wal::durable_through`] says, per actor, the highest
//! sequence of its incarnation that is, and [`Wal::commits`] wakes whoever waits for that. Ingest
//! waits (backpressure) while the open group holds `max_pending_bytes` and the writer is behind.
//!
//! # On disk
//! `<dir>/wal-<first LSN, 20 digits>.log` segments, each a sequence of records:
//!
//! ```text
//! offset  size  field
//!      0     4  magic "HACr"
//!      4     4  payload length in bytes (before padding)
//!      8     8  LSN
//!     16     4  replay shard the message's batch went to
//!     20     4  CRC-32 (IEEE) of bytes 4..20 and of the padded payload
//!     24     .  payload: the message packed as for shared memory (`hac_proto::pack_ingest`,
//!               native-endian), zero-padded to a multiple of 8 bytes
//! ```
//!
//! A new segment starts when the current one passes `segment_bytes`, and at every checkpoint's
//! cut ([`Wal::cut`]), so that once the checkpoint is safely written the segments before its cut
//! can be deleted whole ([`Wal::truncate_before`]): the log holds what came after the newest
//! checkpoint.
//!
//! # Reading it back
//! [`Wal::open`] reads every segment in LSN order and checks each record: its magic, that its
//! length fits, its checksum, and that its LSN follows the previous one. The first record that
//! fails ends the log: a torn tail from a kill is cut off (the segment truncated at the last good
//! record, later segments deleted), never misread, and the count of bytes cut is logged. The
//! records at and after a checkpoint's cut are handed to the learner to store again.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hac_proto::{
    IngestRef, WireError, pack_ingest, packed_ingest_identity, packed_ingest_len, unpack_ingest,
};
use parking_lot::{Condvar, Mutex};

use crate::Published;

const MAGIC: [u8; 4] = *b"HACr";
const HEADER: usize = 24;
const PREFIX: &str = "wal-";
const SUFFIX: &str = ".log";

/// How the log is written.
#[derive(Debug, Clone, PartialEq)]
pub struct WalOptions {
    /// The log's directory (created if missing).
    pub dir: PathBuf,
    /// Longest time a stored message waits to be committed (group commit: one `fdatasync` per
    /// interval at most, unless the size trigger fires first).
    pub interval: Duration,
    /// Commit at once when the open group holds this many bytes.
    pub commit_bytes: usize,
    /// Ingest waits while the open group holds this many bytes (the writer is behind).
    pub max_pending_bytes: usize,
    /// Start a new segment once the current one holds this many bytes.
    pub segment_bytes: u64,
}

impl WalOptions {
    /// Defaults for a log in `dir`, committed every `interval`.
    pub fn new(dir: impl Into<PathBuf>, interval: Duration) -> Self {
        Self {
            dir: dir.into(),
            interval,
            commit_bytes: 1 << 20,
            max_pending_bytes: 16 << 20,
            segment_bytes: 64 << 20,
        }
    }
}

/// Why the log could not be opened or written.
#[derive(Debug, thiserror::Error)]
pub enum WalError {
    #[error("write-ahead log {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("write-ahead log {path}: record {lsn}: {source}")]
    Record {
        path: PathBuf,
        lsn: u64,
        #[source]
        source: WireError,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> WalError + '_ {
    move |source| WalError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One record read back.
#[derive(Debug, Clone, Copy)]
pub struct Record<'a> {
    pub lsn: u64,
    pub shard: u32,
    pub message: IngestRef<'a>,
}

/// What [`Wal::open`] found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Recovered {
    /// Records read (at and after `from`).
    pub records: u64,
    /// Bytes cut off at the end (a torn tail, or everything after a damaged record).
    pub cut_bytes: u64,
    /// Why the log was cut, if it was.
    pub cut_reason: Option<String>,
    /// The LSN the next record gets.
    pub next_lsn: u64,
}

/// Live figures of the log, for status and metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WalStatus {
    /// Bytes in the segments on disk.
    pub bytes: u64,
    pub segments: u64,
    /// Records appended, and committed (durable).
    pub appended: u64,
    pub committed: u64,
    /// Commits (`fdatasync`s) so far, and the last one's duration.
    pub commits: u64,
    pub last_commit: Duration,
    /// Why the log stopped committing (a write or sync failed), if it did: nothing more becomes
    /// durable until the learner restarts.
    pub failed: bool,
}

/// The open group and where the writer is.
#[derive(Debug)]
struct Pending {
    buf: Vec<u8>,
    next_lsn: u64,
    /// A checkpoint's cut inside `buf`: (byte offset, LSN of the first record after it).
    cut: Option<(usize, u64)>,
    /// When the oldest record in `buf` was appended.
    oldest: Option<Instant>,
    closing: bool,
    /// Stop without committing the open group ([`Wal::abandon`]).
    abandoned: bool,
    /// Commit now, whatever the interval says ([`Wal::sync`]).
    now: bool,
    /// The writer is writing a group now.
    writing: bool,
}

#[derive(Debug)]
struct Inner {
    options: WalOptions,
    pending: Mutex<Pending>,
    /// The writer waits here for work; ingest and [`Wal::sync`] wait here for room or a commit.
    changed: Condvar,
    /// `actor -> (incarnation, highest sequence committed)`.
    durable: Mutex<HashMap<String, (u64, u64)>>,
    /// Commits so far; waitable from tasks.
    commits: Published<u64>,
    bytes: AtomicU64,
    segments: AtomicU64,
    committed_lsn: AtomicU64,
    commit_count: AtomicU64,
    last_commit_ns: AtomicU64,
    failed: Mutex<Option<String>>,
}

/// The learner's write-ahead log; see the module docs.
#[derive(Debug)]
pub struct Wal {
    inner: Arc<Inner>,
    writer: Mutex<Option<JoinHandle<()>>>,
}

impl Wal {
    /// Opens the log in `options.dir`: reads it back, handing every intact record at or after
    /// LSN `from` to `each` in order (a torn or damaged tail is cut off first), then starts a new
    /// segment and the writer thread. A missing directory is an empty log.
    pub fn open(
        options: WalOptions,
        from: u64,
        mut each: impl FnMut(Record<'_>),
    ) -> Result<(Self, Recovered), WalError> {
        let dir = options.dir.clone();
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let segments = list_segments(&dir)?;
        let mut recovered = Recovered {
            next_lsn: from.max(1),
            ..Recovered::default()
        };
        // The LSN the next record must have (unknown before the first segment).
        let mut expected: Option<u64> = None;
        let mut cut_at: Option<usize> = None;
        let mut words: Vec<u64> = Vec::new();
        for (index, (first, path)) in segments.iter().enumerate() {
            let len = std::fs::metadata(path).map_err(io(path))?.len() as usize;
            words.clear();
            words.resize(len.div_ceil(8), 0);
            let bytes = &mut bytemuck::cast_slice_mut::<u64, u8>(&mut words)[..len];
            read_exact(path, bytes)?;
            if expected.is_some_and(|e| e != *first) {
                recovered.cut_reason = Some(format!(
                    "{} starts at record {first}, the one before ended at {}",
                    file_name(path),
                    expected.unwrap_or_default() - 1
                ));
                cut_at = Some(index);
                break;
            }
            let mut at = 0;
            let mut lsn = *first;
            while at < len {
                match check_record(&bytes[at..], lsn) {
                    Ok((size, shard)) => {
                        let payload = &bytes[at + HEADER..at + HEADER + size];
                        let message =
                            unpack_ingest(payload).map_err(|source| WalError::Record {
                                path: path.clone(),
                                lsn,
                                source,
                            })?;
                        if lsn >= from {
                            each(Record {
                                lsn,
                                shard,
                                message,
                            });
                            recovered.records += 1;
                        }
                        at += HEADER + size.next_multiple_of(8);
                        lsn += 1;
                    }
                    Err(why) => {
                        recovered.cut_reason = Some(format!(
                            "{} at byte {at} (record {lsn}): {why}",
                            file_name(path)
                        ));
                        recovered.cut_bytes += (len - at) as u64;
                        let file = OpenOptions::new()
                            .write(true)
                            .open(path)
                            .map_err(io(path))?;
                        file.set_len(at as u64).map_err(io(path))?;
                        file.sync_all().map_err(io(path))?;
                        break;
                    }
                }
            }
            expected = Some(lsn);
            recovered.next_lsn = recovered.next_lsn.max(lsn);
            if recovered.cut_reason.is_some() {
                cut_at = Some(index + 1);
                break;
            }
        }
        if let Some(index) = cut_at {
            for (_, path) in &segments[index..] {
                recovered.cut_bytes += std::fs::metadata(path).map_or(0, |m| m.len());
                std::fs::remove_file(path).map_err(io(path))?;
            }
        }
        if let Some(why) = &recovered.cut_reason {
            tracing::warn!(
                reason = %why,
                cut_bytes = recovered.cut_bytes,
                "write-ahead log cut at its first damaged record (a torn tail after a kill is expected)"
            );
        }
        let next_lsn = recovered.next_lsn;
        let wal = Self::start(options, next_lsn)?;
        Ok((wal, recovered))
    }

    fn start(options: WalOptions, next_lsn: u64) -> Result<Self, WalError> {
        let dir = options.dir.clone();
        let (file, path) = new_segment(&dir, next_lsn)?;
        let on_disk: Vec<(u64, PathBuf)> = list_segments(&dir)?;
        let bytes = on_disk
            .iter()
            .map(|(_, p)| std::fs::metadata(p).map_or(0, |m| m.len()))
            .sum();
        let inner = Arc::new(Inner {
            pending: Mutex::new(Pending {
                buf: Vec::with_capacity(options.commit_bytes.min(16 << 20)),
                next_lsn,
                cut: None,
                oldest: None,
                closing: false,
                abandoned: false,
                now: false,
                writing: false,
            }),
            options,
            changed: Condvar::new(),
            durable: Mutex::default(),
            commits: Published::default(),
            bytes: AtomicU64::new(bytes),
            segments: AtomicU64::new(on_disk.len() as u64),
            committed_lsn: AtomicU64::new(next_lsn - 1),
            commit_count: AtomicU64::new(0),
            last_commit_ns: AtomicU64::new(0),
            failed: Mutex::new(None),
        });
        inner.commits.publish(Arc::new(0));
        let writer = {
            let inner = inner.clone();
            std::thread::Builder::new()
                .name("wal-writer".into())
                .spawn(move || inner.write_loop(file, path))
                .map_err(io(&dir))?
        };
        Ok(Self {
            inner,
            writer: Mutex::new(Some(writer)),
        })
    }

    /// Appends a stored message (its batch went to replay shard `shard`); returns its LSN. The
    /// caller appends an actor's messages in its sequence order. Waits while the open group is
    /// full and the writer behind (backpressure).
    pub fn append(&self, shard: u32, message: &IngestRef<'_>) -> u64 {
        let size = packed_ingest_len(message);
        let inner = &self.inner;
        let mut pending = inner.pending.lock();
        while pending.buf.len() >= inner.options.max_pending_bytes && !pending.closing {
            inner.changed.notify_all();
            inner
                .changed
                .wait_for(&mut pending, Duration::from_millis(100));
        }
        let lsn = pending.next_lsn;
        pending.next_lsn += 1;
        let start = pending.buf.len();
        pending
            .buf
            .resize(start + HEADER + size.next_multiple_of(8), 0);
        let record = &mut pending.buf[start..];
        record[0..4].copy_from_slice(&MAGIC);
        record[4..8].copy_from_slice(&(size as u32).to_le_bytes());
        record[8..16].copy_from_slice(&lsn.to_le_bytes());
        record[16..20].copy_from_slice(&shard.to_le_bytes());
        pack_ingest(message, &mut record[HEADER..]);
        pending.oldest.get_or_insert_with(Instant::now);
        if pending.buf.len() >= inner.options.commit_bytes {
            inner.changed.notify_all();
        }
        lsn
    }

    /// A checkpoint's cut, taken while nothing is appended: the LSN of the first record after
    /// it. The writer starts a new segment there, so that the segments before can be deleted
    /// once the checkpoint is written ([`truncate_before`](Self::truncate_before)).
    pub fn cut(&self) -> u64 {
        let mut pending = self.inner.pending.lock();
        let lsn = pending.next_lsn;
        let at = pending.buf.len();
        pending.cut = Some((at, lsn));
        lsn
    }

    /// Deletes every segment whose records are all before `lsn` (a checkpoint's cut, once the
    /// checkpoint is written); the segment being written is kept.
    pub fn truncate_before(&self, lsn: u64) -> Result<u64, WalError> {
        let dir = &self.inner.options.dir;
        let segments = list_segments(dir)?;
        let mut removed = 0;
        for pair in segments.windows(2) {
            let ((_, path), (next_first, _)) = (&pair[0], &pair[1]);
            if *next_first <= lsn {
                let bytes = std::fs::metadata(path).map_or(0, |m| m.len());
                std::fs::remove_file(path).map_err(io(path))?;
                self.inner.bytes.fetch_sub(bytes, Ordering::Relaxed);
                self.inner.segments.fetch_sub(1, Ordering::Relaxed);
                removed += bytes;
            }
        }
        if removed > 0 {
            sync_dir(dir)?;
        }
        Ok(removed)
    }

    /// The highest sequence of `actor_id`'s `incarnation` that is committed (0: none).
    pub fn durable_through(&self, actor_id: &str, incarnation: u64) -> u64 {
        match self.inner.durable.lock().get(actor_id) {
            Some(&(inc, seq)) if inc == incarnation => seq,
            _ => 0,
        }
    }

    /// Declares `actor_id`'s `incarnation` durable through `sequence` (what a resumed learner
    /// recovered from its checkpoint and this log).
    pub fn set_durable(&self, actor_id: &str, incarnation: u64, sequence: u64) {
        self.inner
            .durable
            .lock()
            .insert(actor_id.to_string(), (incarnation, sequence));
    }

    /// The number of commits so far, published after each: wait on it for durability to advance.
    pub fn commits(&self) -> &Published<u64> {
        &self.inner.commits
    }

    /// Waits until everything appended so far is committed (or the log failed or closed).
    pub fn sync(&self, timeout: Duration) -> bool {
        let inner = &self.inner;
        let deadline = Instant::now() + timeout;
        let mut pending = inner.pending.lock();
        let target = pending.next_lsn - 1;
        pending.now = true;
        loop {
            if inner.committed_lsn.load(Ordering::Acquire) >= target {
                return true;
            }
            if inner.failed.lock().is_some() || Instant::now() >= deadline {
                return false;
            }
            inner.changed.notify_all();
            inner
                .changed
                .wait_for(&mut pending, Duration::from_millis(20));
        }
    }

    pub fn status(&self) -> WalStatus {
        let inner = &self.inner;
        WalStatus {
            bytes: inner.bytes.load(Ordering::Relaxed),
            segments: inner.segments.load(Ordering::Relaxed),
            appended: inner.pending.lock().next_lsn - 1,
            committed: inner.committed_lsn.load(Ordering::Acquire),
            commits: inner.commit_count.load(Ordering::Relaxed),
            last_commit: Duration::from_nanos(inner.last_commit_ns.load(Ordering::Relaxed)),
            failed: inner.failed.lock().is_some(),
        }
    }

    /// Stops the writer without committing the open group, as a kill would (for tests of
    /// recovery); what was committed stays.
    pub fn abandon(&self) {
        self.inner.pending.lock().abandoned = true;
        self.close();
    }

    /// Commits what is appended and stops the writer.
    pub fn close(&self) {
        self.inner.pending.lock().closing = true;
        self.inner.changed.notify_all();
        if let Some(writer) = self.writer.lock().take() {
            let _ = writer.join();
        }
    }
}

impl Drop for Wal {
    fn drop(&mut self) {
        self.close();
    }
}

impl Inner {
    /// The writer thread: commits groups (see the module docs) until closed.
    fn write_loop(&self, mut file: File, mut path: PathBuf) {
        let mut spare: Vec<u8> = Vec::with_capacity(self.options.commit_bytes.min(16 << 20));
        let mut written: u64 = 0;
        loop {
            let (mut group, cut, closing) = {
                let mut pending = self.pending.lock();
                loop {
                    if pending.abandoned {
                        return;
                    }
                    let due = pending.oldest.is_some_and(|t| {
                        pending.now
                            || t.elapsed() >= self.options.interval
                            || pending.buf.len() >= self.options.commit_bytes
                    });
                    if due || pending.closing || pending.cut.is_some() && pending.buf.is_empty() {
                        break;
                    }
                    let wait = pending.oldest.map_or(self.options.interval, |t| {
                        self.options.interval.saturating_sub(t.elapsed())
                    });
                    self.changed
                        .wait_for(&mut pending, wait.max(Duration::from_millis(1)));
                }
                let group = std::mem::replace(&mut pending.buf, std::mem::take(&mut spare));
                pending.oldest = None;
                pending.now = false;
                pending.writing = true;
                let cut = pending.cut.take();
                let closing = pending.closing;
                self.changed.notify_all();
                (group, cut, closing)
            };
            if self.failed.lock().is_none() {
                let started = Instant::now();
                let result = self.commit(&mut group, cut, &mut file, &mut path, &mut written);
                match result {
                    Ok(()) => {
                        self.last_commit_ns.store(
                            u64::try_from(started.elapsed().as_nanos()).unwrap_or(u64::MAX),
                            Ordering::Relaxed,
                        );
                        let n = self.commit_count.fetch_add(1, Ordering::Relaxed) + 1;
                        self.commits.publish(Arc::new(n));
                    }
                    Err(e) => {
                        tracing::error!(error = %e, "write-ahead log failed: nothing more becomes durable until the learner restarts");
                        *self.failed.lock() = Some(e.to_string());
                    }
                }
            }
            group.clear();
            spare = group;
            {
                let mut pending = self.pending.lock();
                pending.writing = false;
                self.changed.notify_all();
                if closing && pending.buf.is_empty() {
                    return;
                }
            }
        }
    }

    /// Writes and syncs one group (starting a new segment at a checkpoint's cut or when the
    /// current one is full), then publishes its messages as durable.
    fn commit(
        &self,
        group: &mut [u8],
        cut: Option<(usize, u64)>,
        file: &mut File,
        path: &mut PathBuf,
        written: &mut u64,
    ) -> Result<(), WalError> {
        fill_checksums(group);
        let rotate = |file: &mut File, path: &mut PathBuf, lsn: u64| {
            file.sync_data().map_err(io(path))?;
            let (new_file, new_path) = new_segment(&self.options.dir, lsn)?;
            *file = new_file;
            *path = new_path;
            self.segments.fetch_add(1, Ordering::Relaxed);
            Ok::<(), WalError>(())
        };
        if cut.is_none()
            && *written >= self.options.segment_bytes
            && let Some(lsn) = first_lsn_of(group)
        {
            rotate(file, path, lsn)?;
            *written = 0;
        }
        let split = cut.map_or(group.len(), |(at, _)| at);
        let write = |file: &mut File, path: &Path, bytes: &[u8]| {
            if !bytes.is_empty() {
                file.write_all(bytes).map_err(io(path))?;
                self.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
            }
            Ok::<u64, WalError>(bytes.len() as u64)
        };
        let mut appended = write(file, path, &group[..split])?;
        if let Some((_, lsn)) = cut {
            rotate(file, path, lsn)?;
            *written = 0;
            appended = write(file, path, &group[split..])?;
        }
        *written += appended;
        file.sync_data().map_err(io(path))?;
        // Durable now: the highest sequence per actor and incarnation in the group.
        let mut durable = self.durable.lock();
        let mut last = 0;
        for_each_record(group, |lsn, payload| {
            last = lsn;
            if let Ok((actor_id, incarnation, sequence)) = packed_ingest_identity(payload) {
                match durable.get_mut(actor_id) {
                    Some(entry) => {
                        if entry.0 != incarnation || entry.1 < sequence {
                            *entry = (incarnation, sequence);
                        }
                    }
                    None => {
                        durable.insert(actor_id.to_string(), (incarnation, sequence));
                    }
                }
            }
        });
        drop(durable);
        if last > 0 {
            self.committed_lsn.store(last, Ordering::Release);
        }
        Ok(())
    }
}

/// The LSN of the first record in `group`, if any.
fn first_lsn_of(group: &[u8]) -> Option<u64> {
    (group.len() >= HEADER).then(|| u64::from_le_bytes(group[8..16].try_into().expect("8 bytes")))
}

/// Calls `f(lsn, payload)` for every record of a group this process appended (well-formed).
fn for_each_record(group: &[u8], mut f: impl FnMut(u64, &[u8])) {
    let mut at = 0;
    while at + HEADER <= group.len() {
        let size = u32::from_le_bytes(group[at + 4..at + 8].try_into().expect("4 bytes")) as usize;
        let lsn = u64::from_le_bytes(group[at + 8..at + 16].try_into().expect("8 bytes"));
        f(lsn, &group[at + HEADER..at + HEADER + size]);
        at += HEADER + size.next_multiple_of(8);
    }
}

/// Computes and writes every record's checksum.
fn fill_checksums(group: &mut [u8]) {
    let mut at = 0;
    while at + HEADER <= group.len() {
        let size = u32::from_le_bytes(group[at + 4..at + 8].try_into().expect("4 bytes")) as usize;
        let end = at + HEADER + size.next_multiple_of(8);
        let crc = checksum(&group[at..end]);
        group[at + 20..at + 24].copy_from_slice(&crc.to_le_bytes());
        at = end;
    }
}

/// CRC-32 of a record: its LSN and shard, and its padded payload (magic, length and the
/// checksum field itself are checked otherwise).
fn checksum(record: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&record[4..20]);
    hasher.update(&record[HEADER..]);
    hasher.finalize()
}

/// Checks the record at the start of `bytes`, which must have LSN `lsn`: its payload size and
/// shard, or why it is not a valid record.
fn check_record(bytes: &[u8], lsn: u64) -> Result<(usize, u32), String> {
    if bytes.len() < HEADER {
        return Err(format!(
            "{} bytes, shorter than a record header",
            bytes.len()
        ));
    }
    if bytes[0..4] != MAGIC {
        return Err("no record magic".into());
    }
    let size = u32::from_le_bytes(bytes[4..8].try_into().expect("4 bytes")) as usize;
    let end = HEADER + size.next_multiple_of(8);
    if end > bytes.len() {
        return Err(format!(
            "a record of {end} bytes, only {} left (torn)",
            bytes.len()
        ));
    }
    let stored = u32::from_le_bytes(bytes[20..24].try_into().expect("4 bytes"));
    if checksum(&bytes[..end]) != stored {
        return Err("checksum mismatch".into());
    }
    let got = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes"));
    if got != lsn {
        return Err(format!("LSN {got}, expected {lsn}"));
    }
    let shard = u32::from_le_bytes(bytes[16..20].try_into().expect("4 bytes"));
    Ok((size, shard))
}

/// The segments in `dir`, by first LSN.
fn list_segments(dir: &Path) -> Result<Vec<(u64, PathBuf)>, WalError> {
    let mut found = Vec::new();
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(found),
        Err(e) => return Err(io(dir)(e)),
    };
    for entry in entries {
        let entry = entry.map_err(io(dir))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let Some(lsn) = name
            .strip_prefix(PREFIX)
            .and_then(|n| n.strip_suffix(SUFFIX))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            continue;
        };
        found.push((lsn, entry.path()));
    }
    found.sort();
    Ok(found)
}

/// Creates (or empties: its records were cut) the segment starting at `lsn`.
fn new_segment(dir: &Path, lsn: u64) -> Result<(File, PathBuf), WalError> {
    let path = dir.join(format!("{PREFIX}{lsn:020}{SUFFIX}"));
    let file = OpenOptions::new()
        .create(true)
        .write(true)
        .truncate(true)
        .open(&path)
        .map_err(io(&path))?;
    sync_dir(dir)?;
    Ok((file, path))
}

fn sync_dir(dir: &Path) -> Result<(), WalError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))
}

fn read_exact(path: &Path, into: &mut [u8]) -> Result<(), WalError> {
    use std::io::Read as _;
    File::open(path)
        .and_then(|mut f| f.read_exact(into))
        .map_err(io(path))
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
}

#[cfg(test)]
mod tests {
    use hac_core::{Batch, LevelDims};
    use hac_proto::IngestItemRef;

    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("hac-wal-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    /// Commits only on `sync`.
    fn options(dir: &Path) -> WalOptions {
        WalOptions {
            commit_bytes: usize::MAX,
            max_pending_bytes: usize::MAX,
            ..WalOptions::new(dir, Duration::from_secs(3600))
        }
    }

    /// Message `sequence` of actor `a`: a batch of `sequence` transitions whose states are the
    /// sequence number.
    fn append(wal: &Wal, sequence: u64) -> u64 {
        let dims = LevelDims {
            state: 2,
            goal: 1,
            action: 1,
        };
        let mut batch = Batch::zeros(dims, sequence as usize);
        batch.states.fill(sequence as f32);
        wal.append(
            sequence as u32 % 3,
            &IngestRef {
                actor_id: "a",
                incarnation: 7,
                sequence,
                item: IngestItemRef::Batch {
                    level: 0,
                    weights_version: 1,
                    batch: batch.view(),
                },
            },
        )
    }

    /// Every record from `from` on: (LSN, shard, sequence), each checked against its content.
    fn read(dir: &Path, from: u64) -> (Vec<(u64, u32, u64)>, Recovered, Wal) {
        let mut records = Vec::new();
        let (wal, recovered) = Wal::open(options(dir), from, |r| {
            let IngestItemRef::Batch { batch, .. } = r.message.item else {
                panic!("a batch")
            };
            assert_eq!(batch.len as u64, r.message.sequence);
            assert!(batch.states.iter().all(|&s| s == r.message.sequence as f32));
            records.push((r.lsn, r.shard, r.message.sequence));
        })
        .unwrap();
        (records, recovered, wal)
    }

    fn segments(dir: &Path) -> Vec<(u64, PathBuf)> {
        list_segments(dir).unwrap()
    }

    #[test]
    fn records_read_back_in_order_after_a_commit_and_the_rest_is_lost() {
        let dir = scratch("replay");
        let (_, _, wal) = read(&dir, 1);
        for sequence in 1..=5 {
            assert_eq!(append(&wal, sequence), sequence);
        }
        assert_eq!(wal.durable_through("a", 7), 0);
        assert!(wal.sync(Duration::from_secs(10)));
        assert_eq!(wal.durable_through("a", 7), 5);
        assert_eq!(wal.durable_through("a", 8), 0, "another incarnation");
        append(&wal, 6);
        wal.abandon();
        drop(wal);
        let (records, recovered, wal) = read(&dir, 1);
        let expected: Vec<_> = (1..=5).map(|s| (s, s as u32 % 3, s)).collect();
        assert_eq!(records, expected);
        assert_eq!(recovered.next_lsn, 6);
        assert_eq!(recovered.cut_reason, None);
        // Appending goes on with the next LSN, in a new segment.
        assert_eq!(append(&wal, 6), 6);
        assert!(wal.sync(Duration::from_secs(10)));
        drop(wal);
        let (records, _, _) = read(&dir, 4);
        assert_eq!(
            records.iter().map(|r| r.0).collect::<Vec<_>>(),
            [4, 5, 6],
            "from an LSN on"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_torn_tail_is_cut_off_never_misread() {
        let dir = scratch("torn");
        let (_, _, wal) = read(&dir, 1);
        for sequence in 1..=4 {
            append(&wal, sequence);
        }
        assert!(wal.sync(Duration::from_secs(10)));
        drop(wal);
        let (_, path) = segments(&dir).into_iter().next().unwrap();
        let len = std::fs::metadata(&path).unwrap().len();
        // A kill in the middle of the last record's write.
        OpenOptions::new()
            .write(true)
            .open(&path)
            .unwrap()
            .set_len(len - 5)
            .unwrap();
        let (records, recovered, wal) = read(&dir, 1);
        assert_eq!(records.iter().map(|r| r.2).collect::<Vec<_>>(), [1, 2, 3]);
        assert!(
            recovered.cut_reason.as_deref().unwrap().contains("torn"),
            "{recovered:?}"
        );
        assert_eq!(recovered.next_lsn, 4);
        assert!(std::fs::metadata(&path).unwrap().len() < len - 5, "cut");
        // The cut record's LSN is used again, by the next record.
        assert_eq!(append(&wal, 4), 4);
        assert!(wal.sync(Duration::from_secs(10)));
        drop(wal);
        let (records, recovered, _) = read(&dir, 1);
        assert_eq!(
            records.iter().map(|r| r.2).collect::<Vec<_>>(),
            [1, 2, 3, 4]
        );
        assert_eq!(recovered.cut_reason, None);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_damaged_record_ends_the_log_there() {
        let dir = scratch("checksum");
        let (_, _, wal) = read(&dir, 1);
        for sequence in 1..=3 {
            append(&wal, sequence);
        }
        assert!(wal.sync(Duration::from_secs(10)));
        drop(wal);
        // A later segment, which must go with the damage before it.
        let (_, _, wal) = read(&dir, 1);
        append(&wal, 4);
        assert!(wal.sync(Duration::from_secs(10)));
        drop(wal);
        let (_, path) = segments(&dir).into_iter().next().unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        // One bit of the second record's payload (record 1: 24 + 72 + 8 + 4 x 6 bytes).
        let second = HEADER + (72 + 8 + 4 * 6usize).next_multiple_of(8);
        bytes[second + HEADER + 80] ^= 1;
        std::fs::write(&path, &bytes).unwrap();
        let (records, recovered, _) = read(&dir, 1);
        assert_eq!(records.iter().map(|r| r.2).collect::<Vec<_>>(), [1]);
        assert!(
            recovered
                .cut_reason
                .as_deref()
                .unwrap()
                .contains("checksum"),
            "{recovered:?}"
        );
        assert_eq!(recovered.next_lsn, 2);
        assert!(
            segments(&dir).iter().all(|(first, _)| *first <= 2),
            "the segment after the damage is gone: {:?}",
            segments(&dir)
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_checkpoints_cut_starts_a_segment_and_truncation_drops_what_it_holds() {
        let dir = scratch("cut");
        let (_, _, wal) = read(&dir, 1);
        for sequence in 1..=3 {
            append(&wal, sequence);
        }
        let cut = wal.cut();
        assert_eq!(cut, 4);
        for sequence in 4..=5 {
            append(&wal, sequence);
        }
        assert!(wal.sync(Duration::from_secs(10)));
        let firsts: Vec<u64> = segments(&dir).iter().map(|s| s.0).collect();
        assert_eq!(firsts, [1, 4], "a new segment at the cut");
        let before = wal.status().bytes;
        let freed = wal.truncate_before(cut).unwrap();
        assert!(freed > 0);
        assert_eq!(wal.status().bytes, before - freed);
        assert_eq!(segments(&dir).iter().map(|s| s.0).collect::<Vec<_>>(), [4]);
        // Truncating at the same cut again deletes nothing more (the segment being written
        // stays).
        assert_eq!(wal.truncate_before(cut).unwrap(), 0);
        drop(wal);
        let (records, recovered, _) = read(&dir, cut);
        assert_eq!(records.iter().map(|r| r.2).collect::<Vec<_>>(), [4, 5]);
        assert_eq!(recovered.next_lsn, 6);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
