//! Model configuration with the presets of `configs/` and the paper's ablation variants
//! (Table 3) as typed options.

use serde::{Deserialize, Serialize};

use dex2hoi_data::FeatureLayout;
use dex2hoi_repr::SkeletonKind;

use crate::error::{ModelError, Result};

/// The presets of `configs/` at the repository root, compiled in: the one source of every
/// preset's numbers. Each is a whole training configuration; the model reads its `[model]`
/// table ([`ModelConfig::preset`]) and `dex2hoi-train` the rest.
pub const PRESETS: [(&str, &str); 5] = [
    ("tiny", include_str!("../../../configs/tiny.toml")),
    ("demo", include_str!("../../../configs/demo.toml")),
    ("small", include_str!("../../../configs/small.toml")),
    ("paper", include_str!("../../../configs/paper.toml")),
    ("humoto", include_str!("../../../configs/humoto.toml")),
];

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

/// What the condition reads of where the objects stood when the prompt began (beyond the
/// paper; docs/CONVENTIONS.md, "Denoiser").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObjectStart {
    /// Nothing: the paper's condition.
    #[default]
    Off,
    /// Each object's rotation and world position at the prompt's first frame.
    Absolute,
    /// The same less the object's at the window's last prefix frame: the change that puts it
    /// back, in the units of the prefix-residual head's output.
    FromPrefix,
}

impl ObjectStart {
    /// Whether the condition reads nothing of it.
    pub fn is_off(&self) -> bool {
        *self == Self::Off
    }
}

/// What the output head predicts (beyond the paper).
///
/// See docs/CONVENTIONS.md, "Prefix-residual prediction".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Prediction {
    /// The clean predicted frames themselves (the paper).
    Absolute,
    /// Each predicted frame's difference from the last prefix frame, which the model adds back
    /// (in normalised feature space): a body or object that stays where the prefix left it is
    /// the head's zero output, so a window continues from its prefix without a jump.
    PrefixResidual,
    /// The difference from the last prefix frame on every channel but the hand-relative ones
    /// (so on the body, the object's rotation and its world position), and the clean values
    /// themselves on the hand-relative channels (the wrist offsets and the mixture logits), whose
    /// targets are far from the prefix's values whenever a hand reaches for an object.
    PrefixResidualWorld,
    /// The difference from the last prefix frame only where things are placed in the world:
    /// the body's root rotation and displacement, each object's rotation and world position.
    /// The clean values themselves everywhere else: the joint rotations below the root (the
    /// fingers among them) and the hand-relative channels.
    PrefixResidualPlacement,
    /// [`Self::PrefixResidualWorld`] with the finger joints' rotations predicted as clean
    /// values: the residual on the root, the 22 body joints (so the wrists, and a held object
    /// with them, continue from the prefix) and each object's rotation and world position.
    PrefixResidualCleanFingers,
}

impl Prediction {
    /// Whether the model adds the last prefix frame (to some or all channels).
    pub fn adds_prefix(self) -> bool {
        !matches!(self, Self::Absolute)
    }
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
    /// What the output head predicts.
    pub prediction: Prediction,
    /// The prompt clock (beyond the paper): the condition also sees how long the prompt has
    /// been in force ([`crate::model::ModelInput::elapsed`]), so that a window that starts
    /// at rest early in a prompt starts the task and one late in it stays at rest. Absent
    /// (false) in the models made before it.
    #[serde(default)]
    pub prompt_clock: bool,
    /// What the condition reads of where each object stood at the first frame of the prompt in
    /// force (beyond the paper; [`crate::model::ModelInput::object_start`]), so that an object
    /// put back after a hold longer than the prefix can go back where it stood. Absent (off)
    /// in the models made before it, and left out of a written configuration when off.
    #[serde(default, skip_serializing_if = "ObjectStart::is_off")]
    pub object_start: ObjectStart,
    /// The memory of set-down objects (beyond the paper): the condition also reads whether
    /// each object has been moved and set down again since the prompt in force began
    /// ([`crate::model::ModelInput::settled`]), so that a window whose prefix shows a task
    /// already done does not start it again. Absent (false) in the models made before it, and
    /// left out of a written configuration when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub settled_objects: bool,
    /// The start frame in the prefix (beyond the paper): the first prefix token shows both
    /// streams' rows at the first frame of the prompt in force instead of the frame `T_p`
    /// frames back ([`crate::model::ModelInput::object_start`]), so that attention can read
    /// where each object stood as it reads the prefix. No parameters of its own. Absent
    /// (false) in the models made before it, and left out of a written configuration when
    /// false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub start_in_prefix: bool,
    /// The reach frame in the prefix (beyond the paper): the first prefix token of each stream
    /// shows its rows at the frame its object was reached, the last before the object first
    /// moved since the prompt in force began, once that lies before the prefix
    /// ([`crate::model::ModelInput::reach`], `dex2hoi_data::settled::reach_frames`), so that
    /// the arm that took an object can be read when it puts it back. No parameters of its
    /// own; not with `start_in_prefix`. Absent (false) in the models made before it, and left
    /// out of a written configuration when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub reach_in_prefix: bool,
}

impl ModelConfig {
    /// For tests: `configs/tiny.toml` (latent 32, 2 layers, short windows).
    pub fn tiny() -> Self {
        Self::compiled_in("tiny")
    }

    /// The CPU default: `configs/small.toml` (latent 256, 4 layers).
    pub fn small() -> Self {
        Self::compiled_in("small")
    }

    /// The paper's size (MDM's): `configs/paper.toml` (latent 512, 8 layers, dropout 0.1).
    pub fn paper() -> Self {
        Self::compiled_in("paper")
    }

    /// The `[model]` table of a preset of `configs/` by name (see [`PRESETS`]).
    pub fn preset(name: &str) -> Result<Self> {
        let (_, text) = PRESETS.iter().find(|(n, _)| *n == name).ok_or_else(|| {
            let names: Vec<&str> = PRESETS.iter().map(|(n, _)| *n).collect();
            ModelError::config("preset", names.join(", "), name)
        })?;
        #[derive(Deserialize)]
        struct ModelTable {
            model: ModelConfig,
        }
        let table: ModelTable = toml::from_str(text).map_err(|e| {
            ModelError::config(&format!("configs/{name}.toml"), "a [model] table", e.message())
        })?;
        Ok(table.model)
    }

    fn compiled_in(name: &str) -> Self {
        Self::preset(name).expect("the compiled-in presets parse (tested)")
    }

    /// Numbers per frame of the body part `[h, r]`.
    pub fn body_features(&self) -> usize {
        self.layout().body_width()
    }

    /// Numbers per frame of one stream `[h, r, o]`.
    pub fn stream_features(&self) -> usize {
        self.layout().stream_width()
    }

    /// The feature layout of this model's streams.
    pub fn layout(&self) -> FeatureLayout {
        FeatureLayout::new(self.joints)
    }

    /// Frames of a window, `T_p + T_f`.
    pub fn window_frames(&self) -> usize {
        self.prefix_frames + self.predicted_frames
    }

    /// The built-in skeleton with `joints` joints (52: SMPL-X, 65: Mixamo), for what needs to
    /// know which joints are fingers.
    pub fn skeleton_kind(&self) -> Result<SkeletonKind> {
        match self.joints {
            52 => Ok(SkeletonKind::Smplx52),
            65 => Ok(SkeletonKind::Mixamo65),
            other => Err(ModelError::config(
                "joints",
                "52 (SMPL-X) or 65 (Mixamo) with prediction = \"prefix_residual_clean_fingers\"",
                other,
            )),
        }
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
        if self.prediction.adds_prefix() && self.prefix_frames == 0 {
            return Err(ModelError::config(
                "prefix_frames",
                "at least 1 with a prefix-residual prediction",
                0,
            ));
        }
        if self.start_in_prefix && self.reach_in_prefix {
            return Err(ModelError::config(
                "reach_in_prefix",
                "not with start_in_prefix (both show their frame as the first prefix token)",
                true,
            ));
        }
        if (self.start_in_prefix || self.reach_in_prefix) && self.prefix_frames < 2 {
            return Err(ModelError::config(
                "prefix_frames",
                "at least 2 with the start or reach frame in the prefix (its first frame is that \
                 frame, its last the frame the window continues)",
                self.prefix_frames,
            ));
        }
        if self.prediction == Prediction::PrefixResidualCleanFingers {
            self.skeleton_kind()?;
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
