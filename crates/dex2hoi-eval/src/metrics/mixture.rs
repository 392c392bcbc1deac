//! The hand-object mixture of paper Eq. 4: its weights from generated object features, and how
//! often they pick the hand that holds the object in the ground truth.

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_repr::object_repr::{MIXTURE_RANGE, OBJECT_FEATURE_SIZE, softmax3};

use crate::error::{EvalError, Result};

use super::contact::hand_flags;
use super::sample::check_array;

/// The mixture weights `softmax(alpha)` (Eq. 4) of object features.
///
/// # Shapes
/// - `object_features`: `[T, 2, 18]` (the logits sit at [`MIXTURE_RANGE`]); returns
///   `[T, 2, 3]`.
///
/// # Errors
/// A length that is not a multiple of `2 * 18`, non-finite logits.
pub fn mixture_weights_from_features(object_features: &[f32]) -> Result<Vec<f32>> {
    let per_frame = MAX_OBJECTS * OBJECT_FEATURE_SIZE;
    if !object_features.len().is_multiple_of(per_frame) {
        return Err(EvalError::invalid(
            "object features",
            format!("[T, {MAX_OBJECTS}, {OBJECT_FEATURE_SIZE}]"),
            format!("{} numbers", object_features.len()),
        ));
    }
    let mut weights = Vec::with_capacity(object_features.len() / OBJECT_FEATURE_SIZE * 3);
    for (i, features) in object_features.chunks_exact(OBJECT_FEATURE_SIZE).enumerate() {
        let logits: [f32; 3] = std::array::from_fn(|k| features[MIXTURE_RANGE.start + k]);
        if logits.iter().any(|v| !v.is_finite()) {
            return Err(EvalError::invalid(
                "mixture logits",
                "finite numbers",
                format!("{logits:?} at frame {}, slot {}", i / MAX_OBJECTS, i % MAX_OBJECTS),
            ));
        }
        weights.extend(softmax3(logits));
    }
    Ok(weights)
}

/// The counts behind [`mixture_agreement`]: `(agreeing, judged)` slot-frames.
///
/// # Shapes
/// - `weights`: `[T, 2, 3]` (left, right, global; weights or logits), `truth_contact`:
///   `[T, 2, 2]`, the same `T`.
///
/// # Errors
/// Lengths that do not match, non-finite numbers.
pub fn mixture_agreement_counts(
    weights: &[f32],
    truth_contact: &[f32],
    present: [bool; MAX_OBJECTS],
) -> Result<(usize, usize)> {
    let truth = hand_flags(truth_contact)?;
    let frames = truth.len();
    check_array("mixture weights", weights, frames * MAX_OBJECTS * 3, "[T, 2, 3]", frames)?;
    let mut agree = 0;
    let mut judged = 0;
    for (t, hands) in truth.iter().enumerate() {
        for slot in (0..MAX_OBJECTS).filter(|&s| present[s]) {
            let holder = match hands[slot] {
                [true, false] => 0,
                [false, true] => 1,
                _ => continue,
            };
            let base = (t * MAX_OBJECTS + slot) * 3;
            let w = &weights[base..base + 3];
            // The first of equal maxima wins (left before right before global).
            let argmax = (1..3).fold(0, |best, k| if w[k] > w[best] { k } else { best });
            judged += 1;
            agree += usize::from(argmax == holder);
        }
    }
    Ok((agree, judged))
}

/// Mixture agreement: over the slot-frames of present objects where **exactly one** hand holds
/// the object in the ground truth, the share where the argmax of the predicted mixture weights
/// (Eq. 4: left, right, global) is that hand. `None` when there are no such slot-frames.
///
/// # Shapes
/// - `weights`: `[T, 2, 3]` (weights or logits), `truth_contact`: `[T, 2, 2]`
///   ([`ProcessedSequence::hand_contact`](dex2hoi_data::features::ProcessedSequence::hand_contact)), the same `T`.
///
/// # Errors
/// As [`mixture_agreement_counts`].
pub fn mixture_agreement(
    weights: &[f32],
    truth_contact: &[f32],
    present: [bool; MAX_OBJECTS],
) -> Result<Option<f64>> {
    let (agree, judged) = mixture_agreement_counts(weights, truth_contact, present)?;
    Ok((judged > 0).then(|| agree as f64 / judged as f64))
}
