//! The geometric losses pose each window on its own sequence's body (the dataset's
//! `rest_offsets`): the ground truth itself, fed back as the prediction, leaves the joint
//! velocity term at zero even when the subjects' proportions differ from the built-in skeleton
//! and from each other, mirrored windows included.

use std::path::Path;

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::dataset::Split;
use dex2hoi_data::features::ObjectDecoding;
use dex2hoi_data::settled::{
    MOVED_RISE_M, MOVED_TRAVEL_M, SET_DOWN_HEIGHT_M, STILL_FRAMES, STILL_M,
};
use dex2hoi_repr::object_repr::GLOBAL_POSITION_RANGE;
use dex2hoi_train::batch::BatchOptions;
use dex2hoi_train::{Term, TrainConfig, Trainer};

#[test]
fn the_ground_truth_has_no_joint_error_on_its_own_body() {
    let mut data = dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).unwrap();
    let topology = data.manifest.builtin_skeleton().unwrap();
    // Give every training sequence another subject: one scale per sequence and a per-bone
    // asymmetry, with the joints recomputed by FK on that body.
    for (k, sequence) in data.splits.get_mut(&Split::Train).unwrap().iter_mut().enumerate() {
        let scale = 0.85 + 0.04 * k as f32;
        sequence.rest_offsets = (topology.rest_offsets().iter().enumerate())
            .map(|(j, o)| *o * scale * (1.0 + 0.05 * (j as f32).sin()))
            .collect();
        let (_, decoded) = sequence.decode(&topology, ObjectDecoding::GlobalOnly).unwrap();
        sequence.joint_positions =
            decoded.joints.positions.iter().flat_map(|p| p.to_array()).collect();
    }
    let config = TrainConfig::preset("tiny").unwrap();
    let trainer =
        Trainer::new(config.clone(), &data, Path::new("procedural"), &Device::Cpu).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let options = BatchOptions {
        size: 6,
        swap_probability: 0.5,
        mirror_probability: 0.5,
        first_window_share: 0.0,
        put_down_share: 0.0,
    };
    let batch = trainer.training_set().batch(&options, &mut rng, &Device::Cpu).unwrap();
    let (tp, tf) = (config.model.prefix_frames, config.model.predicted_frames);
    let truth = batch.features.narrow(2, tp, tf).unwrap().to_dtype(DType::F64).unwrap();
    let timesteps = vec![10; batch.size];
    let objective = trainer.loss_context().objective(&truth, &batch, &timesteps).unwrap();
    let (_, joint_velocity) =
        objective.terms.iter().find(|(t, _)| *t == Term::JointVelocity).unwrap();
    let value = joint_velocity.to_scalar::<f64>().unwrap();
    // In cm^2 per frame^2; the built-in body instead gives errors of centimetres.
    assert!(value < 1e-6, "joint velocity of the ground truth: {value}");
}

/// `first_window_share`: all of a batch from the sequences' first windows at 1, about that
/// share at 0.5, and at 0 the same batch as a configuration without it.
#[test]
fn a_share_of_windows_comes_from_the_first_windows() {
    let data = dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).unwrap();
    let mut config = TrainConfig::preset("tiny").unwrap();
    config.training.window_stride = 5;
    let trainer = Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).unwrap();
    let starts = |share: f64, size: usize| -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let options = BatchOptions {
            size,
            swap_probability: 0.5,
            mirror_probability: 0.5,
            first_window_share: share,
            put_down_share: 0.0,
        };
        let batch = trainer.training_set().batch(&options, &mut rng, &Device::Cpu).unwrap();
        batch.elapsed.to_vec1::<f32>().unwrap()
    };
    let windows = trainer.training_set().windows();
    let firsts = windows.iter().filter(|w| w.start == 0).count();
    assert!(firsts * 4 < windows.len(), "{firsts} first windows of {}", windows.len());
    assert!(starts(1.0, 64).iter().all(|&s| s == 0.0));
    let uniform = starts(0.0, 64);
    let at_zero = uniform.iter().filter(|&&s| s == 0.0).count();
    assert!(at_zero < 24, "{at_zero} of 64 first windows drawn uniformly");
    let half = starts(0.5, 64);
    let at_zero = half.iter().filter(|&&s| s == 0.0).count();
    assert!((20..=48).contains(&at_zero), "{at_zero} of 64 first windows at a share of 0.5");
    // A share of 0 is left out of a written configuration, so those written before read the same.
    let mut config = TrainConfig::preset("tiny").unwrap();
    config.training.window_stride = 5;
    let toml = toml::to_string(&config).unwrap();
    assert!(!toml.contains("first_window_share"), "{toml}");
}

/// Two batches of `size` windows drawn with the same seed, streams swapped at random: no window
/// mirrored, then every window.
fn unmirrored_and_mirrored(trainer: &Trainer, size: usize) -> [dex2hoi_train::batch::Batch; 2] {
    [0.0, 1.0].map(|mirror_probability| {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let options = BatchOptions {
            size,
            swap_probability: 0.5,
            mirror_probability,
            first_window_share: 0.0,
            put_down_share: 0.0,
        };
        trainer.training_set().batch(&options, &mut rng, &Device::Cpu).unwrap()
    })
}

/// The side text term's targets: in the procedural data, a pick and place ends to the side
/// its texts name (or, where the table's edge stopped it, within the centre band), never to
/// the other; a mirrored window's targets are the other sides.
#[test]
fn the_sides_a_batch_moves_to_are_those_its_texts_name() {
    let data = dex2hoi_synth::build_dataset(48, 5, 20.0, &|_| {}).unwrap();
    let config = TrainConfig::preset("tiny").unwrap();
    let trainer = Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).unwrap();
    // The side words of a text that are not a hand's: `[left, right]`.
    let sides_named = |text: &str| {
        let words: Vec<String> = dex2hoi_model::text::words(text);
        let mut named = [0usize; 2];
        for (i, word) in words.iter().enumerate() {
            let of_hand = words.get(i + 1).is_some_and(|w| w == "hand" || w == "handed");
            for (side, name) in ["left", "right"].iter().enumerate() {
                named[side] += usize::from(word == name && !of_hand);
            }
        }
        named
    };
    let (mut agree, mut centre) = (0, 0);
    for sequence in trainer.training_set().sequences() {
        if sequence.action.as_deref() != Some("pick_place") {
            continue;
        }
        let travel = sequence.objects_travel();
        for text in &sequence.texts {
            let side = match sides_named(text) {
                [1, 0] => 0,
                [0, 1] => 1,
                _ => continue,
            };
            assert!(!travel[1 - side], "{text}: the object ends on the other side");
            if travel[side] {
                agree += 1;
            } else {
                centre += 1;
            }
        }
    }
    assert!(agree >= 10 && centre * 10 <= agree, "{agree} texts agree, {centre} end in the centre");
    // Every window mirrored or none: a window whose (mirrored) text names one side, says
    // nothing of where it ends against another object ("next to", "of") and passes nothing
    // from hand to hand (a hand over puts the object down on the taking hand's side of the
    // body, which may be the other way from where it stood) moves an object to that side or
    // to none.
    for batch in unmirrored_and_mirrored(&trainer, 160) {
        let sides = batch.sides.to_vec2::<f32>().unwrap();
        let mut checked = 0;
        for (text, moved) in batch.texts.iter().zip(&sides) {
            let words = dex2hoi_model::text::words(text);
            let both_hands = ["left", "right"].iter().all(|side| {
                words.windows(2).any(|w| w[0] == *side && (w[1] == "hand" || w[1] == "handed"))
            });
            if both_hands || words.iter().any(|w| w == "next" || w == "of" || w == "other") {
                continue;
            }
            let side = match sides_named(text) {
                [1, 0] => 0,
                [0, 1] => 1,
                _ => continue,
            };
            assert_eq!(moved[1 - side], 0.0, "{text}: {moved:?}");
            checked += usize::from(moved[side] == 1.0);
        }
        assert!(checked > 5, "{checked} windows move an object to the side they name");
    }
}

/// The text term's targets: in the procedural data, a one-handed task's text that names one
/// hand names the hand that holds an object and no other (in a pour the other hand steadies
/// the bowl, so both hold there); a mirrored window's targets are the other hands.
#[test]
fn the_hands_a_batch_holds_are_those_its_texts_name() {
    let data = dex2hoi_synth::build_dataset(48, 5, 20.0, &|_| {}).unwrap();
    let config = TrainConfig::preset("tiny").unwrap();
    let trainer = Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).unwrap();
    let names = |text: &str, hand: &str| {
        let words: Vec<String> = dex2hoi_model::text::words(text);
        words.windows(2).any(|w| w[0] == hand && (w[1] == "hand" || w[1] == "handed"))
    };
    let mut one_handed = 0;
    for sequence in trainer.training_set().sequences() {
        let [left, right] = dex2hoi_train::batch::hands_holding(sequence);
        assert!(left || right, "{}: no hand holds anything", sequence.source_id);
        let one_handed_task =
            matches!(sequence.action.as_deref(), Some("pick_place" | "move_next_to" | "inspect"));
        for text in sequence.texts.iter().filter(|_| one_handed_task) {
            let (named_left, named_right) = (names(text, "left"), names(text, "right"));
            if named_left != named_right {
                one_handed += 1;
                assert_eq!([left, right], [named_left, named_right], "{text}");
            }
        }
    }
    assert!(one_handed > 20, "{one_handed} texts name one hand");
    // Every window mirrored or none: the hand a window's (mirrored) text names holds.
    for batch in unmirrored_and_mirrored(&trainer, 48) {
        let hands = batch.hands.to_vec2::<f32>().unwrap();
        let mut checked = 0;
        for (text, held) in batch.texts.iter().zip(&hands) {
            match (names(text, "left"), names(text, "right")) {
                (true, false) => assert_eq!(held[0], 1.0, "{text}"),
                (false, true) => assert_eq!(held[1], 1.0, "{text}"),
                _ => continue,
            }
            checked += 1;
        }
        assert!(checked > 5, "{checked} windows name one hand");
        assert!(hands.iter().any(|h| h[0] != h[1]), "some windows hold with one hand");
    }
}

/// The tiny preset on 16 procedural sequences, windows every 5 frames.
fn tiny_trainer_with_stride_5() -> Trainer {
    let data = dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).unwrap();
    let mut config = TrainConfig::preset("tiny").unwrap();
    config.training.window_stride = 5;
    Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).unwrap()
}

/// A batch of `size` windows, half of them swapped and half mirrored, a `share` of them first
/// windows, drawn with `seed`.
fn swapped_and_mirrored_batch(
    trainer: &Trainer,
    size: usize,
    share: f64,
    seed: u64,
) -> dex2hoi_train::batch::Batch {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let options = BatchOptions {
        size,
        swap_probability: 0.5,
        mirror_probability: 0.5,
        first_window_share: share,
        put_down_share: 0.0,
    };
    trainer.training_set().batch(&options, &mut rng, &Device::Cpu).unwrap()
}

/// The object start's rows: each window's sequence at frame 0, swapped and mirrored with the
/// window. A batch of first windows starts at those rows; in a batch of windows from anywhere,
/// a window that starts later reads rows other than its own first frame.
#[test]
fn the_start_rows_are_each_sequences_first_frame_swapped_and_mirrored_with_the_window() {
    let trainer = tiny_trainer_with_stride_5();
    let batch = |share: f64| swapped_and_mirrored_batch(&trainer, 32, share, 5);
    // Per window, whether its start rows equal its own first frame's, and its start frame.
    let own_first_frame = |share: f64| -> Vec<(bool, f32)> {
        let batch = batch(share);
        let frame_zero = batch.features.narrow(2, 0, 1).unwrap().squeeze(2).unwrap();
        let difference = (&batch.object_start - &frame_zero).unwrap().abs().unwrap();
        let largest: Vec<f32> =
            difference.flatten_from(1).unwrap().max(1).unwrap().to_vec1().unwrap();
        let starts: Vec<f32> = batch.elapsed.to_vec1().unwrap();
        largest.iter().zip(starts).map(|(&d, start)| (d == 0.0, start)).collect()
    };
    assert!(own_first_frame(1.0).iter().all(|&(same, start)| same && start == 0.0));
    let anywhere = own_first_frame(0.0);
    assert!(anywhere.iter().all(|&(same, start)| same || start > 0.0));
    let later = anywhere.iter().filter(|(_, start)| *start > 0.0).count();
    let elsewhere = anywhere.iter().filter(|(same, _)| !same).count();
    assert!(later > 16 && elsewhere == later, "{elsewhere} of {later} later windows");
}

/// The reach rows: a window at the start of its sequence, or whose object has not left where it
/// stood before the prefix, shows its own first frame; in windows from anywhere, some show an
/// earlier frame, on which the object (in the stream the window's swap puts it in) still stands
/// where it started (within the tracker's rule for a move).
#[test]
fn the_reach_rows_show_the_last_frame_before_each_object_moved() {
    let trainer = tiny_trainer_with_stride_5();
    let stats = trainer.training_set().stats();
    let layout = dex2hoi_data::FeatureLayout::new(trainer.config().model.joints);
    let d = layout.stream_width();
    let position = layout.object_part_range(GLOBAL_POSITION_RANGE);
    let rows = |t: &Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
    let first_windows = swapped_and_mirrored_batch(&trainer, 32, 1.0, 8);
    let frame_zero = first_windows.features.narrow(2, 0, 1).unwrap().squeeze(2).unwrap();
    assert_eq!(rows(&first_windows.reach), rows(&frame_zero));
    let anywhere = swapped_and_mirrored_batch(&trainer, 64, 0.0, 8);
    let first = rows(&anywhere.features.narrow(2, 0, 1).unwrap().squeeze(2).unwrap());
    let (reach, start) = (rows(&anywhere.reach), rows(&anywhere.object_start));
    let mut earlier = 0;
    for k in 0..reach.len() / d {
        let row = |v: &[f32]| v[k * d..(k + 1) * d].to_vec();
        if row(&reach) == row(&first) {
            continue;
        }
        earlier += 1;
        let world = |v: &[f32]| -> Vec<f32> {
            position.clone().map(|c| v[k * d + c] * stats.std[c] + stats.mean[c]).collect()
        };
        let (at, from) = (world(&reach), world(&start));
        let travel: f32 = at.iter().zip(&from).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt();
        assert!(travel <= MOVED_TRAVEL_M + 1e-4, "row {k}: {travel} m from where it stood");
        assert!(at[1] - from[1] <= MOVED_RISE_M + 1e-4, "row {k}: risen {}", at[1] - from[1]);
    }
    assert!(earlier >= 8, "{earlier} of 128 reach rows show an earlier frame");
}

/// The memory of set-down objects' flags: none in windows at the start of their sequences
/// (nothing has been moved yet), some in windows from anywhere, each flag on a window whose
/// prefix shows that object standing still on its last frames (up to `STILL_FRAMES`), in the slot the
/// window's swap puts it in.
#[test]
fn the_settled_flags_are_set_only_after_a_move_on_a_still_object() {
    let trainer = tiny_trainer_with_stride_5();
    let batch = |share: f64| swapped_and_mirrored_batch(&trainer, 64, share, 6);
    let flags = |batch: &dex2hoi_train::batch::Batch| batch.settled.to_vec2::<f32>().unwrap();
    assert!(flags(&batch(1.0)).iter().flatten().all(|&f| f == 0.0));
    let anywhere = batch(0.0);
    let settled = flags(&anywhere);
    let flagged = settled.iter().flatten().filter(|&&f| f == 1.0).count();
    assert!(flagged >= 8, "{flagged} flags in 64 windows");
    assert!(settled.iter().flatten().all(|&f| f == 0.0 || f == 1.0));
    // A flagged object's world position over the prefix's last frames, unnormalised.
    let stats = trainer.training_set().stats();
    let layout = dex2hoi_data::FeatureLayout::new(trainer.config().model.joints);
    let tp = trainer.config().model.prefix_frames;
    let d = layout.stream_width();
    let features: Vec<f32> = anywhere.features.flatten_all().unwrap().to_vec1().unwrap();
    let t_all = anywhere.features.dims()[2];
    let position = layout.object_part_range(GLOBAL_POSITION_RANGE);
    for (i, window) in settled.iter().enumerate() {
        for (slot, &flag) in window.iter().enumerate() {
            if flag == 0.0 {
                continue;
            }
            let at = |t: usize| -> Vec<f32> {
                let row = &features[((i * 2 + slot) * t_all + t) * d..][..d];
                position.clone().map(|c| row[c] * stats.std[c] + stats.mean[c]).collect()
            };
            let last = at(tp - 1);
            for t in tp.saturating_sub(STILL_FRAMES)..tp {
                let moved: f32 =
                    at(t).iter().zip(&last).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt();
                assert!(moved <= STILL_M + 1e-4, "window {i}, slot {slot}, frame {t}: {moved}");
            }
        }
    }
}

/// The put-down flags: some windows from anywhere set an object down within their predicted
/// frames; each flagged object is not yet set down by the prefix's last frame (its memory flag
/// is 0), and on the window's last frames (up to `STILL_FRAMES`) it stands still at the height
/// it started at, in the slot the window's swap puts it in.
#[test]
fn the_put_down_flags_mark_objects_set_down_within_the_predicted_frames() {
    let trainer = tiny_trainer_with_stride_5();
    let batch = swapped_and_mirrored_batch(&trainer, 128, 0.0, 9);
    let settled = batch.settled.to_vec2::<f32>().unwrap();
    let stats = trainer.training_set().stats();
    let layout = dex2hoi_data::FeatureLayout::new(trainer.config().model.joints);
    let d = layout.stream_width();
    let t_all = batch.features.dims()[2];
    let features: Vec<f32> = batch.features.flatten_all().unwrap().to_vec1().unwrap();
    let start: Vec<f32> = batch.object_start.flatten_all().unwrap().to_vec1().unwrap();
    let position = layout.object_part_range(GLOBAL_POSITION_RANGE);
    let world = |row: &[f32]| -> Vec<f32> {
        position.clone().map(|c| row[c] * stats.std[c] + stats.mean[c]).collect()
    };
    let mut flagged = 0;
    for (i, window) in batch.put_down.iter().enumerate() {
        for (slot, &put) in window.iter().enumerate() {
            if !put {
                continue;
            }
            flagged += 1;
            assert!(batch.presence_values[i][slot], "window {i}, slot {slot}: no object");
            assert_eq!(settled[i][slot], 0.0, "window {i}, slot {slot}: set down before");
            let at = |t: usize| world(&features[((i * 2 + slot) * t_all + t) * d..][..d]);
            let last = at(t_all - 1);
            for t in t_all.saturating_sub(STILL_FRAMES)..t_all {
                let moved: f32 =
                    at(t).iter().zip(&last).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt();
                assert!(moved <= STILL_M + 1e-4, "window {i}, slot {slot}, frame {t}: {moved}");
            }
            let from = world(&start[(i * 2 + slot) * d..][..d]);
            let height = (last[1] - from[1]).abs();
            assert!(height <= SET_DOWN_HEIGHT_M + 1e-4, "window {i}, slot {slot}: {height} m");
        }
    }
    assert!(flagged >= 4, "{flagged} put-downs in 128 windows");
}

/// `put_down_share`: at 1 every window of a batch sets an object down within its predicted
/// frames; such windows are a minority of all, and a share of 0 is left out of a written
/// configuration.
#[test]
fn a_share_of_windows_comes_from_those_that_set_an_object_down() {
    let trainer = tiny_trainer_with_stride_5();
    let set = trainer.training_set();
    let (put_down, all) = (set.put_down_windows().len(), set.windows().len());
    assert!(put_down > 0 && put_down * 2 < all, "{put_down} of {all} windows set an object down");
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let options = BatchOptions {
        size: 64,
        swap_probability: 0.5,
        mirror_probability: 0.5,
        first_window_share: 0.0,
        put_down_share: 1.0,
    };
    let batch = set.batch(&options, &mut rng, &Device::Cpu).unwrap();
    assert!(batch.put_down.iter().all(|slots| slots.iter().any(|&p| p)));
    let toml = toml::to_string(trainer.config()).unwrap();
    assert!(!toml.contains("put_down"), "{toml}");
}

/// The action labels of the procedural data, one per task family.
const FAMILIES: [&str; 8] =
    ["handover", "hold_two", "inspect", "lift_both", "move_next_to", "pick_place", "pour", "swap"];

/// The action label of window `index` of a trainer's set.
fn action_of(trainer: &Trainer, index: usize) -> &str {
    let set = trainer.training_set();
    set.sequences()[set.windows()[index].sequence].action.as_deref().unwrap_or("")
}

/// A tiny trainer on 16 procedural sequences (two of each task family) whose windows are drawn
/// with `weights` by action, or its error's message.
fn trainer_weighted_by_action(weights: &[(&str, f64)]) -> Result<Trainer, String> {
    let data = dex2hoi_synth::build_dataset(16, 5, 20.0, &|_| {}).unwrap();
    let mut config = TrainConfig::preset("tiny").unwrap();
    config.training.window_stride = 5;
    config.training.action_weights = weights.iter().map(|&(a, w)| (a.to_owned(), w)).collect();
    Trainer::new(config, &data, Path::new("procedural"), &Device::Cpu).map_err(|e| e.to_string())
}

/// `action_weights`: a listed action's windows are drawn with its weight against 1 for the
/// others, in every pool (first windows, put-down windows, the rest); without weights the
/// draws are those of a uniform index, as before the option existed.
#[test]
fn windows_are_drawn_by_the_weight_of_their_action() {
    let options = |first: f64, put_down: f64| BatchOptions {
        size: 1,
        swap_probability: 0.5,
        mirror_probability: 0.5,
        first_window_share: first,
        put_down_share: put_down,
    };
    let draws = 4000;

    let unweighted = trainer_weighted_by_action(&[]).unwrap();
    let windows = unweighted.training_set().windows().len();
    let (mut rng, mut uniform) = (ChaCha8Rng::seed_from_u64(4), ChaCha8Rng::seed_from_u64(4));
    for _ in 0..200 {
        let drawn = unweighted.training_set().draw_window(&options(0.0, 0.0), &mut rng);
        assert_eq!(drawn, rand::Rng::random_range(&mut uniform, 0..windows));
    }

    let pour = trainer_weighted_by_action(&[("pour", 4.0)]).unwrap();
    let pours = (0..windows).filter(|&i| action_of(&pour, i) == "pour").count();
    assert!(pours > 0 && pours * 4 < windows, "{pours} pour windows of {windows}");
    let expected = 4.0 * pours as f64 / (4.0 * pours as f64 + (windows - pours) as f64);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let drawn = (0..draws)
        .filter(|_| {
            let index = pour.training_set().draw_window(&options(0.0, 0.0), &mut rng);
            action_of(&pour, index) == "pour"
        })
        .count();
    let share = drawn as f64 / draws as f64;
    // Four binomial standard deviations of 4000 draws at a share near 0.4 are 0.03.
    assert!((share - expected).abs() < 0.03, "pour drawn {share}, expected {expected}");

    let only_swap: Vec<(&str, f64)> =
        FAMILIES.iter().filter(|&&a| a != "swap").map(|&a| (a, 0.0)).collect();
    let swap = trainer_weighted_by_action(&only_swap).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for (first, put_down) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.5, 0.5)] {
        for _ in 0..200 {
            let index = swap.training_set().draw_window(&options(first, put_down), &mut rng);
            assert_eq!(action_of(&swap, index), "swap", "shares {first}, {put_down}");
        }
    }
}

/// The error of a trainer with `weights`.
fn refusal(weights: &[(&str, f64)]) -> String {
    match trainer_weighted_by_action(weights) {
        Ok(_) => panic!("weights {weights:?} accepted"),
        Err(error) => error,
    }
}

/// `action_weights` is checked: a label no training sequence has (the known ones named), a
/// negative weight, weights that leave no window; it survives the written configuration and
/// is left out of it when empty.
#[test]
fn action_weights_are_checked_and_written() {
    let error = refusal(&[("poor", 2.0)]);
    assert!(error.contains("training.action_weights.poor") && error.contains("pour"), "{error}");
    let error = refusal(&[("pour", -1.0)]);
    assert!(error.contains("non-negative"), "{error}");
    let zero: Vec<(&str, f64)> = FAMILIES.iter().map(|&a| (a, 0.0)).collect();
    let error = refusal(&zero);
    assert!(error.contains("0 for every window"), "{error}");

    let trainer = trainer_weighted_by_action(&[("pour", 3.0), ("swap", 2.5)]).unwrap();
    let toml = trainer.config().to_toml().unwrap();
    let read = TrainConfig::from_toml(&toml, "written").unwrap();
    assert_eq!(&read, trainer.config());
    assert_eq!(read.training.action_weights.get("swap"), Some(&2.5));
    let plain = TrainConfig::preset("tiny").unwrap().to_toml().unwrap();
    assert!(!plain.contains("action_weights"), "{plain}");
}
