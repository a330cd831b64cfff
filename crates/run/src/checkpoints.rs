//! Checkpoints on disk: `<run>/checkpoints/ckpt-<seq>/`, each a set of files with a `MANIFEST`.
//!
//! What the files hold is the writer's business (the learner's are described in `hac_learner`);
//! this module makes them durable and verifiable:
//!
//! - writing goes to a hidden temporary directory: every file is written and fsynced, then the
//!   `MANIFEST` (each file's length and SHA-256) is written and fsynced last, then the directory
//!   itself; then it is renamed to `ckpt-<seq>` (six digits or more, increasing) and the parent
//!   directory fsynced. A crash leaves either a complete checkpoint or a temporary directory,
//!   which the next write removes;
//! - only the newest `keep` checkpoints are kept;
//! - loading takes the newest checkpoint whose files all match the manifest (and that the caller
//!   can decode); each one skipped on the way is reported with the reason (a file of the wrong
//!   length, a checksum mismatch, a missing file or manifest).
//!
//! `MANIFEST` is text: the line `hac-checkpoint 1`, one line `<sha256 hex> <bytes> <name>` per
//! file, and the line `end`.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use sha2::{Digest, Sha256};

/// The manifest's file name, and its first and last lines.
pub const MANIFEST: &str = "MANIFEST";
const HEADER: &str = "hac-checkpoint 1";
const END: &str = "end";
const PREFIX: &str = "ckpt-";
const TEMP_PREFIX: &str = ".tmp-ckpt-";

/// The checkpoints of one run directory.
#[derive(Debug, Clone)]
pub struct CheckpointStore {
    dir: PathBuf,
}

/// A checkpoint just written.
#[derive(Debug, Clone)]
pub struct Written {
    pub name: String,
    pub path: PathBuf,
    /// Bytes of all its files, the manifest included.
    pub bytes: u64,
}

/// A checkpoint that could not be used, and why (`is corrupt: ...`, `cannot be read: ...`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    pub name: String,
    pub reason: String,
}

/// The newest usable checkpoint, decoded, and the newer ones skipped on the way.
#[derive(Debug)]
pub struct Loaded<T> {
    pub name: String,
    pub value: T,
    pub skipped: Vec<Skipped>,
}

impl CheckpointStore {
    /// The store of the run directory `run` (`<run>/checkpoints`; created when first written).
    pub fn of_run(run: &Path) -> Self {
        Self {
            dir: run.join("checkpoints"),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Names of the checkpoints present (complete or not), oldest first.
    pub fn list(&self) -> Result<Vec<String>> {
        let mut found: Vec<(u64, String)> = Vec::new();
        let entries = match std::fs::read_dir(&self.dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(e).with_context(|| format!("reading {}", self.dir.display())),
        };
        for entry in entries {
            let entry = entry.with_context(|| format!("reading {}", self.dir.display()))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if let Some(seq) = name.strip_prefix(PREFIX).and_then(|s| s.parse().ok()) {
                found.push((seq, name));
            }
        }
        found.sort();
        Ok(found.into_iter().map(|(_, name)| name).collect())
    }

    /// Writes `files` (names without `/`) as the next checkpoint (see the module docs), then
    /// removes all but the newest `keep` (at least 1).
    pub fn write(&self, files: &[(String, Vec<u8>)], keep: usize) -> Result<Written> {
        std::fs::create_dir_all(&self.dir)
            .with_context(|| format!("creating {}", self.dir.display()))?;
        self.remove_temporaries()?;
        let seq = self
            .list()?
            .last()
            .and_then(|name| name[PREFIX.len()..].parse::<u64>().ok())
            .map_or(1, |seq| seq + 1);
        let name = format!("{PREFIX}{seq:06}");
        let temp = self.dir.join(format!("{TEMP_PREFIX}{seq:06}"));
        std::fs::create_dir(&temp).with_context(|| format!("creating {}", temp.display()))?;

        let mut manifest = format!("{HEADER}\n");
        let mut bytes = 0;
        for (file, contents) in files {
            if file.contains('/') || file.contains(char::is_whitespace) || file == MANIFEST {
                bail!("invalid checkpoint file name `{file}`");
            }
            write_synced(&temp.join(file), contents)?;
            manifest += &format!(
                "{} {} {file}\n",
                hex(&Sha256::digest(contents)),
                contents.len()
            );
            bytes += contents.len() as u64;
        }
        manifest += END;
        manifest.push('\n');
        write_synced(&temp.join(MANIFEST), manifest.as_bytes())?;
        bytes += manifest.len() as u64;
        sync_dir(&temp)?;
        let path = self.dir.join(&name);
        std::fs::rename(&temp, &path)
            .with_context(|| format!("renaming {} to {}", temp.display(), path.display()))?;
        sync_dir(&self.dir)?;

        let names = self.list()?;
        for old in names.iter().take(names.len().saturating_sub(keep.max(1))) {
            let old = self.dir.join(old);
            std::fs::remove_dir_all(&old)
                .with_context(|| format!("removing old checkpoint {}", old.display()))?;
        }
        Ok(Written { name, path, bytes })
    }

    /// Reads checkpoint `name`, verifying every file against the manifest; the error says
    /// what does not match.
    pub fn read(&self, name: &str) -> Result<BTreeMap<String, Vec<u8>>, String> {
        let dir = self.dir.join(name);
        let manifest = match std::fs::read_to_string(dir.join(MANIFEST)) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(format!("{MANIFEST} is missing"));
            }
            Err(e) => return Err(format!("reading {MANIFEST}: {e}")),
        };
        let mut lines = manifest.lines();
        if lines.next() != Some(HEADER) {
            return Err(format!("{MANIFEST} does not start with `{HEADER}`"));
        }
        let mut files = BTreeMap::new();
        let mut ended = false;
        for line in lines {
            if line == END {
                ended = true;
                break;
            }
            let mut parts = line.splitn(3, ' ');
            let (Some(sha), Some(len), Some(file)) = (parts.next(), parts.next(), parts.next())
            else {
                return Err(format!("{MANIFEST} has a malformed line `{line}`"));
            };
            let len: u64 = len
                .parse()
                .map_err(|_| format!("{MANIFEST} has a malformed line `{line}`"))?;
            let contents = match std::fs::read(dir.join(file)) {
                Ok(contents) => contents,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    return Err(format!("{file} is missing"));
                }
                Err(e) => return Err(format!("reading {file}: {e}")),
            };
            if contents.len() as u64 != len {
                return Err(format!(
                    "{file} is {} bytes, {MANIFEST} says {len}",
                    contents.len()
                ));
            }
            if hex(&Sha256::digest(&contents)) != sha {
                return Err(format!(
                    "{file} does not match its SHA-256 in {MANIFEST} (the contents changed)"
                ));
            }
            files.insert(file.to_string(), contents);
        }
        if !ended {
            return Err(format!("{MANIFEST} is truncated (no `{END}` line)"));
        }
        Ok(files)
    }

    /// The newest checkpoint that verifies and that `decode` accepts, with every newer one
    /// skipped on the way; `None` if there is none at all (skipped ones are then an error).
    pub fn load_newest<T, E: std::fmt::Display>(
        &self,
        decode: impl Fn(&BTreeMap<String, Vec<u8>>) -> Result<T, E>,
    ) -> Result<Option<Loaded<T>>> {
        let mut skipped = Vec::new();
        for name in self.list()?.into_iter().rev() {
            let reason = match self.read(&name) {
                Ok(files) => match decode(&files) {
                    Ok(value) => {
                        return Ok(Some(Loaded {
                            name,
                            value,
                            skipped,
                        }));
                    }
                    Err(e) => format!("cannot be read: {e}"),
                },
                Err(e) => format!("is corrupt: {e}"),
            };
            skipped.push(Skipped { name, reason });
        }
        if skipped.is_empty() {
            return Ok(None);
        }
        let reasons: Vec<String> = skipped
            .iter()
            .map(|s| format!("{} {}", s.name, s.reason))
            .collect();
        bail!(
            "no usable checkpoint in {}: {}",
            self.dir.display(),
            reasons.join("; ")
        )
    }

    /// Removes every checkpoint (a run directory being overwritten).
    pub fn remove_all(&self) -> Result<()> {
        match std::fs::remove_dir_all(&self.dir) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e).with_context(|| format!("removing {}", self.dir.display())),
        }
    }

    /// Removes temporary directories that interrupted writes left behind.
    fn remove_temporaries(&self) -> Result<()> {
        for entry in std::fs::read_dir(&self.dir)
            .with_context(|| format!("reading {}", self.dir.display()))?
        {
            let path = entry?.path();
            let is_temp = path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(TEMP_PREFIX));
            if is_temp {
                std::fs::remove_dir_all(&path)
                    .with_context(|| format!("removing {}", path.display()))?;
            }
        }
        Ok(())
    }
}

impl<T> Loaded<T> {
    /// One line per skipped checkpoint: `checkpoint X is corrupt: ...; using Y`.
    pub fn skipped_lines(&self) -> Vec<String> {
        self.skipped
            .iter()
            .map(|s| format!("checkpoint {} {}; using {}", s.name, s.reason, self.name))
            .collect()
    }
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    file.write_all(bytes)
        .and_then(|()| file.sync_all())
        .with_context(|| format!("writing {}", path.display()))
}

/// Makes a directory's entries (new files, renames) durable.
fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .with_context(|| format!("syncing {}", dir.display()))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "hac-checkpoints-test-{}-{name}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn files(tag: u8) -> Vec<(String, Vec<u8>)> {
        vec![
            ("a.json".to_string(), vec![b'{', tag, b'}']),
            ("b.bin".to_string(), vec![tag; 100]),
        ]
    }

    fn decode(files: &BTreeMap<String, Vec<u8>>) -> Result<u8, String> {
        Ok(files["b.bin"][0])
    }

    #[test]
    fn writes_are_numbered_kept_to_k_and_loaded_newest_first() {
        let run = scratch("keep");
        let store = CheckpointStore::of_run(&run);
        assert!(store.load_newest(decode).unwrap().is_none());
        for tag in 1..=5 {
            let written = store.write(&files(tag), 3).unwrap();
            assert_eq!(written.name, format!("ckpt-{tag:06}"));
        }
        assert_eq!(
            store.list().unwrap(),
            ["ckpt-000003", "ckpt-000004", "ckpt-000005"]
        );
        let loaded = store.load_newest(decode).unwrap().unwrap();
        assert_eq!((loaded.name.as_str(), loaded.value), ("ckpt-000005", 5));
        assert!(loaded.skipped.is_empty());
        // A crash mid-write leaves a temporary directory: ignored, then cleaned up.
        std::fs::create_dir_all(store.dir().join(".tmp-ckpt-000006")).unwrap();
        assert_eq!(store.load_newest(decode).unwrap().unwrap().value, 5);
        store.write(&files(6), 3).unwrap();
        assert!(!store.dir().join(".tmp-ckpt-000006").exists());
        let _ = std::fs::remove_dir_all(&run);
    }

    #[test]
    fn truncated_flipped_or_unfinished_checkpoints_are_skipped_with_the_reason() {
        let run = scratch("corrupt");
        let store = CheckpointStore::of_run(&run);
        for tag in 1..=4 {
            store.write(&files(tag), 10).unwrap();
        }
        let dir = |n: u8| store.dir().join(format!("ckpt-{n:06}"));
        // Newest: a file cut short. Then: a flipped byte. Then: no manifest.
        let b = dir(4).join("b.bin");
        std::fs::write(&b, &std::fs::read(&b).unwrap()[..60]).unwrap();
        let a = dir(3).join("a.json");
        let mut bytes = std::fs::read(&a).unwrap();
        bytes[1] ^= 0x40;
        std::fs::write(&a, bytes).unwrap();
        std::fs::remove_file(dir(2).join(MANIFEST)).unwrap();

        let loaded = store.load_newest(decode).unwrap().unwrap();
        assert_eq!((loaded.name.as_str(), loaded.value), ("ckpt-000001", 1));
        let lines = loaded.skipped_lines();
        assert_eq!(
            lines[0],
            "checkpoint ckpt-000004 is corrupt: b.bin is 60 bytes, MANIFEST says 100; using ckpt-000001"
        );
        assert!(lines[1].contains("ckpt-000003") && lines[1].contains("SHA-256"));
        assert!(lines[2].contains("ckpt-000002") && lines[2].contains("MANIFEST is missing"));

        // A checkpoint that verifies but does not decode is skipped as well.
        let picky = |files: &BTreeMap<String, Vec<u8>>| match files["b.bin"][0] {
            1 => Err("unsupported version"),
            n => Ok(n),
        };
        let e = store.load_newest(picky).unwrap_err().to_string();
        assert!(
            e.contains("no usable checkpoint") && e.contains("unsupported version"),
            "{e}"
        );
        // A truncated manifest and a missing file.
        store.write(&files(5), 10).unwrap();
        let manifest = dir(5).join(MANIFEST);
        let text = std::fs::read_to_string(&manifest).unwrap();
        std::fs::write(&manifest, text.trim_end().trim_end_matches("end")).unwrap();
        assert!(store.read("ckpt-000005").unwrap_err().contains("truncated"));
        std::fs::write(&manifest, text).unwrap();
        std::fs::remove_file(dir(5).join("a.json")).unwrap();
        assert_eq!(store.read("ckpt-000005").unwrap_err(), "a.json is missing");
        let _ = std::fs::remove_dir_all(&run);
    }
}
