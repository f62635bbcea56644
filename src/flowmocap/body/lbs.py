"""SMPL-format linear blend skinning as pure torch functions.

The maths follows Loper et al. 2015 ("SMPL: A Skinned Multi-Person Linear Model"),
Eqs. 1-4: shape blend shapes, joint regression, pose blend shapes, a rigid kinematic
chain and linear blend skinning. Every function is batched over a leading dimension B
and differentiable. Units: metres for positions, radians for axis-angle rotations.
"""

from __future__ import annotations

import functools

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
    order, levels, inverse = _chain_levels(tuple(int(p) for p in parents.tolist()))
    rel_joints = torch.cat([joints[:, :1], joints[:, 1:] - joints[:, parents[1:]]], dim=1)
    local = _affine(rotmats, rel_joints)[:, order]  # (B, J, 4, 4), a level of the tree after another
    # the chain one level of the tree at a time: a level's transforms are their parents'
    # (all in the level before) times their own, one batched product per level
    chain = [local[:, :1]]
    start = 1
    for count, parent_pos in levels:
        chain.append(chain[-1][:, parent_pos] @ local[:, start:start + count])
        start += count
    world = torch.cat(chain, dim=1)[:, inverse]
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint location: rel = world @ [I, -J_rest; 0, 1].
    offset = torch.einsum("bjcd,bjd->bjc", world[..., :3, :3], joints)
    return posed_joints, _affine(world[..., :3, :3], posed_joints - offset)


def _affine(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` homogeneous transforms ``[R t; 0 1]`` of ``R (..., 3, 3)`` and ``t (..., 3)``."""
    top = torch.cat([R, t[..., None]], dim=-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=R.dtype, device=R.device).expand(*R.shape[:-2], 1, 4)
    return torch.cat([top, bottom], dim=-2)


@functools.cache
def _chain_levels(parents: tuple[int, ...]) -> tuple[list[int], list[tuple[int, list[int]]], list[int]]:
    """The kinematic tree by depth: the joints in order of depth (the root first), per
    level after the root its joint count and each joint's parent's position in the level
    before, and the permutation back to joint order."""
    depth = [0] * len(parents)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    by_level = [[j for j in range(len(parents)) if depth[j] == d] for d in range(max(depth) + 1)]
    order = [j for level in by_level for j in level]
    levels = [(len(level), [by_level[d - 1].index(parents[j]) for j in level])
              for d, level in enumerate(by_level) if d > 0]
    inverse = [order.index(j) for j in range(len(parents))]
    return order, levels, inverse


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


def shaped_rest(betas: torch.Tensor, v_template: torch.Tensor, shapedirs: torch.Tensor,
                J_regressor: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The shaped body in the rest pose: ``v_shaped (B, V, 3)`` and its regressed
    ``rest_joints (B, J, 3)``, metres (arguments as :func:`lbs`)."""
    v_shaped = v_template + blend_shapes(betas, shapedirs)
    return v_shaped, vertices_to_joints(J_regressor, v_shaped)


def lbs(
    betas: torch.Tensor,
    pose: torch.Tensor,
    v_template: torch.Tensor,
    shapedirs: torch.Tensor,
    posedirs: torch.Tensor | None,
    J_regressor: torch.Tensor,
    parents: torch.Tensor,
    weights: torch.Tensor,
    shaped: tuple[torch.Tensor, torch.Tensor] | None = None,
    with_vertices: bool = True,
) -> dict[str, torch.Tensor | None]:
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
        shaped: ``(v_shaped (B, V, 3), rest_joints (B, J, 3))`` of ``betas`` when already
            known (:func:`shaped_rest`), to skip the shape blend shapes and the joint
            regressor for a shape that stays fixed (the tracker's).
        with_vertices: False: skip the pose blend shapes and the skinning (``vertices``
            is None), for objectives of the joints alone.

    Returns:
        dict with ``vertices (B, V, 3)``, ``joints (B, J, 3)`` (posed),
        ``rest_vertices (B, V, 3)`` (shaped, unposed), ``rest_joints (B, J, 3)``,
        ``rotmats (B, J, 3, 3)`` and ``transforms (B, J, 4, 4)`` (see
        :func:`rigid_transforms`).
    """
    B = pose.shape[0]
    J = J_regressor.shape[0]
    v_shaped, rest_joints = shaped if shaped is not None else shaped_rest(betas, v_template, shapedirs, J_regressor)
    rotmats = axis_angle_to_matrix(pose.reshape(B, J, 3))
    joints, transforms = rigid_transforms(rotmats, rest_joints, parents)
    vertices = None
    if with_vertices:
        v_posed = v_shaped
        if posedirs is not None:
            v_posed = v_shaped + (pose_feature(rotmats) @ posedirs).reshape(B, -1, 3)
        vertices = skin(v_posed, weights, transforms)
    return {
        "vertices": vertices,
        "joints": joints,
        "rest_vertices": v_shaped,
        "rest_joints": rest_joints,
        "rotmats": rotmats,
        "transforms": transforms,
    }
