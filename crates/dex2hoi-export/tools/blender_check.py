"""Imports dex2hoi's motion.glb and motion.bvh into Blender (the `bpy` module, headless) and
compares what Blender plays with motion.npz.

- glTF: every armature bone's head (world) at the given frames against the npz `joints`
  (bones matched by name to `joint_names`, as the rig names them); each object's world
  position and rotation against `object_translations` / `object_rotations`; with --model, the
  skinned mesh's vertices (Blender's own armature deformation) against an `smplx`-style linear
  blend skinning of the npz's parameters with that model file (the four largest weights per
  vertex, no pose blend shapes, as motion.glb carries it); with --character, the skinned mesh
  against a linear blend skinning of that character file (read by Blender's importer) by the
  npz's pose (`character_lbs.py`).
- BVH: every bone's head against the npz `joints`.

Blender is Z up; our files are Y up, and both importers turn Y up into Z up the same way:
Blender (x, y, z) = ours (x, -z, y).

Usage: python blender_check.py EXPORT_DIR [--model SMPLX.npz | --character CHARACTER.glb]
       [--frames 0,3,6]
Prints one JSON object (errors in metres and radians); exits 1 on a broken import.
"""

import argparse
import json
import os
import sys

import bpy
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from character_lbs import character_lbs  # noqa: E402  (beside this script)
from smplx_lbs import smplx_lbs  # noqa: E402


def to_ours(v):
    return np.array([v[0], v[2], -v[1]], dtype=np.float64)


# Blender rotation matrix -> ours: C R C^T with C the axis change above.
C = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])


def fresh_scene(fps):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    # Blender keys frames at time * fps; an integer rate keeps key k on frame k.
    scene.render.fps = int(round(fps))
    scene.render.fps_base = scene.render.fps / fps
    return scene


def armature(kind):
    arms = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    if len(arms) != 1:
        sys.exit(f"{kind}: expected one armature, found {len(arms)}")
    return arms[0]


def bone_heads(arm, names):
    """World bone heads (ours) of the named bones, in `names` order."""
    out = []
    for name in names:
        bone = arm.pose.bones.get(name)
        if bone is None:
            sys.exit(f"no bone {name!r} in the imported armature")
        out.append(to_ours(arm.matrix_world @ bone.head))
    return np.array(out)


def posed_vertices(mesh_object):
    """The skinned mesh's vertices (ours) as Blender deforms them on the current frame."""
    evaluated = mesh_object.evaluated_get(bpy.context.evaluated_depsgraph_get())
    posed = np.array([to_ours(evaluated.matrix_world @ v.co) for v in evaluated.to_mesh().vertices])
    evaluated.to_mesh_clear()
    return posed


def check_glb(path, d, frames, model, character):
    names = [str(n) for n in d["joint_names"]]
    if str(d["skeleton"]) == "mixamo65":
        names = ["mixamorig:" + n for n in names]
    if character:
        fresh_scene(float(d["fps"]))
        character_posed, character_rest = character_lbs(character, d, frames)
    scene = fresh_scene(float(d["fps"]))
    bpy.ops.import_scene.gltf(filepath=path)
    arm = armature("glTF")
    result = {"bones": len(arm.pose.bones), "joint_error": 0.0}
    objects = [str(n) for n in d["object_names"]]
    result["object_position_error"] = 0.0
    result["object_rotation_error"] = 0.0
    skinned = [o for o in bpy.data.objects if o.type == "MESH" and o.find_armature() is arm]
    if model:
        reference, rest, _ = smplx_lbs(model, d)
        mesh_object = skinned[0]
        # The importer keeps the primitive's vertex order (merge_vertices is off): check it on
        # the rest mesh, where coincident vertices of different bones would fool a search.
        rest_blender = np.array([to_ours(mesh_object.matrix_world @ v.co)
                                 for v in mesh_object.data.vertices])
        if rest_blender.shape != rest.shape or np.abs(rest_blender - rest).max() > 1e-5:
            sys.exit("glTF: the imported rest mesh is not the model's shaped template in order")
        order = np.arange(len(rest))
        result["mesh_vertices"] = len(order)
        result["mesh_error"] = 0.0
    if character:
        mesh_object = skinned[0]
        rest_blender = np.array([to_ours(mesh_object.matrix_world @ v.co)
                                 for v in mesh_object.data.vertices])
        if rest_blender.shape != character_rest.shape:
            sys.exit(f"glTF: {len(rest_blender)} vertices, the character has "
                     f"{len(character_rest)}")
        result["mesh_vertices"] = len(rest_blender)
        result["rest_mesh_error"] = float(np.abs(rest_blender - character_rest).max())
        result["mesh_error"] = 0.0
    for t in frames:
        scene.frame_set(t)
        heads = bone_heads(arm, names)
        result["joint_error"] = max(result["joint_error"],
                                    float(np.abs(heads - d["joints"][t]).max()))
        for k, name in enumerate(objects):
            obj = bpy.data.objects.get(name)
            if obj is None:
                sys.exit(f"glTF: no object {name!r}")
            world = np.array(obj.matrix_world)
            position = to_ours(world[:3, 3])
            rotation = C @ world[:3, :3] @ C.T
            result["object_position_error"] = max(
                result["object_position_error"],
                float(np.abs(position - d["object_translations"][k, t]).max()))
            relative = rotation.T @ d["object_rotations"][k, t].astype(np.float64)
            # atan2 of the skew and symmetric parts stays accurate near zero (arccos does not).
            skew = np.array([relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0],
                             relative[1, 0] - relative[0, 1]])
            angle = np.arctan2(np.linalg.norm(skew), np.trace(relative) - 1)
            result["object_rotation_error"] = max(result["object_rotation_error"], float(angle))
        if model or character:
            expected = reference[t][order] if model else character_posed[t]
            result["mesh_error"] = max(result["mesh_error"],
                                       float(np.abs(posed_vertices(mesh_object) - expected).max()))
    return result


def check_bvh(path, d, frames):
    names = [str(n) for n in d["joint_names"]]
    if str(d["skeleton"]) == "mixamo65":
        names = ["mixamorig:" + n for n in names]
    scene = fresh_scene(float(d["fps"]))
    bpy.ops.import_anim.bvh(filepath=path, global_scale=1.0, frame_start=0, use_fps_scale=False,
                            update_scene_fps=False, rotate_mode="NATIVE", axis_forward="-Z",
                            axis_up="Y")
    arm = armature("BVH")
    # The importer keys BVH frame i at its first key + i (frame_start + 1 in Blender 4.2).
    first = min(k.co[0] for c in arm.animation_data.action.fcurves for k in c.keyframe_points)
    result = {"bones": len(arm.pose.bones), "joint_error": 0.0, "first_key": first}
    for t in frames:
        scene.frame_set(int(first) + t)
        heads = bone_heads(arm, names)
        result["joint_error"] = max(result["joint_error"],
                                    float(np.abs(heads - d["joints"][t]).max()))
    return result


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("export_dir")
    parser.add_argument("--model")
    parser.add_argument("--character")
    parser.add_argument("--frames", default="0")
    args = parser.parse_args()
    d = np.load(os.path.join(args.export_dir, "motion.npz"))
    frames = [int(f) for f in args.frames.split(",")]
    report = {
        "blender": bpy.app.version_string,
        "skeleton": str(d["skeleton"]),
        "frames": frames,
        "glb": check_glb(os.path.join(args.export_dir, "motion.glb"), d, frames, args.model,
                         args.character),
        "bvh": check_bvh(os.path.join(args.export_dir, "motion.bvh"), d, frames),
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
