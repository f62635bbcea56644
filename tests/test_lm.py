"""Levenberg-Marquardt on the stacked residuals (fit.lm): residuals and Jacobians against
frame_energy, finite differences and flow_residuals; the solver against L-BFGS."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.body.skeleton import EVAL_JOINTS
from flowmocap.errors import InputError, OptimizationError
from flowmocap.fit import lm
from flowmocap.fit.config import TrackerConfig
from flowmocap.fit.jacobian import projection_jacobian, skinned_point_jacobian
from flowmocap.fit.tracker import FrameState, Scene, frame_data, frame_energy, keypoint_observation, track_frame
from flowmocap.io.sequence import load_sequence
from flowmocap.render import flow_residuals, rasterize, render_flow
from flowmocap.synth import synthesize

CFG = TrackerConfig(silhouette_model="mesh")


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small tensors on a shared 2-core machine: one torch thread is several times faster."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("lmclip") / "seq"
    synthesize("builtin:walk", d, size="160x120", frames=4, flow=False)
    return load_sequence(d)


def _scene(seq, dtype):
    model = load_body_model("default", dtype=dtype)
    return Scene(model, torch.as_tensor(seq.gt["betas"], dtype=dtype)[None], seq.camera)


def _state(seq, i, dtype):
    return FrameState(torch.as_tensor(seq.gt["poses"][i], dtype=dtype), torch.as_tensor(seq.gt["trans"][i], dtype=dtype))


def _frame(seq, scene, i, cfg=CFG):
    """Frame i's data with the flow rendered from the ground truth as the observation."""
    prev, cur = _state(seq, i - 1, scene.betas.dtype), _state(seq, i, scene.betas.dtype)
    with torch.no_grad():
        _, prev_px, _ = scene.forward(prev.pose, prev.trans)
        _, px, depth = scene.forward(cur.pose, cur.trans)
    r = rasterize(px.double().numpy(), depth.double().numpy(), scene.faces, seq.size[1], seq.size[0],
                  cull_backfaces=True)
    flow, _ = render_flow(r, px.double().numpy(), prev_px.double().numpy(), scene.faces)
    # detected joints: the true ones with 2 px noise, one far off (the robust tail), two missing
    with torch.no_grad():
        out, _, _ = scene.forward(cur.pose, cur.trans)
        j2d = scene.camera.project(out.joints[0]).double().numpy()
    j2d += np.random.default_rng(i).normal(scale=2.0, size=j2d.shape)
    j2d[5] += 40.0
    conf = np.full(24, 0.9)
    conf[[10, 11]] = 0.1
    return frame_data(seq.mask(i), flow, cfg, 1.0, keypoint_observation(j2d, conf)), prev, prev_px


def _wild_state(seq, dtype):
    """A state of frame 2 with many joint limits exceeded and capsules interpenetrating."""
    base = _state(seq, 2, dtype)
    rng = np.random.default_rng(0)
    pose = base.pose + torch.as_tensor(rng.normal(scale=0.6, size=72), dtype=dtype)
    pose[:3] = base.pose[:3]
    return FrameState(pose, base.trans + torch.tensor([0.03, -0.02, 0.05], dtype=dtype))


def _near_state(seq, dtype, scale=0.05, seed=1):
    base = _state(seq, 2, dtype)
    rng = np.random.default_rng(seed)
    return FrameState(base.pose + torch.as_tensor(rng.normal(scale=scale, size=72), dtype=dtype),
                      base.trans + torch.as_tensor(rng.normal(scale=0.02, size=3), dtype=dtype))


def test_stacked_residuals_sum_to_frame_energy(clip):
    scene = _scene(clip, torch.float64)
    data, prev, prev_px = _frame(clip, scene, 2)
    for state in (_wild_state(clip, torch.float64), _near_state(clip, torch.float64)):
        for stage in range(len(CFG.stages)):
            total, terms = frame_energy(scene, state, data, CFG, stage, prev_px, prev.pose)
            blocks = lm.residual_blocks(scene, state, data, CFG, stage, prev_px, prev.pose)
            assert {b.name for b in blocks} == set(terms)
            for b in blocks:
                assert b.J.shape == (b.r.shape[0], 75)
                np.testing.assert_allclose(b.r @ b.r, terms[b.name], rtol=1e-9, atol=1e-12, err_msg=b.name)
            r, J = lm.stacked_residuals(scene, state, data, CFG, stage, prev_px, prev.pose)
            np.testing.assert_allclose(r @ r, float(total), rtol=1e-9)
    # the wild state exercises every block
    blocks = {b.name: b for b in lm.residual_blocks(scene, _wild_state(clip, torch.float64), data, CFG, 1,
                                                    prev_px, prev.pose)}
    assert (blocks["limits"].r != 0).sum() >= 3 and (blocks["penetration"].r != 0).sum() >= 2
    # float32 (as the tracker runs): the same up to float32 rounding
    scene32 = _scene(clip, torch.float32)
    data32, prev32, prev_px32 = _frame(clip, scene32, 2)
    st = _near_state(clip, torch.float32)
    total, _ = frame_energy(scene32, st, data32, CFG, 1, prev_px32, prev32.pose)
    r, _ = lm.stacked_residuals(scene32, st, data32, CFG, 1, prev_px32, prev32.pose)
    np.testing.assert_allclose(r @ r, float(total), rtol=1e-5)


def test_jacobian_matches_finite_differences_and_the_gradient(clip):
    scene = _scene(clip, torch.float64)
    data, prev, prev_px = _frame(clip, scene, 2)
    state = _wild_state(clip, torch.float64)
    x0 = torch.cat([state.pose, state.trans])
    # without the flow renderer's occlusion-boundary rows (an approximation of the
    # derivative of a piecewise constant image) the Jacobian is the exact derivative
    r0, J = lm.stacked_residuals(scene, state, data, CFG, 1, prev_px, prev.pose, boundary=False)
    h = 1e-7
    for col in (0, 4, 3 * 1 + 0, 3 * 4 + 0, 3 * 16 + 2, 3 * 18 + 1, 72, 74):
        rs = []
        for sign in (1.0, -1.0):
            x = x0.clone()
            x[col] += sign * h
            rs.append(lm.stacked_residuals(scene, FrameState(x[:72], x[72:]), data, CFG, 1, prev_px, prev.pose,
                                           boundary=False)[0])
        assert rs[0].shape == rs[1].shape == r0.shape, "the coverage changed under the finite difference"
        fd = (rs[0] - rs[1]) / (2 * h)
        scale = max(np.abs(J[:, col]).max(), 1e-3)
        np.testing.assert_allclose(J[:, col], fd, atol=1e-5 * scale, err_msg=f"column {col}")
    # with the boundary rows: J^T r is half the gradient that L-BFGS follows
    r, J = lm.stacked_residuals(scene, state, data, CFG, 1, prev_px, prev.pose)
    p, t = state.pose.clone().requires_grad_(), state.trans.clone().requires_grad_()
    frame_energy(scene, FrameState(p, t), data, CFG, 1, prev_px, prev.pose)[0].backward()
    grad = torch.cat([p.grad, t.grad]).numpy()
    np.testing.assert_allclose(2 * J.T @ r, grad, rtol=1e-6, atol=1e-6 * np.abs(grad).max())


def test_flow_block_and_pixel_jacobian_match_the_reference_implementations(clip):
    scene = _scene(clip, torch.float64)
    data, prev, prev_px = _frame(clip, scene, 2)
    state = _near_state(clip, torch.float64)
    with torch.no_grad():
        out, px, depth = scene.forward(state.pose, state.trans)
    dpx = lm.pixel_jacobian(scene, out, state.pose)
    J3 = skinned_point_jacobian(state.pose.numpy(), out.transforms[0].numpy(), out.joints[0].numpy(),
                                out.rest_vertices[0].numpy(), scene.model.weights.numpy())
    P = projection_jacobian(out.vertices[0].numpy(), scene.camera.R, scene.camera.t, scene.camera.fx, scene.camera.fy)
    ref = np.einsum("nab,nbk->nak", P, J3)
    np.testing.assert_allclose(dpx, ref, atol=1e-7 * np.abs(ref).max())
    for stage in range(len(CFG.stages)):
        full = flow_residuals(px.numpy(), prev_px.numpy(), scene.faces, data.targets[stage], depth_cur=depth.numpy(),
                              cull_backfaces=True)
        Jf = full.jac_cur @ dpx.reshape(-1, 75)
        r, J, rest = lm.flow_block(px.numpy(), prev_px.numpy(), depth.numpy(), scene.faces, data.targets[stage], dpx)
        np.testing.assert_allclose(r @ r + rest, full.residuals @ full.residuals, rtol=1e-10)
        np.testing.assert_allclose(J.T @ J, Jf.T @ Jf, rtol=1e-8, atol=1e-10 * np.abs(Jf.T @ Jf).max())
        np.testing.assert_allclose(J.T @ r, Jf.T @ full.residuals, rtol=1e-8,
                                   atol=1e-10 * np.abs(Jf.T @ full.residuals).max())


def _joint_error_cm(scene, state, seq, i):
    with torch.no_grad():
        out, _, _ = scene.forward(state.pose, state.trans)
    ev = list(EVAL_JOINTS)
    return float(np.linalg.norm(out.joints[0].numpy()[ev] - seq.gt["joints3d"][i][ev], axis=1).mean() * 100)


def test_lm_reduces_the_energy_and_recovers_the_pose_like_lbfgs(clip):
    scene = _scene(clip, torch.float32)
    for i, seed in ((2, 1), (3, 2)):
        data, prev, prev_px = _frame(clip, scene, i)
        base = _state(clip, i, torch.float32)
        rng = np.random.default_rng(seed)
        init = FrameState(base.pose + torch.as_tensor(rng.normal(scale=0.06, size=72), dtype=torch.float32),
                          base.trans + torch.tensor([0.03, -0.02, 0.04]))
        with torch.no_grad():
            e_init = float(frame_energy(scene, init, data, CFG, 1, prev_px, prev.pose)[0])
        stats = {}
        s_lm, t_lm = lm.lm_track_frame(scene, init, data, CFG, prev, stats=stats)
        s_lb, t_lb = track_frame(scene, init, data, CFG, prev)
        assert set(t_lm) == set(t_lb) and s_lm.pose.shape == (72,) and s_lm.trans.shape == (3,)
        assert s_lm.pose.dtype == torch.float32
        assert t_lm["total"] < 0.2 * e_init
        assert stats["jacobians"] <= 2 * CFG.iterations
        err_init = _joint_error_cm(scene, init, clip, i)
        err_lm, err_lb = _joint_error_cm(scene, s_lm, clip, i), _joint_error_cm(scene, s_lb, clip, i)
        print(f"frame {i}: init {err_init:.2f} cm E {e_init:.3f}; LM {err_lm:.2f} cm E {t_lm['total']:.4f}; "
              f"L-BFGS {err_lb:.2f} cm E {t_lb['total']:.4f}")
        assert err_lm < 0.5 * err_init
        assert err_lm < 1.5 * err_lb + 0.5
        assert t_lm["total"] < 1.5 * t_lb["total"] + 1e-3


def test_lm_needs_the_mesh_silhouette_and_finite_values(clip):
    scene = _scene(clip, torch.float32)
    data, prev, _ = _frame(clip, scene, 2)
    with pytest.raises(InputError, match="silhouette_model='mesh'"):
        lm.lm_track_frame(scene, prev, data, TrackerConfig(silhouette_model="capsules"), prev)
    # without a mask the capsule setting does not matter
    data_nomask, _, _ = _frame(clip, scene, 2, TrackerConfig())
    data_nomask.mask, data_nomask.silhouette = None, None
    state, terms = lm.lm_track_frame(scene, prev, data_nomask, TrackerConfig(iterations=2), prev)
    assert "silhouette" not in terms and np.isfinite(terms["total"])
    bad = FrameState(prev.pose.clone(), prev.trans.clone())
    bad.trans[0] = float("nan")
    with pytest.raises(OptimizationError):
        lm.lm_track_frame(scene, bad, data, CFG, prev)
