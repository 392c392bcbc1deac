//! `--smplx-model` and `--betas`, or `--character`, shared by `sample` and `data show`: the
//! body mesh to skin in `motion.glb`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use dex2hoi_export::{Body, CharacterMesh, RigBone, SmplxMesh};
use dex2hoi_import::character::Character;
use dex2hoi_repr::Skeleton;

/// The body of the exported motion.
#[derive(Debug, Args)]
pub struct BodyArgs {
    /// Your SMPL-X model (`SMPLX_NEUTRAL.npz`, or a directory holding it or `smplx/` with it):
    /// motion.glb then carries the skinned SMPL-X mesh, and every file uses the model's skeleton.
    #[arg(long, value_name = "FILE|DIR", conflicts_with = "character")]
    smplx_model: Option<PathBuf>,
    /// Body-shape coefficients of the SMPL-X model, comma-separated (zeros by default).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, requires = "smplx_model")]
    betas: Vec<f32>,
    /// A Mixamo-rigged character (`.glb`, in Mixamo's T-pose at rest; bones named as Mixamo
    /// names them, with or without `mixamorig:`) for a Mixamo-65 motion: motion.glb then
    /// carries its skinned mesh and its bones in their own frames, and every file uses its
    /// skeleton.
    #[arg(long, value_name = "FILE.glb")]
    character: Option<PathBuf>,
}

/// A body loaded for the export.
#[derive(Debug)]
pub enum LoadedBody {
    /// An SMPL-X model shaped by betas.
    Smplx(SmplxMesh),
    /// A Mixamo character.
    Character(CharacterMesh),
}

impl LoadedBody {
    /// The body as the exporter takes it.
    pub fn as_body(&self) -> Body<'_> {
        match self {
            Self::Smplx(mesh) => Body::Smplx(mesh),
            Self::Character(character) => Body::Character(character),
        }
    }

    /// The skeleton the motion is exported on.
    pub fn skeleton(&self) -> &Skeleton {
        match self {
            Self::Smplx(mesh) => &mesh.skeleton,
            Self::Character(character) => &character.skeleton,
        }
    }

    /// Checks that a motion on `skeleton` can be shown with this body.
    pub fn fits(&self, skeleton: &Skeleton) -> Result<()> {
        match self {
            Self::Smplx(mesh) => mesh.fits(skeleton)?,
            Self::Character(character) => character.fits(skeleton)?,
        }
        Ok(())
    }

    /// Root positions of a motion made on `from` for this body: a character's are scaled to
    /// its height ([`CharacterMesh::retarget_root`]); an SMPL-X model keeps the pelvis path.
    pub fn root_positions(&self, from: &Skeleton, positions: &[glam::Vec3]) -> Vec<glam::Vec3> {
        match self {
            Self::Smplx(_) => positions.to_vec(),
            Self::Character(character) => character.retarget_root(from, positions),
        }
    }
}

impl BodyArgs {
    /// The body, when one is given, for motions on `motion`'s topology; an error names the
    /// file and what is wrong.
    pub fn load(&self, motion: &Skeleton) -> Result<Option<LoadedBody>> {
        if let Some(path) = &self.smplx_model {
            let mesh = SmplxMesh::load(path, &self.betas)
                .with_context(|| format!("--smplx-model {}", path.display()))?;
            return Ok(Some(LoadedBody::Smplx(mesh)));
        }
        let Some(path) = &self.character else { return Ok(None) };
        let context = || format!("--character {}", path.display());
        let read = Character::read(path).with_context(context)?;
        let bones: Vec<RigBone> = read
            .bones
            .into_iter()
            .map(|b| RigBone { name: b.name, parent: b.parent, rest: b.rest })
            .collect();
        let character = CharacterMesh::new(
            path.clone(),
            motion,
            &bones,
            read.vertices,
            read.faces,
            &read.joints,
            &read.weights,
        )
        .with_context(context)?;
        Ok(Some(LoadedBody::Character(character)))
    }
}
