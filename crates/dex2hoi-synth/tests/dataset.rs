//! The dataset format, augmentation and windows.

use dex2hoi_data::augment::{mirror, mirror_text, swap_streams};
use dex2hoi_data::dataset::{Dataset, Split};
use dex2hoi_data::features::MixtureTargets;
use dex2hoi_data::window::{WindowConfig, resample, windows};
use dex2hoi_repr::Skeleton;
use dex2hoi_synth::build_dataset;
use dex2hoi_synth::text::{Phrasing, grammar_words};

fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("dex2hoi-{name}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

fn small(seed: u64) -> Dataset {
    build_dataset(88, seed, 20.0, &|_| {}).unwrap()
}

#[test]
fn save_and_load_round_trip_and_same_seed_same_bytes() {
    let mut dataset = small(3);
    // Each sequence keeps its own body: one subject is taller than the built-in skeleton.
    let tall = &mut dataset.splits.get_mut(&Split::Train).unwrap()[1];
    tall.rest_offsets.iter_mut().for_each(|o| *o *= 1.1);
    // Blocks of eight: block 9 (indices 72-79) is the test split, one of every task.
    assert_eq!(dataset.manifest.splits[&Split::Test].sequences, 8);
    assert_eq!(dataset.manifest.splits[&Split::Test].actions.len(), 8);
    assert_eq!(dataset.manifest.splits[&Split::Train].sequences, 80);
    let a = temp_dir("a");
    dataset.save(&a).unwrap();
    let loaded = Dataset::load(&a).unwrap();
    assert_eq!(loaded.manifest, dataset.manifest);
    assert_eq!(loaded.splits, dataset.splits);
    let builtin = Skeleton::smplx();
    let train = &loaded.splits[&Split::Train];
    assert_eq!(train[0].skeleton(&builtin).unwrap(), builtin);
    assert_ne!(train[1].skeleton(&builtin).unwrap(), builtin);
    assert_eq!(loaded.stats, dataset.stats);
    assert_eq!(loaded.objects.len(), 8);
    for (x, y) in loaded.objects.iter().zip(&dataset.objects) {
        assert_eq!((&x.name, &x.mesh, &x.bps, &x.samples), (&y.name, &y.mesh, &y.bps, &y.samples));
    }
    // Same seed, same bytes; another seed, other bytes.
    let b = temp_dir("b");
    let mut again = small(3);
    again.splits.get_mut(&Split::Train).unwrap()[1].rest_offsets.iter_mut().for_each(|o| *o *= 1.1);
    again.save(&b).unwrap();
    let c = temp_dir("c");
    small(4).save(&c).unwrap();
    for file in [
        "manifest.json",
        "train.safetensors",
        "test.safetensors",
        "train.json",
        "objects.safetensors",
        "stats.safetensors",
    ] {
        let bytes = |d: &std::path::Path| std::fs::read(d.join(file)).unwrap();
        assert_eq!(bytes(&a), bytes(&b), "{file}");
        if file.starts_with("train") {
            assert_ne!(bytes(&a), bytes(&c), "{file}");
        }
    }
    // Every sequence has a description in a held-out phrasing, and no sequence of any split is
    // trained on it.
    let trained: std::collections::HashSet<&String> =
        loaded.splits.values().flatten().flat_map(|s| &s.texts).collect();
    for sequence in loaded.splits.values().flatten() {
        assert_eq!(sequence.held_out_texts.len(), 1, "{}", sequence.source_id);
        assert!(sequence.held_out_texts.iter().all(|t| !trained.contains(t)));
    }
    // A dataset of format 2 (no held-out descriptions) reads, without them.
    let old = temp_dir("format-2");
    dataset.save(&old).unwrap();
    let manifest = std::fs::read_to_string(old.join("manifest.json")).unwrap();
    let current = format!("\"format_version\": {}", dex2hoi_data::dataset::FORMAT_VERSION);
    let mut manifest: serde_json::Value =
        serde_json::from_str(&manifest.replace(&current, "\"format_version\": 2")).unwrap();
    manifest.as_object_mut().unwrap().remove("mixture_targets").expect("written in format 5");
    std::fs::write(old.join("manifest.json"), serde_json::to_vec(&manifest).unwrap()).unwrap();
    for split in ["train", "test"] {
        let path = old.join(format!("{split}.json"));
        let mut infos: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        for info in infos.as_array_mut().unwrap() {
            info.as_object_mut().unwrap().remove("held_out_texts").expect("written in format 3");
        }
        std::fs::write(&path, serde_json::to_vec(&infos).unwrap()).unwrap();
    }
    let read = Dataset::load(&old).unwrap();
    assert!(read.splits.values().flatten().all(|s| s.held_out_texts.is_empty()));
    // Its mixture targets were the paper's rule, as new data's by default.
    assert_eq!(read.manifest.mixture_targets, MixtureTargets::Proximity);
    assert_eq!(loaded.manifest.mixture_targets, MixtureTargets::default());
    assert_eq!(read.splits[&Split::Test][0].texts, loaded.splits[&Split::Test][0].texts);
    std::fs::remove_dir_all(old).ok();
    // Statistics: floors hold, mixture channels are left as logits.
    let width = dataset.manifest.stream_feature_size;
    assert!(dataset.stats.std.iter().all(|s| *s >= 0.01));
    assert_eq!(&dataset.stats.mean[width - 3..], &[0.0; 3]);
    assert_eq!(&dataset.stats.std[width - 3..], &[1.0; 3]);
    for d in [a, b, c] {
        std::fs::remove_dir_all(d).ok();
    }
}

#[test]
fn broken_datasets_give_clear_errors() {
    let dir = temp_dir("broken");
    let error = Dataset::load(&dir).unwrap_err().to_string();
    assert!(error.contains("manifest.json"), "{error}");
    build_dataset(9, 1, 20.0, &|_| {}).unwrap().save(&dir).unwrap();
    std::fs::write(dir.join("train.safetensors"), b"garbage").unwrap();
    let error = Dataset::load(&dir).unwrap_err().to_string();
    assert!(error.contains("train.safetensors"), "{error}");
    let manifest = std::fs::read_to_string(dir.join("manifest.json")).unwrap();
    let current = format!("\"format_version\": {}", dex2hoi_data::dataset::FORMAT_VERSION);
    assert!(manifest.contains(&current));
    // A dataset of the first format (no rest skeletons) is refused with what to do.
    std::fs::write(dir.join("manifest.json"), manifest.replace(&current, "\"format_version\": 1"))
        .unwrap();
    let error = Dataset::load(&dir).unwrap_err().to_string();
    assert!(error.contains("format_version") && error.contains("data prepare"), "{error}");
    std::fs::write(dir.join("manifest.json"), manifest.replace(&current, "\"format_version\": 99"))
        .unwrap();
    let error = Dataset::load(&dir).unwrap_err().to_string();
    assert!(error.contains("format_version") && error.contains("newer"), "{error}");
    std::fs::write(dir.join("manifest.json"), "{").unwrap();
    assert!(Dataset::load(&dir).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn mirroring_and_swapping_twice_is_the_identity() {
    let dataset = build_dataset(16, 2, 20.0, &|_| {}).unwrap();
    let skeleton = Skeleton::smplx();
    for sequence in &dataset.splits[&Split::Train] {
        assert_eq!(&mirror(&mirror(sequence, &skeleton), &skeleton), sequence);
        assert_eq!(&swap_streams(&swap_streams(sequence)), sequence);
        let mirrored = mirror(sequence, &skeleton);
        assert_ne!(&mirrored, sequence);
        // Hands trade places: the left hand's contacts become the right hand's.
        for (a, b) in mirrored.hand_contact.chunks(2).zip(sequence.hand_contact.chunks(2)) {
            assert_eq!((a[0], a[1]), (b[1], b[0]));
        }
        let swapped = swap_streams(sequence);
        assert_eq!(swapped.object_names[0], sequence.object_names[1]);
    }
    assert_eq!(
        mirror_text("The left hand passes the Left cup to the right."),
        "The right hand passes the Right cup to the left."
    );
    assert_eq!(mirror_text("leftover rights"), "leftover rights");
    assert_eq!(mirror_text("Leftwards, then RIGHTWARD."), "Rightwards, then LEFTWARD.");
    // Every word of the description grammar that names a side is mirrored, so a mirrored
    // window's text says what its motion does.
    for phrasing in [Phrasing::Training, Phrasing::HeldOut] {
        for word in grammar_words(phrasing) {
            if word.contains("left") || word.contains("right") {
                let image = mirror_text(&word);
                assert_ne!(image, word, "{word} is not mirrored");
                assert_eq!(mirror_text(&image), word);
            }
        }
    }
}

#[test]
fn windows_cover_sequences_and_pad_short_ones() {
    let config = WindowConfig::default();
    let all = windows(&[60, 75, 30, 0], &config).unwrap();
    let of = |s: usize| all.iter().filter(|w| w.sequence == s).copied().collect::<Vec<_>>();
    assert_eq!(of(0).len(), 1);
    // 75 frames: starts 0 and 10 fit, then one window ending at the last frame.
    assert_eq!(of(1).iter().map(|w| w.start).collect::<Vec<_>>(), vec![0, 10, 15]);
    let short = of(2)[0];
    assert_eq!(short.valid_frames, 30);
    let mask = short.mask(&config);
    assert_eq!(mask.len(), 60);
    assert_eq!(mask.iter().sum::<f32>(), 30.0);
    assert_eq!(short.frame(45), 29, "padding repeats the last frame");
    assert!(of(3).is_empty());
    assert!(windows(&[10], &WindowConfig { stride: 0, ..config }).is_err());
}

#[test]
fn resampling_keeps_the_motion() {
    let synth = dex2hoi_synth::generate(0, 1, 20.0).unwrap();
    let s = &synth.sequence;
    let same = resample(s, 20.0).unwrap();
    assert_eq!(same.frames(), s.frames());
    for (a, b) in same.local_rotations.iter().zip(&s.local_rotations) {
        assert!(a.abs_diff_eq(*b, 1e-5));
    }
    let half = resample(s, 10.0).unwrap();
    assert_eq!(half.frames(), (s.frames() - 1) / 2 + 1);
    let joints = s.skeleton.joint_count();
    for k in 0..half.frames() {
        for j in 0..joints {
            assert!(
                half.local_rotations[k * joints + j]
                    .abs_diff_eq(s.local_rotations[2 * k * joints + j], 1e-5)
            );
        }
        assert!(
            half.objects[0].translations[k].abs_diff_eq(s.objects[0].translations[2 * k], 1e-5)
        );
    }
    let up = resample(s, 30.0).unwrap();
    assert!((up.frames() as f32 / 30.0 - s.frames() as f32 / 20.0).abs() < 0.1);
    assert!(resample(s, 0.0).is_err());
}

#[test]
fn feature_mirroring_equals_mirroring_the_raw_motion() {
    use dex2hoi_data::augment::mirror_sequence;
    use dex2hoi_data::features::{TargetConfig, process_sequence};
    use dex2hoi_repr::MeshQuery;
    let skeleton = Skeleton::smplx();
    for index in [0, 2, 4, 7] {
        let synth = dex2hoi_synth::generate(index, 5, 20.0).unwrap();
        let process = |s: &dex2hoi_data::Sequence| {
            let queries: Vec<MeshQuery> =
                s.objects.iter().map(|o| MeshQuery::new(&o.mesh).unwrap()).collect();
            let refs: Vec<&MeshQuery> = queries.iter().collect();
            process_sequence(s, &refs, &TargetConfig::default()).unwrap()
        };
        // An asymmetric subject (each bone scaled by its own factor): mirroring must carry
        // the body over, or the mirrored joints would not be FK of the mirrored rotations.
        let mut raw = synth.sequence.clone();
        let scaled = (raw.skeleton.rest_offsets().iter().enumerate())
            .map(|(j, o)| *o * (1.0 + 0.08 * (j as f32 * 1.7).sin()))
            .collect();
        raw.skeleton = raw.skeleton.with_rest_offsets(scaled).unwrap();
        let a = mirror(&process(&raw), &skeleton);
        let b = process(&mirror_sequence(&raw));
        assert_ne!(a.rest_offsets, process(&raw).rest_offsets);
        let close = |x: &[f32], y: &[f32], what: &str| {
            assert_eq!(x.len(), y.len());
            for (k, (p, q)) in x.iter().zip(y).enumerate() {
                assert!((p - q).abs() < 2e-4, "sequence {index}, {what}[{k}]: {p} vs {q}");
            }
        };
        close(&a.body, &b.body, "body");
        close(&a.objects, &b.objects, "objects");
        close(&a.joint_positions, &b.joint_positions, "joint positions");
        close(&a.hand_distances, &b.hand_distances, "hand distances");
        close(&a.object_rotations, &b.object_rotations, "object rotations");
        close(&a.object_positions, &b.object_positions, "object positions");
        assert_eq!(a.foot_contact, b.foot_contact);
        assert_eq!(a.texts, b.texts);
        let offsets = |s: &dex2hoi_data::features::ProcessedSequence| -> Vec<f32> {
            s.rest_offsets.iter().flat_map(|o| o.to_array()).collect()
        };
        close(&offsets(&a), &offsets(&b), "rest offsets");
    }
}

#[test]
fn the_layout_serves_sequences_assets_and_windows() {
    use dex2hoi_data::layout::{slot_bps, slot_frames};
    use dex2hoi_data::window::Window;

    let dataset = build_dataset(9, 2, 20.0, &|_| {}).unwrap();
    let layout = dataset.layout();
    assert_eq!(layout.body_width(), dataset.manifest.body_feature_size);
    assert_eq!(layout.stream_width(), dataset.manifest.stream_feature_size);
    assert_eq!(layout.stream_width(), dataset.stats.mean.len());
    let sequence = &dataset.splits[&Split::Train][1];
    let frames = sequence.frames;

    // A prefix as the model reads it, and back.
    let streams = sequence.stream_features(0..5).unwrap();
    let (body, objects) = layout.streams_to_frames(&streams).unwrap();
    assert_eq!(body, sequence.body[layout.body_frames(0..5)]);
    assert_eq!(objects, sequence.objects[layout.object_frames(0..5)]);
    assert!(sequence.stream_features(0..frames + 1).is_err());

    // Object names to assets and BPS.
    let slots = dataset.slot_assets(sequence).unwrap();
    for (slot, name) in sequence.object_names.iter().enumerate() {
        assert_eq!(slots[slot].map(|k| dataset.objects[k].name.as_str()), name.as_deref());
    }
    let points = dataset.manifest.bps.points;
    let bps = slot_bps(&dataset.objects, slots, points).unwrap();
    assert_eq!(bps.len(), 2 * points * 3);
    let first = slots[0].expect("every sequence has an object in slot A");
    assert_eq!(bps[..points * 3], dataset.objects[first].bps_features());
    assert!(slot_bps(&dataset.objects, slots, points + 1).is_err());
    assert_eq!(
        dataset.asset(&dataset.objects[first].name).unwrap().name,
        dataset.objects[first].name
    );
    let mut stranger = sequence.clone();
    stranger.object_names[0] = Some("anvil".into());
    assert!(dataset.asset("anvil").is_none());
    assert!(dataset.slot_assets(&stranger).unwrap_err().to_string().contains("anvil"));

    // A padded window repeats the last frame of every per-frame array.
    let window = Window { sequence: 1, start: frames - 3, valid_frames: 3 };
    let cut = window.cut(sequence, 5);
    assert_eq!(cut.frames, 5);
    assert_eq!(
        cut.body[layout.body_frames(0..3)],
        sequence.body[layout.body_frames(frames - 3..frames)]
    );
    assert_eq!(cut.body[layout.body_row(4)], sequence.body[layout.body_row(frames - 1)]);
    assert_eq!(
        cut.hand_contact[slot_frames(4..5, 2)],
        sequence.hand_contact[slot_frames(frames - 1..frames, 2)]
    );
    assert_eq!(cut.foot_contact.len(), 5 * 4);

    // A manifest whose widths disagree with its joint count is refused.
    let dir = temp_dir("widths");
    dataset.save(&dir).unwrap();
    let manifest = std::fs::read_to_string(dir.join("manifest.json")).unwrap();
    let wrong = format!("\"body_feature_size\": {}", layout.body_width() + 1);
    let right = format!("\"body_feature_size\": {}", layout.body_width());
    assert!(manifest.contains(&right));
    std::fs::write(dir.join("manifest.json"), manifest.replace(&right, &wrong)).unwrap();
    let error = Dataset::load(&dir).unwrap_err().to_string();
    assert!(error.contains("feature sizes"), "{error}");
    std::fs::remove_dir_all(dir).ok();
}

/// `TrainingTexts::Templates` describes the same motions with the task's three fixed
/// sentences, `TrainingTexts::Both` with both sets: only the training texts change.
#[test]
fn template_texts_describe_the_same_motions() {
    use dex2hoi_synth::{SynthOptions, TrainingTexts, build_dataset_with};
    let with = |texts| SynthOptions { texts, ..SynthOptions::default() };
    let grammar = build_dataset_with(16, 4, 20.0, with(TrainingTexts::Grammar), &|_| {}).unwrap();
    let templates =
        build_dataset_with(16, 4, 20.0, with(TrainingTexts::Templates), &|_| {}).unwrap();
    let mut words = std::collections::BTreeSet::new();
    for (split, sequences) in &grammar.splits {
        for (a, b) in sequences.iter().zip(&templates.splits[split]) {
            assert_eq!(a.source_id, b.source_id);
            assert_eq!(a.held_out_texts, b.held_out_texts);
            assert_eq!(a.body, b.body, "{}", a.source_id);
            assert_ne!(a.texts, b.texts, "{}", a.source_id);
            assert_eq!(b.texts.len(), 3);
            assert!(b.texts[0].starts_with("The person "), "{}", b.texts[0]);
            for text in &b.texts {
                let split = text.split(|c: char| !c.is_alphanumeric()).filter(|w| !w.is_empty());
                words.extend(split.map(str::to_lowercase));
            }
        }
    }
    // The template sentences use 80 words (the grammar 341).
    assert!(words.len() <= 80, "{} words", words.len());
    // `Both`: the grammar's phrasings, then the fixed sentences, for the same motions.
    let both = build_dataset_with(16, 4, 20.0, with(TrainingTexts::Both), &|_| {}).unwrap();
    for (split, sequences) in &both.splits {
        for ((a, b), c) in
            sequences.iter().zip(&grammar.splits[split]).zip(&templates.splits[split])
        {
            assert_eq!(a.body, b.body, "{}", a.source_id);
            assert_eq!(a.held_out_texts, b.held_out_texts);
            assert_eq!(a.texts, [b.texts.as_slice(), c.texts.as_slice()].concat());
        }
    }
}

/// `RestAroundTask::Short`: the person starts within 0.9 s and the sequence ends when the last
/// hand is back; the task itself is drawn as with the default rest.
#[test]
fn short_rest_ends_sequences_with_the_task() {
    use dex2hoi_synth::plan::{REST_AFTER_TASK, RestAroundTask, SHORT_IDLE_BEFORE_TASK, Timing};
    use dex2hoi_synth::{generate, generate_with};
    for index in 0..16 {
        let drawn = generate(index, 6, 20.0).unwrap();
        let timing = Timing { rest: RestAroundTask::Short, ..Timing::default() };
        let short = generate_with(index, 6, 20.0, timing).unwrap();
        let last_retract = |s: &dex2hoi_synth::SynthSequence| {
            s.attachments.iter().map(|a| a.retract_end).fold(0.0, f32::max)
        };
        let first_reach = |s: &dex2hoi_synth::SynthSequence| {
            s.attachments.iter().map(|a| a.reach_start).fold(f32::INFINITY, f32::min)
        };
        let seconds = |s: &dex2hoi_synth::SynthSequence| s.sequence.frames() as f32 / 20.0;
        // The task's own length is the same; only the rest around it changed.
        let task = |s: &dex2hoi_synth::SynthSequence| last_retract(s) - first_reach(s);
        assert!((task(&drawn) - task(&short)).abs() < 1e-4, "sequence {index}");
        assert!(first_reach(&short) < SHORT_IDLE_BEFORE_TASK.end + 1e-4, "sequence {index}");
        assert!(seconds(&short) - last_retract(&short) < 0.1, "sequence {index}");
        assert!(seconds(&drawn) - last_retract(&drawn) >= REST_AFTER_TASK.start - 0.1);
        assert_eq!(short.sequence.texts, drawn.sequence.texts);
    }
}
