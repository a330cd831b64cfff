//! Reading and writing `f32` tensors and string metadata in the safetensors format.
//!
//! safetensors keeps metadata in a `HashMap`, whose order (and so the file's bytes) would change
//! from run to run. To make equal states give equal files, all metadata goes into the single
//! entry [`METADATA_KEY`] as sorted `key=value` pairs separated by `;` (keys and values here are
//! names and numbers, which contain neither character). Files meant for other programs (the
//! exported policy) keep one plain metadata entry per key instead
//! ([`TensorWriter::finish_plain`]); the reader accepts both.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::str::FromStr;

use safetensors::{Dtype, SafeTensors, View};

use crate::NnError;

/// One little-endian `f32` tensor, ready to be written.
struct F32Tensor {
    shape: Vec<usize>,
    bytes: Vec<u8>,
}

impl View for &F32Tensor {
    fn dtype(&self) -> Dtype {
        Dtype::F32
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

/// The one safetensors metadata entry this crate writes.
const METADATA_KEY: &str = "hac_nn";

/// Collects named tensors and metadata, then serialises them.
#[derive(Default)]
pub(crate) struct TensorWriter {
    tensors: Vec<(String, F32Tensor)>,
    metadata: BTreeMap<String, String>,
}

impl TensorWriter {
    pub fn add(&mut self, name: String, shape: &[usize], values: &[f32]) {
        debug_assert_eq!(shape.iter().product::<usize>(), values.len());
        let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let shape = shape.to_vec();
        self.tensors.push((name, F32Tensor { shape, bytes }));
    }

    pub fn meta(&mut self, key: String, value: impl ToString) {
        let value = value.to_string();
        debug_assert!(![&key, &value].iter().any(|s| s.contains([';', '='])));
        self.metadata.insert(key, value);
    }

    pub fn finish(self) -> Vec<u8> {
        let tensors = self.tensors.iter().map(|(name, t)| (name.as_str(), t));
        let pairs: Vec<String> = self
            .metadata
            .iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        let metadata = HashMap::from([(METADATA_KEY.to_string(), pairs.join(";"))]);
        // Only a header above safetensors' 100 MB limit can fail, far beyond any network here.
        safetensors::serialize(tensors, Some(metadata)).expect("serialising in-memory f32 tensors")
    }

    /// [`finish`](Self::finish) with every metadata entry as its own safetensors metadata key,
    /// as other tools expect to find them.
    pub fn finish_plain(self) -> Vec<u8> {
        let tensors = self.tensors.iter().map(|(name, t)| (name.as_str(), t));
        let metadata: HashMap<String, String> = self.metadata.into_iter().collect();
        safetensors::serialize(tensors, Some(metadata)).expect("serialising in-memory f32 tensors")
    }
}

/// A parsed safetensors buffer with typed, shape-checked accessors.
pub(crate) struct TensorReader<'a> {
    file: SafeTensors<'a>,
    metadata: BTreeMap<String, String>,
}

impl<'a> TensorReader<'a> {
    pub fn new(bytes: &'a [u8]) -> Result<Self, NnError> {
        let file = SafeTensors::deserialize(bytes)?;
        let (_, header) = SafeTensors::read_metadata(bytes)?;
        let metadata = match header.metadata().as_ref() {
            Some(m) => match m.get(METADATA_KEY) {
                Some(pairs) => pairs
                    .split(';')
                    .filter_map(|pair| pair.split_once('='))
                    .map(|(k, v)| (k.to_string(), v.to_string()))
                    .collect(),
                None => m.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
            },
            None => BTreeMap::new(),
        };
        Ok(Self { file, metadata })
    }

    /// The shape of tensor `name`, if present.
    pub fn shape(&self, name: &str) -> Option<Vec<usize>> {
        self.file.tensor(name).ok().map(|t| t.shape().to_vec())
    }

    /// Tensor `name`, which must be `f32` of shape `expected`.
    pub fn read(&self, name: &str, expected: &[usize]) -> Result<Vec<f32>, NnError> {
        let t = self
            .file
            .tensor(name)
            .map_err(|_| NnError::MissingTensor(name.to_string()))?;
        if t.dtype() != Dtype::F32 {
            return Err(NnError::Dtype {
                name: name.to_string(),
                found: format!("{:?}", t.dtype()),
            });
        }
        if t.shape() != expected {
            return Err(NnError::Shape {
                name: name.to_string(),
                expected: format!("{expected:?}"),
                found: t.shape().to_vec(),
            });
        }
        Ok(t.data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    }

    /// Reads tensor `name` into `out`, whose length fixes the expected (one-dimensional) shape.
    pub fn read_into(&self, name: &str, out: &mut [f32]) -> Result<(), NnError> {
        out.copy_from_slice(&self.read(name, &[out.len()])?);
        Ok(())
    }

    /// Checks the `format` metadata entry, so a file of another kind is refused by name.
    pub fn expect_format(&self, expected: &str) -> Result<(), NnError> {
        let format: String = self.meta("format")?;
        if format != expected {
            return Err(NnError::Metadata {
                key: "format".into(),
                reason: format!("expected `{expected}`, got `{format}`"),
            });
        }
        Ok(())
    }

    /// Every metadata entry.
    pub fn metadata(&self) -> &BTreeMap<String, String> {
        &self.metadata
    }

    /// Metadata entry `key`, parsed.
    pub fn meta<T: FromStr>(&self, key: &str) -> Result<T, NnError> {
        let value = self.metadata.get(key).ok_or_else(|| NnError::Metadata {
            key: key.to_string(),
            reason: "missing".into(),
        })?;
        value.parse().map_err(|_| NnError::Metadata {
            key: key.to_string(),
            reason: format!("cannot parse `{value}`"),
        })
    }
}
