//! One level's Q table as a safetensors file, stored compactly.
//!
//! A table holds `cells x cells x slots` values (up to 2^25 by default). Positions are
//! `((s * cells) + g) * slots + a` in the dense table, with `s` and `g` cell numbers (free cells
//! in row-major order, see [`crate::grid`]) and `a` the action slot (a move at level 0; a subgoal
//! offset within the level's radius above). The writer picks the smaller of two encodings:
//!
//! - sparse, when few entries differ from the initial value: tensor `index`, `u32 [n]`, the
//!   ascending positions of those entries, and tensor `value`, `f32 [n]`, their values;
//! - coded, when most entries were updated (every goal at once, `all_goals` / `all_segments`)
//!   and the table holds at most 256 distinct values (as with learning rate 1, where a value is
//!   one of the few discounted path lengths): tensor `palette`, `f32 [p]`, the distinct values,
//!   and tensor `code`, `u8`, the palette index of every position: one byte each, or, when
//!   `p <= 16`, two per byte (the first position in the low four bits), `ceil(len / 2)` bytes.
//!
//! Metadata: one entry `hac_tabular` with sorted `key=value` pairs joined by `;` (one entry so
//! that equal tables give equal bytes): `format` (`hac-tabular-q-v2`; `v1` files, always sparse,
//! still load), `level`, `grid_size`, `cells`, `slots`, `subgoal_radius` (`none` at level 0),
//! `initial_value`.
//!
//! Loading checks every layout key against the agent it fills, so a table only ever lands in a
//! table of the same shape and meaning.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap, HashSet};

use safetensors::{Dtype, SafeTensors, View};

use crate::agent::TabularAgent;

/// The `format` metadata value of this layout.
pub const FORMAT: &str = "hac-tabular-q-v2";
/// The earlier format, sparse only, which loads as well.
const FORMAT_V1: &str = "hac-tabular-q-v1";
/// Most distinct values a coded table holds.
const MAX_PALETTE: usize = 256;
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
        // Values compared bitwise, so that -0.0 (and anything else not identical) is kept.
        let initial = self.initial_value.to_bits();
        let n = table.iter().filter(|q| q.to_bits() != initial).count();
        let tensors = match palette_of(table) {
            Some(palette) if coded_bytes(table.len(), palette.len()) < 8 * n => {
                coded(table, &palette)
            }
            _ => sparse(table, initial, n),
        };
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
            if key == "format" && *found == FORMAT_V1 {
                continue;
            }
            if *found != expected {
                return Err(TableFileError::Mismatch {
                    key,
                    expected,
                    found: found.to_string(),
                });
            }
        }
        let file = SafeTensors::deserialize(bytes)?;
        let tensor = |name: &'static str, dtype: Dtype| {
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
            Ok(t)
        };
        let read = |name: &'static str, dtype: Dtype| {
            Ok::<_, TableFileError>(
                tensor(name, dtype)?
                    .data()
                    .chunks_exact(4)
                    .map(|b| [b[0], b[1], b[2], b[3]])
                    .collect::<Vec<[u8; 4]>>(),
            )
        };
        let len = self.tables[level].len();
        let table = if file.names().contains(&"palette") {
            let palette: Vec<f32> = read("palette", Dtype::F32)?
                .into_iter()
                .map(f32::from_le_bytes)
                .collect();
            decode(&palette, tensor("code", Dtype::U8)?.data(), len)?
        } else {
            let index = read("index", Dtype::U32)?;
            let value = read("value", Dtype::F32)?;
            decode_sparse(&index, &value, self.initial_value, len)?
        };
        self.tables[level] = table;
        self.rebuild_best(level);
        Ok(())
    }
}

fn raw(dtype: Dtype, n: usize, bytes: Vec<u8>) -> Raw {
    Raw {
        dtype,
        shape: vec![n],
        bytes,
    }
}

/// The `index` and `value` tensors of the `n` entries of `table` whose bits differ from
/// `initial`.
fn sparse(table: &[f32], initial: u32, n: usize) -> [(&'static str, Raw); 2] {
    let (mut index, mut value) = (Vec::with_capacity(4 * n), Vec::with_capacity(4 * n));
    for (i, &q) in table.iter().enumerate() {
        if q.to_bits() != initial {
            index.extend_from_slice(&(i as u32).to_le_bytes());
            value.extend_from_slice(&q.to_le_bytes());
        }
    }
    [
        ("index", raw(Dtype::U32, n, index)),
        ("value", raw(Dtype::F32, n, value)),
    ]
}

/// The table of `len` entries, `initial` except at the positions `index` holds `value`s for.
fn decode_sparse(
    index: &[[u8; 4]],
    value: &[[u8; 4]],
    initial: f32,
    len: usize,
) -> Result<Vec<f32>, TableFileError> {
    if index.len() != value.len() {
        return Err(TableFileError::Tensor {
            name: "value",
            problem: format!("{} values for {} indices", value.len(), index.len()),
        });
    }
    let mut table = vec![initial; len];
    for (i, v) in index.iter().zip(value) {
        let i = u32::from_le_bytes(*i) as usize;
        let slot = table.get_mut(i).ok_or_else(|| TableFileError::Tensor {
            name: "index",
            problem: format!("position {i} is outside the table of {len} entries"),
        })?;
        *slot = f32::from_le_bytes(*v);
    }
    Ok(table)
}

/// The distinct values of `table` (bitwise) in order of first appearance, if at most
/// [`MAX_PALETTE`].
fn palette_of(table: &[f32]) -> Option<Vec<f32>> {
    let mut palette: Vec<f32> = Vec::new();
    let mut seen: HashSet<u32> = HashSet::new();
    let mut last = None;
    for &q in table {
        // Long runs of one value are the rule: skip the lookup for them.
        if last == Some(q.to_bits()) {
            continue;
        }
        last = Some(q.to_bits());
        if seen.insert(q.to_bits()) {
            if palette.len() == MAX_PALETTE {
                return None;
            }
            palette.push(q);
        }
    }
    Some(palette)
}

/// Bytes of a coded table of `len` entries with a palette of `p` values.
fn coded_bytes(len: usize, p: usize) -> usize {
    let code = if p <= 16 { len.div_ceil(2) } else { len };
    code + 4 * p
}

/// The `palette` and `code` tensors of `table`.
fn coded(table: &[f32], palette: &[f32]) -> [(&'static str, Raw); 2] {
    let index: HashMap<u32, u8> = palette
        .iter()
        .enumerate()
        .map(|(i, q)| (q.to_bits(), i as u8))
        .collect();
    let code_of = |q: &f32| index[&q.to_bits()];
    let code: Vec<u8> = if palette.len() <= 16 {
        table
            .chunks(2)
            .map(|pair| code_of(&pair[0]) | pair.get(1).map_or(0, |q| code_of(q) << 4))
            .collect()
    } else {
        table.iter().map(code_of).collect()
    };
    let values = palette.iter().flat_map(|q| q.to_le_bytes()).collect();
    [
        ("code", raw(Dtype::U8, code.len(), code)),
        ("palette", raw(Dtype::F32, palette.len(), values)),
    ]
}

/// The table of `len` entries that `code` encodes against `palette`.
fn decode(palette: &[f32], code: &[u8], len: usize) -> Result<Vec<f32>, TableFileError> {
    let bad = |problem: String| TableFileError::Tensor {
        name: "code",
        problem,
    };
    if palette.is_empty() || palette.len() > MAX_PALETTE {
        return Err(TableFileError::Tensor {
            name: "palette",
            problem: format!("{} values, expected 1 to {MAX_PALETTE}", palette.len()),
        });
    }
    let value = |c: u8| {
        palette.get(c as usize).copied().ok_or_else(|| {
            bad(format!(
                "code {c} is outside the palette of {} values",
                palette.len()
            ))
        })
    };
    if code.len() == len {
        code.iter().map(|&c| value(c)).collect()
    } else if code.len() == len.div_ceil(2) && palette.len() <= 16 {
        let mut table = Vec::with_capacity(len);
        for &byte in code {
            table.push(value(byte & 0x0f)?);
            if table.len() < len {
                table.push(value(byte >> 4)?);
            }
        }
        Ok(table)
    } else {
        Err(bad(format!(
            "{} bytes for a table of {len} entries (expected {len}, or {} with at most 16 values)",
            code.len(),
            len.div_ceil(2)
        )))
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
        // Updates as they come, so that `touch` writes one entry at any level.
        let tabular = TabularConfig {
            all_segments: false,
            ..TabularConfig::default()
        };
        TabularAgent::new(&grid, &config, &tabular, Rng::seed_from(0)).unwrap()
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
            extra: &[],
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

    /// Fills every entry of level `level` with one of `values`, by position.
    fn fill(a: &mut TabularAgent, level: usize, values: &[f32]) {
        for (i, q) in a.tables[level].iter_mut().enumerate() {
            *q = values[(i * 7 + i / 3) % values.len()];
        }
    }

    #[test]
    fn dense_tables_are_coded_in_one_byte_or_half_a_byte_per_entry() {
        let mut a = agent(2, 5, 10);
        let len = a.tables[1].len();
        // 12 distinct values (every goal learned): two entries per byte.
        let few: Vec<f32> = (0..12).map(|i| -0.5 * i as f32).collect();
        fill(&mut a, 1, &few);
        let bytes = a.table_to_safetensors(1).unwrap();
        assert!(bytes.len() < len / 2 + 1000, "{} for {len}", bytes.len());
        // 200 distinct values (-0.0 among them, kept apart from 0.0): one byte per entry.
        let mut many: Vec<f32> = (0..199).map(|i| -0.01 * i as f32).collect();
        many.push(-0.0);
        fill(&mut a, 0, &many);
        let level0 = a.table_to_safetensors(0).unwrap();
        assert!(level0.len() < a.tables[0].len() + 2000);
        assert!(level0.len() > a.tables[0].len());

        let mut b = agent(2, 5, 10);
        b.load_table(1, &bytes).unwrap();
        b.load_table(0, &level0).unwrap();
        for level in 0..2 {
            let bits = |t: &[f32]| t.iter().map(|q| q.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                bits(&a.tables[level]),
                bits(&b.tables[level]),
                "level {level}"
            );
        }
        assert_eq!(b.table_to_safetensors(1).unwrap(), bytes, "same bytes");

        // More than 256 values: sparse, whatever the density.
        let spread: Vec<f32> = (0..300).map(|i| -0.01 * i as f32).collect();
        fill(&mut a, 1, &spread);
        let sparse = a.table_to_safetensors(1).unwrap();
        assert!(sparse.len() > 7 * len);
        let mut c = agent(2, 5, 10);
        c.load_table(1, &sparse).unwrap();
        assert_eq!(a.tables[1], c.tables[1]);
    }

    #[test]
    fn malformed_codes_are_refused_and_leave_the_table_alone() {
        let mut a = agent(2, 5, 10);
        fill(&mut a, 1, &[-1.0, -2.0, -3.0]);
        let good = a.table_to_safetensors(1).unwrap();
        let file = SafeTensors::deserialize(&good).unwrap();
        let (_, header) = SafeTensors::read_metadata(&good).unwrap();
        let palette: Vec<u8> = file.tensor("palette").unwrap().data().to_vec();
        let code: Vec<u8> = file.tensor("code").unwrap().data().to_vec();
        let rebuild = |palette: &[u8], code: &[u8]| {
            let tensors = [
                ("code", raw(Dtype::U8, code.len(), code.to_vec())),
                (
                    "palette",
                    raw(Dtype::F32, palette.len() / 4, palette.to_vec()),
                ),
            ];
            safetensors::serialize(
                tensors.iter().map(|(name, t)| (*name, t)),
                header.metadata().clone(),
            )
            .unwrap()
        };
        assert_eq!(rebuild(&palette, &code), good);
        let mut b = agent(2, 5, 10);
        let before = b.tables[1].clone();
        // A code beyond the palette (3 values: nibble 5 points nowhere).
        let mut beyond = code.clone();
        beyond[10] = 0x55;
        let err = b.load_table(1, &rebuild(&palette, &beyond)).unwrap_err();
        assert!(err.to_string().contains("outside the palette"), "{err}");
        // A code of the wrong length.
        let err = b.load_table(1, &rebuild(&palette, &code[1..])).unwrap_err();
        assert!(err.to_string().contains("bytes for a table"), "{err}");
        // An empty palette.
        let err = b.load_table(1, &rebuild(&[], &code)).unwrap_err();
        assert!(err.to_string().contains("palette"), "{err}");
        assert_eq!(b.tables[1], before);
    }

    #[test]
    fn sparse_files_of_the_first_format_still_load() {
        let mut a = agent(2, 5, 10);
        touch(&mut a, 1, &[0.0, 2.0], -0.25);
        let v2 = a.table_to_safetensors(1).unwrap();
        let (_, header) = SafeTensors::read_metadata(&v2).unwrap();
        let mut metadata = header.metadata().clone().unwrap();
        let pairs = metadata[METADATA_KEY].replace(FORMAT, FORMAT_V1);
        metadata.insert(METADATA_KEY.to_string(), pairs);
        let file = SafeTensors::deserialize(&v2).unwrap();
        let copy = |name: &str| {
            let t = file.tensor(name).unwrap();
            raw(t.dtype(), t.shape()[0], t.data().to_vec())
        };
        let tensors = [("index", copy("index")), ("value", copy("value"))];
        let v1 = safetensors::serialize(tensors.iter().map(|(name, t)| (*name, t)), Some(metadata))
            .unwrap();
        let mut b = agent(2, 5, 10);
        b.load_table(1, &v1).unwrap();
        assert_eq!(a.tables[1], b.tables[1]);
        // Any other format is refused by name.
        let mut other = v1.clone();
        let at = other
            .windows(FORMAT_V1.len())
            .position(|w| w == FORMAT_V1.as_bytes())
            .unwrap();
        other[at + FORMAT_V1.len() - 1] = b'9';
        let err = b.load_table(1, &other).unwrap_err().to_string();
        assert!(err.contains("format"), "{err}");
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
