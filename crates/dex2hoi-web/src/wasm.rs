//! The WebAssembly bindings the page calls (`page/worker.js`): [`Generator`] and [`Motion`]
//! wrap [`WebGenerator`] and [`WebMotion`] one to one; errors become JavaScript errors with the
//! whole chain of causes in their message.

use std::ops::ControlFlow;

use wasm_bindgen::prelude::*;

use dex2hoi_sample::ProgressHook;

use crate::{WebGenerator, WebMotion, WebObject, WebRequest, catalogue_names};

#[wasm_bindgen]
extern "C" {
    /// The page's progress report, a global function of the worker that runs the model: frames
    /// generated so far, and in all.
    #[wasm_bindgen(js_name = dex2hoiProgress)]
    fn report_progress(frames_done: u32, frames: u32);
}

/// An error as JavaScript shows it: the message and its causes, joined by `: `.
fn js_error(error: &dyn std::error::Error) -> JsError {
    let mut message = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let text = cause.to_string();
        if !message.contains(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
        source = cause.source();
    }
    JsError::new(&message)
}

/// The names of the built-in object catalogue.
#[wasm_bindgen]
pub fn catalogue() -> Vec<String> {
    catalogue_names()
}

/// A loaded model ([`WebGenerator`]).
#[wasm_bindgen]
pub struct Generator {
    inner: WebGenerator,
}

#[wasm_bindgen]
impl Generator {
    /// Loads a packed model file's bytes.
    #[wasm_bindgen(constructor)]
    pub fn new(model: &[u8]) -> Result<Generator, JsError> {
        let inner = WebGenerator::from_model_bytes(model).map_err(|e| js_error(&e))?;
        Ok(Self { inner })
    }

    /// The model's frame rate.
    pub fn fps(&self) -> f32 {
        self.inner.fps()
    }

    /// The most frames a request may ask for.
    #[wasm_bindgen(js_name = maxFrames)]
    pub fn max_frames(&self) -> usize {
        self.inner.max_frames()
    }

    /// The words the model knows.
    pub fn words(&self) -> Vec<String> {
        self.inner.words()
    }

    /// The warning for the prompt's words the model never saw, if any.
    pub fn warning(&self, prompt: &str) -> Option<String> {
        self.inner.unknown_words_warning(prompt)
    }

    /// Generates a motion: the prompt, a mesh file from the visitor's disk (its name and
    /// bytes; the first object when given), the catalogue objects (`mug`, or `mug@x,y,z`), the
    /// seed and the number of frames. With `report`, calls the worker's global
    /// `dex2hoiProgress(framesDone, frames)` after each window.
    pub fn generate(
        &self,
        prompt: &str,
        mesh_name: Option<String>,
        mesh: Option<Vec<u8>>,
        objects: Vec<String>,
        seed: u64,
        frames: usize,
        report: bool,
    ) -> Result<Motion, JsError> {
        let file = match (&mesh_name, &mesh) {
            (Some(file_name), Some(bytes)) => Some(WebObject::File { file_name, bytes }),
            _ => None,
        };
        let request = WebRequest {
            prompt,
            objects: file.into_iter().chain(objects.iter().map(|n| WebObject::Named(n))).collect(),
            seed,
            frames,
        };
        let progress = report.then(|| {
            ProgressHook::new(|p| {
                report_progress(p.frames_done as u32, p.frames as u32);
                ControlFlow::Continue(())
            })
        });
        let inner = self.inner.generate(&request, progress).map_err(|e| js_error(&e))?;
        Ok(Motion { inner })
    }
}

/// A generated motion ([`WebMotion`]).
#[wasm_bindgen]
pub struct Motion {
    inner: WebMotion,
}

#[wasm_bindgen]
impl Motion {
    /// `motion.glb`.
    pub fn glb(&self) -> Vec<u8> {
        self.inner.glb.clone()
    }

    /// `motion.npz`.
    pub fn npz(&self) -> Vec<u8> {
        self.inner.npz.clone()
    }

    /// `motion.bvh`.
    pub fn bvh(&self) -> String {
        self.inner.bvh.clone()
    }

    /// Frames generated.
    pub fn frames(&self) -> usize {
        self.inner.frames
    }

    /// Joints of the skeleton.
    #[wasm_bindgen(js_name = jointCount)]
    pub fn joint_count(&self) -> usize {
        self.inner.joint_count
    }

    /// Frames per second.
    pub fn fps(&self) -> f32 {
        self.inner.fps
    }

    /// Seconds the generation took.
    pub fn seconds(&self) -> f64 {
        self.inner.seconds
    }

    /// World positions of the joints, `[frames * joints * 3]`.
    pub fn joints(&self) -> Vec<f32> {
        self.inner.joints.clone()
    }

    /// Contact states of the joints, `[frames * joints]` (0 free, 1 contact, 2 inside).
    #[wasm_bindgen(js_name = handContacts)]
    pub fn hand_contacts(&self) -> Vec<u8> {
        self.inner.hand_contacts.clone()
    }

    /// The table the objects stand on: `[height, centre x, centre z, half width, half
    /// depth]`, or nothing.
    pub fn table(&self) -> Option<Vec<f32>> {
        self.inner
            .table
            .map(|t| vec![t.height, t.centre.x, t.centre.y, t.half_extents.x, t.half_extents.y])
    }
}
