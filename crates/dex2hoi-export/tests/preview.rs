//! `preview.gif`: a known scene is rendered and its pixels checked (floor, table, body,
//! object, sky where each must be), the GIF decodes to the same frames with the right delays,
//! and rendering is deterministic.

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
        text: "standing".into(),
        motion: &motion,
        objects: vec![ExportObject { name: "box".into(), mesh: &mesh, slot: 0 }],
    };
    let options = PreviewOptions { table: Some(TABLE), ..PreviewOptions::default() };
    let preview = render_preview(&export, &options).expect("rendered");
    if let Some(dir) = std::env::var_os("DEX2HOI_PREVIEW_DIR") {
        let path = std::path::Path::new(&dir).join("known-scene.gif");
        write_preview_gif(&path, &export, &options).expect("written");
    }
    assert_eq!((preview.width, preview.height), (320, 320));
    assert_eq!(preview.frames.len(), 3);
    assert!(preview.frames.iter().all(|f| f.len() == 320 * 320));
    assert_eq!(preview.delays, [5, 5, 5]);

    let surface_at = |world: Vec3| {
        let pixel = preview.camera.project(world).expect("in front of the camera");
        assert!(
            pixel.x >= 0.0 && pixel.y >= 0.0 && pixel.x < 320.0 && pixel.y < 320.0,
            "{world} projects outside the image to {pixel}"
        );
        preview.surface_at(0, pixel.x as u32, pixel.y as u32).expect("a pixel")
    };
    assert_eq!(surface_at(skeleton.rest_offsets()[0]), Surface::Body, "pelvis");
    let chest = skeleton.rest_positions()[9];
    assert_eq!(surface_at(chest), Surface::Body, "chest");
    assert_eq!(surface_at(Vec3::new(0.25, 0.98, 0.5)), Surface::Object(0), "box");
    assert_eq!(surface_at(Vec3::new(-0.35, 0.9, 0.8)), Surface::Table, "table top");
    assert_eq!(surface_at(Vec3::new(0.9, 0.0, 0.6)), Surface::Floor, "floor beside the table");
    assert_eq!(preview.surface_at(0, 0, 0), Some(Surface::Background), "sky in the corner");
    // Every surface kind shows up, and a still scene gives identical frames.
    assert_eq!(preview.frames[0], preview.frames[2]);
}

#[test]
fn the_gif_decodes_to_the_rendered_frames_and_rendering_is_deterministic() {
    let skeleton = Skeleton::smplx();
    let motion = common::wavy_motion(&skeleton, 5, 2);
    let meshes = common::object_meshes();
    let export = common::export(&skeleton, &motion, &meshes, "wave");
    let options = PreviewOptions { width: 96, height: 64, table: None };
    let preview = render_preview(&export, &options).expect("rendered");
    assert_eq!(preview, render_preview(&export, &options).expect("again"));
    // The body moves, so consecutive frames differ.
    assert_ne!(preview.frames[0], preview.frames[1]);

    let bytes = encode_preview_gif(&export, &options).expect("encoded");
    assert_eq!(bytes, preview.encode_gif().expect("encoded"));
    let mut decoder = gif::DecodeOptions::new();
    decoder.set_color_output(gif::ColorOutput::Indexed);
    let mut decoder = decoder.read_info(&bytes[..]).expect("a GIF");
    assert_eq!((decoder.width(), decoder.height()), (96, 64));
    let mut frames = 0;
    while let Some(frame) = decoder.read_next_frame().expect("a frame") {
        assert_eq!((frame.width, frame.height, frame.delay), (96, 64, 5));
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
        let pelvis = preview.camera.project(motion.joints.position(t, 0)).expect("in front");
        assert_eq!(preview.surface_at(t, pelvis.x as u32, pelvis.y as u32), Some(Surface::Body));
    }
    let kinds: std::collections::HashSet<Surface> = (0..320)
        .flat_map(|y| (0..320).map(move |x| (x, y)))
        .filter_map(|(x, y)| preview.surface_at(0, x, y))
        .collect();
    for kind in
        [Surface::Background, Surface::Floor, Surface::Table, Surface::Body, Surface::Object(0)]
    {
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
