//! The nearest surface sample of each query point, for the objective's signed distances
//! (`loss.rs`: `d = n_k . (x - s_k)` for the nearest sample `s_k`).
//!
//! Two searches give the same choice: [`nearest_on_host`] reads the points back and searches on
//! the CPU's threads, [`DeviceClouds::nearest`] searches with tensor operations where the
//! points are. On the CPU the host search is the faster (no `[Q, K]` matrix of distances); on a
//! GPU the tensor search keeps the step free of a read-back, so that the host never waits for
//! the device in the middle of a step. Both are brute force over the object's surface samples
//! (512 per object, `dex2hoi_data::SURFACE_SAMPLES`), and the choice is not differentiated.
//!
//! Architecture Invariant: the two searches pick, for every query, a sample whose distance is
//! the least within float rounding (`tests::tensor_search_matches_the_host_search`); where
//! two samples tie to that precision they may pick different ones.

use candle_core::{D, DType, Device, Tensor};
use rayon::prelude::*;

use dex2hoi_data::MAX_OBJECTS;

use crate::batch::SurfaceCloud;
use crate::error::Result;

/// Where the nearest surface samples are searched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SurfaceSearch {
    /// [`nearest_on_host`]: the points read back, searched on the CPU's threads.
    Host,
    /// [`DeviceClouds::nearest`]: tensor operations on the points' device.
    Tensor,
}

impl SurfaceSearch {
    /// The faster for a device: the host search on the CPU, the tensor search on a GPU.
    pub fn for_device(device: &Device) -> Self {
        if device.is_cpu() { Self::Host } else { Self::Tensor }
    }
}

/// The most elements of one `[rows, Q, K]` block of squared distances the tensor search makes
/// at once (256 MB in f32): batches larger than that are searched a block of rows at a time.
const BLOCK_ELEMENTS: usize = 1 << 26;

/// For every query point (object frame) of every window and slot, the nearest surface sample of
/// the slot's object and its normal (zeros for an empty slot), searched on the host.
///
/// # Shapes
/// - `local`: `[B, 2, Q, 3]` flattened; returns two such arrays
pub fn nearest_on_host(
    local: &[f32],
    slots: &[[Option<usize>; MAX_OBJECTS]],
    clouds: &[SurfaceCloud],
    queries: usize,
) -> (Vec<f32>, Vec<f32>) {
    let mut nearest = vec![0.0f32; local.len()];
    let mut normals = vec![0.0f32; local.len()];
    nearest
        .par_chunks_mut(queries * 3)
        .zip(normals.par_chunks_mut(queries * 3))
        .enumerate()
        .for_each(|(row, (nearest, normals))| {
            let (i, s) = (row / MAX_OBJECTS, row % MAX_OBJECTS);
            let Some(cloud) = slots.get(i).and_then(|slots| slots[s]).map(|c| &clouds[c]) else {
                return;
            };
            let points = &local[row * queries * 3..(row + 1) * queries * 3];
            for q in 0..queries {
                let x = glam::Vec3::from_slice(&points[q * 3..q * 3 + 3]);
                let mut best = (f32::INFINITY, 0);
                for (k, p) in cloud.points.iter().enumerate() {
                    let distance = x.distance_squared(*p);
                    if distance < best.0 {
                        best = (distance, k);
                    }
                }
                nearest[q * 3..q * 3 + 3].copy_from_slice(&cloud.points[best.1].to_array());
                normals[q * 3..q * 3 + 3].copy_from_slice(&cloud.normals[best.1].to_array());
            }
        });
    (nearest, normals)
}

/// Every object's surface samples as tensors on one device, for [`DeviceClouds::nearest`]:
/// `[C + 1, K, 3]` points and normals, the last row an empty slot's (zeros). Clouds with fewer
/// samples than the largest repeat their first sample, which changes no nearest distance.
#[derive(Debug, Clone)]
pub struct DeviceClouds {
    points: Tensor,
    normals: Tensor,
    /// `C`, the row of an empty slot.
    empty: u32,
}

impl DeviceClouds {
    /// The clouds on `device`, in f32.
    pub fn new(clouds: &[SurfaceCloud], device: &Device) -> Result<Self> {
        let samples = clouds.iter().map(|c| c.points.len()).max().unwrap_or(1).max(1);
        let rows = clouds.len() + 1;
        let mut points = vec![0.0f32; rows * samples * 3];
        let mut normals = vec![0.0f32; rows * samples * 3];
        for (c, cloud) in clouds.iter().enumerate().filter(|(_, c)| !c.points.is_empty()) {
            for k in 0..samples {
                let j = if k < cloud.points.len() { k } else { 0 };
                let at = (c * samples + k) * 3;
                points[at..at + 3].copy_from_slice(&cloud.points[j].to_array());
                normals[at..at + 3].copy_from_slice(&cloud.normals[j].to_array());
            }
        }
        let shape = (rows, samples, 3);
        Ok(Self {
            points: Tensor::from_vec(points, shape, device)?,
            normals: Tensor::from_vec(normals, shape, device)?,
            empty: clouds.len() as u32,
        })
    }

    /// Whether the clouds are on `device`.
    pub fn is_on(&self, device: &Device) -> bool {
        self.points.device().same_device(device)
    }

    /// The nearest sample and its normal for every query, searched where `local` is, as
    /// [`nearest_on_host`] does on the host: the squared distances `|x|^2 - 2 x.s + |s|^2` of a
    /// block of rows to every sample of the row's object, their smallest, and a gather.
    ///
    /// # Shapes
    /// - `local`: `[B, 2, Q, 3]` (any float type; not differentiated)
    /// - returns two `[B, 2, Q, 3]` tensors in f32
    pub fn nearest(
        &self,
        local: &Tensor,
        slots: &[[Option<usize>; MAX_OBJECTS]],
    ) -> Result<(Tensor, Tensor)> {
        self.nearest_in_blocks(local, slots, BLOCK_ELEMENTS)
    }

    /// [`Self::nearest`] with blocks of at most `block_elements` squared distances (at least one
    /// row each).
    fn nearest_in_blocks(
        &self,
        local: &Tensor,
        slots: &[[Option<usize>; MAX_OBJECTS]],
        block_elements: usize,
    ) -> Result<(Tensor, Tensor)> {
        let (batch, slot_count, queries, _) = local.dims4()?;
        let rows = batch * slot_count;
        let device = local.device();
        let local = local.detach().to_dtype(DType::F32)?.reshape((rows, queries, 3))?;
        let ids: Vec<u32> = (0..rows)
            .map(|row| {
                slots
                    .get(row / MAX_OBJECTS)
                    .and_then(|s| s[row % MAX_OBJECTS])
                    .map_or(self.empty, |c| c as u32)
            })
            .collect();
        let ids = Tensor::from_vec(ids, rows, device)?;
        let samples = self.points.dim(1)?;
        let block = (block_elements / (queries * samples).max(1)).clamp(1, rows.max(1));
        let mut nearest = Vec::new();
        let mut normals = Vec::new();
        for start in (0..rows).step_by(block) {
            let len = block.min(rows - start);
            let x = local.narrow(0, start, len)?; // [r, Q, 3]
            let row_ids = ids.narrow(0, start, len)?;
            let points = self.points.index_select(&row_ids, 0)?; // [r, K, 3]
            let cloud_normals = self.normals.index_select(&row_ids, 0)?;
            let cross = x.matmul(&points.transpose(1, 2)?.contiguous()?)?; // [r, Q, K]
            let squared = (cross
                .affine(-2.0, 0.0)?
                .broadcast_add(&x.sqr()?.sum_keepdim(D::Minus1)?)?
                .broadcast_add(&points.sqr()?.sum(D::Minus1)?.unsqueeze(1)?))?;
            let best = squared.argmin_keepdim(D::Minus1)?; // [r, Q, 1]
            let index = best.broadcast_as((len, queries, 3))?.contiguous()?;
            nearest.push(points.contiguous()?.gather(&index, 1)?);
            normals.push(cloud_normals.contiguous()?.gather(&index, 1)?);
        }
        let shape = (batch, slot_count, queries, 3);
        Ok((Tensor::cat(&nearest, 0)?.reshape(shape)?, Tensor::cat(&normals, 0)?.reshape(shape)?))
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    fn cloud(rng: &mut ChaCha8Rng, samples: usize, radius: f32) -> SurfaceCloud {
        let mut points = Vec::new();
        let mut normals = Vec::new();
        for _ in 0..samples {
            let v = Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize_or(Vec3::Y);
            points.push(v * radius);
            normals.push(v);
        }
        SurfaceCloud { points, normals }
    }

    /// The tensor search on the CPU against the host search: odd sizes, clouds of different
    /// sizes, an empty slot, a block size that splits the rows.
    #[test]
    fn tensor_search_matches_the_host_search() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let clouds =
            vec![cloud(&mut rng, 37, 0.05), cloud(&mut rng, 512, 0.12), cloud(&mut rng, 5, 0.3)];
        let slots = vec![[Some(1), None], [Some(0), Some(2)], [Some(2), Some(1)]];
        let (batch, queries) = (slots.len(), 53);
        let local: Vec<f32> =
            (0..batch * MAX_OBJECTS * queries * 3).map(|_| rng.random_range(-0.4..0.4)).collect();
        let (host_nearest, host_normals) = nearest_on_host(&local, &slots, &clouds, queries);
        let device = DeviceClouds::new(&clouds, &Device::Cpu).unwrap();
        let tensor =
            Tensor::from_vec(local.clone(), (batch, MAX_OBJECTS, queries, 3), &Device::Cpu)
                .unwrap();
        let (nearest, normals) = device.nearest(&tensor, &slots).unwrap();
        let nearest: Vec<f32> = nearest.flatten_all().unwrap().to_vec1().unwrap();
        let normals: Vec<f32> = normals.flatten_all().unwrap().to_vec1().unwrap();
        let mut same = 0;
        for (q, x) in local.chunks(3).enumerate() {
            let x = Vec3::from_slice(x);
            let at = q * 3..q * 3 + 3;
            let (a, b) = (
                Vec3::from_slice(&nearest[at.clone()]),
                Vec3::from_slice(&host_nearest[at.clone()]),
            );
            // The same distance within f32 rounding of the expanded form.
            assert!(
                (x.distance_squared(a) - x.distance_squared(b)).abs() <= 1e-6,
                "query {q}: tensor {a} at {}, host {b} at {}",
                x.distance(a),
                x.distance(b)
            );
            if a == b {
                same += 1;
                assert_eq!(&normals[at.clone()], &host_normals[at]);
            }
        }
        assert!(same * 100 >= local.len() / 3 * 99, "the same sample for {same} queries");
        // The empty slot: zeros, as on the host.
        let empty = (MAX_OBJECTS - 1) * queries * 3..MAX_OBJECTS * queries * 3;
        assert!(nearest[empty.clone()].iter().chain(&normals[empty]).all(|v| *v == 0.0));
    }

    #[test]
    fn blocks_give_the_same_search() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let clouds = vec![cloud(&mut rng, 64, 0.1), cloud(&mut rng, 9, 0.2)];
        let slots = vec![[Some(0), Some(1)], [Some(1), None], [Some(0), Some(0)]];
        let queries = 11;
        let values: Vec<f32> =
            (0..3 * MAX_OBJECTS * queries * 3).map(|_| rng.random_range(-0.3..0.3)).collect();
        let local = Tensor::from_vec(values, (3, MAX_OBJECTS, queries, 3), &Device::Cpu).unwrap();
        let device = DeviceClouds::new(&clouds, &Device::Cpu).unwrap();
        let (whole, whole_normals) = device.nearest(&local, &slots).unwrap();
        // Blocks of two rows (of six), then of one.
        for rows in [2, 1] {
            let (blocks, block_normals) =
                device.nearest_in_blocks(&local, &slots, rows * queries * 64).unwrap();
            for (a, b) in [(&whole, &blocks), (&whole_normals, &block_normals)] {
                let difference = (a - b).unwrap().abs().unwrap().max_all().unwrap();
                assert_eq!(difference.to_scalar::<f32>().unwrap(), 0.0, "blocks of {rows} rows");
            }
        }
    }
}
