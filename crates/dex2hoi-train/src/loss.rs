//! The training objective (paper Sec. 3.3, Eq. 8-12).
//!
//! `L = w_diff L_diff + L_vel + foot + penetration + lambda_w L_mix + lambda_t L_trans +
//! lambda_o L_off + lambda_p L_dist` (Eq. 12; the velocity, foot and penetration terms are the
//! "geometry regularization losses" the paper takes from InterGen, CoDA and HOIDiNi), plus,
//! beyond the paper and off by default, `lambda_g` times the global branch's error (the
//! `global` term, [`LossConfig::global`]), the error of where objects set down in the window
//! end (the `put_down` term, [`LossConfig::put_down`]) and logistic losses on the hands and the side the
//! text names, read from its embedding (the `text_hands` and `text_sides` terms,
//! [`LossConfig::text_hands`], [`LossConfig::text_sides`]). Every term
//! is a masked mean over what exists: predicted frames that are real (not padding, not the
//! prefix), object slots that hold an object, and for the geometric terms, samples whose
//! diffusion step is at most `geometric_max_timestep`. Lengths are in centimetres.
//!
//! The geometric terms decode the prediction: 6D rotations -> matrices -> differentiable FK
//! (`dex2hoi_repr::fk`) for joints and wrists; object positions through the softmax mixture of
//! Eq. 4 with the *predicted* wrists, so that `L_trans` reaches every branch and the weights.
//! Signed distances of joints to the predicted-pose objects use the object's surface samples
//! with normals: `d = n_k . (x - s_k)` for the nearest sample `s_k` of the joint `x` in the
//! object frame. The choice of the nearest sample is not differentiated (it is piecewise
//! constant); `d` is, in the joint, the object's rotation and its decoded position (unless
//! `contact_turns_objects` or `contact_moves_objects` makes those constants). Within the
//! 10 cm of `L_dist` the samples (512 per object, about 1 cm apart on a mug) make this a close
//! stand-in for the mesh's signed distance, and it needs no mesh queries in the loop. The search
//! runs on the host on the CPU and with tensor operations on a GPU ([`crate::surface`]).

use candle_core::{D, DType, Tensor};

use dex2hoi_data::FeatureLayout;
use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::layout::OBJECT_FEATURE_SIZE;
use dex2hoi_data::normalise::Normaliser;
use dex2hoi_model::ObjectRepresentation;
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::object_repr::{
    GLOBAL_POSITION_RANGE, LEFT_OFFSET_RANGE, MIXTURE_RANGE, RIGHT_OFFSET_RANGE, TensorWrists,
    tensor_decode_position, tensor_decode_rotation, tensor_mixture_weights, tensor_softmax,
};
use dex2hoi_repr::rotation::tensor::{rotate_inverse, sixd_to_matrix};
use dex2hoi_repr::tensor_forward_kinematics_per_sample;

use crate::batch::{Batch, SurfaceCloud};
use crate::config::LossConfig;
use crate::error::Result;
use crate::surface::{DeviceClouds, SurfaceSearch, nearest_on_host};

/// The text terms' logits are their two channels times this, so that the channels stay near
/// the size of the embedding's others (a few tenths) while the logits reach a few units.
pub const TEXT_LOGIT_SCALE: f64 = 4.0;

/// The text terms' targets are 0 and 1 moved this far in, so that their best logits are
/// finite (`ln(0.98 / 0.02)`, about 3.9: channels of about 1 at [`TEXT_LOGIT_SCALE`]) and the
/// channels stop growing once the hands are told apart; with targets of 0 and 1 they kept
/// growing in training, and the sides came closer beside them
/// (`docs/results/long-generations.md`, "The hand from the words: a text term").
pub const TEXT_TARGET_MARGIN: f64 = 0.02;

/// The embedding channels the `text_hands` term reads: left hand, right hand.
pub const HAND_CHANNELS: std::ops::Range<usize> = 0..2;

/// The embedding channels the `text_sides` term reads: an object ends to the left, to the
/// right.
pub const SIDE_CHANNELS: std::ops::Range<usize> = 2..4;

/// Centimetres per metre: geometric terms are measured in centimetres.
pub const CENTIMETRES: f64 = 100.0;

/// The terms of the objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Term {
    /// `L_diff`: MSE on x0 (normalised features).
    Diffusion,
    /// `L_vel` on features.
    FeatureVelocity,
    /// `L_vel` on FK joint positions.
    JointVelocity,
    /// Foot skating.
    FootContact,
    /// Joints inside objects.
    Penetration,
    /// `L_mix` (Eq. 8).
    Mixture,
    /// `L_trans` (Eq. 9).
    Translation,
    /// `L_off` (Eq. 10).
    Offset,
    /// The global branch against the object's position (beyond the paper, see
    /// [`LossConfig::global`]).
    Global,
    /// Where the objects set down within the window end, against the data (beyond the paper,
    /// see [`LossConfig::put_down`]).
    PutDown,
    /// `L_dist` (Eq. 11).
    Distance,
    /// The hands the text names, read from its embedding (beyond the paper, see
    /// [`LossConfig::text_hands`]).
    TextHands,
    /// The side the text names, read from its embedding (beyond the paper, see
    /// [`LossConfig::text_sides`]).
    TextSides,
}

impl Term {
    /// Every term, in reporting order.
    pub const ALL: [Term; 13] = [
        Term::Diffusion,
        Term::FeatureVelocity,
        Term::JointVelocity,
        Term::FootContact,
        Term::Penetration,
        Term::Mixture,
        Term::Translation,
        Term::Offset,
        Term::Global,
        Term::PutDown,
        Term::Distance,
        Term::TextHands,
        Term::TextSides,
    ];

    /// The name in logs and `metrics.jsonl`.
    pub fn name(self) -> &'static str {
        match self {
            Term::Diffusion => "diffusion",
            Term::FeatureVelocity => "feature_velocity",
            Term::JointVelocity => "joint_velocity",
            Term::FootContact => "foot_contact",
            Term::Penetration => "penetration",
            Term::Mixture => "mixture",
            Term::Translation => "translation",
            Term::Offset => "offset",
            Term::Global => "global",
            Term::PutDown => "put_down",
            Term::Distance => "distance",
            Term::TextHands => "text_hands",
            Term::TextSides => "text_sides",
        }
    }

    /// Whether the term decodes the prediction (FK, the object channels, signed distances)
    /// rather than comparing normalised features.
    pub fn decodes_prediction(self) -> bool {
        self.reads_prediction() && !matches!(self, Term::Diffusion | Term::FeatureVelocity)
    }

    /// Whether the term is a function of the model's prediction ([`LossContext::objective`]);
    /// the text terms are functions of the text embedding ([`LossContext::text_terms`]).
    pub fn reads_prediction(self) -> bool {
        !matches!(self, Term::TextHands | Term::TextSides)
    }

    /// The weight of the term in a configuration.
    pub fn weight(self, config: &LossConfig) -> f64 {
        match self {
            Term::Diffusion => config.diffusion,
            Term::FeatureVelocity => config.feature_velocity,
            Term::JointVelocity => config.joint_velocity,
            Term::FootContact => config.foot_contact,
            Term::Penetration => config.penetration,
            Term::Mixture => config.mixture,
            Term::Translation => config.translation,
            Term::Offset => config.offset,
            Term::Global => config.global,
            Term::PutDown => config.put_down,
            Term::Distance => config.distance,
            Term::TextHands => config.text_hands,
            Term::TextSides => config.text_sides,
        }
    }
}

/// The objective of one batch: the weighted total and every active term (unweighted).
#[derive(Debug, Clone)]
pub struct Objective {
    /// `sum_k weight_k * term_k`, a scalar.
    pub total: Tensor,
    /// Active terms with their unweighted values (scalars).
    pub terms: Vec<(Term, Tensor)>,
}

impl Objective {
    /// Adds a term, weighted as the configuration says: each of [`LossContext::objective`]'s
    /// and those computed apart from it (the text terms).
    pub fn add(&mut self, term: Term, value: Tensor, config: &LossConfig) -> Result<()> {
        let weighted = value.affine(term.weight(config), 0.0)?;
        self.total = (&self.total + weighted.to_dtype(self.total.dtype())?)?;
        self.terms.push((term, value));
        Ok(())
    }
}

/// The mean binary cross-entropy of logits `x` against targets `y` in [0, 1],
/// `max(x, 0) - x y + ln(1 + exp(-|x|))`: `-y ln s(x) - (1 - y) ln(1 - s(x))` for the sigmoid
/// `s`, in a form that neither overflows nor loses precision for large `|x|`.
///
/// # Shapes
/// - `logits`, `targets`: the same shape; returns a scalar
pub fn logistic_loss(logits: &Tensor, targets: &Tensor) -> Result<Tensor> {
    let softplus_of_minus_abs = (logits.abs()?.neg()?.exp()? + 1.0)?.log()?;
    let loss = ((logits.relu()? - (logits * targets)?)? + softplus_of_minus_abs)?;
    Ok(loss.mean_all()?)
}

/// What the objective needs besides the batch: configuration, skeleton, statistics, clouds.
#[derive(Debug, Clone)]
pub struct LossContext {
    config: LossConfig,
    representation: ObjectRepresentation,
    skeleton: Skeleton,
    prefix_frames: usize,
    mean: Vec<f32>,
    std: Vec<f32>,
    clouds: Vec<SurfaceCloud>,
    /// Where the nearest surface samples are searched; `None`: the faster for the device
    /// ([`SurfaceSearch::for_device`]).
    surface_search: Option<SurfaceSearch>,
    /// The clouds on the device of the first tensor search (made once, then reused).
    device_clouds: std::sync::OnceLock<DeviceClouds>,
}

impl LossContext {
    /// A context; `mean` and `std` are the per-channel statistics of one stream `[D]`.
    pub fn new(
        config: LossConfig,
        representation: ObjectRepresentation,
        skeleton: Skeleton,
        prefix_frames: usize,
        mean: Vec<f32>,
        std: Vec<f32>,
        clouds: Vec<SurfaceCloud>,
    ) -> Self {
        Self {
            config,
            representation,
            skeleton,
            prefix_frames,
            mean,
            std,
            clouds,
            surface_search: None,
            device_clouds: std::sync::OnceLock::new(),
        }
    }

    /// The same context with the nearest surface samples searched as `search` says, whatever
    /// the device (both searches pick the same samples; `dex2hoi_train::surface`).
    pub fn with_surface_search(mut self, search: SurfaceSearch) -> Self {
        self.surface_search = Some(search);
        self
    }

    /// The surface clouds as tensors on `device`, made once per device.
    fn device_clouds(&self, device: &candle_core::Device) -> Result<DeviceClouds> {
        if let Some(clouds) = self.device_clouds.get().filter(|c| c.is_on(device)) {
            return Ok(clouds.clone());
        }
        let clouds = DeviceClouds::new(&self.clouds, device)?;
        // A context used on a second device keeps the first one's clouds.
        let _ = self.device_clouds.set(clouds.clone());
        Ok(clouds)
    }

    /// The configuration.
    pub fn config(&self) -> &LossConfig {
        &self.config
    }

    fn active(&self, term: Term) -> bool {
        let c = &self.config;
        if term.weight(c) == 0.0 || (c.mse_only && term != Term::Diffusion) {
            return false;
        }
        let hand_relative = self.representation == ObjectRepresentation::HandRelative;
        match term {
            Term::Mixture | Term::Offset | Term::Global => c.mixture_supervision && hand_relative,
            Term::Translation => c.mixture_supervision,
            Term::Distance => c.distance_loss,
            _ => true,
        }
    }

    /// The objective for a prediction of the predicted frames.
    ///
    /// # Shapes
    /// - `prediction`: `[batch, 2, T_f, D]`, normalised x0 as the model returns it
    /// - `timesteps`: `batch` diffusion steps
    pub fn objective(
        &self,
        prediction: &Tensor,
        batch: &Batch,
        timesteps: &[usize],
    ) -> Result<Objective> {
        let window = Window::new(self, prediction, batch, timesteps)?;
        let target = batch.features.narrow(2, window.tp, window.tf)?.to_dtype(window.dtype)?;
        let mut terms: Vec<(Term, Tensor)> = Vec::new();
        self.feature_terms(&window, prediction, &target, &mut terms)?;
        let geometric = Term::ALL.iter().any(|&t| t.decodes_prediction() && self.active(t));
        if geometric {
            self.geometric_terms(&window, prediction, &target, &mut terms)?;
        }
        let total = Tensor::zeros((), window.dtype, &window.device)?;
        let mut objective = Objective { total, terms: Vec::with_capacity(terms.len()) };
        for (term, value) in terms {
            objective.add(term, value, &self.config)?;
        }
        Ok(objective)
    }

    /// The active text terms, each with its value: `text_hands` ([`LossConfig::text_hands`])
    /// reads channels [`HAND_CHANNELS`] of each text's embedding, times [`TEXT_LOGIT_SCALE`],
    /// as the logits of "the left hand holds an object" and "the right hand does", against
    /// [`Batch::hands`]; `text_sides` ([`LossConfig::text_sides`]) reads [`SIDE_CHANNELS`] as
    /// those of "an object ends to the left of where it stood" and "one ends to the right",
    /// against [`Batch::sides`]. Each is the mean [`logistic_loss`] against its targets moved
    /// [`TEXT_TARGET_MARGIN`] in from 0 and 1.
    ///
    /// # Shapes
    /// - `embedding`: `[batch, E]`, `E >= 4`, the encoder's output before the text dropout
    pub fn text_terms(&self, embedding: &Tensor, batch: &Batch) -> Result<Vec<(Term, Tensor)>> {
        let mut terms = Vec::new();
        for (term, channels, targets) in [
            (Term::TextHands, HAND_CHANNELS, &batch.hands),
            (Term::TextSides, SIDE_CHANNELS, &batch.sides),
        ] {
            if self.active(term) {
                let logits = embedding
                    .narrow(1, channels.start, channels.len())?
                    .affine(TEXT_LOGIT_SCALE, 0.0)?;
                let margin = TEXT_TARGET_MARGIN;
                let targets =
                    targets.to_dtype(logits.dtype())?.affine(1.0 - 2.0 * margin, margin)?;
                terms.push((term, logistic_loss(&logits, &targets)?));
            }
        }
        Ok(terms)
    }

    /// `L_diff` and the feature part of `L_vel` on normalised features: the body once (both
    /// streams carry the fused body), each present object's channels in its own stream.
    fn feature_terms(
        &self,
        window: &Window<'_>,
        prediction: &Tensor,
        target: &Tensor,
        terms: &mut Vec<(Term, Tensor)>,
    ) -> Result<()> {
        let (b, tf, d) = (window.batch, window.tf, window.width);
        let object_channel: Vec<f32> = (0..OBJECT_FEATURE_SIZE)
            .map(|c| {
                let hand_relative_only = LEFT_OFFSET_RANGE.contains(&c)
                    || RIGHT_OFFSET_RANGE.contains(&c)
                    || MIXTURE_RANGE.contains(&c);
                let supervised = self.representation == ObjectRepresentation::HandRelative
                    || !hand_relative_only;
                f32::from(u8::from(supervised))
            })
            .collect();
        let mut channels = vec![0.0f32; b * 2 * d];
        for i in 0..b {
            for s in 0..MAX_OBJECTS {
                let row = &mut channels[(i * 2 + s) * d..(i * 2 + s + 1) * d];
                if s == 0 {
                    row[window.layout.body_range()].fill(1.0);
                }
                if window.batch_data.presence_values[i][s] {
                    row[window.layout.object_range()].copy_from_slice(&object_channel);
                }
            }
        }
        let channel_sum: Vec<f32> =
            (0..b).map(|i| channels[i * 2 * d..(i + 1) * 2 * d].iter().sum()).collect();
        let channels = window.constant(channels, &[b, 2, 1, d])?;
        let diff = (prediction - target)?;
        if self.active(Term::Diffusion) {
            let frames: Vec<f32> =
                (0..b * tf).map(|n| window.frame_valid(n / tf, n % tf)).collect();
            let count: f32 = (0..b * tf).map(|n| frames[n] * channel_sum[n / tf]).sum();
            let mask = Mask {
                weight: channels.broadcast_mul(&window.constant(frames, &[b, 1, tf, 1])?)?,
                count,
            };
            terms.push((Term::Diffusion, mask.mean(&diff.sqr()?, 1.0)?));
        }
        let steps = window.steps();
        if self.active(Term::FeatureVelocity) && steps > 0 {
            let pairs = window.step_weights(|_| 1.0);
            let count: f32 = (0..b * steps).map(|n| pairs[n] * channel_sum[n / steps]).sum();
            let mask = Mask {
                weight: channels.broadcast_mul(&window.constant(pairs, &[b, 1, steps, 1])?)?,
                count,
            };
            let velocity = window.step_differences(&diff, 2)?;
            terms.push((Term::FeatureVelocity, mask.mean(&velocity.sqr()?, 1.0)?));
        }
        Ok(())
    }

    /// The terms that decode the prediction: through FK (joint velocity, foot contact), the
    /// object channels (Eq. 8, 10), the decoded object positions (Eq. 9) and the signed
    /// distances of the joints to the predicted-pose objects (penetration, Eq. 11).
    fn geometric_terms(
        &self,
        window: &Window<'_>,
        prediction: &Tensor,
        target: &Tensor,
        terms: &mut Vec<(Term, Tensor)>,
    ) -> Result<()> {
        let (b, tf) = (window.batch, window.tf);
        let raw = window.denormalise(prediction)?;
        let target_raw = window.denormalise(target)?;
        let body = self.body_kinematics(window, &raw)?;
        if self.active(Term::JointVelocity) && window.steps() > 0 {
            terms.push((Term::JointVelocity, self.joint_velocity(window, &body)?));
        }
        if self.active(Term::FootContact) && tf > 1 {
            terms.push((Term::FootContact, self.foot_contact(window, &body)?));
        }
        // The terms below read the objects against this body; without
        // `object_terms_move_root` its root is a constant to them.
        let body = if self.config.object_terms_move_root { body } else { body.with_root_fixed()? };

        // Objects: the prediction's 18 numbers per slot, decoded with the predicted wrists.
        let objects = window.layout.object_of(&raw)?; // [B, 2, T_f, 18]
        let target_objects = window.layout.object_of(&target_raw)?;
        let slots = window.slot_mask(false)?;
        let gated_slots = window.slot_mask(true)?;
        if self.active(Term::Mixture) {
            let predicted = tensor_mixture_weights(&objects)?;
            let wanted = tensor_softmax(&target_objects.narrow(3, MIXTURE_RANGE.start, 3)?)?;
            terms.push((Term::Mixture, slots.mean(&(predicted - wanted)?.sqr()?, 1.0)?));
        }
        // The predicted branch minus the data's, for `L_off` and the global branch's term.
        let branch_error = |r: std::ops::Range<usize>| {
            objects.narrow(3, r.start, r.len())? - target_objects.narrow(3, r.start, r.len())?
        };
        let cm2 = CENTIMETRES * CENTIMETRES;
        if self.active(Term::Offset) {
            let left = branch_error(LEFT_OFFSET_RANGE)?;
            let right = branch_error(RIGHT_OFFSET_RANGE)?;
            terms.push((Term::Offset, slots.mean(&(left.sqr()? + right.sqr()?)?, 0.5 * cm2)?));
        }
        if self.active(Term::Global) {
            let error = branch_error(GLOBAL_POSITION_RANGE)?;
            terms.push((Term::Global, slots.mean(&error.sqr()?, cm2)?));
        }
        let needs_position = self.active(Term::Translation)
            || self.active(Term::PutDown)
            || self.active(Term::Penetration)
            || self.active(Term::Distance);
        if !needs_position {
            return Ok(());
        }
        let object_positions = self.object_positions(&objects, &body, b, tf)?;
        if self.active(Term::Translation) || self.active(Term::PutDown) {
            let squared_error = (&object_positions
                - window.batch_data.object_positions.to_dtype(window.dtype)?)?
            .sqr()?;
            if self.active(Term::Translation) {
                terms.push((Term::Translation, gated_slots.mean(&squared_error, cm2)?));
            }
            if self.active(Term::PutDown) {
                // Every diffusion step: where a put-down ends is decided at the noisy ones.
                let ends = Mask::new(window, window.put_down_ends(), &[b, 2, tf, 1], 1)?;
                terms.push((Term::PutDown, ends.mean(&squared_error, cm2)?));
            }
        }
        if !(self.active(Term::Penetration) || self.active(Term::Distance)) {
            return Ok(());
        }
        // The contact terms see the object where the prediction puts it; without
        // `contact_moves_objects` its channels are constants to them, so that only the joints
        // (and, through the wrists, a held object with its hand) answer.
        let distances = if self.config.contact_moves_objects {
            self.signed_distances(window, &objects, &object_positions, &body)?
        } else {
            let fixed = objects.detach();
            let positions = self.object_positions(&fixed, &body, b, tf)?;
            self.signed_distances(window, &fixed, &positions, &body)?
        };
        if self.active(Term::Penetration) {
            let joints = Mask {
                weight: gated_slots.weight.clone(),
                count: gated_slots.count * window.joints as f32,
            };
            terms.push((Term::Penetration, joints.mean(&distances.neg()?.relu()?, 1.0)?));
        }
        if self.active(Term::Distance) {
            terms.push((Term::Distance, self.distance(window, &distances)?));
        }
        Ok(())
    }

    /// The predicted body through FK, roots measured from the sequence's first frame.
    ///
    /// # Shapes
    /// - `raw`: `[B, 2, T_f, D]` denormalised; positions `[B, T_f, J, 3]`, rotations
    ///   `[B, T_f, J, 3, 3]`
    fn body_kinematics(&self, window: &Window<'_>, raw: &Tensor) -> Result<BodyKinematics> {
        let body_raw = window.layout.stream_body_of(raw)?;
        let rotations = sixd_to_matrix(&window.layout.joint_rotations_of(&body_raw)?)?;
        let root = window
            .layout
            .root_of(&body_raw)?
            .broadcast_add(&window.batch_data.root_start.to_dtype(window.dtype)?)?;
        // Each window on its own body: the ground-truth joints are FK of the same offsets.
        let (positions, world_rotations) = tensor_forward_kinematics_per_sample(
            &self.skeleton,
            &window.batch_data.rest_offsets.to_dtype(window.dtype)?,
            &rotations,
            &root,
        )?;
        Ok(BodyKinematics { positions, world_rotations, root })
    }

    /// `L_vel` on joint positions: MSE of the error's frame-to-frame change, in cm (with
    /// `velocity_across_the_seam`, from the prefix's last frame on).
    fn joint_velocity(&self, window: &Window<'_>, body: &BodyKinematics) -> Result<Tensor> {
        let weights = window.step_weights(|i| window.gate[i]);
        let shape = [window.batch, window.steps(), 1, 1];
        let mask = Mask::new(window, weights, &shape, window.joints * 3)?;
        let error = (&body.positions - window.batch_data.joints.to_dtype(window.dtype)?)?
            .affine(CENTIMETRES, 0.0)?;
        mask.mean(&window.step_differences(&error, 1)?.sqr()?, 1.0)
    }

    /// Foot skating: the squared velocity (cm per frame) of the ankle and toe joints on frames
    /// where the ground truth has them in contact.
    fn foot_contact(&self, window: &Window<'_>, body: &BodyKinematics) -> Result<Tensor> {
        let (b, tf) = (window.batch, window.tf);
        let groups = self.skeleton.groups();
        let feet = [
            groups.left_foot[0],
            groups.left_foot[groups.left_foot.len() - 1],
            groups.right_foot[0],
            groups.right_foot[groups.right_foot.len() - 1],
        ];
        let weights: Vec<f32> = (0..b * (tf - 1) * 4)
            .map(|n| {
                let (i, k, f) = (n / ((tf - 1) * 4), (n / 4) % (tf - 1), n % 4);
                window.batch_data.foot_contact_values[(i * tf + k) * 4 + f]
                    * window.frame_valid(i, k)
                    * window.frame_valid(i, k + 1)
                    * window.gate[i]
            })
            .collect();
        let mask = Mask::new(window, weights, &[b, tf - 1, 4, 1], 1)?;
        let index = Tensor::from_vec(feet.map(|j| j as u32).to_vec(), 4, &window.device)?;
        let foot = body.positions.index_select(&index, 2)?.affine(CENTIMETRES, 0.0)?; // [B, T_f, 4, 3]
        mask.mean(&frame_differences(&foot, 1)?.sqr()?, 1.0)
    }

    /// Object positions decoded from the prediction: the softmax mixture of Eq. 4 with the
    /// predicted wrists, or the global branch alone for the `global_only` variant.
    ///
    /// # Shapes
    /// - `objects`: `[B, 2, T_f, 18]`; returns `[B, 2, T_f, 3]`
    fn object_positions(
        &self,
        objects: &Tensor,
        body: &BodyKinematics,
        b: usize,
        tf: usize,
    ) -> Result<Tensor> {
        Ok(match self.representation {
            ObjectRepresentation::HandRelative => {
                let wrists = TensorWrists::from_fk(
                    &body.positions,
                    &body.world_rotations,
                    self.skeleton.groups().left_wrist,
                    self.skeleton.groups().right_wrist,
                )?;
                let spread3 = |t: &Tensor| t.unsqueeze(1)?.broadcast_as((b, 2, tf, 3));
                let spread33 = |t: &Tensor| t.unsqueeze(1)?.broadcast_as((b, 2, tf, 3, 3));
                let wrists = TensorWrists {
                    left_position: spread3(&wrists.left_position)?,
                    left_rotation: spread33(&wrists.left_rotation)?,
                    right_position: spread3(&wrists.right_position)?,
                    right_rotation: spread33(&wrists.right_rotation)?,
                };
                tensor_decode_position(objects, &wrists)?
            }
            ObjectRepresentation::GlobalOnly => {
                objects.narrow(3, GLOBAL_POSITION_RANGE.start, 3)?
            }
        })
    }

    /// Signed distances in cm of every joint to each predicted-pose object (see the module
    /// documentation for the surface-sample approximation).
    ///
    /// # Shapes
    /// - returns `[B, 2, T_f, J]`
    fn signed_distances(
        &self,
        window: &Window<'_>,
        objects: &Tensor,
        object_positions: &Tensor,
        body: &BodyKinematics,
    ) -> Result<Tensor> {
        let (b, tf, joints) = (window.batch, window.tf, window.joints);
        let object_rotations = tensor_decode_rotation(objects)?; // [B, 2, T_f, 3, 3]
        let object_rotations = if self.config.contact_turns_objects {
            object_rotations
        } else {
            object_rotations.detach()
        };
        let relative =
            body.positions.unsqueeze(1)?.broadcast_sub(&object_positions.unsqueeze(3)?)?; // [B, 2, T_f, J, 3]
        let local = rotate_inverse(&object_rotations.unsqueeze(3)?, &relative)?;
        let slots = &window.batch_data.clouds;
        let search = self.surface_search.unwrap_or(SurfaceSearch::for_device(&window.device));
        let (nearest, normals) = match search {
            SurfaceSearch::Host => {
                let values: Vec<f32> =
                    local.detach().to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
                let (nearest, normals) = nearest_on_host(&values, slots, &self.clouds, tf * joints);
                let shape = [b, 2, tf, joints, 3];
                (window.constant(nearest, &shape)?, window.constant(normals, &shape)?)
            }
            SurfaceSearch::Tensor => {
                let queries = local.reshape((b, 2, tf * joints, 3))?;
                let (nearest, normals) =
                    self.device_clouds(&window.device)?.nearest(&queries, slots)?;
                let shape = (b, 2, tf, joints, 3);
                (
                    nearest.reshape(shape)?.to_dtype(window.dtype)?,
                    normals.reshape(shape)?.to_dtype(window.dtype)?,
                )
            }
        };
        Ok(((local - nearest)? * normals)?.sum(D::Minus1)?.affine(CENTIMETRES, 0.0)?)
    }

    /// `L_dist` (Eq. 11): Huber on the hand joints' signed distances where the ground truth has
    /// them within the approach radius `d_min`.
    fn distance(&self, window: &Window<'_>, distances: &Tensor) -> Result<Tensor> {
        let (b, tf) = (window.batch, window.tf);
        let groups = self.skeleton.groups();
        let hand: Vec<u32> =
            groups.left_hand.iter().chain(&groups.right_hand).map(|&j| j as u32).collect();
        let h = hand.len();
        let radius = self.config.approach_radius as f32;
        let slot_frames = window.slot_frames(true);
        let within: Vec<f32> = (0..b * 2 * tf * h)
            .map(|n| {
                let near = window.batch_data.hand_distance_values[n] < radius;
                f32::from(u8::from(near)) * slot_frames[n / h]
            })
            .collect();
        let mask = Mask::new(window, within, &[b, 2, tf, h], 1)?;
        let index = Tensor::from_vec(hand, h, &window.device)?;
        let predicted = distances.index_select(&index, 3)?;
        let wanted =
            window.batch_data.hand_distances.to_dtype(window.dtype)?.affine(CENTIMETRES, 0.0)?;
        mask.mean(&huber(&(predicted - wanted)?, self.config.huber_delta_cm)?, 1.0)
    }
}

/// The predicted body after FK.
struct BodyKinematics {
    /// `[B, T_f, J, 3]` joint positions in metres.
    positions: Tensor,
    /// `[B, T_f, J, 3, 3]` world rotations.
    world_rotations: Tensor,
    /// `[B, T_f, 3]` the root's positions, from which every joint is placed.
    root: Tensor,
}

impl BodyKinematics {
    /// The same body with the root's positions constants: the joints keep their values, and a
    /// gradient on them reaches the joint rotations but not the root (FK adds the root to
    /// every joint alike, so moving them by `root.detach() - root`, zero in value, takes the
    /// root's part of the gradient away).
    fn with_root_fixed(self) -> Result<Self> {
        let shift = (self.root.detach() - &self.root)?.unsqueeze(2)?;
        Ok(Self {
            positions: self.positions.broadcast_add(&shift)?,
            world_rotations: self.world_rotations,
            root: self.root.detach(),
        })
    }
}

/// A batch's predicted window with what every term needs: sizes, which frames are real, the
/// gate of the geometric terms and the statistics.
struct Window<'a> {
    batch_data: &'a Batch,
    batch: usize,
    tp: usize,
    tf: usize,
    width: usize,
    layout: FeatureLayout,
    joints: usize,
    dtype: DType,
    device: candle_core::Device,
    /// Per sample, 1 when its diffusion step is at most `geometric_max_timestep`.
    gate: Vec<f32>,
    /// Whether the velocity terms measure the step into the window:
    /// `velocity_across_the_seam`, and a prefix to step from.
    seam: bool,
    normaliser: Normaliser,
}

impl<'a> Window<'a> {
    fn new(
        context: &LossContext,
        prediction: &Tensor,
        batch_data: &'a Batch,
        timesteps: &[usize],
    ) -> Result<Self> {
        let (batch, _, tf, width) = prediction.dims4()?;
        let (dtype, device) = (prediction.dtype(), prediction.device().clone());
        let joints = context.skeleton.joint_count();
        let gate = timesteps
            .iter()
            .map(|&t| match context.config.geometric_max_timestep {
                Some(limit) if t > limit => 0.0,
                _ => 1.0,
            })
            .collect();
        Ok(Self {
            batch_data,
            batch,
            tp: context.prefix_frames,
            tf,
            width,
            layout: FeatureLayout::new(joints),
            joints,
            dtype,
            gate,
            seam: context.config.velocity_across_the_seam && context.prefix_frames > 0,
            normaliser: Normaliser::new(&context.mean, &context.std, dtype, &device)?,
            device,
        })
    }

    /// A constant tensor of the prediction's dtype and device.
    fn constant(&self, values: Vec<f32>, shape: &[usize]) -> Result<Tensor> {
        Ok(Tensor::from_vec(values, shape, &self.device)?.to_dtype(self.dtype)?)
    }

    /// 1 when predicted frame `k` of sample `i` is real (not padding).
    fn frame_valid(&self, i: usize, k: usize) -> f32 {
        let t_all = self.tp + self.tf;
        self.batch_data.frame_mask_values[i * t_all + self.tp + k]
    }

    /// The frame-to-frame steps the velocity terms measure: between consecutive predicted
    /// frames, and with [`Self::seam`] also the one from the prefix's last frame to the first.
    fn steps(&self) -> usize {
        if self.seam { self.tf } else { self.tf.saturating_sub(1) }
    }

    /// Per sample and step of [`Self::steps`] `[B, steps]`: both its frames real, times
    /// `per_sample(i)`.
    fn step_weights(&self, per_sample: impl Fn(usize) -> f32) -> Vec<f32> {
        let (steps, t_all) = (self.steps(), self.tp + self.tf);
        if steps == 0 {
            return Vec::new();
        }
        // The first step's first frame, counted over the prefix and the predicted frames.
        let first = t_all - 1 - steps;
        (0..self.batch * steps)
            .map(|n| {
                let (i, k) = (n / steps, n % steps);
                let real = |frame: usize| self.batch_data.frame_mask_values[i * t_all + frame];
                real(first + k) * real(first + k + 1) * per_sample(i)
            })
            .collect()
    }

    /// The frame-to-frame differences of `error` over the predicted frames along `dim`, one per
    /// step of [`Self::steps`]: with [`Self::seam`], the prefix's last frame comes first, with
    /// an error of 0 (the prefix is the data), so that the first difference is the step into
    /// the window.
    fn step_differences(&self, error: &Tensor, dim: usize) -> Result<Tensor> {
        if !self.seam {
            return frame_differences(error, dim);
        }
        let before = error.narrow(dim, 0, 1)?.zeros_like()?;
        frame_differences(&Tensor::cat(&[&before, error], dim)?, dim)
    }

    /// `[B, 2, T_f]`: real frames of slots that hold an object (and, `gated`, of samples whose
    /// step passes the gate).
    fn slot_frames(&self, gated: bool) -> Vec<f32> {
        let tf = self.tf;
        let mut frames = vec![0.0f32; self.batch * 2 * tf];
        for i in 0..self.batch {
            let gate = if gated { self.gate[i] } else { 1.0 };
            for s in 0..MAX_OBJECTS {
                if self.batch_data.presence_values[i][s] {
                    for k in 0..tf {
                        frames[(i * 2 + s) * tf + k] = self.frame_valid(i, k) * gate;
                    }
                }
            }
        }
        frames
    }

    /// `[B, 2, T_f]`: 1 on the last real predicted frame of each object set down within the
    /// window ([`Batch::put_down`]), 0 elsewhere.
    fn put_down_ends(&self) -> Vec<f32> {
        let tf = self.tf;
        let mut ends = vec![0.0f32; self.batch * 2 * tf];
        for i in 0..self.batch {
            let Some(last) = (0..tf).rev().find(|&k| self.frame_valid(i, k) > 0.0) else {
                continue;
            };
            for s in 0..MAX_OBJECTS {
                if self.batch_data.put_down[i][s] && self.batch_data.presence_values[i][s] {
                    ends[(i * 2 + s) * tf + last] = 1.0;
                }
            }
        }
        ends
    }

    /// [`Window::slot_frames`] as a mask over `[B, 2, T_f, 1]`.
    fn slot_mask(&self, gated: bool) -> Result<Mask> {
        let shape = [self.batch, 2, self.tf, 1];
        Mask::new(self, self.slot_frames(gated), &shape, 1)
    }

    /// Normalised features back to raw ones (`x std + mean`).
    fn denormalise(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.normaliser.denormalise(x)?)
    }
}

/// A masked mean: the weights broadcast over the values, and how many values they count.
struct Mask {
    weight: Tensor,
    count: f32,
}

impl Mask {
    /// Weights of shape `shape`, each covering `values_per_weight` values of the term.
    fn new(
        window: &Window<'_>,
        weights: Vec<f32>,
        shape: &[usize],
        values_per_weight: usize,
    ) -> Result<Self> {
        let count = weights.iter().sum::<f32>() * values_per_weight as f32;
        Ok(Self { weight: window.constant(weights, shape)?, count })
    }

    /// `scale * sum(values * weight) / count` (a count below 1 counts as 1: an empty mask
    /// gives 0).
    fn mean(&self, values: &Tensor, scale: f64) -> Result<Tensor> {
        Ok(values
            .broadcast_mul(&self.weight)?
            .sum_all()?
            .affine(scale / f64::from(self.count.max(1.0)), 0.0)?)
    }
}

/// Frame-to-frame differences along `dim`.
fn frame_differences(x: &Tensor, dim: usize) -> Result<Tensor> {
    let frames = x.dim(dim)?;
    Ok((x.narrow(dim, 1, frames - 1)? - x.narrow(dim, 0, frames - 1)?)?)
}

/// The Huber function `rho_delta` elementwise: `e^2 / 2` within `delta`, `delta (|e| - delta/2)`
/// beyond, written as `q^2 / 2 + delta (|e| - q)` with `q = min(|e|, delta)`.
pub fn huber(error: &Tensor, delta: f64) -> Result<Tensor> {
    let magnitude = error.abs()?;
    let quadratic = magnitude.minimum(delta)?;
    let linear = (&magnitude - &quadratic)?;
    Ok((quadratic.sqr()?.affine(0.5, 0.0)? + linear.affine(delta, 0.0)?)?)
}
