"""An `smplx`-style linear blend skinning of a dex2hoi `motion.npz` with an SMPL-X model file, as
`motion.glb` carries the body: shape blend shapes by the npz's `betas`, joints by `J_regressor`,
the four largest skinning weights per vertex renormalised, no pose-corrective blend shapes.
numpy only; used by the export tests and by `blender_check.py`.

Usage: python smplx_lbs.py MODEL.npz MOTION.npz OUT_DIR
writes OUT_DIR/numpy_vertices.npy (T, V, 3) and OUT_DIR/numpy_joints.npy (T, 55, 3).
Exits 3 when numpy is missing.
"""

import os
import sys

try:
    import numpy as np
except ImportError:
    sys.exit(3)


def smplx_lbs(model_path, d):
    """(T, V, 3) vertices of the npz's parameters skinned with the model, the shaped rest
    vertices (V, 3) and the posed joints (T, 55, 3)."""
    m = np.load(model_path)
    betas = d["betas"][0].astype(np.float64)
    dirs = m["shapedirs"].astype(np.float64)
    n = min(len(betas), dirs.shape[2])
    v = m["v_template"].astype(np.float64) + dirs[:, :, :n] @ betas[:n]
    J = m["J_regressor"].astype(np.float64) @ v
    parents = m["kintree_table"][0].astype(np.int64)
    parents[parents > 54] = -1
    T = d["transl"].shape[0]
    pose = np.concatenate(
        [d["global_orient"][:, None], d["body_pose"].reshape(T, 21, 3), d["jaw_pose"][:, None],
         d["leye_pose"][:, None], d["reye_pose"][:, None], d["left_hand_pose"].reshape(T, 15, 3),
         d["right_hand_pose"].reshape(T, 15, 3)], axis=1).astype(np.float64)
    angle = np.linalg.norm(pose, axis=-1, keepdims=True)
    axis = pose / np.maximum(angle, 1e-12)
    K = np.zeros(pose.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -axis[..., 2], axis[..., 1], -axis[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    s, c = np.sin(angle)[..., None], np.cos(angle)[..., None]
    R = np.eye(3) + s * K + (1 - c) * (K @ K)
    G = np.zeros((T, 55, 4, 4))
    for j in range(55):
        local = np.zeros((T, 4, 4))
        local[:, :3, :3], local[:, 3, 3] = R[:, j], 1
        local[:, :3, 3] = J[j] - (J[parents[j]] if parents[j] >= 0 else 0)
        G[:, j] = local if parents[j] < 0 else G[:, parents[j]] @ local
    A = G.copy()
    A[:, :, :3, 3] -= np.einsum("tjab,jb->tja", G[:, :, :3, :3], J)
    W = m["weights"].astype(np.float64)
    top = np.argsort(-W, axis=1, kind="stable")[:, :4]
    kept = np.zeros_like(W)
    rows = np.arange(W.shape[0])[:, None]
    kept[rows, top] = W[rows, top]
    kept /= kept.sum(axis=1, keepdims=True)
    blend = np.einsum("vj,tjab->tvab", kept, A)
    verts = np.einsum("tvab,vb->tva", blend[..., :3, :3], v) + blend[..., :3, 3]
    transl = d["transl"][:, None].astype(np.float64)
    return verts + transl, v, G[:, :, :3, 3] + transl


if __name__ == "__main__":
    model, motion, out = sys.argv[1:4]
    vertices, _, joints = smplx_lbs(model, np.load(motion))
    np.save(os.path.join(out, "numpy_vertices.npy"), vertices)
    np.save(os.path.join(out, "numpy_joints.npy"), joints)
    print("numpy LBS:", vertices.shape)
