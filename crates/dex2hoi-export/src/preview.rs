//! `preview.gif` and `preview.png`: the motion drawn by a small z-buffered software rasteriser,
//! so that a person can look at a result without any other tool.
//!
//! The scene is the body (the export's skinned mesh, an SMPL-X model's or a character's, posed
//! by linear blend skinning; else the capsule body of [`mod@crate::body_mesh`]), the object
//! meshes, an optional table
//! and a checkered floor at `y = 0`, under one directional light with Lambert shading (flat per
//! triangle, lit from whichever side faces the camera). Each frame shows two views side by
//! side, both framing the bounding box of every joint and object over all frames: a
//! three-quarter view from the character's front left (35 degrees round from +Z towards +X, 20
//! degrees above the horizon) and a side view from its right (10 degrees above the horizon).
//! A motion that travels farther than [`FOLLOW_BEYOND_M`] (walking while carrying) would be
//! drawn small that way: there the views follow the person, framing a box of one size (the
//! largest of any frame's) about each frame's centre averaged over [`FOLLOW_SMOOTHING_S`].
//! Above them a caption band writes the prompt in force on the frame with the project's bitmap
//! font ([`dex2hoi_plot::font`]). Hand bones are coloured by contact: yellow when one of their joints
//! is within [`CONTACT_RADIUS_M`] of an object's surface, red when one is deeper than
//! [`PENETRATION_TOLERANCE_M`] inside it (the thresholds of the contact and penetration
//! metrics). `preview.png` is a still sheet of the first view at 0, 25, 50, 75 and 100% of the
//! clip under the whole prompt, each panel labelled with its time.
//!
//! Colours come from one fixed palette: eleven surfaces ([`Surface`]) times 23 shades (padded to
//! 256 entries), so every pixel is an exact palette index (no quantisation, no dithering) and the
//! same motion always gives the same bytes. GIF frame delays are whole centiseconds: frame `i` lasts
//! `round(100 (i + 1) / fps) - round(100 i / fps)` cs (at least 2, since browsers slow down
//! shorter delays), so 20 fps gives 5 cs per frame and 30 fps alternates 3, 4 and 3 cs.

use std::borrow::Cow;
use std::path::Path;

use glam::{Mat3, Mat4, Vec2, Vec3};
use rayon::prelude::*;

use dex2hoi_repr::mesh::box_mesh;
use dex2hoi_repr::{CONTACT_RADIUS_M, Mesh, MeshQuery, PENETRATION_TOLERANCE_M};

use crate::body_mesh::body_mesh;
use crate::error::{ExportError, Result};
use crate::{Checked, ExportMotion, write_file};
use dex2hoi_plot::font;

/// Shades per surface in the palette.
pub const SHADES: usize = 23;
/// Entries of the palette (the surfaces' shades, padded with black).
const PALETTE_SIZE: usize = 256;
/// Vertical field of view of the camera.
const FIELD_OF_VIEW_Y: f32 = 40.0 * std::f32::consts::PI / 180.0;
/// Camera direction: degrees round from +Z towards +X, and above the horizon.
const CAMERA_AZIMUTH: f32 = 35.0 * std::f32::consts::PI / 180.0;
const CAMERA_ELEVATION: f32 = 20.0 * std::f32::consts::PI / 180.0;
/// The side view: from the character's right (-X), a little above the horizon.
const SIDE_AZIMUTH: f32 = -90.0 * std::f32::consts::PI / 180.0;
const SIDE_ELEVATION: f32 = 10.0 * std::f32::consts::PI / 180.0;
/// Caption: font scale, lines at most, margin around the text and gap between lines (pixels).
const CAPTION_SCALE: usize = 2;
const CAPTION_LINES: usize = 2;
const CAPTION_MARGIN: usize = 6;
const CAPTION_LINE_GAP: usize = 4;
/// Panels of `preview.png`, at these fractions of the clip.
pub const SHEET_PANELS: usize = 5;
/// Added to the framed box's half diagonal for the body's thickness.
const FRAMING_MARGIN: f32 = 0.15;
/// Distance of the near clipping plane.
const NEAR: f32 = 0.05;
/// Direction towards the light (above, in front, to the character's left).
const LIGHT: Vec3 = Vec3::new(0.4, 1.0, 0.6);
/// Light that reaches surfaces facing away from the light.
const AMBIENT: f32 = 0.35;
/// How far (metres, across the floor) a motion's joints and objects may spread before the views
/// follow the person rather than frame everything at once.
pub const FOLLOW_BEYOND_M: f32 = 2.5;
/// Seconds over which a following view's centre is averaged, so that the camera glides.
pub const FOLLOW_SMOOTHING_S: f32 = 1.0;
/// Floor tiles (metres) and how far the floor reaches from the framed centre.
const FLOOR_TILE: f32 = 0.5;
const FLOOR_REACH: f32 = 4.0;
/// Thickness of the table top and width of its square legs.
const TABLE_TOP_THICKNESS: f32 = 0.04;
const TABLE_LEG_WIDTH: f32 = 0.05;
/// Smallest and largest image side.
const MIN_SIDE: u32 = 16;
const MAX_SIDE: u32 = 4096;

/// What a pixel of the preview shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Surface {
    /// Nothing (the sky).
    Background,
    /// The floor (either tile colour).
    Floor,
    /// The table.
    Table,
    /// The body.
    Body,
    /// An object, by its index in [`ExportMotion::objects`] (the third and later share a
    /// colour).
    Object(usize),
    /// A hand bone in contact with an object.
    Contact,
    /// A hand bone inside an object.
    Penetration,
    /// The caption's text.
    Caption,
}

/// Palette slots (each [`SHADES`] entries) and their base colours.
const PALETTE_SURFACES: [[u8; 3]; 11] = [
    [222, 230, 240], // background
    [205, 203, 196], // floor, light tiles
    [172, 170, 163], // floor, dark tiles
    [150, 104, 64],  // table
    [88, 140, 212],  // body
    [236, 124, 40],  // first object
    [56, 178, 92],   // second object
    [196, 64, 160],  // further objects
    [250, 204, 32],  // hand in contact
    [228, 36, 36],   // hand inside an object
    [28, 30, 40],    // caption text
];
const BACKGROUND: usize = 0;
const FLOOR_LIGHT: usize = 1;
const FLOOR_DARK: usize = 2;
const TABLE: usize = 3;
const BODY: usize = 4;
const FIRST_OBJECT: usize = 5;
const FURTHER_OBJECTS: usize = 7;
const CONTACT: usize = 8;
const PENETRATION: usize = 9;
const CAPTION: usize = 10;

fn surface_of_slot(slot: usize) -> Surface {
    match slot {
        BACKGROUND => Surface::Background,
        FLOOR_LIGHT | FLOOR_DARK => Surface::Floor,
        TABLE => Surface::Table,
        BODY => Surface::Body,
        CONTACT => Surface::Contact,
        PENETRATION => Surface::Penetration,
        CAPTION => Surface::Caption,
        object => Surface::Object(object - FIRST_OBJECT),
    }
}

/// The palette slot of an object index.
fn object_slot(object: usize) -> usize {
    (FIRST_OBJECT + object).min(FURTHER_OBJECTS)
}

/// The palette: entry `slot * SHADES + shade` is the slot's colour at light level
/// `shade / (SHADES - 1)`; black after the last slot.
pub fn palette() -> Vec<[u8; 3]> {
    let mut entries: Vec<[u8; 3]> = PALETTE_SURFACES
        .iter()
        .flat_map(|base| {
            (0..SHADES).map(move |shade| {
                let light = shade as f32 / (SHADES - 1) as f32;
                base.map(|c| (c as f32 * light).round() as u8)
            })
        })
        .collect();
    entries.resize(PALETTE_SIZE, [0; 3]);
    entries
}

/// The palette index of a slot lit at `light` in `[0, 1]`.
fn colour(slot: usize, light: f32) -> u8 {
    let shade = (light.clamp(0.0, 1.0) * (SHADES - 1) as f32).round() as usize;
    (slot * SHADES + shade) as u8
}

/// A table: a top at `height` over a rectangle of the floor, on four legs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableBox {
    /// Height of the top surface (metres).
    pub height: f32,
    /// Centre of the top, `(x, z)`.
    pub centre: Vec2,
    /// Half extents of the top, `(x, z)`.
    pub half_extents: Vec2,
}

/// Options of the preview.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PreviewOptions {
    /// Width of each of the two views in pixels (16-4096): the image is twice as wide.
    pub width: u32,
    /// Height of the views in pixels (16-4096): the image adds the caption band above.
    pub height: u32,
    /// The table to draw, if any.
    pub table: Option<TableBox>,
    /// Whether the prompt is written above the views.
    pub caption: bool,
}

impl Default for PreviewOptions {
    /// Views of 320 x 320 pixels, no table, with the caption.
    fn default() -> Self {
        Self { width: 320, height: 320, table: None, caption: true }
    }
}

impl PreviewOptions {
    fn check(&self) -> Result<()> {
        for (what, side) in [("preview width", self.width), ("preview height", self.height)] {
            if !(MIN_SIDE..=MAX_SIDE).contains(&side) {
                return Err(ExportError::invalid(
                    what,
                    format!("{MIN_SIDE} to {MAX_SIDE} pixels"),
                    side,
                ));
            }
        }
        if let Some(table) = &self.table {
            let valid = table.height.is_finite()
                && table.height > TABLE_TOP_THICKNESS
                && table.centre.is_finite()
                && table.half_extents.is_finite()
                && table.half_extents.min_element() > TABLE_LEG_WIDTH;
            if !valid {
                return Err(ExportError::invalid(
                    "preview table",
                    format!(
                        "a finite centre, a height above {TABLE_TOP_THICKNESS} m and half extents \
                         above {TABLE_LEG_WIDTH} m"
                    ),
                    format!("{table:?}"),
                ));
            }
        }
        Ok(())
    }
}

/// The fixed perspective camera of a preview.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Camera position (world).
    pub eye: Vec3,
    /// The point at the image centre.
    pub target: Vec3,
    /// Vertical field of view (radians).
    pub fov_y: f32,
    /// Width of the camera's view in pixels.
    pub width: u32,
    /// Height of the camera's view in pixels.
    pub height: u32,
    /// Where the view's top-left corner sits in the preview image (pixels).
    pub origin: Vec2,
}

impl Camera {
    /// The camera looking from `(azimuth, elevation)` that frames the box `[min, max]`.
    fn framing(
        (min, max): (Vec3, Vec3),
        (width, height): (u32, u32),
        (azimuth, elevation): (f32, f32),
        origin: Vec2,
    ) -> Self {
        let target = (min + max) * 0.5;
        let radius = (max - min).length() * 0.5 + FRAMING_MARGIN;
        let aspect = width as f32 / height as f32;
        // The narrower of the two fields of view must hold the bounding sphere.
        let half_fov = (FIELD_OF_VIEW_Y * 0.5).min(((FIELD_OF_VIEW_Y * 0.5).tan() * aspect).atan());
        let direction = Vec3::new(
            azimuth.sin() * elevation.cos(),
            elevation.sin(),
            azimuth.cos() * elevation.cos(),
        );
        Self {
            eye: target + direction * radius / half_fov.sin(),
            target,
            fov_y: FIELD_OF_VIEW_Y,
            width,
            height,
            origin,
        }
    }

    fn view(&self) -> Mat4 {
        glam::camera::rh::view::look_at_mat4(self.eye, self.target, Vec3::Y)
    }

    /// A point in camera space (looking down -Z) to pixel coordinates and inverse depth.
    fn screen_position(&self, camera_space: Vec3) -> (Vec2, f32) {
        let focal = 1.0 / (self.fov_y * 0.5).tan();
        let aspect = self.width as f32 / self.height as f32;
        let inverse_depth = 1.0 / -camera_space.z;
        let ndc = Vec2::new(
            focal / aspect * camera_space.x * inverse_depth,
            focal * camera_space.y * inverse_depth,
        );
        let pixel = Vec2::new(
            (ndc.x + 1.0) * 0.5 * self.width as f32,
            (1.0 - ndc.y) * 0.5 * self.height as f32,
        );
        (pixel, inverse_depth)
    }

    /// Pixel coordinates in the preview image (x to the right, y down, pixel `(i, j)` covering
    /// `[i, i + 1) x [j, j + 1)`) of a world point, `None` behind the near plane.
    pub fn project(&self, world: Vec3) -> Option<Vec2> {
        let camera_space = self.view().transform_point3(world);
        (camera_space.z < -NEAR).then(|| self.screen_position(camera_space).0 + self.origin)
    }
}

/// A rendered preview: palette indices per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Preview {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Per frame, `width * height` palette indices, row by row from the top.
    pub frames: Vec<Vec<u8>>,
    /// Per frame, its delay in centiseconds.
    pub delays: Vec<u16>,
    /// The two views of the first frame: the three-quarter view (left), the side view (right).
    pub views: [Camera; 2],
    /// The views of every frame: the same on every frame, unless they follow a motion that
    /// travels far.
    pub frame_views: Vec<[Camera; 2]>,
    /// Height of the caption band above the views (0 without a caption).
    pub caption_height: u32,
}

impl Preview {
    /// What the pixel `(x, y)` of a frame shows (`None` outside the image or the clip).
    pub fn surface_at(&self, frame: usize, x: u32, y: u32) -> Option<Surface> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let index = *self.frames.get(frame)?.get((y * self.width + x) as usize)?;
        Some(surface_of_slot(index as usize / SHADES))
    }

    /// The animated GIF (global palette, looping forever).
    pub fn encode_gif(&self) -> Result<Vec<u8>> {
        let gif_error = |e: gif::EncodingError| ExportError::invalid("GIF encoding", "success", e);
        let flat_palette: Vec<u8> = palette().concat();
        let (width, height) = (self.width as u16, self.height as u16);
        let mut encoder =
            gif::Encoder::new(Vec::new(), width, height, &flat_palette).map_err(gif_error)?;
        encoder.set_repeat(gif::Repeat::Infinite).map_err(gif_error)?;
        for (pixels, &delay) in self.frames.iter().zip(&self.delays) {
            let frame = gif::Frame {
                width,
                height,
                delay,
                buffer: Cow::Borrowed(pixels),
                ..gif::Frame::default()
            };
            encoder.write_frame(&frame).map_err(gif_error)?;
        }
        encoder.into_inner().map_err(gif_error)
    }
}

/// Frame delays in centiseconds with the rounding error carried over (module documentation).
pub fn frame_delays(frames: usize, fps: f32) -> Vec<u16> {
    let at = |frame: usize| (frame as f64 * 100.0 / fps as f64).round();
    (0..frames).map(|i| (at(i + 1) - at(i)).clamp(2.0, u16::MAX as f64) as u16).collect()
}

/// A triangle in world space with its palette slot.
#[derive(Debug, Clone, Copy)]
struct Triangle {
    corners: [Vec3; 3],
    slot: usize,
}

fn mesh_triangles(vertices: &[Vec3], faces: &[[u32; 3]], slot: usize, out: &mut Vec<Triangle>) {
    out.extend(faces.iter().map(|f| Triangle { corners: f.map(|i| vertices[i as usize]), slot }));
}

fn moved_mesh(mesh: &Mesh, rotation: Mat3, translation: Vec3) -> Vec<Vec3> {
    mesh.vertices.iter().map(|&v| rotation * v + translation).collect()
}

/// The floor tiles and the table, which do not move.
fn static_triangles(centre: Vec3, spread: f32, table: Option<&TableBox>) -> Vec<Triangle> {
    let mut out = Vec::new();
    let tiles = ((FLOOR_REACH + spread) / FLOOR_TILE).ceil() as i32;
    let (first_x, first_z) = (
        (centre.x / FLOOR_TILE).floor() as i32 - tiles,
        (centre.z / FLOOR_TILE).floor() as i32 - tiles,
    );
    for i in first_x..first_x + 2 * tiles {
        for k in first_z..first_z + 2 * tiles {
            let (x0, z0) = (i as f32 * FLOOR_TILE, k as f32 * FLOOR_TILE);
            let (x1, z1) = (x0 + FLOOR_TILE, z0 + FLOOR_TILE);
            let slot = if (i + k).rem_euclid(2) == 0 { FLOOR_LIGHT } else { FLOOR_DARK };
            let corner = |x: f32, z: f32| Vec3::new(x, 0.0, z);
            // Counter-clockwise seen from above.
            out.push(Triangle { corners: [corner(x0, z0), corner(x0, z1), corner(x1, z1)], slot });
            out.push(Triangle { corners: [corner(x0, z0), corner(x1, z1), corner(x1, z0)], slot });
        }
    }
    if let Some(table) = table {
        let top_centre =
            Vec3::new(table.centre.x, table.height - TABLE_TOP_THICKNESS * 0.5, table.centre.y);
        let top = box_mesh(Vec3::new(
            table.half_extents.x,
            TABLE_TOP_THICKNESS * 0.5,
            table.half_extents.y,
        ));
        mesh_triangles(&moved_mesh(&top, Mat3::IDENTITY, top_centre), &top.faces, TABLE, &mut out);
        let leg_height = table.height - TABLE_TOP_THICKNESS;
        let leg =
            box_mesh(Vec3::new(TABLE_LEG_WIDTH * 0.5, leg_height * 0.5, TABLE_LEG_WIDTH * 0.5));
        let inset = table.half_extents - Vec2::splat(TABLE_LEG_WIDTH);
        for (sx, sz) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
            let position = Vec3::new(
                table.centre.x + sx * inset.x,
                leg_height * 0.5,
                table.centre.y + sz * inset.y,
            );
            mesh_triangles(
                &moved_mesh(&leg, Mat3::IDENTITY, position),
                &leg.faces,
                TABLE,
                &mut out,
            );
        }
    }
    out
}

/// A z-buffered image of palette indices.
struct Raster<'a> {
    camera: &'a Camera,
    view: Mat4,
    light: Vec3,
    pixels: Vec<u8>,
    /// Inverse view depth of the nearest surface so far (0: nothing).
    depth: Vec<f32>,
}

impl<'a> Raster<'a> {
    fn new(camera: &'a Camera) -> Self {
        let count = (camera.width * camera.height) as usize;
        Self {
            camera,
            view: camera.view(),
            light: LIGHT.normalize(),
            pixels: vec![colour(BACKGROUND, 1.0); count],
            depth: vec![0.0; count],
        }
    }

    /// Copies the view into an image `width` pixels wide at the camera's origin.
    fn copy_into(&self, image: &mut [u8], width: u32) {
        let (x0, y0) = (self.camera.origin.x as u32, self.camera.origin.y as u32);
        let row = self.camera.width as usize;
        for y in 0..self.camera.height {
            let to = ((y0 + y) * width + x0) as usize;
            image[to..to + row].copy_from_slice(&self.pixels[y as usize * row..][..row]);
        }
    }

    fn draw(&mut self, triangle: &Triangle) {
        let [a, b, c] = triangle.corners;
        let mut normal = (b - a).cross(c - a).normalize_or_zero();
        if normal == Vec3::ZERO {
            return;
        }
        // Lit from the side that faces the camera (meshes of either winding look right).
        if normal.dot(self.camera.eye - a) < 0.0 {
            normal = -normal;
        }
        let light = AMBIENT + (1.0 - AMBIENT) * normal.dot(self.light).max(0.0);
        let index = colour(triangle.slot, light);
        let camera_space = triangle.corners.map(|p| self.view.transform_point3(p));
        // Clip against the near plane (Sutherland-Hodgman on one plane), then fan.
        let mut polygon: Vec<Vec3> = Vec::with_capacity(4);
        for k in 0..3 {
            let (p, q) = (camera_space[k], camera_space[(k + 1) % 3]);
            let (p_in, q_in) = (p.z < -NEAR, q.z < -NEAR);
            if p_in {
                polygon.push(p);
            }
            if p_in != q_in {
                let t = (-NEAR - p.z) / (q.z - p.z);
                polygon.push(p + (q - p) * t);
            }
        }
        for k in 1..polygon.len().saturating_sub(1) {
            self.fill([polygon[0], polygon[k], polygon[k + 1]], index);
        }
    }

    /// Fills a camera-space triangle in front of the near plane.
    fn fill(&mut self, corners: [Vec3; 3], index: u8) {
        let screen = corners.map(|p| self.camera.screen_position(p));
        let [(p0, w0), (p1, w1), (p2, w2)] = screen;
        let edge = |a: Vec2, b: Vec2, p: Vec2| (b - a).perp_dot(p - a);
        let area = edge(p0, p1, p2);
        if area.abs() < 1e-12 {
            return;
        }
        let (width, height) = (self.camera.width as f32, self.camera.height as f32);
        let min = p0.min(p1).min(p2).max(Vec2::ZERO).floor();
        let max = p0.max(p1).max(p2).min(Vec2::new(width - 1.0, height - 1.0)).ceil();
        if min.x > max.x || min.y > max.y {
            return;
        }
        for y in min.y as u32..=max.y as u32 {
            for x in min.x as u32..=max.x as u32 {
                let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                let b0 = edge(p1, p2, p) / area;
                let b1 = edge(p2, p0, p) / area;
                let b2 = edge(p0, p1, p) / area;
                if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                    continue;
                }
                let inverse_depth = b0 * w0 + b1 * w1 + b2 * w2;
                let at = (y * self.camera.width + x) as usize;
                if inverse_depth > self.depth[at] {
                    self.depth[at] = inverse_depth;
                    self.pixels[at] = index;
                }
            }
        }
    }
}

/// Renders every frame of a motion (see the module documentation).
///
/// # Shapes
/// - the motion's `local_rotations`: `[frames * joints]`; `root_positions`: `[frames]`; each
///   exported object's slot: `[frames]` rotations and positions
pub fn render_preview(motion: &ExportMotion<'_>, options: &PreviewOptions) -> Result<Preview> {
    options.check()?;
    let checked = motion.check()?;
    render_checked(&checked, options)
}

fn render_checked(motion: &Checked<'_>, options: &PreviewOptions) -> Result<Preview> {
    let boxes = frame_boxes(motion);
    let (min, max) =
        boxes.iter().fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), &(a, b)| {
            (lo.min(a), hi.max(b))
        });
    let caption_height = if options.caption { caption_band_height() } else { 0 };
    let size = (options.width, options.height);
    let views_of = |framed: (Vec3, Vec3)| {
        [
            Camera::framing(
                framed,
                size,
                (CAMERA_AZIMUTH, CAMERA_ELEVATION),
                Vec2::new(0.0, caption_height as f32),
            ),
            Camera::framing(
                framed,
                size,
                (SIDE_AZIMUTH, SIDE_ELEVATION),
                Vec2::new(options.width as f32, caption_height as f32),
            ),
        ]
    };
    let following = following_boxes(&boxes, (min, max), motion.fps);
    // Following views look along the whole path: the floor reaches past all of it.
    let spread = if following.is_some() { ((max - min) * 0.5).max_element() } else { 0.0 };
    let frame_views: Vec<[Camera; 2]> = match following {
        Some(following) => following.into_iter().map(views_of).collect(),
        None => vec![views_of((min, max)); motion.frames],
    };
    let views = frame_views[0];
    let scenery = static_triangles((min + max) * 0.5, spread, options.table.as_ref());
    let body = DrawnBody::of(motion);
    let rest = motion.skeleton.rest_positions();
    let joints = motion.skeleton.joint_count();
    let states = hand_states(motion)?;
    let (image_width, image_height) = (2 * options.width, caption_height + options.height);
    let frames = (0..motion.frames)
        .into_par_iter()
        .map(|t| {
            let span = t * joints..(t + 1) * joints;
            let posed =
                body.posed(&rest, &motion.fk.rotations[span.clone()], &motion.fk.positions[span]);
            let frame_states = &states[t * joints..(t + 1) * joints];
            let mut moving: Vec<Triangle> = body
                .faces
                .iter()
                .zip(&body.face_bones)
                .map(|(f, bone)| {
                    let slot =
                        bone.map_or(BODY, |(a, b)| frame_states[a].max(frame_states[b]).slot());
                    Triangle { corners: f.map(|i| posed[i as usize]), slot }
                })
                .collect();
            for (k, object) in motion.objects.iter().enumerate() {
                let vertices = moved_mesh(object.mesh, object.rotations[t], object.positions[t]);
                mesh_triangles(&vertices, &object.mesh.faces, object_slot(k), &mut moving);
            }
            let mut image = vec![colour(BACKGROUND, 1.0); (image_width * image_height) as usize];
            for camera in &frame_views[t] {
                let mut raster = Raster::new(camera);
                for triangle in scenery.iter().chain(&moving) {
                    raster.draw(triangle);
                }
                raster.copy_into(&mut image, image_width);
            }
            if options.caption {
                let lines =
                    font::wrap(motion.prompt_at(t), caption_columns(image_width), CAPTION_LINES);
                draw_lines(&mut image, image_width, 0, &lines);
            }
            image
        })
        .collect();
    Ok(Preview {
        width: image_width,
        height: image_height,
        frames,
        delays: frame_delays(motion.frames, motion.fps),
        views,
        frame_views,
        caption_height,
    })
}

/// The body a preview draws, each vertex following up to four joints.
struct DrawnBody<'a> {
    vertices: Cow<'a, [Vec3]>,
    faces: Cow<'a, [[u32; 3]]>,
    /// Per vertex, four joints of the motion's skeleton and their weights.
    joints: Vec<[u16; 4]>,
    weights: Vec<[f32; 4]>,
    /// Per face, the two hand joints whose contact colours it (`None` off the hands).
    face_bones: Vec<Option<(usize, usize)>>,
}

impl<'a> DrawnBody<'a> {
    /// The export's skinned body, or the skeleton's capsules: a capsule face belongs to its
    /// bone, a skinned face to the joint that weighs most on its first corner.
    fn of(motion: &Checked<'a>) -> Self {
        let groups = motion.skeleton.groups();
        let in_hand = |j: usize| groups.left_hand.contains(&j) || groups.right_hand.contains(&j);
        match motion.body {
            Some(body) => {
                let crate::BodySkin { vertices, faces, joints, weights } = body.skin();
                let face_bones = faces
                    .iter()
                    .map(|f| {
                        let corner = f[0] as usize;
                        let strongest = (0..4)
                            .max_by(|&a, &b| weights[corner][a].total_cmp(&weights[corner][b]))
                            .expect("four influences");
                        let joint = usize::from(joints[corner][strongest]);
                        in_hand(joint).then_some((joint, joint))
                    })
                    .collect();
                Self {
                    vertices: Cow::Borrowed(vertices),
                    faces: Cow::Borrowed(faces),
                    joints,
                    weights,
                    face_bones,
                }
            }
            None => {
                let capsules = body_mesh(motion.skeleton);
                let face_bones = capsules
                    .faces
                    .iter()
                    .map(|f| {
                        let (bound, end) = (
                            usize::from(capsules.joints[f[0] as usize]),
                            usize::from(capsules.bone_ends[f[0] as usize]),
                        );
                        (in_hand(bound) && in_hand(end)).then_some((bound, end))
                    })
                    .collect();
                Self {
                    joints: capsules.joints.iter().map(|&j| [j, 0, 0, 0]).collect(),
                    weights: vec![[1.0, 0.0, 0.0, 0.0]; capsules.vertices.len()],
                    vertices: Cow::Owned(capsules.vertices),
                    faces: Cow::Owned(capsules.faces),
                    face_bones,
                }
            }
        }
    }

    /// Vertex positions by linear blend skinning: `v' = sum_k w_k (G_j (v - rest_j) + p_j)`
    /// over each vertex's joints `j`, from their world rotations and positions.
    ///
    /// # Shapes
    /// - `rest_positions`, `rotations`, `positions`: `[joints]`
    fn posed(&self, rest_positions: &[Vec3], rotations: &[Mat3], positions: &[Vec3]) -> Vec<Vec3> {
        self.vertices
            .iter()
            .zip(self.joints.iter().zip(&self.weights))
            .map(|(&v, (joints, weights))| {
                joints
                    .iter()
                    .zip(weights)
                    .filter(|(_, w)| **w != 0.0)
                    .map(|(&j, &w)| {
                        let j = usize::from(j);
                        (rotations[j] * (v - rest_positions[j]) + positions[j]) * w
                    })
                    .sum()
            })
            .collect()
    }
}

/// Per frame, the box of its joints and of its objects (each as far as its mesh reaches).
fn frame_boxes(motion: &Checked<'_>) -> Vec<(Vec3, Vec3)> {
    let joints = motion.skeleton.joint_count();
    let reaches: Vec<f32> = motion
        .objects
        .iter()
        .map(|o| {
            let (low, high) = o.mesh.bounding_box();
            low.abs().max(high.abs()).length()
        })
        .collect();
    (0..motion.frames)
        .map(|t| {
            let mut bounds = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
            for &p in &motion.fk.positions[t * joints..(t + 1) * joints] {
                bounds = (bounds.0.min(p), bounds.1.max(p));
            }
            for (object, reach) in motion.objects.iter().zip(&reaches) {
                let p = object.positions[t];
                bounds =
                    (bounds.0.min(p - Vec3::splat(*reach)), bounds.1.max(p + Vec3::splat(*reach)));
            }
            bounds
        })
        .collect()
}

/// The boxes following views frame, one per frame, when the motion spreads farther than
/// [`FOLLOW_BEYOND_M`] across the floor: the largest frame's box size about each frame's
/// centre averaged over [`FOLLOW_SMOOTHING_S`]. `None` when one view holds it all.
fn following_boxes(
    boxes: &[(Vec3, Vec3)],
    (min, max): (Vec3, Vec3),
    fps: f32,
) -> Option<Vec<(Vec3, Vec3)>> {
    let across = Vec2::new(max.x - min.x, max.z - min.z).length();
    if across <= FOLLOW_BEYOND_M {
        return None;
    }
    let half = boxes.iter().fold(Vec3::ZERO, |h, (a, b)| h.max((*b - *a) * 0.5));
    let centres: Vec<Vec3> = boxes.iter().map(|(a, b)| (*a + *b) * 0.5).collect();
    let reach = ((FOLLOW_SMOOTHING_S * fps * 0.5).round() as usize).max(1);
    Some(
        (0..boxes.len())
            .map(|t| {
                let span = t.saturating_sub(reach)..(t + reach + 1).min(boxes.len());
                let centre = centres[span.clone()].iter().sum::<Vec3>() / span.len() as f32;
                (centre - half, centre + half)
            })
            .collect(),
    )
}

/// Height of the caption band: [`CAPTION_LINES`] lines of the font with margins.
fn caption_band_height() -> u32 {
    let line = (font::GLYPH_HEIGHT * CAPTION_SCALE + CAPTION_LINE_GAP) as u32;
    2 * CAPTION_MARGIN as u32 + CAPTION_LINES as u32 * line - CAPTION_LINE_GAP as u32
}

/// Characters that fit on a caption line of an image `width` pixels wide.
fn caption_columns(width: u32) -> usize {
    (width as usize).saturating_sub(2 * CAPTION_MARGIN) / (font::ADVANCE * CAPTION_SCALE)
}

/// Writes caption lines in the caption colour, the first at the band's top margin, starting
/// `x` pixels from the image's left edge.
fn draw_lines(image: &mut [u8], width: u32, x: usize, lines: &[String]) {
    for (k, line) in lines.iter().enumerate() {
        let y = CAPTION_MARGIN + k * (font::GLYPH_HEIGHT * CAPTION_SCALE + CAPTION_LINE_GAP);
        draw_label(image, width, (x + CAPTION_MARGIN, y), line);
    }
}

/// Writes `text` in the caption colour at the caption's scale with its top-left corner at
/// `(x, y)` of an image `width` pixels wide, clipped to the image.
fn draw_label(image: &mut [u8], width: u32, (x, y): (usize, usize), text: &str) {
    let width = width as usize;
    let height = image.len() / width;
    let ink = colour(CAPTION, 1.0);
    font::draw_text(x, y, text, CAPTION_SCALE, |px, py| {
        if px < width && py < height {
            image[py * width + px] = ink;
        }
    });
}

/// How a hand joint meets the objects on a frame, worst last (what colours the hands of the
/// preview, and of the web page's view).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum JointState {
    /// Farther than [`CONTACT_RADIUS_M`] from every object, or not a hand joint.
    Free,
    /// Within [`CONTACT_RADIUS_M`] of an object's surface.
    Contact,
    /// Deeper than [`PENETRATION_TOLERANCE_M`] inside an object.
    Inside,
}

impl JointState {
    /// The palette slot of a hand bone in this state.
    fn slot(self) -> usize {
        match self {
            Self::Free => BODY,
            Self::Contact => CONTACT,
            Self::Inside => PENETRATION,
        }
    }
}

/// Per frame and joint (`[frames * joints]`), how each hand joint meets the nearest object:
/// inside deeper than [`PENETRATION_TOLERANCE_M`], else within [`CONTACT_RADIUS_M`] of the
/// surface, else free (every other joint is free).
pub(crate) fn hand_states(motion: &Checked<'_>) -> Result<Vec<JointState>> {
    let joints = motion.skeleton.joint_count();
    let groups = motion.skeleton.groups();
    let hands: Vec<usize> = groups.left_hand.iter().chain(&groups.right_hand).copied().collect();
    let queries =
        motion.objects.iter().map(|o| MeshQuery::new(o.mesh)).collect::<Result<Vec<_>, _>>()?;
    let mut states = vec![JointState::Free; motion.frames * joints];
    states.par_chunks_mut(joints).enumerate().for_each(|(t, frame)| {
        for &j in &hands {
            let p = motion.fk.position(t, j);
            let nearest = motion
                .objects
                .iter()
                .zip(&queries)
                .map(|(o, q)| q.signed_distance(o.rotations[t].transpose() * (p - o.positions[t])))
                .fold(f32::INFINITY, f32::min);
            frame[j] = if nearest < -PENETRATION_TOLERANCE_M {
                JointState::Inside
            } else if nearest < CONTACT_RADIUS_M {
                JointState::Contact
            } else {
                JointState::Free
            };
        }
    });
    Ok(states)
}

impl Preview {
    /// `preview.png`'s image as palette indices: the first view at [`SHEET_PANELS`] evenly
    /// spaced frames (the first and the last included) side by side under the caption band
    /// with `text`, each panel labelled with its time at `fps`.
    ///
    /// # Shapes
    /// - returns `(width, height, [height * width] indices)`
    pub fn sheet(&self, text: &str, fps: f32) -> (u32, u32, Vec<u8>) {
        let view = self.views[0];
        let (panel_width, panel_height) = (view.width, view.height);
        let (width, height) =
            (SHEET_PANELS as u32 * panel_width, self.caption_height + panel_height);
        let mut image = vec![colour(BACKGROUND, 1.0); (width * height) as usize];
        let last = self.frames.len().saturating_sub(1);
        for panel in 0..SHEET_PANELS {
            let frame = (panel * last + (SHEET_PANELS - 1) / 2) / (SHEET_PANELS - 1);
            let pixels = &self.frames[frame];
            for y in 0..panel_height {
                let from = ((y + self.caption_height) * self.width) as usize;
                let to = ((y + self.caption_height) * width + panel as u32 * panel_width) as usize;
                image[to..to + panel_width as usize]
                    .copy_from_slice(&pixels[from..from + panel_width as usize]);
            }
            let label = format!("{:.1} s", frame as f32 / fps);
            let y = (height as usize)
                .saturating_sub(CAPTION_MARGIN + font::GLYPH_HEIGHT * CAPTION_SCALE);
            let x = panel * panel_width as usize + CAPTION_MARGIN;
            draw_label(&mut image, width, (x, y), &label);
        }
        if self.caption_height > 0 {
            let lines = font::wrap(text, caption_columns(width), CAPTION_LINES);
            draw_lines(&mut image, width, 0, &lines);
        }
        (width, height, image)
    }

    /// `preview.png`'s bytes (see [`Preview::sheet`]): an RGB PNG.
    pub fn encode_sheet_png(&self, text: &str, fps: f32) -> Result<Vec<u8>> {
        let (width, height, indices) = self.sheet(text, fps);
        let palette = palette();
        let rgb: Vec<u8> = indices.iter().flat_map(|&i| palette[i as usize]).collect();
        encode_rgb_png(width, height, &rgb)
    }
}

/// The PNG of a preview sheet.
fn encode_rgb_png(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>> {
    dex2hoi_plot::encode_rgb_png(width, height, rgb)
        .map_err(|e| ExportError::invalid("PNG encoding", "success", e))
}

/// The bytes of `preview.gif` (see [`render_preview`]).
///
/// # Shapes
/// - as [`render_preview`]
pub fn encode_preview_gif(motion: &ExportMotion<'_>, options: &PreviewOptions) -> Result<Vec<u8>> {
    render_preview(motion, options)?.encode_gif()
}

/// Writes `preview.gif` atomically (see [`render_preview`]).
///
/// # Shapes
/// - as [`render_preview`]
pub fn write_preview_gif(
    path: &Path,
    motion: &ExportMotion<'_>,
    options: &PreviewOptions,
) -> Result<()> {
    let bytes = encode_preview_gif(motion, options)?;
    write_file(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn twenty_fps_is_five_centiseconds_and_thirty_fps_keeps_the_average() {
        assert_eq!(frame_delays(4, 20.0), vec![5, 5, 5, 5]);
        let delays = frame_delays(30, 30.0);
        assert_eq!(delays.iter().map(|&d| d as u32).sum::<u32>(), 100);
        assert!(delays.iter().all(|&d| d == 3 || d == 4));
        assert!(frame_delays(3, 200.0).iter().all(|&d| d == 2));
    }

    #[test]
    fn palette_has_256_entries_and_shades_grow_brighter() {
        let palette = palette();
        assert_eq!(palette.len(), 256);
        let body = &palette[BODY * SHADES..(BODY + 1) * SHADES];
        assert!(body.windows(2).all(|w| w[0].iter().zip(&w[1]).all(|(a, b)| a <= b)));
        assert_eq!(surface_of_slot(colour(BODY, 0.7) as usize / SHADES), Surface::Body);
        assert_eq!(
            surface_of_slot(colour(object_slot(1), 0.2) as usize / SHADES),
            Surface::Object(1)
        );
    }

    #[test]
    fn a_triangle_straddling_the_near_plane_is_clipped_not_dropped() {
        let camera = Camera {
            eye: Vec3::new(0.0, 1.0, 0.0),
            target: Vec3::new(0.0, 1.0, -1.0),
            fov_y: FIELD_OF_VIEW_Y,
            width: 32,
            height: 32,
            origin: Vec2::ZERO,
        };
        let mut raster = Raster::new(&camera);
        // A floor triangle from behind the camera to far in front of it.
        let triangle = Triangle {
            corners: [
                Vec3::new(-5.0, 0.0, 5.0),
                Vec3::new(5.0, 0.0, 5.0),
                Vec3::new(0.0, 0.0, -50.0),
            ],
            slot: FLOOR_LIGHT,
        };
        raster.draw(&triangle);
        // The lower half of the image sees the floor, the upper half the sky.
        let at = |x: u32, y: u32| raster.pixels[(y * 32 + x) as usize] as usize / SHADES;
        assert_eq!(at(16, 30), FLOOR_LIGHT);
        assert_eq!(at(16, 2), BACKGROUND);
    }
}
