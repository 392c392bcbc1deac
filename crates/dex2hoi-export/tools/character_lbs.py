"""A linear blend skinning of a Mixamo character by a dex2hoi `motion.npz`, the reference
`blender_check.py --character` holds motion.glb's skinned character against.

The character file is read by Blender's own glTF importer (not by dex2hoi): its skinned meshes
in the file's node order, each vertex at rest with its vertex-group weights by bone name, and
the bones' parents. The pose is the npz's alone: joint j turns the points bound to it by its
world rotation G_j (the product of `local_rotations` down the `parents` chain, relative to the
rest pose) about its rest position (from `rest_offsets`) and carries them to `joints`:
x -> G_j (x - rest_j) + joints_j. A bone of the character that the motion lacks moves with its
nearest ancestor that the motion has.

Blender is Z up; ours is Y up: Blender (x, y, z) = ours (x, -z, y).
"""

import json
import struct

import bpy
import numpy as np

PREFIX = "mixamorig:"


def to_ours(v):
    return np.array([v[0], v[2], -v[1]], dtype=np.float64)


def skinned_node_names(path):
    """Names of the nodes that carry a skinned mesh, in the file's node order."""
    with open(path, "rb") as f:
        data = f.read()
    length = struct.unpack("<I", data[12:16])[0]
    document = json.loads(data[20:20 + length])
    meshes = document.get("meshes", [])

    def skinned(node):
        if "mesh" not in node or "skin" not in node:
            return False
        primitives = meshes[node["mesh"]]["primitives"]
        return all("JOINTS_0" in p["attributes"] for p in primitives)

    return [n.get("name", "") for n in document["nodes"] if skinned(n)]


def character_lbs(path, d, frames):
    """Posed vertices at `frames` (dict frame -> (V, 3)) and the (V, 3) rest vertices of the
    character in `path` skinned by the npz `d`. Leaves the character imported in the current
    Blender scene."""
    bpy.ops.import_scene.gltf(filepath=path)
    arms = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    if len(arms) != 1:
        raise SystemExit(f"character: expected one armature, found {len(arms)}")
    arm = arms[0]
    arm.data.pose_position = "REST"
    depsgraph = bpy.context.evaluated_depsgraph_get()
    names = [str(n) for n in d["joint_names"]]
    index = {n: j for j, n in enumerate(names)}

    def joint_of(bone_name):
        """Our joint that moves the bone: its own, else its nearest ancestor's."""
        bone = arm.data.bones.get(bone_name)
        while bone is not None:
            bare = bone.name[len(PREFIX):] if bone.name.startswith(PREFIX) else bone.name
            if bare in index:
                return index[bare]
            bone = bone.parent
        raise SystemExit(f"character: bone {bone_name!r} has no ancestor the motion drives")

    rest_vertices, weights = [], []
    for name in skinned_node_names(path):
        obj = bpy.data.objects.get(name)
        if obj is None or obj.type != "MESH":
            raise SystemExit(f"character: no imported mesh object {name!r}")
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        rest_vertices += [to_ours(evaluated.matrix_world @ v.co) for v in mesh.vertices]
        evaluated.to_mesh_clear()
        groups = [joint_of(g.name) for g in obj.vertex_groups]
        for v in obj.data.vertices:
            row = np.zeros(len(names))
            for g in v.groups:
                row[groups[g.group]] += g.weight
            if row.sum() <= 0:
                raise SystemExit(f"character: vertex {v.index} of {name!r} has no weight")
            weights.append(row / row.sum())
    rest = np.array(rest_vertices)
    W = np.array(weights)
    # The npz's pose: world rotations down the tree, rest positions from the offsets.
    parents = d["parents"].astype(np.int64)
    offsets = d["rest_offsets"].astype(np.float64)
    local = d["local_rotations"].astype(np.float64)
    T, J = local.shape[:2]
    G = np.zeros((T, J, 3, 3))
    rest_joints = np.zeros((J, 3))
    for j in range(J):
        p = parents[j]
        G[:, j] = local[:, j] if p < 0 else G[:, p] @ local[:, j]
        rest_joints[j] = offsets[j] + (rest_joints[p] if p >= 0 else 0)
    joints = d["joints"].astype(np.float64)
    posed = {}
    for t in frames:
        # x -> G_j (x - rest_j) + joints_j, blended by the weights.
        moved = np.einsum("jab,vjb->vja", G[t], rest[:, None, :] - rest_joints[None]) + joints[t]
        posed[t] = np.einsum("vj,vja->va", W, moved)
    return posed, rest
