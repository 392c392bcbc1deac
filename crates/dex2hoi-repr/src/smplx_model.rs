//! Reading the arrays of a user-supplied SMPL-X model file (`.npz`, as the SMPL-X website ships
//! `SMPLX_NEUTRAL.npz`). Only plain numeric arrays are read; other entries are left alone.

use std::path::{Path, PathBuf};

use glam::Vec3;

use crate::error::{ReprError, Result};
use crate::skeleton::{SMPLX55_PARENTS, Skeleton};

/// An open `.npz` file: a zip archive whose entries are `.npy` files named `KEY.npy`.
pub type NpzArchive = zip::ZipArchive<std::io::BufReader<std::fs::File>>;

/// A numeric array read from an `.npz` entry, in C order, converted to `f64`.
#[derive(Debug, Clone)]
pub struct NpzArray {
    /// Row-major values.
    pub values: Vec<f64>,
    /// The shape.
    pub shape: Vec<usize>,
}

/// The longest `.npy` header read. numpy writes a few hundred bytes (padded to a multiple of
/// 64); the length is a `u32` in format versions 2 and 3, which would otherwise let a file of a
/// few bytes make the reader allocate 4 GiB for its header.
pub const MAX_HEADER_BYTES: usize = 1 << 20;

/// Reads one numeric array from an open archive; Fortran-ordered arrays are transposed into C
/// order. Object (pickled) arrays, strings and records are refused with the key's name. The
/// header's length and the shape's size are checked against the entry's size before anything
/// is allocated for them.
pub fn read_npz_array(
    archive: &mut NpzArchive,
    path: &Path,
    key: &str,
    expected: &str,
) -> Result<NpzArray> {
    use std::io::Read;
    let io_error = |source| ReprError::Io { path: path.to_path_buf(), source };
    let entry_name = format!("{key}.npy");
    if !archive.file_names().any(|name| name == entry_name) {
        return Err(ReprError::MissingKey {
            path: path.to_path_buf(),
            key: key.into(),
            expected: expected.into(),
        });
    }
    let source_name = format!("{}[{key}]", path.display());
    let mut entry = archive.by_name(&entry_name).map_err(|e| io_error(std::io::Error::other(e)))?;
    let entry_bytes = entry.size();
    // The preamble (magic, version, header length) is read here to bound the header before
    // npyz allocates it, then handed back to npyz in front of the rest of the entry.
    let mut preamble = vec![0u8; 10];
    entry.read_exact(&mut preamble).map_err(io_error)?;
    let header_bytes = match (&preamble[..6], preamble[6]) {
        (b"\x93NUMPY", 1) => usize::from(u16::from_le_bytes([preamble[8], preamble[9]])),
        (b"\x93NUMPY", 2 | 3) => {
            preamble.extend([0, 0]);
            entry.read_exact(&mut preamble[10..]).map_err(io_error)?;
            u32::from_le_bytes([preamble[8], preamble[9], preamble[10], preamble[11]]) as usize
        }
        _ => {
            return Err(ReprError::format(
                source_name,
                "header",
                "a numpy array (\\x93NUMPY, version 1, 2 or 3)",
                format!("{:?}", &preamble[..8]),
            ));
        }
    };
    let data_start = (preamble.len() + header_bytes) as u64;
    if header_bytes > MAX_HEADER_BYTES || data_start > entry_bytes {
        return Err(ReprError::format(
            source_name,
            "header length",
            format!(
                "at most {MAX_HEADER_BYTES} bytes (numpy writes a few hundred) within the \
                 entry's {entry_bytes} bytes"
            ),
            header_bytes,
        ));
    }
    let mut header = vec![0u8; header_bytes];
    entry.read_exact(&mut header).map_err(io_error)?;
    // npyz multiplies the dimensions unchecked (an overflow panics with overflow checks).
    if let Some(dims) = header_shape(&header)
        && dims.iter().try_fold(1u64, |n, &d| n.checked_mul(d)).is_none()
    {
        return Err(ReprError::format(
            source_name,
            "shape",
            "dimensions whose product fits in 64 bits",
            format!("{dims:?}"),
        ));
    }
    preamble.extend(header);
    let file = npyz::NpyFile::new(std::io::Cursor::new(preamble).chain(entry)).map_err(io_error)?;
    let shape: Vec<usize> = file.shape().iter().map(|&d| d as usize).collect();
    let order = file.order();
    let type_string = match file.dtype() {
        npyz::DType::Plain(type_str) => type_str.to_string(),
        other => other.descr(),
    };
    let kind = type_string.trim_start_matches(['<', '>', '|', '=']);
    let numeric = "a numeric array (f4, f8, i4, i8, u4, u8)";
    let item_bytes: u64 = match kind {
        "f4" | "i4" | "u4" => 4,
        "f8" | "i8" | "u8" => 8,
        _ => return Err(ReprError::format(source_name, "array type", numeric, type_string)),
    };
    // The values must fit in what the entry holds past its header.
    let data_bytes = file.shape().iter().try_fold(item_bytes, |n, &d| n.checked_mul(d));
    if data_bytes.is_none_or(|n| n > entry_bytes - data_start) {
        return Err(ReprError::format(
            source_name,
            "shape",
            format!(
                "values of {item_bytes} bytes within the entry's {} bytes of data",
                entry_bytes - data_start
            ),
            format!("{shape:?}"),
        ));
    }
    let values: Vec<f64> = match kind {
        "f4" => file.into_vec::<f32>().map_err(io_error)?.into_iter().map(f64::from).collect(),
        "f8" => file.into_vec::<f64>().map_err(io_error)?,
        "i4" => file.into_vec::<i32>().map_err(io_error)?.into_iter().map(f64::from).collect(),
        "i8" => file.into_vec::<i64>().map_err(io_error)?.into_iter().map(|v| v as f64).collect(),
        "u4" => file.into_vec::<u32>().map_err(io_error)?.into_iter().map(f64::from).collect(),
        "u8" => file.into_vec::<u64>().map_err(io_error)?.into_iter().map(|v| v as f64).collect(),
        _ => return Err(ReprError::format(source_name, "array type", numeric, type_string)),
    };
    let count: usize = shape.iter().product();
    if values.len() != count {
        return Err(ReprError::format(
            source_name,
            "element count",
            format!("{count} values for shape {shape:?}"),
            values.len(),
        ));
    }
    let values = match order {
        npyz::Order::C => values,
        npyz::Order::Fortran => fortran_to_c(&values, &shape),
    };
    Ok(NpzArray { values, shape })
}

/// The dimensions of the `'shape': (...)` entry of a numpy header, when it reads as one.
fn header_shape(header: &[u8]) -> Option<Vec<u64>> {
    let text = std::str::from_utf8(header).ok()?;
    let after = &text[text.find("'shape'")? + "'shape'".len()..];
    let inner = after.trim_start().strip_prefix(':')?.trim_start().strip_prefix('(')?;
    let inner = &inner[..inner.find(')')?];
    inner
        .split(',')
        .map(str::trim)
        .filter(|d| !d.is_empty())
        .map(|d| d.trim_end_matches('L').parse().ok())
        .collect()
}

/// [`read_npz_array`] for an entry the file may lack (`None` then).
fn read_optional(
    archive: &mut NpzArchive,
    path: &Path,
    key: &str,
    expected: &str,
) -> Result<Option<NpzArray>> {
    match read_npz_array(archive, path, key, expected) {
        Ok(array) => Ok(Some(array)),
        Err(ReprError::MissingKey { .. }) => Ok(None),
        Err(other) => Err(other),
    }
}

/// Reorders column-major values into row-major order.
fn fortran_to_c(values: &[f64], shape: &[usize]) -> Vec<f64> {
    let count = values.len();
    let mut out = vec![0.0; count];
    let mut index = vec![0usize; shape.len()];
    for c_position in 0..count {
        // Column-major position of the multi-index.
        let mut f_position = 0;
        let mut stride = 1;
        for (axis, &i) in index.iter().enumerate() {
            f_position += i * stride;
            stride *= shape[axis];
        }
        out[c_position] = values[f_position];
        for axis in (0..shape.len()).rev() {
            index[axis] += 1;
            if index[axis] < shape[axis] {
                break;
            }
            index[axis] = 0;
        }
    }
    out
}

/// The arrays of an SMPL-X model file that rest joints (and, with `f` and `weights`, a skinned
/// body mesh) need.
#[derive(Debug, Clone)]
pub struct SmplxModel {
    path: PathBuf,
    /// Template vertices `(V, 3)`.
    pub v_template: NpzArray,
    /// Shape blend shapes `(V, 3, S)`.
    pub shapedirs: NpzArray,
    /// Joint regressor `(55, V)`.
    pub j_regressor: NpzArray,
    /// Triangles `f` `(F, 3)` (vertex indices below `V`), when the file has them.
    pub faces: Option<Vec<[u32; 3]>>,
    /// Linear-blend-skinning weights `weights` `(V, 55)`, when the file has them.
    pub weights: Option<NpzArray>,
}

/// The mesh of a model shaped by body-shape coefficients, in its rest pose.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapedSmplx {
    /// `v_template + shapedirs[..., :n] . betas`, `(V, 3)`.
    pub vertices: Vec<Vec3>,
    /// The 55 rest joints `J_regressor @ vertices`.
    pub joints: Vec<Vec3>,
    /// The model's triangles.
    pub faces: Vec<[u32; 3]>,
    /// Skinning weights over the 55 joints, `(V, 55)` row-major.
    pub weights: Vec<f64>,
}

impl SmplxModel {
    /// Opens the file and checks the keys and shapes of `v_template`, `shapedirs`,
    /// `J_regressor` and `kintree_table` (whose parent row must be the SMPL-X tree).
    pub fn load(path: &Path) -> Result<Self> {
        let io_error = |source| ReprError::Io { path: path.to_path_buf(), source };
        let file = std::fs::File::open(path).map_err(io_error)?;
        let mut archive = NpzArchive::new(std::io::BufReader::new(file))
            .map_err(|e| io_error(std::io::Error::other(e)))?;
        let name = path.display().to_string();
        let shape_error = |key: &str, expected: String, got: &[usize]| ReprError::Shape {
            source_name: name.clone(),
            key: key.into(),
            expected,
            got: got.to_vec(),
        };
        let v_template =
            read_npz_array(&mut archive, path, "v_template", "template vertices (V, 3)")?;
        if v_template.shape.len() != 2 || v_template.shape[1] != 3 || v_template.shape[0] == 0 {
            return Err(shape_error("v_template", "(V, 3)".into(), &v_template.shape));
        }
        let vertex_count = v_template.shape[0];
        let shapedirs =
            read_npz_array(&mut archive, path, "shapedirs", "shape blend shapes (V, 3, S)")?;
        if shapedirs.shape.len() != 3 || shapedirs.shape[..2] != [vertex_count, 3] {
            return Err(shape_error(
                "shapedirs",
                format!("({vertex_count}, 3, S)"),
                &shapedirs.shape,
            ));
        }
        let j_regressor =
            read_npz_array(&mut archive, path, "J_regressor", "joint regressor (55, V)")?;
        if j_regressor.shape != [55, vertex_count] {
            return Err(shape_error(
                "J_regressor",
                format!("(55, {vertex_count})"),
                &j_regressor.shape,
            ));
        }
        let kintree =
            read_npz_array(&mut archive, path, "kintree_table", "kinematic tree (2, 55)")?;
        if kintree.shape != [2, 55] {
            return Err(shape_error("kintree_table", "(2, 55)".into(), &kintree.shape));
        }
        // The root's parent is stored as -1 (int) or 2^32 - 1 (uint32).
        let parents: Vec<i64> = kintree.values[..55]
            .iter()
            .map(|&p| if p < 0.0 || p >= f64::from(u32::MAX) { -1 } else { p as i64 })
            .collect();
        let expected: Vec<i64> = SMPLX55_PARENTS.iter().map(|&p| i64::from(p)).collect();
        if parents != expected {
            return Err(ReprError::format(
                name,
                "kintree_table parents",
                format!("the SMPL-X tree {expected:?}"),
                format!("{parents:?}"),
            ));
        }
        for (key, array) in
            [("v_template", &v_template), ("shapedirs", &shapedirs), ("J_regressor", &j_regressor)]
        {
            if let Some(index) = array.values.iter().position(|v| !v.is_finite()) {
                return Err(ReprError::NonFinite {
                    source_name: name.clone(),
                    what: format!("`{key}` value"),
                    index,
                });
            }
        }
        let faces = read_optional(&mut archive, path, "f", "triangles (F, 3)")?
            .map(|f| {
                let index = f
                    .values
                    .iter()
                    .position(|&i| !(i >= 0.0 && i < vertex_count as f64 && i.fract() == 0.0));
                if f.shape.len() != 2 || f.shape[1] != 3 || f.shape[0] == 0 {
                    Err(shape_error("f", "(F, 3)".into(), &f.shape))
                } else if let Some(index) = index {
                    Err(ReprError::format(
                        name.clone(),
                        "`f` (triangles)",
                        format!("vertex indices below {vertex_count}"),
                        format!("{} at entry {index}", f.values[index]),
                    ))
                } else {
                    Ok(f.values
                        .chunks_exact(3)
                        .map(|t| [t[0], t[1], t[2]].map(|i| i as u32))
                        .collect())
                }
            })
            .transpose()?;
        let weights = read_optional(&mut archive, path, "weights", "skinning weights (V, 55)")?;
        if let Some(weights) = &weights {
            if weights.shape != [vertex_count, 55] {
                return Err(shape_error(
                    "weights",
                    format!("({vertex_count}, 55)"),
                    &weights.shape,
                ));
            }
            if let Some(index) = weights.values.iter().position(|w| !w.is_finite() || *w < 0.0) {
                return Err(ReprError::format(
                    name.clone(),
                    "`weights` (skinning weights)",
                    "finite non-negative numbers",
                    format!("{} at entry {index}", weights.values[index]),
                ));
            }
        }
        Ok(Self { path: path.to_path_buf(), v_template, shapedirs, j_regressor, faces, weights })
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The 55 rest joints for the given shape coefficients (at most as many as `shapedirs` has).
    pub fn rest_joints(&self, betas: &[f32]) -> Result<Vec<Vec3>> {
        Ok(self.regress(&self.shaped_vertices(betas)?))
    }

    /// The mesh shaped by `betas` with its rest joints, faces and skinning weights; the file must
    /// have `f` and `weights` (an error names the missing one).
    pub fn shaped(&self, betas: &[f32]) -> Result<ShapedSmplx> {
        let missing = |key: &str, expected: &str| ReprError::MissingKey {
            path: self.path.clone(),
            key: key.into(),
            expected: expected.into(),
        };
        let faces = self.faces.clone().ok_or_else(|| missing("f", "triangles (F, 3)"))?;
        let weights = self
            .weights
            .as_ref()
            .ok_or_else(|| missing("weights", "skinning weights (V, 55)"))?
            .values
            .clone();
        let flat = self.shaped_vertices(betas)?;
        let joints = self.regress(&flat);
        let vertices = flat
            .chunks_exact(3)
            .map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
            .collect();
        Ok(ShapedSmplx { vertices, joints, faces, weights })
    }

    /// `v_template + shapedirs[..., :n] . betas`, flat `(V * 3)`.
    fn shaped_vertices(&self, betas: &[f32]) -> Result<Vec<f64>> {
        let shape_count = self.shapedirs.shape[2];
        if betas.len() > shape_count {
            return Err(ReprError::invalid(
                format!("betas for {}", self.path.display()),
                format!("at most {shape_count} shape coefficients"),
                betas.len(),
            ));
        }
        if let Some(index) = betas.iter().position(|b| !b.is_finite()) {
            return Err(ReprError::NonFinite {
                source_name: "betas".into(),
                what: "beta".into(),
                index,
            });
        }
        let vertex_count = self.v_template.shape[0];
        let mut vertices = self.v_template.values.clone();
        for v in 0..vertex_count {
            for axis in 0..3 {
                let base = (v * 3 + axis) * shape_count;
                let blend: f64 = betas
                    .iter()
                    .enumerate()
                    .map(|(k, &b)| self.shapedirs.values[base + k] * f64::from(b))
                    .sum();
                vertices[v * 3 + axis] += blend;
            }
        }
        Ok(vertices)
    }

    /// The 55 joints the model's `J_regressor` gives for a mesh of its topology: a subject's
    /// personalised template (GRAB's `tools/subject_meshes/{gender}/s{n}.ply`, its `vtemp`).
    /// `source_name` names the mesh in errors.
    pub fn joints_of(&self, vertices: &[Vec3], source_name: &str) -> Result<Vec<Vec3>> {
        let vertex_count = self.v_template.shape[0];
        if vertices.len() != vertex_count {
            return Err(ReprError::invalid(
                format!("template mesh {source_name}"),
                format!("{vertex_count} vertices (the topology of {})", self.path.display()),
                vertices.len(),
            ));
        }
        let flat: Vec<f64> = vertices.iter().flat_map(|v| v.to_array().map(f64::from)).collect();
        Ok(self.regress(&flat))
    }

    /// `J_regressor @ vertices` for flat `(V * 3)` vertices.
    fn regress(&self, vertices: &[f64]) -> Vec<Vec3> {
        let vertex_count = self.v_template.shape[0];
        (0..55)
            .map(|joint| {
                let row =
                    &self.j_regressor.values[joint * vertex_count..(joint + 1) * vertex_count];
                let mut sum = [0.0f64; 3];
                for (v, &weight) in row.iter().enumerate() {
                    if weight != 0.0 {
                        for axis in 0..3 {
                            sum[axis] += weight * vertices[v * 3 + axis];
                        }
                    }
                }
                Vec3::new(sum[0] as f32, sum[1] as f32, sum[2] as f32)
            })
            .collect()
    }
}

impl Skeleton {
    /// Rest joints computed from a user-supplied SMPL-X model file (`SMPLX_NEUTRAL.npz` and
    /// friends) and body-shape coefficients, reduced from 55 to 52 joints:
    /// `J = J_regressor @ (v_template + shapedirs[..., :n] . betas)`, then offsets child minus
    /// parent. The file's `kintree_table` must describe the SMPL-X tree. Arrays may be stored
    /// as `f32` or `f64`, in C or Fortran order; extra keys (including pickled ones) are ignored.
    pub fn from_smplx_model(path: &Path, betas: &[f32]) -> Result<Self> {
        let model = SmplxModel::load(path)?;
        Self::from_smplx_joints(&model.rest_joints(betas)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fortran_order_is_transposed() {
        // numpy: np.arange(6).reshape(2, 3, order='F') stores [0..6] column-major.
        let c = fortran_to_c(&[0.0, 1.0, 2.0, 3.0, 4.0, 5.0], &[2, 3]);
        assert_eq!(c, vec![0.0, 2.0, 4.0, 1.0, 3.0, 5.0]);
    }
}
