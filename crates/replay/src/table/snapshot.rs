//! A [`ReplayTable`]'s contents as a safetensors file, for checkpoints.
//!
//! Layout: for every shard `s`, tensors `shard{s}.states`, `shard{s}.actions`,
//! `shard{s}.next_states`, `shard{s}.goals` (`[rows, width]`) and `shard{s}.rewards`,
//! `shard{s}.terminals` (`[rows]`), all `f32`, rows in storage order; metadata `format` =
//! `hac-replay/table`, `state_dim`, `action_dim`, `goal_dim`, `shards`, `capacity`,
//! `shard{s}.next` (the row the next insert writes, which is the oldest once the shard is full)
//! and `shard{s}.inserted` (transitions ever written to the shard, which can exceed its rows).
//! Storage order, not age order: the sampler draws row positions, so a restored table samples
//! exactly the batches the saved one would have.
//! The metadata is one safetensors entry, [`METADATA_KEY`], of sorted `key=value` pairs joined
//! by `;`, so that equal tables give equal files (safetensors would write a map in random
//! order).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::Ordering;

use hac_core::{Transition, TransitionKind};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};

use super::ReplayTable;

const FORMAT: &str = "hac-replay/table";
const METADATA_KEY: &str = "hac_replay";

/// Why a replay snapshot could not be restored.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    #[error("invalid safetensors data: {0}")]
    Format(#[from] safetensors::SafeTensorError),
    #[error("replay snapshot: {0}")]
    Invalid(String),
}

fn invalid<T>(message: String) -> Result<T, SnapshotError> {
    Err(SnapshotError::Invalid(message))
}

impl ReplayTable {
    /// Every shard's rows with its write position and insert counter (layout in the module
    /// docs).
    /// Each shard is copied under its lock; writers must be stopped for the table as a whole to
    /// be one consistent cut.
    pub fn to_safetensors(&self) -> Vec<u8> {
        let mut metadata = BTreeMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("state_dim".to_string(), self.dims.state.to_string()),
            ("action_dim".to_string(), self.dims.action.to_string()),
            ("goal_dim".to_string(), self.dims.goal.to_string()),
            ("shards".to_string(), self.shards.len().to_string()),
            ("capacity".to_string(), self.capacity.to_string()),
        ]);
        // Written only for a level with extra values, so HAC's snapshots keep their layout.
        if self.extra_width > 0 {
            metadata.insert("extra_width".into(), self.extra_width.to_string());
        }
        let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
        for (s, shard) in self.shards.iter().enumerate() {
            let ring = shard.0.ring.lock();
            metadata.insert(
                format!("shard{s}.inserted"),
                shard.0.inserted.load(Ordering::Relaxed).to_string(),
            );
            metadata.insert(format!("shard{s}.next"), ring.next().to_string());
            for (name, values, width) in ring.fields() {
                if name == "extra" && width == 0 {
                    continue;
                }
                let values = &values[..ring.len() * width];
                let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
                let shape = match name {
                    "rewards" | "terminals" => vec![ring.len()],
                    _ => vec![ring.len(), width],
                };
                tensors.push((format!("shard{s}.{name}"), shape, bytes));
            }
        }
        let pairs: Vec<String> = metadata.iter().map(|(k, v)| format!("{k}={v}")).collect();
        let metadata = HashMap::from([(METADATA_KEY.to_string(), pairs.join(";"))]);
        let views = tensors.iter().map(|(name, shape, bytes)| {
            let view = TensorView::new(Dtype::F32, shape.clone(), bytes)
                .expect("the shape matches the bytes by construction");
            (name.as_str(), view)
        });
        // Only a header above safetensors' 100 MB limit can fail: far more tensors than here.
        safetensors::serialize(views, Some(metadata)).expect("serialising in-memory f32 tensors")
    }

    /// Fills this empty table with a snapshot of a table of the same dimensions, capacity and
    /// shard count ([`to_safetensors`](Self::to_safetensors)); rows keep their positions, so
    /// FIFO order and sampling are as in the saved table.
    pub fn restore_safetensors(&self, bytes: &[u8]) -> Result<(), SnapshotError> {
        let file = SafeTensors::deserialize(bytes)?;
        let (_, header) = SafeTensors::read_metadata(bytes)?;
        let metadata: BTreeMap<String, String> = header
            .metadata()
            .as_ref()
            .and_then(|m| m.get(METADATA_KEY))
            .map(|pairs| {
                pairs
                    .split(';')
                    .filter_map(|pair| pair.split_once('='))
                    .map(|(k, v)| (k.to_string(), v.to_string()))
                    .collect()
            })
            .unwrap_or_default();
        let meta = |key: &str| -> Result<&str, SnapshotError> {
            metadata
                .get(key)
                .map(String::as_str)
                .ok_or_else(|| SnapshotError::Invalid(format!("metadata `{key}` is missing")))
        };
        let number = |key: &str| -> Result<u64, SnapshotError> {
            let value = meta(key)?;
            value.parse().map_err(|_| {
                SnapshotError::Invalid(format!("metadata `{key}` = `{value}` is not a count"))
            })
        };
        if meta("format")? != FORMAT {
            return invalid(format!(
                "format is `{}`, expected `{FORMAT}`",
                meta("format")?
            ));
        }
        let expected = [
            ("state_dim", self.dims.state as u64),
            ("action_dim", self.dims.action as u64),
            ("goal_dim", self.dims.goal as u64),
            ("shards", self.shards.len() as u64),
            ("capacity", self.capacity as u64),
        ];
        let extra_width = match metadata.get("extra_width") {
            Some(_) => number("extra_width")?,
            None => 0,
        };
        if extra_width != self.extra_width as u64 {
            return invalid(format!(
                "`extra_width` is {extra_width}, this table has {}",
                self.extra_width
            ));
        }
        for (key, value) in expected {
            let found = number(key)?;
            if found != value {
                return invalid(format!("`{key}` is {found}, this table has {value}"));
            }
        }
        if !self.is_empty() {
            return invalid("the table to restore into is not empty".into());
        }
        for (s, shard) in self.shards.iter().enumerate() {
            let mut columns = Vec::with_capacity(7);
            let mut rows = None;
            let ring = shard.0.ring.lock();
            for (name, _, width) in ring.fields() {
                if name == "extra" && width == 0 {
                    columns.push(Vec::new());
                    continue;
                }
                let key = format!("shard{s}.{name}");
                let tensor = file
                    .tensor(&key)
                    .map_err(|_| SnapshotError::Invalid(format!("tensor `{key}` is missing")))?;
                let n = tensor.shape().first().copied().unwrap_or(0);
                let want: Vec<usize> = match name {
                    "rewards" | "terminals" => vec![n],
                    _ => vec![n, width],
                };
                if tensor.dtype() != Dtype::F32 || tensor.shape() != want {
                    return invalid(format!(
                        "tensor `{key}` is {:?} {:?}, expected F32 {want:?}",
                        tensor.dtype(),
                        tensor.shape()
                    ));
                }
                if *rows.get_or_insert(n) != n {
                    return invalid(format!("tensor `{key}` has {n} rows, other fields differ"));
                }
                let values: Vec<f32> = tensor
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                columns.push(values);
            }
            drop(ring);
            let rows = rows.unwrap_or(0);
            let inserted = number(&format!("shard{s}.inserted"))?;
            let next = number(&format!("shard{s}.next"))?;
            let capacity = shard.0.capacity;
            let consistent = if rows < capacity {
                next == rows as u64
            } else {
                rows == capacity && next < capacity as u64
            };
            if !consistent || inserted < rows as u64 {
                return invalid(format!(
                    "shard {s} holds {rows} rows, next {next}, {inserted} inserted, capacity \
                     {capacity}"
                ));
            }
            let (state, action, goal) = (self.dims.state, self.dims.action, self.dims.goal);
            let e = self.extra_width;
            let mut ring = shard.0.ring.lock();
            for j in 0..rows {
                ring.push(&Transition {
                    kind: TransitionKind::HindsightAction,
                    state: &columns[0][j * state..(j + 1) * state],
                    action: &columns[1][j * action..(j + 1) * action],
                    reward: columns[2][j],
                    next_state: &columns[3][j * state..(j + 1) * state],
                    goal: &columns[4][j * goal..(j + 1) * goal],
                    terminal: columns[5][j] != 0.0,
                    extra: &columns[6][j * e..(j + 1) * e],
                });
            }
            ring.set_next(next as usize);
            shard.0.inserted.store(inserted, Ordering::Relaxed);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use hac_core::{Batch, LevelDims, Rng};

    use super::*;

    const DIMS: LevelDims = LevelDims {
        state: 2,
        goal: 1,
        action: 1,
    };

    fn table_with(ids: std::ops::Range<u32>) -> ReplayTable {
        let table = ReplayTable::new(DIMS, 7, 2);
        for id in ids {
            let x = id as f32;
            table.insert(&Transition {
                kind: TransitionKind::HindsightGoal,
                state: &[x, x + 0.5],
                action: &[-x],
                reward: -1.0,
                next_state: &[x + 1.0, x + 1.5],
                goal: &[2.0 * x],
                terminal: id % 2 == 0,
                extra: &[],
            });
        }
        table
    }

    #[test]
    fn a_restored_table_holds_the_same_rows_in_the_same_order() {
        // 11 inserts into 7 rows: both shards have wrapped around.
        let table = table_with(0..11);
        let bytes = table.to_safetensors();
        assert!(bytes == table.to_safetensors(), "equal tables, equal files");
        let restored = ReplayTable::new(DIMS, 7, 2);
        restored.restore_safetensors(&bytes).unwrap();
        assert_eq!(restored.inserted_total(), 11);
        assert_eq!(
            restored.shard_lens().collect::<Vec<_>>(),
            table.shard_lens().collect::<Vec<_>>()
        );
        for s in 0..2 {
            assert_eq!(restored.rows_oldest_first(s), table.rows_oldest_first(s));
        }
        // The same contents and RNG state sample the same batch.
        let (mut a, mut b) = (Batch::zeros(DIMS, 16), Batch::zeros(DIMS, 16));
        table.sample(&mut Rng::seed_from(3), &mut a).unwrap();
        restored.sample(&mut Rng::seed_from(3), &mut b).unwrap();
        assert_eq!(a, b);
        // FIFO order survives: the next insert overwrites the oldest row in both.
        for t in [&table, &restored] {
            t.insert_into(
                0,
                &Transition {
                    kind: TransitionKind::HindsightAction,
                    state: &[100.0, 100.5],
                    action: &[0.0],
                    reward: 0.0,
                    next_state: &[0.0, 0.0],
                    goal: &[0.0],
                    terminal: false,
                    extra: &[],
                },
            );
        }
        assert_eq!(restored.rows_oldest_first(0), table.rows_oldest_first(0));
    }

    #[test]
    fn snapshots_of_other_tables_or_damaged_ones_are_refused() {
        let bytes = table_with(0..5).to_safetensors();
        let other = ReplayTable::new(DIMS, 8, 2);
        let e = other.restore_safetensors(&bytes).unwrap_err().to_string();
        assert!(e.contains("capacity"), "{e}");
        let full = table_with(0..1);
        let e = full.restore_safetensors(&bytes).unwrap_err().to_string();
        assert!(e.contains("not empty"), "{e}");
        let empty = ReplayTable::new(DIMS, 7, 2);
        let e = empty
            .restore_safetensors(&bytes[..bytes.len() - 3])
            .unwrap_err();
        assert!(matches!(e, SnapshotError::Format(_)), "{e}");
        assert!(empty.is_empty());
        // An empty table round trips too.
        let e2 = ReplayTable::new(DIMS, 7, 2);
        e2.restore_safetensors(&ReplayTable::new(DIMS, 7, 2).to_safetensors())
            .unwrap();
        assert!(e2.is_empty());
    }
}
