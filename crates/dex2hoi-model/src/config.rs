//! Model configuration with the presets of the issue tracker and the paper's ablation variants
//! (Table 3) as typed options.

use serde::{Deserialize, Serialize};

use crate::error::{ModelError, Result};

/// How object motion is represented (paper Sec. 3.1; Table 3 "w/o hand-relative").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectRepresentation {
    /// Rotation, both wrist offsets, global position and mixture logits (Eq. 2).
    HandRelative,
    /// Rotation and global position only: the wrist offsets and mixture logits are zeroed on
    /// input and the position decodes from the global branch.
    GlobalOnly,
}

/// How the streams are laid out (Table 3 "single stream"; also the MDM-style baseline).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamLayout {
    /// One stream per object with shared weights and cross-attention (Eq. 5).
    Dual,
    /// One stream over the body and both objects, no cross-attention.
    Single,
}

/// How the two streams' body predictions become one (Table 3 "fusion -> average").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BodyFusion {
    /// The Motion Fusion Network (Eq. 7).
    Network,
    /// The element-wise average of the two predictions.
    Average,
}

/// The networks' sizes and variants.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Joints `J` of the skeleton (52 for SMPL-X).
    pub joints: usize,
    /// Width of the latent frame tokens.
    pub latent: usize,
    /// Blocks of the denoiser.
    pub layers: usize,
    /// Attention heads (must divide `latent`).
    pub heads: usize,
    /// Hidden width of the feed-forward layers.
    pub feed_forward: usize,
    /// Self-attention layers of the Motion Fusion Network.
    pub fusion_layers: usize,
    /// Dropout probability during training.
    pub dropout: f64,
    /// Clean prefix frames `T_p`.
    pub prefix_frames: usize,
    /// Predicted frames `T_f`.
    pub predicted_frames: usize,
    /// Width of the text embedding the model receives (512 CLIP, 384 MiniLM, or the built-in
    /// encoder's).
    pub text_embedding: usize,
    /// BPS basis points per object.
    pub bps_points: usize,
    /// Object representation.
    pub object_representation: ObjectRepresentation,
    /// Stream layout.
    pub stream_layout: StreamLayout,
    /// Body fusion.
    pub body_fusion: BodyFusion,
}

impl ModelConfig {
    fn base(
        latent: usize,
        layers: usize,
        heads: usize,
        feed_forward: usize,
        fusion_layers: usize,
    ) -> Self {
        Self {
            joints: 52,
            latent,
            layers,
            heads,
            feed_forward,
            fusion_layers,
            dropout: 0.0,
            prefix_frames: 20,
            predicted_frames: 40,
            text_embedding: 256,
            bps_points: 1024,
            object_representation: ObjectRepresentation::HandRelative,
            stream_layout: StreamLayout::Dual,
            body_fusion: BodyFusion::Network,
        }
    }

    /// For tests: latent 32, 2 layers, 2 heads, ff 64, fusion 1 layer, short windows.
    pub fn tiny() -> Self {
        Self {
            prefix_frames: 4,
            predicted_frames: 8,
            text_embedding: 16,
            bps_points: 16,
            ..Self::base(32, 2, 2, 64, 1)
        }
    }

    /// The CPU default: latent 256, 4 layers, 4 heads, ff 512, fusion 2 layers.
    pub fn small() -> Self {
        Self::base(256, 4, 4, 512, 2)
    }

    /// The paper's size (MDM's): latent 512, 8 layers, 4 heads, ff 1024, fusion 4, dropout 0.1.
    pub fn paper() -> Self {
        Self { dropout: 0.1, ..Self::base(512, 8, 4, 1024, 4) }
    }

    /// A preset by name: `tiny`, `small` or `paper`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "tiny" => Ok(Self::tiny()),
            "small" => Ok(Self::small()),
            "paper" => Ok(Self::paper()),
            other => Err(ModelError::config("preset", "tiny, small or paper", other)),
        }
    }

    /// Numbers per frame of the body part `[h, r]`.
    pub fn body_features(&self) -> usize {
        6 * self.joints + 3
    }

    /// Numbers per frame of one stream `[h, r, o]`.
    pub fn stream_features(&self) -> usize {
        self.body_features() + 18
    }

    /// Frames of a window, `T_p + T_f`.
    pub fn window_frames(&self) -> usize {
        self.prefix_frames + self.predicted_frames
    }

    /// Checks that the sizes fit together.
    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("joints", self.joints),
            ("latent", self.latent),
            ("layers", self.layers),
            ("heads", self.heads),
            ("feed_forward", self.feed_forward),
            ("predicted_frames", self.predicted_frames),
            ("text_embedding", self.text_embedding),
            ("bps_points", self.bps_points),
        ];
        for (field, value) in positive {
            if value == 0 {
                return Err(ModelError::config(field, "a positive number", value));
            }
        }
        if !self.latent.is_multiple_of(self.heads) {
            return Err(ModelError::config(
                "heads",
                format!("a divisor of latent {}", self.latent),
                self.heads,
            ));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(ModelError::config("dropout", "a probability in [0, 1)", self.dropout));
        }
        if self.body_fusion == BodyFusion::Network
            && self.fusion_layers == 0
            && self.stream_layout == StreamLayout::Dual
        {
            return Err(ModelError::config(
                "fusion_layers",
                "at least 1 with the fusion network",
                0,
            ));
        }
        Ok(())
    }
}
