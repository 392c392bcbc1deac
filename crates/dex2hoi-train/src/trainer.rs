//! The training loop: batches, noising, the model, the objective, AdamW and EMA; checkpoints
//! that resume bit for bit; the run directory.
//!
//! Every random draw of a step comes from a ChaCha8 stream seeded by the run's seed and the
//! step number (window choice, text choice and dropout, augmentation, timesteps, noise, dropout
//! masks, in that order; a batch that trains in groups draws one seed per group there instead,
//! each group's masks drawn from its own seed), so the generator state of a checkpoint is its
//! step: a resumed run draws exactly what an uninterrupted one would.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use dex2hoi_data::dataset::{Dataset, write_atomically};
use dex2hoi_data::window::WindowConfig;
use dex2hoi_diffusion::{CosineSchedule, gaussian, sample_timesteps};
use dex2hoi_model::checkpoint::{CONFIG_KEY, FORMAT, FORMAT_KEY, read_tensors, write_tensors};
use dex2hoi_model::text::{UNKNOWN, Vocabulary};
use dex2hoi_model::{Model, ModelInput, SeededVarMap};
use dex2hoi_optim::{AdamW, Ema, Parameter, learning_rate, parameters_of, step_rng};
use dex2hoi_sample::{
    RunFiles, STEP_KEY, STEPS_BEFORE_KEY, TRAIN_CONFIG_KEY, TextModule, VOCABULARY_KEY,
    trained_steps,
};

use crate::batch::{BatchOptions, TrainingSet};
use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::loss::{LossContext, Term};
use crate::run::{append_metrics, read_metrics, truncate_metrics, write_static};

/// Salt of the built-in text encoder's parameter seed (its names differ from the model's, the
/// salt keeps the two streams apart anyway).
const TEXT_SEED_SALT: u64 = 0x7465_7874;

/// What one step did.
#[derive(Debug, Clone, PartialEq)]
pub struct StepReport {
    /// Steps done after this one.
    pub step: usize,
    /// The weighted total loss.
    pub loss: f64,
    /// Each active term, unweighted.
    pub terms: Vec<(Term, f64)>,
    /// The learning rate used.
    pub learning_rate: f64,
    /// The gradient norm before clipping.
    pub gradient_norm: f64,
    /// Wall-clock seconds of the step.
    pub seconds: f64,
    /// Where the seconds went.
    pub timing: StepTiming,
}

/// Seconds spent in the parts of a step.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepTiming {
    /// Drawing the batch, embedding the texts, noising.
    pub batch: f64,
    /// The model's forward pass.
    pub forward: f64,
    /// The objective (FK, decode, distances).
    pub objective: f64,
    /// The backward pass.
    pub backward: f64,
    /// AdamW and EMA.
    pub update: f64,
}

/// Every trained parameter by checkpoint name, sorted: `model.*`, then `text_encoder.*`.
pub fn trained_parameters(model_vars: &SeededVarMap, text: &TextModule) -> Vec<Parameter> {
    let mut parameters = parameters_of(model_vars.var_map(), "model.");
    if let TextModule::Builtin { vars, .. } = text {
        parameters.extend(parameters_of(vars.var_map(), "text_encoder."));
    }
    parameters
}

/// The model's prediction of a step's batch, `[batch, 2, T_f, D]`, with its graph.
enum Prediction {
    /// One forward pass over the whole batch.
    Whole(Tensor),
    /// One forward pass per group of rows ([`Trainer::predict`]): `whole` is their outputs
    /// joined, a leaf that the objective is computed on; `groups` holds each group's first
    /// row and output, whose graphs reach the parameters; `text` the texts' embedding (with
    /// the text encoder's graph) and the leaf the groups read it from.
    Grouped { whole: Var, groups: Vec<(usize, Tensor)>, text: (Tensor, Var) },
}

impl Prediction {
    /// The prediction of the whole batch.
    fn tensor(&self) -> &Tensor {
        match self {
            Self::Whole(prediction) => prediction,
            Self::Grouped { whole, .. } => whole.as_tensor(),
        }
    }
}

/// A model in training with its optimiser state.
#[derive(Debug)]
pub struct Trainer {
    config: TrainConfig,
    data: TrainingSet,
    schedule: CosineSchedule,
    model: Model,
    text: TextModule,
    parameters: Vec<Parameter>,
    optimizer: AdamW,
    ema: Ema,
    loss: LossContext,
    step: usize,
    /// Training steps of the model the run started from ([`Trainer::initialise_from`]).
    steps_before: usize,
    device: Device,
}

impl Trainer {
    /// A fresh trainer (parameters from the seed) on `device` for a dataset that fits the
    /// configuration.
    pub fn new(
        config: TrainConfig,
        dataset: &Dataset,
        dataset_path: &Path,
        device: &Device,
    ) -> Result<Self> {
        config.validate("config")?;
        config.check_dataset(&dataset.manifest, dataset_path)?;
        let device = device.clone();
        let window = WindowConfig {
            prefix_frames: config.model.prefix_frames,
            predicted_frames: config.model.predicted_frames,
            stride: config.training.window_stride,
        };
        let data = TrainingSet::new(dataset, window)?;
        let model_vars = SeededVarMap::new(config.training.seed);
        let model = Model::new(&config.model, model_vars.builder(DType::F32, &device))?;
        let vocabulary = Vocabulary::from_texts(
            data.sequences().iter().flat_map(|s| s.texts.iter().map(String::as_str)),
        );
        let text = TextModule::new(
            &config.text,
            config.model.text_embedding,
            vocabulary,
            config.training.seed ^ TEXT_SEED_SALT,
            &device,
        )?;
        let parameters = trained_parameters(&model_vars, &text);
        let optimizer = AdamW::new(config.optimizer.clone(), &parameters)?;
        let ema = Ema::new(&parameters)?;
        let loss = LossContext::new(
            config.loss.clone(),
            config.model.object_representation,
            data.skeleton().clone(),
            config.model.prefix_frames,
            data.stats().mean.clone(),
            data.stats().std.clone(),
            data.clouds().to_vec(),
        );
        let schedule = CosineSchedule::new(config.training.diffusion_steps)?;
        Ok(Self {
            config,
            data,
            schedule,
            model,
            text,
            parameters,
            optimizer,
            ema,
            loss,
            step: 0,
            steps_before: 0,
            device,
        })
    }

    /// The network being trained.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The training windows.
    pub fn training_set(&self) -> &TrainingSet {
        &self.data
    }

    /// The objective's context.
    pub fn loss_context(&self) -> &LossContext {
        &self.loss
    }

    /// Steps done.
    pub fn steps_done(&self) -> usize {
        self.step
    }

    /// Training steps of the model the run started from (0 for a run from the seed).
    pub fn steps_before(&self) -> usize {
        self.steps_before
    }

    /// The configuration.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The trained parameters (checkpoint names).
    pub fn parameters(&self) -> &[Parameter] {
        &self.parameters
    }

    /// Embeds the batch's texts with word dropout (built-in encoder) and text dropout (the
    /// null condition, a zero row).
    fn encode_text(&self, texts: &[String], rng: &mut ChaCha8Rng) -> Result<Tensor> {
        let t = &self.config.training;
        let keep: Vec<f32> =
            texts.iter().map(|_| if rng.random_bool(t.text_dropout) { 0.0 } else { 1.0 }).collect();
        let embedded = match &self.text {
            TextModule::Builtin { encoder, .. } => {
                let ids: Vec<Vec<u32>> = texts
                    .iter()
                    .map(|text| {
                        let mut ids = encoder.vocabulary().tokenize(text);
                        for id in &mut ids {
                            if rng.random_bool(t.word_dropout) {
                                *id = UNKNOWN;
                            }
                        }
                        ids
                    })
                    .collect();
                encoder.encode_ids(&ids)?
            }
            TextModule::Frozen(encoder) => {
                let refs: Vec<&str> = texts.iter().map(String::as_str).collect();
                encoder.encode(&refs)?.to_device(&self.device)?
            }
        };
        let keep = Tensor::from_vec(keep, (texts.len(), 1), &self.device)?;
        Ok(embedded.to_dtype(DType::F32)?.broadcast_mul(&keep)?)
    }

    /// The objective of the batch of a step (no update): for tests and benchmarks. For a batch
    /// that trains in groups (`training.group_windows`) the total's graph ends at the joined
    /// prediction, not at the parameters.
    pub fn objective_at(&self, step: usize) -> Result<crate::loss::Objective> {
        let mut rng = step_rng(self.config.training.seed, step);
        Ok(self.objective(&mut rng, &mut StepTiming::default())?.0)
    }

    fn objective(
        &self,
        rng: &mut ChaCha8Rng,
        timing: &mut StepTiming,
    ) -> Result<(crate::loss::Objective, Prediction)> {
        let clock = Instant::now();
        let c = &self.config;
        let options = BatchOptions {
            size: c.training.batch_size,
            swap_probability: c.training.swap_probability,
            mirror_probability: c.training.mirror_probability,
        };
        let batch = self.data.batch(&options, rng, &self.device)?;
        let text = self.encode_text(&batch.texts, rng)?;
        let timesteps = sample_timesteps(&self.schedule, batch.size, rng);
        let (tp, tf) = (c.model.prefix_frames, c.model.predicted_frames);
        let x0 = batch.features.narrow(2, tp, tf)?;
        let noise = gaussian(x0.dims(), rng, DType::F32, &self.device)?;
        let noisy = self.schedule.add_noise(&x0, &noise, &timesteps)?;
        let prefix = batch.features.narrow(2, 0, tp)?;
        let timestep_tensor = CosineSchedule::timestep_tensor(&timesteps, &self.device)?;
        let input = ModelInput {
            noisy: &noisy,
            prefix: &prefix,
            timesteps: &timestep_tensor,
            text: &text,
            bps: &batch.bps,
            presence: &batch.presence,
            frame_mask: Some(&batch.frame_mask),
        };
        timing.batch = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let prediction = self.predict(&input, batch.size, rng)?;
        timing.forward = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let objective = self.loss.objective(prediction.tensor(), &batch, &timesteps)?;
        timing.objective = clock.elapsed().as_secs_f64();
        Ok((objective, prediction))
    }

    /// The model's prediction for a batch of `windows`: one forward pass, or on the CPU, with
    /// `training.group_windows` set and smaller than the batch, one per group of at most that
    /// many windows, the groups in parallel. Each group draws its dropout masks from its own
    /// generator, seeded by a draw of the step's stream in group order.
    ///
    /// Why groups: candle runs many of the backward pass's operations (gradient sums, copies,
    /// zero fills) on the calling thread, one after the other; in groups, each thread runs
    /// those of its own groups (the products are still split over the pool's threads).
    /// Measured on 2 threads (`benches/train.rs`, `small`, batch 32, session 17): one group of
    /// 16 windows on one thread took 0.77 s, the whole batch on both 1.0 s.
    fn predict(
        &self,
        input: &ModelInput<'_>,
        windows: usize,
        rng: &mut ChaCha8Rng,
    ) -> Result<Prediction> {
        let groups = match self.config.training.group_windows {
            Some(most) if self.device.is_cpu() => windows.div_ceil(most.max(1)),
            _ => 1,
        };
        if groups <= 1 {
            return Ok(Prediction::Whole(self.model.forward(input, Some(rng))?));
        }
        let seeds: Vec<u64> = (0..groups).map(|_| rng.random()).collect();
        let bounds: Vec<(usize, usize)> = dex2hoi_model::row_groups(windows, groups).collect();
        // The texts' embedding as a leaf too: its graph (the built-in encoder's) is walked
        // once, from the groups' summed gradients, rather than once per group.
        let text = Var::from_tensor(&input.text.detach())?;
        let model = &self.model;
        let outputs: Vec<Tensor> = bounds
            .par_iter()
            .zip(&seeds)
            .map(|(&(start, len), &seed)| -> Result<Tensor> {
                let rows = |t: &Tensor| t.narrow(0, start, len);
                let mask = input.frame_mask.map(rows).transpose()?;
                let group = ModelInput {
                    noisy: &rows(input.noisy)?,
                    prefix: &rows(input.prefix)?,
                    timesteps: &rows(input.timesteps)?,
                    text: &rows(text.as_tensor())?,
                    bps: &rows(input.bps)?,
                    presence: &rows(input.presence)?,
                    frame_mask: mask.as_ref(),
                };
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                Ok(model.forward(&group, Some(&mut rng))?)
            })
            .collect::<Result<_>>()?;
        let detached: Vec<Tensor> = outputs.iter().map(Tensor::detach).collect();
        let whole = Var::from_tensor(&Tensor::cat(&detached, 0)?)?;
        let groups = bounds.into_iter().map(|(start, _)| start).zip(outputs).collect();
        Ok(Prediction::Grouped { whole, groups, text: (input.text.clone(), text) })
    }

    /// The gradients of the trained parameters: through the objective and the model at once
    /// for a whole-batch prediction. For a grouped one: the objective's gradient with respect
    /// to the joined prediction first, then each group's backward pass from its rows of it
    /// (as many groups at a time as the pool has threads, so that only that many gradient
    /// stores are alive), the parameters' gradients summed in group order, and last the text
    /// encoder's from the groups' summed gradient of the embedding.
    fn gradients(&self, total: &Tensor, prediction: Prediction) -> Result<GradStore> {
        let (whole, groups, (text, text_leaf)) = match prediction {
            Prediction::Whole(_) => return Ok(total.backward()?),
            Prediction::Grouped { whole, groups, text } => (whole, groups, text),
        };
        let upstream = match total.backward()?.get(whole.as_tensor()) {
            Some(gradient) => gradient.detach(),
            None => whole.as_tensor().zeros_like()?,
        };
        let mut merged: Option<GradStore> = None;
        let mut text_gradient: Option<Tensor> = None;
        for chunk in groups.chunks(rayon::current_num_threads().max(1)) {
            let stores = chunk
                .par_iter()
                .map(|(start, output)| -> Result<GradStore> {
                    let rows = upstream.narrow(0, *start, output.dim(0)?)?;
                    Ok((output * rows)?.sum_all()?.backward()?)
                })
                .collect::<Result<Vec<_>>>()?;
            for mut store in stores {
                if let Some(gradient) = store.remove(text_leaf.as_tensor()) {
                    text_gradient = Some(match text_gradient {
                        Some(sum) => (sum + gradient)?,
                        None => gradient,
                    });
                }
                merged = Some(match merged {
                    None => store,
                    Some(merged) => self.add_gradients(merged, &store)?,
                });
            }
        }
        let mut merged = merged.expect("at least two groups");
        if let Some(gradient) = text_gradient {
            let of_text = (text * gradient.detach())?.sum_all()?.backward()?;
            merged = self.add_gradients(merged, &of_text)?;
        }
        Ok(merged)
    }

    /// `into` with the trained parameters' gradients of `from` added.
    fn add_gradients(&self, mut into: GradStore, from: &GradStore) -> Result<GradStore> {
        for parameter in &self.parameters {
            let var = parameter.var.as_tensor();
            let sum = match (into.get(var), from.get(var)) {
                (Some(a), Some(b)) => (a + b)?,
                (None, Some(b)) => b.clone(),
                _ => continue,
            };
            into.insert(var, sum);
        }
        Ok(into)
    }

    /// One optimiser step. A NaN or infinite loss returns [`TrainError::NonFinite`] before
    /// anything is updated.
    pub fn step(&mut self, last_checkpoint: usize) -> Result<StepReport> {
        let started = Instant::now();
        let mut rng = step_rng(self.config.training.seed, self.step);
        let mut timing = StepTiming::default();
        let (objective, prediction) = self.objective(&mut rng, &mut timing)?;
        let loss = f64::from(objective.total.to_dtype(DType::F32)?.to_scalar::<f32>()?);
        let mut terms = Vec::with_capacity(objective.terms.len());
        for (term, value) in &objective.terms {
            let value = f64::from(value.to_dtype(DType::F32)?.to_scalar::<f32>()?);
            if !value.is_finite() {
                return Err(TrainError::NonFinite {
                    step: self.step + 1,
                    term: term.name().into(),
                    value,
                    last_checkpoint,
                });
            }
            terms.push((*term, value));
        }
        if !loss.is_finite() {
            return Err(TrainError::NonFinite {
                step: self.step + 1,
                term: "total".into(),
                value: loss,
                last_checkpoint,
            });
        }
        let clock = Instant::now();
        let gradients = self.gradients(&objective.total, prediction)?;
        timing.backward = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let rate = learning_rate(&self.config.optimizer, self.step, self.config.training.steps);
        let update = self.optimizer.update(&self.parameters, &gradients, rate)?;
        if !update.gradient_norm.is_finite() {
            return Err(TrainError::NonFinite {
                step: self.step + 1,
                term: "gradient norm".into(),
                value: update.gradient_norm,
                last_checkpoint,
            });
        }
        self.ema.update(&self.parameters, self.config.optimizer.ema_decay, self.step)?;
        timing.update = clock.elapsed().as_secs_f64();
        self.step += 1;
        Ok(StepReport {
            step: self.step,
            loss,
            terms,
            learning_rate: update.learning_rate,
            gradient_norm: update.gradient_norm,
            seconds: started.elapsed().as_secs_f64(),
            timing,
        })
    }

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
    /// The model must have this configuration's network and text encoder and the dataset's
    /// vocabulary; the training settings (losses, optimiser, batch) are this run's. The
    /// normalisation statistics are the dataset's, as for every run: fine-tuning on the model's
    /// own dataset keeps them as they were.
    pub fn initialise_from(&mut self, path: &Path) -> Result<()> {
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
        for (section, model, run) in [
            (
                "[model]",
                serde_json::to_value(&stored.model),
                serde_json::to_value(&self.config.model),
            ),
            ("[text]", serde_json::to_value(&stored.text), serde_json::to_value(&self.config.text)),
        ] {
            let (model, run) =
                (model.expect("a config serialises"), run.expect("a config serialises"));
            let differing: Vec<String> = run
                .as_object()
                .into_iter()
                .flatten()
                .filter(|(key, value)| model.get(key.as_str()) != Some(value))
                .map(|(key, value)| {
                    let theirs =
                        model.get(key.as_str()).map_or("nothing".into(), |v| v.to_string());
                    format!("{key} = {theirs} (this run: {value})")
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
        self.check_vocabulary(&metadata, path)?;
        for (k, p) in self.parameters.iter().enumerate() {
            let name = format!("ema.{}", p.name);
            let t = tensors
                .get(&name)
                .ok_or_else(|| TrainError::checkpoint(path, &name, "a tensor", "nothing"))?;
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
        Ok(())
    }

    /// Checks that the built-in encoder's vocabulary in a file's metadata is this dataset's.
    fn check_vocabulary(&self, metadata: &BTreeMap<String, String>, path: &Path) -> Result<()> {
        if let TextModule::Builtin { encoder, .. } = &self.text {
            let words: Option<Vec<String>> = metadata
                .get(VOCABULARY_KEY)
                .map(|w| serde_json::from_str(w))
                .transpose()
                .map_err(|e| TrainError::checkpoint(path, VOCABULARY_KEY, "a word list", e))?;
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

/// Where a run's weights start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunStart<'a> {
    /// A new run, its parameters from the configuration's seed.
    Fresh,
    /// Continue the run in the output directory from its checkpoint, bit for bit.
    Resume,
    /// A new run from the EMA weights of this packed model or checkpoint
    /// ([`Trainer::initialise_from`]).
    InitialisedFrom(&'a Path),
}

/// How [`train`] runs.
#[derive(Debug, Clone, Copy)]
pub struct TrainOptions<'a> {
    /// Where the weights start.
    pub start: RunStart<'a>,
    /// Set (for example by Ctrl-C) to stop after the current step with a checkpoint.
    pub stop: &'a AtomicBool,
    /// Keep a numbered snapshot every this many steps ([`SNAPSHOTS_DIR`]); a run-time choice,
    /// not part of the configuration, so a resumed run may change it.
    pub snapshot_every: Option<usize>,
    /// Where the model trains; a run-time choice, not part of the configuration or the
    /// checkpoint, so a run may be resumed on another device.
    pub device: &'a Device,
}

/// Folder of a run directory that holds its snapshots: `step-000300/` and so on, each a run
/// directory of its own (configuration, dataset manifest, statistics, checkpoint) that
/// `dex2hoi sample` and `dex2hoi evaluate` take as `--run`.
pub const SNAPSHOTS_DIR: &str = "snapshots";

/// The snapshot directory of a step.
pub fn snapshot_dir(run_dir: &Path, step: usize) -> PathBuf {
    run_dir.join(SNAPSHOTS_DIR).join(format!("step-{step:06}"))
}

/// Copies the run's checkpoint and what loading it needs into the step's snapshot directory,
/// whole or not at all (written beside it, then renamed).
fn write_snapshot(files: &RunFiles, run_dir: &Path, step: usize) -> Result<()> {
    let target = snapshot_dir(run_dir, step);
    let partial = target.with_extension("partial");
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(&partial)
        .map_err(TrainError::io(&partial, "creating a snapshot directory"))?;
    let copies = RunFiles::new(&partial);
    for (from, to) in [
        (&files.config, &copies.config),
        (&files.dataset, &copies.dataset),
        (&files.stats, &copies.stats),
        (&files.checkpoint, &copies.checkpoint),
    ] {
        std::fs::copy(from, to).map_err(TrainError::io(from, "copying into a snapshot"))?;
    }
    let _ = std::fs::remove_dir_all(&target);
    std::fs::rename(&partial, &target)
        .map_err(TrainError::io(&target, "moving a snapshot into place"))?;
    Ok(())
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainSummary {
    /// Steps done in all.
    pub steps: usize,
    /// Training steps of the model the run started from (0 for a run from the seed).
    pub steps_before: usize,
    /// Whether it stopped early on request.
    pub interrupted: bool,
    /// The last step's report, if a step ran.
    pub last: Option<StepReport>,
    /// The run directory.
    pub run_dir: PathBuf,
}

/// Trains into a run directory: writes the resolved `config.toml`, the dataset manifest and
/// statistics, then steps, logging to `metrics.jsonl`, checkpointing every
/// `checkpoint_every` steps, on a stop request and at the end (each time with the loss-curve
/// PNG), and with `snapshot_every`, keeping a numbered snapshot of those steps. A new run
/// (fresh or initialised from a model) refuses a directory that already holds a checkpoint;
/// [`RunStart::Resume`] continues one and refuses a different configuration (apart from
/// `training.steps`).
pub fn train(
    run_dir: &Path,
    config: TrainConfig,
    dataset: &Dataset,
    dataset_path: &Path,
    options: TrainOptions<'_>,
    on_step: &mut dyn FnMut(&StepReport, usize),
) -> Result<TrainSummary> {
    if options.snapshot_every == Some(0) {
        return Err(TrainError::config(
            "training options",
            "snapshot_every",
            "a positive number of steps",
            0,
        ));
    }
    let files = RunFiles::new(run_dir);
    std::fs::create_dir_all(run_dir)
        .map_err(TrainError::io(run_dir, "creating the run directory"))?;
    let exists = files.checkpoint.exists();
    let resume = options.start == RunStart::Resume;
    if exists && !resume {
        return Err(TrainError::checkpoint(
            &files.checkpoint,
            "run directory",
            "a new run directory (or --resume to continue this run)",
            "an existing checkpoint",
        ));
    }
    if resume && !exists {
        return Err(TrainError::checkpoint(
            &files.checkpoint,
            "resume",
            "a checkpoint to continue from",
            "no such file",
        ));
    }
    let mut trainer = Trainer::new(config, dataset, dataset_path, options.device)?;
    let mut last_checkpoint = 0;
    match options.start {
        RunStart::Resume => {
            trainer.restore(&files.checkpoint)?;
            last_checkpoint = trainer.steps_done();
            truncate_metrics(&files, last_checkpoint)?;
        }
        RunStart::Fresh => {
            let _ = std::fs::remove_file(&files.metrics);
        }
        RunStart::InitialisedFrom(model) => {
            trainer.initialise_from(model)?;
            let _ = std::fs::remove_file(&files.metrics);
        }
    }
    write_static(&files, trainer.config(), dataset)?;
    let total = trainer.config().training.steps;
    let (log_every, checkpoint_every) =
        (trainer.config().training.log_every, trainer.config().training.checkpoint_every);
    let mut last = None;
    let mut interrupted = false;
    let save = |trainer: &Trainer| -> Result<()> {
        trainer.save(&files.checkpoint)?;
        crate::plot::write_loss_curve(&files.loss_curve, &read_metrics(&files)?)
    };
    while trainer.steps_done() < total {
        if options.stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        let report = trainer.step(last_checkpoint)?;
        if report.step == 1 || report.step % log_every == 0 || report.step == total {
            append_metrics(&files, &report)?;
        }
        on_step(&report, total);
        let snapshot = options.snapshot_every.is_some_and(|n| report.step % n == 0);
        if (report.step % checkpoint_every == 0 || snapshot) && report.step < total {
            save(&trainer)?;
            last_checkpoint = report.step;
        }
        if snapshot && report.step < total {
            write_snapshot(&files, run_dir, report.step)?;
        }
        last = Some(report);
    }
    save(&trainer)?;
    let steps = trainer.steps_done();
    if options.snapshot_every.is_some_and(|n| steps % n == 0) && steps == total {
        write_snapshot(&files, run_dir, steps)?;
    }
    Ok(TrainSummary {
        steps,
        steps_before: trainer.steps_before(),
        interrupted,
        last,
        run_dir: run_dir.to_path_buf(),
    })
}

/// Appends a line to a file (creating it).
pub(crate) fn append_line(path: &Path, line: &str) -> Result<()> {
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(TrainError::io(path, "opening for appending"))?;
    writeln!(file, "{line}").map_err(TrainError::io(path, "appending"))
}

/// Re-exported for the run files.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    Ok(write_atomically(path, bytes)?)
}
