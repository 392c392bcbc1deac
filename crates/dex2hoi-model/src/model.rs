//! The Dex2HOI networks (paper Sec. 3.2): the dual-stream denoiser `D_theta` (Eq. 5) with
//! InterGen-style blocks shared by both streams, and the Motion Fusion Network `D_h` (Eq. 7),
//! plus the ablation variants of Table 3 selected by [`ModelConfig`].
//!
//! The module tree: [`Model`] holds one `Layout` (dual or single stream), each a
//! `Conditioning`, a `Denoiser` (frame tokens, [`TransformerBlock`]s with AdaLN, the output
//! head) and, for the dual layout, a `Fusion` of the two bodies. Parameter names mirror it,
//! except that the denoiser's parameters sit at the root (`blocks.3.cross_attention.query`,
//! `head.weight`), as every checkpoint names them.

use candle_core::{D, DType, Tensor};
use candle_nn::{VarBuilder, init::Init};
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::{FeatureLayout, MAX_OBJECTS};
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::object_repr::{
    GLOBAL_POSITION_RANGE, LEFT_OFFSET_RANGE, MIXTURE_RANGE, RIGHT_OFFSET_RANGE, ROTATION_RANGE,
};

/// The parts of an object's representation the object start reads: its rotation and its world
/// position (the hand-relative parts say where the hands were, not where the object stood).
pub const OBJECT_START_PARTS: [std::ops::Range<usize>; 2] = [ROTATION_RANGE, GLOBAL_POSITION_RANGE];

/// Numbers the object start reads per object: 6 + 3.
pub const OBJECT_START_WIDTH: usize = ROTATION_RANGE.end - ROTATION_RANGE.start
    + GLOBAL_POSITION_RANGE.end
    - GLOBAL_POSITION_RANGE.start;

use crate::config::{
    BodyFusion, ModelConfig, ObjectRepresentation, ObjectStart, Prediction, StreamLayout,
};
use crate::error::{ModelError, Result};
use crate::layers::{Dense, Modulation, dense, timestep_embedding, zero_dense};
use crate::transformer::{BlockConfig, Norm, Other, TransformerBlock, TransformerEncoder};

pub(crate) mod inference;

/// `rows` split into `groups` runs as even as can be, in order: each run's first row and length
/// (the row groups of [`crate::InferenceModel::forward`] and of training on the CPU).
pub fn row_groups(rows: usize, groups: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..groups).map(move |g| {
        let (start, end) = (g * rows / groups, (g + 1) * rows / groups);
        (start, end - start)
    })
}

/// What the model reads for one batch.
#[derive(Debug, Clone, Copy)]
pub struct ModelInput<'a> {
    /// Noisy predicted frames of both streams, `[batch, 2, T_f, 6J + 3 + 18]`.
    pub noisy: &'a Tensor,
    /// Clean prefix frames of both streams, `[batch, 2, T_p, 6J + 3 + 18]`.
    pub prefix: &'a Tensor,
    /// Diffusion timesteps, `[batch]`.
    pub timesteps: &'a Tensor,
    /// Text embeddings, `[batch, text_embedding]` (zero rows are the null condition).
    pub text: &'a Tensor,
    /// Each object's BPS features, `[batch, 2, bps_points * 3]` (zeros for an empty slot).
    pub bps: &'a Tensor,
    /// Object presence flags, `[batch, 2]` (1 present, 0 empty).
    pub presence: &'a Tensor,
    /// Valid frames of the window (prefix then predicted), `[batch, T_p + T_f]`; `None` when
    /// every frame is real.
    pub frame_mask: Option<&'a Tensor>,
    /// Frames from the start of the prompt in force to the window's first prefix frame,
    /// `[batch]`: what the prompt clock reads (`ModelConfig::prompt_clock`; ignored without
    /// it, required with it). Clamped to [`CLOCK_FRAMES`].
    pub elapsed: Option<&'a Tensor>,
    /// Both streams' normalised rows at the first frame of the prompt in force, `[batch, 2,
    /// 6J + 3 + 18]`: where the object start reads each object's rotation and world position
    /// (`ModelConfig::object_start`), and the first prefix token with the start frame in the
    /// prefix (`ModelConfig::start_in_prefix`); ignored without either, required with one.
    pub object_start: Option<&'a Tensor>,
    /// Whether each object has been moved and set down again since the prompt in force began,
    /// as of the window's last prefix frame (`dex2hoi_data::settled`), 1 or 0, `[batch, 2]`:
    /// what the memory of set-down objects reads (`ModelConfig::settled_objects`; ignored
    /// without it, required with it).
    pub settled: Option<&'a Tensor>,
    /// Both streams' normalised rows at the frame each stream's object was reached
    /// (`dex2hoi_data::settled::reach_frames`: the last frame before it first moved since the
    /// prompt in force began, or the window's first prefix frame while that is earlier),
    /// `[batch, 2, 6J + 3 + 18]`: the first prefix token with the reach frame in the prefix
    /// (`ModelConfig::reach_in_prefix`; ignored without it, required with it).
    pub reach: Option<&'a Tensor>,
}

/// The prompt clock stops here (frames): twelve seconds at 20 fps, beyond the longest rest
/// that follows a task in the procedural data, so every reading it takes was trained on.
pub const CLOCK_FRAMES: f64 = 240.0;

/// What the condition reads of the prompt in force besides its words.
#[derive(Debug, Clone, Copy, Default)]
pub struct PromptState<'a> {
    /// See [`ModelInput::elapsed`].
    pub elapsed: Option<&'a Tensor>,
    /// See [`ModelInput::object_start`].
    pub object_start: Option<&'a Tensor>,
    /// See [`ModelInput::settled`].
    pub settled: Option<&'a Tensor>,
    /// See [`ModelInput::reach`].
    pub reach: Option<&'a Tensor>,
}

impl<'a> PromptState<'a> {
    fn of(input: &ModelInput<'a>) -> Self {
        Self {
            elapsed: input.elapsed,
            object_start: input.object_start,
            settled: input.settled,
            reach: input.reach,
        }
    }
}

/// What [`Conditioning::fixed_part`] reads of the prompt in force besides its words, each in
/// the shape the stream layout gives it.
struct PromptReadings<'a> {
    elapsed: Option<&'a Tensor>,
    start: Option<&'a Tensor>,
    settled: Option<&'a Tensor>,
}

/// Each object's placement in stream rows: its rotation and world position
/// ([`OBJECT_START_PARTS`]).
///
/// # Shapes
/// - `rows`: `[batch, 2, 6J + 3 + 18]`; returns `[batch, 2, OBJECT_START_WIDTH]`
fn placements(layout: FeatureLayout, rows: &Tensor, dtype: DType) -> Result<Tensor> {
    let object = layout.object_of(&rows.to_dtype(dtype)?)?;
    let parts = OBJECT_START_PARTS
        .into_iter()
        .map(|part| object.narrow(D::Minus1, part.start, part.len()))
        .collect::<candle_core::Result<Vec<_>>>()?;
    Ok(Tensor::cat(&parts, D::Minus1)?)
}

/// `Linear -> SiLU -> Linear`.
///
/// # Shapes
/// - `x`: `[..., input]`; returns `[..., output]`
fn two_layers((first, second): &(Dense, Dense), x: &Tensor) -> Result<Tensor> {
    second.forward(&first.forward(x)?.silu()?)
}

/// An input the configuration requires, or an error that names it and what it holds.
fn required<'a>(input: Option<&'a Tensor>, name: &str, holding: &str) -> Result<&'a Tensor> {
    input.ok_or_else(|| ModelError::shape(name, holding, &[]))
}

/// The condition embedding of each stream: timestep MLP + projected text + the stream's object
/// (BPS MLP and presence), the sum split in the part that changes with the timestep and the
/// part that does not (computed once per sample by the inference path).
#[derive(Debug, Clone)]
struct Conditioning {
    time_in: Dense,
    time_out: Dense,
    text: Dense,
    bps_in: Dense,
    bps_out: Dense,
    presence: Dense,
    /// The prompt clock's MLP (its output layer zero-initialised, so that a model that gains
    /// the clock starts as it was).
    clock: Option<(Dense, Dense)>,
    /// What the object start reads, and its MLP over this stream's object and the other's
    /// (its output layer zero-initialised, like the clock's).
    object_start: Option<(ObjectStart, (Dense, Dense))>,
    /// The memory of set-down objects' MLP over this stream's object's flag and the other's
    /// (its output layer zero-initialised, like the clock's).
    settled: Option<(Dense, Dense)>,
    layout: FeatureLayout,
    latent: usize,
}

impl Conditioning {
    fn new(cfg: &ModelConfig, bps_inputs: usize, vb: VarBuilder<'_>) -> Result<Self> {
        let l = cfg.latent;
        Ok(Self {
            time_in: dense(l, l, vb.pp("time_in"))?,
            time_out: dense(l, l, vb.pp("time_out"))?,
            text: dense(cfg.text_embedding, l, vb.pp("text"))?,
            bps_in: dense(bps_inputs, l, vb.pp("bps_in"))?,
            bps_out: dense(l, l, vb.pp("bps_out"))?,
            presence: dense(2, l, vb.pp("presence"))?,
            clock: if cfg.prompt_clock {
                Some((dense(l, l, vb.pp("clock_in"))?, zero_dense(l, l, vb.pp("clock_out"))?))
            } else {
                None
            },
            object_start: match cfg.object_start {
                ObjectStart::Off => None,
                reading => Some((
                    reading,
                    (
                        dense(2 * OBJECT_START_WIDTH, l, vb.pp("object_start_in"))?,
                        zero_dense(l, l, vb.pp("object_start_out"))?,
                    ),
                )),
            },
            settled: if cfg.settled_objects {
                Some((
                    dense(MAX_OBJECTS, l, vb.pp("settled_in"))?,
                    zero_dense(l, l, vb.pp("settled_out"))?,
                ))
            } else {
                None
            },
            layout: cfg.layout(),
            latent: l,
        })
    }

    /// The part that does not change over a sample's diffusion steps: projected text, object
    /// (BPS MLP), presence and, with the prompt clock, the elapsed frames, and with the object
    /// start, where the objects stood when the prompt began ([`Self::object_start`]), and with
    /// the memory of set-down objects, which of them have been moved and set down again.
    ///
    /// # Shapes
    /// - `text`: `[batch, E]`; `bps`: `[batch, bps_inputs]`; `presence`: `[batch, 2]`;
    ///   `prompt.elapsed`: `[batch]`; `prompt.start`: `[batch, 2 * OBJECT_START_WIDTH]` and
    ///   `prompt.settled`: `[batch, 2]` (this stream's object, then the other's, zero where
    ///   absent); returns `[batch, latent]`
    fn fixed_part(
        &self,
        text: &Tensor,
        bps: &Tensor,
        presence: &Tensor,
        prompt: PromptReadings<'_>,
    ) -> Result<Tensor> {
        let PromptReadings { elapsed, start, settled } = prompt;
        let object = self.bps_out.forward(&self.bps_in.forward(bps)?.silu()?)?;
        let mut fixed =
            ((self.text.forward(text)? + object)? + self.presence.forward(presence)?)?;
        if let Some(clock) = &self.clock {
            let elapsed =
                required(elapsed, "elapsed", "the frames since each prompt began (prompt clock)")?;
            let elapsed = elapsed.to_dtype(DType::F64)?.clamp(0.0, CLOCK_FRAMES)?;
            let device = self.time_in.weight.device();
            let embedded = timestep_embedding(&elapsed, self.latent, fixed.dtype(), device)?;
            fixed = (fixed + two_layers(clock, &embedded)?)?;
        }
        if let Some((_, mlp)) = &self.object_start {
            let start = required(start, "object_start", "each object's start (object start)")?;
            fixed = (fixed + two_layers(mlp, start)?)?;
        }
        if let Some(mlp) = &self.settled {
            let settled =
                required(settled, "settled", "which objects are set down again (settled objects)")?;
            let settled = settled.to_dtype(fixed.dtype())?;
            fixed = (fixed + two_layers(mlp, &settled)?)?;
        }
        Ok(fixed)
    }

    /// What the object start reads of each object: its placement at the prompt's first frame,
    /// or that less its placement at the window's last prefix frame; `None` when it is off.
    ///
    /// # Shapes
    /// - `rows`: `[batch, 2, D]` (see [`ModelInput::object_start`]); `prefix`: `[batch, 2,
    ///   T_p, D]`; returns `[batch, 2, OBJECT_START_WIDTH]`
    fn object_start(
        &self,
        rows: Option<&Tensor>,
        prefix: &Tensor,
        dtype: DType,
    ) -> Result<Option<Tensor>> {
        let Some((reading, _)) = self.object_start else { return Ok(None) };
        let rows = required(rows, "object_start", "the rows at each prompt's first frame")?;
        let start = placements(self.layout, rows, dtype)?;
        Ok(Some(match reading {
            ObjectStart::FromPrefix => {
                let last = prefix.narrow(2, prefix.dim(2)? - 1, 1)?.squeeze(2)?;
                (start - placements(self.layout, &last, dtype)?)?
            }
            _ => start,
        }))
    }

    /// The timestep MLP.
    ///
    /// # Shapes
    /// - `timesteps`: `[batch]`; returns `[batch, latent]`
    fn time(&self, timesteps: &Tensor, dtype: DType) -> Result<Tensor> {
        let (time_in, time_out) =
            (|x: &Tensor| self.time_in.forward(x), |x: &Tensor| self.time_out.forward(x));
        self.time_with(timesteps, dtype, time_in, time_out)
    }

    /// [`Self::time`] with its two linear layers given (the inference path's products).
    fn time_with(
        &self,
        timesteps: &Tensor,
        dtype: DType,
        time_in: impl Fn(&Tensor) -> Result<Tensor>,
        time_out: impl Fn(&Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let device = self.time_in.weight.device();
        let time = timestep_embedding(timesteps, self.latent, dtype, device)?;
        time_out(&time_in(&time)?.silu()?)
    }
}

/// The denoiser shared by both layouts: frame tokens (projection, positions, prefix/noisy
/// type), AdaLN blocks, a final AdaLN and a zero-initialised head, so that the model starts
/// predicting zeros.
#[derive(Debug, Clone)]
struct Denoiser {
    input: Dense,
    positions: Tensor,
    frame_types: Tensor,
    blocks: Vec<TransformerBlock>,
    final_modulation: Modulation,
    head: Dense,
    /// Per-channel input mask (zeros the hand-relative channels for `GlobalOnly`).
    channel_mask: Option<Tensor>,
    prefix_frames: usize,
    predicted_frames: usize,
}

/// A per-channel mask of a frame holding the body and `objects` objects: 1 everywhere but on
/// each object's hand-relative channels (the wrist offsets and the mixture logits), 0 there.
///
/// # Shapes
/// - returns `[6J + 3 + 18 objects]`
fn without_hand_relative_channels(cfg: &ModelConfig, objects: usize) -> Vec<f32> {
    let layout = cfg.layout();
    let mut mask = vec![1.0f32; layout.body_width() + objects * layout.object_width()];
    for k in 0..objects {
        // Object `k` of a frame sits `k` object widths after the first one.
        let shift = k * layout.object_width();
        for part in [LEFT_OFFSET_RANGE, RIGHT_OFFSET_RANGE, MIXTURE_RANGE] {
            let range = layout.object_part_range(part);
            mask[range.start + shift..range.end + shift].fill(0.0);
        }
    }
    mask
}

/// A stream row's mask (one object) that keeps the channels placing the body and the object in
/// the world: the root joint's rotation, the root displacement, the object's rotation and
/// world position (`Prediction::PrefixResidualPlacement`).
///
/// # Shapes
/// - returns `[6J + 3 + 18]`
fn placement_channels(cfg: &ModelConfig) -> Vec<f32> {
    let layout = cfg.layout();
    let mut mask = vec![0.0f32; layout.stream_width()];
    let placement = [
        layout.joint_rotation_range(0),
        layout.root_range(),
        layout.object_part_range(ROTATION_RANGE),
        layout.object_part_range(GLOBAL_POSITION_RANGE),
    ];
    for range in placement {
        mask[range].fill(1.0);
    }
    mask
}

/// A stream row's mask (one object) without the hand-relative channels and without the finger
/// joints' rotations (the hands' joints but the wrists, of the skeleton with `cfg.joints`
/// joints) (`Prediction::PrefixResidualCleanFingers`).
///
/// # Shapes
/// - returns `[6J + 3 + 18]`
fn without_hand_channels(cfg: &ModelConfig) -> Result<Vec<f32>> {
    let layout = cfg.layout();
    let mut mask = without_hand_relative_channels(cfg, 1);
    let skeleton = Skeleton::builtin(cfg.skeleton_kind()?);
    let groups = skeleton.groups();
    let wrists = [groups.left_wrist, groups.right_wrist];
    for &joint in groups.left_hand.iter().chain(&groups.right_hand) {
        if !wrists.contains(&joint) {
            mask[layout.joint_rotation_range(joint)].fill(0.0);
        }
    }
    Ok(mask)
}

/// A channel mask as a tensor of the parameters' device and type.
fn mask_tensor(mask: Vec<f32>, device: &candle_core::Device, dtype: DType) -> Result<Tensor> {
    let width = mask.len();
    Ok(Tensor::from_vec(mask, width, device)?.to_dtype(dtype)?)
}

impl Denoiser {
    /// A denoiser of frames holding the body and `objects` objects; the blocks cross-attend to
    /// the other stream in the dual layout.
    fn new(cfg: &ModelConfig, objects: usize, vb: VarBuilder<'_>) -> Result<Self> {
        let l = cfg.latent;
        let layout = cfg.layout();
        let frame_features = layout.body_width() + objects * layout.object_width();
        let block = BlockConfig {
            latent: l,
            heads: cfg.heads,
            feed_forward: cfg.feed_forward,
            dropout: cfg.dropout,
            norm: Norm::Adaptive,
            cross_attention: cfg.stream_layout == StreamLayout::Dual,
        };
        let blocks = (0..cfg.layers)
            .map(|i| TransformerBlock::new(&block, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<_>>()?;
        let channel_mask = match cfg.object_representation {
            ObjectRepresentation::HandRelative => None,
            ObjectRepresentation::GlobalOnly => Some(mask_tensor(
                without_hand_relative_channels(cfg, objects),
                vb.device(),
                vb.dtype(),
            )?),
        };
        let small_normal = Init::Randn { mean: 0.0, stdev: 0.02 };
        Ok(Self {
            input: dense(frame_features, l, vb.pp("input"))?,
            positions: vb.get_with_hints((cfg.window_frames(), l), "positions", small_normal)?,
            frame_types: vb.get_with_hints((2, l), "frame_types", small_normal)?,
            blocks,
            final_modulation: Modulation::new(l, vb.pp("final_modulation"))?,
            head: zero_dense(l, frame_features, vb.pp("head"))?,
            channel_mask,
            prefix_frames: cfg.prefix_frames,
            predicted_frames: cfg.predicted_frames,
        })
    }

    /// Frame tokens: projection, positions, prefix/noisy type.
    ///
    /// # Shapes
    /// - `frames`: `[batch, T_p + T_f, features]`; returns `[batch, T_p + T_f, latent]`
    fn tokens(&self, frames: &Tensor) -> Result<Tensor> {
        let frames = match &self.channel_mask {
            Some(mask) => frames.broadcast_mul(mask)?,
            None => frames.clone(),
        };
        Ok(self.input.forward(&frames)?.broadcast_add(&self.frame_embedding()?)?)
    }

    /// What each frame's token adds to its projection: its position and its type (prefix or
    /// noisy).
    ///
    /// # Shapes
    /// - returns `[T_p + T_f, latent]`
    fn frame_embedding(&self) -> Result<Tensor> {
        let latent = self.positions.dims()[1];
        let kind = |k: usize, count: usize| -> Result<Tensor> {
            Ok(self.frame_types.get(k)?.unsqueeze(0)?.broadcast_as((count, latent))?)
        };
        let types =
            Tensor::cat(&[kind(0, self.prefix_frames)?, kind(1, self.predicted_frames)?], 0)?;
        Ok((self.positions.clone() + types)?)
    }

    /// The clean predicted frames (x0). With `other_condition` the batch stacks both streams
    /// (rows `0..B` stream A, `B..2B` stream B) and each block's cross-attention reads the
    /// other stream's previous-layer state, found by swapping the halves (Eq. 5).
    ///
    /// # Shapes
    /// - `frames`: `[batch, T_p + T_f, features]`; `condition`, `other_condition`:
    ///   `[batch, latent]`; `mask`: `[batch, T_p + T_f]`
    /// - returns `[batch, T_f, features]`
    fn forward(
        &self,
        frames: &Tensor,
        condition: &Tensor,
        other_condition: Option<&Tensor>,
        mask: Option<&Tensor>,
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let mut x = self.tokens(frames)?;
        for block in &self.blocks {
            let other_tokens = other_condition.map(|_| swap_streams(&x)).transpose()?;
            let other =
                other_tokens.as_ref().map(|tokens| Other { tokens, condition: other_condition });
            x = block.forward(&x, Some(condition), other, mask, rng.as_deref_mut())?;
        }
        let out = self.head.forward(&self.final_modulation.forward(&x, condition)?)?;
        Ok(out.narrow(1, self.prefix_frames, self.predicted_frames)?)
    }
}

/// Swaps the halves of a batch that stacks both streams (`[A; B] -> [B; A]`).
fn swap_streams(t: &Tensor) -> Result<Tensor> {
    let half = t.dim(0)? / 2;
    Ok(Tensor::cat(&[t.narrow(0, half, half)?, t.narrow(0, 0, half)?], 0)?)
}

/// Moves the stream axis into the batch: `[B, 2, ...] -> [2B, ...]`, stream A first.
fn streams_into_batch(t: &Tensor) -> Result<Tensor> {
    let mut shape = t.dims()[1..].to_vec();
    shape[0] *= t.dim(0)?;
    Ok(t.transpose(0, 1)?.contiguous()?.reshape(shape)?)
}

/// The average of the bodies of the streams that hold an object, `(a + p_B b) / (1 + p_B)`
/// (stream A always holds one).
///
/// # Shapes
/// - `body_a`, `masked_b` (`p_B b`): `[batch, T_f, 6J + 3]`; `present`: `[batch, 1, 1]`
/// - returns `[batch, T_f, 6J + 3]`
fn body_average(body_a: &Tensor, masked_b: &Tensor, present: &Tensor) -> Result<Tensor> {
    Ok((body_a + masked_b)?.broadcast_div(&(present + 1.0)?)?)
}

/// The Motion Fusion Network `D_h` (Eq. 7): self-attention over frames of both streams' body
/// predictions, predicting a correction to their average (the output layer starts at zero, so
/// the network starts as the average and learns what the average misses).
#[derive(Debug, Clone)]
struct FusionNetwork {
    input: Dense,
    positions: Tensor,
    layers: TransformerEncoder,
    output: Dense,
}

/// The layers of a [`FusionNetwork`] pass: the input projection, the trunk (blocks and final
/// norm) and the output projection.
struct FusionLayers<I, E, O> {
    input: I,
    encode: E,
    output: O,
}

impl FusionNetwork {
    fn new(cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let l = cfg.latent;
        let block = BlockConfig::plain(l, cfg.heads, cfg.feed_forward, cfg.dropout);
        Ok(Self {
            input: dense(2 * cfg.body_features() + 1, l, vb.pp("input"))?,
            positions: vb.get_with_hints(
                (cfg.predicted_frames, l),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            layers: TransformerEncoder::new(&block, cfg.fusion_layers, vb.pp("layers"))?,
            output: zero_dense(l, cfg.body_features(), vb.pp("output"))?,
        })
    }

    /// # Shapes
    /// - `body_a`, `body_b`: `[batch, T_f, 6J + 3]`; `presence_b`: `[batch]`
    /// - returns the fused body `[batch, T_f, 6J + 3]`
    fn forward(
        &self,
        body_a: &Tensor,
        body_b: &Tensor,
        presence_b: &Tensor,
        rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let layers = FusionLayers {
            input: |x: &Tensor| self.input.forward(x),
            encode: |x: &Tensor| self.layers.forward(x, None, rng),
            output: |x: &Tensor| self.output.forward(x),
        };
        self.fuse(body_a, body_b, presence_b, layers)
    }

    /// [`Self::forward`] with its layers given (the inference path's products and fused
    /// blocks).
    fn fuse<I, E, O>(
        &self,
        body_a: &Tensor,
        body_b: &Tensor,
        presence_b: &Tensor,
        layers: FusionLayers<I, E, O>,
    ) -> Result<Tensor>
    where
        I: Fn(&Tensor) -> Result<Tensor>,
        E: FnOnce(&Tensor) -> Result<Tensor>,
        O: Fn(&Tensor) -> Result<Tensor>,
    {
        let FusionLayers { input, encode, output } = layers;
        let (batch, frames, _) = body_a.dims3()?;
        let present = presence_b.reshape((batch, 1, 1))?;
        let masked_b = body_b.broadcast_mul(&present)?;
        let flag = present.broadcast_as((batch, frames, 1))?.contiguous()?;
        let average = body_average(body_a, &masked_b, &present)?;
        let tokens = input(&Tensor::cat(&[body_a, &masked_b, &flag], D::Minus1)?)?;
        let x = tokens.broadcast_add(&self.positions.narrow(0, 0, frames)?)?;
        Ok((average + output(&encode(&x)?)?)?)
    }
}

/// How the dual layout makes one body of the two streams' (Table 3 "fusion -> average").
#[derive(Debug, Clone)]
enum Fusion {
    Network(FusionNetwork),
    Average,
}

impl Fusion {
    /// # Shapes
    /// - `body_a`, `body_b`: `[batch, T_f, 6J + 3]`; `presence_b`: `[batch]`
    /// - returns the fused body `[batch, T_f, 6J + 3]`
    fn forward(
        &self,
        body_a: &Tensor,
        body_b: &Tensor,
        presence_b: &Tensor,
        rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        match self {
            Self::Network(network) => network.forward(body_a, body_b, presence_b, rng),
            Self::Average => present_average(body_a, body_b, presence_b),
        }
    }
}

/// [`body_average`] with stream B's body masked by its presence (Table 3 "fusion -> average").
///
/// # Shapes
/// - `body_a`, `body_b`: `[batch, T_f, 6J + 3]`; `presence_b`: `[batch]`
/// - returns `[batch, T_f, 6J + 3]`
fn present_average(body_a: &Tensor, body_b: &Tensor, presence_b: &Tensor) -> Result<Tensor> {
    let present = presence_b.reshape((presence_b.dim(0)?, 1, 1))?;
    body_average(body_a, &body_b.broadcast_mul(&present)?, &present)
}

/// The dual layout (Eq. 5): one stream per object through the same denoiser, cross-attending
/// to each other, then one body from both (Eq. 7).
#[derive(Debug, Clone)]
struct DualStream {
    conditioning: Conditioning,
    denoiser: Denoiser,
    fusion: Fusion,
    layout: FeatureLayout,
}

impl DualStream {
    fn new(cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let fusion = match cfg.body_fusion {
            BodyFusion::Network => Fusion::Network(FusionNetwork::new(cfg, vb.pp("fusion"))?),
            BodyFusion::Average => Fusion::Average,
        };
        Ok(Self {
            conditioning: Conditioning::new(cfg, cfg.bps_points * 3, vb.pp("conditioning"))?,
            denoiser: Denoiser::new(cfg, 1, vb)?,
            fusion,
            layout: cfg.layout(),
        })
    }

    /// Each stream's condition `c^A`, `c^B` sees its own object's BPS and both presence flags.
    ///
    /// # Shapes
    /// - see [`ModelInput`]; returns `[2 batch, latent]`, stream A first
    fn condition(&self, input: &ModelInput<'_>, dtype: DType) -> Result<Tensor> {
        let prompt = PromptState::of(input);
        let fixed = self.fixed_condition(
            input.text,
            input.bps,
            input.presence,
            prompt,
            input.prefix,
            dtype,
        )?;
        let timesteps = Tensor::cat(&[input.timesteps, input.timesteps], 0)?;
        Ok((self.conditioning.time(&timesteps, dtype)? + fixed)?)
    }

    /// The part of [`Self::condition`] that does not depend on the timestep.
    ///
    /// # Shapes
    /// - `text`, `bps`, `presence`, `prompt`, `prefix`: see [`ModelInput`]; returns
    ///   `[2 batch, latent]`
    fn fixed_condition(
        &self,
        text: &Tensor,
        bps: &Tensor,
        presence: &Tensor,
        prompt: PromptState<'_>,
        prefix: &Tensor,
        dtype: DType,
    ) -> Result<Tensor> {
        let own = streams_into_batch(&presence.to_dtype(dtype)?.unsqueeze(2)?)?;
        let flags = Tensor::cat(&[&own, &swap_streams(&own)?], 1)?;
        let bps = streams_into_batch(bps)?.broadcast_mul(&own)?;
        let text = text.to_dtype(dtype)?;
        let elapsed = prompt.elapsed.map(|e| Tensor::cat(&[e, e], 0)).transpose()?;
        // Each stream reads its own object's numbers first, then the other's, zero where a
        // slot is empty: `[batch, 2, W]` per slot becomes `[2 batch, 2 W]` per stream.
        let own_then_other = |per_slot: &Tensor| -> Result<Tensor> {
            let own_slot = streams_into_batch(per_slot)?.broadcast_mul(&own)?;
            Ok(Tensor::cat(&[&own_slot, &swap_streams(&own_slot)?], 1)?)
        };
        let start = self.conditioning.object_start(prompt.object_start, prefix, dtype)?;
        let start = start.map(|start| own_then_other(&start)).transpose()?;
        let settled = prompt
            .settled
            .map(|settled| own_then_other(&settled.to_dtype(dtype)?.unsqueeze(2)?))
            .transpose()?;
        self.conditioning.fixed_part(
            &Tensor::cat(&[&text, &text], 0)?,
            &bps,
            &flags,
            PromptReadings {
                elapsed: elapsed.as_ref(),
                start: start.as_ref(),
                settled: settled.as_ref(),
            },
        )
    }

    /// # Shapes
    /// - see [`ModelInput`]; returns `[batch, 2, T_f, 6J + 3 + 18]`
    fn forward(&self, input: &ModelInput<'_>, mut rng: Option<&mut ChaCha8Rng>) -> Result<Tensor> {
        let frames = streams_into_batch(&Tensor::cat(&[input.prefix, input.noisy], 2)?)?;
        let condition = self.condition(input, frames.dtype())?;
        let mask = input
            .frame_mask
            .map(|m| Tensor::cat(&[m, m], 0)?.to_dtype(frames.dtype()))
            .transpose()?;
        let out = self.denoiser.forward(
            &frames,
            &condition,
            Some(&swap_streams(&condition)?),
            mask.as_ref(),
            rng.as_deref_mut(),
        )?; // [2B, T_f, D]
        self.assemble(&out, input.presence, |a, b, presence_b| {
            self.fusion.forward(a, b, presence_b, rng)
        })
    }

    /// Eq. 6 and 7: each stream's prediction splits into body and object; `fuse` makes one
    /// body of the two, which both streams then carry.
    ///
    /// # Shapes
    /// - `out`: `[2 batch, T_f, 6J + 3 + 18]`, stream A first; `presence`: `[batch, 2]`
    /// - `fuse(body_a, body_b, presence_b)`: `[batch, T_f, 6J + 3]` twice and `[batch]`
    /// - returns `[batch, 2, T_f, 6J + 3 + 18]`
    fn assemble(
        &self,
        out: &Tensor,
        presence: &Tensor,
        fuse: impl FnOnce(&Tensor, &Tensor, &Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let batch = out.dim(0)? / 2;
        let stream = |s: usize| out.narrow(0, s * batch, batch);
        let (body_a, body_b) =
            (self.layout.body_of(&stream(0)?)?, self.layout.body_of(&stream(1)?)?);
        let presence_b = presence.to_dtype(out.dtype())?.narrow(1, 1, 1)?.squeeze(1)?;
        let body = fuse(&body_a, &body_b, &presence_b)?;
        let with_body = |s: usize| -> Result<Tensor> {
            let object = self.layout.object_of(&stream(s)?)?;
            Ok(Tensor::cat(&[&body, &object], 2)?)
        };
        Ok(Tensor::stack(&[with_body(0)?, with_body(1)?], 1)?)
    }
}

/// The single-stream layout (Table 3 "single stream", also the MDM-style baseline): one
/// sequence of frames `[h, r, o^A, o^B]`, no cross-attention and no fusion.
#[derive(Debug, Clone)]
struct SingleStream {
    conditioning: Conditioning,
    denoiser: Denoiser,
    layout: FeatureLayout,
}

impl SingleStream {
    fn new(cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Self {
            conditioning: Conditioning::new(cfg, 2 * cfg.bps_points * 3, vb.pp("conditioning"))?,
            denoiser: Denoiser::new(cfg, 2, vb)?,
            layout: cfg.layout(),
        })
    }

    /// # Shapes
    /// - see [`ModelInput`]; returns `[batch, 2, T_f, 6J + 3 + 18]`
    fn forward(&self, input: &ModelInput<'_>, rng: Option<&mut ChaCha8Rng>) -> Result<Tensor> {
        let single = self.frames(input.prefix, input.noisy)?;
        let dtype = single.dtype();
        let prompt = PromptState::of(input);
        let fixed = self.fixed_condition(
            input.text,
            input.bps,
            input.presence,
            prompt,
            input.prefix,
            dtype,
        )?;
        let condition = (self.conditioning.time(input.timesteps, dtype)? + fixed)?;
        let mask = input.frame_mask.map(|m| m.to_dtype(dtype)).transpose()?;
        let out = self.denoiser.forward(&single, &condition, None, mask.as_ref(), rng)?;
        self.split(&out)
    }

    /// The single stream's frames `[h, r, o^A, o^B]` of a window.
    ///
    /// # Shapes
    /// - `prefix`, `noisy`: see [`ModelInput`]; returns `[batch, T_p + T_f, 6J + 3 + 2 * 18]`
    fn frames(&self, prefix: &Tensor, noisy: &Tensor) -> Result<Tensor> {
        let frames = Tensor::cat(&[prefix, noisy], 2)?; // [B, 2, T, D]
        let of_stream = |s: usize| frames.narrow(1, s, 1)?.squeeze(1);
        let object = |s: usize| self.layout.object_of(&of_stream(s)?);
        let body = self.layout.body_of(&of_stream(0)?)?;
        Ok(Tensor::cat(&[&body, &object(0)?, &object(1)?], 2)?)
    }

    /// The part of the condition that does not depend on the timestep.
    ///
    /// # Shapes
    /// - `text`, `bps`, `presence`, `prompt`, `prefix`: see [`ModelInput`]; returns
    ///   `[batch, latent]`
    fn fixed_condition(
        &self,
        text: &Tensor,
        bps: &Tensor,
        presence: &Tensor,
        prompt: PromptState<'_>,
        prefix: &Tensor,
        dtype: DType,
    ) -> Result<Tensor> {
        let batch = text.dim(0)?;
        let presence = presence.to_dtype(dtype)?;
        let bps = bps.broadcast_mul(&presence.unsqueeze(2)?)?.reshape((batch, ()))?;
        // Both objects' numbers, slot A first, zero where a slot is empty: `[batch, 2, W]`
        // becomes `[batch, 2 W]`.
        let both_slots = |per_slot: &Tensor| -> Result<Tensor> {
            Ok(per_slot.broadcast_mul(&presence.unsqueeze(2)?)?.reshape((batch, ()))?)
        };
        let start = self.conditioning.object_start(prompt.object_start, prefix, dtype)?;
        let start = start.map(|start| both_slots(&start)).transpose()?;
        let settled = prompt
            .settled
            .map(|settled| both_slots(&settled.to_dtype(dtype)?.unsqueeze(2)?))
            .transpose()?;
        let text = text.to_dtype(dtype)?;
        let readings = PromptReadings {
            elapsed: prompt.elapsed,
            start: start.as_ref(),
            settled: settled.as_ref(),
        };
        self.conditioning.fixed_part(&text, &bps, &presence, readings)
    }

    /// The denoiser's single-stream output as both streams' frames.
    ///
    /// # Shapes
    /// - `out`: `[batch, T_f, 6J + 3 + 2 * 18]`; returns `[batch, 2, T_f, 6J + 3 + 18]`
    fn split(&self, out: &Tensor) -> Result<Tensor> {
        // The single stream's frames are `[h, r, o^A, o^B]`: object `s` sits `s` object widths
        // after the body.
        let body = self.layout.body_of(out)?;
        let (width, object_width) = (self.layout.body_width(), self.layout.object_width());
        let stream = |s: usize| -> Result<Tensor> {
            let object = out.narrow(2, width + s * object_width, object_width)?;
            Ok(Tensor::cat(&[&body, &object], 2)?)
        };
        Ok(Tensor::stack(&[stream(0)?, stream(1)?], 1)?)
    }
}

/// The stream layouts, each a module with its own `forward` (like candle's `UNetDownBlock`).
#[derive(Debug, Clone)]
enum Layout {
    Dual(DualStream),
    Single(SingleStream),
}

/// The whole model: conditioning, the (dual- or single-) stream denoiser and the body fusion.
#[derive(Debug, Clone)]
pub struct Model {
    config: ModelConfig,
    layout: Layout,
    /// Which channels of a stream row take the last prefix frame (`None`: all or none, as
    /// `config.prediction` says), `[6J + 3 + 18]`.
    residual_mask: Option<Tensor>,
}

impl Model {
    /// Builds the model; parameter names mirror the module tree (`blocks.3.cross_attention.query`).
    pub fn new(config: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        config.validate()?;
        let (device, dtype) = (vb.device().clone(), vb.dtype());
        let layout = match config.stream_layout {
            StreamLayout::Dual => Layout::Dual(DualStream::new(config, vb)?),
            StreamLayout::Single => Layout::Single(SingleStream::new(config, vb)?),
        };
        let residual_mask = match config.prediction {
            Prediction::Absolute | Prediction::PrefixResidual => None,
            // A stream row holds one object.
            Prediction::PrefixResidualWorld => Some(without_hand_relative_channels(config, 1)),
            Prediction::PrefixResidualPlacement => Some(placement_channels(config)),
            Prediction::PrefixResidualCleanFingers => Some(without_hand_channels(config)?),
        };
        let residual_mask =
            residual_mask.map(|mask| mask_tensor(mask, &device, dtype)).transpose()?;
        Ok(Self { config: config.clone(), layout, residual_mask })
    }

    /// The configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    fn check_input(&self, input: &ModelInput<'_>) -> Result<()> {
        let c = &self.config;
        let batch = input.noisy.dims().first().copied().unwrap_or(0);
        let expect = |name: &str, t: &Tensor, shape: Vec<usize>| -> Result<()> {
            if t.dims() != shape.as_slice() {
                return Err(ModelError::shape(name, format!("{shape:?}"), t.dims()));
            }
            Ok(())
        };
        let d = c.stream_features();
        expect("noisy", input.noisy, vec![batch, 2, c.predicted_frames, d])?;
        expect("prefix", input.prefix, vec![batch, 2, c.prefix_frames, d])?;
        expect("timesteps", input.timesteps, vec![batch])?;
        expect("text", input.text, vec![batch, c.text_embedding])?;
        expect("bps", input.bps, vec![batch, 2, c.bps_points * 3])?;
        expect("presence", input.presence, vec![batch, 2])?;
        if let Some(mask) = input.frame_mask {
            expect("frame_mask", mask, vec![batch, c.window_frames()])?;
        }
        if let Some(elapsed) = input.elapsed {
            expect("elapsed", elapsed, vec![batch])?;
        }
        if let Some(start) = input.object_start {
            expect("object_start", start, vec![batch, 2, d])?;
        }
        if let Some(settled) = input.settled {
            expect("settled", settled, vec![batch, 2])?;
        }
        if let Some(reach) = input.reach {
            expect("reach", reach, vec![batch, 2, d])?;
        }
        Ok(())
    }

    /// Predicts the clean predicted frames of both streams (x0): the object parts from each
    /// stream, the body from the fusion (network or average) and the same in both streams.
    ///
    /// `rng` switches training mode on (dropout masks drawn from it).
    ///
    /// # Shapes
    /// - see [`ModelInput`]; returns `[batch, 2, T_f, 6J + 3 + 18]`
    pub fn forward(&self, input: &ModelInput<'_>, rng: Option<&mut ChaCha8Rng>) -> Result<Tensor> {
        self.check_input(input)?;
        let tokens = self.token_prefix(input.prefix, input.object_start, input.reach)?;
        let read = ModelInput { prefix: &tokens, ..*input };
        let out = match &self.layout {
            Layout::Dual(dual) => dual.forward(&read, rng)?,
            Layout::Single(single) => single.forward(&read, rng)?,
        };
        self.add_prefix_residual(out, input.prefix)
    }

    /// The prefix the denoiser reads as tokens: the prefix itself, or the prefix whose first
    /// frame is the rows at the first frame of the prompt in force (the start frame in the
    /// prefix, `ModelConfig::start_in_prefix`) or at the frame each stream's object was
    /// reached (the reach frame in the prefix, `ModelConfig::reach_in_prefix`). Why: an object
    /// put back after a hold longer than the prefix is put down where nothing in the window
    /// says it stood; as a token, where it stood (or the arm that took it there) can be read by
    /// attention the way the prefix's frames are. The prefix-residual head and the object start
    /// from the prefix still read the real last prefix frame.
    ///
    /// # Shapes
    /// - `prefix`: `[batch, 2, T_p, D]`; `start`, `reach`: `[batch, 2, D]`; returns `prefix`'s
    ///   shape
    pub(crate) fn token_prefix(
        &self,
        prefix: &Tensor,
        start: Option<&Tensor>,
        reach: Option<&Tensor>,
    ) -> Result<Tensor> {
        let first = if self.config.start_in_prefix {
            required(start, "object_start", "the rows at each prompt's first frame")?
        } else if self.config.reach_in_prefix {
            required(reach, "reach", "the rows at the frame each object was reached")?
        } else {
            return Ok(prefix.clone());
        };
        let rest = prefix.narrow(2, 1, self.config.prefix_frames - 1)?;
        Ok(Tensor::cat(&[&first.to_dtype(prefix.dtype())?.unsqueeze(2)?, &rest], 2)?)
    }

    /// The head's output as clean frames: with a prefix-residual [`Prediction`] the last
    /// prefix frame is added to every predicted frame (normalised features; every channel, or
    /// every channel but the hand-relative ones). The body is read from stream A's prefix for both
    /// streams, as everywhere a frame's body is read, so that both streams keep one body.
    ///
    /// # Shapes
    /// - `head`: `[batch, 2, T_f, D]`; `prefix`: `[batch, 2, T_p, D]`; returns `head`'s shape
    fn add_prefix_residual(&self, head: Tensor, prefix: &Tensor) -> Result<Tensor> {
        if !self.config.prediction.adds_prefix() {
            return Ok(head);
        }
        let last = prefix.narrow(2, self.config.prefix_frames - 1, 1)?;
        let (batch, streams, _, width) = last.dims4()?;
        let body_width = self.config.body_features();
        let body = last
            .narrow(1, 0, 1)?
            .narrow(3, 0, body_width)?
            .broadcast_as((batch, streams, 1, body_width))?;
        let objects = last.narrow(3, body_width, width - body_width)?;
        let mut last = Tensor::cat(&[&body, &objects], 3)?;
        if let Some(mask) = &self.residual_mask {
            last = last.broadcast_mul(mask)?;
        }
        Ok(head.broadcast_add(&last)?)
    }

    /// The device of the parameters.
    pub fn device(&self) -> &candle_core::Device {
        match &self.layout {
            Layout::Dual(dual) => dual.denoiser.positions.device(),
            Layout::Single(single) => single.denoiser.positions.device(),
        }
    }

    /// The floating-point type of the parameters.
    pub fn dtype(&self) -> DType {
        match &self.layout {
            Layout::Dual(dual) => dual.denoiser.positions.dtype(),
            Layout::Single(single) => single.denoiser.positions.dtype(),
        }
    }
}
