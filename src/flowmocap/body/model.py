"""The body model: a small torch module that holds an SMPL-format model's buffers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from flowmocap.body.lbs import lbs, shaped_rest
from flowmocap.body.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from flowmocap.errors import InputError


@dataclass
class BodyOutput:
    """Result of :meth:`BodyModel.forward`; B is the batch size, V the vertex count.

    Attributes:
        vertices: ``(B, V, 3)`` posed, translated vertices in metres (None when the
            forward pass was asked for the joints only).
        joints: ``(B, 24, 3)`` posed, translated SMPL joints in metres.
        rest_vertices: ``(B, V, 3)`` shaped vertices in the rest pose (no translation).
        rest_joints: ``(B, 24, 3)`` joints of the shaped rest pose.
        transforms: ``(B, 24, 4, 4)`` rest-to-posed rigid transform of each joint's
            bone, translation included (``x_posed = R @ x_rest + t``).
    """

    vertices: torch.Tensor | None
    joints: torch.Tensor
    rest_vertices: torch.Tensor
    rest_joints: torch.Tensor
    transforms: torch.Tensor


@dataclass
class ModelArrays:
    """Plain numpy arrays of an SMPL-format model, as read from a file.

    Shapes: ``v_template (V,3)``, ``faces (F,3)``, ``weights (V,24)``,
    ``J_regressor (24,V)``, ``shapedirs (V,3,S)``, ``posedirs (V,3,207)`` or ``None``.
    """

    v_template: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    J_regressor: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray | None
    gender: str
    kind: str
    source: str


class BodyModel(torch.nn.Module):
    """SMPL-format body: ``betas (B,10), pose (B,72), trans (B,3) -> vertices, joints``.

    Holds buffers only; build one with :func:`flowmocap.body.load_body_model`.
    The rest pose is SMPL's: T-pose, y up, facing +z, metres.

    Args:
        arrays: the model's :class:`ModelArrays`.
        num_betas: shape coefficients used (extra ``shapedirs`` are dropped, missing ones
            are zero).
        dtype: dtype of the float buffers.

    Attributes:
        faces: ``(F, 3)`` int64 triangle indices, counter-clockwise from outside.
        parents: ``(24,)`` parent joint indices (root: -1).
        gender, kind, source: strings describing where the model came from.
    """

    joint_names = JOINT_NAMES

    def __init__(self, arrays: ModelArrays, num_betas: int = 10, dtype=torch.float32):
        super().__init__()
        a = arrays
        V = a.v_template.shape[0]
        S = a.shapedirs.shape[2]
        shapedirs = np.zeros((V, 3, num_betas), dtype=np.float64)
        k = min(S, num_betas)
        shapedirs[:, :, :k] = a.shapedirs[:, :, :k]
        self.num_betas = num_betas
        self.gender = a.gender
        self.kind = a.kind
        self.source = a.source
        self.name: str | None = None  # set by load_body_model: "default" or the model file's path
        t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype)  # noqa: E731
        self.register_buffer("v_template", t(a.v_template))
        self.register_buffer("shapedirs", t(shapedirs))
        self.register_buffer("J_regressor", t(a.J_regressor))
        self.register_buffer("weights", t(a.weights))
        if a.posedirs is not None:
            P = a.posedirs.shape[2]
            self.register_buffer("posedirs", t(a.posedirs.reshape(V * 3, P).T))
        else:
            self.posedirs = None
        self.register_buffer("faces", torch.as_tensor(a.faces.astype(np.int64)))
        self.register_buffer("parents", torch.tensor(PARENTS, dtype=torch.int64))

    @property
    def num_vertices(self) -> int:
        """Number of vertices V."""
        return self.v_template.shape[0]

    @property
    def faces_np(self) -> np.ndarray:
        """``(F, 3)`` int32 faces as a numpy array (for the renderer)."""
        return self.faces.cpu().numpy().astype(np.int32)

    def shaped(self, betas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The shaped body in the rest pose, ``(v_shaped (B, V, 3), rest_joints (B, J, 3))``
        metres, for :meth:`forward`'s ``shaped`` (``betas`` as there)."""
        betas = _batch(betas, self.num_betas, "betas", self.v_template.device, self.v_template.dtype)
        return shaped_rest(betas, self.v_template, self.shapedirs, self.J_regressor)

    def forward(
        self,
        betas: torch.Tensor | None = None,
        pose: torch.Tensor | None = None,
        trans: torch.Tensor | None = None,
        shaped: tuple[torch.Tensor, torch.Tensor] | None = None,
        with_vertices: bool = True,
    ) -> BodyOutput:
        """Pose and shape the body.

        Args:
            betas: ``(B, num_betas)`` or ``(num_betas,)`` shape coefficients; fewer
                columns are zero-padded. Default: the mean shape.
            pose: ``(B, 72)``, ``(B, 24, 3)`` or ``(72,)`` axis-angle in radians.
                Default: the rest pose.
            trans: ``(B, 3)`` or ``(3,)`` global translation in metres. Default: zero.
            shaped: :meth:`shaped` of these ``betas``, to skip recomputing the shaped
                rest body when the shape stays fixed (its batch must be 1 or B).
            with_vertices: False: joints and transforms only (``vertices`` is None),
                without the pose blend shapes and the skinning.

        A batch of 1 broadcasts against the others' batch size.

        Returns:
            :class:`BodyOutput`.
        """
        dev, dt = self.v_template.device, self.v_template.dtype
        betas = _batch(betas, self.num_betas, "betas", dev, dt)
        pose = _batch(pose, 3 * NUM_JOINTS, "pose", dev, dt)
        trans = _batch(trans, 3, "trans", dev, dt)
        B = max(betas.shape[0], pose.shape[0], trans.shape[0])
        if min(betas.shape[0], pose.shape[0], trans.shape[0]) == 0:
            raise InputError("betas, pose and trans must hold at least one body each (a batch of 0 was given).")
        for name, x in (("betas", betas), ("pose", pose), ("trans", trans)):
            if x.shape[0] not in (1, B):
                raise InputError(
                    f"{name} has batch size {x.shape[0]} but another input has {B}; "
                    "give equal batch sizes or a batch of 1 to broadcast."
                )
        betas, pose, trans = (x.expand(B, -1) for x in (betas, pose, trans))
        if shaped is not None:
            shaped = tuple(x.expand(B, -1, -1) for x in shaped)
        out = lbs(
            betas, pose, self.v_template, self.shapedirs, self.posedirs,
            self.J_regressor, self.parents, self.weights, shaped=shaped, with_vertices=with_vertices,
        )
        transforms = out["transforms"].clone()
        transforms[..., :3, 3] = transforms[..., :3, 3] + trans[:, None]
        return BodyOutput(
            vertices=out["vertices"] + trans[:, None] if with_vertices else None,
            joints=out["joints"] + trans[:, None],
            rest_vertices=out["rest_vertices"],
            rest_joints=out["rest_joints"],
            transforms=transforms,
        )


def _batch(x, width: int, name: str, device, dtype) -> torch.Tensor:
    if x is None:
        return torch.zeros(1, width, device=device, dtype=dtype)
    x = torch.as_tensor(x, device=device, dtype=dtype)
    if name == "pose" and x.dim() == 3 and x.shape[1:] == (NUM_JOINTS, 3):
        x = x.reshape(x.shape[0], -1)
    if x.dim() == 1:
        x = x[None]
    if x.dim() != 2:
        raise InputError(f"{name} must have shape (B, {width}); got {tuple(x.shape)}.")
    if name == "betas" and x.shape[1] < width:
        x = torch.nn.functional.pad(x, (0, width - x.shape[1]))
    if x.shape[1] != width:
        raise InputError(f"{name} must have shape (B, {width}); got {tuple(x.shape)}.")
    if not torch.isfinite(x).all():
        raise InputError(f"{name} contains NaN or infinite values.")
    return x
