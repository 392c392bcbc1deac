//! The web API on the shipped model, natively: it generates what `dex2hoi_sample::sample`
//! generates with `dex2hoi sample`'s defaults (the browser test compares the page itself with
//! the binary), reads meshes from bytes, and refuses bad requests with a message that names
//! the problem.

use std::num::NonZeroUsize;
use std::sync::OnceLock;

use dex2hoi_data::MAX_OBJECTS;
use dex2hoi_diffusion::SamplerConfig;
use dex2hoi_sample::{
    DEFAULT_TABLE_HEIGHT, Prompt, SampleRequest, SceneObject, TrainedRun, Weights, sample,
};
use dex2hoi_web::{MAX_SECONDS, WebGenerator, WebObject, WebRequest, catalogue_names};

const MODEL: &str =
    concat!(env!("CARGO_MANIFEST_DIR"), "/../dex2hoi-cli/model/dex2hoi-demo.safetensors");
const PROMPT: &str =
    "The person picks up the mug with the right hand and puts it down to the left.";

fn model_bytes() -> &'static [u8] {
    static BYTES: OnceLock<Vec<u8>> = OnceLock::new();
    BYTES.get_or_init(|| std::fs::read(MODEL).expect("the shipped model"))
}

fn generator() -> WebGenerator {
    WebGenerator::from_model_bytes(model_bytes()).expect("the shipped model loads")
}

fn request<'a>(prompt: &'a str, objects: Vec<WebObject<'a>>, frames: usize) -> WebRequest<'a> {
    WebRequest { prompt, objects, seed: 5, frames }
}

/// A closed box of `size` metres (an OBJ file's text).
fn box_obj(size: f32) -> String {
    let mut text = String::new();
    for i in 0..8 {
        let corner = |bit: usize| if i >> bit & 1 == 1 { size } else { 0.0 };
        text.push_str(&format!("v {} {} {}\n", corner(0), corner(1), corner(2)));
    }
    for face in ["1 3 4 2", "5 6 8 7", "1 2 6 5", "3 7 8 4", "1 5 7 3", "2 4 8 6"] {
        text.push_str(&format!("f {face}\n"));
    }
    text
}

#[test]
fn a_generation_is_the_sample_commands_with_its_exports_and_contacts() {
    let generator = &generator();
    let frames = 60;
    let motion =
        generator.generate(&request(PROMPT, vec![WebObject::Named("mug")], frames), None).unwrap();
    let run = TrainedRun::from_model_bytes(
        model_bytes(),
        std::path::Path::new("shipped"),
        Weights::Ema,
        &candle_core::Device::Cpu,
    )
    .unwrap();
    let expected = sample(
        &run,
        &SampleRequest {
            prompts: vec![Prompt { start_frame: 0, text: PROMPT.into() }],
            objects: vec![SceneObject::parse("mug", None).unwrap()],
            frames: NonZeroUsize::new(frames).unwrap(),
            seed: 5,
            sampler: SamplerConfig::default(),
            table_height: DEFAULT_TABLE_HEIGHT,
            free_objects: dex2hoi_sample::rest::FreeObjects::AtRest,
            seams: dex2hoi_sample::seams::Seams::sample_default(),
            progress: None,
        },
    )
    .unwrap();
    let fk = dex2hoi_repr::forward_kinematics(
        &run.skeleton,
        &expected.motion.local_rotations,
        &expected.motion.root_positions,
    );
    let joints: Vec<f32> = fk.unwrap().positions.iter().flat_map(|p| p.to_array()).collect();
    assert_eq!(motion.joints, joints);
    assert_eq!((motion.frames, motion.joint_count, motion.fps), (frames, 52, 20.0));
    // The exports are whole files.
    assert_eq!(&motion.glb[..4], b"glTF");
    assert_eq!(&motion.npz[..2], b"PK");
    assert!(motion.bvh.starts_with("HIERARCHY"));
    // Contacts: a state per frame and joint, only ever on the hands.
    assert_eq!(motion.hand_contacts.len(), frames * 52);
    let groups = run.skeleton.groups();
    for (i, &state) in motion.hand_contacts.iter().enumerate() {
        let joint = i % 52;
        assert!(state <= 2);
        if !groups.left_hand.contains(&joint) && !groups.right_hand.contains(&joint) {
            assert_eq!(state, 0, "joint {joint}");
        }
    }
    // The mug stands on the default table.
    let table = motion.table.expect("a table under the mug");
    assert_eq!(table.height, DEFAULT_TABLE_HEIGHT);
}

#[test]
fn a_mesh_from_the_visitors_disk_is_an_object() {
    let obj = box_obj(0.08);
    let objects = vec![WebObject::File { file_name: "Crate.obj", bytes: obj.as_bytes() }];
    let motion =
        generator().generate(&request("The person picks up the box.", objects, 20), None).unwrap();
    assert_eq!(motion.frames, 20);
    // The GLB names the object by the file's stem.
    let length = u32::from_le_bytes(motion.glb[12..16].try_into().unwrap()) as usize;
    let json = std::str::from_utf8(&motion.glb[20..20 + length]).unwrap();
    assert!(json.contains("\"Crate\""), "{json}");
}

#[test]
fn bad_requests_are_refused_with_what_is_wrong() {
    let generator = &generator();
    let mug = || vec![WebObject::Named("mug")];
    let error =
        |request: WebRequest<'_>| generator.generate(&request, None).unwrap_err().to_string();
    assert!(error(request("  ", mug(), 20)).contains("empty prompt"));
    let most = generator.max_frames();
    assert_eq!(most, (MAX_SECONDS * 20.0) as usize);
    for frames in [0, most + 1] {
        let message = error(request(PROMPT, mug(), frames));
        assert!(message.contains(&format!("1 to {most} frames")), "{message}");
    }
    let three = vec![WebObject::Named("mug"); MAX_OBJECTS + 1];
    assert!(error(request(PROMPT, three, 20)).contains("one or two objects"));
    assert!(error(request(PROMPT, vec![], 20)).contains("one or two objects"));
    let unknown = error(request(PROMPT, vec![WebObject::Named("teapot")], 20));
    assert!(unknown.contains("teapot") && unknown.contains("mug, bottle"), "{unknown}");
    let broken = vec![WebObject::File { file_name: "broken.obj", bytes: b"v 0 0 0\nf 1 2 3\n" }];
    let message = error(request(PROMPT, broken, 20));
    assert!(message.contains("broken.obj"), "{message}");
    let not_a_mesh = vec![WebObject::File { file_name: "photo.jpg", bytes: b"\xff\xd8" }];
    assert!(error(request(PROMPT, not_a_mesh, 20)).contains("photo.jpg"));
    let model = WebGenerator::from_model_bytes(b"not a model").unwrap_err().to_string();
    assert!(model.contains("<the page's model>"), "{model}");
}

#[test]
fn the_page_knows_the_catalogue_and_warns_of_unknown_words() {
    let names = catalogue_names();
    assert!(names.iter().any(|n| n == "mug") && names.iter().any(|n| n == "box"), "{names:?}");
    let generator = &generator();
    assert!(generator.words().iter().any(|w| w == "mug"));
    assert_eq!(generator.unknown_words_warning(PROMPT), None);
    let warning = generator.unknown_words_warning("Juggle the teacup.").unwrap();
    assert!(warning.contains("`juggle`") && warning.contains("`teacup`"), "{warning}");
}
