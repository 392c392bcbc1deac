//! Training batches: windows of `T_p + T_f` frames cut from the training split, augmented
//! (stream swap, left/right mirror), normalised, with the targets the losses need.

use std::collections::BTreeMap;

use candle_core::{DType, Device, Tensor};
use glam::Vec3;
use rand::Rng;
use rand::distr::Distribution;
use rand::distr::weighted::WeightedIndex;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::FeatureLayout;
use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::augment::{mirror, swap_streams};
use dex2hoi_data::dataset::{Dataset, FeatureStats, Split};
use dex2hoi_data::features::{ObjectAsset, ProcessedSequence};
use dex2hoi_data::settled::SettledObjects;
use dex2hoi_data::window::{Window, WindowConfig, windows};
use dex2hoi_repr::Skeleton;

use crate::error::{Result, TrainError};

/// An object's surface samples in its own frame, for the penetration and distance terms.
#[derive(Debug, Clone)]
pub struct SurfaceCloud {
    /// Sample positions, `[samples]`.
    pub points: Vec<Vec3>,
    /// Outward unit normals at the samples.
    pub normals: Vec<Vec3>,
}

impl SurfaceCloud {
    /// An object asset's surface samples.
    pub fn of(asset: &ObjectAsset) -> Self {
        Self { points: asset.samples.points.clone(), normals: asset.samples.normals.clone() }
    }
}

/// What the batches are cut from: the training split, its windows and the object assets.
#[derive(Debug, Clone)]
pub struct TrainingSet {
    skeleton: Skeleton,
    sequences: Vec<ProcessedSequence>,
    windows: Vec<Window>,
    /// Every window, drawn as [`LoopConfig::action_weights`] says.
    ///
    /// [`LoopConfig::action_weights`]: crate::LoopConfig::action_weights
    all_windows: WindowPool,
    /// Each sequence's first window (starting at frame 0).
    first_windows: WindowPool,
    /// Per window and source slot, whether the object is set down within the window's
    /// predicted frames ([`Batch::put_down`] before the swap).
    put_down_of: Vec<[bool; MAX_OBJECTS]>,
    /// The windows that set some object down.
    put_down_windows: WindowPool,
    window: WindowConfig,
    /// Per sequence and slot, the index of the object asset.
    assets_of: Vec<[Option<usize>; MAX_OBJECTS]>,
    /// Per sequence, whether each hand (left, right) holds an object ([`hands_holding`]).
    hands_of: Vec<[bool; 2]>,
    /// Per sequence, whether some object ends to the person's left, and to the right, of
    /// where it stood ([`ProcessedSequence::objects_travel`]).
    sides_of: Vec<[bool; 2]>,
    bps: Vec<Vec<f32>>,
    clouds: Vec<SurfaceCloud>,
    bps_width: usize,
    stats: FeatureStats,
}

/// One batch of `B` windows. Features are normalised; targets are in the canonical frame, in
/// metres.
#[derive(Debug, Clone)]
pub struct Batch {
    /// Windows in the batch `B`.
    pub size: usize,
    /// Normalised features of both streams, prefix then predicted frames, `[B, 2, T, D]`.
    pub features: Tensor,
    /// Valid frames, `[B, T]` (1 real, 0 padding).
    pub frame_mask: Tensor,
    /// The same as numbers, batch-major.
    pub frame_mask_values: Vec<f32>,
    /// BPS per slot, `[B, 2, P * 3]` (zeros for an empty slot).
    pub bps: Tensor,
    /// Presence per slot, `[B, 2]`.
    pub presence: Tensor,
    /// The same as flags.
    pub presence_values: Vec<[bool; MAX_OBJECTS]>,
    /// One description per window (mirrored with the window).
    pub texts: Vec<String>,
    /// Ground-truth joint positions of the predicted frames, `[B, T_f, J, 3]`.
    pub joints: Tensor,
    /// Ground-truth object positions of the predicted frames, `[B, 2, T_f, 3]`.
    pub object_positions: Tensor,
    /// Ground-truth signed hand-joint distances of the predicted frames, `[B, 2, T_f, H]`.
    pub hand_distances: Tensor,
    /// The same as numbers.
    pub hand_distance_values: Vec<f32>,
    /// Ground-truth foot contact of the predicted frames, `[B, T_f, 4]`.
    pub foot_contact: Tensor,
    /// The same as numbers.
    pub foot_contact_values: Vec<f32>,
    /// The root position at the first frame of each window's sequence, `[B, 1, 3]`.
    pub root_start: Tensor,
    /// The rest offsets of each window's body (its sequence's subject, mirrored with the
    /// window), `[B, J, 3]`: the losses pose the prediction on them.
    pub rest_offsets: Tensor,
    /// Frames from the start of each window's sequence (where its texts begin to apply) to
    /// the window's first frame, `[B]`: what the prompt clock reads.
    pub elapsed: Tensor,
    /// Both streams' normalised rows at the first frame of each window's sequence (where its
    /// texts begin to apply; swapped and mirrored with the window), `[B, 2, D]`: what the object
    /// start reads.
    pub object_start: Tensor,
    /// Per window and slot, whether the object has been moved and set down again between its
    /// sequence's first frame and the window's last prefix frame
    /// ([`dex2hoi_data::settled`]; swapped with the window), 1 or 0, `[B, 2]`: what the
    /// memory of set-down objects reads.
    pub settled: Tensor,
    /// Both streams' normalised rows at the frame each stream's object was reached
    /// ([`SettledObjects::reach_frames`]: the last frame before it first moved, or the
    /// window's first frame while that is earlier; swapped and mirrored with the window),
    /// `[B, 2, D]`: the first prefix token with the reach frame in the prefix.
    pub reach: Tensor,
    /// Per window and slot, whether the object is set down within the window's predicted
    /// frames: moved and set down again by the window's last real frame
    /// ([`dex2hoi_data::settled`]) but not yet by its last prefix frame (swapped with the
    /// window). Where these objects end is what the `put_down` term measures.
    pub put_down: Vec<[bool; MAX_OBJECTS]>,
    /// Per window and slot, the index of the object's surface cloud.
    pub clouds: Vec<[Option<usize>; MAX_OBJECTS]>,
    /// Whether each hand holds an object at some time of the window's whole sequence
    /// ([`hands_holding`]), left then right (mirrored with the window), 1 or 0, `[B, 2]`: what
    /// the text of the window names, for the `text_hands` term.
    pub hands: Tensor,
    /// Whether some object of the window's whole sequence ends to the person's left, and to
    /// the right, of where it stood ([`ProcessedSequence::objects_travel`]; mirrored with the
    /// window), 1 or 0, `[B, 2]`: the side the text names, for the `text_sides` term.
    pub sides: Tensor,
}

impl Batch {
    /// The batch with every tensor moved to `device` (a batch drawn on another host thread
    /// onto the step's device).
    pub fn to_device(self, device: &Device) -> Result<Self> {
        let on = |t: Tensor| -> Result<Tensor> { Ok(t.to_device(device)?) };
        Ok(Self {
            features: on(self.features)?,
            frame_mask: on(self.frame_mask)?,
            bps: on(self.bps)?,
            presence: on(self.presence)?,
            joints: on(self.joints)?,
            object_positions: on(self.object_positions)?,
            hand_distances: on(self.hand_distances)?,
            foot_contact: on(self.foot_contact)?,
            root_start: on(self.root_start)?,
            rest_offsets: on(self.rest_offsets)?,
            elapsed: on(self.elapsed)?,
            object_start: on(self.object_start)?,
            settled: on(self.settled)?,
            reach: on(self.reach)?,
            hands: on(self.hands)?,
            sides: on(self.sides)?,
            ..self
        })
    }
}

/// The frames a hand must touch an object for, in a sequence, to count as holding one: a
/// quarter of a second at 20 fps, so that a brush in passing does not count
/// (docs/CONVENTIONS.md, "Losses").
pub const HOLDING_FRAMES: usize = 5;

/// Whether each hand (left, right) touches an object on at least [`HOLDING_FRAMES`] frames
/// of a sequence.
pub fn hands_holding(sequence: &ProcessedSequence) -> [bool; 2] {
    let mut frames = [0usize; 2];
    for frame in sequence.hand_contact.chunks_exact(MAX_OBJECTS * 2) {
        for (hand, count) in frames.iter_mut().enumerate() {
            let touching = (0..MAX_OBJECTS).any(|slot| frame[slot * 2 + hand] > 0.5);
            *count += usize::from(touching);
        }
    }
    frames.map(|count| count >= HOLDING_FRAMES)
}

/// Per window and slot, whether the object is set down within the window's predicted frames:
/// the tracker of [`dex2hoi_data::settled`], following the window's sequence from its first
/// frame, counts it as set down after the window's last real frame but not after its last
/// prefix frame. One pass of the tracker per sequence.
fn put_downs(
    sequences: &[ProcessedSequence],
    windows: &[Window],
    config: &WindowConfig,
) -> Vec<[bool; MAX_OBJECTS]> {
    let settled_by_frame: Vec<Vec<[bool; MAX_OBJECTS]>> = sequences
        .iter()
        .map(|sequence| {
            let mut tracker = SettledObjects::new();
            (0..sequence.frames)
                .map(|t| {
                    tracker.push(std::array::from_fn(|s| {
                        let p = (t * MAX_OBJECTS + s) * 3;
                        Vec3::from_slice(&sequence.object_positions[p..p + 3])
                    }));
                    tracker.settled()
                })
                .collect()
        })
        .collect();
    let (tp, t_all) = (config.prefix_frames, config.prefix_frames + config.predicted_frames);
    windows
        .iter()
        .map(|window| {
            let settled = &settled_by_frame[window.sequence];
            let (before, after) = (settled[window.frame(tp - 1)], settled[window.frame(t_all - 1)]);
            std::array::from_fn(|s| after[s] && !before[s])
        })
        .collect()
}

/// Some of a training set's windows, each drawn with the weight of its sequence's action.
#[derive(Debug, Clone)]
struct WindowPool {
    /// Indices into [`TrainingSet::windows`].
    indices: Vec<usize>,
    /// The windows' weights when some are not 1; absent, the windows are drawn uniformly, with
    /// the draws of a set without weights.
    weights: Option<WeightedIndex<f64>>,
}

impl WindowPool {
    /// The windows `indices`, drawn uniformly.
    fn uniform(indices: Vec<usize>) -> Self {
        Self { indices, weights: None }
    }

    /// The same windows drawn with `weight_of` each window; `None` when every weight is 0.
    fn weighted(&self, weight_of: &[f64]) -> Option<Self> {
        let weights = WeightedIndex::new(self.indices.iter().map(|&i| weight_of[i])).ok()?;
        Some(Self { indices: self.indices.clone(), weights: Some(weights) })
    }

    /// One window's index, from a pool with some window to draw.
    fn draw(&self, rng: &mut ChaCha8Rng) -> usize {
        let at = match &self.weights {
            Some(weights) => weights.sample(rng),
            None => rng.random_range(0..self.indices.len()),
        };
        self.indices[at]
    }
}

/// How a batch is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BatchOptions {
    /// Windows per batch.
    pub size: usize,
    /// Probability of swapping the streams.
    pub swap_probability: f64,
    /// Probability of mirroring.
    pub mirror_probability: f64,
    /// Share of windows drawn from the first windows of sequences
    /// ([`crate::LoopConfig::first_window_share`]).
    pub first_window_share: f64,
    /// Share of the other windows drawn from those that set an object down
    /// ([`crate::LoopConfig::put_down_share`]).
    pub put_down_share: f64,
}

impl TrainingSet {
    /// The training split of a dataset cut into windows.
    pub fn new(dataset: &Dataset, window: WindowConfig) -> Result<Self> {
        let skeleton = dataset.manifest.builtin_skeleton()?;
        let sequences = dataset.splits.get(&Split::Train).cloned().unwrap_or_default();
        if sequences.is_empty() {
            return Err(TrainError::config(
                "dataset",
                "training split",
                "at least one sequence",
                "none",
            ));
        }
        let counts: Vec<usize> = sequences.iter().map(|s| s.frames).collect();
        let windows = windows(&counts, &window)?;
        if windows.is_empty() {
            return Err(TrainError::config(
                "dataset",
                "training split",
                "a sequence with at least one frame",
                "only empty sequences",
            ));
        }
        let all_windows = WindowPool::uniform((0..windows.len()).collect());
        let first_windows =
            WindowPool::uniform((0..windows.len()).filter(|&i| windows[i].start == 0).collect());
        let put_down_of = put_downs(&sequences, &windows, &window);
        let put_down_windows = WindowPool::uniform(
            (0..windows.len()).filter(|&i| put_down_of[i].iter().any(|&p| p)).collect(),
        );
        let assets_of = sequences
            .iter()
            .map(|s| dataset.slot_assets(s))
            .collect::<std::result::Result<_, _>>()?;
        let hands_of = sequences.iter().map(hands_holding).collect();
        let sides_of = sequences.iter().map(ProcessedSequence::objects_travel).collect();
        let bps_width = dataset.manifest.bps.points * 3;
        let bps = dataset.objects.iter().map(ObjectAsset::bps_features).collect();
        let clouds = dataset.objects.iter().map(SurfaceCloud::of).collect();
        Ok(Self {
            skeleton,
            sequences,
            windows,
            all_windows,
            first_windows,
            put_down_of,
            put_down_windows,
            window,
            assets_of,
            hands_of,
            sides_of,
            bps,
            clouds,
            bps_width,
            stats: dataset.stats.clone(),
        })
    }

    /// The built-in skeleton of the dataset: the topology and joint groups every sequence
    /// shares (each window's body is [`Batch::rest_offsets`]).
    pub fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }

    /// The windows.
    pub fn windows(&self) -> &[Window] {
        &self.windows
    }

    /// Indices into [`Self::windows`] of the windows that set some object down within their
    /// predicted frames ([`Batch::put_down`]).
    pub fn put_down_windows(&self) -> &[usize] {
        &self.put_down_windows.indices
    }

    /// The set with its windows drawn by the action label of their sequence: a window of a
    /// sequence labelled with a key of `weights` with that weight, every other window with
    /// weight 1 ([`crate::LoopConfig::action_weights`], whose labels
    /// [`crate::TrainConfig::check_dataset`] checks; its error names `source_name`). No weights
    /// leave the set as it is.
    ///
    /// # Errors
    /// Weights that leave no window to draw.
    pub fn weighted_by_action(
        mut self,
        weights: &BTreeMap<String, f64>,
        source_name: &str,
    ) -> Result<Self> {
        if weights.is_empty() {
            return Ok(self);
        }
        let weight_of: Vec<f64> = self
            .windows
            .iter()
            .map(|w| {
                let action = self.sequences[w.sequence].action.as_ref();
                action.and_then(|a| weights.get(a)).copied().unwrap_or(1.0)
            })
            .collect();
        self.all_windows = self.all_windows.weighted(&weight_of).ok_or_else(|| {
            TrainError::config(
                source_name,
                "training.action_weights",
                "weights that leave some window to draw",
                "0 for every window",
            )
        })?;
        let empty = || WindowPool::uniform(Vec::new());
        self.first_windows = self.first_windows.weighted(&weight_of).unwrap_or_else(empty);
        self.put_down_windows = self.put_down_windows.weighted(&weight_of).unwrap_or_else(empty);
        Ok(self)
    }

    /// Draws the index (into [`Self::windows`]) of one window of a batch: with
    /// `options.first_window_share` from the first windows, else with
    /// `options.put_down_share` from those that set an object down, else from all, each pool
    /// as [`Self::weighted_by_action`] weighs it.
    pub fn draw_window(&self, options: &BatchOptions, rng: &mut ChaCha8Rng) -> usize {
        // No draw for a share when it is 0, so that such runs keep their random stream.
        let drawn_from = |share: f64, pool: &WindowPool, rng: &mut ChaCha8Rng| {
            (share > 0.0 && !pool.indices.is_empty() && rng.random_bool(share))
                .then(|| pool.draw(rng))
        };
        // Every window is drawable: `TrainingSet::new` has at least one, and
        // `weighted_by_action` refuses weights that leave none.
        drawn_from(options.first_window_share, &self.first_windows, rng)
            .or_else(|| drawn_from(options.put_down_share, &self.put_down_windows, rng))
            .unwrap_or_else(|| self.all_windows.draw(rng))
    }

    /// The training sequences.
    pub fn sequences(&self) -> &[ProcessedSequence] {
        &self.sequences
    }

    /// The objects' surface clouds, in asset order.
    pub fn clouds(&self) -> &[SurfaceCloud] {
        &self.clouds
    }

    /// The normalisation statistics.
    pub fn stats(&self) -> &FeatureStats {
        &self.stats
    }

    /// Draws a batch: windows uniformly (a share of them from the sequences' first windows
    /// when asked), one of each window's texts, then a swap and a mirror
    /// with their probabilities, all from `rng`.
    pub fn batch(
        &self,
        options: &BatchOptions,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Batch> {
        let b = options.size;
        let (tp, tf) = (self.window.prefix_frames, self.window.predicted_frames);
        let t_all = tp + tf;
        let joints = self.skeleton.joint_count();
        let layout = FeatureLayout::new(joints);
        let width = layout.stream_width();
        let h = self.skeleton.groups().left_hand.len() + self.skeleton.groups().right_hand.len();
        let mut features = vec![0.0f32; b * 2 * t_all * width];
        let mut frame_mask = vec![0.0f32; b * t_all];
        let mut bps = vec![0.0f32; b * 2 * self.bps_width];
        let mut presence = vec![0.0f32; b * 2];
        let mut presence_values = Vec::with_capacity(b);
        let mut texts = Vec::with_capacity(b);
        let mut target_joints = vec![0.0f32; b * tf * joints * 3];
        let mut object_positions = vec![0.0f32; b * 2 * tf * 3];
        let mut hand_distances = vec![0.0f32; b * 2 * tf * h];
        let mut foot_contact = vec![0.0f32; b * tf * 4];
        let mut root_start = vec![0.0f32; b * 3];
        let mut rest_offsets = Vec::with_capacity(b * joints * 3);
        let mut clouds = Vec::with_capacity(b);
        let mut elapsed = Vec::with_capacity(b);
        let mut start = vec![0.0f32; b * 2 * width];
        let mut settled = Vec::with_capacity(b * 2);
        let mut reach = vec![0.0f32; b * 2 * width];
        let mut put_down = Vec::with_capacity(b);
        let mut hands = Vec::with_capacity(b * 2);
        let mut sides = Vec::with_capacity(b * 2);
        for i in 0..b {
            let index = self.draw_window(options, rng);
            let window = self.windows[index];
            elapsed.push(window.start as f32);
            let source = &self.sequences[window.sequence];
            let text = source.texts[rng.random_range(0..source.texts.len())].clone();
            let swap = rng.random_bool(options.swap_probability);
            let mirrored = rng.random_bool(options.mirror_probability);
            // The window and its sequence's first frame, each swapped and mirrored alike.
            let augmented = |mut cut: ProcessedSequence| {
                if swap {
                    cut = swap_streams(&cut);
                }
                if mirrored {
                    cut = mirror(&cut, &self.skeleton);
                }
                cut
            };
            let mut w = window.cut(source, t_all);
            w.texts = vec![text];
            let mut w = augmented(w);
            let mut slots = self.assets_of[window.sequence];
            if swap {
                slots.swap(0, 1);
            }
            let whole = Window { sequence: window.sequence, start: 0, valid_frames: 1 };
            let first = augmented(whole.cut(source, 1));
            for s in 0..MAX_OBJECTS {
                let row = &mut start[(i * 2 + s) * width..][..width];
                layout.write_stream_row(&first.body, &first.objects, 0, s, row);
                self.stats.normalise_row(row);
            }
            let position = |t: usize| -> [Vec3; MAX_OBJECTS] {
                std::array::from_fn(|s| {
                    let p = (t * MAX_OBJECTS + s) * 3;
                    Vec3::from_slice(&source.object_positions[p..p + 3])
                })
            };
            // One tracker over the sequence up to the window's last prefix frame serves the
            // set-down flags and the reach frames.
            let tracker = SettledObjects::after(window.frame(tp - 1) + 1, position);
            let [mut a, mut b_settled] = tracker.settled();
            let mut put = self.put_down_of[index];
            if swap {
                (a, b_settled) = (b_settled, a);
                put.swap(0, 1);
            }
            settled.extend([f32::from(u8::from(a)), f32::from(u8::from(b_settled))]);
            put_down.push(put);
            // Each source slot's reach frame, cut and augmented as the window; the stream it
            // lands in after the swap shows it.
            let reached = tracker.reach_frames(window.frame(0));
            for (slot, &frame) in reached.iter().enumerate() {
                let at = Window { sequence: window.sequence, start: frame, valid_frames: 1 };
                let cut = augmented(at.cut(source, 1));
                let stream = if swap { 1 - slot } else { slot };
                let row = &mut reach[(i * 2 + stream) * width..][..width];
                layout.write_stream_row(&cut.body, &cut.objects, 0, stream, row);
                self.stats.normalise_row(row);
            }
            for (of, out) in [(&self.hands_of, &mut hands), (&self.sides_of, &mut sides)] {
                let [left, right] = of[window.sequence];
                let (left, right) = if mirrored { (right, left) } else { (left, right) };
                out.extend([f32::from(u8::from(left)), f32::from(u8::from(right))]);
            }
            for k in 0..t_all {
                frame_mask[i * t_all + k] = if k < window.valid_frames { 1.0 } else { 0.0 };
                for s in 0..MAX_OBJECTS {
                    let row = &mut features[((i * 2 + s) * t_all + k) * width..][..width];
                    layout.write_stream_row(&w.body, &w.objects, k, s, row);
                    self.stats.normalise_row(row);
                }
            }
            for s in 0..MAX_OBJECTS {
                presence[i * 2 + s] = f32::from(u8::from(w.object_present[s]));
                if let Some(asset) = slots[s] {
                    bps[(i * 2 + s) * self.bps_width..][..self.bps_width]
                        .copy_from_slice(&self.bps[asset]);
                }
            }
            for k in 0..tf {
                let f = tp + k;
                target_joints[(i * tf + k) * joints * 3..][..joints * 3]
                    .copy_from_slice(&w.joint_positions[f * joints * 3..(f + 1) * joints * 3]);
                foot_contact[(i * tf + k) * 4..][..4]
                    .copy_from_slice(&w.foot_contact[f * 4..f * 4 + 4]);
                for s in 0..MAX_OBJECTS {
                    let p = (f * MAX_OBJECTS + s) * 3;
                    object_positions[((i * 2 + s) * tf + k) * 3..][..3]
                        .copy_from_slice(&w.object_positions[p..p + 3]);
                    let d = (f * MAX_OBJECTS + s) * h;
                    hand_distances[((i * 2 + s) * tf + k) * h..][..h]
                        .copy_from_slice(&w.hand_distances[d..d + h]);
                }
            }
            root_start[i * 3..i * 3 + 3].copy_from_slice(&w.root_start.to_array());
            rest_offsets.extend(w.rest_offsets.iter().flat_map(|o| o.to_array()));
            presence_values.push(w.object_present);
            texts.push(w.texts.swap_remove(0));
            clouds.push(slots);
        }
        let tensor = |values: Vec<f32>, shape: &[usize]| -> Result<Tensor> {
            Ok(Tensor::from_vec(values, shape, device)?.to_dtype(DType::F32)?)
        };
        Ok(Batch {
            size: b,
            features: tensor(features, &[b, 2, t_all, width])?,
            frame_mask: tensor(frame_mask.clone(), &[b, t_all])?,
            frame_mask_values: frame_mask,
            bps: tensor(bps, &[b, 2, self.bps_width])?,
            presence: tensor(presence, &[b, 2])?,
            presence_values,
            texts,
            joints: tensor(target_joints, &[b, tf, joints, 3])?,
            object_positions: tensor(object_positions, &[b, 2, tf, 3])?,
            hand_distances: tensor(hand_distances.clone(), &[b, 2, tf, h])?,
            hand_distance_values: hand_distances,
            foot_contact: tensor(foot_contact.clone(), &[b, tf, 4])?,
            foot_contact_values: foot_contact,
            root_start: tensor(root_start, &[b, 1, 3])?,
            elapsed: tensor(elapsed, &[b])?,
            object_start: tensor(start, &[b, 2, width])?,
            settled: tensor(settled, &[b, 2])?,
            reach: tensor(reach, &[b, 2, width])?,
            put_down,
            rest_offsets: tensor(rest_offsets, &[b, joints, 3])?,
            clouds,
            hands: tensor(hands, &[b, 2])?,
            sides: tensor(sides, &[b, 2])?,
        })
    }
}
