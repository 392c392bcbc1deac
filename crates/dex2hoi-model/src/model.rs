//! The Dex2HOI networks (paper Sec. 3.2): the dual-stream denoiser `D_theta` (Eq. 5) with
//! InterGen-style blocks shared by both streams, and the Motion Fusion Network `D_h` (Eq. 7),
//! plus the ablation variants of Table 3 selected by [`ModelConfig`].

use candle_core::{D, DType, Tensor};
use candle_nn::{VarBuilder, init::Init};
use rand_chacha::ChaCha8Rng;

use dex2hoi_repr::object_repr::{
    LEFT_OFFSET_RANGE, MIXTURE_RANGE, OBJECT_FEATURE_SIZE, RIGHT_OFFSET_RANGE,
};

use crate::config::{BodyFusion, ModelConfig, ObjectRepresentation, StreamLayout};
use crate::error::{ModelError, Result};
use crate::layers::{
    Attention, Dense, FeedForward, Modulation, dense, dropout, layer_norm, timestep_embedding,
    zero_dense,
};

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
}

/// The condition embedding of each stream: timestep MLP + projected text + the stream's object
/// (BPS MLP and presence).
#[derive(Debug, Clone)]
struct Conditioning {
    time_in: Dense,
    time_out: Dense,
    text: Dense,
    bps_in: Dense,
    bps_out: Dense,
    presence: Dense,
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
            latent: l,
        })
    }

    /// # Shapes
    /// - `timesteps`: `[batch]`; `text`: `[batch, E]`; `bps`: `[batch, bps_inputs]`;
    ///   `presence`: `[batch, 2]`; returns `[batch, latent]`
    fn forward(
        &self,
        timesteps: &Tensor,
        text: &Tensor,
        bps: &Tensor,
        presence: &Tensor,
    ) -> Result<Tensor> {
        let time = timestep_embedding(timesteps, self.latent, text.dtype(), text.device())?;
        let time = self.time_out.forward(&self.time_in.forward(&time)?.silu()?)?;
        let object = self.bps_out.forward(&self.bps_in.forward(bps)?.silu()?)?;
        let total = ((time + self.text.forward(text)?)? + object)?;
        Ok((total + self.presence.forward(presence)?)?)
    }
}

/// One InterGen block: AdaLN self-attention, cross-attention to the other stream's
/// previous-layer state (dual layout only), AdaLN feed-forward, each with a residual.
#[derive(Debug, Clone)]
struct Block {
    self_modulation: Modulation,
    self_attention: Attention,
    cross: Option<(Modulation, Modulation, Attention)>,
    ff_modulation: Modulation,
    feed_forward: FeedForward,
    dropout: f64,
}

impl Block {
    fn new(cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let l = cfg.latent;
        let cross = match cfg.stream_layout {
            StreamLayout::Dual => Some((
                Modulation::new(l, vb.pp("cross_modulation"))?,
                Modulation::new(l, vb.pp("cross_other_modulation"))?,
                Attention::new(l, cfg.heads, vb.pp("cross_attention"))?,
            )),
            StreamLayout::Single => None,
        };
        Ok(Self {
            self_modulation: Modulation::new(l, vb.pp("self_modulation"))?,
            self_attention: Attention::new(l, cfg.heads, vb.pp("self_attention"))?,
            cross,
            ff_modulation: Modulation::new(l, vb.pp("ff_modulation"))?,
            feed_forward: FeedForward::new(l, cfg.feed_forward, vb.pp("feed_forward"))?,
            dropout: cfg.dropout,
        })
    }

    /// `other` and `other_emb` are the other stream's previous-layer state and condition (the
    /// dual layout swaps the halves of the batch to get them).
    fn forward(
        &self,
        x: &Tensor,
        emb: &Tensor,
        other: Option<(&Tensor, &Tensor)>,
        mask: Option<&Tensor>,
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let h = self.self_modulation.forward(x, emb)?;
        let attended = self.self_attention.forward(&h, &h, mask)?;
        let mut x = (x + dropout(&attended, self.dropout, rng.as_deref_mut())?)?;
        if let (Some((modulation, other_modulation, attention)), Some((other, other_emb))) =
            (&self.cross, other)
        {
            let queries = modulation.forward(&x, emb)?;
            let keys = other_modulation.forward(other, other_emb)?;
            let attended = attention.forward(&queries, &keys, mask)?;
            x = (x + dropout(&attended, self.dropout, rng.as_deref_mut())?)?;
        }
        let h = self.ff_modulation.forward(&x, emb)?;
        let out = self.feed_forward.forward(&h, self.dropout, rng.as_deref_mut())?;
        Ok((x + dropout(&out, self.dropout, rng)?)?)
    }
}

/// A pre-norm transformer layer without conditioning, for the fusion network.
#[derive(Debug, Clone)]
struct FusionLayer {
    attention: Attention,
    feed_forward: FeedForward,
}

/// The Motion Fusion Network `D_h` (Eq. 7): self-attention over frames of both streams' body
/// predictions, predicting a correction to their average (the output layer starts at zero, so
/// the network starts as the average and learns what the average misses).
#[derive(Debug, Clone)]
struct FusionNetwork {
    input: Dense,
    positions: Tensor,
    layers: Vec<FusionLayer>,
    output: Dense,
    dropout: f64,
}

impl FusionNetwork {
    fn new(cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let l = cfg.latent;
        let layers = (0..cfg.fusion_layers)
            .map(|i| {
                let vb = vb.pp(format!("layers.{i}"));
                Ok(FusionLayer {
                    attention: Attention::new(l, cfg.heads, vb.pp("attention"))?,
                    feed_forward: FeedForward::new(l, cfg.feed_forward, vb.pp("feed_forward"))?,
                })
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            input: dense(2 * cfg.body_features() + 1, l, vb.pp("input"))?,
            positions: vb.get_with_hints(
                (cfg.predicted_frames, l),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            layers,
            output: zero_dense(l, cfg.body_features(), vb.pp("output"))?,
            dropout: cfg.dropout,
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
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let (batch, frames, _) = body_a.dims3()?;
        let present = presence_b.reshape((batch, 1, 1))?;
        let masked_b = body_b.broadcast_mul(&present)?;
        let flag = present.broadcast_as((batch, frames, 1))?.contiguous()?;
        let average = ((body_a + &masked_b)?.broadcast_div(&(present.clone() + 1.0)?))?;
        let tokens = self.input.forward(&Tensor::cat(&[body_a, &masked_b, &flag], D::Minus1)?)?;
        let mut x = tokens.broadcast_add(&self.positions.narrow(0, 0, frames)?)?;
        for layer in &self.layers {
            let h = layer_norm(&x)?;
            x = (&x
                + dropout(
                    &layer.attention.forward(&h, &h, None)?,
                    self.dropout,
                    rng.as_deref_mut(),
                )?)?;
            let h = layer_norm(&x)?;
            x = (&x
                + dropout(
                    &layer.feed_forward.forward(&h, self.dropout, rng.as_deref_mut())?,
                    self.dropout,
                    rng.as_deref_mut(),
                )?)?;
        }
        Ok((average + self.output.forward(&layer_norm(&x)?)?)?)
    }
}

/// The whole model: conditioning, the (dual- or single-) stream denoiser and the body fusion.
#[derive(Debug, Clone)]
pub struct Model {
    config: ModelConfig,
    conditioning: Conditioning,
    input: Dense,
    positions: Tensor,
    frame_types: Tensor,
    blocks: Vec<Block>,
    final_modulation: Modulation,
    head: Dense,
    fusion: Option<FusionNetwork>,
    /// Per-channel input mask (zeros the hand-relative channels for `GlobalOnly`).
    channel_mask: Option<Tensor>,
}

impl Model {
    /// Builds the model; parameter names mirror the module tree (`blocks.3.cross_attention.query`).
    pub fn new(config: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        config.validate()?;
        let l = config.latent;
        let single = config.stream_layout == StreamLayout::Single;
        let frame_features = if single {
            config.stream_features() + OBJECT_FEATURE_SIZE
        } else {
            config.stream_features()
        };
        let bps_inputs = config.bps_points * 3 * if single { 2 } else { 1 };
        let blocks = (0..config.layers)
            .map(|i| Block::new(config, vb.pp(format!("blocks.{i}"))))
            .collect::<Result<_>>()?;
        let fusion = match (config.stream_layout, config.body_fusion) {
            (StreamLayout::Dual, BodyFusion::Network) => {
                Some(FusionNetwork::new(config, vb.pp("fusion"))?)
            }
            _ => None,
        };
        let channel_mask = match config.object_representation {
            ObjectRepresentation::HandRelative => None,
            ObjectRepresentation::GlobalOnly => {
                let mut mask = vec![1.0f32; frame_features];
                let objects = if single { 2 } else { 1 };
                for k in 0..objects {
                    let base = config.body_features() + k * OBJECT_FEATURE_SIZE;
                    for range in [LEFT_OFFSET_RANGE, RIGHT_OFFSET_RANGE, MIXTURE_RANGE] {
                        mask[base + range.start..base + range.end].fill(0.0);
                    }
                }
                Some(Tensor::from_vec(mask, frame_features, vb.device())?.to_dtype(vb.dtype())?)
            }
        };
        Ok(Self {
            config: config.clone(),
            conditioning: Conditioning::new(config, bps_inputs, vb.pp("conditioning"))?,
            input: dense(frame_features, l, vb.pp("input"))?,
            positions: vb.get_with_hints(
                (config.window_frames(), l),
                "positions",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            frame_types: vb.get_with_hints(
                (2, l),
                "frame_types",
                Init::Randn { mean: 0.0, stdev: 0.02 },
            )?,
            blocks,
            final_modulation: Modulation::new(l, vb.pp("final_modulation"))?,
            head: zero_dense(l, frame_features, vb.pp("head"))?,
            fusion,
            channel_mask,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    fn check_input(&self, input: &ModelInput<'_>) -> Result<usize> {
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
        Ok(batch)
    }

    /// Frame tokens: projection, positions, prefix/noisy type.
    fn tokens(&self, frames: &Tensor) -> Result<Tensor> {
        let c = &self.config;
        let frames = match &self.channel_mask {
            Some(mask) => frames.broadcast_mul(mask)?,
            None => frames.clone(),
        };
        let types = Tensor::cat(
            &[
                self.frame_types.get(0)?.unsqueeze(0)?.broadcast_as((c.prefix_frames, c.latent))?,
                self.frame_types
                    .get(1)?
                    .unsqueeze(0)?
                    .broadcast_as((c.predicted_frames, c.latent))?,
            ],
            0,
        )?;
        let position = (self.positions.clone() + types)?;
        Ok(self.input.forward(&frames)?.broadcast_add(&position)?)
    }

    /// Predicts the clean predicted frames of both streams (x0): the object parts from each
    /// stream, the body from the fusion (network or average) and the same in both streams.
    ///
    /// `rng` switches training mode on (dropout masks drawn from it).
    ///
    /// # Shapes
    /// - see [`ModelInput`]; returns `[batch, 2, T_f, 6J + 3 + 18]`
    pub fn forward(
        &self,
        input: &ModelInput<'_>,
        mut rng: Option<&mut ChaCha8Rng>,
    ) -> Result<Tensor> {
        let batch = self.check_input(input)?;
        let c = &self.config;
        let (tf, body) = (c.predicted_frames, c.body_features());
        let frames = Tensor::cat(&[input.prefix, input.noisy], 2)?; // [B, 2, T, D]
        let presence = input.presence.to_dtype(frames.dtype())?;
        let text = input.text.to_dtype(frames.dtype())?;
        match c.stream_layout {
            StreamLayout::Dual => {
                // Streams into the batch: rows 0..B are stream A, B..2B stream B.
                let stacked = frames.transpose(0, 1)?.contiguous()?.reshape((
                    2 * batch,
                    c.window_frames(),
                    c.stream_features(),
                ))?;
                let bps = input
                    .bps
                    .transpose(0, 1)?
                    .contiguous()?
                    .reshape((2 * batch, c.bps_points * 3))?;
                let own = presence.transpose(0, 1)?.contiguous()?.reshape((2 * batch, 1))?;
                let other_presence =
                    Tensor::cat(&[own.narrow(0, batch, batch)?, own.narrow(0, 0, batch)?], 0)?;
                let flags = Tensor::cat(&[&own, &other_presence], 1)?;
                let timesteps = Tensor::cat(&[input.timesteps, input.timesteps], 0)?;
                let text = Tensor::cat(&[&text, &text], 0)?;
                let emb = self.conditioning.forward(
                    &timesteps,
                    &text,
                    &bps.broadcast_mul(&own)?,
                    &flags,
                )?;
                let mask = input
                    .frame_mask
                    .map(|m| Tensor::cat(&[m, m], 0))
                    .transpose()?
                    .map(|m| m.to_dtype(frames.dtype()))
                    .transpose()?;
                let swap = |t: &Tensor| -> Result<Tensor> {
                    Ok(Tensor::cat(&[t.narrow(0, batch, batch)?, t.narrow(0, 0, batch)?], 0)?)
                };
                let other_emb = swap(&emb)?;
                let mut x = self.tokens(&stacked)?;
                for block in &self.blocks {
                    let other = swap(&x)?;
                    x = block.forward(
                        &x,
                        &emb,
                        Some((&other, &other_emb)),
                        mask.as_ref(),
                        rng.as_deref_mut(),
                    )?;
                }
                let out = self.head.forward(&self.final_modulation.forward(&x, &emb)?)?;
                let out = out.narrow(1, c.prefix_frames, tf)?; // [2B, T_f, D]
                let body_a = out.narrow(0, 0, batch)?.narrow(2, 0, body)?;
                let body_b = out.narrow(0, batch, batch)?.narrow(2, 0, body)?;
                let presence_b = presence.narrow(1, 1, 1)?.squeeze(1)?;
                let fused = match &self.fusion {
                    Some(fusion) => fusion.forward(&body_a, &body_b, &presence_b, rng)?,
                    None => {
                        let present = presence_b.reshape((batch, 1, 1))?;
                        (&body_a + body_b.broadcast_mul(&present)?)?
                            .broadcast_div(&(present + 1.0)?)?
                    }
                };
                let object = |s: usize| {
                    out.narrow(0, s * batch, batch)?.narrow(2, body, OBJECT_FEATURE_SIZE)
                };
                let stream_a = Tensor::cat(&[&fused, &object(0)?], 2)?;
                let stream_b = Tensor::cat(&[&fused, &object(1)?], 2)?;
                Ok(Tensor::stack(&[stream_a, stream_b], 1)?)
            }
            StreamLayout::Single => {
                let body_part = frames.narrow(1, 0, 1)?.squeeze(1)?.narrow(2, 0, body)?;
                let object = |s: usize| {
                    frames.narrow(1, s, 1)?.squeeze(1)?.narrow(2, body, OBJECT_FEATURE_SIZE)
                };
                let single = Tensor::cat(&[&body_part, &object(0)?, &object(1)?], 2)?;
                let bps = input
                    .bps
                    .broadcast_mul(&presence.unsqueeze(2)?)?
                    .reshape((batch, 2 * c.bps_points * 3))?;
                let emb = self.conditioning.forward(input.timesteps, &text, &bps, &presence)?;
                let mask = input.frame_mask.map(|m| m.to_dtype(frames.dtype())).transpose()?;
                let mut x = self.tokens(&single)?;
                for block in &self.blocks {
                    x = block.forward(&x, &emb, None, mask.as_ref(), rng.as_deref_mut())?;
                }
                let out = self.head.forward(&self.final_modulation.forward(&x, &emb)?)?.narrow(
                    1,
                    c.prefix_frames,
                    tf,
                )?;
                let fused = out.narrow(2, 0, body)?;
                let stream = |s: usize| -> Result<Tensor> {
                    Ok(Tensor::cat(
                        &[
                            &fused,
                            &out.narrow(2, body + s * OBJECT_FEATURE_SIZE, OBJECT_FEATURE_SIZE)?,
                        ],
                        2,
                    )?)
                };
                Ok(Tensor::stack(&[stream(0)?, stream(1)?], 1)?)
            }
        }
    }

    /// The floating-point type of the parameters.
    pub fn dtype(&self) -> DType {
        self.positions.dtype()
    }
}
