//! Training configuration: one TOML file with the model, the text encoder, the loss weights
//! (paper Eq. 12), the optimiser and the loop. The presets live in `configs/*.toml` at the
//! repository root (`tiny` for tests, `demo`, `small`, `paper`) and are compiled in.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use dex2hoi_data::dataset::{Manifest, Split};
use dex2hoi_model::ModelConfig;
use dex2hoi_optim::OptimizerConfig;
use dex2hoi_repr::SkeletonKind;
use dex2hoi_sample::{RunConfig, TextConfig};

use crate::error::{Result, TrainError};

/// Everything a training run is configured by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// The networks.
    pub model: ModelConfig,
    /// The text encoder.
    #[serde(default)]
    pub text: TextConfig,
    /// The objective.
    #[serde(default)]
    pub loss: LossConfig,
    /// The optimiser and its schedule.
    #[serde(default)]
    pub optimizer: OptimizerConfig,
    /// The loop.
    pub training: LoopConfig,
}

/// Weights and options of the objective (paper Sec. 3.3, Eq. 8-12). Geometric terms are
/// measured in centimetres, so that a weight of 1 makes a 1 cm error cost about as much as
/// one standard deviation of a feature in `L_diff`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossConfig {
    /// `L_diff`: masked MSE on x0 over the predicted frames (default 1).
    pub diffusion: f64,
    /// `L_vel`, feature part: MSE of frame-to-frame differences of the features (default 1).
    pub feature_velocity: f64,
    /// `L_vel`, joint part: MSE of FK joint velocities in cm per frame (default 1).
    pub joint_velocity: f64,
    /// Foot skating: predicted velocity of feet in ground-truth contact, cm per frame
    /// (default 1).
    pub foot_contact: f64,
    /// Penetration: mean depth in cm of predicted joints inside the predicted-pose objects
    /// (default 10: the term is a mean over all joints, most of them far from any object, so at
    /// weight 1 it hardly acts; docs/results/penetration.md measures 1, 10 and 50).
    pub penetration: f64,
    /// `lambda_w` of `L_mix` (Eq. 8, default 1).
    pub mixture: f64,
    /// `lambda_t` of `L_trans` (Eq. 9, cm², default 0.01: about one over the variance of object positions, ~10 cm).
    pub translation: f64,
    /// `lambda_o` of `L_off` (Eq. 10, cm², default 0.01, likewise).
    pub offset: f64,
    /// Beyond the paper: the weight of the global branch `p^G` against the object's position
    /// on every frame (cm²), `L_off`'s counterpart for the third branch. Default 0, the
    /// paper's objective, where `p^G` is supervised only by `L_diff` while a hand holds the
    /// object (`L_trans` reaches it through a mixture weight near zero then), so it drifts
    /// and the object drops to the drifted height when the hand lets go
    /// (`docs/results/shipped-model.md`, "Long generations").
    pub global: f64,
    /// Beyond the paper: the weight of the error (cm²) of where each object set down within
    /// the window's predicted frames ([`crate::batch::Batch::put_down`]) ends, the decoded
    /// position on the window's last frame against the data's, at every diffusion step.
    /// Default 0, the paper's objective (and then left out of a written configuration).
    ///
    /// Why: where a put-down ends is decided at the noisiest steps, beyond
    /// `geometric_max_timestep`, where `L_trans` does not reach, and `L_trans` spreads its
    /// weight over every frame. From the data's own context one window before an inspected
    /// object is put back, the model trained without this term predicts from step 999 an end
    /// a median 9 cm from the object's place (2 cm from step 700), and its samples miss by
    /// 11-13 cm, on training sequences as on test ones (`docs/results/long-generations.md`, "Where
    /// a put-down ends: a term for it").
    #[serde(skip_serializing_if = "is_zero")]
    pub put_down: f64,
    /// `lambda_p` of `L_dist` (Eq. 11, default 1).
    pub distance: f64,
    /// Beyond the paper, for the built-in text encoder only: the weight of a logistic loss
    /// that reads the first two channels of each text's embedding (scaled) as logits of "the
    /// left hand holds an object in this sequence" and "the right hand does", against the
    /// data's hand contacts ([`crate::batch::Batch::hands`]; [`crate::LossContext::text_terms`]).
    /// Default 0, the paper's objective.
    ///
    /// Why: a denoiser that can guess the hand from where the object stands passes no
    /// gradient to the words that name the hand, and an encoder that does not tell the hands
    /// apart gives the denoiser nothing to read, so neither starts; this term makes the
    /// encoder tell them apart (`docs/results/long-generations.md`, "The hand from the words:
    /// a text term").
    pub text_hands: f64,
    /// Beyond the paper, for the built-in text encoder only: the weight of the same logistic
    /// loss on the embedding's third and fourth channels, read as logits of "an object ends
    /// to the person's left of where it stood" and "one ends to the right", against the
    /// data's object motion ([`crate::batch::Batch::sides`];
    /// [`crate::LossContext::text_terms`]). Default 0, the paper's objective.
    ///
    /// Why: with `text_hands` alone the encoder brought the sides closer together as it told
    /// the hands apart, and objects ended on the side asked for in about half the
    /// generations; the term alone did not change that (`docs/results/long-generations.md`,
    /// "The side from the words: a text term for the side (not shipped)").
    pub text_sides: f64,
    /// Huber threshold `delta` of `L_dist` in cm (default 1).
    pub huber_delta_cm: f64,
    /// Approach radius `d_min` of `L_dist` in metres (default 0.10, the paper's).
    pub approach_radius: f64,
    /// Whether the signed-distance terms (penetration, `L_dist`) reach the predicted object
    /// rotation (default true, as the paper's objective). Through it the model
    /// can lower both terms by turning the object instead of placing the hand: the 30140-step
    /// model's objects turned a median 6 degrees on the first generated frame even where the
    /// ground truth leaves them still, and its held objects tilted 15-25 degrees where the data
    /// carries them upright (`docs/results/shipped-model.md`, "Objects that turn"). False
    /// stops that gradient, so the rotation channels learn from `L_diff` and `L_vel` only; the
    /// terms still reach the joints and the object's position.
    pub contact_turns_objects: bool,
    /// Whether the signed-distance terms reach the object channels that place the object (its
    /// wrist offsets, global position and mixture logits; default true, as the paper's
    /// objective). False makes all the object's channels constants to those terms
    /// (its rotation too, whatever `contact_turns_objects` says); with the hand-relative
    /// representation its decoded position still follows the predicted wrists, so a held object
    /// moves with its hand and the terms have to move the fingers (with `global_only` the terms
    /// then reach no object channel at all). It does not cure the sinking that comes with
    /// `contact_turns_objects = false`: with it the objects sink more
    /// (`docs/results/shipped-model.md`, "Objects that turn").
    pub contact_moves_objects: bool,
    /// Whether the terms that read the objects against the predicted body (`L_trans` through
    /// the decoded positions, penetration, `L_dist`) reach the root's displacement (default
    /// true, as the paper's objective). Through it the model can bring a hand to an object by
    /// moving the whole body: the model of 73740 steps, trained on data whose root never
    /// moves, raised or lowered it by up to 2 cm on the first frame of every window, so that
    /// after ten seconds the person stood up to 7 cm above the floor. False makes the root a
    /// constant to those terms (they still reach every joint rotation), so that it learns from
    /// `L_diff`, `L_vel` and the foot term only.
    pub object_terms_move_root: bool,
    /// Whether `L_vel` (on features and on joints) also measures the step from the prefix's
    /// last frame to the first predicted frame (beyond the paper, whose velocity terms stay
    /// within the predicted frames; default false). The autoregressive sampler joins its
    /// windows there: the model of 73740 steps moved the body a mean 2-3 cm per joint from a
    /// window's last frame to the next one's first, against 0.05-0.35 cm between frames within
    /// a window.
    pub velocity_across_the_seam: bool,
    /// Geometric terms (through FK or the object decode) only for diffusion steps `t <=` this
    /// (default 700 of 1000, InterGen's); `None` applies them at every step.
    pub geometric_max_timestep: Option<usize>,
    /// Table 3 "w/o mixture supervision" when false: no `L_mix`, `L_trans`, `L_off` (nor the
    /// global branch's term).
    pub mixture_supervision: bool,
    /// Table 3 "w/o `L_dist`" when false.
    pub distance_loss: bool,
    /// Everything but `L_diff` off (the benchmark's "MSE only").
    pub mse_only: bool,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            diffusion: 1.0,
            feature_velocity: 1.0,
            joint_velocity: 1.0,
            foot_contact: 1.0,
            penetration: 10.0,
            mixture: 1.0,
            translation: 0.01,
            offset: 0.01,
            global: 0.0,
            put_down: 0.0,
            distance: 1.0,
            text_hands: 0.0,
            text_sides: 0.0,
            huber_delta_cm: 1.0,
            approach_radius: 0.10,
            contact_turns_objects: true,
            contact_moves_objects: true,
            object_terms_move_root: true,
            velocity_across_the_seam: false,
            geometric_max_timestep: Some(700),
            mixture_supervision: true,
            distance_loss: true,
            mse_only: false,
        }
    }
}

/// The loop: steps, batches, augmentation, logging and checkpoints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoopConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// Windows per batch.
    pub batch_size: usize,
    /// Seed of everything random: parameters, batches, noise, dropout.
    pub seed: u64,
    /// Frames between training-window starts (default 10).
    #[serde(default = "default_stride")]
    pub window_stride: usize,
    /// Diffusion steps `T` of the cosine schedule (default 1000).
    #[serde(default = "dex2hoi_sample::default_diffusion_steps")]
    pub diffusion_steps: usize,
    /// Probability of the null text condition, for classifier-free guidance (default 0.1).
    #[serde(default = "default_text_dropout")]
    pub text_dropout: f64,
    /// Probability that a word of the built-in encoder's input becomes `[UNK]` (default 0.1).
    #[serde(default = "default_word_dropout")]
    pub word_dropout: f64,
    /// Probability of swapping the two streams (default 0.5, InterGen's).
    #[serde(default = "default_half")]
    pub swap_probability: f64,
    /// Probability of mirroring left/right (default 0.5).
    #[serde(default = "default_half")]
    pub mirror_probability: f64,
    /// Share of a batch's windows drawn from the first windows of sequences (starting at frame
    /// 0) rather than uniformly from all windows (default 0: uniformly). A first window is where
    /// a generation from a standing start decides which hand reaches and where to: about one
    /// window in fourteen of the procedural data, too few for the words that only matter there
    /// (the hand, the side) to be learned from.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub first_window_share: f64,
    /// Share of the windows not drawn as first windows that are drawn from the windows that
    /// set an object down within their predicted frames ([`crate::batch::Batch::put_down`])
    /// rather than uniformly (default 0: uniformly). Beyond the paper; with the `put_down`
    /// term it says how often the objective sees where a put-down ends.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub put_down_share: f64,
    /// Share of a batch's windows whose noisy input comes from the model's own prediction
    /// rather than from the data alone (default 0: none). Beyond the paper. For such a window
    /// the model first predicts the clean window from the data's noisy one at the drawn step
    /// `t` (without dropout or gradient), and its input is the DDIM step from there along that
    /// prediction to a step `t'` drawn uniformly below `t`
    /// ([`dex2hoi_diffusion::CosineSchedule::step_towards`]); the target stays the data's
    /// window and the objective reads `t'`. Sampling reaches every step from the model's own
    /// earlier predictions, not from the data; this trains the model to pull such an input
    /// back to the data, where the data alone never shows it one (the put-down that drifts
    /// along the sampler's steps, docs/results/long-generations.md).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub own_prediction_share: f64,
    /// The classifier-free guidance scale of the prediction that the windows of
    /// `own_prediction_share` step along (default: none, the conditional prediction). With a
    /// scale `s` they step along `x0_null + s (x0_cond - x0_null)`
    /// ([`dex2hoi_diffusion::guided`]), the null prediction made from the same rows with the
    /// text embedding zeroed: the prediction the sampler steps along at guidance `s` (2.0 by
    /// default, [`dex2hoi_diffusion::DEFAULT_GUIDANCE`]), where the conditional one is not.
    /// Beyond the paper; one more forward pass of those windows. Needs a share above 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub own_prediction_guidance: Option<f64>,
    /// How often windows are drawn by the action label of their sequence (a task family of the
    /// procedural data, a GRAB intent): a window of a sequence whose label is listed is drawn
    /// with that weight, every other window with weight 1 (default: none listed, so uniformly).
    /// Every draw follows it: the first windows, the put-down windows and the rest. Beyond the
    /// paper; for a dataset whose actions are not learned alike, such as the procedural pour
    /// and swap (docs/results/long-generations.md). A label no training sequence has is an
    /// error, so that a misspelt one does not silently weigh nothing.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub action_weights: BTreeMap<String, f64>,
    /// Steps between log lines in `metrics.jsonl` (default 10).
    #[serde(default = "default_log_every")]
    pub log_every: usize,
    /// Steps between checkpoints (default 500).
    #[serde(default = "default_checkpoint_every")]
    pub checkpoint_every: usize,
    /// Most windows of a batch per group on the CPU (the presets: 8): the model's forward and
    /// backward passes run once per group of rows, the groups in parallel, each drawing its own
    /// dropout masks (see `Trainer::step`). A batch of at most this many windows is one group;
    /// absent, the whole batch is one group (so that runs configured without the option resume
    /// as they trained). A number of the configuration rather than of the
    /// machine, so that the thread count does not change a run's bits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group_windows: Option<usize>,
}

fn default_stride() -> usize {
    10
}
fn default_text_dropout() -> f64 {
    0.1
}
fn default_word_dropout() -> f64 {
    0.1
}
fn default_half() -> f64 {
    0.5
}
fn is_zero(value: &f64) -> bool {
    *value == 0.0
}
fn default_log_every() -> usize {
    10
}
fn default_checkpoint_every() -> usize {
    500
}

/// The presets of `configs/`, by name (compiled in once, by `dex2hoi-model`).
pub use dex2hoi_model::PRESETS;

impl TrainConfig {
    /// Parses TOML; `source_name` names the file in errors.
    pub fn from_toml(text: &str, source_name: &str) -> Result<Self> {
        let config: Self = toml::from_str(text).map_err(|e| {
            TrainError::config(source_name, "TOML", "a training configuration", e.message())
        })?;
        config.validate(source_name)?;
        Ok(config)
    }

    /// Reads and validates a TOML file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(TrainError::io(path, "reading"))?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// The training configuration stored in a packed model or a checkpoint (the configuration
    /// it was trained with).
    pub fn from_model_file(path: &Path) -> Result<Self> {
        let (_, metadata) =
            dex2hoi_model::checkpoint::read_tensors(path, &candle_core::Device::Cpu)?;
        Self::from_model_metadata(&metadata, path)
    }

    /// The training configuration in the metadata of a packed model or a checkpoint read from
    /// `path` (named in errors).
    pub fn from_model_metadata(metadata: &BTreeMap<String, String>, path: &Path) -> Result<Self> {
        let text = metadata.get(dex2hoi_sample::TRAIN_CONFIG_KEY).ok_or_else(|| {
            TrainError::checkpoint(
                path,
                dex2hoi_sample::TRAIN_CONFIG_KEY,
                "a packed model or a checkpoint (with its training configuration)",
                "nothing",
            )
        })?;
        Self::from_toml(text, &path.display().to_string())
    }

    /// A preset of `configs/` by name.
    pub fn preset(name: &str) -> Result<Self> {
        let (_, text) = PRESETS.iter().find(|(n, _)| *n == name).ok_or_else(|| {
            TrainError::config("preset", "name", "tiny, demo, small or paper", name)
        })?;
        Self::from_toml(text, &format!("configs/{name}.toml"))
    }

    /// The configuration as TOML.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string(self)
            .map_err(|e| TrainError::config("config", "TOML", "a serialisable configuration", e))
    }

    /// The part of the configuration that sampling reads back from the run directory.
    pub fn run_config(&self) -> RunConfig {
        RunConfig {
            model: self.model.clone(),
            text: self.text.clone(),
            diffusion_steps: self.training.diffusion_steps,
        }
    }

    /// Checks values and combinations before anything is built.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, expected: &str, got: &dyn std::fmt::Display| {
            Err(TrainError::config(source_name, field, expected, got))
        };
        self.model.validate().map_err(|e| {
            TrainError::config(source_name, "model", "a valid model configuration", e)
        })?;
        let t = &self.training;
        for (field, value) in [
            ("training.steps", t.steps),
            ("training.batch_size", t.batch_size),
            ("training.window_stride", t.window_stride),
            ("training.diffusion_steps", t.diffusion_steps),
            ("training.log_every", t.log_every),
            ("training.checkpoint_every", t.checkpoint_every),
            ("training.group_windows", t.group_windows.unwrap_or(1)),
        ] {
            if value == 0 {
                return bad(field, "a positive number", &value);
            }
        }
        for (field, p) in [
            ("training.text_dropout", t.text_dropout),
            ("training.word_dropout", t.word_dropout),
            ("training.swap_probability", t.swap_probability),
            ("training.mirror_probability", t.mirror_probability),
            ("training.first_window_share", t.first_window_share),
            ("training.put_down_share", t.put_down_share),
            ("training.own_prediction_share", t.own_prediction_share),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(field, "a probability in [0, 1]", &p);
            }
        }
        if let Some(scale) = t.own_prediction_guidance {
            if !scale.is_finite() {
                return bad("training.own_prediction_guidance", "a finite scale", &scale);
            }
            if t.own_prediction_share == 0.0 {
                return bad(
                    "training.own_prediction_guidance",
                    "no scale while training.own_prediction_share is 0 (it guides nothing)",
                    &scale,
                );
            }
        }
        for (action, &weight) in &t.action_weights {
            if !(weight >= 0.0 && weight.is_finite()) {
                return bad(
                    &format!("training.action_weights.{action}"),
                    "a non-negative weight",
                    &weight,
                );
            }
        }
        let o = &self.optimizer;
        if !(o.learning_rate.is_finite() && o.learning_rate > 0.0) {
            return bad("optimizer.learning_rate", "a positive number", &o.learning_rate);
        }
        for (field, beta) in [("optimizer.beta1", o.beta1), ("optimizer.beta2", o.beta2)] {
            if !(0.0..1.0).contains(&beta) {
                return bad(field, "a number in [0, 1)", &beta);
            }
        }
        if !(o.epsilon > 0.0 && o.epsilon.is_finite()) {
            return bad("optimizer.epsilon", "a positive number", &o.epsilon);
        }
        if !(o.weight_decay >= 0.0 && o.weight_decay.is_finite()) {
            return bad("optimizer.weight_decay", "a non-negative number", &o.weight_decay);
        }
        if !(0.0..=1.0).contains(&o.final_learning_rate_ratio) {
            return bad(
                "optimizer.final_learning_rate_ratio",
                "a number in [0, 1]",
                &o.final_learning_rate_ratio,
            );
        }
        if let Some(clip) = o.gradient_clip
            && !(clip > 0.0 && clip.is_finite())
        {
            return bad("optimizer.gradient_clip", "a positive number", &clip);
        }
        if !(0.0..1.0).contains(&o.ema_decay) {
            return bad("optimizer.ema_decay", "a number in [0, 1)", &o.ema_decay);
        }
        let l = &self.loss;
        for (field, w) in [
            ("loss.diffusion", l.diffusion),
            ("loss.feature_velocity", l.feature_velocity),
            ("loss.joint_velocity", l.joint_velocity),
            ("loss.foot_contact", l.foot_contact),
            ("loss.penetration", l.penetration),
            ("loss.mixture", l.mixture),
            ("loss.translation", l.translation),
            ("loss.offset", l.offset),
            ("loss.global", l.global),
            ("loss.put_down", l.put_down),
            ("loss.distance", l.distance),
            ("loss.text_hands", l.text_hands),
            ("loss.text_sides", l.text_sides),
        ] {
            if !(w >= 0.0 && w.is_finite()) {
                return bad(field, "a non-negative weight", &w);
            }
        }
        if !(l.huber_delta_cm > 0.0 && l.huber_delta_cm.is_finite()) {
            return bad("loss.huber_delta_cm", "a positive number", &l.huber_delta_cm);
        }
        if !(l.approach_radius > 0.0 && l.approach_radius.is_finite()) {
            return bad(
                "loss.approach_radius",
                "a positive distance in metres",
                &l.approach_radius,
            );
        }
        if let Some(limit) = l.geometric_max_timestep
            && limit >= t.diffusion_steps
        {
            return bad(
                "loss.geometric_max_timestep",
                &format!("a step below training.diffusion_steps = {}", t.diffusion_steps),
                &limit,
            );
        }
        match &self.text {
            TextConfig::Builtin { width, heads, max_tokens, .. } => {
                if *width == 0 || *heads == 0 || !width.is_multiple_of(*heads) || *max_tokens == 0 {
                    return bad(
                        "text",
                        "a width divisible by the heads and a positive max_tokens",
                        &format!("width {width}, heads {heads}, max_tokens {max_tokens}"),
                    );
                }
            }
            TextConfig::Bert { .. } | TextConfig::Clip { .. } => {
                for (field, weight) in
                    [("loss.text_hands", l.text_hands), ("loss.text_sides", l.text_sides)]
                {
                    if weight > 0.0 {
                        return bad(
                            field,
                            "0 with a frozen text encoder (the term trains the built-in one)",
                            &weight,
                        );
                    }
                }
            }
        }
        Ok(())
    }

    /// Refuses a dataset that does not fit: skeleton size, feature sizes, BPS size, a missing
    /// or empty training split.
    pub fn check_dataset(&self, manifest: &Manifest, path: &Path) -> Result<()> {
        let mismatch = |what: &str, expected: String, got: String| {
            Err(TrainError::Dataset { path: path.to_path_buf(), what: what.into(), expected, got })
        };
        let m = &self.model;
        if manifest.joints != m.joints {
            let preset = match SkeletonKind::from_name(&manifest.skeleton) {
                Ok(SkeletonKind::Mixamo65) => "; the `humoto` preset is for it",
                _ => "",
            };
            return mismatch(
                "joints",
                format!("{} (model.joints)", m.joints),
                format!("{} ({}{preset})", manifest.joints, manifest.skeleton),
            );
        }
        if manifest.stream_feature_size != m.stream_features() {
            return mismatch(
                "stream feature size",
                m.stream_features().to_string(),
                manifest.stream_feature_size.to_string(),
            );
        }
        if manifest.bps.points != m.bps_points {
            return mismatch(
                "BPS points",
                format!("{} (model.bps_points)", m.bps_points),
                manifest.bps.points.to_string(),
            );
        }
        let train = match manifest.splits.get(&Split::Train) {
            Some(s) if s.sequences > 0 => s,
            _ => {
                return mismatch(
                    "training split",
                    "at least one training sequence".into(),
                    "none".into(),
                );
            }
        };
        // Unlabelled sequences count under the empty label.
        let labelled = |action: &String| !action.is_empty() && train.actions.contains_key(action);
        if let Some(unknown) = self.training.action_weights.keys().find(|a| !labelled(a)) {
            let known: Vec<&str> =
                train.actions.keys().filter(|a| !a.is_empty()).map(String::as_str).collect();
            let known = if known.is_empty() { "none".into() } else { known.join(", ") };
            return mismatch(
                &format!("training.action_weights.{unknown}"),
                format!("an action label of the training split ({known})"),
                "a label no training sequence has".into(),
            );
        }
        Ok(())
    }
}
