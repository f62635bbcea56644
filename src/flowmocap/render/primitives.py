"""Simple closed and open meshes for tests, benchmarks and figures.

All meshes are returned as ``(verts (V, 3) float64 metres, faces (F, 3) int32)`` with
outward normals by the right-hand rule (counter-clockwise seen from outside).
"""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError

__all__ = ["icosphere", "box", "grid_mesh", "mannequin"]


def icosphere(subdivisions: int = 2, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosahedron subdivided ``subdivisions`` times, scaled to ``radius``.

    Faces: ``20 * 4**subdivisions`` (0: 20, 1: 80, 2: 320, 3: 1280, 4: 5120).

    Args:
        subdivisions: 0..7.
        radius: metres.

    Returns:
        ``verts (V, 3)`` float64 metres (centred at the origin) and ``faces (F, 3)`` int32.
    """
    if subdivisions < 0 or subdivisions > 7:
        raise InputError(f"subdivisions must be in 0..7, got {subdivisions}")
    t = (1.0 + 5.0**0.5) / 2.0
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
         [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    faces = np.array(f, dtype=np.int64)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (a, b) if a < b else (b, a)
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = np.array(new, dtype=np.int64)
    return radius * np.array(verts), faces.astype(np.int32)


def box(size: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box centred at the origin: 8 vertices, 12 faces.

    ``size``: ``(x, y, z)`` edge lengths in metres. Returns ``verts (8, 3)`` float64
    metres and ``faces (12, 3)`` int32.
    """
    sx, sy, sz = (0.5 * float(s) for s in size)
    verts = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    # vertex index = 4 * (x>0) + 2 * (y>0) + (z>0)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, c, d in quads:
        faces += [[a, b, c], [a, c, d]]
    return verts, np.array(faces, dtype=np.int32)


def grid_mesh(nx: int, ny: int, size: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """A flat ``nx`` x ``ny``-cell grid in the z = 0 plane centred at the origin,
    normal along -z (facing a camera that looks along +z), ``2 * nx * ny`` faces.

    ``size``: ``(x, y)`` extent in metres. Returns ``verts ((nx + 1) (ny + 1), 3)`` float64
    metres and ``faces (2 nx ny, 3)`` int32.
    """
    xs = np.linspace(-0.5, 0.5, nx + 1) * size[0]
    ys = np.linspace(-0.5, 0.5, ny + 1) * size[1]
    X, Y = np.meshgrid(xs, ys)
    verts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    # counter-clockwise seen from -z (x right, y down in the camera image)
    faces = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])
    return verts, faces.astype(np.int32)


def mannequin(subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A person-shaped stand-in: 11 ellipsoids (head, torso, pelvis, upper/lower arms and
    legs), 1.75 m tall, y up, facing +z, feet at y = 0. With ``subdivisions=3`` it has
    14,080 faces (the size of an SMPL body: 13,776). Returns ``verts (V, 3)`` float64
    metres and ``faces (F, 3)`` int32."""
    parts = [  # centre (x, y, z), semi-axes (x, y, z)
        ((0.0, 1.62, 0.0), (0.09, 0.12, 0.10)),
        ((0.0, 1.28, 0.0), (0.18, 0.24, 0.11)),
        ((0.0, 0.96, 0.0), (0.17, 0.12, 0.11)),
        ((0.28, 1.28, 0.0), (0.05, 0.16, 0.05)),
        ((-0.28, 1.28, 0.0), (0.05, 0.16, 0.05)),
        ((0.30, 0.98, 0.02), (0.045, 0.15, 0.045)),
        ((-0.30, 0.98, 0.02), (0.045, 0.15, 0.045)),
        ((0.10, 0.66, 0.0), (0.08, 0.22, 0.08)),
        ((-0.10, 0.66, 0.0), (0.08, 0.22, 0.08)),
        ((0.10, 0.24, -0.01), (0.06, 0.22, 0.06)),
        ((-0.10, 0.24, -0.01), (0.06, 0.22, 0.06)),
    ]
    sv, sf = icosphere(subdivisions)
    verts, faces = [], []
    for k, (c, s) in enumerate(parts):
        verts.append(sv * np.array(s) + np.array(c))
        faces.append(sf + k * len(sv))
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32)
