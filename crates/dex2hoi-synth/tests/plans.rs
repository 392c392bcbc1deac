//! Properties of the procedural plans over many seeds: the hand the words name does not follow
//! from where the object stands, nor the side a pick and place names from the hand or the
//! object's place; a hand-over ends on the taking hand's side; every sequence ends at rest, the
//! box is lifted, an object no hand holds stands on the table top, a drawn pace changes only
//! the times of the task, ending some earlier and some later than the even pace, and an object
//! set down after the task moved it is left there.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_data::character::Hand;
use dex2hoi_data::settled::{MOVED_RISE_M, MOVED_TRAVEL_M, SettledObjects};
use dex2hoi_synth::plan::{
    HANDOVER_START, HANDOVER_TRAVEL, IDLE_BEFORE_TASK, ONE_HANDED_PUT_DOWN, ONE_HANDED_REACH, Plan,
    REST_AFTER_TASK, TASK_TEMPO, Task, TaskTempo, Timing, plan_task, plan_task_with,
};
use dex2hoi_synth::text::Description;
use dex2hoi_synth::{SynthSequence, generate};
use glam::Vec3;

fn plans(task: Task, seeds: std::ops::Range<u64>) -> impl Iterator<Item = Plan> {
    seeds.map(move |seed| plan_task(task, &mut ChaCha8Rng::seed_from_u64(seed)))
}

/// Where the object of a one-handed task stands on `frame`, sideways towards the acting hand's
/// side (positive: on that hand's side), and the hand, in a generated sequence (after the draws
/// the physical checks refused).
fn towards_hand_at(synth: &SynthSequence, frame: usize) -> (f32, Hand) {
    let first = &synth.attachments[0];
    let object = &synth.sequence.objects[first.object];
    // The scene is turned about +Y and moved: measure in the character's frame at the start.
    let root = synth.sequence.root_positions[0];
    let turn = synth.sequence.local_rotations[0];
    let local = turn.transpose() * (object.translations[frame] - root);
    (local.x * first.hand.side(), first.hand)
}

fn start_towards_hand(synth: &SynthSequence) -> (f32, Hand) {
    towards_hand_at(synth, 0)
}

#[test]
fn the_hand_does_not_follow_from_where_the_object_stands() {
    for task in [Task::PickPlace, Task::Inspect, Task::Handover] {
        let family = Task::ALL.iter().position(|&t| t == task).expect("a task family");
        let starts: Vec<(f32, Hand)> = (0..400)
            .map(|k| start_towards_hand(&generate(family + 8 * k, 9, 20.0).expect("generated")))
            .collect();
        let (low, high) = (ONE_HANDED_REACH.start, ONE_HANDED_REACH.end);
        assert!(starts.iter().all(|&(x, _)| (low - 1e-6..=high + 1e-6).contains(&x)), "{task:?}");
        // Across the body or in the middle (within 5 cm) in a good share of plans.
        let crossing = starts.iter().filter(|&&(x, _)| x < 0.05).count() as f32 / 400.0;
        assert!((0.25..0.75).contains(&crossing), "{task:?}: {crossing}");
        // An object on the person's left is taken by either hand, each at least a fifth of
        // the time: a model cannot read the hand off the object's side.
        let on_left: Vec<Hand> = starts
            .iter()
            .filter(|&&(x, hand)| x * hand.side() > 0.05)
            .map(|&(_, hand)| hand)
            .collect();
        let by_right = on_left.iter().filter(|&&h| h == Hand::Right).count() as f32;
        let share = by_right / on_left.len() as f32;
        assert!((0.2..0.8).contains(&share), "{task:?}: right hand takes {share} of left objects");
    }
}

#[test]
fn the_side_a_pick_and_place_names_follows_neither_the_hand_nor_the_place() {
    let family = Task::ALL.iter().position(|&t| t == Task::PickPlace).expect("a task family");
    let mut own_side = 0;
    let mut middle = (0, 0);
    for k in 0..400 {
        let synth = generate(family + 8 * k, 9, 20.0).expect("generated");
        let (start, hand) = start_towards_hand(&synth);
        let (end, _) = towards_hand_at(&synth, synth.sequence.frames() - 1);
        let Description::PickPlace { hand: named, towards, .. } = synth.description else {
            panic!("{}: not a pick and place", synth.sequence.source_id);
        };
        assert_eq!(named, hand, "{}", synth.sequence.source_id);
        // The words say where the motion puts it: 10-16 cm that way, within reach.
        let moved = (end - start) * if towards == hand { 1.0 } else { -1.0 };
        assert!((0.09..0.17).contains(&moved), "{}: {moved} m", synth.sequence.source_id);
        let reach = ONE_HANDED_PUT_DOWN.start - 1e-4..=ONE_HANDED_PUT_DOWN.end + 1e-4;
        assert!(reach.contains(&end), "{}: put down at {end} m", synth.sequence.source_id);
        own_side += usize::from(towards == hand);
        if start.abs() < 0.05 {
            middle.0 += 1;
            middle.1 += usize::from(towards == hand);
        }
    }
    // Towards the hand's own side about half the time, in the middle of the table too: the
    // hand and where the object stands do not tell the side, only the words do.
    let share = own_side as f32 / 400.0;
    assert!((0.42..0.58).contains(&share), "{share} of pick and places go to the hand's side");
    assert!(middle.0 >= 60, "{} of 400 objects start in the middle", middle.0);
    let share = middle.1 as f32 / middle.0 as f32;
    assert!((0.35..0.65).contains(&share), "{share} of those in the middle go to the hand's side");
}

#[test]
fn a_handover_ends_further_on_the_taking_hands_side_than_it_started() {
    let family = Task::ALL.iter().position(|&t| t == Task::Handover).expect("a task family");
    let mut on_taking_side = 0;
    for k in 0..200 {
        let synth = generate(family + 8 * k, 9, 20.0).expect("generated");
        let id = &synth.sequence.source_id;
        let (start, giver) = start_towards_hand(&synth);
        let (end, _) = towards_hand_at(&synth, synth.sequence.frames() - 1);
        let Description::Handover { from, .. } = synth.description else {
            panic!("{id}: not a hand-over");
        };
        assert_eq!(from, giver, "{id}");
        let starts = HANDOVER_START.start - 1e-4..=HANDOVER_START.end + 1e-4;
        assert!(starts.contains(&start), "{id}: starts at {start} m");
        // Positive towards the giving hand: the words' side is the other way.
        assert!(start - end >= HANDOVER_TRAVEL - 1e-3, "{id}: from {start} m to {end} m");
        on_taking_side += usize::from(start < -0.05);
    }
    // Some objects already stand on the taking hand's side, and still go further that way.
    assert!(on_taking_side >= 20, "{on_taking_side} of 200 start on the taking hand's side");
}

#[test]
fn every_plan_ends_with_the_person_at_rest_for_a_varying_time() {
    let mut tails = Vec::new();
    for task in Task::ALL {
        for plan in plans(task, 0..60) {
            let (_, done) = task_span(&plan);
            let tail = plan.duration - done;
            assert!(
                (REST_AFTER_TASK.start..REST_AFTER_TASK.end).contains(&tail),
                "{task:?}: {tail} s of rest"
            );
            tails.push(tail);
        }
    }
    let (shortest, longest) =
        tails.iter().fold((f32::INFINITY, 0.0f32), |(a, b), &t| (a.min(t), b.max(t)));
    assert!(shortest < 1.0 && longest > 7.0, "rest tails from {shortest} to {longest} s");
}

#[test]
fn the_box_is_lifted_with_both_hands() {
    // Sequence indices 1, 9, 17, ... are the two-handed lift.
    let boxes = (0..40)
        .map(|k| generate(1 + 8 * k, 3, 20.0).expect("generation succeeds"))
        .filter(|s| s.sequence.objects[0].name == "box")
        .count();
    assert!(boxes >= 4, "{boxes} of 40 two-handed lifts use the box");
}

#[test]
fn objects_no_hand_holds_stand_on_the_table_top() {
    for index in 0..48 {
        let synth = generate(index, 5, 20.0).expect("generation succeeds");
        let s = &synth.sequence;
        for (o, object) in s.objects.iter().enumerate() {
            for f in 0..s.frames() {
                let t = f as f32 / s.fps;
                let held =
                    synth.attachments.iter().any(|a| a.object == o && a.start < t && t < a.end);
                if held {
                    continue;
                }
                let lowest = object
                    .mesh
                    .vertices
                    .iter()
                    .map(|v| (object.rotations[f] * *v + object.translations[f]).y)
                    .fold(f32::INFINITY, f32::min);
                let height = lowest - synth.table_height;
                assert!(
                    height.abs() < 2e-3,
                    "{} {}: free at {t:.2} s with its bottom {:.1} mm off the table",
                    s.source_id,
                    object.name,
                    height * 1e3
                );
            }
        }
    }
}

#[test]
fn a_share_of_plans_stand_still_for_longer_than_a_prefix_before_the_task() {
    // The demo preset's prefix: 20 frames at 20 fps.
    let prefix_seconds = 1.0;
    let mut longer = 0;
    let mut all = 0;
    for task in Task::ALL {
        for plan in plans(task, 0..60) {
            let (first, _) = task_span(&plan);
            assert!(IDLE_BEFORE_TASK.contains(&first), "{task:?}: first reach at {first} s");
            longer += usize::from(first > prefix_seconds + 0.25);
            all += 1;
        }
    }
    let share = longer as f32 / all as f32;
    assert!((0.3..0.8).contains(&share), "{share} of plans stand still for over 1.25 s");
}

/// The first reach and the time the last hand is back at rest.
fn task_span(plan: &Plan) -> (f32, f32) {
    let first = plan.attachments.iter().map(|a| a.reach_start).fold(f32::INFINITY, f32::min);
    let done = plan.attachments.iter().map(|a| a.retract_end).fold(0.0, f32::max);
    (first, done)
}

#[test]
fn the_tempo_changes_the_times_of_the_task_and_nothing_else() {
    let (even, drawn) =
        (Timing::default(), Timing { tempo: TaskTempo::Drawn, ..Timing::default() });
    for task in Task::ALL {
        let (mut faster, mut slower) = (0, 0);
        for seed in 0..60 {
            let at_even = plan_task_with(task, even, &mut ChaCha8Rng::seed_from_u64(seed));
            let paced = plan_task_with(task, drawn, &mut ChaCha8Rng::seed_from_u64(seed));
            assert_eq!(at_even.tempo, 1.0);
            assert!(TASK_TEMPO.contains(&paced.tempo), "{task:?} {seed}: tempo {}", paced.tempo);
            // The same scene, objects, places and words.
            assert_eq!(at_even.table_height, paced.table_height);
            assert_eq!(at_even.texts, paced.texts);
            assert_eq!(at_even.held_out_texts, paced.held_out_texts);
            assert_eq!(at_even.objects.len(), paced.objects.len());
            for ((a, track_a), (b, track_b)) in at_even.objects.iter().zip(&paced.objects) {
                assert_eq!(a.name, b.name);
                let poses = |t: &dex2hoi_synth::plan::Track| -> Vec<_> {
                    t.keys.iter().map(|k| (k.1.position, k.1.rotation)).collect()
                };
                assert_eq!(poses(track_a), poses(track_b), "{task:?} {seed}");
            }
            // The same idle time before, and a task that takes longer at a slower pace.
            let (first_even, done_even) = task_span(&at_even);
            let (first_paced, done_paced) = task_span(&paced);
            assert_eq!(first_even, first_paced, "{task:?} {seed}");
            let longer = (done_paced - first_paced) - (done_even - first_even);
            assert!(longer * (paced.tempo - 1.0) >= 0.0, "{task:?} {seed}: {longer} s longer");
            faster += usize::from(paced.tempo < 0.8);
            slower += usize::from(paced.tempo > 1.2);
        }
        assert!(faster >= 6 && slower >= 6, "{task:?}: {faster} fast, {slower} slow of 60");
    }
}

/// A ten-second generation reads the prompt clock at every time from 0 to 10 s; at rest, a
/// model can tell before the task from after it only by the clock. At the even pace no lift
/// with both hands was done before 4.5 s (400 seeds), so a person standing still at 4 s was,
/// in the data, always about to start; drawn paces end a tenth of every family's tasks before
/// the even pace's earliest, and keep a tenth busy for longer than its latest.
#[test]
fn drawn_paces_end_tasks_earlier_and_later_than_the_even_pace() {
    let (even, drawn) =
        (Timing::default(), Timing { tempo: TaskTempo::Drawn, ..Timing::default() });
    for task in Task::ALL {
        let done = |timing: Timing| -> Vec<f32> {
            (0..400)
                .map(|seed| {
                    task_span(&plan_task_with(task, timing, &mut ChaCha8Rng::seed_from_u64(seed))).1
                })
                .collect()
        };
        let (at_even, paced) = (done(even), done(drawn));
        let earliest = at_even.iter().copied().fold(f32::INFINITY, f32::min);
        let latest = at_even.iter().copied().fold(0.0, f32::max);
        let earlier = paced.iter().filter(|&&t| t < earliest).count();
        let later = paced.iter().filter(|&&t| t > latest).count();
        eprintln!(
            "{task:?}: even pace {earliest:.2}-{latest:.2} s; drawn: {earlier} earlier, {later} later"
        );
        assert!(earlier >= 40 && later >= 40, "{task:?}: {earlier} earlier, {later} later of 400");
    }
}

/// What the memory of set-down objects reads (`dex2hoi_data::settled`) on generated sequences:
/// by the last frame every object the task moved is set down and flagged, and none it leaves
/// is; once flagged, an object is never moved again, except the object a swap parks on the
/// way (flagged while parked, then carried to the other's place), which only its words tell.
#[test]
fn objects_a_task_moves_are_flagged_set_down_at_the_end_and_then_left() {
    for (family, &task) in Task::ALL.iter().enumerate() {
        let mut moved_again = 0;
        for k in 0..40 {
            let synth = generate(family + 8 * k, 11, 20.0).expect("generated");
            let objects = &synth.sequence.objects;
            let frames = objects[0].translations.len();
            let position = |t: usize| -> [Vec3; MAX_OBJECTS] {
                std::array::from_fn(|s| objects.get(s).map_or(Vec3::ZERO, |o| o.translations[t]))
            };
            let moved: Vec<bool> = (0..objects.len())
                .map(|s| {
                    (0..frames).any(|t| {
                        let travel = position(t)[s] - position(0)[s];
                        travel.length() > MOVED_TRAVEL_M || travel.y > MOVED_RISE_M
                    })
                })
                .collect();
            let mut tracker = SettledObjects::new();
            let mut first_flagged = [None; MAX_OBJECTS];
            for t in 0..frames {
                tracker.push(position(t));
                for (s, flagged) in tracker.settled().into_iter().enumerate() {
                    if flagged && first_flagged[s].is_none() {
                        first_flagged[s] = Some(t);
                    }
                }
            }
            let last = tracker.settled();
            for s in 0..objects.len() {
                assert_eq!(last[s], moved[s], "{task:?}, sequence {k}, slot {s}");
                let Some(from) = first_flagged[s] else { continue };
                let left =
                    (from..frames).all(|t| (position(t)[s] - position(from)[s]).length() < 0.02);
                moved_again += usize::from(!left);
            }
        }
        let expected = if task == Task::Swap { 40 } else { 0 };
        assert_eq!(moved_again, expected, "{task:?}: objects moved again after being set down");
    }
}
