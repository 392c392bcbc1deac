//! `preview.gif` and `preview.png`: a known scene is rendered and its pixels checked in both
//! views (floor, table, body, object, sky where each must be; the caption's text in its band),
//! hands are coloured by contact and penetration, the GIF decodes to the same frames with the
//! right delays, the sheet has its five panels, and rendering is deterministic.

mod common;

use glam::{Mat3, Vec2, Vec3};

use dex2hoi_data::features::DecodedMotion;
use dex2hoi_export::{
    ExportMotion, ExportObject, PreviewOptions, Surface, TableBox, encode_preview_gif,
    render_preview, write_preview_gif,
};
use dex2hoi_repr::mesh::box_mesh;
use dex2hoi_repr::{Skeleton, forward_kinematics};

const TABLE: TableBox =
    TableBox { height: 0.9, centre: Vec2::new(0.0, 0.6), half_extents: Vec2::new(0.5, 0.3) };

/// The rest pose standing still for `frames` frames with a box on the table.
fn still_scene(skeleton: &Skeleton, frames: usize) -> DecodedMotion {
    let joints = skeleton.joint_count();
    let local_rotations = vec![Mat3::IDENTITY; frames * joints];
    let root_positions = vec![skeleton.rest_offsets()[0]; frames];
    let fk = forward_kinematics(skeleton, &local_rotations, &root_positions).expect("FK");
    let object = (vec![Mat3::IDENTITY; frames], vec![Vec3::new(0.25, 0.98, 0.5); frames]);
    DecodedMotion { local_rotations, root_positions, joints: fk, objects: [Some(object), None] }
}

#[test]
fn a_known_scene_shows_each_surface_where_it_must() {
    let skeleton = Skeleton::smplx();
    let motion = still_scene(&skeleton, 3);
    let mesh = box_mesh(Vec3::new(0.08, 0.08, 0.08));
    let export = ExportMotion {
        skeleton: &skeleton,
        fps: 20.0,
        prompts: vec![(0, "standing".into())],
        motion: &motion,
        objects: vec![ExportObject { name: "box".into(), mesh: &mesh, slot: 0 }],
        body: None,
    };
    let options = PreviewOptions { table: Some(TABLE), ..PreviewOptions::default() };
    let preview = render_preview(&export, &options).expect("rendered");
    if let Some(dir) = std::env::var_os("DEX2HOI_PREVIEW_DIR") {
        let path = std::path::Path::new(&dir).join("known-scene.gif");
        write_preview_gif(&path, &export, &options).expect("written");
    }
    // Two 320 x 320 views side by side under the caption band.
    let band = preview.caption_height;
    assert!(band >= 20, "caption band {band}");
    assert_eq!((preview.width, preview.height), (640, 320 + band));
    assert_eq!(preview.frames.len(), 3);
    assert!(preview.frames.iter().all(|f| f.len() == 640 * (320 + band) as usize));
    assert_eq!(preview.delays, [5, 5, 5]);

    for (k, view) in preview.views.iter().enumerate() {
        let surface_at = |world: Vec3| {
            let pixel = view.project(world).expect("in front of the camera");
            let inside = pixel.x >= view.origin.x
                && pixel.y >= view.origin.y
                && pixel.x < view.origin.x + 320.0
                && pixel.y < view.origin.y + 320.0;
            assert!(inside, "view {k}: {world} projects outside the view to {pixel}");
            preview.surface_at(0, pixel.x as u32, pixel.y as u32).expect("a pixel")
        };
        assert_eq!(surface_at(skeleton.rest_offsets()[0]), Surface::Body, "view {k}: pelvis");
        let chest = skeleton.rest_positions()[9];
        assert_eq!(surface_at(chest), Surface::Body, "view {k}: chest");
        assert_eq!(surface_at(Vec3::new(0.25, 0.98, 0.5)), Surface::Object(0), "view {k}: box");
        let floor = Vec3::new(0.9, 0.0, -0.6);
        assert_eq!(surface_at(floor), Surface::Floor, "view {k}: floor behind");
        let corner = (view.origin.x as u32, view.origin.y as u32);
        assert_eq!(preview.surface_at(0, corner.0, corner.1), Some(Surface::Background), "sky");
    }
    let table_top = preview.views[0].project(Vec3::new(-0.35, 0.9, 0.8)).unwrap();
    assert_eq!(preview.surface_at(0, table_top.x as u32, table_top.y as u32), Some(Surface::Table));
    // The caption's text is written in its band, and only there.
    let caption_pixels = |preview: &dex2hoi_export::Preview, rows: std::ops::Range<u32>| {
        rows.flat_map(|y| (0..preview.width).map(move |x| (x, y)))
            .filter(|&(x, y)| preview.surface_at(0, x, y) == Some(Surface::Caption))
            .count()
    };
    assert!(caption_pixels(&preview, 0..band) > 50);
    assert_eq!(caption_pixels(&preview, band..preview.height), 0);
    let plain = render_preview(&export, &PreviewOptions { caption: false, ..options }).unwrap();
    assert_eq!((plain.caption_height, plain.height), (0, 320));
    assert_eq!(caption_pixels(&plain, 0..plain.height), 0);
    // Every surface kind shows up, and a still scene gives identical frames.
    assert_eq!(preview.frames[0], preview.frames[2]);
}

#[test]
fn the_gif_decodes_to_the_rendered_frames_and_rendering_is_deterministic() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 5, 2);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes, "wave");
    let options = PreviewOptions { width: 96, height: 64, table: None, caption: false };
    let preview = render_preview(&export, &options).expect("rendered");
    assert_eq!(preview, render_preview(&export, &options).expect("again"));
    // The body moves, so consecutive frames differ.
    assert_ne!(preview.frames[0], preview.frames[1]);

    let bytes = encode_preview_gif(&export, &options).expect("encoded");
    assert_eq!(bytes, preview.encode_gif().expect("encoded"));
    let mut decoder = gif::DecodeOptions::new();
    decoder.set_color_output(gif::ColorOutput::Indexed);
    let mut decoder = decoder.read_info(&bytes[..]).expect("a GIF");
    assert_eq!((decoder.width(), decoder.height()), (192, 64));
    let mut frames = 0;
    while let Some(frame) = decoder.read_next_frame().expect("a frame") {
        assert_eq!((frame.width, frame.height, frame.delay), (192, 64, 5));
        assert_eq!(&frame.buffer[..], &preview.frames[frames][..]);
        frames += 1;
    }
    assert_eq!(frames, 5);
}

#[test]
fn a_procedural_sequence_renders_with_the_body_over_the_pelvis_in_every_frame() {
    let (synth, motion) = common::synth_motion(3);
    let export = common::synth_export(&synth, &motion);
    let table = TableBox { height: synth.table_height, ..TABLE };
    let options = PreviewOptions { table: Some(table), ..PreviewOptions::default() };
    let preview = render_preview(&export, &options).expect("rendered");
    assert_eq!(preview.frames.len(), synth.sequence.frames());
    for t in 0..preview.frames.len() {
        for view in &preview.views {
            let pelvis = view.project(motion.joints.position(t, 0)).expect("in front");
            let at = preview.surface_at(t, pelvis.x as u32, pelvis.y as u32);
            assert_eq!(at, Some(Surface::Body), "frame {t}");
        }
    }
    let (width, height) = (preview.width, preview.height);
    let kinds: std::collections::HashSet<Surface> = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .filter_map(|(x, y)| preview.surface_at(0, x, y))
        .collect();
    for kind in [
        Surface::Background,
        Surface::Floor,
        Surface::Table,
        Surface::Body,
        Surface::Object(0),
        Surface::Caption,
    ] {
        assert!(kinds.contains(&kind), "{kind:?} missing from {kinds:?}");
    }
    if let Some(dir) = std::env::var_os("DEX2HOI_PREVIEW_DIR") {
        write_preview_gif(&std::path::Path::new(&dir).join("preview.gif"), &export, &options)
            .expect("written");
    }
}

#[test]
fn bad_options_and_bad_motions_are_clear_errors_and_write_nothing() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 2, 0);
    let dir = common::scratch_dir("preview-errors");
    let path = dir.join("preview.gif");
    let export = common::export(&skeleton, &motion, &[], "");
    let tiny = PreviewOptions { width: 4, ..PreviewOptions::default() };
    let error = write_preview_gif(&path, &export, &tiny).expect_err("too small").to_string();
    assert!(error.contains("preview width") && error.contains('4'), "{error}");
    let bad_fps = ExportMotion { fps: 0.0, ..export.clone() };
    let error = write_preview_gif(&path, &bad_fps, &PreviewOptions::default()).expect_err("fps");
    assert!(error.to_string().contains("frame rate"), "{error}");
    assert_eq!(std::fs::read_dir(&dir).expect("listed").count(), 0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The rest pose with one box placed relative to the right hand: its top `gap` metres below
/// the hand's lowest joint (negative: that far above it, so the fingers sink in).
fn hand_scene(skeleton: &Skeleton, gap: f32) -> (DecodedMotion, Vec3) {
    let mut motion = still_scene(skeleton, 2);
    let hand = &skeleton.groups().right_hand;
    let positions: Vec<Vec3> = hand.iter().map(|&j| motion.joints.position(0, j)).collect();
    let centre = positions.iter().copied().sum::<Vec3>() / positions.len() as f32;
    let lowest = positions.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
    let half = 0.06;
    let place = Vec3::new(centre.x, lowest - gap - half, centre.z);
    motion.objects[0] = Some((vec![Mat3::IDENTITY; 2], vec![place; 2]));
    (motion, centre)
}

fn count(preview: &dex2hoi_export::Preview, kind: Surface) -> usize {
    (0..preview.height)
        .flat_map(|y| (0..preview.width).map(move |x| (x, y)))
        .filter(|&(x, y)| preview.surface_at(0, x, y) == Some(kind))
        .count()
}

#[test]
fn hands_are_coloured_by_contact_and_penetration() {
    let skeleton = Skeleton::smplx();
    let mesh = box_mesh(Vec3::splat(0.06));
    let options = PreviewOptions::default();
    let render = |motion: &DecodedMotion| {
        let export = ExportMotion {
            skeleton: &skeleton,
            fps: 20.0,
            prompts: vec![(0, "touching".into())],
            motion,
            objects: vec![ExportObject { name: "box".into(), mesh: &mesh, slot: 0 }],
            body: None,
        };
        render_preview(&export, &options).expect("rendered")
    };
    // Far away: no colour. 2 cm below the hand (within the 5 cm contact radius): the hand's
    // bones take the contact colour where the hand projects, and nothing is red.
    let (far, _) = hand_scene(&skeleton, 0.5);
    let far = render(&far);
    assert_eq!((count(&far, Surface::Contact), count(&far, Surface::Penetration)), (0, 0));
    let (near, hand) = hand_scene(&skeleton, 0.02);
    let near = render(&near);
    assert!(count(&near, Surface::Contact) > 20, "{}", count(&near, Surface::Contact));
    assert_eq!(count(&near, Surface::Penetration), 0);
    for view in &near.views {
        let pixel = view.project(hand).expect("in front");
        let around = (-4i32..=4)
            .flat_map(|dy| (-4i32..=4).map(move |dx| (dx, dy)))
            .filter_map(|(dx, dy)| {
                near.surface_at(0, (pixel.x as i32 + dx) as u32, (pixel.y as i32 + dy) as u32)
            })
            .filter(|s| *s == Surface::Contact)
            .count();
        assert!(around > 0, "no contact colour around the hand at {pixel}");
    }
    // The box's top 3 cm above the lowest finger joint: the sunken bones that show are red.
    let (inside, _) = hand_scene(&skeleton, -0.03);
    let inside = render(&inside);
    assert!(count(&inside, Surface::Penetration) > 5, "{}", count(&inside, Surface::Penetration));
}

#[test]
fn the_sheet_has_five_panels_of_the_first_view() {
    let (synth, motion) = common::synth_motion(3);
    let export = common::synth_export(&synth, &motion);
    let preview = render_preview(&export, &PreviewOptions::default()).expect("rendered");
    let (width, height, pixels) = preview.sheet(&export.text(), export.fps);
    assert_eq!((width, height), (5 * 320, preview.height));
    let last = preview.frames.len() - 1;
    // Frames at 0, 25, 50, 75 and 100% of the clip, rounded to the nearest.
    let at = |k: usize| (k * last + 2) / 4;
    for (panel, frame) in [0, at(1), at(2), at(3), last].into_iter().enumerate() {
        // The panel's middle row is the first view's middle row of its frame.
        let y = (preview.caption_height + 160) as usize;
        let sheet_row = &pixels[y * width as usize + panel * 320..][..320];
        let frame_row = &preview.frames[frame][y * preview.width as usize..][..320];
        assert_eq!(sheet_row, frame_row, "panel {panel} is frame {frame}");
    }
    let png = preview.encode_sheet_png(&export.text(), export.fps).expect("encoded");
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let reader = decoder.read_info().expect("a PNG");
    assert_eq!((reader.info().width, reader.info().height), (width, height));
    if let Some(dir) = std::env::var_os("DEX2HOI_PREVIEW_DIR") {
        std::fs::write(
            std::path::Path::new(&dir).join("preview.png"),
            preview.encode_sheet_png(&export.text(), export.fps).unwrap(),
        )
        .unwrap();
    }
}

#[test]
fn the_views_follow_a_person_who_walks_far_and_stay_put_otherwise() {
    let skeleton = Skeleton::mixamo();
    let joints = skeleton.joint_count();
    // Walking 6 m ahead (5 cm a frame) without an object.
    let frames = 120;
    let local_rotations = vec![Mat3::IDENTITY; frames * joints];
    let root_positions: Vec<Vec3> = (0..frames)
        .map(|t| skeleton.rest_offsets()[0] + Vec3::new(0.0, 0.0, 0.05 * t as f32))
        .collect();
    let fk = forward_kinematics(&skeleton, &local_rotations, &root_positions).expect("FK");
    let walk = DecodedMotion { local_rotations, root_positions, joints: fk, objects: [None, None] };
    let export = ExportMotion {
        skeleton: &skeleton,
        fps: 20.0,
        prompts: vec![(0, "walking".into())],
        motion: &walk,
        objects: Vec::new(),
        body: None,
    };
    let preview = render_preview(&export, &PreviewOptions::default()).expect("rendered");
    assert_eq!(preview.frame_views.len(), frames);
    assert_eq!(preview.views, preview.frame_views[0]);
    assert_ne!(preview.frame_views[0], preview.frame_views[frames - 1], "the views move along");
    for t in [0, frames / 2, frames - 1] {
        for (k, view) in preview.frame_views[t].iter().enumerate() {
            let pelvis = view.project(walk.root_positions[t]).expect("in front");
            let from_centre = pelvis - view.origin - Vec2::new(160.0, 160.0);
            // Near the middle of the view (which frames about two metres), drawn large.
            assert!(from_centre.length() < 80.0, "frame {t}, view {k}: pelvis at {pelvis}");
            let surface = preview.surface_at(t, pelvis.x as u32, pelvis.y as u32);
            assert_eq!(surface, Some(Surface::Body), "frame {t}, view {k}");
            let head = view.project(walk.joints.position(t, 5)).unwrap();
            assert!((head - pelvis).length() > 40.0, "frame {t}, view {k}: the body is small");
        }
    }
    // Standing still, every frame has the same views.
    let still = still_scene(&skeleton, 3);
    let export = ExportMotion { motion: &still, ..export };
    let preview = render_preview(&export, &PreviewOptions::default()).expect("rendered");
    assert!(preview.frame_views.iter().all(|v| *v == preview.views));
}
