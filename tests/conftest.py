"""Shared test fixtures: a small synthetic SMPL-format body written in the real layouts; and
:func:`load_script`, a benchmark's or tool's script loaded as a module."""

from __future__ import annotations

import importlib.util
import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from flowmocap.body.skeleton import PARENTS, children

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def load_script(path: str | Path, name: str | None = None) -> types.ModuleType:
    """The script at ``path`` (a ``benchmarks/`` or ``tools/`` file, not a package module)
    loaded as a module named ``name`` (default: the file's stem)."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod

# Rest-pose joint positions of a T-posed person (metres; y up, facing +z, left = +x).
TOY_JOINTS = np.array([
    [0.00, 0.00, 0.00], [0.09, -0.08, 0.0], [-0.09, -0.08, 0.0], [0.0, 0.11, -0.02],
    [0.10, -0.48, 0.01], [-0.10, -0.48, 0.01], [0.0, 0.24, 0.0], [0.10, -0.88, -0.03],
    [-0.10, -0.88, -0.03], [0.0, 0.29, 0.01], [0.11, -0.93, 0.10], [-0.11, -0.93, 0.10],
    [0.0, 0.51, -0.02], [0.08, 0.40, -0.01], [-0.08, 0.40, -0.01], [0.0, 0.61, 0.03],
    [0.18, 0.43, -0.02], [-0.18, 0.43, -0.02], [0.43, 0.42, -0.03], [-0.43, 0.42, -0.03],
    [0.68, 0.43, -0.03], [-0.68, 0.43, -0.03], [0.76, 0.42, -0.04], [-0.76, 0.42, -0.04],
])


def _ring(centre, axis, radius, n=8):
    axis = axis / np.linalg.norm(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return centre + radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)


def make_toy_arrays(seed: int = 0, with_posedirs: bool = True) -> dict:
    """A tiny SMPL-layout model: for each joint a ring of vertices centred on the joint
    (the joint regressor averages it) and a ring half-way along its bone."""
    rng = np.random.default_rng(seed)
    verts, weights, jreg_rows, faces = [], [], [], []
    n = 8
    for j in range(24):
        kids = children(j)
        end = TOY_JOINTS[kids[0]] if kids else TOY_JOINTS[j] + 0.5 * (TOY_JOINTS[j] - TOY_JOINTS[PARENTS[j]])
        axis = end - TOY_JOINTS[j]
        base = len(verts)
        for v in _ring(TOY_JOINTS[j], axis, 0.04, n):
            verts.append(v)
            w = np.zeros(24)
            w[j] = 0.5 if j else 1.0
            if j:
                w[PARENTS[j]] = 0.5
            weights.append(w)
        for v in _ring(0.5 * (TOY_JOINTS[j] + end), axis, 0.035, n):
            verts.append(v)
            w = np.zeros(24)
            w[j] = 1.0
            weights.append(w)
        jreg_rows.append(list(range(base, base + n)))
        for k in range(n):
            a, b = base + k, base + (k + 1) % n
            faces += [[a, b, b + n], [a, b + n, a + n]]
    V = len(verts)
    J_regressor = np.zeros((24, V))
    for j, idx in enumerate(jreg_rows):
        J_regressor[j, idx] = 1.0 / n
    out = {
        "v_template": np.array(verts),
        "f": np.array(faces, dtype=np.uint32),
        "weights": np.array(weights),
        "J_regressor": J_regressor,
        "shapedirs": 0.02 * rng.standard_normal((V, 3, 10)),
        "kintree_table": np.array([[4294967295] + list(PARENTS[1:]), list(range(24))], dtype=np.int64),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }
    if with_posedirs:
        out["posedirs"] = 0.01 * rng.standard_normal((V, 3, 207))
    return out


class _FakeCh:
    """Mimics chumpy.ch.Ch for pickling: an object whose state holds the array in 'x'."""


def write_smpl_pkl(path: Path, arrays: dict) -> None:
    """Write arrays as the original SMPL .pkl does: chumpy Ch objects and a scipy csc
    J_regressor pickled with protocol 2, under the module names the real files use."""
    ch_mod = types.ModuleType("chumpy.ch")
    Ch = type("Ch", (_FakeCh,), {"__module__": "chumpy.ch"})
    ch_mod.Ch = Ch
    csc_mod = types.ModuleType("scipy.sparse.csc")
    Csc = type("csc_matrix", (), {"__module__": "scipy.sparse.csc"})
    csc_mod.csc_matrix = Csc
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch", "scipy.sparse.csc")}
    sys.modules["chumpy"] = types.ModuleType("chumpy")
    sys.modules["chumpy.ch"] = ch_mod
    sys.modules["scipy.sparse.csc"] = csc_mod
    try:
        data = {}
        for key, value in arrays.items():
            if key in ("v_template", "shapedirs", "posedirs"):
                obj = Ch()
                obj.__dict__.update({"x": np.asarray(value), "_dirty_vars": set(), "_itr": None,
                                     "_parents": {}, "_cache": {"r": {}}, "_depends_on_deps": {}})
                data[key] = obj
            elif key == "J_regressor":
                m = sp.csc_matrix(value)
                obj = Csc()
                obj.__dict__.update({"data": m.data, "indices": m.indices, "indptr": m.indptr,
                                     "_shape": m.shape, "maxprint": 50})
                data[key] = obj
            else:
                data[key] = value
        path.write_bytes(pickle.dumps(data, protocol=2))
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


@pytest.fixture(scope="session")
def toy_arrays():
    return make_toy_arrays()


@pytest.fixture(scope="session")
def toy_files(tmp_path_factory, toy_arrays):
    """Paths of the toy model as SMPL-style .pkl and .npz."""
    d = tmp_path_factory.mktemp("toy_model")
    pkl = d / "SMPL_NEUTRAL.pkl"
    write_smpl_pkl(pkl, toy_arrays)
    npz = d / "SMPL_NEUTRAL.npz"
    np.savez(npz, **{k: v for k, v in toy_arrays.items()})
    return {"pkl": pkl, "npz": npz, "dir": d}


@pytest.fixture(scope="session")
def toy_model(toy_files):
    import torch

    from flowmocap.body import load_body_model

    return load_body_model(toy_files["npz"], dtype=torch.float64)
