#!/usr/bin/env python3
"""A PyTorch reference implementation of dex2hoi's denoiser, for benchmarking only.

It is not part of dex2hoi and is not used for training or sampling: it exists so that
dex2hoi's speed on the CPU can be compared with PyTorch doing the same work on the same
machine. Run it through `cargo xtask bench compare` (see bench/README.md) or directly:

    python3 bench/torch_reference.py [--presets small,paper] [--threads 2] [--quick]

With `--device cuda` the same work runs on an NVIDIA GPU (f32 throughout, PyTorch's default
TF32 setting kept), every timed region bracketed by `torch.cuda.synchronize()`.

It mirrors these Rust sources, which are the specification:

- crates/dex2hoi-model/src/model.rs: Model (dual layout), Conditioning, Denoiser (frame tokens,
  positions, frame types), swap_streams, streams_into_batch, FusionNetwork, body_average
- crates/dex2hoi-model/src/transformer.rs: the pre-norm TransformerBlock (AdaLN or plain layer
  norm, optional cross-attention to the other stream) and TransformerEncoder
- crates/dex2hoi-model/src/layers.rs: layer_norm, Dense (weight stored [input, output]),
  Modulation, Attention (query and fused key_value), FeedForward, timestep_embedding
- crates/dex2hoi-model/src/config.rs with configs/{small,paper}.toml: the `[model]` table
- crates/dex2hoi-data/src/layout.rs: the per-stream feature layout (6J + 3 body, 18 object)
- crates/dex2hoi-diffusion/src/{schedule,sampler}.rs: the cosine schedule, respacing, DDIM with
  classifier-free guidance (conditional and null rows in one batch)
- crates/dex2hoi-sample/benches/sample.rs: the FLOP count and the sampling benchmark's setup
- crates/dex2hoi-optim/src/{config,adamw,ema}.rs: AdamW, gradient clipping, EMA settings
- crates/dex2hoi-train/src/loss.rs: L_diff (the body counted once, each object in its stream)

Only the dual stream layout with the fusion network and hand-relative objects (the `small` and
`paper` presets) is implemented. Parameter names mirror the Rust module tree, so the weights
written by crates/dex2hoi-sample/benches/reference.rs load by name, and the forward pass on
the inputs stored there must reproduce dex2hoi's output to 1e-4.

Needs only torch and numpy. Each measurement whose peak memory is reported runs in its own
process (the script re-invokes itself with `--case`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import signal
import struct
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# --- configuration ---------------------------------------------------------------------------

ROTATION_FEATURES = 6  # a 6D rotation per joint
ROOT_FEATURES = 3  # the root displacement
OBJECT_FEATURES = 18  # one object slot's channels
# Channels of an object slot predicted as clean values by the world-frame residual head: the
# offsets in the two wrist frames and the mixture logits (LEFT_OFFSET_RANGE, RIGHT_OFFSET_RANGE,
# MIXTURE_RANGE of crates/dex2hoi-repr/src/object_repr.rs).
HAND_RELATIVE_CHANNELS = (*range(6, 9), *range(9, 12), *range(15, 18))
PREDICTIONS = ("absolute", "prefix_residual", "prefix_residual_world")
DIFFUSION_STEPS = 1000  # DEFAULT_DIFFUSION_STEPS of schedule.rs
SAMPLING_STEPS = 50  # SamplerConfig::default()
GUIDANCE = 2.0  # SamplerConfig::default() (dex2hoi_diffusion::DEFAULT_GUIDANCE)
TOLERANCE = 1e-4  # largest accepted |torch - dex2hoi| on the reference batch

# OptimizerConfig::default() of crates/dex2hoi-optim/src/config.rs (the learning rate is the
# `small` preset's).
LEARNING_RATE = 2e-4
BETAS = (0.9, 0.999)
EPSILON = 1e-8
WEIGHT_DECAY = 0.01  # on matrices (rank >= 2) only, as Parameter::decays
GRADIENT_CLIP = 1.0
EMA_DECAY = 0.999
TRAIN_BATCH = 32


@dataclass(frozen=True)
class Config:
    """The `[model]` table of a preset (ModelConfig of config.rs)."""

    joints: int
    latent: int
    layers: int
    heads: int
    feed_forward: int
    fusion_layers: int
    dropout: float
    prefix_frames: int
    predicted_frames: int
    text_embedding: int
    bps_points: int
    object_representation: str
    stream_layout: str
    body_fusion: str
    prediction: str

    @classmethod
    def preset(cls, root: Path, name: str) -> Config:
        path = root / "configs" / f"{name}.toml"
        if not path.exists():
            known = ", ".join(sorted(p.stem for p in path.parent.glob("*.toml")))
            raise SystemExit(f"no preset {name!r} in {path.parent} (known: {known})")
        with open(path, "rb") as f:
            table = tomllib.load(f).get("model")
        if table is None:
            raise SystemExit(f"{path}: no [model] table")
        names = {f.name for f in fields(cls)}
        unknown, missing = set(table) - names, names - set(table)
        if unknown or missing:
            raise SystemExit(f"{path}: unknown {sorted(unknown)}, missing {sorted(missing)}")
        cfg = cls(**table)
        cfg.validate(path)
        return cfg

    def validate(self, where: Path) -> None:
        unsupported = {
            "stream_layout": (self.stream_layout, "dual"),
            "body_fusion": (self.body_fusion, "network"),
            "object_representation": (self.object_representation, "hand_relative"),
        }
        for field, (value, supported) in unsupported.items():
            if value != supported:
                raise SystemExit(
                    f"{where}: {field} = {value!r} is not implemented by this reference "
                    f"(only {supported!r}: the small and paper presets)"
                )
        if self.prediction not in PREDICTIONS:
            raise SystemExit(f"{where}: prediction {self.prediction!r} is not one of {PREDICTIONS}")
        if self.latent % self.heads != 0:
            raise SystemExit(f"{where}: heads {self.heads} does not divide latent {self.latent}")
        if not 0.0 <= self.dropout < 1.0:
            raise SystemExit(f"{where}: dropout {self.dropout} is not in [0, 1)")
        if self.fusion_layers == 0:
            raise SystemExit(f"{where}: the fusion network needs at least one layer")

    @property
    def body_features(self) -> int:
        """`6J + 3` (FeatureLayout::body_width)."""
        return ROTATION_FEATURES * self.joints + ROOT_FEATURES

    @property
    def stream_features(self) -> int:
        """`6J + 3 + 18` (FeatureLayout::stream_width), the model's `D`."""
        return self.body_features + OBJECT_FEATURES

    @property
    def window_frames(self) -> int:
        return self.prefix_frames + self.predicted_frames


def flops_per_forward(c: Config, batch: int) -> float:
    """Multiply-adds x 2 of one forward pass (benches/sample.rs, ported as is)."""
    t, tf, l, ff = (
        float(c.window_frames),
        float(c.predicted_frames),
        float(c.latent),
        float(c.feed_forward),
    )
    dual = c.stream_layout == "dual"
    streams = 2.0 if dual else 1.0

    def attention(tokens: float) -> float:
        return 4.0 * tokens * l * l * 2.0 + 2.0 * tokens * tokens * l * 2.0

    def feed_forward(tokens: float) -> float:
        return 2.0 * tokens * l * ff * 2.0

    cross = attention(t) if dual else 0.0
    block = attention(t) + cross + feed_forward(t)
    io = 2.0 * t * l * c.stream_features * 2.0
    denoiser = streams * (c.layers * block + io)
    fusion = (
        c.fusion_layers * (attention(tf) + feed_forward(tf))
        if dual and c.body_fusion == "network"
        else 0.0
    )
    return batch * (denoiser + fusion)


# --- layers (layers.rs) ----------------------------------------------------------------------


def layer_norm(x: torch.Tensor) -> torch.Tensor:
    """Layer norm over the last dimension, no affine parameters, eps 1e-6 inside the sqrt."""
    return F.layer_norm(x, (x.shape[-1],), eps=1e-6)


def dropout(x: torch.Tensor, p: float, training: bool) -> torch.Tensor:
    """Dropout in training, the identity otherwise (and for p = 0, as dex2hoi)."""
    if not training or p <= 0.0:
        return x
    return F.dropout(x, p, training=True)


def timestep_embedding(timesteps: torch.Tensor, dim: int) -> torch.Tensor:
    """`[sin(t f_k) for k < half, cos(t f_(k - half)) for k >= half]`, `f_k = 10000^(-k/half)`,
    computed in f64 and returned as f32 (as layers.rs)."""
    half = max(dim // 2, 1)
    k = torch.arange(dim, dtype=torch.float64, device=timesteps.device) % half
    frequency = torch.exp(-math.log(10000.0) * k / half)
    angle = timesteps.to(torch.float64)[:, None] * frequency[None, :]
    first = torch.arange(dim, device=timesteps.device) < (dim // 2)
    return torch.where(first, torch.sin(angle), torch.cos(angle)).to(torch.float32)


class Dense(nn.Module):
    """A linear layer whose weight is stored `[input, output]`: `y = x @ W + b`."""

    def __init__(self, inputs: int, outputs: int, zero: bool = False) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(inputs, outputs))
        self.bias = nn.Parameter(torch.empty(outputs))
        if zero:  # zero_dense: AdaLN modulations and output heads
            nn.init.zeros_(self.weight)
            nn.init.zeros_(self.bias)
        else:  # dense: like nn.Linear, uniform in +-1/sqrt(input)
            bound = 1.0 / math.sqrt(inputs)
            nn.init.uniform_(self.weight, -bound, bound)
            nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(-1, x.shape[-1])
        out = torch.addmm(self.bias, flat, self.weight)
        return out.view(*x.shape[:-1], self.weight.shape[1])


class Modulation(Dense):
    """AdaLN: `layer_norm(x) * (1 + scale) + shift` with `(shift, scale) = Dense(SiLU(emb))`.
    The zero-initialised linear layer's parameters sit directly under the modulation's name
    (`blocks.0.self_modulation.weight`), as in the Rust module."""

    def __init__(self, latent: int) -> None:
        super().__init__(latent, 2 * latent, zero=True)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        params = super().forward(F.silu(emb)).unsqueeze(1)  # [batch, 1, 2 latent]
        shift, scale = params.chunk(2, dim=-1)
        return layer_norm(x) * (1.0 + scale) + shift


class Attention(nn.Module):
    """Multi-head attention with a separate query and a fused key_value `[latent, 2 latent]`
    (keys first, values second); `softmax(q k^T / sqrt(head)) v`, then `out`."""

    def __init__(self, latent: int, heads: int) -> None:
        super().__init__()
        self.query = Dense(latent, latent)
        self.key_value = Dense(latent, 2 * latent)
        self.out = Dense(latent, latent)
        self.heads = heads

    def split_heads(self, x: torch.Tensor) -> torch.Tensor:
        batch, frames, latent = x.shape
        return x.view(batch, frames, self.heads, latent // self.heads).transpose(1, 2)

    def forward(
        self, queries: torch.Tensor, keys: torch.Tensor, key_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        batch, query_frames, latent = queries.shape
        q = self.split_heads(self.query(queries))
        k, v = (self.split_heads(part) for part in self.key_value(keys).chunk(2, dim=-1))
        bias = None
        if key_mask is not None:  # 0 where attended, -1e9 where masked
            bias = ((key_mask.to(q.dtype) - 1.0) * 1e9)[:, None, None, :]
        # The default scale is 1 / sqrt(head), as dex2hoi's.
        attended = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        merged = attended.transpose(1, 2).reshape(batch, query_frames, latent)
        return self.out(merged)


class FeedForward(nn.Module):
    """`down(SiLU(up(x)))`, dropout on the hidden layer in training."""

    def __init__(self, latent: int, hidden: int) -> None:
        super().__init__()
        self.up = Dense(latent, hidden)
        self.down = Dense(hidden, latent)

    def forward(self, x: torch.Tensor, p: float) -> torch.Tensor:
        return self.down(dropout(F.silu(self.up(x)), p, self.training))


# --- the transformer (transformer.rs) ---------------------------------------------------------


def pre_norm(
    modulation: Modulation | None, x: torch.Tensor, condition: torch.Tensor | None
) -> torch.Tensor:
    """PreNorm: plain layer norm, or AdaLN under `condition`."""
    if modulation is None:
        return layer_norm(x)
    if condition is None:
        raise ValueError("an AdaLN block needs a condition")
    return modulation(x, condition)


class TransformerBlock(nn.Module):
    """`x + SA(norm(x))`, then `x + CA(norm(x), norm'(other))` when configured, then
    `x + FF(norm(x))`, dropout on each residual branch. With AdaLN the parameters are
    `self_modulation`, `self_attention`, `cross_modulation`, `cross_other_modulation`,
    `cross_attention`, `ff_modulation`, `feed_forward`; with plain layer norm `attention`,
    `feed_forward` (and `cross_attention`)."""

    def __init__(
        self,
        latent: int,
        heads: int,
        feed_forward: int,
        dropout: float,
        adaptive: bool,
        cross_attention: bool,
    ) -> None:
        super().__init__()

        def modulation() -> Modulation | None:
            return Modulation(latent) if adaptive else None

        self.adaptive = adaptive
        self.dropout = dropout
        self.self_modulation = modulation()
        # The self-attention's name depends on the norm (kept for checkpoints in dex2hoi).
        if adaptive:
            self.self_attention = Attention(latent, heads)
        else:
            self.attention = Attention(latent, heads)
        self.cross_modulation = modulation() if cross_attention else None
        self.cross_other_modulation = modulation() if cross_attention else None
        self.cross_attention = Attention(latent, heads) if cross_attention else None
        self.ff_modulation = modulation()
        self.feed_forward = FeedForward(latent, feed_forward)

    def forward(
        self,
        x: torch.Tensor,
        condition: torch.Tensor | None = None,
        other_tokens: torch.Tensor | None = None,
        other_condition: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        attention = self.self_attention if self.adaptive else self.attention
        h = pre_norm(self.self_modulation, x, condition)
        x = x + dropout(attention(h, h, mask), self.dropout, self.training)
        if (self.cross_attention is None) != (other_tokens is None):
            raise ValueError("another sequence is needed exactly when the block cross-attends")
        if self.cross_attention is not None:
            queries = pre_norm(self.cross_modulation, x, condition)
            # The other stream's tokens are normalised under the other stream's condition.
            keys = pre_norm(self.cross_other_modulation, other_tokens, other_condition)
            attended = self.cross_attention(queries, keys, mask)
            x = x + dropout(attended, self.dropout, self.training)
        h = pre_norm(self.ff_modulation, x, condition)
        out = self.feed_forward(h, self.dropout)
        return x + dropout(out, self.dropout, self.training)


class TransformerEncoder(nn.ModuleList):
    """Plain pre-norm blocks named `0`, `1`, ..., then the final layer norm."""

    def __init__(self, block: Callable[[], TransformerBlock], count: int) -> None:
        super().__init__(block() for _ in range(count))

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        for block in self:
            x = block(x, mask=mask)
        return layer_norm(x)


# --- the model (model.rs) ---------------------------------------------------------------------


def swap_streams(t: torch.Tensor) -> torch.Tensor:
    """`[A; B] -> [B; A]` over the batch dimension."""
    half = t.shape[0] // 2
    return torch.cat([t[half:], t[:half]], dim=0)


def streams_into_batch(t: torch.Tensor) -> torch.Tensor:
    """`[B, 2, ...] -> [2B, ...]`, stream A first."""
    return t.transpose(0, 1).reshape(-1, *t.shape[2:])


def body_average(
    body_a: torch.Tensor, masked_b: torch.Tensor, present: torch.Tensor
) -> torch.Tensor:
    """`(a + p_B b) / (1 + p_B)`."""
    return (body_a + masked_b) / (present + 1.0)


class Conditioning(nn.Module):
    """Timestep MLP + projected text + the stream's object (BPS MLP) + presence flags."""

    def __init__(self, cfg: Config, bps_inputs: int) -> None:
        super().__init__()
        l = cfg.latent
        self.latent = l
        self.time_in = Dense(l, l)
        self.time_out = Dense(l, l)
        self.text = Dense(cfg.text_embedding, l)
        self.bps_in = Dense(bps_inputs, l)
        self.bps_out = Dense(l, l)
        self.presence = Dense(2, l)

    def forward(
        self, timesteps: torch.Tensor, text: torch.Tensor, bps: torch.Tensor, presence: torch.Tensor
    ) -> torch.Tensor:
        time = timestep_embedding(timesteps, self.latent)
        time = self.time_out(F.silu(self.time_in(time)))
        obj = self.bps_out(F.silu(self.bps_in(bps)))
        return time + self.text(text) + obj + self.presence(presence)


class Denoiser(nn.Module):
    """Frame tokens (projection + positions + prefix/noisy type), AdaLN blocks cross-attending
    to the other stream, a final AdaLN and the head. Its parameters sit at the model's root in
    dex2hoi (`blocks.3...`, `head.weight`): see `rust_name`."""

    def __init__(self, cfg: Config, objects: int) -> None:
        super().__init__()
        l = cfg.latent
        features = cfg.body_features + objects * OBJECT_FEATURES
        self.prefix_frames = cfg.prefix_frames
        self.predicted_frames = cfg.predicted_frames
        self.input = Dense(features, l)
        self.positions = nn.Parameter(torch.randn(cfg.window_frames, l) * 0.02)
        self.frame_types = nn.Parameter(torch.randn(2, l) * 0.02)
        self.blocks = nn.ModuleList(
            TransformerBlock(
                l,
                cfg.heads,
                cfg.feed_forward,
                cfg.dropout,
                adaptive=True,
                cross_attention=cfg.stream_layout == "dual",
            )
            for _ in range(cfg.layers)
        )
        self.final_modulation = Modulation(l)
        self.head = Dense(l, features, zero=True)

    def tokens(self, frames: torch.Tensor) -> torch.Tensor:
        latent = self.positions.shape[1]
        types = torch.cat(
            [
                self.frame_types[0].expand(self.prefix_frames, latent),
                self.frame_types[1].expand(self.predicted_frames, latent),
            ]
        )
        return self.input(frames) + (self.positions + types)

    def forward(
        self,
        frames: torch.Tensor,
        condition: torch.Tensor,
        other_condition: torch.Tensor | None,
        mask: torch.Tensor | None,
    ) -> torch.Tensor:
        """`frames` `[batch, T_p + T_f, features]` (with `other_condition`, rows `0..B` are
        stream A and `B..2B` stream B); returns the clean predicted frames."""
        x = self.tokens(frames)
        for block in self.blocks:
            other = swap_streams(x) if other_condition is not None else None
            x = block(x, condition, other, other_condition, mask)
        out = self.head(self.final_modulation(x, condition))
        return out[:, self.prefix_frames : self.prefix_frames + self.predicted_frames]


class FusionNetwork(nn.Module):
    """The Motion Fusion Network: self-attention over both streams' body predictions, predicting
    a correction to their average."""

    def __init__(self, cfg: Config) -> None:
        super().__init__()
        l = cfg.latent
        self.input = Dense(2 * cfg.body_features + 1, l)
        self.positions = nn.Parameter(torch.randn(cfg.predicted_frames, l) * 0.02)
        self.layers = TransformerEncoder(
            lambda: TransformerBlock(
                l, cfg.heads, cfg.feed_forward, cfg.dropout, adaptive=False, cross_attention=False
            ),
            cfg.fusion_layers,
        )
        self.output = Dense(l, cfg.body_features, zero=True)

    def forward(
        self, body_a: torch.Tensor, body_b: torch.Tensor, presence_b: torch.Tensor
    ) -> torch.Tensor:
        batch, frames, _ = body_a.shape
        present = presence_b.reshape(batch, 1, 1)
        masked_b = body_b * present
        flag = present.expand(batch, frames, 1)
        average = body_average(body_a, masked_b, present)
        tokens = self.input(torch.cat([body_a, masked_b, flag], dim=-1))
        x = tokens + self.positions[:frames]
        return average + self.output(self.layers(x))


class DualStream(nn.Module):
    """The dual layout: one stream per object through the shared denoiser, cross-attending to
    each other, then one body from both by the fusion network. This is the whole model for
    the presets this reference supports (Model with Layout::Dual)."""

    def __init__(self, cfg: Config) -> None:
        super().__init__()
        self.cfg = cfg
        self.conditioning = Conditioning(cfg, cfg.bps_points * 3)
        self.denoiser = Denoiser(cfg, objects=1)
        self.fusion = FusionNetwork(cfg)

    def condition(
        self,
        timesteps: torch.Tensor,
        text: torch.Tensor,
        bps: torch.Tensor,
        presence: torch.Tensor,
    ) -> torch.Tensor:
        """Each stream's condition sees its own object's BPS and both presence flags (its own
        first); returns `[2B, latent]`, stream A first."""
        own = streams_into_batch(presence.unsqueeze(2))  # [2B, 1]
        flags = torch.cat([own, swap_streams(own)], dim=1)
        bps = streams_into_batch(bps) * own
        return self.conditioning(
            torch.cat([timesteps, timesteps]), torch.cat([text, text]), bps, flags
        )

    def forward(
        self,
        noisy: torch.Tensor,
        prefix: torch.Tensor,
        timesteps: torch.Tensor,
        text: torch.Tensor,
        bps: torch.Tensor,
        presence: torch.Tensor,
        frame_mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Predicts x0 of both streams, `[B, 2, T_f, D]` (shapes as ModelInput)."""
        frames = streams_into_batch(torch.cat([prefix, noisy], dim=2))
        condition = self.condition(timesteps, text, bps, presence)
        mask = None if frame_mask is None else torch.cat([frame_mask, frame_mask])
        out = self.denoiser(frames, condition, swap_streams(condition), mask)  # [2B, T_f, D]
        batch = out.shape[0] // 2
        body_width = self.cfg.body_features
        stream_a, stream_b = out[:batch], out[batch:]
        body = self.fusion(stream_a[..., :body_width], stream_b[..., :body_width], presence[:, 1])
        with_body = [
            torch.cat([body, stream[..., body_width : body_width + OBJECT_FEATURES]], dim=2)
            for stream in (stream_a, stream_b)
        ]
        return self.add_prefix_residual(torch.stack(with_body, dim=1), prefix)

    def add_prefix_residual(self, head: torch.Tensor, prefix: torch.Tensor) -> torch.Tensor:
        """Model::add_prefix_residual: the residual heads add the last prefix frame (the body of
        stream A to both streams, each stream its own object), the world-frame head on every
        channel but the hand-relative ones. `head` `[B, 2, T_f, D]`, `prefix` `[B, 2, T_p, D]`."""
        if self.cfg.prediction == "absolute":
            return head
        last = prefix[:, :, -1:]
        body_width = self.cfg.body_features
        body = last[:, :1, :, :body_width].expand(-1, 2, -1, -1)
        last = torch.cat([body, last[..., body_width:]], dim=3)
        if self.cfg.prediction == "prefix_residual_world":
            mask = torch.ones(last.shape[-1], dtype=last.dtype, device=last.device)
            for k in HAND_RELATIVE_CHANNELS:
                mask[body_width + k] = 0.0
            last = last * mask
        return head + last

    def check_input(self, inputs: dict[str, torch.Tensor]) -> None:
        c = self.cfg
        batch = inputs["noisy"].shape[0]
        d = c.stream_features
        expected = {
            "noisy": (batch, 2, c.predicted_frames, d),
            "prefix": (batch, 2, c.prefix_frames, d),
            "timesteps": (batch,),
            "text": (batch, c.text_embedding),
            "bps": (batch, 2, c.bps_points * 3),
            "presence": (batch, 2),
        }
        for name, shape in expected.items():
            if tuple(inputs[name].shape) != shape:
                raise ValueError(f"{name}: expected {shape}, got {tuple(inputs[name].shape)}")


def rust_name(name: str) -> str:
    """The dex2hoi parameter name of a torch parameter: the denoiser's sit at the root."""
    return name.removeprefix("denoiser.")


# --- safetensors ------------------------------------------------------------------------------

SAFETENSORS_DTYPES = {
    "F64": np.dtype("<f8"),
    "F32": np.dtype("<f4"),
    "F16": np.dtype("<f2"),
    "I64": np.dtype("<i8"),
    "I32": np.dtype("<i4"),
    "U32": np.dtype("<u4"),
    "U8": np.dtype("u1"),
}


class SafeTensors:
    """A safetensors file read one tensor at a time (8-byte little-endian header length, a
    JSON header of dtype / shape / data_offsets, then the raw little-endian data), so that
    loading costs no more memory than the largest tensor."""

    def __init__(self, path: Path) -> None:
        self.path = path
        with open(path, "rb") as f:
            (length,) = struct.unpack("<Q", f.read(8))
            header = json.loads(f.read(length))
        header.pop("__metadata__", None)
        self.header: dict[str, dict] = header
        self.base = 8 + length

    def names(self) -> list[str]:
        return sorted(self.header)

    def get(self, name: str) -> torch.Tensor:
        info = self.header[name]
        dtype = SAFETENSORS_DTYPES.get(info["dtype"])
        if dtype is None:
            raise ValueError(f"{self.path}: {name} has unsupported dtype {info['dtype']}")
        start, end = info["data_offsets"]
        shape = tuple(info["shape"])
        if end - start != math.prod(shape) * dtype.itemsize:
            raise ValueError(f"{self.path}: {name}: {end - start} bytes for shape {shape}")
        with open(self.path, "rb") as f:
            f.seek(self.base + start)
            data = f.read(end - start)
        array = np.frombuffer(data, dtype=dtype).reshape(shape)
        return torch.from_numpy(array.copy())


def load_parameters(model: nn.Module, weights: SafeTensors) -> None:
    """Copies every `model.<name>` tensor into the parameter of the same dex2hoi name; any name
    missing on either side or any shape mismatch is an error."""
    params = {rust_name(n): p for n, p in model.named_parameters()}
    stored = {n.removeprefix("model."): n for n in weights.names() if n.startswith("model.")}
    missing, unexpected = sorted(set(params) - set(stored)), sorted(set(stored) - set(params))
    if missing or unexpected:
        raise SystemExit(
            f"{weights.path}: parameters missing from the file: {missing}; "
            f"in the file but not in this model: {unexpected}"
        )
    with torch.no_grad():
        for name, param in params.items():
            value = weights.get(stored[name])
            if value.shape != param.shape:
                raise SystemExit(
                    f"{weights.path}: {name}: file {tuple(value.shape)}, model {tuple(param.shape)}"
                )
            param.copy_(value)


def reference_inputs(weights: SafeTensors) -> dict[str, torch.Tensor]:
    return {
        name: weights.get(f"input.{name}")
        for name in ("noisy", "prefix", "timesteps", "text", "bps", "presence")
    }


# --- diffusion (schedule.rs, sampler.rs) ------------------------------------------------------


class CosineSchedule:
    """`beta_t = min(1 - f(t+1)/f(t), 0.999)`, `f(t) = cos^2(((t/T) + s)/(1 + s) pi/2)`,
    `alpha_bar_t = prod_{i <= t} (1 - beta_i)`, in f64 as schedule.rs."""

    def __init__(self, steps: int = DIFFUSION_STEPS) -> None:
        def f(t: int) -> float:
            x = (t / steps + 0.008) / (1.0 + 0.008)
            c = math.cos(x * (math.pi / 2.0))
            return c * c

        self.betas = [min(1.0 - f(t + 1) / f(t), 0.999) for t in range(steps)]
        self.alpha_bars = []
        product = 1.0
        for beta in self.betas:
            product *= 1.0 - beta
            self.alpha_bars.append(product)

    @property
    def steps(self) -> int:
        return len(self.betas)

    def respaced(self, count: int) -> list[int]:
        """`count` timesteps spread evenly over `[0, T)`, descending from `T - 1` to 0."""
        steps = self.steps
        if not 1 <= count <= steps:
            raise ValueError(f"sampling steps: 1 to {steps}, got {count}")
        if count == 1:
            return [steps - 1]
        # f64 `round` rounds half away from zero; the values are non-negative.
        spaced = [math.floor(k * (steps - 1) / (count - 1) + 0.5) for k in range(count)]
        out = [t for i, t in enumerate(spaced) if i == 0 or t != spaced[i - 1]]
        return out[::-1]

    def add_noise(
        self, x0: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor
    ) -> torch.Tensor:
        """`sqrt(alpha_bar_t) x0 + sqrt(1 - alpha_bar_t) noise`, one timestep per sample."""
        alpha_bar = torch.tensor(
            self.alpha_bars, dtype=torch.float64, device=timesteps.device
        )[timesteps]
        shape = (-1,) + (1,) * (x0.dim() - 1)
        signal = alpha_bar.sqrt().to(x0.dtype).view(shape)
        scale = (1.0 - alpha_bar).sqrt().to(x0.dtype).view(shape)
        return x0 * signal + noise * scale


@dataclass
class WindowCondition:
    """What a window is conditioned on (dex2hoi-sample's WindowCondition), batch B."""

    prefix: torch.Tensor  # [B, 2, T_p, D]
    text: torch.Tensor  # [B, E]
    bps: torch.Tensor  # [B, 2, 3P]
    presence: torch.Tensor  # [B, 2]


def sample_window(
    model: Callable[..., torch.Tensor],
    cfg: Config,
    schedule: CosineSchedule,
    condition: WindowCondition,
    generator: torch.Generator,
    steps: int = SAMPLING_STEPS,
    guidance: float = GUIDANCE,
    eta: float = 0.0,
) -> torch.Tensor:
    """DDIM from pure noise with classifier-free guidance: every step runs one forward on a
    batch of the conditional rows followed by the null rows (text zeroed)."""
    batch = condition.text.shape[0]
    device = condition.text.device  # `generator` must be on it too
    shape = (batch, 2, cfg.predicted_frames, cfg.stream_features)
    # The guided batch: the condition twice, the second copy's text zeroed (ModelDenoiser).
    prefix = torch.cat([condition.prefix, condition.prefix])
    text = torch.cat([condition.text, torch.zeros_like(condition.text)])
    bps = torch.cat([condition.bps, condition.bps])
    presence = torch.cat([condition.presence, condition.presence])
    timesteps = schedule.respaced(steps)
    x = torch.randn(shape, generator=generator, device=device)
    for k, t in enumerate(timesteps):
        t_batch = torch.full((2 * batch,), float(t), device=device)
        x0 = model(torch.cat([x, x]), prefix, t_batch, text, bps, presence)
        conditional, unconditional = x0[:batch], x0[batch:]
        x0 = unconditional + (conditional - unconditional) * guidance
        if k + 1 == len(timesteps):
            return x0
        ab, ab_prev = schedule.alpha_bars[t], schedule.alpha_bars[timesteps[k + 1]]
        epsilon = (x - x0 * math.sqrt(ab)) / math.sqrt(1.0 - ab)
        sigma = eta * math.sqrt((1.0 - ab_prev) / (1.0 - ab)) * math.sqrt(1.0 - ab / ab_prev)
        direction = math.sqrt(max(1.0 - ab_prev - sigma * sigma, 0.0))
        x = x0 * math.sqrt(ab_prev) + epsilon * direction
        if sigma > 0.0:
            x = x + torch.randn(shape, generator=generator, device=device) * sigma
    return x


# --- measurements -----------------------------------------------------------------------------


def median(values: list[float]) -> float:
    """The middle of the sorted values (as the Rust benches: `sorted[n / 2]`)."""
    return sorted(values)[len(values) // 2]


def synchronize(device: torch.device) -> None:
    """Waits for the device's queued work (a no-op on the CPU), so that the clock read next
    covers it: called before each timed region starts and before each clock read in it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(
    f: Callable[[], object], runs: int, warm_up: bool, device: torch.device = torch.device("cpu")
) -> float:
    if warm_up:
        f()
    times = []
    for _ in range(runs):
        synchronize(device)
        start = time.perf_counter()
        f()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return median(times)


def peak_rss_mb() -> float:
    # ru_maxrss is in KiB on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def peak_memory(device: torch.device) -> dict:
    """The process's peak resident memory and, on a GPU, the peak of the memory PyTorch's
    allocator handed out on it (`torch.cuda.max_memory_allocated`, GiB; each case runs in its
    own process, so it is the case's)."""
    out: dict = {"peak_rss_mb": peak_rss_mb()}
    if device.type == "cuda":
        out["peak_gpu_gib"] = torch.cuda.max_memory_allocated(device) / 2.0**30
    return out


# Products per timed run on a GPU: one 1024^3 f32 product takes tens of microseconds there, about
# what a launch and a synchronisation cost, so each timed run queues several.
GPU_MATMUL_REPEATS = 10


def matmul_gflops(device: torch.device) -> float:
    """A 1024 x 1024 x 1024 f32 product, median of 9 after a warm-up: 2 * 1024^3 / seconds (on
    a GPU each timed run is GPU_MATMUL_REPEATS products, synchronised)."""
    g = torch.Generator().manual_seed(0)
    a = torch.randn(1024, 1024, generator=g).to(device)
    b = torch.randn(1024, 1024, generator=g).to(device)
    repeats = GPU_MATMUL_REPEATS if device.type == "cuda" else 1

    def products() -> None:
        for _ in range(repeats):
            torch.mm(a, b)

    seconds = timed(products, 9, warm_up=True, device=device) / repeats
    return 2.0 * 1024**3 / seconds / 1e9


def tf32_matmul() -> bool:
    """Whether float32 matrix products on CUDA may use TF32 (PyTorch's default: no)."""
    return bool(torch.backends.cuda.matmul.allow_tf32)


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"


def reference_path(root: Path, preset: str) -> Path:
    return root / "target" / "bench" / "reference" / f"{preset}.safetensors"


def missing_reference(root: Path, preset: str) -> str:
    return (
        f"{reference_path(root, preset)} does not exist: run `cargo bench -p dex2hoi-sample "
        "--bench reference` first (`cargo xtask bench compare` does), or pass --skip-check"
    )


def build_model(cfg: Config, root: Path, preset: str, skip_check: bool, device: torch.device):
    """The model on `device` with dex2hoi's reference weights, the reference inputs (on
    `device`) and output (on the host); None with `--skip-check` when the file is absent: then
    the weights are a fresh initialisation (made on the host, so the same on every device)."""
    torch.manual_seed(0)
    model = DualStream(cfg)
    path = reference_path(root, preset)
    if not path.exists():
        if skip_check:
            return model.to(device), None, None
        raise SystemExit(missing_reference(root, preset))
    weights = SafeTensors(path)
    load_parameters(model, weights)
    inputs = reference_inputs(weights)
    model.check_input(inputs)
    inputs = {name: value.to(device) for name, value in inputs.items()}
    return model.to(device), inputs, weights.get("output")


def max_abs_diff(model: Callable[..., torch.Tensor], inputs, expected) -> float | None:
    """The largest |model(inputs) - expected|, compared on the host."""
    if inputs is None:
        return None
    with torch.no_grad():
        out = model(**inputs).cpu()
    return float((out - expected).abs().max())


def sample_condition(cfg: Config, device: torch.device) -> WindowCondition:
    """Batch 1, two objects present (benches/sample.rs); drawn on the host, moved to `device`."""
    g = torch.Generator().manual_seed(1)
    return WindowCondition(
        prefix=torch.randn(1, 2, cfg.prefix_frames, cfg.stream_features, generator=g).to(device),
        text=torch.randn(1, cfg.text_embedding, generator=g).to(device),
        bps=torch.randn(1, 2, cfg.bps_points * 3, generator=g).to(device),
        presence=torch.ones(1, 2, device=device),
    )


def sample_runs(preset: str, quick: bool) -> tuple[int, bool]:
    """Runs and whether to warm up: small 5, paper 3 after a warm-up; `--quick` 1, none."""
    if quick:
        return 1, False
    return (5 if preset == "small" else 3), True


def case_sample(args, preset: str) -> dict:
    """Checks the forward pass, then times sampling eagerly under no_grad and inference_mode."""
    cfg = Config.preset(args.root, preset)
    device = torch.device(args.device)
    model, inputs, expected = build_model(cfg, args.root, preset, args.skip_check, device)
    model.eval()
    diff = max_abs_diff(model, inputs, expected)
    if diff is not None:
        print(f"{preset}: max |torch - dex2hoi| = {diff:.3e}", file=sys.stderr)
    schedule, condition = CosineSchedule(), sample_condition(cfg, device)
    runs, warm_up = sample_runs(preset, args.quick)
    generator = torch.Generator(device=device).manual_seed(2)

    def one() -> None:
        sample_window(model, cfg, schedule, condition, generator)

    with torch.no_grad():
        eager = timed(one, runs, warm_up, device)
    with torch.inference_mode():
        inference = timed(one, runs, warm_up, device)
    return {
        "max_abs_diff": diff,
        "eager": eager,
        "inference_mode": inference,
        **peak_memory(device),
    }


def case_compile(args, preset: str) -> dict:
    """torch.compile of the model: the first call's time (compilation) and sampling with it."""
    cfg = Config.preset(args.root, preset)
    device = torch.device(args.device)
    model, inputs, expected = build_model(cfg, args.root, preset, args.skip_check, device)
    model.eval()
    schedule, condition = CosineSchedule(), sample_condition(cfg, device)
    runs, warm_up = sample_runs(preset, args.quick)
    generator = torch.Generator(device=device).manual_seed(2)
    try:
        compiled = torch.compile(model, dynamic=False)
        with torch.no_grad():
            # The reference batch has the guided batch's shapes (2 rows): one compilation.
            synchronize(device)
            start = time.perf_counter()
            if inputs is not None:
                diff = max_abs_diff(compiled, inputs, expected)
            else:
                diff = None
                sample_window(compiled, cfg, schedule, condition, generator, steps=1)
            synchronize(device)
            compile_seconds = time.perf_counter() - start
            seconds = timed(
                lambda: sample_window(compiled, cfg, schedule, condition, generator),
                runs,
                warm_up,
                device,
            )
    except Exception as error:  # report why, the compiled mode is optional
        reason = f"{type(error).__name__}: {error}".strip().splitlines()[0][:400]
        return {"seconds": None, "reason": reason, **peak_memory(device)}
    return {
        "seconds": seconds,
        "compile_seconds": compile_seconds,
        "max_abs_diff": diff,
        **peak_memory(device),
    }


def diffusion_loss_weights(cfg: Config, presence: torch.Tensor) -> tuple[torch.Tensor, float]:
    """L_diff's channel weights `[B, 2, 1, D]` and count (loss.rs feature_terms): the body once
    (stream A), each present object's channels in its own stream, every frame real."""
    batch = presence.shape[0]
    weights = torch.zeros(batch, 2, 1, cfg.stream_features, device=presence.device)
    weights[:, 0, :, : cfg.body_features] = 1.0
    weights[:, :, :, cfg.body_features :] = presence[:, :, None, None]
    count = float(weights.sum()) * cfg.predicted_frames
    return weights, max(count, 1.0)


def case_train(args, preset: str) -> dict:
    """Training steps on random windows: q_sample, forward in training mode, L_diff, backward,
    clipped AdamW and the EMA update, as dex2hoi-train's Trainer::step with `mse_only`."""
    cfg = Config.preset(args.root, preset)
    device = torch.device(args.device)
    torch.manual_seed(0)
    model = DualStream(cfg).to(device)  # before the optimiser: its state follows the parameters
    model.train()
    params = list(model.parameters())
    optimizer = torch.optim.AdamW(
        [
            {"params": [p for p in params if p.dim() >= 2], "weight_decay": WEIGHT_DECAY},
            {"params": [p for p in params if p.dim() < 2], "weight_decay": 0.0},
        ],
        lr=LEARNING_RATE,
        betas=BETAS,
        eps=EPSILON,
        foreach=True,
    )
    ema = [p.detach().clone() for p in params]
    schedule = CosineSchedule()
    # The random windows are drawn on the device (a CUDA generator there).
    g = torch.Generator(device=device).manual_seed(3)
    b, d, tp, tf = TRAIN_BATCH, cfg.stream_features, cfg.prefix_frames, cfg.predicted_frames
    presence = torch.ones(b, 2, device=device)
    weights, count = diffusion_loss_weights(cfg, presence)
    step = 0

    def clock() -> float:
        synchronize(device)
        return time.perf_counter()

    def one_step() -> tuple[float, float, float, float]:
        nonlocal step
        start = clock()
        features = torch.randn(b, 2, tp + tf, d, generator=g, device=device)
        prefix, x0 = features[:, :, :tp], features[:, :, tp:]
        text = torch.randn(b, cfg.text_embedding, generator=g, device=device)
        bps = torch.randn(b, 2, cfg.bps_points * 3, generator=g, device=device)
        timesteps = torch.randint(0, schedule.steps, (b,), generator=g, device=device)
        noise = torch.randn(x0.shape, generator=g, device=device)
        noisy = schedule.add_noise(x0, noise, timesteps)
        # dex2hoi's trainer always passes the window's frame mask (all real here).
        frame_mask = torch.ones(b, tp + tf, device=device)
        batch_done = clock()
        prediction = model(noisy, prefix, timesteps.float(), text, bps, presence, frame_mask)
        loss = ((prediction - x0).square() * weights).sum() / count
        forward_done = clock()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        backward_done = clock()
        torch.nn.utils.clip_grad_norm_(params, GRADIENT_CLIP, foreach=True)
        optimizer.step()
        decay = min(EMA_DECAY, (1.0 + step) / (10.0 + step))
        with torch.no_grad():
            torch._foreach_lerp_(ema, [p.detach() for p in params], 1.0 - decay)
        step += 1
        update_done = clock()
        return (
            update_done - start,
            forward_done - batch_done,
            backward_done - forward_done,
            update_done - backward_done,
        )

    one_step()  # warm-up: allocates the optimiser state
    runs = 1 if args.quick else 7
    measured = [one_step() for _ in range(runs)]
    seconds, forward, backward, update = (median(list(part)) for part in zip(*measured))
    return {
        "seconds": seconds,
        "forward": forward,
        "backward": backward,
        "update": update,
        "batch": TRAIN_BATCH,
        **peak_memory(device),
    }


CASES = {"sample": case_sample, "compile": case_compile, "train": case_train}


def end_group(child: subprocess.Popen) -> None:
    """Ends a case's process group (the case and any compile workers it started)."""
    os.killpg(child.pid, signal.SIGKILL)
    child.wait()


def run_case(args, case: str, timeout: float | None = None) -> dict:
    """Runs `--case PRESET-KIND` in a fresh process and returns its result (or the error).

    The process gets an empty TorchInductor cache, so that a compilation is timed cold, and its
    own process group, so that a timeout also ends any compile workers it started."""
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--case",
        case,
        "--threads",
        str(args.threads),
        "--root",
        str(args.root),
        "--device",
        args.device,
    ]
    command += ["--quick"] * args.quick + ["--skip-check"] * args.skip_check
    with tempfile.TemporaryDirectory(prefix="torch-reference-") as cache:
        # Triton's kernel cache (compilation on a GPU) is emptied too.
        env = {
            **os.environ,
            "TORCHINDUCTOR_CACHE_DIR": cache,
            "TRITON_CACHE_DIR": os.path.join(cache, "triton"),
        }
        child = subprocess.Popen(
            command, stdout=subprocess.PIPE, text=True, env=env, start_new_session=True
        )
        try:
            stdout, _ = child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            end_group(child)
            return {"error": f"did not finish within {timeout:.0f} s"}
        except BaseException:  # Ctrl-C does not reach the child's own session
            end_group(child)
            raise
    lines = [line for line in stdout.splitlines() if line.startswith("RESULT ")]
    if child.returncode != 0 or not lines:
        return {"error": f"`--case {case}` failed with exit status {child.returncode}"}
    return json.loads(lines[-1].removeprefix("RESULT "))


# --- the report -------------------------------------------------------------------------------


def rate(flops: float, seconds: float | None, matmul: float) -> dict:
    if seconds is None:
        return {"seconds": None, "gflops": None, "share_of_matmul": None}
    gflops = flops / seconds / 1e9
    return {"seconds": seconds, "gflops": gflops, "share_of_matmul": gflops / matmul}


def check_line(diff: float | None, failed: list[str], what: str) -> str:
    if diff is None:
        return "skipped (no reference file)"
    if diff > TOLERANCE:
        failed.append(f"{what}: max abs diff {diff:.3e} > {TOLERANCE:.0e}")
        return f"max |torch - dex2hoi| = {diff:.2e} > {TOLERANCE:.0e} FAILED"
    return f"max |torch - dex2hoi| = {diff:.2e} (tolerance {TOLERANCE:.0e}) ok"


def print_mode(mode: str, result: dict) -> None:
    if result["seconds"] is None:
        print(f"  {mode:<16} unavailable: {result.get('reason')}")
        return
    extra = ""
    if "compile_seconds" in result:
        extra = f" (first call {result['compile_seconds']:.1f} s)"
    print(
        f"  {mode:<16} {result['seconds']:>8.3f} s per 60-frame sample, "
        f"{result['gflops']:6.1f} GFLOP/s ({100 * result['share_of_matmul']:.0f}% of matmul){extra}"
    )


def bench_preset(args, preset: str, matmul: float, failed: list[str]) -> dict:
    """The check and the three sampling modes of one preset, each printed and returned."""
    cfg = Config.preset(args.root, preset)
    flops = flops_per_forward(cfg, 2) * SAMPLING_STEPS
    name = f"{preset} (latent {cfg.latent}, {cfg.layers} layers)"
    print(f"{name}: {flops / 1e9:.1f} GFLOP per sample")
    sampled = run_case(args, f"{preset}-sample")
    if "error" in sampled:
        failed.append(f"{preset} sampling: {sampled['error']}")
        print(f"  sampling failed: {sampled['error']}\n")
        return sampled
    print(f"  check            {check_line(sampled['max_abs_diff'], failed, preset)}")
    if args.no_compile:
        compiled = {"seconds": None, "reason": "skipped (--no-compile)"}
    else:
        compiled = run_case(args, f"{preset}-compile", timeout=args.compile_timeout)
        if "error" in compiled:
            compiled = {"seconds": None, "reason": compiled["error"]}
        elif compiled["seconds"] is not None:
            line = check_line(compiled["max_abs_diff"], failed, f"{preset} compiled")
            print(f"  check (compiled) {line}")
    extra = {k: v for k, v in compiled.items() if k != "seconds"}
    modes = {
        "eager": rate(flops, sampled["eager"], matmul),
        "inference_mode": rate(flops, sampled["inference_mode"], matmul),
        "compile": {**rate(flops, compiled["seconds"], matmul), **extra},
    }
    for mode, result in modes.items():
        print_mode(mode, result)
    if "peak_gpu_gib" in sampled:
        print(
            f"  peak GPU memory while sampling: {sampled['peak_gpu_gib']:.3f} GiB "
            "(torch.cuda.max_memory_allocated)"
        )
    print(
        f"  peak RSS while sampling: {sampled['peak_rss_mb']:.0f} MB "
        f"({sampled['import_rss_mb']:.0f} MB of it once torch is imported)\n"
    )
    gpu = {k: sampled[k] for k in ("peak_gpu_gib",) if k in sampled}
    return {
        "max_abs_diff": sampled["max_abs_diff"],
        "flops_per_sample": flops,
        "sample": modes,
        **gpu,
        "peak_rss_mb": sampled["peak_rss_mb"],
        "import_rss_mb": sampled["import_rss_mb"],
    }


def bench_training(args, failed: list[str]) -> dict:
    trained = run_case(args, "small-train")
    if "error" in trained:
        failed.append(f"training: {trained['error']}")
        print(f"training step (small) failed: {trained['error']}")
        return trained
    gpu = ""
    if "peak_gpu_gib" in trained:
        gpu = f"peak GPU memory {trained['peak_gpu_gib']:.3f} GiB (max_memory_allocated), "
    print(
        f"training step (small, batch {TRAIN_BATCH} x 60 frames): {trained['seconds']:.3f} s "
        f"(forward {trained['forward']:.3f}, backward {trained['backward']:.3f}, "
        f"update {trained['update']:.3f}); {gpu}peak RSS {trained['peak_rss_mb']:.0f} MB "
        f"({trained['import_rss_mb']:.0f} MB once torch is imported)"
    )
    return trained


def write_atomically(path: Path, report: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(report, indent=2) + "\n")
    os.replace(temporary, path)


def run_all(args) -> int:
    for preset in args.presets:  # fail early on an unknown or unsupported preset
        Config.preset(args.root, preset)
        if not args.skip_check and not reference_path(args.root, preset).exists():
            raise SystemExit(missing_reference(args.root, preset))
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    matmul = matmul_gflops(device)
    name = device_name(device)
    report: dict = {
        "torch": torch.__version__,
        "device": name,
        "threads": args.threads,
        "quick": args.quick,
        "matmul_gflops": matmul,
    }
    threads = f"{args.threads} thread{'s' * (args.threads != 1)}"
    where = "cpu"
    matmul_what = "f32"
    if device.type == "cuda":
        tf32 = tf32_matmul()
        report["cuda"] = torch.version.cuda
        report["matmul_allow_tf32"] = tf32
        where = f"cuda: {name}, CUDA {torch.version.cuda}"
        matmul_what = f"f32, TF32 {'on' if tf32 else 'off'}"
    print(
        f"PyTorch reference for dex2hoi (torch {torch.__version__}, {where}, {threads}; medians)\n"
    )
    print(f"{f'matmul 1024 x 1024 x 1024 ({matmul_what})':<44} {matmul:>8.1f} GFLOP/s\n")
    failed: list[str] = []
    for preset in args.presets:
        report[preset] = bench_preset(args, preset, matmul, failed)
    if "small" in args.presets and not args.no_train:
        report["train_small"] = bench_training(args, failed)
    out = args.out if args.out.is_absolute() else args.root / args.out
    write_atomically(out, report)
    print(f"\nwrote {out}")
    for failure in failed:
        print(f"error: {failure}", file=sys.stderr)
    return 1 if failed else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", default="small,paper", help="comma-separated presets")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default="cpu",
        help="where the model runs (cuda: the current NVIDIA GPU, f32, synchronised timings)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("target/bench/torch.json"),
        help="the JSON report (a relative path is under --root)",
    )
    parser.add_argument("--quick", action="store_true", help="one run each, no warm-up")
    parser.add_argument(
        "--root", type=Path, default=Path(__file__).resolve().parent.parent, help="repository root"
    )
    parser.add_argument(
        "--skip-check",
        action="store_true",
        help="without target/bench/reference/*.safetensors: random weights, no check",
    )
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile mode")
    parser.add_argument("--no-train", action="store_true", help="skip the training step")
    parser.add_argument(
        "--compile-timeout", type=float, default=1200.0, help="seconds for the compiled case"
    )
    parser.add_argument("--case", help=argparse.SUPPRESS)  # internal: PRESET-KIND
    args = parser.parse_args()
    args.presets = [p for p in args.presets.split(",") if p]
    if args.threads < 1:
        parser.error("--threads must be at least 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        cuda = torch.version.cuda
        build = f"built with CUDA {cuda}" if cuda else "a CPU-only build"
        raise SystemExit(
            f"--device cuda: torch.cuda.is_available() is false (torch {torch.__version__}, "
            f"{build}): no usable NVIDIA GPU or driver here"
        )
    if args.case is not None:
        torch.set_num_threads(args.threads)
        preset, _, kind = args.case.rpartition("-")
        if kind not in CASES or not preset:
            parser.error(f"unknown case {args.case!r}")
        baseline = peak_rss_mb()  # torch and numpy imported, nothing else done yet
        result = CASES[kind](args, preset)
        result["import_rss_mb"] = baseline
        print("RESULT " + json.dumps(result), flush=True)
        return 0
    return run_all(args)


if __name__ == "__main__":
    sys.exit(main())
