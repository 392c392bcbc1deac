//! The no-grad inference path (sampling): the function of [`Model::forward`] without dropout
//! or an autograd graph, made of fused forward-only CPU operations ([`crate::fused`]) and
//! parameters rearranged once, at load time:
//! - the query, key and value projections of each self-attention in one `[latent, 3 latent]`
//!   product;
//! - every AdaLN modulation of the denoiser (four per block and the final one) in one
//!   `[latent, columns]` product per diffusion step;
//! - the part of the condition that does not depend on the timestep (text, BPS and presence
//!   projections) computed once per sample ([`InferenceModel::prepare`]);
//! - every weight packed for the products ([`PackedMatrix`]).
//!
//! The last denoiser block computes only the predicted frames, the only ones the head reads.
//!
//! Stored parameter names do not change: the rearranged tensors are built from the modules
//! that [`Model::new`] made. An [`InferenceModel`] is a snapshot: build it after the weights
//! are final. On a device other than the CPU, or in a dtype other than f32, it runs the
//! composite [`Model::forward`].

use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

use super::PromptState;
use super::{Denoiser, DualStream, Fusion, FusionLayers, Layout, Model, ModelInput, SingleStream};
use super::{present_average, streams_into_batch};
use crate::error::Result;
use crate::fused::{self, PackedMatrix};
use crate::layers::{Dense, Modulation};
use crate::transformer::{PreNorm, TransformerBlock};

/// `x @ weight` over the last dimension (the bias is added by the fused consumer).
///
/// # Shapes
/// - `x`: `[..., input]`; `weight`: `[input, output]`; returns `[..., output]`
fn product(x: &Tensor, weight: &PackedMatrix) -> Result<Tensor> {
    Ok(fused::product(&x.contiguous()?, weight)?)
}

/// A linear layer's parameters, detached from the autograd graph, the weight packed.
#[derive(Debug, Clone)]
struct Linear {
    weight: PackedMatrix,
    bias: Tensor,
}

impl Linear {
    fn of(dense: &Dense) -> Result<Self> {
        Ok(Self { weight: PackedMatrix::new(&dense.weight)?, bias: dense.bias.detach() })
    }

    /// Parameters of layers that read the same input, side by side (their outputs
    /// concatenated).
    fn side_by_side(layers: &[&Dense]) -> Result<Self> {
        let weights: Vec<&Tensor> = layers.iter().map(|d| &d.weight).collect();
        let biases: Vec<&Tensor> = layers.iter().map(|d| &d.bias).collect();
        Ok(Self {
            weight: PackedMatrix::new(&Tensor::cat(&weights, 1)?)?,
            bias: Tensor::cat(&biases, 0)?.detach(),
        })
    }

    /// # Shapes
    /// - `x`: `[..., input]`; returns `[..., output]`
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(fused::bias(&product(x, &self.weight)?, &self.bias, false)?)
    }
}

/// Collects the AdaLN modulations of a denoiser into one table (see the module's docs).
#[derive(Default)]
struct TableBuilder {
    layers: Vec<Dense>,
    columns: usize,
}

impl TableBuilder {
    /// Adds a modulation; returns its first column.
    fn add(&mut self, modulation: &Modulation) -> usize {
        let column = self.columns;
        self.columns += modulation.linear.weight.dims()[1];
        self.layers.push(modulation.linear.clone());
        column
    }

    fn norm(&mut self, norm: &PreNorm) -> Norm {
        match norm {
            PreNorm::Plain => Norm::Plain,
            PreNorm::Adaptive(modulation) => Norm::Adaptive { column: self.add(modulation) },
        }
    }

    fn finish(self) -> Result<Option<Linear>> {
        if self.layers.is_empty() {
            return Ok(None);
        }
        Linear::side_by_side(&self.layers.iter().collect::<Vec<_>>()).map(Some)
    }
}

/// A block's normalisation: plain layer norm, or AdaLN with its modulation at `column` of the
/// step's table.
#[derive(Debug, Clone, Copy)]
enum Norm {
    Plain,
    Adaptive { column: usize },
}

impl Norm {
    /// With `swap_halves`, each sequence is normalised as the other half's (the other
    /// stream).
    ///
    /// # Shapes
    /// - `x`: `[N, T, latent]`; `table`: `[N, columns]`; returns `x`'s shape
    fn forward(&self, x: &Tensor, table: Option<&Tensor>, swap_halves: bool) -> Result<Tensor> {
        match (self, table) {
            (Self::Adaptive { column }, Some(table)) => {
                Ok(fused::adaln(x, table, *column, swap_halves)?)
            }
            (Self::Adaptive { .. }, None) => Err(crate::error::ModelError::shape(
                "modulation table",
                "a table for an AdaLN block",
                &[],
            )),
            (Self::Plain, _) if swap_halves => Ok(fused::layer_norm(&super::swap_streams(x)?)?),
            (Self::Plain, _) => Ok(fused::layer_norm(x)?),
        }
    }
}

/// The cross-attention of a [`Block`]: queries from this stream, keys and values from the
/// other stream's block input.
#[derive(Debug, Clone)]
struct Cross {
    norm: Norm,
    other_norm: Norm,
    query: PackedMatrix,
    key_value: PackedMatrix,
    /// Query, key and value biases, `[3 latent]`.
    bias: Tensor,
    out: Linear,
}

/// [`TransformerBlock`] for inference.
#[derive(Debug, Clone)]
struct Block {
    self_norm: Norm,
    /// Queries, keys and values of the self-attention in one product, `[latent, 3 latent]`.
    qkv: Linear,
    self_out: Linear,
    cross: Option<Cross>,
    ff_norm: Norm,
    up: Linear,
    down: Linear,
    heads: usize,
    latent: usize,
}

impl Block {
    fn new(block: &TransformerBlock, table: &mut TableBuilder) -> Result<Self> {
        let attention = &block.self_attention;
        let latent = attention.query.weight.dims()[1];
        let self_norm = table.norm(&block.self_norm);
        let cross = match &block.cross {
            Some(cross) => Some(Cross {
                norm: table.norm(&cross.norm),
                other_norm: table.norm(&cross.other_norm),
                query: PackedMatrix::new(&cross.attention.query.weight)?,
                key_value: PackedMatrix::new(&cross.attention.key_value.weight)?,
                bias: Tensor::cat(
                    &[&cross.attention.query.bias, &cross.attention.key_value.bias],
                    0,
                )?
                .detach(),
                out: Linear::of(&cross.attention.out)?,
            }),
            None => None,
        };
        Ok(Self {
            self_norm,
            qkv: Linear::side_by_side(&[&attention.query, &attention.key_value])?,
            self_out: Linear::of(&attention.out)?,
            cross,
            ff_norm: table.norm(&block.ff_norm),
            up: Linear::of(&block.feed_forward.up)?,
            down: Linear::of(&block.feed_forward.down)?,
            heads: attention.heads,
            latent,
        })
    }

    fn attention_op(&self, key_column: usize) -> fused::Attention {
        fused::Attention { heads: self.heads, latent: self.latent, query_column: 0, key_column }
    }

    /// [`TransformerBlock::forward`] without dropout; with a cross-attention, the batch stacks
    /// both streams and the keys come from the other half of `x` (Eq. 5).
    ///
    /// With `kept = Some((start, len))` only frames `start..start + len` of each sequence are
    /// computed and returned (the last block, whose other frames the head drops): every frame
    /// still serves as a key and value, and past the attention each frame's row is computed
    /// on its own, so the kept rows are those of the whole block.
    ///
    /// # Shapes
    /// - `x`: `[N, T, latent]`; `table`: `[N, columns]` (AdaLN only)
    /// - returns `[N, len, latent]` (`len = T` without `kept`)
    fn forward(
        &self,
        x: &Tensor,
        table: Option<&Tensor>,
        kept: Option<(usize, usize)>,
    ) -> Result<Tensor> {
        let l = self.latent;
        let keep = |t: &Tensor| -> Result<Tensor> {
            Ok(match kept {
                Some((start, len)) => t.narrow(1, start, len)?.contiguous()?,
                None => t.clone(),
            })
        };
        let h = self.self_norm.forward(x, table, false)?;
        let qkv = product(&h, &self.qkv.weight)?;
        let attended = fused::attention(&keep(&qkv)?, &qkv, &self.qkv.bias, self.attention_op(l))?;
        let out = product(&attended, &self.self_out.weight)?;
        let mut y = fused::residual(&keep(x)?, &out, &self.self_out.bias)?;
        if let Some(cross) = &self.cross {
            let queries = product(&cross.norm.forward(&y, table, false)?, &cross.query)?;
            let keys = product(&cross.other_norm.forward(x, table, true)?, &cross.key_value)?;
            let attended = fused::attention(&queries, &keys, &cross.bias, self.attention_op(0))?;
            y = fused::residual(&y, &product(&attended, &cross.out.weight)?, &cross.out.bias)?;
        }
        let h = self.ff_norm.forward(&y, table, false)?;
        let hidden = fused::bias(&product(&h, &self.up.weight)?, &self.up.bias, true)?;
        Ok(fused::residual(&y, &product(&hidden, &self.down.weight)?, &self.down.bias)?)
    }
}

/// The denoiser for inference (see [`Denoiser`]).
#[derive(Debug, Clone)]
struct FastDenoiser {
    input: PackedMatrix,
    /// The input bias, positions and prefix/noisy types of each frame, `[T, latent]`.
    tokens: Tensor,
    channel_mask: Option<Tensor>,
    blocks: Vec<Block>,
    /// Every AdaLN modulation side by side.
    modulations: Linear,
    final_column: usize,
    head: Linear,
    prefix_frames: usize,
    predicted_frames: usize,
}

impl FastDenoiser {
    fn new(denoiser: &Denoiser) -> Result<Self> {
        let tokens = denoiser.frame_embedding()?.broadcast_add(&denoiser.input.bias)?.detach();
        let mut table = TableBuilder::default();
        let blocks =
            denoiser.blocks.iter().map(|b| Block::new(b, &mut table)).collect::<Result<_>>()?;
        let final_column = table.add(&denoiser.final_modulation);
        let modulations = table.finish()?.expect("the final modulation at least");
        Ok(Self {
            input: PackedMatrix::new(&denoiser.input.weight)?,
            tokens,
            channel_mask: denoiser.channel_mask.as_ref().map(Tensor::detach),
            blocks,
            modulations,
            final_column,
            head: Linear::of(&denoiser.head)?,
            prefix_frames: denoiser.prefix_frames,
            predicted_frames: denoiser.predicted_frames,
        })
    }

    /// # Shapes
    /// - `frames`: `[N, T_p + T_f, features]`; `condition`: `[N, latent]`
    /// - returns `[N, T_f, features]`
    fn forward(&self, frames: &Tensor, condition: &Tensor) -> Result<Tensor> {
        let frames = match &self.channel_mask {
            Some(mask) => frames.broadcast_mul(mask)?,
            None => frames.clone(),
        };
        let mut x = product(&frames, &self.input)?.broadcast_add(&self.tokens)?;
        let table = self.modulations.forward(&condition.silu()?)?;
        let predicted = (self.prefix_frames, self.predicted_frames);
        let Some((last, blocks)) = self.blocks.split_last() else {
            return Err(crate::error::ModelError::shape("denoiser", "at least one block", &[]));
        };
        for block in blocks {
            x = block.forward(&x, Some(&table), None)?;
        }
        // The head reads the predicted frames only: the last block computes just those.
        let predicted = last.forward(&x, Some(&table), Some(predicted))?;
        self.head.forward(&fused::adaln(&predicted, &table, self.final_column, false)?)
    }
}

/// The body fusion for inference (see [`Fusion`]): the Motion Fusion Network's blocks; its
/// input and output layers, and the average, are the model's own.
#[derive(Debug, Clone)]
enum FastFusion {
    Network { input: Linear, blocks: Vec<Block>, output: Linear },
    Average,
}

impl FastFusion {
    fn new(fusion: &Fusion) -> Result<Self> {
        Ok(match fusion {
            Fusion::Network(network) => {
                let mut table = TableBuilder::default();
                let blocks = network.layers.blocks.iter().map(|b| Block::new(b, &mut table));
                Self::Network {
                    input: Linear::of(&network.input)?,
                    blocks: blocks.collect::<Result<_>>()?,
                    output: Linear::of(&network.output)?,
                }
            }
            Fusion::Average => Self::Average,
        })
    }

    /// # Shapes
    /// - `body_a`, `body_b`: `[batch, T_f, 6J + 3]`; `presence_b`: `[batch]`
    /// - returns the fused body `[batch, T_f, 6J + 3]`
    fn forward(
        &self,
        fusion: &Fusion,
        body_a: &Tensor,
        body_b: &Tensor,
        presence_b: &Tensor,
    ) -> Result<Tensor> {
        match (self, fusion) {
            (Self::Network { input, blocks, output }, Fusion::Network(network)) => {
                let layers = FusionLayers {
                    input: |x: &Tensor| input.forward(x),
                    encode: |x: &Tensor| {
                        let mut x = x.clone();
                        for block in blocks {
                            x = block.forward(&x, None, None)?;
                        }
                        Ok(fused::layer_norm(&x)?)
                    },
                    output: |x: &Tensor| output.forward(x),
                };
                network.fuse(body_a, body_b, presence_b, layers)
            }
            _ => present_average(body_a, body_b, presence_b),
        }
    }
}

/// The layouts' inference paths.
#[derive(Debug, Clone)]
enum FastLayout {
    Dual { denoiser: FastDenoiser, fusion: FastFusion },
    Single { denoiser: FastDenoiser },
}

/// What a window's samples are conditioned on, with the part of the condition embedding that
/// does not change over the diffusion steps computed once.
#[derive(Debug, Clone)]
pub struct PreparedCondition {
    text: Tensor,
    bps: Tensor,
    presence: Tensor,
    elapsed: Option<Tensor>,
    object_start: Option<Tensor>,
    settled: Option<Tensor>,
    reach: Option<Tensor>,
    /// The timestep-independent part of the condition embedding: `[2 batch, latent]` in the
    /// dual layout (stream A first), `[batch, latent]` in the single one.
    fixed: Tensor,
}

impl PreparedCondition {
    /// The rows of the batch.
    pub fn batch(&self) -> usize {
        self.text.dims()[0]
    }

    /// Rows `start..start + len` of the batch.
    fn rows(&self, start: usize, len: usize) -> Result<Self> {
        let batch = self.batch();
        let latent = self.fixed.dim(1)?;
        // `fixed` holds `streams` blocks of `batch` rows (stream A's block first).
        let streams = self.fixed.dim(0)? / batch.max(1);
        Ok(Self {
            text: self.text.narrow(0, start, len)?,
            bps: self.bps.narrow(0, start, len)?,
            presence: self.presence.narrow(0, start, len)?,
            elapsed: self.elapsed.as_ref().map(|e| e.narrow(0, start, len)).transpose()?,
            object_start: self
                .object_start
                .as_ref()
                .map(|s| s.narrow(0, start, len))
                .transpose()?,
            settled: self.settled.as_ref().map(|s| s.narrow(0, start, len)).transpose()?,
            reach: self.reach.as_ref().map(|r| r.narrow(0, start, len)).transpose()?,
            fixed: self
                .fixed
                .reshape((streams, batch, latent))?
                .narrow(1, start, len)?
                .reshape((streams * len, latent))?,
        })
    }
}

/// The model for sampling (see the module's docs).
#[derive(Debug, Clone)]
pub struct InferenceModel {
    model: Model,
    /// `None` where the fused operations do not apply (another device or dtype).
    fast: Option<Fast>,
}

/// The inference path's layers: the layout's and the timestep MLP's.
#[derive(Debug, Clone)]
struct Fast {
    layout: FastLayout,
    time_in: Linear,
    time_out: Linear,
}

impl InferenceModel {
    /// Rearranges `model`'s parameters for inference (a snapshot of their current values).
    pub fn new(model: &Model) -> Result<Self> {
        let on_cpu = matches!(model.device(), Device::Cpu) && model.dtype() == DType::F32;
        let fast = if on_cpu {
            let (layout, conditioning) = match &model.layout {
                Layout::Dual(DualStream { denoiser, fusion, conditioning, .. }) => {
                    let denoiser = FastDenoiser::new(denoiser)?;
                    (FastLayout::Dual { denoiser, fusion: FastFusion::new(fusion)? }, conditioning)
                }
                Layout::Single(SingleStream { denoiser, conditioning, .. }) => {
                    (FastLayout::Single { denoiser: FastDenoiser::new(denoiser)? }, conditioning)
                }
            };
            Some(Fast {
                layout,
                time_in: Linear::of(&conditioning.time_in)?,
                time_out: Linear::of(&conditioning.time_out)?,
            })
        } else {
            None
        };
        Ok(Self { model: model.clone(), fast })
    }

    /// The composite model.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The configuration.
    pub fn config(&self) -> &super::ModelConfig {
        self.model.config()
    }

    /// The floating-point type of the parameters.
    pub fn dtype(&self) -> DType {
        self.model.dtype()
    }

    /// Whether the fused CPU operations run (f32 on the CPU).
    pub fn is_fused(&self) -> bool {
        self.fast.is_some()
    }

    /// Computes once what the condition of a window's samples needs at every step.
    ///
    /// # Shapes
    /// - `text`: `[batch, text_embedding]` (zero rows are the null condition); `bps`:
    ///   `[batch, 2, bps_points * 3]`; `presence`: `[batch, 2]`; `prompt`: `[batch]` and
    ///   `[batch, 2, D]` and `[batch, 2]` and `[batch, 2, D]` (see [`ModelInput::elapsed`],
    ///   [`ModelInput::object_start`], [`ModelInput::settled`] and [`ModelInput::reach`]);
    ///   `prefix`: `[batch, 2, T_p, D]`, the prefix the window's steps will see (read by an
    ///   object start from the prefix)
    pub fn prepare(
        &self,
        text: &Tensor,
        bps: &Tensor,
        presence: &Tensor,
        prompt: PromptState<'_>,
        prefix: &Tensor,
    ) -> Result<PreparedCondition> {
        let dtype = self.model.dtype();
        let fixed = match &self.model.layout {
            Layout::Dual(dual) => {
                dual.fixed_condition(text, bps, presence, prompt, prefix, dtype)?
            }
            Layout::Single(single) => {
                single.fixed_condition(text, bps, presence, prompt, prefix, dtype)?
            }
        };
        Ok(PreparedCondition {
            text: text.detach(),
            bps: bps.detach(),
            presence: presence.detach(),
            elapsed: prompt.elapsed.map(Tensor::detach),
            object_start: prompt.object_start.map(Tensor::detach),
            settled: prompt.settled.map(Tensor::detach),
            reach: prompt.reach.map(Tensor::detach),
            fixed: fixed.detach(),
        })
    }

    /// The clean predicted frames of both streams (x0), as [`Model::forward`] without
    /// dropout and with every frame valid.
    ///
    /// # Shapes
    /// - `prefix`: `[batch, 2, T_p, D]`; `noisy`: `[batch, 2, T_f, D]`; `timesteps`: `[batch]`
    /// - returns `[batch, 2, T_f, D]`
    pub fn forward(
        &self,
        prefix: &Tensor,
        noisy: &Tensor,
        timesteps: &Tensor,
        condition: &PreparedCondition,
    ) -> Result<Tensor> {
        self.model.check_input(&self.input(prefix, noisy, timesteps, condition))?;
        let batch = noisy.dim(0)?;
        let threads = rayon::current_num_threads();
        // The rows of the batch are independent samples (the conditional and null rows of
        // guidance among them): one group of rows per thread, each forward pass on its own
        // thread with its products on that thread, instead of every operation split over the
        // threads. At sampling sizes (a few hundred tokens) the per-operation hand-offs between
        // threads cost more than the products they split. With fewer rows than threads every
        // operation is split as before, so that no thread idles.
        let parts = if self.fast.is_some() && batch >= threads { threads } else { 1 };
        if parts <= 1 {
            return self.forward_rows(prefix, noisy, timesteps, condition);
        }
        let bounds: Vec<(usize, usize)> = super::row_groups(batch, parts).collect();
        let outputs = bounds
            .into_par_iter()
            .map(|(start, len)| {
                crate::matmul::in_row_group(|| {
                    self.forward_rows(
                        &prefix.narrow(0, start, len)?,
                        &noisy.narrow(0, start, len)?,
                        &timesteps.narrow(0, start, len)?,
                        &condition.rows(start, len)?,
                    )
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Tensor::cat(&outputs, 0)?)
    }

    /// The composite model's input for these tensors.
    fn input<'a>(
        &self,
        prefix: &'a Tensor,
        noisy: &'a Tensor,
        timesteps: &'a Tensor,
        condition: &'a PreparedCondition,
    ) -> ModelInput<'a> {
        ModelInput {
            noisy,
            prefix,
            timesteps,
            text: &condition.text,
            bps: &condition.bps,
            presence: &condition.presence,
            frame_mask: None,
            elapsed: condition.elapsed.as_ref(),
            object_start: condition.object_start.as_ref(),
            settled: condition.settled.as_ref(),
            reach: condition.reach.as_ref(),
        }
    }

    /// [`Self::forward`] on one group of rows (the whole input already checked).
    fn forward_rows(
        &self,
        prefix: &Tensor,
        noisy: &Tensor,
        timesteps: &Tensor,
        condition: &PreparedCondition,
    ) -> Result<Tensor> {
        let input = self.input(prefix, noisy, timesteps, condition);
        let dtype = self.model.dtype();
        let Some(fast) = &self.fast else { return self.model.forward(&input, None) };
        let tokens = self.model.token_prefix(
            prefix,
            condition.object_start.as_ref(),
            condition.reach.as_ref(),
        )?;
        let time_in = |x: &Tensor| fast.time_in.forward(x);
        let time_out = |x: &Tensor| fast.time_out.forward(x);
        let head = match (&fast.layout, &self.model.layout) {
            (FastLayout::Dual { denoiser, fusion }, Layout::Dual(dual)) => {
                let frames = streams_into_batch(&Tensor::cat(&[&tokens, noisy], 2)?)?;
                let timesteps = Tensor::cat(&[timesteps, timesteps], 0)?;
                let time = dual.conditioning.time_with(&timesteps, dtype, time_in, time_out)?;
                let out = denoiser.forward(&frames, &(time + &condition.fixed)?)?;
                dual.assemble(&out, &condition.presence, |a, b, presence_b| {
                    fusion.forward(&dual.fusion, a, b, presence_b)
                })
            }
            (FastLayout::Single { denoiser }, Layout::Single(single)) => {
                let frames = single.frames(&tokens, noisy)?;
                let time = single.conditioning.time_with(timesteps, dtype, time_in, time_out)?;
                single.split(&denoiser.forward(&frames, &(time + &condition.fixed)?)?)
            }
            _ => unreachable!("the inference layout is built from the model's"),
        }?;
        self.model.add_prefix_residual(head, prefix)
    }
}
