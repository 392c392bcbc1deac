//! `motion.bvh`: the skeleton's animation in BioVision hierarchy form.
//!
//! The hierarchy holds every joint with its rest offset from its parent (metres); leaves end in
//! an `End Site` half as long as their own bone. The root's `OFFSET` is zero and its position
//! channels hold the root's world position, which Blender (absolute positions) and three.js
//! (positions added to the offset) both read the same way. Every joint has three rotation
//! channels `Zrotation Xrotation Yrotation` in degrees: the local rotation is
//! `R = Rz(z) Rx(x) Ry(y)` acting on column vectors, the usual BVH reading of the channel order.
//! Joints are written depth first, so the channel order of the `MOTION` lines is the hierarchy
//! order, which need not be the skeleton's joint order. Joints carry the rig's own names
//! (`mixamorig:Hips` for Mixamo). BVH has no rest orientations (its rest pose is identity
//! rotations on the offsets), so a Mixamo motion keeps our frames here; `motion.glb` has
//! Mixamo's.

use std::fmt::Write as _;
use std::path::Path;

use glam::{DMat3, Mat3, Vec3};

use crate::error::{ExportError, Result};
use crate::{ExportMotion, write_file};

/// Below this `cos(x)` the ZXY decomposition is at gimbal lock and sets the Y angle to zero.
const GIMBAL_COS: f64 = 1e-9;

/// Euler angles `(z, x, y)` in radians with `R = Rz(z) Rx(x) Ry(y)`, `x` in `[-pi/2, pi/2]`.
pub fn matrix_to_euler_zxy(rotation: Mat3) -> [f64; 3] {
    let r = DMat3::from_cols(
        rotation.x_axis.as_dvec3(),
        rotation.y_axis.as_dvec3(),
        rotation.z_axis.as_dvec3(),
    );
    // `r.col(c)[row]` is R[row][c]: R[2][1] = sin x, R[2][0] = -cos x sin y,
    // R[2][2] = cos x cos y, R[0][1] = -sin z cos x, R[1][1] = cos z cos x.
    let at = |row: usize, column: usize| r.col(column)[row];
    let x = at(2, 1).clamp(-1.0, 1.0).asin();
    if x.cos() > GIMBAL_COS {
        let y = (-at(2, 0)).atan2(at(2, 2));
        let z = (-at(0, 1)).atan2(at(1, 1));
        [z, x, y]
    } else {
        // cos x = 0: only z + y (or z - y) is defined; with y = 0, R[0][0] = cos z, R[1][0] = sin z.
        [at(1, 0).atan2(at(0, 0)), x, 0.0]
    }
}

/// The rotation about one axis.
fn axis_rotation(axis: char, radians: f64) -> Option<DMat3> {
    match axis {
        'X' => Some(DMat3::from_rotation_x(radians)),
        'Y' => Some(DMat3::from_rotation_y(radians)),
        'Z' => Some(DMat3::from_rotation_z(radians)),
        _ => None,
    }
}

/// `Rz(z) Rx(x) Ry(y)`.
pub fn euler_zxy_to_matrix([z, x, y]: [f64; 3]) -> Mat3 {
    let r = DMat3::from_rotation_z(z) * DMat3::from_rotation_x(x) * DMat3::from_rotation_y(y);
    r.as_mat3()
}

fn depth_first(children: &[Vec<usize>], joint: usize, order: &mut Vec<usize>) {
    order.push(joint);
    for &child in &children[joint] {
        depth_first(children, child, order);
    }
}

/// The text of `motion.bvh` for a motion (format in the module documentation).
///
/// # Shapes
/// - the motion's `local_rotations`: `[frames * joints]`; `root_positions`: `[frames]`
pub fn encode_bvh(motion: &ExportMotion<'_>) -> Result<String> {
    let checked = motion.check()?;
    let skeleton = checked.skeleton;
    let children = skeleton.children();
    let offsets = skeleton.rest_offsets();
    let names = skeleton.rig_joint_names();
    let mut order = Vec::with_capacity(skeleton.joint_count());
    depth_first(&children, 0, &mut order);

    let mut out = String::from("HIERARCHY\n");
    // Writing to a String cannot fail; `let _ =` keeps the builder free of unwraps.
    let mut open = vec![0usize];
    let _ = writeln!(out, "ROOT {}\n{{", names[0]);
    let _ = writeln!(out, "\tOFFSET 0.000000 0.000000 0.000000");
    let _ =
        writeln!(out, "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation");
    for window in order.windows(2) {
        let (previous, joint) = (window[0], window[1]);
        let parent = skeleton.parents()[joint].unwrap_or(0);
        if children[previous].is_empty() {
            close_leaf(&mut out, open.len(), offsets[previous]);
        }
        while open.last() != Some(&parent) {
            open.pop();
            let _ = writeln!(out, "{}}}", "\t".repeat(open.len()));
        }
        let indent = "\t".repeat(open.len());
        let o = offsets[joint];
        let _ = writeln!(out, "{indent}JOINT {}\n{indent}{{", names[joint]);
        let _ = writeln!(out, "{indent}\tOFFSET {:.6} {:.6} {:.6}", o.x, o.y, o.z);
        let _ = writeln!(out, "{indent}\tCHANNELS 3 Zrotation Xrotation Yrotation");
        open.push(joint);
    }
    if let Some(&last) = order.last().filter(|&&j| children[j].is_empty()) {
        close_leaf(&mut out, open.len(), offsets[last]);
    }
    while open.pop().is_some() {
        let _ = writeln!(out, "{}}}", "\t".repeat(open.len()));
    }

    let _ =
        writeln!(out, "MOTION\nFrames: {}\nFrame Time: {:.7}", checked.frames, 1.0 / checked.fps);
    let joints = skeleton.joint_count();
    for frame in 0..checked.frames {
        let root = checked.root_positions[frame];
        let mut line = format!("{:.6} {:.6} {:.6}", root.x, root.y, root.z);
        for &joint in &order {
            let [z, x, y] = matrix_to_euler_zxy(checked.local_rotations[frame * joints + joint]);
            let _ =
                write!(line, " {:.6} {:.6} {:.6}", z.to_degrees(), x.to_degrees(), y.to_degrees());
        }
        out.push_str(&line);
        out.push('\n');
    }
    Ok(out)
}

/// The `End Site` of a leaf joint (half its own bone further on) and the leaf's closing brace.
fn close_leaf(out: &mut String, depth: usize, leaf_offset: Vec3) {
    let indent = "\t".repeat(depth);
    let end = leaf_offset * 0.5;
    let _ = writeln!(out, "{indent}End Site\n{indent}{{");
    let _ = writeln!(out, "{indent}\tOFFSET {:.6} {:.6} {:.6}", end.x, end.y, end.z);
    let _ = writeln!(out, "{indent}}}");
}

/// Writes `motion.bvh` atomically (see [`encode_bvh`]).
///
/// # Shapes
/// - as [`encode_bvh`]
pub fn write_bvh(path: &Path, motion: &ExportMotion<'_>) -> Result<()> {
    let text = encode_bvh(motion)?;
    write_file(path, text.as_bytes())
}

/// A BVH file read back: joints in hierarchy (depth-first) order.
#[derive(Debug, Clone, PartialEq)]
pub struct BvhMotion {
    /// Joint names (`End Site`s are not joints).
    pub joint_names: Vec<String>,
    /// Parent of each joint, `None` for the root.
    pub parents: Vec<Option<usize>>,
    /// `OFFSET` of each joint.
    pub offsets: Vec<Vec3>,
    /// Seconds per frame.
    pub frame_time: f32,
    /// Root position channels per frame (zero when the root has none), plus the root offset.
    pub root_positions: Vec<Vec3>,
    /// Local rotations, frame-major `[frames * joints]`.
    pub local_rotations: Vec<Mat3>,
}

/// The channels of one joint.
#[derive(Debug, Clone, Default)]
struct Channels {
    /// Index of each position channel (x, y, z) in the joint's channel list.
    position: [Option<usize>; 3],
    /// The rotation axes in channel order with their index in the joint's channel list.
    rotation: Vec<(char, usize)>,
    count: usize,
}

/// A cursor over the whitespace-separated tokens of a BVH file, with line numbers.
struct Tokens<'a> {
    tokens: Vec<(usize, &'a str)>,
    next: usize,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str) -> Self {
        let tokens = text
            .lines()
            .enumerate()
            .flat_map(|(line, content)| content.split_whitespace().map(move |t| (line + 1, t)))
            .collect();
        Self { tokens, next: 0 }
    }

    fn line(&self) -> usize {
        self.tokens.get(self.next).or(self.tokens.last()).map_or(0, |t| t.0)
    }

    fn error(&self, expected: impl Into<String>, got: impl std::fmt::Display) -> ExportError {
        ExportError::invalid(format!("BVH line {}", self.line()), expected, got)
    }

    fn peek(&self) -> Option<&'a str> {
        self.tokens.get(self.next).map(|t| t.1)
    }

    fn take(&mut self, what: &str) -> Result<&'a str> {
        let token = self.peek().ok_or_else(|| self.error(what, "the end of the file"))?;
        self.next += 1;
        Ok(token)
    }

    fn expect(&mut self, keyword: &str) -> Result<()> {
        let token = self.take(keyword)?;
        if token != keyword {
            self.next -= 1;
            return Err(self.error(format!("`{keyword}`"), format!("`{token}`")));
        }
        Ok(())
    }

    fn number<T: std::str::FromStr>(&mut self, what: &str) -> Result<T> {
        let token = self.take(what)?;
        token.parse().map_err(|_| {
            self.next -= 1;
            self.error(what, format!("`{token}`"))
        })
    }

    fn vector(&mut self) -> Result<Vec3> {
        Ok(Vec3::new(self.number("a number")?, self.number("a number")?, self.number("a number")?))
    }
}

/// Reads one joint (after its `ROOT`/`JOINT` keyword) and its subtree.
fn parse_joint(
    tokens: &mut Tokens<'_>,
    parent: Option<usize>,
    out: &mut BvhMotion,
    channels: &mut Vec<Channels>,
) -> Result<()> {
    let index = out.joint_names.len();
    out.joint_names.push(tokens.take("a joint name")?.to_string());
    out.parents.push(parent);
    tokens.expect("{")?;
    tokens.expect("OFFSET")?;
    out.offsets.push(tokens.vector()?);
    tokens.expect("CHANNELS")?;
    let count: usize = tokens.number("a channel count")?;
    let mut joint_channels = Channels { count, ..Channels::default() };
    for k in 0..count {
        let name = tokens.take("a channel name")?;
        let mut chars = name.chars();
        let axis = chars.next().unwrap_or(' ');
        match (axis, chars.as_str()) {
            ('X' | 'Y' | 'Z', "position") => {
                joint_channels.position[(axis as u8 - b'X') as usize] = Some(k)
            }
            ('X' | 'Y' | 'Z', "rotation") => joint_channels.rotation.push((axis, k)),
            _ => return Err(tokens.error("a channel such as `Xposition` or `Zrotation`", name)),
        }
    }
    channels.push(joint_channels);
    loop {
        match tokens.take("`JOINT`, `End` or `}`")? {
            "JOINT" => parse_joint(tokens, Some(index), out, channels)?,
            "End" => {
                tokens.expect("Site")?;
                tokens.expect("{")?;
                tokens.expect("OFFSET")?;
                tokens.vector()?;
                tokens.expect("}")?;
            }
            "}" => return Ok(()),
            other => {
                tokens.next -= 1;
                return Err(tokens.error("`JOINT`, `End Site` or `}`", other));
            }
        }
    }
}

/// Parses BVH text: any rotation channel order per joint, position channels on any joint (only
/// the root's are kept). Rotations compose in channel order (`R = R_first R_second R_third`).
pub fn parse_bvh(text: &str) -> Result<BvhMotion> {
    let mut tokens = Tokens::new(text);
    tokens.expect("HIERARCHY")?;
    tokens.expect("ROOT")?;
    let mut out = BvhMotion {
        joint_names: Vec::new(),
        parents: Vec::new(),
        offsets: Vec::new(),
        frame_time: 0.0,
        root_positions: Vec::new(),
        local_rotations: Vec::new(),
    };
    let mut channels = Vec::new();
    parse_joint(&mut tokens, None, &mut out, &mut channels)?;
    tokens.expect("MOTION")?;
    tokens.expect("Frames:")?;
    let frames: usize = tokens.number("a frame count")?;
    tokens.expect("Frame")?;
    tokens.expect("Time:")?;
    out.frame_time = tokens.number("seconds per frame")?;
    for _ in 0..frames {
        for (joint, joint_channels) in channels.iter().enumerate() {
            let mut values = Vec::with_capacity(joint_channels.count);
            for _ in 0..joint_channels.count {
                values.push(tokens.number::<f64>("a channel value")?);
            }
            let mut rotation = DMat3::IDENTITY;
            for &(axis, k) in &joint_channels.rotation {
                let turn = axis_rotation(axis, values[k].to_radians())
                    .ok_or_else(|| tokens.error("a rotation axis", axis))?;
                rotation *= turn;
            }
            out.local_rotations.push(rotation.as_mat3());
            if joint == 0 {
                let position = joint_channels.position.map(|k| k.map_or(0.0, |k| values[k]));
                out.root_positions.push(out.offsets[0] + glam::DVec3::from(position).as_vec3());
            }
        }
    }
    if let Some(extra) = tokens.peek() {
        return Err(tokens.error(format!("{frames} frames and then the end of the file"), extra));
    }
    Ok(out)
}

/// Reads and parses a BVH file (see [`parse_bvh`]).
pub fn read_bvh(path: &Path) -> Result<BvhMotion> {
    let text = std::fs::read_to_string(path).map_err(|source| ExportError::Io {
        path: path.to_path_buf(),
        action: "reading",
        source,
    })?;
    parse_bvh(&text).map_err(|error| match error {
        ExportError::Invalid { context, expected, got } => ExportError::Invalid {
            context: format!("{}: {context}", path.display()),
            expected,
            got,
        },
        other => other,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dex2hoi_repr::rotation::axis_angle_to_matrix;

    #[test]
    fn euler_zxy_round_trips_including_gimbal_lock() {
        let cases = [
            Vec3::new(0.3, -1.2, 0.7),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(3.0, 0.1, -0.2),
            Vec3::new(1.0, 0.0, 0.0) * std::f32::consts::FRAC_PI_2,
            Vec3::new(-1.0, 0.0, 0.0) * std::f32::consts::FRAC_PI_2,
        ];
        for rotation_vector in cases {
            let r = axis_angle_to_matrix(rotation_vector);
            let back = euler_zxy_to_matrix(matrix_to_euler_zxy(r));
            assert!(
                (back - r).to_cols_array().iter().all(|d| d.abs() < 1e-5),
                "{rotation_vector}: {r} vs {back}"
            );
        }
        // The order is Rz Rx Ry, not another order.
        let [z, x, y] = [0.4, 0.5, 0.6];
        let expected =
            Mat3::from_rotation_z(z) * Mat3::from_rotation_x(x) * Mat3::from_rotation_y(y);
        let angles = matrix_to_euler_zxy(expected);
        assert!((angles[0] - 0.4).abs() < 1e-5 && (angles[1] - 0.5).abs() < 1e-5);
        assert!((angles[2] - 0.6).abs() < 1e-5);
    }

    #[test]
    fn malformed_bvh_is_an_error_with_a_line_number() {
        let error = parse_bvh("HIERARCHY\nROOT hips\n{\nOFFSET 0 0 x\n").expect_err("bad number");
        assert!(error.to_string().contains("BVH line 4"), "{error}");
        let error = parse_bvh("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Wrotation\n}\n")
            .expect_err("bad channel");
        assert!(error.to_string().contains("Wrotation"), "{error}");
    }
}
