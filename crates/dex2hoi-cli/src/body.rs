//! `--smplx-model` and `--betas`, shared by `sample` and `data show`: the SMPL-X body mesh to
//! skin in `motion.glb`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use dex2hoi_export::SmplxMesh;

/// The body of the exported motion.
#[derive(Debug, Args)]
pub struct BodyArgs {
    /// Your SMPL-X model (`SMPLX_NEUTRAL.npz`, or a directory holding it or `smplx/` with it):
    /// motion.glb then carries the skinned SMPL-X mesh, and every file uses the model's skeleton.
    #[arg(long, value_name = "FILE|DIR")]
    smplx_model: Option<PathBuf>,
    /// Body-shape coefficients of the SMPL-X model, comma-separated (zeros by default).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "smplx_model")]
    betas: Vec<f32>,
}

impl BodyArgs {
    /// The shaped model, when one is given; an error names the file and what is wrong.
    pub fn load(&self) -> Result<Option<SmplxMesh>> {
        let Some(path) = &self.smplx_model else { return Ok(None) };
        let mesh = SmplxMesh::load(path, &self.betas)
            .with_context(|| format!("--smplx-model {}", path.display()))?;
        Ok(Some(mesh))
    }
}
