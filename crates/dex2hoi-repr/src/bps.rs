//! Basis Point Set object features (Prokudin et al. 2019, as used by OMOMO and CHOIS; paper
//! Sec. 3.2 conditions each stream on its object's BPS).
//!
//! A fixed basis of points, drawn once from a seed uniformly inside a ball centred on the object
//! frame's origin; the feature of an object is, for each basis point, the 3-D offset to its
//! nearest point on the object's surface, in the object's own frame (`N x 3` numbers).

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;

use crate::error::{ReprError, Result};
use crate::sdf::MeshQuery;

/// The default number of basis points (CHOIS, OMOMO, HIMO).
pub const DEFAULT_BPS_POINTS: usize = 1024;

/// A seeded basis of points uniform in a ball.
#[derive(Debug, Clone, PartialEq)]
pub struct BpsBasis {
    points: Vec<Vec3>,
    radius: f32,
    seed: u64,
}

impl BpsBasis {
    /// Draws `count` points uniformly in the ball of `radius` around the origin: a Gaussian
    /// direction and a radius `r * u^(1/3)`, which is uniform in volume.
    pub fn new(count: usize, radius: f32, seed: u64) -> Result<Self> {
        if count == 0 || !(radius > 0.0 && radius.is_finite()) {
            return Err(ReprError::invalid(
                "BPS basis",
                "at least one point and a positive, finite radius",
                format!("{count} points, radius {radius}"),
            ));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut points = Vec::with_capacity(count);
        while points.len() < count {
            let direction = Vec3::new(
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
            );
            let length = direction.length();
            if length < 1e-6 {
                continue;
            }
            let u: f32 = rng.random();
            points.push(direction / length * (radius * u.cbrt()));
        }
        Ok(Self { points, radius, seed })
    }

    /// The basis points.
    pub fn points(&self) -> &[Vec3] {
        &self.points
    }

    /// The ball's radius.
    pub fn radius(&self) -> f32 {
        self.radius
    }

    /// The seed the basis was drawn with.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The BPS feature of an object: for each basis point, `nearest_surface_point - basis_point`
    /// in the object frame, in parallel.
    ///
    /// # Shapes
    /// - returns `[points]` offsets (flatten to `points * 3` numbers)
    pub fn encode(&self, object: &MeshQuery) -> Vec<Vec3> {
        self.points.par_iter().map(|b| object.closest(*b).point - *b).collect()
    }

    /// [`Self::encode`] flattened to `points * 3` numbers, point-major.
    pub fn encode_flat(&self, object: &MeshQuery) -> Vec<f32> {
        self.encode(object).into_iter().flat_map(|v| v.to_array()).collect()
    }
}
