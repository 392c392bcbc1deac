//! Building blocks, all made of operations with a backward pass (candle's fused `layer_norm` and
//! `softmax_last_dim` have none; ours, in [`crate::differentiable`], do): layer norm without
//! affine parameters, AdaLN modulation, multi-head attention, feed-forward, dropout from an
//! explicit random stream, and the sinusoidal timestep embedding. The transformer block built from them is in
//! [`crate::transformer`].

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{VarBuilder, init::Init};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

pub use crate::differentiable::Activation;
use crate::error::Result;
pub use crate::kernel::LAYER_NORM_EPS;

/// Layer norm over the last dimension without affine parameters, [`LAYER_NORM_EPS`]: fused with a
/// hand-written backward pass on the CPU and a GPU ([`crate::differentiable`]), composed elsewhere.
///
/// # Shapes
/// - `x`: `[..., features]`; returns the same shape
pub fn layer_norm(x: &Tensor) -> Result<Tensor> {
    if crate::differentiable::applies_per_row(x) {
        return Ok(crate::differentiable::layer_norm(x)?);
    }
    layer_norm_composite(x)
}

/// [`layer_norm`] composed of candle operations (any device).
pub fn layer_norm_composite(x: &Tensor) -> Result<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let centred = x.broadcast_sub(&mean)?;
    let variance = centred.sqr()?.mean_keepdim(D::Minus1)?;
    Ok(centred.broadcast_div(&(variance + LAYER_NORM_EPS)?.sqrt()?)?)
}

/// Softmax over the last dimension, composed of candle operations: the composite attention's
/// where [`crate::differentiable::masked_softmax`] does not apply (the CPU's fused attention has
/// its softmax inside; candle's fused `softmax_last_dim` has no backward pass).
pub fn softmax(x: &Tensor) -> Result<Tensor> {
    Ok(candle_nn::ops::softmax(x, D::Minus1)?)
}

/// A linear layer whose weight is stored `[input, output]`, so that the product needs no
/// transposed operand (about a quarter faster on the CPU than candle's `[output, input]`), and
/// whose leading dimensions are flattened into one matrix product.
#[derive(Debug, Clone)]
pub struct Dense {
    pub(crate) weight: Tensor,
    pub(crate) bias: Tensor,
}

/// A [`Dense`] layer initialised like PyTorch's `nn.Linear` (Kaiming-uniform weight, uniform
/// bias in `+-1/sqrt(input)`).
pub fn dense(input: usize, output: usize, vb: VarBuilder<'_>) -> Result<Dense> {
    // Stored [input, output]: the fan-in is the first dimension.
    let kaiming = Init::Kaiming {
        dist: candle_nn::init::NormalOrUniform::Uniform,
        fan: candle_nn::init::FanInOut::FanOut,
        non_linearity: candle_nn::init::NonLinearity::ExplicitGain(1.0 / 3f64.sqrt()),
    };
    let weight = vb.get_with_hints((input, output), "weight", kaiming)?;
    let bound = 1.0 / (input as f64).sqrt();
    let bias = vb.get_with_hints(output, "bias", Init::Uniform { lo: -bound, up: bound })?;
    Ok(Dense { weight, bias })
}

/// A [`Dense`] layer whose weight and bias start at zero (AdaLN modulations and output heads,
/// so that every block starts as the identity and the model starts predicting zeros).
pub fn zero_dense(input: usize, output: usize, vb: VarBuilder<'_>) -> Result<Dense> {
    let weight = vb.get_with_hints((input, output), "weight", Init::Const(0.0))?;
    let bias = vb.get_with_hints(output, "bias", Init::Const(0.0))?;
    Ok(Dense { weight, bias })
}

impl Dense {
    /// # Shapes
    /// - `x`: `[..., input]`; returns `[..., output]`
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_with(x, Activation::Identity)
    }

    /// `act(x W + b)`: one fused operation with a hand-written backward pass on the CPU
    /// ([`crate::differentiable::linear`]), composed elsewhere.
    ///
    /// # Shapes
    /// - `x`: `[..., input]`; returns `[..., output]`
    pub fn forward_with(&self, x: &Tensor, activation: Activation) -> Result<Tensor> {
        if crate::differentiable::applies(x) {
            return Ok(crate::differentiable::linear(x, &self.weight, &self.bias, activation)?);
        }
        let dims = x.dims();
        let input = dims[dims.len() - 1];
        let rows = x.elem_count() / input.max(1);
        let flat = x.contiguous()?.reshape((rows, input))?;
        let biased = flat.matmul(&self.weight)?.broadcast_add(&self.bias)?;
        let out = match activation {
            Activation::Identity => biased,
            Activation::Silu => biased.silu()?,
        };
        let mut shape = dims.to_vec();
        *shape.last_mut().expect("a non-scalar input") = self.weight.dims()[1];
        Ok(out.reshape(shape)?)
    }
}

/// Dropout with a mask drawn from `rng` (training) or the identity (`rng` is `None`).
///
/// On the CPU the mask's draws come from `rng` itself. Elsewhere they are drawn on the device
/// by its own generator, seeded by one draw of `rng`: a mask drawn on the host and uploaded
/// costs a host draw per element (about a second a step for the `paper` preset on a GPU). The
/// masks then depend on the device, but the same step of the same run draws the same ones.
pub fn dropout(x: &Tensor, p: f64, rng: Option<&mut ChaCha8Rng>) -> Result<Tensor> {
    let Some(rng) = rng else { return Ok(x.clone()) };
    if p <= 0.0 {
        return Ok(x.clone());
    }
    let keep = 1.0 - p;
    if !x.device().is_cpu() {
        x.device().set_seed(rng.random())?;
        let uniform = Tensor::rand(0f32, 1f32, x.shape(), x.device())?;
        let mask = uniform.lt(keep)?.to_dtype(x.dtype())?.affine(1.0 / keep, 0.0)?;
        return Ok((x * mask)?);
    }
    let mask: Vec<f32> = (0..x.elem_count())
        .map(|_| if rng.random::<f64>() < keep { (1.0 / keep) as f32 } else { 0.0 })
        .collect();
    let mask = Tensor::from_vec(mask, x.shape(), x.device())?.to_dtype(x.dtype())?;
    Ok((x * mask)?)
}

/// AdaLN: `norm(x) * (1 + scale) + shift` with `(shift, scale) = Dense(SiLU(emb))`, the linear
/// layer zero-initialised.
#[derive(Debug, Clone)]
pub struct Modulation {
    pub(crate) linear: Dense,
}

impl Modulation {
    /// A modulation for `latent`-wide tokens and conditions.
    pub fn new(latent: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Self { linear: zero_dense(latent, 2 * latent, vb)? })
    }

    /// # Shapes
    /// - `x`: `[batch, frames, latent]`; `emb`: `[batch, latent]`; returns `x`'s shape
    pub fn forward(&self, x: &Tensor, emb: &Tensor) -> Result<Tensor> {
        let (_, _, latent) = x.dims3()?;
        let params = self.linear.forward(&emb.silu()?)?;
        if crate::differentiable::applies_per_row(x) {
            return Ok(crate::differentiable::modulate(x, &params)?);
        }
        let params = params.unsqueeze(1)?;
        let shift = params.narrow(D::Minus1, 0, latent)?;
        let scale = params.narrow(D::Minus1, latent, latent)?;
        Ok(layer_norm(x)?.broadcast_mul(&(scale + 1.0)?)?.broadcast_add(&shift)?)
    }
}

/// Multi-head attention.
#[derive(Debug, Clone)]
pub struct Attention {
    pub(crate) query: Dense,
    /// Keys and values in one product, `[latent, 2 latent]`: one larger matrix product runs
    /// faster than two.
    pub(crate) key_value: Dense,
    pub(crate) out: Dense,
    pub(crate) heads: usize,
}

impl Attention {
    /// Attention over `latent`-wide tokens with `heads` heads.
    pub fn new(latent: usize, heads: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Self {
            query: dense(latent, latent, vb.pp("query"))?,
            key_value: dense(latent, 2 * latent, vb.pp("key_value"))?,
            out: dense(latent, latent, vb.pp("out"))?,
            heads,
        })
    }

    fn split_heads(&self, x: &Tensor) -> Result<Tensor> {
        let (batch, frames, latent) = x.dims3()?;
        Ok(x.reshape((batch, frames, self.heads, latent / self.heads))?
            .transpose(1, 2)?
            .contiguous()?)
    }

    /// Attention of `queries` to `keys` (which also give the values); `key_mask` (1 = attend,
    /// 0 = ignore) masks keys such as padding frames.
    ///
    /// # Shapes
    /// - `queries`: `[batch, query_frames, latent]`; `keys`: `[batch, key_frames, latent]`
    /// - `key_mask`: `[batch, key_frames]`
    /// - returns `[batch, query_frames, latent]`
    pub fn forward(
        &self,
        queries: &Tensor,
        keys: &Tensor,
        key_mask: Option<&Tensor>,
    ) -> Result<Tensor> {
        let (batch, query_frames, latent) = queries.dims3()?;
        let head = latent / self.heads;
        let q = self.query.forward(queries)?;
        let key_value = self.key_value.forward(keys)?;
        // The fused operations take a mask always: all ones when none is given.
        let mask = |like: &Tensor| -> Result<Tensor> {
            Ok(match key_mask {
                Some(mask) => mask.clone(),
                None => Tensor::ones((batch, keys.dims3()?.1), like.dtype(), like.device())?,
            })
        };
        if crate::differentiable::applies(&q) {
            let attended =
                crate::differentiable::attention(&q, &key_value, &mask(&q)?, self.heads)?;
            return self.out.forward(&attended);
        }
        let q = self.split_heads(&q)?;
        let k = self.split_heads(&key_value.narrow(2, 0, latent)?)?;
        let v = self.split_heads(&key_value.narrow(2, latent, latent)?)?;
        let scores = (q.matmul(&k.transpose(2, 3)?.contiguous()?)? / (head as f64).sqrt())?;
        let weights = if crate::differentiable::applies_per_row(&scores) {
            crate::differentiable::masked_softmax(&scores, &mask(&scores)?)?
        } else if let Some(mask) = key_mask {
            // 0 where attended, -1e9 where masked, broadcast over heads and queries.
            let bias =
                ((mask.to_dtype(scores.dtype())? - 1.0)? * 1e9)?.unsqueeze(1)?.unsqueeze(1)?;
            softmax(&scores.broadcast_add(&bias)?)?
        } else {
            softmax(&scores)?
        };
        let attended = weights.matmul(&v)?;
        let merged =
            attended.transpose(1, 2)?.contiguous()?.reshape((batch, query_frames, latent))?;
        self.out.forward(&merged)
    }
}

/// Two linear layers with a SiLU between (SiLU rather than MDM's GELU: as smooth, and on the
/// CPU candle's SiLU is about six times faster than its tanh-based GELU, a third of the
/// sampling time otherwise).
#[derive(Debug, Clone)]
pub struct FeedForward {
    pub(crate) up: Dense,
    pub(crate) down: Dense,
}

impl FeedForward {
    /// `latent -> hidden -> latent`.
    pub fn new(latent: usize, hidden: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Self {
            up: dense(latent, hidden, vb.pp("up"))?,
            down: dense(hidden, latent, vb.pp("down"))?,
        })
    }

    /// # Shapes
    /// - `x`: `[..., latent]`; returns the same shape
    pub fn forward(&self, x: &Tensor, p: f64, rng: Option<&mut ChaCha8Rng>) -> Result<Tensor> {
        let hidden = dropout(&self.up.forward_with(x, Activation::Silu)?, p, rng)?;
        self.down.forward(&hidden)
    }
}

/// Sinusoidal embedding of diffusion timesteps (`[sin(t f_k), cos(t f_k)]`,
/// `f_k = 10000^(-k / (dim/2))`).
///
/// # Shapes
/// - `timesteps`: `[batch]` (any numeric dtype); returns `[batch, dim]`
pub fn timestep_embedding(
    timesteps: &Tensor,
    dim: usize,
    dtype: DType,
    device: &Device,
) -> Result<Tensor> {
    let t: Vec<f64> = timesteps.to_dtype(DType::F64)?.to_vec1()?;
    let half = dim / 2;
    let mut values = Vec::with_capacity(t.len() * dim);
    for step in &t {
        for k in 0..dim {
            let frequency =
                (-(10000f64.ln()) * (k % half.max(1)) as f64 / half.max(1) as f64).exp();
            values.push(if k < half { (step * frequency).sin() } else { (step * frequency).cos() });
        }
    }
    Ok(Tensor::from_vec(values, (t.len(), dim), device)?.to_dtype(dtype)?)
}
