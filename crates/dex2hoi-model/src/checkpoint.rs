//! Checkpoints: safetensors files with named tensors and string metadata; the model's
//! configuration always travels in the metadata, and a checkpoint whose configuration or
//! parameters do not match is refused with the file and the difference named. Writes are
//! atomic (temporary file, then rename).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use candle_core::safetensors::Load;
use candle_core::{DType, Device, Tensor};

use crate::config::ModelConfig;
use crate::error::{ModelError, Result};
use crate::init::SeededVarMap;
use crate::model::Model;

/// Metadata key of the model configuration (JSON).
pub const CONFIG_KEY: &str = "dex2hoi.model_config";
/// Metadata key of the checkpoint format.
pub const FORMAT_KEY: &str = "dex2hoi.format";
/// The checkpoint format this code writes.
pub const FORMAT: &str = "dex2hoi-checkpoint-1";

fn checkpoint_error(
    path: &Path,
    what: &str,
    expected: impl Into<String>,
    got: impl std::fmt::Display,
) -> ModelError {
    ModelError::Checkpoint {
        path: path.to_path_buf(),
        what: what.into(),
        expected: expected.into(),
        got: got.to_string(),
    }
}

/// Writes named tensors and metadata to a safetensors file, atomically.
pub fn write_tensors(
    path: &Path,
    tensors: &BTreeMap<String, Tensor>,
    metadata: &BTreeMap<String, String>,
) -> Result<()> {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp-{}", std::process::id()));
    let temporary: PathBuf = path.with_file_name(name);
    let contiguous: Vec<(String, Tensor)> =
        tensors.iter().map(|(k, t)| Ok((k.clone(), t.contiguous()?))).collect::<Result<_>>()?;
    let info: HashMap<String, String> = metadata.clone().into_iter().collect();
    safetensors::serialize_to_file(contiguous, Some(info), &temporary)
        .map_err(|e| checkpoint_error(&temporary, "writing", "a writable file", e))?;
    std::fs::rename(&temporary, path).map_err(|source| ModelError::Io {
        path: path.to_path_buf(),
        action: "renaming into place",
        source,
    })
}

/// Reads every tensor and the metadata of a safetensors file.
pub fn read_tensors(
    path: &Path,
    device: &Device,
) -> Result<(BTreeMap<String, Tensor>, BTreeMap<String, String>)> {
    let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
        path: path.to_path_buf(),
        action: "reading the checkpoint",
        source,
    })?;
    read_tensors_from_bytes(&bytes, path, device)
}

/// [`read_tensors`] of a safetensors file already in memory; `path` names it in errors.
pub fn read_tensors_from_bytes(
    bytes: &[u8],
    path: &Path,
    device: &Device,
) -> Result<(BTreeMap<String, Tensor>, BTreeMap<String, String>)> {
    let file = safetensors::SafeTensors::deserialize(bytes)
        .map_err(|e| checkpoint_error(path, "content", "a safetensors file", e))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| checkpoint_error(path, "header", "a safetensors header", e))?;
    let metadata: BTreeMap<String, String> =
        header.metadata().clone().unwrap_or_default().into_iter().collect();
    let mut tensors = BTreeMap::new();
    for (name, view) in file.tensors() {
        // safetensors checks that the bytes match the shape's element count, but a shape with
        // a zero dimension holds no bytes whatever its other dimensions, and candle's strides
        // of such a shape can overflow: every dimension's product must fit.
        let fits =
            view.shape().iter().filter(|&&d| d > 0).try_fold(1usize, |n, &d| n.checked_mul(d));
        if fits.is_none() {
            return Err(checkpoint_error(
                path,
                &name,
                "a shape whose dimensions' product fits memory",
                format!("{:?}", view.shape()),
            ));
        }
        tensors.insert(name, view.load(device)?);
    }
    Ok((tensors, metadata))
}

/// The model configuration stored in checkpoint metadata.
pub fn config_from_metadata(
    path: &Path,
    metadata: &BTreeMap<String, String>,
) -> Result<ModelConfig> {
    if metadata.get(FORMAT_KEY).map(String::as_str) != Some(FORMAT) {
        return Err(checkpoint_error(
            path,
            FORMAT_KEY,
            FORMAT,
            format!("{:?}", metadata.get(FORMAT_KEY)),
        ));
    }
    let json = metadata
        .get(CONFIG_KEY)
        .ok_or_else(|| checkpoint_error(path, CONFIG_KEY, "the model configuration", "nothing"))?;
    let config: ModelConfig = serde_json::from_str(json)
        .map_err(|e| checkpoint_error(path, CONFIG_KEY, "a valid model configuration", e))?;
    config.validate()?;
    Ok(config)
}

/// Metadata with the format and the configuration.
pub fn model_metadata(config: &ModelConfig) -> BTreeMap<String, String> {
    let json = serde_json::to_string(config).expect("a model configuration serialises");
    BTreeMap::from([(FORMAT_KEY.to_string(), FORMAT.to_string()), (CONFIG_KEY.to_string(), json)])
}

/// The parameters of a var map by name, each prefixed.
pub fn named_parameters(vars: &SeededVarMap, prefix: &str) -> BTreeMap<String, Tensor> {
    let data = vars.var_map().data().lock().expect("the var map lock is not poisoned");
    data.iter().map(|(name, var)| (format!("{prefix}{name}"), var.as_tensor().clone())).collect()
}

/// Sets every parameter of a var map from `tensors[prefix + name]`, refusing a missing
/// parameter, a shape that differs, or a tensor under the prefix that the model does not have.
pub fn assign_parameters(
    vars: &SeededVarMap,
    tensors: &BTreeMap<String, Tensor>,
    prefix: &str,
    path: &Path,
) -> Result<()> {
    let data = vars.var_map().data().lock().expect("the var map lock is not poisoned");
    for (name, var) in data.iter() {
        let key = format!("{prefix}{name}");
        let tensor = tensors.get(&key).ok_or_else(|| {
            checkpoint_error(path, &key, format!("a tensor of shape {:?}", var.dims()), "nothing")
        })?;
        if tensor.dims() != var.dims() {
            return Err(checkpoint_error(
                path,
                &key,
                format!("shape {:?}", var.dims()),
                format!("{:?}", tensor.dims()),
            ));
        }
        var.set(&tensor.to_dtype(var.dtype())?.to_device(var.device())?)?;
    }
    if let Some(extra) =
        tensors.keys().find(|k| k.starts_with(prefix) && !data.contains_key(&k[prefix.len()..]))
    {
        return Err(checkpoint_error(
            path,
            extra,
            "only parameters of this model",
            "a parameter it does not have",
        ));
    }
    Ok(())
}

impl Model {
    /// Builds the model stored under `prefix` (`model.`, `ema.model.`) in a checkpoint's
    /// tensors and metadata, read from `path` by [`read_tensors`]. With `expected`, a
    /// checkpoint of another configuration is refused.
    pub fn from_checkpoint(
        path: &Path,
        tensors: &BTreeMap<String, Tensor>,
        metadata: &BTreeMap<String, String>,
        prefix: &str,
        expected: Option<&ModelConfig>,
        dtype: DType,
        device: &Device,
    ) -> Result<(Model, SeededVarMap)> {
        let config = config_from_metadata(path, metadata)?;
        if let Some(expected) = expected
            && expected != &config
        {
            return Err(checkpoint_error(
                path,
                "model configuration",
                serde_json::to_string(expected).unwrap_or_default(),
                serde_json::to_string(&config).unwrap_or_default(),
            ));
        }
        // The configuration comes from the file: its sizes are held to what the file's tensors
        // under `prefix` hold before the model is built, so that a hostile one (a latent width
        // of 10^9) is refused instead of allocated. No size of a model exceeds its count of
        // parameter values, and each parameter must be in the file (`parameter_budget` leaves
        // room for a few missing, which `assign_parameters` then names).
        let elements = tensors
            .iter()
            .filter(|(name, _)| name.starts_with(prefix))
            .map(|(_, tensor)| tensor.elem_count())
            .fold(0usize, usize::saturating_add);
        let budget = crate::init::parameter_budget(elements);
        let within = format!("sizes within the {elements} values of its {prefix}* tensors");
        if let Ok(serde_json::Value::Object(fields)) = serde_json::to_value(&config) {
            for (field, value) in fields {
                if value.as_u64().is_some_and(|v| v > elements as u64) {
                    return Err(checkpoint_error(
                        path,
                        &format!("{CONFIG_KEY} {field}"),
                        within,
                        value,
                    ));
                }
            }
        }
        let vars = SeededVarMap::new(0);
        let (model, refused) = crate::init::with_parameter_budget(budget, || {
            Model::new(&config, vars.builder(dtype, device))
        });
        if let Some(refused) = refused {
            return Err(checkpoint_error(path, CONFIG_KEY, within, refused));
        }
        let model = model?;
        assign_parameters(&vars, tensors, prefix, path)?;
        Ok((model, vars))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A safetensors file of one tensor: the 8-byte header length, the JSON header, the data.
    fn safetensors_file(header: &str, data: &[u8]) -> Vec<u8> {
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend(header.as_bytes());
        bytes.extend(data);
        bytes
    }

    /// A configuration in the metadata asking for more than the file's tensors hold is refused
    /// before the model is built (a latent width of 2^30 used to allocate its layers first).
    #[test]
    fn hostile_configurations_are_refused_before_building() {
        let path = Path::new("hostile.safetensors");
        let config = ModelConfig::tiny();
        let vars = SeededVarMap::new(0);
        Model::new(&config, vars.builder(DType::F32, &Device::Cpu)).unwrap();
        let tensors = named_parameters(&vars, "model.");
        let load = |config: &ModelConfig| {
            let started = std::time::Instant::now();
            let result = Model::from_checkpoint(
                path,
                &tensors,
                &model_metadata(config),
                "model.",
                None,
                DType::F32,
                &Device::Cpu,
            );
            assert!(started.elapsed().as_secs_f32() < 5.0);
            result.map(|_| ()).map_err(|e| e.to_string())
        };
        load(&config).unwrap();
        // A size past every value the file holds.
        let huge = ModelConfig { latent: 1 << 30, ..config.clone() };
        let error = load(&huge).unwrap_err();
        assert!(error.contains("hostile.safetensors") && error.contains("latent"), "{error}");
        // Sizes each within the file, whose parameters together are not.
        let wide = ModelConfig { latent: 4096, feed_forward: 4096, ..config.clone() };
        let error = load(&wide).unwrap_err();
        assert!(error.contains("hostile.safetensors") && error.contains("past the"), "{error}");
    }

    #[test]
    fn empty_tensors_with_huge_dimensions_are_refused() {
        let path = Path::new("huge.safetensors");
        let fine =
            safetensors_file(r#"{"t":{"dtype":"F32","shape":[0,3],"data_offsets":[0,0]}}"#, &[]);
        let (tensors, _) = read_tensors_from_bytes(&fine, path, &Device::Cpu).unwrap();
        assert_eq!(tensors["t"].dims(), [0, 3]);
        let huge = safetensors_file(
            r#"{"t":{"dtype":"F32","shape":[0,1099511627776,1099511627776],"data_offsets":[0,0]}}"#,
            &[],
        );
        let error = read_tensors_from_bytes(&huge, path, &Device::Cpu).unwrap_err().to_string();
        assert!(error.contains("huge.safetensors") && error.contains("fits memory"), "{error}");
    }
}
