"""glTF 2.0 binary (``.glb``) export: the fitted body as one skinned mesh with a 24-joint rig.

Built with ``pygltflib``. Layout:

- node 0 ``body``: the mesh, skinned by skin 0 (a scene root, as glTF wants skinned
  meshes); nodes 1..24: SMPL's joints by name (``pelvis`` ... ``right_hand``), node 1 the
  other scene root. Each joint's ``translation`` is its bone in the fitted shape's rest
  pose (child minus parent rest joint; the pelvis: its rest position), so the skeleton
  has the fitted bone lengths. Node rotations hold frame 0's pose.
- mesh: the fitted shape in the rest pose (T-pose, y up, metres), smooth normals,
  ``JOINTS_0``/``WEIGHTS_0`` the body model's 4 largest skinning weights per vertex,
  renormalised (SMPL's weights have up to 6; the 4 largest carry >= 96.6 % of every
  vertex of the default body). Inverse bind matrices translate each rest joint to the
  origin (the rest pose has identity rotations).
- animation ``motion``: ``LINEAR`` keys at ``k / fps`` seconds (a variable-rate video's own times
  where given), one per video frame: each
  joint's local rotation (unit quaternion ``x, y, z, w``, kept in one hemisphere frame
  to frame) and the pelvis's translation.

Forward kinematics of the file gives the fitted joints exactly (up to float32). Vertices
differ from the fitted mesh by what skinning cannot express: SMPL's pose-corrective blend
shapes and the weights beyond the 4th (a few millimetres). About ``16 x 24 + 16`` bytes
per frame: 0.7 MB per minute at 30 fps, plus about 0.8 MB for the mesh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowmocap.errors import InputError
from flowmocap.export.glb import BODY_COLOUR, GltfBuffer, save_glb, vertex_normals

__all__ = ["write_skinned_glb", "skin_influences", "read_skinned_glb", "glb_joint_positions"]

def skin_influences(weights: np.ndarray, count: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` largest skinning weights per vertex, renormalised to sum 1.

    Args:
        weights: ``(V, J)`` non-negative skinning weights (rows sum to 1).
        count: influences kept per vertex.

    Returns:
        ``joints (V, count)`` uint8 (or uint16 for J > 255) joint indices, and
        ``weights (V, count)`` float32 summing to 1 within float32 rounding; unused slots
        have weight 0 and joint 0.
    """
    w = np.asarray(weights, np.float64)
    if w.ndim != 2 or w.shape[1] < count:
        raise InputError(f"skinning weights must have shape (V, J >= {count}); got {w.shape}.")
    order = np.argsort(-w, axis=1, kind="stable")[:, :count]
    top = np.clip(np.take_along_axis(w, order, axis=1), 0.0, None)
    total = top.sum(1, keepdims=True)
    if np.any(total <= 0):
        raise InputError("a vertex has no positive skinning weight; the model's weights are broken.")
    top = (top / total).astype(np.float32)
    top[:, 0] += np.float32(1.0) - top.sum(1, dtype=np.float32)  # float32 sum exactly 1 where possible
    order = np.where(top > 0, order, 0)  # glTF: unused slots carry joint 0
    return order.astype(np.uint8 if w.shape[1] <= 255 else np.uint16), top


def _quaternions(poses: np.ndarray) -> np.ndarray:
    """``(T, 24, 4)`` float32 ``x, y, z, w`` of ``(T, 72)`` axis-angle, sign-continuous in time."""
    from scipy.spatial.transform import Rotation

    T = poses.shape[0]
    q = Rotation.from_rotvec(poses.reshape(-1, 3)).as_quat().reshape(T, 24, 4)
    for k in range(1, T):
        flip = np.sum(q[k] * q[k - 1], axis=1) < 0
        q[k, flip] *= -1
    return q.astype(np.float32)


def write_skinned_glb(path: str | Path, poses: np.ndarray, trans: np.ndarray, rest_vertices: np.ndarray,
                      rest_joints: np.ndarray, faces: np.ndarray, weights: np.ndarray, fps: float,
                      extras: dict | None = None, times: np.ndarray | None = None) -> Path:
    """Write a fitted motion as a skinned, animated ``.glb`` (see the module docstring).

    Args:
        path: output file.
        poses: ``(T, 72)`` axis-angle radians (SMPL joint order, y-up frame).
        trans: ``(T, 3)`` SMPL translation in metres (the pelvis is at ``rest_joints[0] + trans``).
        rest_vertices: ``(V, 3)`` the fitted shape's rest-pose vertices, metres.
        rest_joints: ``(24, 3)`` its rest-pose joints, metres.
        faces: ``(F, 3)`` triangles, counter-clockwise seen from outside.
        weights: ``(V, 24)`` skinning weights.
        fps: frames per second (Hz) of the keys (at ``k / fps`` seconds unless ``times`` is given).
        times: ``(T,)`` increasing seconds of the keys, e.g. a variable-rate video's own time
            stamps from the first frame; None: ``k / fps``.
        extras: JSON-able dict stored as the scene's ``extras`` (e.g. the camera).

    Returns:
        The path written.
    """
    import pygltflib as g

    from flowmocap.body.skeleton import JOINT_NAMES, PARENTS

    poses = np.asarray(poses, np.float64).reshape(-1, 72)
    trans = np.asarray(trans, np.float64).reshape(-1, 3)
    T = poses.shape[0]
    if T < 1:
        raise InputError("a glb needs at least one frame.")
    if trans.shape[0] != T:
        raise InputError(f"poses have {T} frames but trans {trans.shape[0]}.")
    if not np.all(np.isfinite(poses)) or not np.all(np.isfinite(trans)):
        raise InputError("the motion contains NaN or infinite values; it cannot be exported.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    rv = np.asarray(rest_vertices, np.float64).reshape(-1, 3)
    rj = np.asarray(rest_joints, np.float64).reshape(24, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    joints_idx, w4 = skin_influences(weights)

    gltf = g.GLTF2(asset=g.Asset(generator="flowmocap", version="2.0"))
    blob = GltfBuffer(gltf)
    pos = blob.add(rv.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, bounds=True)
    nor = blob.add(vertex_normals(rv, faces).astype(np.float32), g.VEC3, g.ARRAY_BUFFER)
    jnt = blob.add(joints_idx, g.VEC4, g.ARRAY_BUFFER)
    wgt = blob.add(w4, g.VEC4, g.ARRAY_BUFFER)
    idx = blob.add(faces.astype(np.uint32).reshape(-1), g.SCALAR, g.ELEMENT_ARRAY_BUFFER)
    ibm = np.tile(np.eye(4, dtype=np.float32), (24, 1, 1))
    ibm[:, :3, 3] = -rj
    ibm_acc = blob.add(np.ascontiguousarray(ibm.transpose(0, 2, 1)).reshape(24, 16), g.MAT4)  # column-major

    quats = _quaternions(poses)
    root_pos = (rj[0] + trans).astype(np.float32)
    nodes = [g.Node(name="body", mesh=0, skin=0)]
    for j in range(24):
        local = rj[j] - (rj[PARENTS[j]] if j else 0.0)
        if j == 0:
            local = root_pos[0]
        nodes.append(g.Node(name=JOINT_NAMES[j], translation=[float(v) for v in local],
                            rotation=[float(v) for v in quats[0, j]],
                            children=[c + 1 for c in range(24) if PARENTS[c] == j and c > 0]))
    gltf.nodes = nodes
    gltf.meshes = [g.Mesh(name="body", primitives=[g.Primitive(
        attributes=g.Attributes(POSITION=pos, NORMAL=nor, JOINTS_0=jnt, WEIGHTS_0=wgt), indices=idx, material=0)])]
    gltf.materials = [g.Material(name="body", doubleSided=False, pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=list(BODY_COLOUR), metallicFactor=0.0, roughnessFactor=0.8))]
    gltf.skins = [g.Skin(name="smpl24", inverseBindMatrices=ibm_acc, skeleton=1, joints=list(range(1, 25)))]

    if times is None:
        key_times = np.arange(T) / fps
    else:
        key_times = np.asarray(times, np.float64).reshape(-1)
        if key_times.shape != (T,) or not np.isfinite(key_times).all() or (np.diff(key_times) <= 0).any():
            raise InputError(f"times must be ({T},) increasing finite seconds, one per frame; got shape "
                             f"{key_times.shape}.")
    times = blob.add(key_times.astype(np.float32), g.SCALAR, bounds=True, name="time")
    samplers, channels = [], []
    for j in range(24):
        out = blob.add(np.ascontiguousarray(quats[:, j]), g.VEC4, name=f"{JOINT_NAMES[j]}.rotation")
        samplers.append(g.AnimationSampler(input=times, output=out, interpolation="LINEAR"))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=j + 1, path="rotation")))
    out = blob.add(root_pos, g.VEC3, name="pelvis.translation")
    samplers.append(g.AnimationSampler(input=times, output=out, interpolation="LINEAR"))
    channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                       target=g.AnimationChannelTarget(node=1, path="translation")))
    gltf.animations = [g.Animation(name="motion", samplers=samplers, channels=channels)]
    gltf.scenes = [g.Scene(name="flowmocap", nodes=[0, 1],
                           extras={"fps": float(fps), "frames": T, **(extras or {})})]
    gltf.scene = 0
    return save_glb(gltf, blob, path)


def read_skinned_glb(path: str | Path):
    """Read a ``.glb`` with pygltflib; returns the ``GLTF2`` document and an accessor reader
    ``read(index) -> np.ndarray`` (shape ``(count, components)``; MAT4 as ``(count, 4, 4)``
    row-major)."""
    import pygltflib as g

    gltf = g.GLTF2().load(str(path))
    blob = gltf.binary_blob()
    dtypes = {g.FLOAT: np.float32, g.UNSIGNED_INT: np.uint32, g.UNSIGNED_SHORT: np.uint16, g.UNSIGNED_BYTE: np.uint8}
    sizes = {g.SCALAR: 1, g.VEC2: 2, g.VEC3: 3, g.VEC4: 4, g.MAT4: 16}

    def read(index: int) -> np.ndarray:
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        n = sizes[acc.type]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        a = np.frombuffer(blob, dtype=dtypes[acc.componentType], count=acc.count * n, offset=start)
        a = a.reshape(acc.count, n)
        if acc.type == g.MAT4:
            a = a.reshape(acc.count, 4, 4).transpose(0, 2, 1)
        return a

    return gltf, read


def glb_joint_positions(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions at every key of a skinned ``.glb``, by forward kinematics of its nodes.

    Reads the first skin's joints and the first animation; nodes without an animated
    channel keep their own translation/rotation. Independent of :func:`write_skinned_glb`
    (it only uses the file).

    Returns:
        ``times (K,)`` seconds and ``positions (K, J, 3)`` metres, float64, in skin joint order.
    """
    from scipy.spatial.transform import Rotation

    gltf, read = read_skinned_glb(path)
    skin = gltf.skins[0]
    anim = gltf.animations[0]
    times = None
    tracks: dict[tuple[int, str], np.ndarray] = {}
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        t = read(s.input)[:, 0].astype(np.float64)
        times = t if times is None else times
        if not np.array_equal(t, times):
            raise InputError("the animation's channels have different key times; resample them first.")
        tracks[(ch.target.node, ch.target.path)] = read(s.output).astype(np.float64)
    K = len(times)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    world: dict[int, np.ndarray] = {}

    def transform(i: int) -> np.ndarray:
        if i in world:
            return world[i]
        n = gltf.nodes[i]
        tr = tracks.get((i, "translation"), np.tile(np.asarray(n.translation or [0, 0, 0], np.float64), (K, 1)))
        q = tracks.get((i, "rotation"), np.tile(np.asarray(n.rotation or [0, 0, 0, 1], np.float64), (K, 1)))
        M = np.tile(np.eye(4), (K, 1, 1))
        M[:, :3, :3] = Rotation.from_quat(q).as_matrix()
        M[:, :3, 3] = tr
        if i in parent:
            M = transform(parent[i]) @ M
        world[i] = M
        return M

    pos = np.stack([transform(j)[:, :3, 3] for j in skin.joints], axis=1)
    return times, pos
