"""The learned pose prior (flowmocap.fit.pose_prior): the packaged file, the energy and its
gradient, the left/right mirror, low energy on held-out mocap, high on implausible poses."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TOY_JOINTS

from flowmocap.body import JOINT_NAMES, PARENTS
from flowmocap.body.lbs import rigid_transforms
from flowmocap.errors import DataError, InputError
from flowmocap.fit.pose_prior import (
    MIRROR_JOINTS,
    PRIOR_KIND,
    PosePrior,
    default_prior_path,
    mirror_pose,
)
from flowmocap.geometry import axis_angle_to_matrix

from conftest import load_script

PRIOR_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap" / "prior"
TEST_SUBJECTS = {2, 8, 13, 61}
# Held-out clips (test split: subjects never used for training): walk, bend/pick up, jump, salsa.
HELD_OUT = ("cmu_mb/02_01.bvh", "cmu_mb/02_06.bvh", "cmu_daz/13_11.bvh", "cmu_daz/61_01.bvh")


@pytest.fixture(scope="module")
def prior():
    return PosePrior.load()


def _random_poses(n: int, seed: int, scale: float = 0.4) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, scale, (n, 72))


def _uniform_rotations(n: int, seed: int) -> np.ndarray:
    """``(n, 72)``: joints 1..23 uniformly random rotations, root zero."""
    rng = np.random.default_rng(seed)
    q = rng.standard_normal((n, 23, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.sign(q[..., :1])
    ang = 2 * np.arccos(np.clip(q[..., 0], -1, 1))
    axis = q[..., 1:] / np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    out = np.zeros((n, 24, 3))
    out[:, 1:] = axis * ang[..., None]
    return out.reshape(n, 72)


def _knees_backward(poses: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """The poses with both knees bent ``deg`` the wrong way (knee flexion is about +x)."""
    p = poses.reshape(-1, 24, 3).copy()
    p[:, [4, 5]] = 0.0
    p[:, [4, 5], 0] = -np.radians(deg)
    return p.reshape(-1, 72)


def _elbows_hyperextended(poses: np.ndarray, deg: np.ndarray) -> np.ndarray:
    """The poses with both elbows bent ``deg`` backwards (flexion: -y left, +y right)."""
    p = poses.reshape(-1, 24, 3).copy()
    p[:, [18, 19]] = 0.0
    p[:, 18, 1], p[:, 19, 1] = np.radians(deg[:, 0]), -np.radians(deg[:, 1])
    return p.reshape(-1, 72)


def _energy(prior, poses, dtype=torch.float32) -> np.ndarray:
    with torch.no_grad():
        return prior.energy(torch.as_tensor(poses, dtype=dtype)).double().numpy()


# ----------------------------------------------------------------------------- the file


def test_packaged_prior_loads(prior):
    path = default_prior_path()
    assert path.is_file() and path.stat().st_size < 1_000_000
    assert prior.num_components == 8 and prior.dim == 3 * len(prior.joints)
    assert prior.joints[0] >= 1  # never the root
    for name in ("left_knee", "right_knee", "left_elbow", "right_elbow", "left_hip", "left_shoulder"):
        assert name in prior.joint_names
    # trained on the train split only
    assert not set(prior.info["train_subjects"]) & TEST_SUBJECTS
    assert set(prior.info["test_subjects"]) == TEST_SUBJECTS
    assert prior.info["frames_used"] > 10000 and "mocap.cs.cmu.edu" in prior.info["acknowledgement"]
    np.testing.assert_allclose(prior.weights.sum(), 1.0, atol=1e-9)
    # the covered joints are closed under the mirror (the training set was mirrored)
    assert sorted(MIRROR_JOINTS[j] for j in prior.joints) == list(prior.joints)


def test_wrong_files_raise_data_error(tmp_path, prior):
    with pytest.raises(DataError, match="does not exist.*train_pose_prior"):
        PosePrior.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", weights=np.ones(1))
    with pytest.raises(DataError, match="not a flowmocap pose prior"):
        PosePrior.load(tmp_path / "other.npz")
    (tmp_path / "text.npz").write_text("not a zip file")
    with pytest.raises(DataError, match="not a readable .npz"):
        PosePrior.load(tmp_path / "text.npz")
    # the bundled body model is an .npz too, of another kind
    body = Path(str(default_prior_path())).parents[2] / "body" / "data" / "default_neutral.npz"
    with pytest.raises(DataError, match="not a flowmocap pose prior"):
        PosePrior.load(body)
    np.savez(tmp_path / "v0.npz", kind=np.array(PRIOR_KIND), version=np.array(0))
    with pytest.raises(DataError, match="format version 0"):
        PosePrior.load(tmp_path / "v0.npz")
    bad = dict(np.load(default_prior_path()))
    bad["means"] = bad["means"][:, :-3]
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(DataError, match="invalid pose prior"):
        PosePrior.load(tmp_path / "bad.npz")


def test_save_load_round_trip(tmp_path, prior):
    again = PosePrior.load(prior.save(tmp_path / "p.npz"))
    x = torch.as_tensor(_random_poses(8, 1), dtype=torch.float64)
    torch.testing.assert_close(again.energy(x), prior.energy(x))
    assert again.info == prior.info and again.joints == prior.joints


# ----------------------------------------------------------------------------- energy


def test_energy_shapes_dtypes_and_minimum(prior):
    x64 = torch.as_tensor(_random_poses(16, 2), dtype=torch.float64)
    e = prior.energy(x64)
    assert e.shape == (16,) and e.dtype == torch.float64 and (e >= 0).all()
    torch.testing.assert_close(prior.energy(x64[:, 3:]), e)  # (B, 69): joints 1..23
    torch.testing.assert_close(prior.energy(x64[0]), e[:1])  # one pose, no batch
    e32 = prior.energy(x64.float())
    assert e32.dtype == torch.float32
    torch.testing.assert_close(e32.double(), e, rtol=1e-4, atol=1e-3)
    # the root does not matter
    y = x64.clone()
    y[:, :3] = 1.0
    torch.testing.assert_close(prior.energy(y), e)
    # 0 at the mean of the component with the lowest constant, > 0 elsewhere
    k = int(np.argmin(prior.log_normalizers))
    best = torch.zeros(1, 72, dtype=torch.float64)
    best[0, torch.as_tensor(prior.columns)] = torch.as_tensor(prior.means[k])
    assert prior.energy(best).item() == pytest.approx(0.0, abs=1e-9)
    # residuals: their squares sum to the energy
    r = prior.residuals(x64)
    assert r.shape == (16, prior.dim + 1)
    torch.testing.assert_close((r * r).sum(-1), e)
    # the full mixture's log density is at least the best component's
    assert (prior.log_likelihood(x64) >= -e - prior.log_normalizers.min() - 1e-9).all()
    with pytest.raises(InputError, match=r"\(B, 72\) or \(B, 69\)"):
        prior.energy(torch.zeros(2, 70))
    with pytest.raises(InputError, match="floating"):
        prior.energy(np.zeros((2, 72)))


def test_energy_is_a_function_of_the_rotation(prior):
    """A rotation vector past pi and its equivalent below pi give the same energy."""
    x = torch.as_tensor(_random_poses(4, 3, scale=0.3), dtype=torch.float64)
    y = x.clone().reshape(4, 24, 3)
    r = y[:, 16]  # left shoulder
    theta = r.norm(dim=-1, keepdim=True)
    y[:, 16] = r / theta * (theta - 2 * math.pi)  # same rotation, angle 2 pi - theta > pi
    assert (y[:, 16].norm(dim=-1) > math.pi).all()
    torch.testing.assert_close(prior.energy(y.reshape(4, 72)), prior.energy(x))


def test_gradient_matches_finite_differences(prior):
    # poses near the training data (component means plus noise), away from ties
    rng = np.random.default_rng(4)
    x = np.zeros((3, 72))
    for i, k in enumerate((0, 3, 5)):
        x[i, prior.columns] = prior.means[k] + rng.normal(0, 0.05, prior.dim)
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(prior.energy, (xt,), eps=1e-6, atol=1e-5, rtol=1e-4)
    assert torch.autograd.gradcheck(prior.residuals, (xt,), eps=1e-6, atol=1e-5, rtol=1e-4)
    # float32 gradient agrees with float64's
    x32 = xt.detach().float().requires_grad_(True)
    prior.energy(x32).sum().backward()
    xt.grad = None
    prior.energy(xt).sum().backward()
    torch.testing.assert_close(x32.grad.double(), xt.grad, rtol=1e-3, atol=1e-2)


# ----------------------------------------------------------------------------- mirror


def test_mirror_is_an_involution_and_mirrors_the_joints():
    x = _random_poses(5, 5, scale=0.8)
    np.testing.assert_allclose(mirror_pose(mirror_pose(x)), x)
    np.testing.assert_allclose(mirror_pose(x[:, 3:]), mirror_pose(x)[:, 3:])  # (..., 69) too
    t = torch.as_tensor(x)
    torch.testing.assert_close(mirror_pose(mirror_pose(t)), t)
    torch.testing.assert_close(mirror_pose(t), torch.as_tensor(mirror_pose(x)))
    assert MIRROR_JOINTS[JOINT_NAMES.index("left_elbow")] == JOINT_NAMES.index("right_elbow")
    assert all(MIRROR_JOINTS[MIRROR_JOINTS[j]] == j for j in range(24))
    # Posed joints of the mirrored pose = the posed joints reflected (x -> -x), left and
    # right swapped, on a left/right symmetric skeleton.
    rest = torch.as_tensor(TOY_JOINTS, dtype=torch.float64)
    assert torch.allclose(rest[list(MIRROR_JOINTS)] * torch.tensor([-1.0, 1, 1], dtype=torch.float64), rest)

    def posed(p):
        R = axis_angle_to_matrix(torch.as_tensor(p).reshape(-1, 24, 3))
        return rigid_transforms(R, rest.expand(len(p), 24, 3), torch.as_tensor(PARENTS))[0]

    reflected = posed(x)[:, list(MIRROR_JOINTS)] * torch.tensor([-1.0, 1, 1], dtype=torch.float64)
    torch.testing.assert_close(posed(mirror_pose(x)), reflected)
    with pytest.raises(InputError, match="72 .* or 69"):
        mirror_pose(np.zeros((2, 71)))


# ----------------------------------------------------------------------------- plausibility


def test_implausible_poses_score_high_without_data(prior):
    """No mocap needed: uniform random rotations and broken joints on top of the
    prior's own component means (the most plausible poses) score far above them."""
    means = np.zeros((prior.num_components, 72))
    means[:, prior.columns] = prior.means
    e_means = _energy(prior, means)
    # at its own mean a component costs only its constant c_k - min c
    assert (e_means <= prior.log_normalizers - prior.log_normalizers.min() + 1e-3).all() and e_means.max() < 50
    e_rand = _energy(prior, _uniform_rotations(200, 6))
    assert e_rand.min() > 1000
    deg = np.full((prior.num_components, 2), 60.0)
    assert (_energy(prior, _knees_backward(means, deg)) > e_means + 30).all()
    assert (_energy(prior, _elbows_hyperextended(means, deg)) > e_means + 100).all()


@pytest.fixture(scope="module")
def held_out():
    """``(N, 72)`` poses of test-split clips (first 90 frames of each), retargeted as in
    training; the prior never saw these subjects."""
    if not all((PRIOR_DATA / f).exists() for f in HELD_OUT):
        pytest.skip(f"CMU prior mocap not found at {PRIOR_DATA} (shared data absent)")
    from flowmocap.body import load_body_model
    from flowmocap.io import read_mocap
    from flowmocap.io.retarget import retarget

    model = load_body_model("default")
    clips = [retarget(read_mocap(PRIOR_DATA / f).slice(0, 90), model, origin=None, ground=None).poses
             for f in HELD_OUT]
    return np.concatenate(clips)


def test_held_out_mocap_low_implausible_high(prior, held_out):
    e = _energy(prior, held_out)
    p90 = np.percentile(e, 90)
    assert np.median(e) < 60, np.median(e)
    rng = np.random.default_rng(7)
    deg = rng.uniform(40, 90, (len(held_out), 2))
    knees = _energy(prior, _knees_backward(held_out, deg))
    elbows = _energy(prior, _elbows_hyperextended(held_out, deg))
    rand = _energy(prior, _uniform_rotations(len(held_out), 8))
    assert np.median(knees) > 1.5 * np.median(e) and np.median(knees) > p90
    assert (knees > e).mean() > 0.95
    assert np.median(elbows) > 5 * np.median(e) and (elbows > p90).mean() > 0.95
    assert rand.min() > 20 * p90
    # the prior is (nearly) left/right symmetric: mirrored held-out poses score alike
    em = _energy(prior, mirror_pose(held_out))
    assert abs(np.median(em) - np.median(e)) < 0.1 * np.median(e)


def test_held_out_poses_beat_their_limbs_mirrored_in_depth(prior, held_out):
    """The flip test's alternative (one limb mirrored about the camera ray through it,
    benchmarks/prior_flip.py): the prior prefers the real held-out pose. A forearm or shin
    mirrored bends its elbow or knee the wrong way and nearly always loses; an upper arm
    or thigh mirrored is often a plausible pose too (benchmarks/results/prior_flip_test.md:
    0.82-0.93 on the whole test split)."""
    from flowmocap.body import load_body_model
    from flowmocap.fit.energies import DEPTH_LIMBS

    mod = load_script(Path(__file__).resolve().parents[1] / "benchmarks" / "prior_flip.py")
    poses = np.asarray(held_out[::3], np.float64)
    model = load_body_model("default", dtype=torch.float64)
    index, which, flipped, moved = mod.mirrors(model, poses, DEPTH_LIMBS, np.random.default_rng(0))
    r = mod.discrimination(_energy(prior, poses, torch.float64), _energy(prior, flipped, torch.float64), index, which,
                           moved, len(DEPTH_LIMBS))
    assert r["mirrors"] > 300
    assert r["accuracy"] > 0.85 and r["median_margin"] > 10, r
    lower = [k for k, (p, c) in enumerate(DEPTH_LIMBS) if "elbow" in JOINT_NAMES[p] or "knee" in JOINT_NAMES[p]]
    assert all(r["per_limb"][k]["accuracy"] > 0.95 for k in lower), r["per_limb"]
    # a prior that knows nothing (the same energy for every pose) scores a tie, one half
    flat = mod.discrimination(np.zeros(len(poses)), np.zeros(len(which)), index, which, moved, len(DEPTH_LIMBS))
    assert flat["accuracy"] == 0.5


def _small_prior():
    from flowmocap.fit.pose_prior import PosePrior

    rng = np.random.default_rng(0)
    K, joints = 3, (1, 2)
    D = 3 * len(joints)
    means = rng.normal(0, 0.3, (K, D))
    Ls = []
    for k in range(K):
        A = np.tril(rng.normal(0, 0.5, (D, D)), -1) + np.diag(rng.uniform(1.0, 3.0, D))
        Ls.append(A if k % 2 == 0 else A.T)  # lower and upper triangular factors
    w = np.array([0.5, 0.3, 0.2])
    return PosePrior(w, means, np.stack(Ls), joints)


@pytest.mark.parametrize("which", ["small", "packaged"])
def test_mixture_energies_and_likelihood_match_scipys_gaussians(which):
    """component_energies, energy and log_likelihood against the Gaussian mixture written
    out with scipy (P_k = L_k L_k^T, weights w_k), including a rotation past pi (wrapped)."""
    from scipy.stats import multivariate_normal

    from flowmocap.fit.pose_prior import PosePrior

    prior = _small_prior() if which == "small" else PosePrior.load()
    rng = np.random.default_rng(1)
    B = 4
    pose = np.zeros((B, 72))
    cols = prior.columns
    pose[:, cols] = prior.means[rng.integers(0, prior.num_components, B)] + rng.normal(0, 0.1, (B, prior.dim))
    x = pose[:, cols].copy()
    # one joint given as its equivalent rotation vector with angle 2 pi - theta > pi
    j = cols[:3]
    r = pose[0, j]
    th = np.linalg.norm(r)
    pose[0, j] = r / th * (th - 2 * math.pi)
    pt = torch.tensor(pose)

    comps, ll = [], []
    for k in range(prior.num_components):
        P = prior.precisions_cholesky[k] @ prior.precisions_cholesky[k].T
        cov = np.linalg.inv(P)
        d = x - prior.means[k]
        comps.append(0.5 * np.einsum("bi,ij,bj->b", d, P, d) + prior.log_normalizers[k])
        ll.append(np.log(prior.weights[k]) + multivariate_normal(prior.means[k], cov).logpdf(x))
    comps = np.stack(comps, 1)
    want_e = comps - prior.log_normalizers.min()
    np.testing.assert_allclose(prior.component_energies(pt).numpy(), want_e, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(prior.energy(pt).numpy(), want_e.min(1), rtol=1e-9, atol=1e-9)
    want_ll = np.logaddexp.reduce(np.stack(ll, 1), axis=1)
    np.testing.assert_allclose(prior.log_likelihood(pt).numpy(), want_ll, rtol=1e-9, atol=1e-8)
