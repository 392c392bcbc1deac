//! One training step: a batch drawn, its texts embedded, noised, the model's prediction (in
//! groups of windows on the CPU), the objective, the backward pass, AdamW and EMA.
//!
//! Every random draw of a step comes from a ChaCha8 stream seeded by the run's seed and the
//! step number (window choice, text choice and dropout, augmentation, timesteps, noise, the
//! windows noised along the model's own prediction and their steps, dropout masks, in that
//! order; a batch that trains in groups draws one seed per group there instead,
//! each group's masks drawn from its own seed), so the generator state of a checkpoint is its
//! step: a resumed run draws exactly what an uninterrupted one would.
//!
//! On a GPU two things differ, so that the GPU does not wait for the host. The noise is drawn
//! by the device's generator, seeded from the stream where the CPU draws it value by value (as
//! the dropout masks are). And the next step's batch is drawn on another host thread while this
//! step's backward pass and update are queued ([`Trainer::prefetch_batches`]): it comes from the
//! next step's own stream, first, so it is the batch that step would draw itself. Together they
//! took the batch's part of a `small` step on an H200 from 13 to 2 ms (docs/GPU.md).

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use dex2hoi_data::dataset::Dataset;
use dex2hoi_data::window::WindowConfig;
use dex2hoi_diffusion::{CosineSchedule, gaussian, guided, sample_timesteps};
use dex2hoi_model::text::{UNKNOWN, Vocabulary};
use dex2hoi_model::{Model, ModelInput, SeededVarMap};
use dex2hoi_optim::{AdamW, Ema, Parameter, learning_rate, parameters_of, step_rng};
use dex2hoi_sample::TextModule;

use crate::batch::{Batch, BatchOptions, TrainingSet};
use crate::config::TrainConfig;
use crate::error::{Result, TrainError};
use crate::loss::{LossContext, Term};

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
    pub(crate) config: TrainConfig,
    pub(crate) data: Arc<TrainingSet>,
    pub(crate) schedule: CosineSchedule,
    pub(crate) model: Model,
    pub(crate) text: TextModule,
    pub(crate) parameters: Vec<Parameter>,
    pub(crate) optimizer: AdamW,
    pub(crate) ema: Ema,
    pub(crate) loss: LossContext,
    pub(crate) step: usize,
    /// Training steps of the model the run started from ([`Trainer::initialise_from`]).
    pub(crate) steps_before: usize,
    pub(crate) device: Device,
    /// Whether [`Trainer::step`] draws the next step's batch beside its backward pass and
    /// update ([`Trainer::prefetch_batches`]).
    pub(crate) prefetch: bool,
    /// The next step's batch on the host, with the step's random stream after its draws.
    pub(crate) prefetched: Option<Prefetched>,
    /// Whether the noise is drawn on the host, value by value ([`Trainer::noise_on_host`]).
    pub(crate) host_noise: bool,
}

/// The batch of `step` from the step's own random stream, and the stream after its draws: what
/// the step draws itself, ahead of it on another thread, or for [`Trainer::objective_at`].
fn draw_batch(
    data: &TrainingSet,
    options: &BatchOptions,
    seed: u64,
    step: usize,
    device: &Device,
) -> Result<(Batch, ChaCha8Rng)> {
    let mut rng = step_rng(seed, step);
    let batch = data.batch(options, &mut rng, device)?;
    Ok((batch, rng))
}

/// A batch drawn ahead on the host (see the module documentation).
#[derive(Debug)]
pub(crate) struct Prefetched {
    step: usize,
    batch: Batch,
    rng: ChaCha8Rng,
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
        let data = TrainingSet::new(dataset, window)?
            .weighted_by_action(&config.training.action_weights, "config")?;
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
            data: Arc::new(data),
            schedule,
            model,
            text,
            parameters,
            optimizer,
            ema,
            loss,
            step: 0,
            steps_before: 0,
            prefetch: !device.is_cpu(),
            prefetched: None,
            host_noise: device.is_cpu(),
            device,
        })
    }

    /// Whether the windows' noise is drawn on the host, value by value from the step's stream,
    /// and uploaded (the CPU's way, and its only one), or by the device's generator seeded from
    /// the stream (the default on a GPU): the same run then trains on the same noise on either
    /// device, for comparing them.
    pub fn noise_on_host(&mut self, host: bool) {
        self.host_noise = host || self.device.is_cpu();
    }

    /// Whether each step draws the next step's batch on another host thread while its backward
    /// pass and update are queued: on by default on a GPU, where the host would otherwise draw
    /// it while the GPU waits; off on the CPU, whose cores the step's own work keeps busy. The
    /// batches are the same either way.
    pub fn prefetch_batches(&mut self, prefetch: bool) {
        self.prefetch = prefetch;
        if !prefetch {
            self.prefetched = None;
        }
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

    /// The text module (the built-in encoder's vocabulary among it).
    pub fn text(&self) -> &TextModule {
        &self.text
    }

    /// The configuration.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The trained parameters (checkpoint names).
    pub fn parameters(&self) -> &[Parameter] {
        &self.parameters
    }

    /// Embeds the batch's texts with word dropout (built-in encoder): the embedding, and the
    /// same with text dropout applied (the null condition, a zero row), which the model reads.
    fn encode_text(&self, texts: &[String], rng: &mut ChaCha8Rng) -> Result<(Tensor, Tensor)> {
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
        }
        .to_dtype(DType::F32)?;
        let keep = Tensor::from_vec(keep, (texts.len(), 1), &self.device)?;
        let kept = embedded.broadcast_mul(&keep)?;
        Ok((embedded, kept))
    }

    /// The objective of the batch of a step (no update): for tests and benchmarks. For a batch
    /// that trains in groups (`training.group_windows`) the total's graph ends at the joined
    /// prediction, not at the parameters.
    pub fn objective_at(&self, step: usize) -> Result<crate::loss::Objective> {
        let seed = self.config.training.seed;
        let (batch, mut rng) =
            draw_batch(&self.data, &self.batch_options(), seed, step, &self.device)?;
        Ok(self.objective(batch, &mut rng, &mut StepTiming::default())?.0)
    }

    fn batch_options(&self) -> BatchOptions {
        let t = &self.config.training;
        BatchOptions {
            size: t.batch_size,
            swap_probability: t.swap_probability,
            mirror_probability: t.mirror_probability,
            first_window_share: t.first_window_share,
            put_down_share: t.put_down_share,
        }
    }

    /// The batch of this step on the device and the step's stream after its draws: the one
    /// drawn ahead by the step before, or drawn now.
    fn step_batch(&mut self) -> Result<(Batch, ChaCha8Rng)> {
        match self.prefetched.take() {
            Some(ahead) if ahead.step == self.step => {
                Ok((ahead.batch.to_device(&self.device)?, ahead.rng))
            }
            _ => {
                let seed = self.config.training.seed;
                draw_batch(&self.data, &self.batch_options(), seed, self.step, &self.device)
            }
        }
    }

    /// The noise of a batch's windows: drawn value by value from the step's stream, or by the
    /// device's generator seeded from it ([`Trainer::noise_on_host`]).
    fn noise(&self, shape: &[usize], rng: &mut ChaCha8Rng) -> Result<Tensor> {
        if self.host_noise {
            return Ok(gaussian(shape, rng, DType::F32, &self.device)?);
        }
        self.device.set_seed(rng.random())?;
        Ok(Tensor::randn(0f32, 1f32, shape, &self.device)?)
    }

    fn objective(
        &self,
        batch: Batch,
        rng: &mut ChaCha8Rng,
        timing: &mut StepTiming,
    ) -> Result<(crate::loss::Objective, Prediction)> {
        let clock = Instant::now();
        let c = &self.config;
        let (embedding, text) = self.encode_text(&batch.texts, rng)?;
        let timesteps = sample_timesteps(&self.schedule, batch.size, rng);
        let (tp, tf) = (c.model.prefix_frames, c.model.predicted_frames);
        let x0 = batch.features.narrow(2, tp, tf)?;
        let noise = self.noise(x0.dims(), rng)?;
        let noisy = self.schedule.add_noise(&x0, &noise, &timesteps)?;
        let prefix = batch.features.narrow(2, 0, tp)?;
        let timestep_tensor = CosineSchedule::timestep_tensor(&timesteps, &self.device)?;
        let mut input = batch_input(&batch, &noisy, &prefix, &timestep_tensor, &text);
        timing.batch = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let (own_noisy, own_timestep_tensor);
        let timesteps = match self.along_own_prediction(&input, &timesteps, rng)? {
            Some((noisy, earlier)) => {
                own_noisy = noisy;
                own_timestep_tensor = CosineSchedule::timestep_tensor(&earlier, &self.device)?;
                input.noisy = &own_noisy;
                input.timesteps = &own_timestep_tensor;
                earlier
            }
            None => timesteps,
        };
        let prediction = self.predict(&input, batch.size, rng)?;
        timing.forward = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let mut objective = self.loss.objective(prediction.tensor(), &batch, &timesteps)?;
        for (term, value) in self.loss.text_terms(&embedding, &batch)? {
            objective.add(term, value, &c.loss)?;
        }
        timing.objective = clock.elapsed().as_secs_f64();
        Ok((objective, prediction))
    }

    /// The noisy input of the windows that `training.own_prediction_share` draws, and every
    /// window's step: for each drawn window at a step `t` above 0, the DDIM step from its noisy
    /// input along the model's own prediction of it (no dropout, no gradient; guided at
    /// `training.own_prediction_guidance` when set) to a step drawn uniformly below `t`. `None`, with no draw from `rng`, at a share of 0, and when no
    /// window was drawn.
    fn along_own_prediction(
        &self,
        input: &ModelInput<'_>,
        timesteps: &[usize],
        rng: &mut ChaCha8Rng,
    ) -> Result<Option<(Tensor, Vec<usize>)>> {
        let share = self.config.training.own_prediction_share;
        if share == 0.0 {
            return Ok(None);
        }
        let mut earlier = timesteps.to_vec();
        let mut rows = Vec::new();
        for (row, &t) in timesteps.iter().enumerate() {
            if rng.random_bool(share) && t > 0 {
                earlier[row] = rng.random_range(0..t);
                rows.push(row);
            }
        }
        if rows.is_empty() {
            return Ok(None);
        }
        let ids: Vec<u32> = rows.iter().map(|&row| row as u32).collect();
        let ids = Tensor::from_vec(ids, rows.len(), &self.device)?;
        let drawn =
            InputRows::of(input, &input.text.detach(), |t| t.contiguous()?.index_select(&ids, 0))?;
        let predicted = self.model.forward(&drawn.input(), None)?.detach();
        let predicted = match self.config.training.own_prediction_guidance {
            Some(scale) => {
                let null_text = drawn.text.zeros_like()?;
                let null = ModelInput { text: &null_text, ..drawn.input() };
                let unconditional = self.model.forward(&null, None)?.detach();
                guided(&predicted, &unconditional, scale)?
            }
            None => predicted,
        };
        let from: Vec<usize> = rows.iter().map(|&row| timesteps[row]).collect();
        let to: Vec<usize> = rows.iter().map(|&row| earlier[row]).collect();
        let stepped = self.schedule.step_towards(&drawn.noisy, &predicted, &from, &to)?;
        let mut drawn_rows = rows.iter().enumerate().peekable();
        let mut parts = Vec::with_capacity(timesteps.len());
        for row in 0..timesteps.len() {
            match drawn_rows.next_if(|(_, drawn)| **drawn == row) {
                Some((k, _)) => parts.push(stepped.narrow(0, k, 1)?),
                None => parts.push(input.noisy.narrow(0, row, 1)?),
            }
        }
        Ok(Some((Tensor::cat(&parts, 0)?, earlier)))
    }

    /// The model's prediction for a batch of `windows`: one forward pass, or on the CPU, with
    /// `training.group_windows` set and smaller than the batch, one per group of at most that
    /// many windows, the groups in parallel. Each group draws its dropout masks from its own
    /// generator, seeded by a draw of the step's stream in group order.
    ///
    /// Why groups: candle runs many of the backward pass's operations (gradient sums, copies,
    /// zero fills) on the calling thread, one after the other; in groups, each thread runs
    /// those of its own groups (the products are still split over the pool's threads).
    /// On 2 threads (`cargo xtask bench train`, `small`, batch 32) one group of 16 windows on
    /// each thread takes about three quarters of the time of the whole batch on both.
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
                let group = InputRows::of(input, text.as_tensor(), |t| t.narrow(0, start, len))?;
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                Ok(model.forward(&group.input(), Some(&mut rng))?)
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
    /// encoder's from the groups' summed gradient of the embedding. The objective's own
    /// gradients of the parameters (the text term's, which reads the embedding, not the
    /// prediction) start the sum.
    fn gradients(&self, total: &Tensor, prediction: Prediction) -> Result<GradStore> {
        let (whole, groups, (text, text_leaf)) = match prediction {
            Prediction::Whole(_) => return Ok(total.backward()?),
            Prediction::Grouped { whole, groups, text } => (whole, groups, text),
        };
        let mut of_objective = total.backward()?;
        let upstream = match of_objective.remove(whole.as_tensor()) {
            Some(gradient) => gradient.detach(),
            None => whole.as_tensor().zeros_like()?,
        };
        let mut merged = of_objective;
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
                merged = self.add_gradients(merged, &store)?;
            }
        }
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
        let mut timing = StepTiming::default();
        let clock = Instant::now();
        let (batch, mut rng) = self.step_batch()?;
        let drawn = clock.elapsed().as_secs_f64();
        let (objective, prediction) = self.objective(batch, &mut rng, &mut timing)?;
        timing.batch += drawn;
        // The terms and the total in one transfer: on a GPU each read waits for the device.
        let scalars: Vec<Tensor> = objective
            .terms
            .iter()
            .map(|(_, value)| value)
            .chain([&objective.total])
            .map(|value| value.to_dtype(DType::F32))
            .collect::<candle_core::Result<_>>()?;
        let values: Vec<f32> = Tensor::stack(&scalars, 0)?.to_vec1()?;
        let loss = f64::from(values[objective.terms.len()]);
        let mut terms = Vec::with_capacity(objective.terms.len());
        for ((term, _), &value) in objective.terms.iter().zip(&values) {
            let value = f64::from(value);
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
        let ahead = self.prefetch.then(|| {
            let (data, options) = (Arc::clone(&self.data), self.batch_options());
            let (seed, step) = (self.config.training.seed, self.step + 1);
            std::thread::spawn(move || -> Result<Prefetched> {
                let (batch, rng) = draw_batch(&data, &options, seed, step, &Device::Cpu)?;
                Ok(Prefetched { step, batch, rng })
            })
        });
        let clock = Instant::now();
        let update = self.gradients(&objective.total, prediction).and_then(|gradients| {
            timing.backward = clock.elapsed().as_secs_f64();
            let rate = learning_rate(&self.config.optimizer, self.step, self.config.training.steps);
            let ema = (self.config.optimizer.ema_decay, self.step);
            Ok(self.optimizer.update_with_average(
                &mut self.ema,
                &self.parameters,
                &gradients,
                rate,
                ema,
            )?)
        });
        // A batch that failed to draw is drawn again by the next step, which reports the error.
        self.prefetched = ahead.and_then(|thread| match thread.join() {
            Ok(drawn) => drawn.ok(),
            Err(panic) => std::panic::resume_unwind(panic),
        });
        let update = update?;
        if !update.gradient_norm.is_finite() {
            return Err(TrainError::NonFinite {
                step: self.step + 1,
                term: "gradient norm".into(),
                value: update.gradient_norm,
                last_checkpoint,
            });
        }
        timing.update = clock.elapsed().as_secs_f64() - timing.backward;
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
}

/// Some rows of every tensor of a model input, owned: the groups of a grouped prediction, the
/// windows noised along the model's own prediction.
struct InputRows {
    noisy: Tensor,
    prefix: Tensor,
    timesteps: Tensor,
    text: Tensor,
    bps: Tensor,
    presence: Tensor,
    frame_mask: Option<Tensor>,
    elapsed: Option<Tensor>,
    object_start: Option<Tensor>,
    settled: Option<Tensor>,
    reach: Option<Tensor>,
}

impl InputRows {
    /// The rows `select` takes from each tensor of `input`, the text embedding's from `text`
    /// (the caller's leaf or detached copy of it).
    fn of(
        input: &ModelInput<'_>,
        text: &Tensor,
        select: impl Fn(&Tensor) -> candle_core::Result<Tensor>,
    ) -> Result<Self> {
        let select_some = |t: Option<&Tensor>| t.map(&select).transpose();
        Ok(Self {
            noisy: select(input.noisy)?,
            prefix: select(input.prefix)?,
            timesteps: select(input.timesteps)?,
            text: select(text)?,
            bps: select(input.bps)?,
            presence: select(input.presence)?,
            frame_mask: select_some(input.frame_mask)?,
            elapsed: select_some(input.elapsed)?,
            object_start: select_some(input.object_start)?,
            settled: select_some(input.settled)?,
            reach: select_some(input.reach)?,
        })
    }

    fn input(&self) -> ModelInput<'_> {
        ModelInput {
            noisy: &self.noisy,
            prefix: &self.prefix,
            timesteps: &self.timesteps,
            text: &self.text,
            bps: &self.bps,
            presence: &self.presence,
            frame_mask: self.frame_mask.as_ref(),
            elapsed: self.elapsed.as_ref(),
            object_start: self.object_start.as_ref(),
            settled: self.settled.as_ref(),
            reach: self.reach.as_ref(),
        }
    }
}

/// The model's input for a batch's windows: the noisy predicted frames, the clean prefix, the
/// timesteps and the text embedding given, the rest of the condition from the batch.
fn batch_input<'a>(
    batch: &'a Batch,
    noisy: &'a Tensor,
    prefix: &'a Tensor,
    timesteps: &'a Tensor,
    text: &'a Tensor,
) -> ModelInput<'a> {
    ModelInput {
        noisy,
        prefix,
        timesteps,
        text,
        bps: &batch.bps,
        presence: &batch.presence,
        frame_mask: Some(&batch.frame_mask),
        elapsed: Some(&batch.elapsed),
        object_start: Some(&batch.object_start),
        settled: Some(&batch.settled),
        reach: Some(&batch.reach),
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use dex2hoi_diffusion::{CosineSchedule, gaussian};
    use dex2hoi_model::ModelInput;

    use super::{Trainer, batch_input};
    use crate::batch::{Batch, BatchOptions};
    use crate::config::TrainConfig;

    fn trainer(share: f64) -> Trainer {
        trainer_with(|config| config.training.own_prediction_share = share)
    }

    /// A trainer of the `tiny` preset, as `change` leaves it, on a small procedural dataset.
    fn trainer_with(change: impl FnOnce(&mut TrainConfig)) -> Trainer {
        let data =
            dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).expect("a procedural dataset");
        let mut config = TrainConfig::preset("tiny").unwrap();
        change(&mut config);
        Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).unwrap()
    }

    /// The model's input for a batch of six windows at steps 0 to 999, with the data's noisy
    /// window, and the generator after drawing it.
    fn noisy_input(trainer: &Trainer) -> (Batch, Tensor, Tensor, [usize; 6], ChaCha8Rng) {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let options = BatchOptions {
            size: 6,
            swap_probability: 0.5,
            mirror_probability: 0.5,
            first_window_share: 0.0,
            put_down_share: 0.0,
        };
        let batch = trainer.data.batch(&options, &mut rng, &Device::Cpu).unwrap();
        let (tp, tf) = (trainer.config.model.prefix_frames, trainer.config.model.predicted_frames);
        let x0 = batch.features.narrow(2, tp, tf).unwrap();
        let noise = gaussian(x0.dims(), &mut rng, candle_core::DType::F32, &Device::Cpu).unwrap();
        let timesteps = [0, 1, 250, 600, 900, 999];
        let noisy = trainer.schedule.add_noise(&x0, &noise, &timesteps).unwrap();
        let prefix = batch.features.narrow(2, 0, tp).unwrap();
        (batch, noisy, prefix, timesteps, rng)
    }

    fn largest(t: Tensor) -> f32 {
        t.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// The windows the share draws are noised along the model's own prediction (the DDIM step
    /// from the data's noisy window to an earlier step), the others keep the data's noisy
    /// window and step; a window at step 0 has no earlier step; a share of 0 changes nothing
    /// and draws nothing; a share of a half draws about half the windows.
    #[test]
    fn windows_noised_along_the_models_own_prediction() {
        let trainer = trainer(1.0);
        let (batch, noisy, prefix, timesteps, mut rng) = noisy_input(&trainer);
        let steps = CosineSchedule::timestep_tensor(&timesteps, &Device::Cpu).unwrap();
        let (text, _) = trainer.encode_text(&batch.texts, &mut rng).unwrap();
        let input = batch_input(&batch, &noisy, &prefix, &steps, &text);
        let (stepped, earlier) =
            trainer.along_own_prediction(&input, &timesteps, &mut rng).unwrap().unwrap();
        assert_eq!(earlier[0], 0);
        assert!(earlier.iter().zip(&timesteps).skip(1).all(|(e, t)| e < t), "{earlier:?}");
        let predicted = trainer.model.forward(&input, None).unwrap();
        let expected =
            trainer.schedule.step_towards(&noisy, &predicted, &timesteps, &earlier).unwrap();
        let scale = largest(expected.clone());
        let error = largest((&stepped - &expected).unwrap());
        assert!(error <= 1e-4 * scale, "{error} against values up to {scale}");
        let moved = largest((&stepped - &noisy).unwrap().narrow(0, 1, 5).unwrap());
        assert!(moved > 1e-2);
        let first = (&stepped - &noisy).unwrap().narrow(0, 0, 1).unwrap();
        assert_eq!(largest(first), 0.0);

        let off = self::trainer(0.0);
        let mut draws = rng.clone();
        assert!(off.along_own_prediction(&input, &timesteps, &mut draws).unwrap().is_none());
        assert_eq!(draws.random::<u64>(), rng.random::<u64>());

        let half = self::trainer(0.5);
        let all = [500; 6];
        let drawn: usize = (0..20)
            .map(|_| match half.along_own_prediction(&input, &all, &mut rng).unwrap() {
                Some((_, earlier)) => earlier.iter().filter(|&&t| t < 500).count(),
                None => 0,
            })
            .sum();
        assert!((36..=84).contains(&drawn), "{drawn} of 120 windows drawn");
    }

    /// With `own_prediction_guidance` the windows step along the guided prediction, the null
    /// one made with the text embedding zeroed, as the sampler guides; at scale 1 that is the
    /// conditional prediction. The scale is written to the configuration only when set, and
    /// refused when not finite or with no windows to guide.
    #[test]
    fn own_prediction_guided_as_the_sampler_guides() {
        let mut trainer = trainer_with(|config| {
            config.training.own_prediction_share = 1.0;
            config.training.own_prediction_guidance = Some(2.0);
            config.optimizer.learning_rate = 1e-2;
            config.optimizer.warmup_steps = 0;
        });
        // The text's path starts at zero: a few large steps give the text a say.
        for _ in 0..3 {
            trainer.step(0).unwrap();
        }
        let (batch, noisy, prefix, timesteps, mut rng) = noisy_input(&trainer);
        let steps = CosineSchedule::timestep_tensor(&timesteps, &Device::Cpu).unwrap();
        let (text, _) = trainer.encode_text(&batch.texts, &mut rng).unwrap();
        let input = batch_input(&batch, &noisy, &prefix, &steps, &text);
        let mut draws = rng.clone();
        let (stepped, earlier) =
            trainer.along_own_prediction(&input, &timesteps, &mut draws).unwrap().unwrap();
        let conditional = trainer.model.forward(&input, None).unwrap();
        let null_text = text.zeros_like().unwrap();
        let null = trainer.model.forward(&ModelInput { text: &null_text, ..input }, None).unwrap();
        let predicted = (&null + ((&conditional - &null).unwrap() * 2.0).unwrap()).unwrap();
        let expected =
            trainer.schedule.step_towards(&noisy, &predicted, &timesteps, &earlier).unwrap();
        let scale = largest(expected.clone());
        let error = largest((&stepped - &expected).unwrap());
        assert!(error <= 1e-4 * scale, "{error} against values up to {scale}");
        let along_conditional =
            trainer.schedule.step_towards(&noisy, &conditional, &timesteps, &earlier).unwrap();
        let guidance_moved = largest((&stepped - &along_conditional).unwrap());
        assert!(guidance_moved > 1e-3 * scale, "guidance moved the windows by {guidance_moved}");

        let written = trainer.config.to_toml().unwrap();
        assert!(written.contains("own_prediction_guidance = 2.0"), "{written}");
        let mut along = |guidance: Option<f64>| {
            trainer.config.training.own_prediction_guidance = guidance;
            let mut draws = rng.clone();
            trainer.along_own_prediction(&input, &timesteps, &mut draws).unwrap().unwrap().0
        };
        let one = along(Some(1.0));
        let plain = along(None);
        assert!(largest((&plain - &one).unwrap()) <= 1e-5 * scale);
        assert!(!trainer.config.to_toml().unwrap().contains("own_prediction_guidance = "));
        for (share, guidance, expected) in
            [(0.0, 2.0, "own_prediction_share is 0"), (0.5, f64::NAN, "a finite scale")]
        {
            let mut config = TrainConfig::preset("tiny").unwrap();
            config.training.own_prediction_share = share;
            config.training.own_prediction_guidance = Some(guidance);
            let error = config.validate("guided.toml").unwrap_err().to_string();
            assert!(error.contains("training.own_prediction_guidance"), "{error}");
            assert!(error.contains(expected), "{error}");
        }
    }

    /// Batches drawn ahead on another thread are the ones each step would draw itself: three
    /// steps with and without end with the same weights, bit for bit; a trainer that stops
    /// drawing ahead drops what it drew.
    #[test]
    fn batches_drawn_ahead_train_as_the_steps_own() {
        let weights = |prefetch: bool| -> Vec<Vec<f32>> {
            let mut trainer = trainer(0.5);
            trainer.prefetch_batches(prefetch);
            for _ in 0..3 {
                trainer.step(0).unwrap();
                assert_eq!(
                    trainer.prefetched.as_ref().map(|p| p.step),
                    prefetch.then_some(trainer.step)
                );
            }
            trainer
                .parameters
                .iter()
                .map(|p| p.var.flatten_all().unwrap().to_vec1().unwrap())
                .collect()
        };
        assert!(!trainer(0.0).prefetch, "the CPU trains without drawing ahead by default");
        assert_eq!(weights(true), weights(false));
        let mut trainer = trainer(0.0);
        trainer.prefetch_batches(true);
        trainer.step(0).unwrap();
        assert!(trainer.prefetched.is_some());
        trainer.prefetch_batches(false);
        assert!(trainer.prefetched.is_none());
    }
}
