"""SMPL-format linear blend skinning as pure torch functions.

The maths follows Loper et al. 2015 ("SMPL: A Skinned Multi-Person Linear Model"),
Eqs. 1-4: shape blend shapes, joint regression, pose blend shapes, a rigid kinematic
chain and linear blend skinning. Every function is batched over a leading dimension B
and differentiable. Units: metres for positions, radians for axis-angle rotations.
"""

from __future__ import annotations

import torch

from flowmocap.geometry.rotations import axis_angle_to_matrix


def blend_shapes(betas: torch.Tensor, shapedirs: torch.Tensor) -> torch.Tensor:
    """Per-vertex offsets of a shape.

    Args:
        betas: ``(B, S)`` shape coefficients (unit variance).
        shapedirs: ``(V, 3, S)`` shape blend shapes in metres per unit of beta.

    Returns:
        ``(B, V, 3)`` vertex offsets in metres.
    """
    V, _, S = shapedirs.shape
    return (betas @ shapedirs.reshape(V * 3, S).T).reshape(betas.shape[0], V, 3)


def vertices_to_joints(J_regressor: torch.Tensor, vertices: torch.Tensor) -> torch.Tensor:
    """Regress joint locations from vertices.

    Args:
        J_regressor: ``(J, V)`` regressor, each row a convex combination of vertices.
        vertices: ``(B, V, 3)`` vertex positions in metres.

    Returns:
        ``(B, J, 3)`` joint positions in metres.
    """
    return torch.matmul(J_regressor, vertices)


def pose_feature(rotmats: torch.Tensor) -> torch.Tensor:
    """SMPL's pose-corrective feature: ``(R_k - I)`` of every non-root joint, flattened.

    Args:
        rotmats: ``(B, J, 3, 3)`` local joint rotations.

    Returns:
        ``(B, (J - 1) * 9)``.
    """
    eye = torch.eye(3, dtype=rotmats.dtype, device=rotmats.device)
    return (rotmats[:, 1:] - eye).reshape(rotmats.shape[0], -1)


def rigid_transforms(
    rotmats: torch.Tensor, joints: torch.Tensor, parents: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the kinematic chain.

    Args:
        rotmats: ``(B, J, 3, 3)`` local rotation of each joint relative to its parent.
        joints: ``(B, J, 3)`` joint locations in the rest pose, metres.
        parents: ``(J,)`` parent indices, ``parents[0] == -1``, each parent before its
            children.

    Returns:
        ``posed_joints (B, J, 3)``: joint locations after posing, and
        ``rel_transforms (B, J, 4, 4)``: the transforms that carry a rest-pose point
        rigidly attached to joint j to its posed location (``G_j`` with the rest joint
        location removed: ``x_posed = R x_rest + t``), which is what skinning blends.
    """
    B, J = joints.shape[:2]
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, parents[1:]]
    local = torch.zeros(B, J, 4, 4, dtype=rotmats.dtype, device=rotmats.device)
    local[..., :3, :3] = rotmats
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    chain = [local[:, 0]]
    for j in range(1, J):
        chain.append(chain[int(parents[j])] @ local[:, j])
    world = torch.stack(chain, dim=1)
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint location: rel = world @ [I, -J_rest; 0, 1].
    offset = torch.einsum("bjcd,bjd->bjc", world[..., :3, :3], joints)
    rel = world.clone()
    rel[..., :3, 3] = world[..., :3, 3] - offset
    return posed_joints, rel


def skin(
    vertices: torch.Tensor, weights: torch.Tensor, rel_transforms: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning.

    Args:
        vertices: ``(B, V, 3)`` rest-pose vertices (after shape and pose blend shapes).
        weights: ``(V, J)`` skinning weights, rows summing to 1.
        rel_transforms: ``(B, J, 4, 4)`` from :func:`rigid_transforms`.

    Returns:
        ``(B, V, 3)`` posed vertices.
    """
    B, V = vertices.shape[:2]
    # Blend only the top 3x4 block; (V,J) @ (B,J,12) is one matmul, and applying the
    # per-vertex 3x4 transforms elementwise avoids a batch of V tiny matrix products.
    T = torch.matmul(weights, rel_transforms[:, :, :3, :].reshape(B, -1, 12)).reshape(B, V, 3, 4)
    return (T[..., :3] * vertices[:, :, None, :]).sum(-1) + T[..., 3]


def lbs(
    betas: torch.Tensor,
    pose: torch.Tensor,
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor | None,
    J_regressor: torch.Tensor,
    parents: torch.Tensor,
    weights: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """The whole SMPL function M(beta, theta) without global translation.

    Args:
        betas: ``(B, S)`` shape coefficients.
        pose: ``(B, J * 3)`` axis-angle rotations in radians (root first).
        v_template: ``(V, 3)`` mean template in the rest pose, metres.
        shapedirs: ``(V, 3, S)`` shape blend shapes.
        posedirs: ``((J - 1) * 9, V * 3)`` pose correctives, or ``None``.
        J_regressor: ``(J, V)``.
        parents: ``(J,)`` parent indices.
        weights: ``(V, J)`` skinning weights.

    Returns:
        dict with ``vertices (B, V, 3)``, ``joints (B, J, 3)`` (posed),
        ``rest_vertices (B, V, 3)`` (shaped, unposed), ``rest_joints (B, J, 3)``,
        ``rotmats (B, J, 3, 3)`` and ``transforms (B, J, 4, 4)`` (see
        :func:`rigid_transforms`).
    """
    B = pose.shape[0]
    J = J_regressor.shape[0]
    v_shaped = v_template + blend_shapes(betas, shapedirs)
    rest_joints = vertices_to_joints(J_regressor, v_shaped)
    rotmats = axis_angle_to_matrix(pose.reshape(B, J, 3))
    v_posed = v_shaped
    if posedirs is not None:
        v_posed = v_shaped + (pose_feature(rotmats) @ posedirs).reshape(B, -1, 3)
    joints, transforms = rigid_transforms(rotmats, rest_joints, parents)
    vertices = skin(v_posed, weights, transforms)
    return {
        "vertices": vertices,
        "joints": joints,
        "rest_vertices": v_shaped,
        "rest_joints": rest_joints,
        "rotmats": rotmats,
        "transforms": transforms,
    }
