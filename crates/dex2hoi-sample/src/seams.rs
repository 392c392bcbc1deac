//! Continuous seams, a rule of the autoregressive sampler beyond the paper: each window's body
//! carries on from its prefix.
//!
//! Why: the model's first predicted frame does not continue its prefix. Where one window joins
//! the next the body jumps a median 1.3-2 cm per joint in one frame (the data move 0.2 cm
//! there), a hand up to 6-16 cm, and a jump of the root stays for the rest of the window, so
//! that over ten seconds the person drifts up or down by the sum of the jumps, the feet into
//! the floor or off it (docs/results/long-generations.md, "The seams between windows"). The
//! loss option `velocity_across_the_seam` reduces the jump in training; this rule removes it
//! when sampling, much as an animation engine blends from one clip into the next by the offset
//! between them (inertialization). On each window, against where the prefix leads (its last
//! frame plus its last step, for each body feature):
//! - the root displacement is moved by the first frame's offset on every frame, so the
//!   window's own root motion starts where the prefix leads;
//! - the joint rotations (6D) are moved by the first frame's offset fading to none over
//!   [`fade_frames`] frames (a raised cosine), so the pose turns smoothly into the model's own.
//!
//! Objects are not moved: a held object follows its hand through the hand-relative decoding,
//! and free ones are the objects-at-rest rule's ([`crate::rest`]).
//!
//! Normalisation is an affine map per feature and the rule is an affine combination of frames
//! with weights summing to one, so it gives the same motion on normalised and unnormalised
//! features.

use candle_core::Tensor;

use dex2hoi_data::layout::FeatureLayout;

use crate::error::{Result, SampleError};

/// How each window of a generation joins the frames before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Seams {
    /// As the model generates them (the paper's sampler).
    #[default]
    AsGenerated,
    /// Each window's body carries on from its prefix (see the module docs).
    Continuous,
}

impl Seams {
    /// What `dex2hoi sample` and the web page do unless told otherwise. The rule assumes only
    /// that a person's motion has no jumps, which holds for every dataset. `Default` is the
    /// paper's sampler, which `evaluate` keeps, so that its figures are the model's own.
    pub const fn sample_default() -> Self {
        Self::Continuous
    }
}

/// Frames over which a window's pose offset fades: a quarter of the window (10 of the 40
/// predicted frames, half a second at 20 fps), long enough not to show as a jolt and short
/// enough to leave most of the window the model's own.
pub const fn fade_frames(predicted_frames: usize) -> usize {
    if predicted_frames < 4 { 1 } else { predicted_frames / 4 }
}

/// The weight of the first frame's pose offset on frame `t` of a window: 1 on the first
/// frame, falling as a raised cosine to 0 at frame `fade` and after.
fn pose_weight(t: usize, fade: usize) -> f32 {
    if t >= fade {
        0.0
    } else {
        0.5 * (1.0 + (std::f32::consts::PI * t as f32 / fade as f32).cos())
    }
}

/// Moves the body of `window` so that it carries on from `prefix` (see the module docs), the
/// pose offset fading over `fade` frames ([`fade_frames`] of the model's window). Both are
/// features of the same space (both normalised, or both not).
///
/// # Shapes
/// - `prefix`: `[B, 2, T_p, D]` with `T_p >= 1` (with one frame the prefix leads to itself)
/// - `window`: `[B, 2, T, D]`; returns the same shape
pub fn carry_on(
    prefix: &Tensor,
    window: &Tensor,
    layout: FeatureLayout,
    fade: usize,
) -> Result<Tensor> {
    let (batch, streams, frames, width) = window.dims4()?;
    let (prefix_batch, prefix_streams, prefix_frames, prefix_width) = prefix.dims4()?;
    if (prefix_batch, prefix_streams, prefix_width) != (batch, streams, width)
        || prefix_frames == 0
        || width != layout.stream_width()
    {
        return Err(SampleError::invalid(
            "continuous seams",
            "prefix and window",
            format!(
                "[{batch}, {streams}, T >= 1, {}] and [B, 2, T, D] alike",
                layout.stream_width()
            ),
            format!("{:?} and {:?}", prefix.dims(), window.dims()),
        ));
    }
    if frames == 0 {
        return Ok(window.clone());
    }
    let body = layout.body_width();
    let last = prefix.narrow(2, prefix_frames - 1, 1)?.narrow(3, 0, body)?;
    let leads_to = if prefix_frames >= 2 {
        let before = prefix.narrow(2, prefix_frames - 2, 1)?.narrow(3, 0, body)?;
        ((&last * 2.0)? - before)?
    } else {
        last
    };
    let window_body = window.narrow(3, 0, body)?;
    let offset = (leads_to - window_body.narrow(2, 0, 1)?)?;
    let fade = fade.max(1);
    let rotations = layout.rotations_range();
    let is_rotation: Vec<bool> = (0..body).map(|feature| rotations.contains(&feature)).collect();
    let weights: Vec<f32> = (0..frames)
        .flat_map(|t| {
            let pose = pose_weight(t, fade);
            is_rotation.iter().map(move |&rotation| if rotation { pose } else { 1.0 })
        })
        .collect();
    let weights = Tensor::from_vec(weights, (1, 1, frames, body), window.device())?
        .to_dtype(window.dtype())?;
    let moved = (window_body + offset.broadcast_mul(&weights)?)?;
    Ok(Tensor::cat(&[&moved, &window.narrow(3, body, width - body)?], 3)?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    /// Two joints: a body of 6 * 2 + 3 = 15 features and 18 of an object, 33 per stream.
    const LAYOUT: FeatureLayout = FeatureLayout::new(2);

    /// `[1, 2, frames, D]` whose feature `k` at frame `t` (per stream `s`) is `value(s, t, k)`.
    fn features(frames: usize, value: impl Fn(usize, usize, usize) -> f32) -> Tensor {
        let width = LAYOUT.stream_width();
        let data: Vec<f32> = (0..2)
            .flat_map(|s| (0..frames).flat_map(move |t| (0..width).map(move |k| (s, t, k))))
            .map(|(s, t, k)| value(s, t, k))
            .collect();
        Tensor::from_vec(data, (1, 2, frames, width), &Device::Cpu).unwrap()
    }

    fn values(tensor: &Tensor) -> Vec<Vec<Vec<f32>>> {
        tensor.squeeze(0).unwrap().to_vec3().unwrap()
    }

    /// A prefix moving at a constant step per feature, and a window whose body starts off
    /// where it leads by an offset per feature and moves on its own.
    fn prefix_and_window() -> (Tensor, Tensor) {
        let line = |s: usize, t: usize, k: usize| {
            0.1 * k as f32 - 0.2 * s as f32 + 0.01 * (k + 1) as f32 * t as f32
        };
        let prefix = features(5, line);
        let window = features(12, |s, t, k| {
            let own = 0.03 * (t as f32).sin() * (k as f32 + 1.0);
            line(s, 5 + t, k) + 0.5 - 0.07 * k as f32 + own
        });
        (prefix, window)
    }

    #[test]
    fn the_window_starts_where_the_prefix_leads_the_root_keeps_the_offset_and_the_pose_fades() {
        let (prefix, window) = prefix_and_window();
        let moved = values(&carry_on(&prefix, &window, LAYOUT, 4).unwrap());
        let (before, window) = (values(&prefix), values(&window));
        let body = LAYOUT.body_width();
        for s in 0..2 {
            for k in 0..body {
                let leads_to = 2.0 * before[s][4][k] - before[s][3][k];
                assert!((moved[s][0][k] - leads_to).abs() < 1e-5, "stream {s} feature {k}");
                let offset = leads_to - window[s][0][k];
                for t in 0..12 {
                    let expected = if LAYOUT.root_range().contains(&k) {
                        window[s][t][k] + offset
                    } else {
                        window[s][t][k] + offset * pose_weight(t, 4)
                    };
                    assert!((moved[s][t][k] - expected).abs() < 1e-5, "{s} {t} {k}");
                }
                // After the fade the pose is the window's own.
                if LAYOUT.rotations_range().contains(&k) {
                    assert_eq!(moved[s][6][k], window[s][6][k]);
                }
            }
            // The objects are not moved.
            for t in 0..12 {
                assert_eq!(moved[s][t][body..], window[s][t][body..]);
            }
        }
    }

    #[test]
    fn normalising_before_or_after_gives_the_same_motion() {
        let (prefix, window) = prefix_and_window();
        let width = LAYOUT.stream_width();
        let scale = features(1, |_, _, k| 0.5 + 0.1 * k as f32);
        let shift = features(1, |s, _, k| 0.3 * k as f32 - s as f32);
        let normalise =
            |x: &Tensor| x.broadcast_sub(&shift).unwrap().broadcast_div(&scale).unwrap();
        let denormalise =
            |x: &Tensor| x.broadcast_mul(&scale).unwrap().broadcast_add(&shift).unwrap();
        let raw = carry_on(&prefix, &window, LAYOUT, 4).unwrap();
        let normalised = carry_on(&normalise(&prefix), &normalise(&window), LAYOUT, 4).unwrap();
        let difference = (denormalise(&normalised) - raw).unwrap().abs().unwrap();
        let worst: f32 = difference.max_all().unwrap().to_scalar().unwrap();
        assert!(worst < 1e-5, "{worst} over {width} features");
    }

    #[test]
    fn a_one_frame_prefix_leads_to_itself_and_bad_shapes_are_refused() {
        let (prefix, window) = prefix_and_window();
        let last = prefix.narrow(2, 4, 1).unwrap();
        let moved = values(&carry_on(&last, &window, LAYOUT, 4).unwrap());
        let last = values(&last);
        for k in 0..LAYOUT.body_width() {
            assert!((moved[0][0][k] - last[0][0][k]).abs() < 1e-6);
        }
        let other_width = window.narrow(3, 0, 20).unwrap();
        assert!(carry_on(&prefix, &other_width, LAYOUT, 4).is_err());
        assert!(carry_on(&prefix.narrow(2, 0, 0).unwrap(), &window, LAYOUT, 4).is_err());
        assert!(carry_on(&prefix.narrow(1, 0, 1).unwrap(), &window, LAYOUT, 4).is_err());
        let empty = window.narrow(2, 0, 0).unwrap();
        assert_eq!(carry_on(&prefix, &empty, LAYOUT, 4).unwrap().dims(), empty.dims());
    }

    #[test]
    fn the_pose_weight_falls_from_one_to_zero_over_the_fade() {
        assert_eq!(pose_weight(0, 10), 1.0);
        assert!((pose_weight(5, 10) - 0.5).abs() < 1e-6);
        assert_eq!(pose_weight(10, 10), 0.0);
        assert_eq!(pose_weight(30, 10), 0.0);
        let weights: Vec<f32> = (0..=10).map(|t| pose_weight(t, 10)).collect();
        assert!(weights.windows(2).all(|w| w[1] < w[0]), "{weights:?}");
        assert_eq!(fade_frames(40), 10);
        assert_eq!(fade_frames(2), 1);
    }

    #[test]
    fn the_sampler_default_is_continuous_and_the_paper_s_is_as_generated() {
        assert_eq!(Seams::sample_default(), Seams::Continuous);
        assert_eq!(Seams::default(), Seams::AsGenerated);
    }
}
