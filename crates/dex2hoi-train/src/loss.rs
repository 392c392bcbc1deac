//! The training objective (paper Sec. 3.3, Eq. 8-12).
//!
//! `L = w_diff L_diff + L_vel + foot + penetration + lambda_w L_mix + lambda_t L_trans +
//! lambda_o L_off + lambda_p L_dist` (Eq. 12; the velocity, foot and penetration terms are the
//! "geometry regularization losses" the paper takes from InterGen, CoDA and HOIDiNi). Every term
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
//! constant); `d` is, in the joint, the object's rotation and its decoded position. Within the
//! 10 cm of `L_dist` the samples (512 per object, about 1 cm apart on a mug) make this a close
//! stand-in for the mesh's signed distance, and it needs no mesh queries in the loop.

use candle_core::{D, DType, Tensor};
use rayon::prelude::*;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::features::OBJECT_FEATURE_SIZE;
use dex2hoi_model::ObjectRepresentation;
use dex2hoi_repr::Skeleton;
use dex2hoi_repr::object_repr::{
    GLOBAL_POSITION_RANGE, LEFT_OFFSET_RANGE, MIXTURE_RANGE, RIGHT_OFFSET_RANGE, TensorWrists,
    tensor_decode_position, tensor_decode_rotation, tensor_mixture_weights, tensor_softmax,
};
use dex2hoi_repr::rotation::tensor::{rotate_inverse, sixd_to_matrix};
use dex2hoi_repr::tensor_forward_kinematics;

use crate::batch::{Batch, SurfaceCloud};
use crate::config::LossConfig;
use crate::error::Result;

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
    /// `L_dist` (Eq. 11).
    Distance,
}

impl Term {
    /// Every term, in reporting order.
    pub const ALL: [Term; 9] = [
        Term::Diffusion,
        Term::FeatureVelocity,
        Term::JointVelocity,
        Term::FootContact,
        Term::Penetration,
        Term::Mixture,
        Term::Translation,
        Term::Offset,
        Term::Distance,
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
            Term::Distance => "distance",
        }
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
            Term::Distance => config.distance,
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
        Self { config, representation, skeleton, prefix_frames, mean, std, clouds }
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
            Term::Mixture | Term::Offset => c.mixture_supervision && hand_relative,
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
        let (b, _, tf, d) = prediction.dims4()?;
        let (dtype, device) = (prediction.dtype(), prediction.device().clone());
        let tp = self.prefix_frames;
        let t_all = tp + tf;
        let joints = self.skeleton.joint_count();
        let body = 6 * joints + 3;
        let constant = |values: Vec<f32>, shape: &[usize]| -> Result<Tensor> {
            Ok(Tensor::from_vec(values, shape, &device)?.to_dtype(dtype)?)
        };
        let frame_valid = |i: usize, k: usize| batch.frame_mask_values[i * t_all + tp + k];
        let gate: Vec<f32> = timesteps
            .iter()
            .map(|&t| match self.config.geometric_max_timestep {
                Some(limit) if t > limit => 0.0,
                _ => 1.0,
            })
            .collect();
        let target = batch.features.narrow(2, tp, tf)?.to_dtype(dtype)?;
        let mut terms: Vec<(Term, Tensor)> = Vec::new();

        // L_diff and the feature part of L_vel: the body once (both streams carry the fused
        // body), each present object's channels in its own stream.
        let object_channel: Vec<f32> = (0..OBJECT_FEATURE_SIZE)
            .map(|c| {
                let hand_relative_only = LEFT_OFFSET_RANGE.contains(&c)
                    || RIGHT_OFFSET_RANGE.contains(&c)
                    || MIXTURE_RANGE.contains(&c);
                if self.representation == ObjectRepresentation::GlobalOnly && hand_relative_only {
                    0.0
                } else {
                    1.0
                }
            })
            .collect();
        let mut channels = vec![0.0f32; b * 2 * d];
        for i in 0..b {
            for s in 0..MAX_OBJECTS {
                let row = &mut channels[(i * 2 + s) * d..(i * 2 + s + 1) * d];
                if s == 0 {
                    row[..body].fill(1.0);
                }
                if batch.presence_values[i][s] {
                    row[body..].copy_from_slice(&object_channel);
                }
            }
        }
        let channel_sum: Vec<f32> =
            (0..b).map(|i| channels[i * 2 * d..(i + 1) * 2 * d].iter().sum()).collect();
        let diff = (prediction - &target)?;
        if self.active(Term::Diffusion) {
            let frames: Vec<f32> = (0..b * tf).map(|n| frame_valid(n / tf, n % tf)).collect();
            let count: f32 = (0..b * tf).map(|n| frames[n] * channel_sum[n / tf]).sum();
            let weight = constant(channels.clone(), &[b, 2, 1, d])?
                .broadcast_mul(&constant(frames, &[b, 1, tf, 1])?)?;
            let value =
                (diff.sqr()? * weight)?.sum_all()?.affine(1.0 / f64::from(count.max(1.0)), 0.0)?;
            terms.push((Term::Diffusion, value));
        }
        if self.active(Term::FeatureVelocity) && tf > 1 {
            let pairs: Vec<f32> = (0..b * (tf - 1))
                .map(|n| {
                    let (i, k) = (n / (tf - 1), n % (tf - 1));
                    frame_valid(i, k) * frame_valid(i, k + 1)
                })
                .collect();
            let count: f32 = (0..b * (tf - 1)).map(|n| pairs[n] * channel_sum[n / (tf - 1)]).sum();
            let weight = constant(channels.clone(), &[b, 2, 1, d])?
                .broadcast_mul(&constant(pairs, &[b, 1, tf - 1, 1])?)?;
            let velocity = (diff.narrow(2, 1, tf - 1)? - diff.narrow(2, 0, tf - 1)?)?;
            let value = (velocity.sqr()? * weight)?
                .sum_all()?
                .affine(1.0 / f64::from(count.max(1.0)), 0.0)?;
            terms.push((Term::FeatureVelocity, value));
        }

        let geometric = [
            Term::JointVelocity,
            Term::FootContact,
            Term::Penetration,
            Term::Mixture,
            Term::Translation,
            Term::Offset,
            Term::Distance,
        ]
        .iter()
        .any(|&t| self.active(t));
        if geometric {
            self.geometric_terms(prediction, &target, batch, &gate, &mut terms)?;
        }

        let mut total: Option<Tensor> = None;
        for (term, value) in &terms {
            let weighted = value.affine(term.weight(&self.config), 0.0)?;
            total = Some(match total {
                Some(t) => (t + weighted)?,
                None => weighted,
            });
        }
        let total = match total {
            Some(t) => t,
            None => Tensor::zeros((), dtype, &device)?,
        };
        Ok(Objective { total, terms })
    }

    fn geometric_terms(
        &self,
        prediction: &Tensor,
        target: &Tensor,
        batch: &Batch,
        gate: &[f32],
        terms: &mut Vec<(Term, Tensor)>,
    ) -> Result<()> {
        let (b, _, tf, d) = prediction.dims4()?;
        let (dtype, device) = (prediction.dtype(), prediction.device().clone());
        let tp = self.prefix_frames;
        let t_all = tp + tf;
        let joints = self.skeleton.joint_count();
        let body = 6 * joints + 3;
        let cm = CENTIMETRES;
        let constant = |values: Vec<f32>, shape: &[usize]| -> Result<Tensor> {
            Ok(Tensor::from_vec(values, shape, &device)?.to_dtype(dtype)?)
        };
        let frame_valid = |i: usize, k: usize| batch.frame_mask_values[i * t_all + tp + k];
        let mean = constant(self.mean.clone(), &[d])?;
        let std = constant(self.std.clone(), &[d])?;
        let raw = prediction.broadcast_mul(&std)?.broadcast_add(&mean)?;
        let target_raw = target.broadcast_mul(&std)?.broadcast_add(&mean)?;

        // Body: 6D -> matrices -> FK, roots measured from the sequence's first frame.
        let body_raw = raw.narrow(1, 0, 1)?.squeeze(1)?.narrow(2, 0, body)?;
        let rotations =
            sixd_to_matrix(&body_raw.narrow(2, 0, 6 * joints)?.reshape((b, tf, joints, 6))?)?;
        let root =
            body_raw.narrow(2, 6 * joints, 3)?.broadcast_add(&batch.root_start.to_dtype(dtype)?)?;
        let (positions, world_rotations) =
            tensor_forward_kinematics(&self.skeleton, &rotations, &root)?;

        if self.active(Term::JointVelocity) && tf > 1 {
            let weights: Vec<f32> = (0..b * (tf - 1))
                .map(|n| {
                    let (i, k) = (n / (tf - 1), n % (tf - 1));
                    frame_valid(i, k) * frame_valid(i, k + 1) * gate[i]
                })
                .collect();
            let count = weights.iter().sum::<f32>() * (joints * 3) as f32;
            let error = (&positions - batch.joints.to_dtype(dtype)?)?.affine(cm, 0.0)?;
            let velocity = (error.narrow(1, 1, tf - 1)? - error.narrow(1, 0, tf - 1)?)?;
            let value = velocity
                .sqr()?
                .broadcast_mul(&constant(weights, &[b, tf - 1, 1, 1])?)?
                .sum_all()?
                .affine(1.0 / f64::from(count.max(1.0)), 0.0)?;
            terms.push((Term::JointVelocity, value));
        }

        if self.active(Term::FootContact) && tf > 1 {
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
                    batch.foot_contact_values[(i * tf + k) * 4 + f]
                        * frame_valid(i, k)
                        * frame_valid(i, k + 1)
                        * gate[i]
                })
                .collect();
            let count: f32 = weights.iter().sum();
            let index = Tensor::from_vec(feet.map(|j| j as u32).to_vec(), 4, &device)?;
            let foot = positions.index_select(&index, 2)?.affine(cm, 0.0)?; // [B, T_f, 4, 3]
            let velocity = (foot.narrow(1, 1, tf - 1)? - foot.narrow(1, 0, tf - 1)?)?;
            let value = velocity
                .sqr()?
                .broadcast_mul(&constant(weights, &[b, tf - 1, 4, 1])?)?
                .sum_all()?
                .affine(1.0 / f64::from(count.max(1.0)), 0.0)?;
            terms.push((Term::FootContact, value));
        }

        // Objects: the prediction's 18 numbers per slot, decoded with the predicted wrists.
        let objects = raw.narrow(3, body, OBJECT_FEATURE_SIZE)?; // [B, 2, T_f, 18]
        let target_objects = target_raw.narrow(3, body, OBJECT_FEATURE_SIZE)?;
        let mut slot_frames = vec![0.0f32; b * 2 * tf];
        let mut slot_frames_gated = vec![0.0f32; b * 2 * tf];
        for i in 0..b {
            for s in 0..MAX_OBJECTS {
                if batch.presence_values[i][s] {
                    for k in 0..tf {
                        slot_frames[(i * 2 + s) * tf + k] = frame_valid(i, k);
                        slot_frames_gated[(i * 2 + s) * tf + k] = frame_valid(i, k) * gate[i];
                    }
                }
            }
        }
        let slot_count = slot_frames.iter().sum::<f32>().max(1.0);
        let slot_count_gated = slot_frames_gated.iter().sum::<f32>().max(1.0);
        let slot_mask = constant(slot_frames.clone(), &[b, 2, tf, 1])?;
        let slot_mask_gated = constant(slot_frames_gated.clone(), &[b, 2, tf, 1])?;

        if self.active(Term::Mixture) {
            let predicted = tensor_mixture_weights(&objects)?;
            let wanted = tensor_softmax(&target_objects.narrow(3, MIXTURE_RANGE.start, 3)?)?;
            let value = (predicted - wanted)?
                .sqr()?
                .broadcast_mul(&slot_mask)?
                .sum_all()?
                .affine(1.0 / f64::from(slot_count), 0.0)?;
            terms.push((Term::Mixture, value));
        }
        if self.active(Term::Offset) {
            let part = |t: &Tensor, r: std::ops::Range<usize>| t.narrow(3, r.start, r.len());
            let left =
                (part(&objects, LEFT_OFFSET_RANGE)? - part(&target_objects, LEFT_OFFSET_RANGE)?)?;
            let right =
                (part(&objects, RIGHT_OFFSET_RANGE)? - part(&target_objects, RIGHT_OFFSET_RANGE)?)?;
            let value = (left.sqr()? + right.sqr()?)?
                .broadcast_mul(&slot_mask)?
                .sum_all()?
                .affine(0.5 * cm * cm / f64::from(slot_count), 0.0)?;
            terms.push((Term::Offset, value));
        }

        let needs_position = self.active(Term::Translation)
            || self.active(Term::Penetration)
            || self.active(Term::Distance);
        if !needs_position {
            return Ok(());
        }
        let object_positions = match self.representation {
            ObjectRepresentation::HandRelative => {
                let wrists = TensorWrists::from_fk(
                    &positions,
                    &world_rotations,
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
                tensor_decode_position(&objects, &wrists)?
            }
            ObjectRepresentation::GlobalOnly => {
                objects.narrow(3, GLOBAL_POSITION_RANGE.start, 3)?
            }
        };
        if self.active(Term::Translation) {
            let value = (&object_positions - batch.object_positions.to_dtype(dtype)?)?
                .sqr()?
                .broadcast_mul(&slot_mask_gated)?
                .sum_all()?
                .affine(cm * cm / f64::from(slot_count_gated), 0.0)?;
            terms.push((Term::Translation, value));
        }
        if !(self.active(Term::Penetration) || self.active(Term::Distance)) {
            return Ok(());
        }

        // Signed distances of every joint to each predicted-pose object, [B, 2, T_f, J].
        let object_rotations = tensor_decode_rotation(&objects)?; // [B, 2, T_f, 3, 3]
        let relative = positions.unsqueeze(1)?.broadcast_sub(&object_positions.unsqueeze(3)?)?; // [B, 2, T_f, J, 3]
        let local = rotate_inverse(&object_rotations.unsqueeze(3)?, &relative)?;
        let local_values: Vec<f32> =
            local.detach().to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        let (nearest, normals) =
            nearest_samples(&local_values, &batch.clouds, &self.clouds, b, tf * joints);
        let distances = ((local - constant(nearest, &[b, 2, tf, joints, 3])?)?
            * constant(normals, &[b, 2, tf, joints, 3])?)?
        .sum(D::Minus1)?
        .affine(cm, 0.0)?;

        if self.active(Term::Penetration) {
            let value = distances
                .neg()?
                .relu()?
                .broadcast_mul(&slot_mask_gated)?
                .sum_all()?
                .affine(1.0 / f64::from(slot_count_gated * joints as f32), 0.0)?;
            terms.push((Term::Penetration, value));
        }
        if self.active(Term::Distance) {
            let groups = self.skeleton.groups();
            let hand: Vec<u32> =
                groups.left_hand.iter().chain(&groups.right_hand).map(|&j| j as u32).collect();
            let h = hand.len();
            let radius = self.config.approach_radius as f32;
            let within: Vec<f32> = (0..b * 2 * tf * h)
                .map(|n| {
                    let row = n / h;
                    let near = batch.hand_distance_values[n] < radius;
                    f32::from(u8::from(near)) * slot_frames_gated[row]
                })
                .collect();
            let count = within.iter().sum::<f32>().max(1.0);
            let index = Tensor::from_vec(hand, h, &device)?;
            let predicted = distances.index_select(&index, 3)?;
            let error = (predicted - batch.hand_distances.to_dtype(dtype)?.affine(cm, 0.0)?)?;
            let value = huber(&error, self.config.huber_delta_cm)?
                .broadcast_mul(&constant(within, &[b, 2, tf, h])?)?
                .sum_all()?
                .affine(1.0 / f64::from(count), 0.0)?;
            terms.push((Term::Distance, value));
        }
        Ok(())
    }
}

/// The Huber function `rho_delta` elementwise: `e^2 / 2` within `delta`, `delta (|e| - delta/2)`
/// beyond, written as `q^2 / 2 + delta (|e| - q)` with `q = min(|e|, delta)`.
pub fn huber(error: &Tensor, delta: f64) -> Result<Tensor> {
    let magnitude = error.abs()?;
    let quadratic = magnitude.minimum(delta)?;
    let linear = (&magnitude - &quadratic)?;
    Ok((quadratic.sqr()?.affine(0.5, 0.0)? + linear.affine(delta, 0.0)?)?)
}

/// For every query point (object frame) of every window and slot, the nearest surface sample of
/// the slot's object and its normal (zeros for an empty slot).
///
/// # Shapes
/// - `local`: `[B, 2, Q, 3]` flattened; returns two such arrays
fn nearest_samples(
    local: &[f32],
    slots: &[[Option<usize>; MAX_OBJECTS]],
    clouds: &[SurfaceCloud],
    batch: usize,
    queries: usize,
) -> (Vec<f32>, Vec<f32>) {
    let mut nearest = vec![0.0f32; local.len()];
    let mut normals = vec![0.0f32; local.len()];
    nearest
        .par_chunks_mut(queries * 3)
        .zip(normals.par_chunks_mut(queries * 3))
        .enumerate()
        .for_each(|(row, (nearest, normals))| {
            let (i, s) = (row / 2, row % 2);
            let Some(cloud) = slots.get(i).and_then(|slots| slots[s]).map(|c| &clouds[c]) else {
                return;
            };
            let points = &local[row * queries * 3..(row + 1) * queries * 3];
            for q in 0..queries {
                let x = glam::Vec3::from_slice(&points[q * 3..q * 3 + 3]);
                let mut best = (f32::INFINITY, 0);
                for (k, p) in cloud.points.iter().enumerate() {
                    let distance = x.distance_squared(*p);
                    if distance < best.0 {
                        best = (distance, k);
                    }
                }
                nearest[q * 3..q * 3 + 3].copy_from_slice(&cloud.points[best.1].to_array());
                normals[q * 3..q * 3 + 3].copy_from_slice(&cloud.normals[best.1].to_array());
            }
        });
    debug_assert_eq!(local.len(), batch * 2 * queries * 3);
    (nearest, normals)
}
