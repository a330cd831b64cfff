//! One level's Q table as a safetensors file, stored sparsely.
//!
//! A table holds `cells x cells x slots` values (up to 2^25 by default), nearly all still at the
//! initial value after training, so only the entries that differ from it are written:
//!
//! - tensor `index`: `u32 [n]`, ascending positions `((s * cells) + g) * slots + a` in the dense
//!   table, with `s` and `g` cell numbers (free cells in row-major order, see [`crate::grid`])
//!   and `a` the action slot (a move at level 0; a subgoal offset within the level's radius above);
//! - tensor `value`: `f32 [n]`, the values at those positions;
//! - metadata: one entry `hac_tabular` with sorted `key=value` pairs joined by `;` (one entry so
//!   that equal tables give equal bytes): `format` (`hac-tabular-q-v1`), `level`, `grid_size`,
//!   `cells`, `slots`, `subgoal_radius` (`none` at level 0), `initial_value`.
//!
//! Loading checks every layout key against the agent it fills, so a table only ever lands in a
//! table of the same shape and meaning.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};

use safetensors::{Dtype, SafeTensors, View};

use crate::agent::TabularAgent;

/// The `format` metadata value of this layout.
pub const FORMAT: &str = "hac-tabular-q-v1";
const METADATA_KEY: &str = "hac_tabular";

/// Why a Q-table file cannot be read into an agent.
#[derive(Debug, thiserror::Error)]
pub enum TableFileError {
    #[error("not a safetensors file: {0}")]
    Format(#[from] safetensors::SafeTensorError),
    #[error("not a {FORMAT} Q table: metadata `{0}` is missing")]
    MissingMetadata(&'static str),
    #[error("the table was saved with {key} = {found}, but this run needs {expected}")]
    Mismatch {
        key: &'static str,
        expected: String,
        found: String,
    },
    #[error("tensor `{name}`: {problem}")]
    Tensor { name: &'static str, problem: String },
    #[error("level {level}'s table has {entries} entries, more than a u32 index addresses")]
    TooLarge { level: usize, entries: usize },
}

/// A little-endian tensor ready to be written.
struct Raw {
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: Vec<u8>,
}

impl View for &Raw {
    fn dtype(&self) -> Dtype {
        self.dtype
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.bytes)
    }

    fn data_len(&self) -> usize {
        self.bytes.len()
    }
}

impl TabularAgent {
    /// The layout keys of level `level`'s table, as written to and checked against a file.
    fn table_metadata(&self, level: usize) -> BTreeMap<&'static str, String> {
        let (radius, slots) = self.layout(level);
        BTreeMap::from([
            ("format", FORMAT.to_string()),
            ("level", level.to_string()),
            ("grid_size", self.grid().size().to_string()),
            ("cells", self.grid().num_cells().to_string()),
            ("slots", slots.to_string()),
            (
                "subgoal_radius",
                radius.map_or("none".to_string(), |r| r.to_string()),
            ),
            ("initial_value", self.initial_value.to_string()),
        ])
    }

    /// Level `level`'s table in the format of this module.
    pub fn table_to_safetensors(&self, level: usize) -> Result<Vec<u8>, TableFileError> {
        let table = &self.tables[level];
        if u32::try_from(table.len()).is_err() {
            return Err(TableFileError::TooLarge {
                level,
                entries: table.len(),
            });
        }
        let (mut index, mut value) = (Vec::new(), Vec::new());
        for (i, &q) in table.iter().enumerate() {
            // Bitwise, so that -0.0 (and anything else not identical) is kept.
            if q.to_bits() != self.initial_value.to_bits() {
                index.extend_from_slice(&(i as u32).to_le_bytes());
                value.extend_from_slice(&q.to_le_bytes());
            }
        }
        let n = value.len() / 4;
        let tensors = [
            (
                "index",
                Raw {
                    dtype: Dtype::U32,
                    shape: vec![n],
                    bytes: index,
                },
            ),
            (
                "value",
                Raw {
                    dtype: Dtype::F32,
                    shape: vec![n],
                    bytes: value,
                },
            ),
        ];
        let pairs: Vec<String> = self
            .table_metadata(level)
            .iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        let metadata = HashMap::from([(METADATA_KEY.to_string(), pairs.join(";"))]);
        Ok(safetensors::serialize(
            tensors.iter().map(|(name, t)| (*name, t)),
            Some(metadata),
        )?)
    }

    /// Replaces level `level`'s table with the one in `bytes`, after checking that it was saved
    /// for a table of the same layout. On error the table is unchanged.
    pub fn load_table(&mut self, level: usize, bytes: &[u8]) -> Result<(), TableFileError> {
        let (_, header) = SafeTensors::read_metadata(bytes)?;
        let saved: BTreeMap<&str, &str> = header
            .metadata()
            .as_ref()
            .and_then(|m| m.get(METADATA_KEY))
            .map(|pairs| pairs.split(';').filter_map(|p| p.split_once('=')).collect())
            .unwrap_or_default();
        for (key, expected) in self.table_metadata(level) {
            let found = saved.get(key).ok_or(TableFileError::MissingMetadata(key))?;
            if *found != expected {
                return Err(TableFileError::Mismatch {
                    key,
                    expected,
                    found: found.to_string(),
                });
            }
        }
        let file = SafeTensors::deserialize(bytes)?;
        let read = |name: &'static str, dtype: Dtype| {
            let t = file.tensor(name).map_err(|_| TableFileError::Tensor {
                name,
                problem: "missing".to_string(),
            })?;
            if t.dtype() != dtype || t.shape().len() != 1 {
                return Err(TableFileError::Tensor {
                    name,
                    problem: format!(
                        "expected a {dtype:?} vector, found {:?} of shape {:?}",
                        t.dtype(),
                        t.shape()
                    ),
                });
            }
            Ok(t.data()
                .chunks_exact(4)
                .map(|b| [b[0], b[1], b[2], b[3]])
                .collect::<Vec<[u8; 4]>>())
        };
        let index = read("index", Dtype::U32)?;
        let value = read("value", Dtype::F32)?;
        if index.len() != value.len() {
            return Err(TableFileError::Tensor {
                name: "value",
                problem: format!("{} values for {} indices", value.len(), index.len()),
            });
        }
        let len = self.tables[level].len();
        let mut table = vec![self.initial_value; len];
        for (i, v) in index.iter().zip(&value) {
            let i = u32::from_le_bytes(*i) as usize;
            let slot = table.get_mut(i).ok_or_else(|| TableFileError::Tensor {
                name: "index",
                problem: format!("position {i} is outside the table of {len} entries"),
            })?;
            *slot = f32::from_le_bytes(*v);
        }
        self.tables[level] = table;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use hac_core::{AgentConfig, Rng, Transition, TransitionKind};

    use super::*;
    use crate::grid::Grid;
    use crate::{FourRooms, TabularConfig};

    fn agent(levels: usize, horizon: usize, size: usize) -> TabularAgent {
        let env = FourRooms::new(size).unwrap();
        let config = AgentConfig {
            horizon,
            ..hac_core::Env::default_config(&env, levels)
        };
        let grid = Grid::four_rooms(size).unwrap();
        TabularAgent::new(&grid, &config, &TabularConfig::default(), Rng::seed_from(0)).unwrap()
    }

    fn touch(a: &mut TabularAgent, level: usize, action: &[f32], reward: f32) {
        let t = Transition {
            kind: TransitionKind::HindsightAction,
            state: &[0.0, 0.0],
            action,
            reward,
            next_state: &[0.0, 1.0],
            goal: &[3.0, 3.0],
            terminal: true,
        };
        assert!(a.update(level, &t));
    }

    #[test]
    fn tables_round_trip_exactly_and_sparsely() {
        let mut a = agent(2, 5, 10);
        touch(&mut a, 0, &[3.0], -1.5);
        touch(&mut a, 1, &[0.0, 2.0], -0.25);
        let bytes: Vec<Vec<u8>> = (0..2).map(|l| a.table_to_safetensors(l).unwrap()).collect();
        // Two entries, not the 85 x 85 x slots of the dense table.
        assert!(bytes.iter().all(|b| b.len() < 1000));

        let mut b = agent(2, 5, 10);
        for (level, bytes) in bytes.iter().enumerate() {
            b.load_table(level, bytes).unwrap();
            assert_eq!(a.tables[level], b.tables[level]);
            assert_eq!(&b.table_to_safetensors(level).unwrap(), bytes, "same bytes");
        }
        assert_eq!(
            b.value(1, &[0.0, 0.0], &[3.0, 3.0], &[0.0, 2.0]),
            Some(-0.25)
        );
    }

    #[test]
    fn a_table_of_another_layout_is_refused_by_name() {
        let a = agent(2, 5, 10);
        let level1 = a.table_to_safetensors(1).unwrap();
        let mut other_h = agent(2, 6, 10);
        let err = other_h.load_table(1, &level1).unwrap_err().to_string();
        assert!(err.contains("initial_value"), "{err}");
        let mut other_level = agent(2, 5, 10);
        let err = other_level.load_table(0, &level1).unwrap_err().to_string();
        assert!(err.contains("level"), "{err}");
        let mut bigger = agent(2, 5, 11);
        let err = bigger.load_table(1, &level1).unwrap_err().to_string();
        assert!(err.contains("cells") || err.contains("grid_size"), "{err}");
        assert!(matches!(
            bigger.load_table(1, b"not a table"),
            Err(TableFileError::Format(_))
        ));
    }
}
