//! GRAB (docs/CONVENTIONS.md, "GRAB"): `grab/s{1..10}/{object}_{intent}[_{n}][_Retake].npz`, every
//! top-level entry a 0-d object array (pickled dicts of ndarrays); SMPL-X bodies with the
//! subject's betas from `tools/subject_meshes/{gender}/s{n}_betas.npy`; one object whose mesh
//! is a PLY under the GRAB root, posed in GRAB's transposed convention
//! (`verts = v @ R + t`, so the column-vector rotation is `R^T`); Z up; 120 fps. The split is
//! the one of HOIDiNi and the paper: subjects s1-s9 train, s10 test. Texts are templated from
//! the intent and the object ("The person is passing the mug.").

use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};

use dex2hoi_data::Sequence;
use dex2hoi_data::dataset::Split;
use dex2hoi_repr::rotation::axis_angle_to_matrix;

use crate::error::{ImportError, Result};
use crate::npy::{Npz, read_npy};
use crate::smplx::{HAND_JOINTS, SmplxParams};
use crate::source::{Context, HandPoseSource, Item, Outcome, PrepareOptions, Skipped, SplitRule};
use crate::value::{Field, Value};

pub use crate::source::DEFAULT_TEMPLATE;

/// The subject of the test split.
pub const TEST_SUBJECT: u32 = 10;

/// The 29 GRAB intents as verb phrases for the templates.
const INTENT_VERBS: [(&str, &str); 29] = [
    ("pass", "passing"),
    ("lift", "lifting"),
    ("inspect", "inspecting"),
    ("drink", "drinking from"),
    ("use", "using"),
    ("offhand", "handing over"),
    ("browse", "browsing"),
    ("brush", "brushing with"),
    ("call", "making a call with"),
    ("chop", "chopping with"),
    ("clean", "cleaning with"),
    ("cook", "cooking with"),
    ("eat", "eating"),
    ("fly", "flying"),
    ("open", "opening"),
    ("peel", "peeling"),
    ("play", "playing"),
    ("pour", "pouring from"),
    ("screw", "screwing"),
    ("see", "looking through"),
    ("set", "setting"),
    ("shake", "shaking"),
    ("squeeze", "squeezing"),
    ("stamp", "stamping with"),
    ("staple", "stapling with"),
    ("switchON", "switching on"),
    ("takepicture", "taking a picture with"),
    ("toast", "toasting with"),
    ("wear", "wearing"),
];

/// GRAB object names written as words.
const OBJECT_WORDS: [(&str, &str); 14] = [
    ("alarmclock", "alarm clock"),
    ("coffeemug", "coffee mug"),
    ("doorknob", "door knob"),
    ("eyeglasses", "eyeglasses"),
    ("gamecontroller", "game controller"),
    ("hammer", "hammer"),
    ("headphones", "headphones"),
    ("knife", "knife"),
    ("lightbulb", "light bulb"),
    ("stanfordbunny", "Stanford bunny"),
    ("teapot", "teapot"),
    ("toothbrush", "toothbrush"),
    ("waterbottle", "water bottle"),
    ("wineglass", "wine glass"),
];

/// The verb phrase of an intent (`passing`), the intent itself with `-ing` for unknown ones.
pub fn intent_verb(intent: &str) -> String {
    INTENT_VERBS
        .iter()
        .find(|(i, _)| i.eq_ignore_ascii_case(intent))
        .map_or_else(|| format!("{intent}ing"), |(_, v)| (*v).to_string())
}

/// An object name as words: `wineglass` -> `wine glass`, `cylindersmall` -> `small cylinder`.
pub fn object_words(name: &str) -> String {
    if let Some((_, words)) = OBJECT_WORDS.iter().find(|(n, _)| *n == name) {
        return (*words).to_string();
    }
    for size in ["small", "medium", "middle", "large"] {
        if let Some(shape) = name.strip_suffix(size).filter(|s| !s.is_empty()) {
            return format!("{size} {shape}");
        }
    }
    name.replace('_', " ")
}

/// Fills a template: `{verb}`, `{object}`, `{intent}`.
pub fn fill_template(template: &str, intent: &str, object: &str) -> String {
    template
        .replace("{verb}", &intent_verb(intent))
        .replace("{object}", &object_words(object))
        .replace("{intent}", intent)
}

/// The folder holding `s1`..`s10` and the GRAB root that relative paths resolve against:
/// `root/grab` and `root`, or `root` and its parent when given the `grab` folder itself.
pub fn layout(root: &Path) -> (PathBuf, PathBuf) {
    if root.join("grab").is_dir() {
        (root.join("grab"), root.to_path_buf())
    } else {
        (root.to_path_buf(), root.parent().map_or_else(|| root.to_path_buf(), Path::to_path_buf))
    }
}

/// The subject number of a folder name `s{n}`.
fn subject_number(name: &str) -> Option<u32> {
    name.strip_prefix('s')?.parse().ok()
}

/// Every sequence file, subjects in numeric order, files in name order, with the sequences that
/// the split files do not list or whose intent is excluded.
pub fn discover(options: &PrepareOptions) -> Result<(Vec<Item>, Vec<Skipped>)> {
    let rule = SplitRule::new(options)?;
    let mut items = Vec::new();
    let mut skipped = Vec::new();
    for item in sequence_files(&options.root)? {
        let stem = item.path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
        let intent = intent_from_file_name(&stem).unwrap_or_default();
        if options.exclude_intents.iter().any(|i| i.eq_ignore_ascii_case(intent)) {
            let reason = format!("intent `{intent}` left out (--exclude-intent)");
            skipped.push(Skipped { id: item.id, reason });
            continue;
        }
        if !rule.has_files() {
            items.push(item);
            continue;
        }
        match rule.split(&item.id) {
            Some(split) => items.push(Item { split, ..item }),
            None => skipped
                .push(Skipped { id: item.id, reason: "not listed in the split files".into() }),
        }
    }
    Ok((items, skipped))
}

/// Every sequence file with the subject split (s10 is the test subject).
fn sequence_files(root: &Path) -> Result<Vec<Item>> {
    let (sequences, _) = layout(root);
    let read_dir = |dir: &Path| -> Result<Vec<PathBuf>> {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(ImportError::io(dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        entries.sort();
        Ok(entries)
    };
    let mut subjects: Vec<(u32, PathBuf)> = read_dir(&sequences)?
        .into_iter()
        .filter(|p| p.is_dir())
        .filter_map(|p| {
            let n = subject_number(p.file_name()?.to_str()?)?;
            Some((n, p))
        })
        .collect();
    subjects.sort();
    if subjects.is_empty() {
        return Err(ImportError::missing(
            sequences.display(),
            "s1 .. s10",
            "GRAB's subject folders (give the GRAB root, which holds grab/ and tools/)",
        ));
    }
    let mut items = Vec::new();
    for (subject, dir) in subjects {
        for path in read_dir(&dir)? {
            if path.extension().is_some_and(|e| e == "npz") {
                let stem = path.file_stem().unwrap_or_default().to_string_lossy();
                items.push(Item {
                    id: format!("s{subject}/{stem}"),
                    split: if subject == TEST_SUBJECT { Split::Test } else { Split::Train },
                    path,
                });
            }
        }
    }
    Ok(items)
}

/// `body.vtemp`, the subject's template mesh relative to the GRAB root, when the body has one.
fn body_value_vtemp(body: &Value, body_name: &str) -> Result<Option<String>> {
    let body = Field::root(body_name, "body", body);
    if !body.has("vtemp") {
        return Ok(None);
    }
    Ok(Some(body.get("vtemp", "the template mesh's path")?.text()?))
}

/// Numbers of one archive entry (a dict of parameters) at a key path, `(T, width)`.
fn params(
    field: &Field<'_>,
    key: &str,
    width: Option<usize>,
    frames: Option<usize>,
) -> Result<(Vec<f64>, usize)> {
    let (values, shape) = field.get(key, "per-frame parameters")?.numbers(&[frames, width])?;
    Ok((values, shape[0]))
}

/// The intent of a file name: the second underscore token (`mug_pass_1` -> `pass`).
pub fn intent_from_file_name(stem: &str) -> Option<&str> {
    stem.split('_').nth(1)
}

/// One entry of an archive with its name for messages (`file.npz[key]`).
fn read_entry(archive: &mut Npz, key: &str, expected: &str) -> Result<(String, Value)> {
    let value = archive.read(key, expected)?;
    Ok((format!("{}[{key}]", archive.path().display()), value))
}

/// Reads one GRAB sequence (at 120 fps, in the project's axes).
pub fn load(item: &Item, context: &Context) -> Result<Outcome> {
    let options = &context.options;
    let (_, grab_root) = layout(&options.root);
    let path = &item.path;
    let mut archive = Npz::open(path)?;
    let (gender_name, gender_value) = read_entry(&mut archive, "gender", "the subject's gender")?;
    let gender = Field::root(&gender_name, "gender", &gender_value).text()?;
    let (sbj_name, sbj_value) = read_entry(&mut archive, "sbj_id", "the subject id (s1 .. s10)")?;
    let subject = Field::root(&sbj_name, "sbj_id", &sbj_value).text()?;
    let (obj_name_name, obj_name_value) =
        read_entry(&mut archive, "obj_name", "the object's name")?;
    let object_name = Field::root(&obj_name_name, "obj_name", &obj_name_value).text()?;
    let stem = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
    let intent = if archive.contains("motion_intent") {
        let (n, v) = read_entry(&mut archive, "motion_intent", "the intent")?;
        Field::root(&n, "motion_intent", &v).text()?
    } else {
        intent_from_file_name(&stem)
            .ok_or_else(|| ImportError::missing(path.display(), "motion_intent", "the intent"))?
            .to_string()
    };
    let fps = if archive.contains("framerate") {
        let (n, v) = read_entry(&mut archive, "framerate", "frames per second")?;
        Field::root(&n, "framerate", &v).number()? as f32
    } else {
        120.0
    };
    if fps.is_nan() || fps <= 0.0 {
        return Err(ImportError::format(path.display(), "framerate", "a positive number", fps));
    }

    let (body_name, body_value) =
        read_entry(&mut archive, "body", "the SMPL-X body (a dict with params)")?;
    let body =
        Field::root(&body_name, "body", &body_value).get("params", "the SMPL-X parameters")?;
    let (transl, frames) = params(&body, "transl", Some(3), None)?;
    let frames_opt = Some(frames);
    let (global_orient, _) = params(&body, "global_orient", Some(3), frames_opt)?;
    let (body_pose, _) = params(&body, "body_pose", Some(63), frames_opt)?;

    let smplx = context.smplx()?.body(&gender)?;
    let (left_hand, right_hand) = match options.hand_pose {
        HandPoseSource::Full => {
            let mut hand = |key: &str| -> Result<Vec<f64>> {
                let (n, v) = read_entry(&mut archive, key, "the MANO hand (a dict with params)")?;
                let field = Field::root(&n, key, &v).get("params", "the MANO parameters")?;
                Ok(params(&field, "fullpose", Some(3 * HAND_JOINTS), frames_opt)?.0)
            };
            (hand("lhand")?, hand("rhand")?)
        }
        HandPoseSource::Pca => {
            let components = smplx.hand_components()?;
            let decode = |key: &str, side: usize| -> Result<Vec<f64>> {
                let coefficients = body.get(key, "PCA hand coefficients (T, n)")?;
                let (values, shape) = coefficients.numbers(&[frames_opt, None])?;
                let count = shape[1];
                if count == 0 || count > 3 * HAND_JOINTS {
                    return Err(ImportError::Shape {
                        source_name: body_name.clone(),
                        key: coefficients.path().to_string(),
                        expected: "(T, n) with 1 <= n <= 45".into(),
                        got: shape,
                    });
                }
                Ok(values
                    .chunks_exact(count)
                    .flat_map(|c| components[side].decode(c, true))
                    .collect())
            };
            (decode("left_hand_pose", 0)?, decode("right_hand_pose", 1)?)
        }
    };

    let (object_entry, object_value) =
        read_entry(&mut archive, "object", "the object (a dict with params)")?;
    let object = Field::root(&object_entry, "object", &object_value);
    let object_params = object.get("params", "the object's pose")?;
    let (object_transl, _) = params(&object_params, "transl", Some(3), frames_opt)?;
    let (object_orient, _) = params(&object_params, "global_orient", Some(3), frames_opt)?;
    let mesh_path = if object.has("object_mesh") {
        grab_root.join(object.get("object_mesh", "the mesh path")?.text()?)
    } else {
        grab_root.join(format!("tools/object_meshes/contact_meshes/{object_name}.ply"))
    };

    // The subject's body: its personalised template mesh (`body.vtemp`) when it is there, as
    // GRAB's own code builds it; else the subject's betas.
    let template = match body_value_vtemp(&body_value, &body_name)? {
        Some(relative) => grab_root.join(relative),
        None => grab_root.join(format!("tools/subject_meshes/{gender}/{subject}.ply")),
    };
    let skeleton = if template.is_file() {
        smplx.skeleton_of_template(&template)?
    } else {
        let betas_path =
            grab_root.join(format!("tools/subject_meshes/{gender}/{subject}_betas.npy"));
        let betas_value = read_npy(&betas_path)?;
        let betas_name = betas_path.display().to_string();
        let (betas, _) = Field::root(&betas_name, "", &betas_value).numbers_any_shape()?;
        let betas: Vec<f32> = betas.into_iter().map(|b| b as f32).collect();
        smplx.skeleton(&betas)?
    };

    let smplx_params = SmplxParams { global_orient, body_pose, left_hand, right_hand, transl };
    let (mut local_rotations, mut root_positions) = smplx_params.to_motion(&skeleton);
    let to_y_up = options.up_axis().to_y_up();
    for t in 0..frames {
        local_rotations[t * 52] = to_y_up * local_rotations[t * 52];
        root_positions[t] = to_y_up * root_positions[t];
    }
    // GRAB's transposed convention: verts = v @ R + t, so v_world = R^T v + t.
    let rotations: Vec<Mat3> = object_orient
        .chunks_exact(3)
        .map(|r| axis_angle_to_matrix(Vec3::new(r[0] as f32, r[1] as f32, r[2] as f32)).transpose())
        .collect();
    let translations: Vec<Vec3> = object_transl
        .chunks_exact(3)
        .map(|t| Vec3::new(t[0] as f32, t[1] as f32, t[2] as f32))
        .collect();
    let mesh = context.mesh(&mesh_path)?;
    let object = mesh.object(&object_name, &rotations, &translations, to_y_up);
    let mut warnings = Vec::new();
    let texts = match context.prompts.as_ref().map(|p| p.get(&item.id)) {
        Some(Some(prompt)) => vec![prompt.clone()],
        listed => {
            if listed.is_some() {
                warnings
                    .push("no prompt in the prompt table: the text templates give its text".into());
            }
            options.text_templates.iter().map(|t| fill_template(t, &intent, &object_name)).collect()
        }
    };
    Ok(Outcome::Sequence {
        sequence: Box::new(Sequence {
            skeleton,
            fps,
            local_rotations,
            root_positions,
            objects: vec![object],
            texts,
            action: Some(intent),
            source_id: format!("grab/{}", item.id),
        }),
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texts_from_templates() {
        assert_eq!(
            fill_template(DEFAULT_TEMPLATE, "pass", "mug"),
            "The person is passing the mug."
        );
        assert_eq!(
            fill_template("{intent}: someone is {verb} a {object}", "drink", "wineglass"),
            "drink: someone is drinking from a wine glass"
        );
        assert_eq!(object_words("cylindersmall"), "small cylinder");
        assert_eq!(intent_verb("switchON"), "switching on");
        assert_eq!(intent_from_file_name("mug_pass_1_Retake"), Some("pass"));
        assert_eq!(INTENT_VERBS.len(), 29);
    }
}
