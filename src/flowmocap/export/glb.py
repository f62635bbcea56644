"""glTF 2.0 binary (``.glb``) export: the fitted body as an animated mesh sequence.

One node per frame, each with its own mesh (positions and smooth normals; the triangle
indices are stored once and shared), under one root node ``flowmocap``. One animation
``motion`` switches the frames on and off with step-interpolated ``scale`` keys (frame
``k`` has scale 1 from ``k / fps`` to ``(k + 1) / fps`` and 0 otherwise), the usual way
to play a mesh sequence in Blender, three.js and other glTF viewers. Viewers without
animation show frame 0. Vertices are exact (pose correctives included), at the cost of
about ``24 V`` bytes per frame. glTF is y up, metres, like the export frames. Built with
``pygltflib``; :class:`GltfBuffer` and :func:`save_glb` are shared with the skinned export
(:mod:`flowmocap.export.gltf_skin`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flowmocap.atomic import atomic_write
from flowmocap.errors import InputError
from flowmocap.render.shade import vertex_normals  # the shading's: area-weighted, unit length

__all__ = ["write_mesh_sequence_glb", "GltfBuffer", "vertex_normals", "save_glb"]

BODY_COLOUR = (0.62, 0.68, 0.78, 1.0)


class GltfBuffer:
    """Buffer views and accessors of a document's one binary buffer, built with pygltflib.

    ``add(array, kind)`` appends a C-contiguous float32/uint32/uint16/uint8 array (4-byte
    aligned) as a buffer view and an accessor of glTF type ``kind`` (``"SCALAR"``,
    ``"VEC3"``, ``"VEC4"``, ``"MAT4"``) and returns the accessor's index; ``bounds`` adds
    the ``min``/``max`` that glTF requires for positions and animation inputs.
    Construct with the ``pygltflib.GLTF2`` document the views and accessors go into.
    """

    def __init__(self, gltf):
        self.gltf = gltf
        self.data = bytearray()

    def add(self, array: np.ndarray, kind: str, target: int | None = None, bounds: bool = False,
            name: str | None = None) -> int:
        """Add ``array`` (first axis: the accessor's count) in a buffer view of its own.

        Args:
            array: ``(count,)`` or ``(count, k)``, ``k`` components per element (16 for
                ``"MAT4"``, column-major); float32, uint32, uint16 or uint8.
            kind: glTF accessor type, e.g. ``"SCALAR"``, ``"VEC3"``, ``"MAT4"``.
            target: glTF buffer-view target (e.g. ``ARRAY_BUFFER``), or None.
            bounds: add the accessor's per-component ``min``/``max``.
            name: the accessor's name.

        Returns:
            The accessor's index.
        """
        import pygltflib as g

        array = np.ascontiguousarray(array)
        component = {np.dtype(np.float32): g.FLOAT, np.dtype(np.uint32): g.UNSIGNED_INT,
                     np.dtype(np.uint16): g.UNSIGNED_SHORT, np.dtype(np.uint8): g.UNSIGNED_BYTE}[array.dtype]
        self.data += b"\0" * ((-len(self.data)) % 4)
        self.gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(self.data), byteLength=array.nbytes,
                                                  target=target))
        self.data += array.tobytes()
        count = array.shape[0]
        acc = g.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component, count=int(count),
                         type=kind, name=name)
        if bounds:
            flat = array.reshape(count, -1).astype(np.float64)
            acc.min = flat.min(0).tolist()
            acc.max = flat.max(0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1


def save_glb(gltf, buffer: GltfBuffer, path: str | Path) -> Path:
    """Attach ``buffer`` as the document's binary chunk and write ``path`` as ``.glb``
    (atomically: an interrupted write leaves the old file, or none, never part of one)."""
    import pygltflib as g

    buffer.data += b"\0" * ((-len(buffer.data)) % 4)
    gltf.buffers = [g.Buffer(byteLength=len(buffer.data))]
    gltf.set_binary_blob(bytes(buffer.data))
    path = Path(path)
    data = b"".join(gltf.save_to_bytes())
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))  # never a cut-off .glb under the final name
    return path


def write_mesh_sequence_glb(path: str | Path, frames, faces: np.ndarray, fps: float, num_frames: int,
                            progress: bool = False) -> Path:
    """Write an animated mesh sequence as ``.glb`` (see the module docstring).

    Args:
        path: output file.
        frames: iterable of ``(V, 3)`` vertex arrays in metres (y up), ``num_frames`` of them.
        faces: ``(F, 3)`` triangle indices, counter-clockwise seen from outside.
        fps: frames per second (Hz).
        num_frames: the number of arrays ``frames`` yields.
        progress: show a progress bar.

    Returns:
        The path written.
    """
    import pygltflib as g
    from tqdm import tqdm

    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if num_frames < 1:
        raise InputError("a glb needs at least one frame.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    gltf = g.GLTF2(asset=g.Asset(generator="flowmocap", version="2.0"))
    b = GltfBuffer(gltf)
    indices = b.add(faces.astype(np.uint32).reshape(-1), g.SCALAR, g.ELEMENT_ARRAY_BUFFER, bounds=True)
    nodes = [g.Node(name="flowmocap")]
    samplers, channels = [], []
    n = 0
    for k, verts in enumerate(tqdm(frames, total=num_frames, disable=not progress, unit="frame", desc="glb")):
        v = np.asarray(verts, np.float64)
        pos = b.add(v.astype(np.float32), g.VEC3, g.ARRAY_BUFFER, bounds=True)
        nor = b.add(vertex_normals(v, faces).astype(np.float32), g.VEC3, g.ARRAY_BUFFER)
        gltf.meshes.append(g.Mesh(name=f"frame_{k:06d}", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=pos, NORMAL=nor), indices=indices, material=0)]))
        nodes.append(g.Node(name=f"frame_{k:06d}", mesh=k, scale=[1.0, 1.0, 1.0] if k == 0 else [0.0, 0.0, 0.0]))
        on, off = k / fps, (k + 1) / fps
        times = ([0.0] if k > 0 else []) + [on] + ([off] if k < num_frames - 1 else [])
        scales = ([0.0] if k > 0 else []) + [1.0] + ([0.0] if k < num_frames - 1 else [])
        t_acc = b.add(np.asarray(times, np.float32), g.SCALAR, bounds=True)
        s_acc = b.add(np.repeat(np.asarray(scales, np.float32)[:, None], 3, axis=1), g.VEC3)
        samplers.append(g.AnimationSampler(input=t_acc, output=s_acc, interpolation="STEP"))
        channels.append(g.AnimationChannel(sampler=len(samplers) - 1,
                                           target=g.AnimationChannelTarget(node=k + 1, path="scale")))
        n += 1
    if n != num_frames:
        raise InputError(f"expected {num_frames} frames, got {n}.")
    nodes[0].children = list(range(1, n + 1))
    gltf.nodes = nodes
    gltf.materials = [g.Material(name="body", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=list(BODY_COLOUR), metallicFactor=0.0, roughnessFactor=0.8))]
    gltf.animations = [g.Animation(name="motion", channels=channels, samplers=samplers)]
    gltf.scenes = [g.Scene(nodes=[0], extras={"fps": float(fps), "frames": n, "duration_s": n / fps})]
    gltf.scene = 0
    return save_glb(gltf, b, path)
