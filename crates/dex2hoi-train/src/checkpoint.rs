//! A trainer's checkpoint: written atomically with everything a resumed run needs (parameters,
//! EMA, optimiser moments, step, configuration, vocabulary), restored bit for bit, or read as
//! the starting weights of a new run (fine-tuning).

use std::collections::BTreeMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};

use dex2hoi_model::checkpoint::{CONFIG_KEY, FORMAT, FORMAT_KEY, read_tensors, write_tensors};
use dex2hoi_optim::Parameter;
use dex2hoi_sample::{
    STEP_KEY, STEPS_BEFORE_KEY, TRAIN_CONFIG_KEY, TextModule, VOCABULARY_KEY, trained_steps,
};

use dex2hoi_model::text::{PAD, UNKNOWN, Vocabulary};

use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::step::Trainer;

impl Trainer {
    /// Writes the checkpoint (parameters, EMA, optimiser moments, step, configuration,
    /// vocabulary) atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut tensors = BTreeMap::new();
        // Everything is written as host f32 tensors, so the file is the same whatever device
        // trained it.
        let host =
            |t: &Tensor| -> Result<Tensor> { Ok(t.to_dtype(DType::F32)?.to_device(&Device::Cpu)?) };
        for (k, p) in self.parameters.iter().enumerate() {
            let (first, second) = self.optimizer.moments(k);
            tensors.insert(p.name.clone(), host(p.var.as_tensor())?);
            tensors.insert(format!("ema.{}", p.name), host(self.ema.value(k))?);
            tensors.insert(format!("optimizer.first.{}", p.name), host(first)?);
            tensors.insert(format!("optimizer.second.{}", p.name), host(second)?);
        }
        let mut metadata = BTreeMap::from([
            (FORMAT_KEY.to_string(), FORMAT.to_string()),
            (
                CONFIG_KEY.to_string(),
                serde_json::to_string(&self.config.model).expect("a model config serialises"),
            ),
            (TRAIN_CONFIG_KEY.to_string(), self.config.to_toml()?),
            (STEP_KEY.to_string(), self.step.to_string()),
            ("dex2hoi.optimizer_updates".to_string(), self.optimizer.updates.to_string()),
            (
                "dex2hoi.rng".to_string(),
                format!("chacha8 seeded by {} with the step as stream", self.config.training.seed),
            ),
        ]);
        if self.steps_before > 0 {
            metadata.insert(STEPS_BEFORE_KEY.to_string(), self.steps_before.to_string());
        }
        if let TextModule::Builtin { encoder, .. } = &self.text {
            metadata.insert(
                VOCABULARY_KEY.to_string(),
                serde_json::to_string(encoder.vocabulary().words()).expect("words serialise"),
            );
        }
        write_tensors(path, &tensors, &metadata)?;
        Ok(())
    }

    /// Restores a checkpoint written by [`Trainer::save`] for the same configuration (the
    /// number of steps may differ) and vocabulary.
    pub fn restore(&mut self, path: &Path) -> Result<()> {
        // Read on the host (the file holds host f32 tensors) and placed on the trainer's device.
        let (tensors, metadata) = read_tensors(path, &Device::Cpu)?;
        let stored = metadata.get(TRAIN_CONFIG_KEY).ok_or_else(|| {
            TrainError::checkpoint(path, TRAIN_CONFIG_KEY, "the training configuration", "nothing")
        })?;
        let mut stored = TrainConfig::from_toml(stored, &path.display().to_string())?;
        stored.training.steps = self.config.training.steps;
        if stored != self.config {
            return Err(TrainError::checkpoint(
                path,
                "training configuration",
                "the configuration of the run being resumed (apart from training.steps)",
                "a different one",
            ));
        }
        self.check_vocabulary(&metadata, path)?;
        let read = |name: &str, p: &Parameter| -> Result<&Tensor> {
            let t = tensors
                .get(name)
                .ok_or_else(|| TrainError::checkpoint(path, name, "a tensor", "nothing"))?;
            let count = p.var.elem_count();
            if t.elem_count() != count {
                return Err(TrainError::checkpoint(
                    path,
                    name,
                    format!("{count} values"),
                    t.elem_count(),
                ));
            }
            Ok(t)
        };
        for (k, p) in self.parameters.iter().enumerate() {
            let value = read(&p.name, p)?.reshape(p.var.shape())?;
            p.var.set(&value.to_dtype(p.var.dtype())?.to_device(p.var.device())?)?;
            self.ema.set_value(k, p, read(&format!("ema.{}", p.name), p)?)?;
            self.optimizer.set_moments(
                k,
                p,
                read(&format!("optimizer.first.{}", p.name), p)?,
                read(&format!("optimizer.second.{}", p.name), p)?,
            )?;
        }
        let number = |key: &str| -> Result<usize> {
            metadata
                .get(key)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| TrainError::checkpoint(path, key, "a step count", "nothing"))
        };
        self.step = number(STEP_KEY)?;
        self.optimizer.updates = number("dex2hoi.optimizer_updates")?;
        self.steps_before =
            if metadata.contains_key(STEPS_BEFORE_KEY) { number(STEPS_BEFORE_KEY)? } else { 0 };
        Ok(())
    }

    /// Starts this fresh trainer from the EMA weights of a trained model: a packed model
    /// (`dex2hoi model pack`) or a run's checkpoint. The weights become both the parameters and
    /// their EMA; AdamW starts afresh (zero moments, its warm-up included) and the step count at
    /// 0, so the learning-rate schedule and the batches are this run's own, while the steps the
    /// weights had behind them are kept ([`STEPS_BEFORE_KEY`]) and counted in a packed model.
    /// The model must have this configuration's network and text encoder; the training settings
    /// (losses, optimiser, batch) are this run's. Two differences are bridged:
    /// - a dataset with other words: the built-in encoder's word embeddings are carried over
    ///   by word, and a word the model never saw starts as its unknown-word embedding (what the
    ///   model read it as);
    /// - a configuration that adds the prompt clock to a model without it: the clock keeps its
    ///   initialisation (its output layer is zero, so the model starts as it was).
    ///
    /// The normalisation statistics are the dataset's, as for every run: fine-tuning on the
    /// model's own dataset keeps them as they were. Returns what was bridged.
    pub fn initialise_from(&mut self, path: &Path) -> Result<Initialisation> {
        self.initialise_from_except(path, Fresh::Nothing)
    }

    /// [`Trainer::initialise_from`], with the parts named by `fresh` left at this run's own
    /// initialisation (its seed) instead of taking the model's weights. With
    /// [`Fresh::TextEncoder`] the built-in text encoder starts afresh: its `[text]` settings
    /// and vocabulary are this run's, whatever the model's were, and only the denoiser is
    /// carried over.
    pub fn initialise_from_except(&mut self, path: &Path, fresh: Fresh) -> Result<Initialisation> {
        if self.step > 0 {
            return Err(TrainError::checkpoint(
                path,
                "initial weights",
                "a trainer that has not stepped",
                format!("{} steps done", self.step),
            ));
        }
        let (tensors, metadata) = read_tensors(path, &Device::Cpu)?;
        let format = metadata.get(FORMAT_KEY).map_or("nothing", String::as_str);
        if format != FORMAT {
            return Err(TrainError::checkpoint(path, FORMAT_KEY, FORMAT, format));
        }
        let mut stored = TrainConfig::from_model_metadata(&metadata, path)?;
        // Dropout is how the network trains, not what it is.
        stored.model.dropout = self.config.model.dropout;
        // A run may add the prompt clock, the object start or the memory of set-down objects
        // (each starts with no effect), or the start or reach frame in the prefix (no parameters
        // of its own; the network learns to read its first prefix token anew).
        let gains_clock = !stored.model.prompt_clock && self.config.model.prompt_clock;
        if gains_clock {
            stored.model.prompt_clock = true;
        }
        let gains_start =
            stored.model.object_start.is_off() && !self.config.model.object_start.is_off();
        if gains_start {
            stored.model.object_start = self.config.model.object_start;
        }
        let gains_settled = !stored.model.settled_objects && self.config.model.settled_objects;
        if gains_settled {
            stored.model.settled_objects = true;
        }
        stored.model.start_in_prefix |= self.config.model.start_in_prefix;
        stored.model.reach_in_prefix |= self.config.model.reach_in_prefix;
        for (section, model, run) in [
            (
                "[model]",
                serde_json::to_value(&stored.model),
                serde_json::to_value(&self.config.model),
            ),
            ("[text]", serde_json::to_value(&stored.text), serde_json::to_value(&self.config.text)),
        ] {
            if section == "[text]" && fresh == Fresh::TextEncoder {
                continue;
            }
            let (model, run) =
                (model.expect("a config serialises"), run.expect("a config serialises"));
            // Both ways: a key the model has and the run leaves out (an option it has on,
            // off in the run) differs as much as one the run sets otherwise.
            let keys: std::collections::BTreeSet<&String> = [&model, &run]
                .iter()
                .filter_map(|v| v.as_object())
                .flat_map(|o| o.keys())
                .collect();
            let shown =
                |v: Option<&serde_json::Value>| v.map_or("nothing".into(), |v| v.to_string());
            let differing: Vec<String> = keys
                .into_iter()
                .filter(|key| model.get(key.as_str()) != run.get(key.as_str()))
                .map(|key| {
                    let (theirs, ours) =
                        (shown(model.get(key.as_str())), shown(run.get(key.as_str())));
                    format!("{key} = {theirs} (this run: {ours})")
                })
                .collect();
            if !differing.is_empty() {
                return Err(TrainError::checkpoint(
                    path,
                    section,
                    format!("the {section} settings of this run's configuration"),
                    differing.join(", "),
                ));
            }
        }
        let remap = match fresh {
            Fresh::Nothing => self.vocabulary_remap(&metadata, path)?,
            Fresh::TextEncoder => None,
        };
        let mut initialisation = Initialisation::default();
        if let Some(remap) = &remap {
            // After the two special tokens, which every vocabulary has.
            let words = &remap[2..];
            initialisation.words_carried = words.iter().filter(|r| r.is_some()).count();
            initialisation.words_new = words.len() - initialisation.words_carried;
        }
        for (k, p) in self.parameters.iter().enumerate() {
            if fresh == Fresh::TextEncoder && p.name.starts_with(TEXT_ENCODER_PREFIX) {
                initialisation.fresh.push(p.name.clone());
                continue;
            }
            let name = format!("ema.{}", p.name);
            let Some(t) = tensors.get(&name) else {
                let gained = (gains_clock && p.name.contains(".clock_"))
                    || (gains_start && p.name.contains(".object_start_"))
                    || (gains_settled && p.name.contains(".settled_"));
                if gained {
                    initialisation.kept.push(p.name.clone());
                    continue;
                }
                return Err(TrainError::checkpoint(path, &name, "a tensor", "nothing"));
            };
            let remapped;
            let t = match (&remap, p.name.as_str()) {
                (Some(remap), TOKEN_EMBEDDINGS) => {
                    remapped = remap_rows(t, remap)?;
                    &remapped
                }
                _ => t,
            };
            if t.dims() != p.var.dims() {
                return Err(TrainError::checkpoint(
                    path,
                    &name,
                    format!("shape {:?}", p.var.dims()),
                    format!("{:?}", t.dims()),
                ));
            }
            p.var.set(&t.to_dtype(p.var.dtype())?.to_device(p.var.device())?)?;
            self.ema.set_value(k, p, t)?;
        }
        self.steps_before = trained_steps(&metadata);
        Ok(initialisation)
    }

    /// For the built-in encoder, where each of this dataset's vocabulary entries (`[PAD]`,
    /// `[UNK]`, then the words) comes from in a file's: `Some(row)`, or `None` for a word the
    /// file's model never saw. `None` when the vocabularies are the same or the encoder is a
    /// frozen one.
    fn vocabulary_remap(
        &self,
        metadata: &BTreeMap<String, String>,
        path: &Path,
    ) -> Result<Option<Vec<Option<usize>>>> {
        let TextModule::Builtin { encoder, .. } = &self.text else { return Ok(None) };
        let words = stored_words(metadata, path)?.ok_or_else(|| {
            TrainError::checkpoint(path, VOCABULARY_KEY, "the built-in encoder's words", "none")
        })?;
        if words.as_slice() == encoder.vocabulary().words() {
            return Ok(None);
        }
        let theirs = Vocabulary::from_words(words);
        let ours = encoder.vocabulary();
        let specials = [PAD, UNKNOWN].map(|id| Some(id as usize));
        let by_word = ours.words().iter().map(|word| {
            // `tokenize` of a known word is its one id; an unknown word is `UNKNOWN`.
            let id = theirs.tokenize(word).first().copied().unwrap_or(UNKNOWN);
            (id != UNKNOWN).then_some(id as usize)
        });
        Ok(Some(specials.into_iter().chain(by_word).collect()))
    }

    /// Checks that the built-in encoder's vocabulary in a file's metadata is this dataset's
    /// (resuming a run).
    fn check_vocabulary(&self, metadata: &BTreeMap<String, String>, path: &Path) -> Result<()> {
        if let TextModule::Builtin { encoder, .. } = &self.text {
            let words = stored_words(metadata, path)?;
            if words.as_deref() != Some(encoder.vocabulary().words()) {
                return Err(TrainError::checkpoint(
                    path,
                    VOCABULARY_KEY,
                    "the vocabulary of this dataset",
                    if words.is_some() { "another vocabulary" } else { "none" },
                ));
            }
        }
        Ok(())
    }
}

/// The built-in encoder's word embeddings among the trained parameters, `[vocabulary, width]`.
const TOKEN_EMBEDDINGS: &str = "text_encoder.tokens";

/// The start of the names of the built-in text encoder's parameters.
const TEXT_ENCODER_PREFIX: &str = "text_encoder.";

/// Parts of a model that a run started from it ([`Trainer::initialise_from_except`]) does not
/// take over but trains from its own initialisation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Fresh {
    /// Every weight comes from the model.
    #[default]
    Nothing,
    /// The built-in text encoder starts from this run's seed: for a model whose encoder learned
    /// to pass over words its data never needed (the hand in "with the left hand" when the
    /// object's side already told it), which fine-tuning alone does not undo.
    TextEncoder,
}

/// What [`Trainer::initialise_from`] bridged between the model and this run.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Initialisation {
    /// Words of this dataset's vocabulary whose embeddings came from the model (0 when the
    /// vocabularies are the same).
    pub words_carried: usize,
    /// Words the model never saw, started as its unknown-word embedding.
    pub words_new: usize,
    /// Parameters the model does not have, kept at their initialisation (the prompt clock's
    /// or the object start's).
    pub kept: Vec<String>,
    /// Parameters started afresh on request ([`Fresh`]), though the model has them.
    pub fresh: Vec<String>,
}

/// The rows of a `[rows, width]` embedding table in a new order: row `k` of the result is
/// `table[from[k]]`, or the unknown-word row for `None`.
///
/// # Shapes
/// - `table`: `[rows, width]`; returns `[from.len(), width]`
fn remap_rows(table: &Tensor, from: &[Option<usize>]) -> Result<Tensor> {
    let ids: Vec<u32> = from.iter().map(|row| row.map_or(UNKNOWN, |r| r as u32)).collect();
    let ids = Tensor::from_vec(ids, from.len(), table.device())?;
    Ok(table.index_select(&ids, 0)?)
}

/// The built-in encoder's word list a file's metadata holds (`None` when it holds none).
fn stored_words(metadata: &BTreeMap<String, String>, path: &Path) -> Result<Option<Vec<String>>> {
    metadata
        .get(VOCABULARY_KEY)
        .map(|w| serde_json::from_str(w))
        .transpose()
        .map_err(|e| TrainError::checkpoint(path, VOCABULARY_KEY, "a word list", e))
}
