"""glTF 2.0 binary (``.glb``) export: the fitted body as an animated mesh sequence.

One node per frame, each with its own mesh (positions and smooth normals; the triangle
indices are stored once and shared), under one root node ``flowmocap``. One animation
``motion`` switches the frames on and off with step-interpolated ``scale`` keys (frame
``k`` has scale 1 from ``k / fps`` to ``(k + 1) / fps`` and 0 otherwise), the usual way
to play a mesh sequence in Blender, three.js and other glTF viewers. Viewers without
animation show frame 0. Vertices are exact (pose correctives included), at the cost of
about ``24 V`` bytes per frame. glTF is y up, metres, like the ``"up"`` export frame.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from flowmocap.errors import InputError

__all__ = ["write_mesh_sequence_glb"]

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class _Builder:
    """Accumulates buffer views and accessors of one binary buffer."""

    def __init__(self):
        self.chunks: list[bytes] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            bounds: bool = False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        pad = (-self.size) % 4
        if pad:
            self.chunks.append(b"\0" * pad)
            self.size += pad
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.views.append(view)
        self.chunks.append(data)
        self.size += len(data)
        count = array.shape[0] if kind != "SCALAR" or array.ndim == 1 else array.size
        acc = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(count), "type": kind}
        if bounds:
            flat = array.reshape(int(count), -1)
            acc["min"] = flat.min(0).astype(float).tolist()
            acc["max"] = flat.max(0).astype(float).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        data = b"".join(self.chunks)
        return data + b"\0" * ((-len(data)) % 4)


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    n = np.zeros_like(verts)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


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
    from tqdm import tqdm

    faces = np.asarray(faces, np.uint32).reshape(-1, 3)
    if num_frames < 1:
        raise InputError("a glb needs at least one frame.")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps}.")
    b = _Builder()
    indices = b.add(faces.reshape(-1), _UINT, "SCALAR", _ELEMENT_ARRAY_BUFFER, bounds=True)
    meshes, nodes, channels, samplers = [], [], [], []
    end = num_frames / fps
    n = 0
    for k, verts in enumerate(tqdm(frames, total=num_frames, disable=not progress, unit="frame", desc="glb")):
        v = np.asarray(verts, np.float64)
        pos = b.add(v.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True)
        nor = b.add(_vertex_normals(v, faces.astype(np.int64)).astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER)
        meshes.append({"name": f"frame_{k:06d}",
                       "primitives": [{"attributes": {"POSITION": pos, "NORMAL": nor}, "indices": indices,
                                       "material": 0}]})
        nodes.append({"name": f"frame_{k:06d}", "mesh": k, "scale": [1.0, 1.0, 1.0] if k == 0 else [0.0, 0.0, 0.0]})
        on, off = k / fps, (k + 1) / fps
        times = ([0.0] if k > 0 else []) + [on] + ([off] if k < num_frames - 1 else [])
        scales = ([0.0] if k > 0 else []) + [1.0] + ([0.0] if k < num_frames - 1 else [])
        t_acc = b.add(np.asarray(times, np.float32), _FLOAT, "SCALAR", bounds=True)
        s_acc = b.add(np.repeat(np.asarray(scales, np.float32)[:, None], 3, axis=1), _FLOAT, "VEC3")
        samplers.append({"input": t_acc, "output": s_acc, "interpolation": "STEP"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": k + 1, "path": "scale"}})
        n += 1
    if n != num_frames:
        raise InputError(f"expected {num_frames} frames, got {n}.")
    doc = {
        "asset": {"version": "2.0", "generator": "flowmocap"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"name": "flowmocap", "children": list(range(1, n + 1))}] + nodes,
        "meshes": meshes,
        "materials": [{"name": "body", "pbrMetallicRoughness": {
            "baseColorFactor": [0.62, 0.68, 0.78, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8}}],
        "animations": [{"name": "motion", "channels": channels, "samplers": samplers}],
        "accessors": b.accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": 0}],
        "extras": {"fps": float(fps), "frames": n, "duration_s": end},
    }
    blob = b.blob()
    doc["buffers"][0]["byteLength"] = len(blob)
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(struct.pack("<4sII", b"glTF", 2, total))
        f.write(struct.pack("<I4s", len(text), b"JSON"))
        f.write(text)
        f.write(struct.pack("<I4s", len(blob), b"BIN\0"))
        f.write(blob)
    return path
