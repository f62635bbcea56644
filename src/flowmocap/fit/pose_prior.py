"""A learned pose prior: a Gaussian mixture over the body joints' rotations (SMPLify's recipe).

The prior is a mixture of ``K`` full-covariance Gaussians over the axis-angle rotations
(radians) of a set of body joints, fitted to motion capture by
``tools/train_pose_prior.py`` (CMU clips retargeted onto the SMPL tree by
:mod:`flowmocap.io.retarget`, mirrored left/right) and shipped as
``flowmocap/fit/data/pose_prior.npz`` (provenance and licence: ``fit/data/README.md``).
The root (joint 0: the body's global orientation) is never part of it; joints the
training mocap does not animate (or animates in only one of its two skeletons) are left
out too, and the prior says nothing about them: :attr:`PosePrior.joints` lists those it
covers.

Energy (SMPLify's max-mixture approximation of the negative log-likelihood), for the
covered joints' rotations ``x`` (``D = 3 * len(joints)`` values):

    E(x) = min_k [ 0.5 (x - mu_k)^T P_k (x - mu_k) + c_k ] - min_k c_k,
    c_k  = -log w_k + 0.5 D log(2 pi) - 0.5 log det P_k

with mixture weights ``w_k``, means ``mu_k`` and precisions ``P_k = L_k L_k^T`` (``L_k``
the triangular Cholesky factor stored in the file; scikit-learn's
``precisions_cholesky_``, upper triangular). ``E >= 0`` and is 0 at the
mean of the component with the lowest ``c_k``; it is dimensionless (nats). Its residual
form, ``r = (sqrt(0.5) L_k*^T (x - mu_k*), sqrt(c_k* - min c))`` for the best component
``k*``, has ``sum(r^2) = E``, like the residual/energy pairs of
:mod:`flowmocap.fit.energies`.

Rotation vectors whose angle exceeds pi are first replaced by the equivalent one with an
angle in ``[-pi, pi]`` (same rotation), so the energy is a function of the rotation.

Typical values of the packaged prior (median [p10, p90], recorded in ``info["energy"]``):
held-out mocap (the test subjects, never trained on) 45 [26, 63]; its training poses 29;
the same held-out poses with both knees bent 40-90 degrees backwards 95, with both elbows
bent backwards 410; uniformly random joint rotations about 10^4; the T-pose 60. A
one-sided limit is beyond a Gaussian mixture: on held-out poses one knee bent 20 (40)
degrees backwards costs a median 5 (12) more than the same knee straight, while a
10-degree knee twist costs 15; joint limits remain the tracker's ``E_b``'s job.
"""

from __future__ import annotations

import json
import math
import zipfile
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowmocap.body.skeleton import JOINT_INDEX, JOINT_NAMES, NUM_JOINTS
from flowmocap.errors import DataError, InputError

__all__ = ["MIRROR_JOINTS", "PRIOR_KIND", "PosePrior", "default_prior_path", "mirror_pose"]

#: Value of the ``kind`` entry of a pose-prior file.
PRIOR_KIND = "flowmocap-pose-prior-gmm"
#: Layout version of the file (bumped when the stored arrays change meaning).
FORMAT_VERSION = 1

NUM_POSE = 3 * NUM_JOINTS
NUM_BODY_POSE = NUM_POSE - 3

#: For each SMPL joint, the joint it becomes in the mirror image (left <-> right).
MIRROR_JOINTS: tuple[int, ...] = tuple(
    JOINT_INDEX[n.replace("left_", "right_") if n.startswith("left_") else n.replace("right_", "left_")]
    for n in JOINT_NAMES
)

_RETRAIN = "python tools/train_pose_prior.py in the source repository (see flowmocap/fit/data/README.md)"


def default_prior_path() -> Path:
    """Where the packaged prior lives: ``<package>/fit/data/pose_prior.npz``."""
    return Path(str(resources.files("flowmocap.fit") / "data" / "pose_prior.npz"))


def mirror_pose(pose: Any) -> Any:
    """The left/right mirror image of poses: what the same person does reflected in the
    body's sagittal plane (``x -> -x`` in SMPL's rest frame, left = +x).

    Each joint takes the rotation of its mirror joint (:data:`MIRROR_JOINTS`), and a
    rotation vector ``(x, y, z)`` reflects to ``(x, -y, -z)`` (a reflection ``M`` turns a
    rotation ``R`` into ``M R M``, its axis into ``det(M) M axis``). Valid for bodies
    whose rest pose is left/right symmetric, as SMPL's is; the mirror of the mirror is
    the pose itself.

    Args:
        pose: ``(..., 72)`` all joints (root first) or ``(..., 69)`` joints 1..23,
            radians; a numpy array or a torch tensor.

    Returns:
        The mirrored poses, same shape and type.

    Raises:
        InputError: last dimension neither 72 nor 69.
    """
    width = pose.shape[-1]
    if width not in (NUM_POSE, NUM_BODY_POSE):
        raise InputError(f"pose must have 72 (all joints) or 69 (joints 1..23) values per row, got {width}")
    first = 0 if width == NUM_POSE else 1
    perm = [MIRROR_JOINTS[j] - first for j in range(first, NUM_JOINTS)]
    sign = [1.0, -1.0, -1.0]
    if isinstance(pose, torch.Tensor):
        p = pose.reshape(*pose.shape[:-1], -1, 3)[..., perm, :]
        return (p * torch.tensor(sign, dtype=pose.dtype, device=pose.device)).reshape(pose.shape)
    p = np.asarray(pose)
    return (p.reshape(*p.shape[:-1], -1, 3)[..., perm, :] * np.array(sign)).reshape(p.shape).astype(p.dtype)


def _wrap_rotvec(r: torch.Tensor) -> torch.Tensor:
    """``(..., 3)`` rotation vectors with angles above pi replaced by the equivalent one
    with an angle in ``[-pi, pi]``; others unchanged (finite gradients everywhere but at
    odd multiples of pi)."""
    sq = (r * r).sum(-1, keepdim=True)
    big = sq > math.pi ** 2
    theta = torch.sqrt(torch.where(big, sq, torch.full_like(sq, math.pi ** 2)))
    wrapped = theta - 2 * math.pi * torch.round(theta / (2 * math.pi))
    return torch.where(big, r * (wrapped / theta), r)


class PosePrior:
    """Gaussian-mixture prior over body-joint rotations; see the module docstring.

    Attributes:
        joints: SMPL joint indices covered (ascending, all >= 1).
        weights: ``(K,)`` mixture weights (sum 1).
        means: ``(K, D)`` component means, radians (``D = 3 * len(joints)``).
        precisions_cholesky: ``(K, D, D)`` triangular (upper or lower) ``L_k`` with a
            positive diagonal, ``P_k = L_k L_k^T`` (units 1/rad).
        log_normalizers: ``(K,)`` ``c_k`` of the module docstring.
        info: what the file says about its training (clips, frames, energies, ...).

    The constructor takes ``weights``, ``means``, ``precisions_cholesky``, ``joints`` and
    ``info`` as above (array-likes, converted to float64); InputError where they are
    inconsistent.
    """

    def __init__(self, weights: Any, means: Any, precisions_cholesky: Any, joints: Any,
                 info: dict | None = None):
        w = np.asarray(weights, dtype=np.float64)
        mu = np.asarray(means, dtype=np.float64)
        L = np.asarray(precisions_cholesky, dtype=np.float64)
        j = tuple(int(x) for x in np.asarray(joints).reshape(-1))
        if w.ndim != 1 or w.size == 0:
            raise InputError(f"weights must be (K,) with K >= 1, got shape {w.shape}")
        K, D = w.size, 3 * len(j)
        if not j or sorted(set(j)) != list(j) or j[0] < 1 or j[-1] >= NUM_JOINTS:
            raise InputError(f"joints must be ascending SMPL joint indices in 1..23, got {j}")
        if mu.shape != (K, D) or L.shape != (K, D, D):
            raise InputError(f"means must be ({K}, {D}) and precisions_cholesky ({K}, {D}, {D}) "
                             f"for {K} components over {len(j)} joints, got {mu.shape} and {L.shape}")
        diag = np.diagonal(L, axis1=1, axis2=2)
        triangular = all(not np.triu(Lk, 1).any() or not np.tril(Lk, -1).any() for Lk in L)
        if (not np.isfinite(w).all() or (w <= 0).any() or abs(w.sum() - 1) > 1e-6
                or not np.isfinite(mu).all() or not np.isfinite(L).all() or (diag <= 0).any()
                or not triangular):
            raise InputError("weights must be positive and sum to 1, means finite, and each "
                             "precisions_cholesky[k] triangular with a positive diagonal")
        self.weights, self.means, self.precisions_cholesky, self.joints = w, mu, L, j
        self.log_normalizers = -np.log(w) + 0.5 * D * math.log(2 * math.pi) - np.log(diag).sum(-1)
        self.info = dict(info or {})
        self._cols = torch.as_tensor([3 * i + c for i in j for c in range(3)], dtype=torch.long)
        self._cache: dict[tuple, tuple[torch.Tensor, ...]] = {}

    # ------------------------------------------------------------------ properties

    @property
    def num_components(self) -> int:
        """Number of mixture components K."""
        return int(self.weights.size)

    @property
    def dim(self) -> int:
        """``D``: the number of axis-angle values the prior covers."""
        return 3 * len(self.joints)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the covered joints, in the order of :attr:`joints`."""
        return tuple(JOINT_NAMES[i] for i in self.joints)

    @property
    def columns(self) -> np.ndarray:
        """``(D,)`` the covered values' positions in a ``(72,)`` pose (``3 j + axis``)."""
        return self._cols.numpy().copy()

    # ------------------------------------------------------------------ files

    @classmethod
    def load(cls, path: str | Path | None = None) -> PosePrior:
        """Read a prior file.

        Args:
            path: a ``.npz`` written by :meth:`save`; default: the packaged prior
                (:func:`default_prior_path`).

        Raises:
            DataError: the file is missing, unreadable, or not a pose prior of this kind
                and version; the message says how to get a good one.
        """
        p = default_prior_path() if path is None else Path(path).expanduser()
        if not p.is_file():
            where = "the packaged pose prior" if path is None else "pose prior file"
            raise DataError(f"{where} {p} does not exist. Reinstall flowmocap (the prior ships "
                            f"in the package), or train one with {_RETRAIN}.")
        try:
            with np.load(p, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
            raise DataError(f"{p} is not a readable .npz file ({e}); a pose prior is written by "
                            f"{_RETRAIN}.") from e
        kind = str(data["kind"]) if "kind" in data else None
        if kind != PRIOR_KIND:
            raise DataError(f"{p} is not a flowmocap pose prior (kind {kind!r}, expected {PRIOR_KIND!r}); "
                            f"pass a file written by {_RETRAIN}, or None for the packaged one.")
        version = int(data.get("version", -1))
        if version != FORMAT_VERSION:
            raise DataError(f"{p} is a pose prior of format version {version}; this flowmocap reads "
                            f"version {FORMAT_VERSION}. Retrain it with {_RETRAIN}.")
        missing = [k for k in ("weights", "means", "precisions_cholesky", "joints") if k not in data]
        if missing:
            raise DataError(f"{p} lacks {', '.join(missing)}; retrain it with {_RETRAIN}.")
        info = json.loads(str(data["info"])) if "info" in data else {}
        try:
            return cls(data["weights"], data["means"], data["precisions_cholesky"], data["joints"], info)
        except InputError as e:
            raise DataError(f"{p} holds an invalid pose prior ({e}); retrain it with {_RETRAIN}.") from e

    def save(self, path: str | Path) -> Path:
        """Write the prior as a compressed ``.npz`` (float64 arrays, ``info`` as JSON)."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            p, kind=np.array(PRIOR_KIND), version=np.array(FORMAT_VERSION),
            weights=self.weights, means=self.means, precisions_cholesky=self.precisions_cholesky,
            log_normalizers=self.log_normalizers, joints=np.array(self.joints, dtype=np.int64),
            joint_names=np.array(self.joint_names), info=np.array(json.dumps(self.info, sort_keys=True)),
        )
        return p

    # ------------------------------------------------------------------ evaluation

    def _tensors(self, dtype: torch.dtype, device) -> tuple[torch.Tensor, ...]:
        key = (dtype, str(device))
        if key not in self._cache:
            c = self.log_normalizers - self.log_normalizers.min()
            self._cache[key] = tuple(torch.as_tensor(a, dtype=dtype, device=device) for a in (
                self.means, self.precisions_cholesky, c))
        return self._cache[key]

    def select(self, pose: torch.Tensor) -> torch.Tensor:
        """The covered joints' rotations, ``(B, D)`` radians, angles wrapped to ``[-pi, pi]``.

        Args:
            pose: ``(B, 72)`` all joints (root first; the root is ignored), ``(B, 69)``
                joints 1..23, or one such row without the batch dimension; radians,
                a floating torch tensor (float32 or float64, any device).
        """
        if not isinstance(pose, torch.Tensor) or not pose.is_floating_point():
            raise InputError(f"pose must be a floating torch tensor of shape (B, 72) or (B, 69), "
                             f"got {type(pose).__name__} {getattr(pose, 'dtype', '')}")
        if pose.dim() == 1:
            pose = pose[None]
        if pose.dim() != 2 or pose.shape[1] not in (NUM_POSE, NUM_BODY_POSE):
            raise InputError(f"pose must have shape (B, 72) or (B, 69), got {tuple(pose.shape)}")
        cols = self._cols.to(pose.device) - (3 if pose.shape[1] == NUM_BODY_POSE else 0)
        x = pose.index_select(1, cols)
        return _wrap_rotvec(x.reshape(x.shape[0], -1, 3)).reshape(x.shape)

    def _whitened(self, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, K, D)`` ``L_k^T (x - mu_k)`` and ``(B, K)`` per-component energies."""
        x = self.select(pose)
        mu, L, c = self._tensors(x.dtype, x.device)
        y = torch.einsum("bkd,kde->bke", x[:, None, :] - mu[None], L)
        return y, 0.5 * (y * y).sum(-1) + c

    def component_energies(self, pose: torch.Tensor) -> torch.Tensor:
        """``(B, K)``: ``0.5 (x - mu_k)^T P_k (x - mu_k) + c_k - min c`` for each component
        (nats), of ``pose`` ``(B, 72)`` or ``(B, 69)`` axis-angle radians (see :meth:`select`)."""
        return self._whitened(pose)[1]

    def energy(self, pose: torch.Tensor) -> torch.Tensor:
        """SMPLify's max-mixture negative log-likelihood, shifted so its minimum is 0.

        Args:
            pose: ``(B, 72)`` or ``(B, 69)`` axis-angle, radians (see :meth:`select`).

        Returns:
            ``(B,)`` dimensionless (nats), ``>= 0``; differentiable in ``pose`` (the
            gradient of the best component, as in SMPLify).
        """
        return self.component_energies(pose).min(dim=1).values

    def residuals(self, pose: torch.Tensor) -> torch.Tensor:
        """Residuals whose squares sum to :meth:`energy`.

        Returns:
            ``(B, D + 1)``: ``sqrt(0.5) L_k^T (x - mu_k)`` for each pose's best component
            ``k``, then ``sqrt(c_k - min c)`` (a constant of that component).
        """
        y, e = self._whitened(pose)
        k = e.argmin(dim=1)
        rows = torch.arange(y.shape[0], device=y.device)
        c = self._tensors(y.dtype, y.device)[2][k]
        return torch.cat([math.sqrt(0.5) * y[rows, k], torch.sqrt(c)[:, None]], dim=1)

    def log_likelihood(self, pose: torch.Tensor) -> torch.Tensor:
        """``(B,)`` the full mixture's log density of the covered joints' rotations,
        ``log sum_k w_k N(x; mu_k, P_k^-1)`` in nats (not shifted), of ``pose`` ``(B, 72)``
        or ``(B, 69)`` axis-angle radians (see :meth:`select`)."""
        e = self.component_energies(pose)
        return torch.logsumexp(-e, dim=1) - float(self.log_normalizers.min())

    def __repr__(self) -> str:
        return (f"PosePrior({self.num_components} components over {len(self.joints)} joints: "
                f"{', '.join(self.joint_names)})")
