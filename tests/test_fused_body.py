"""flowmocap.body.fused: the posed body of a fixed shape as one compiled pass with a
hand-written gradient, against the torch body model and finite differences."""

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.body.fused import make_rig, posed_body
from flowmocap.errors import InputError


def _poses(seed: int, dtype=torch.float64) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    big = 1.2 * torch.randn(72, generator=g, dtype=dtype)  # angles up to ~2.5 rad
    small = 0.03 * torch.randn(72, generator=g, dtype=dtype)  # every joint in the Taylor branch
    mixed = big.clone()
    mixed[3::6] = 0.0  # some joints exactly at zero
    mixed[:3] = torch.tensor([0.0, 3.3, 0.2])  # a root beyond pi
    return [big, small, mixed, torch.zeros(72, dtype=dtype)]


def _outputs(out, with_vertices=True):
    parts = [out.joints, out.transforms]
    return parts + [out.vertices] if with_vertices else parts


@pytest.mark.parametrize("posedirs", [True, False])
def test_same_body_and_gradient_as_the_torch_model(toy_model, posedirs):
    model = toy_model
    saved = model.posedirs
    if not posedirs:
        model.posedirs = None
    try:
        betas = 0.5 * torch.randn(1, 10, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        shaped = model.shaped(betas)
        rig = make_rig(model, shaped)
        for k, pose in enumerate(_poses(4)):
            trans = torch.tensor([0.3, -0.2, 4.0], dtype=torch.float64)
            for with_vertices in (True, False):
                p1, t1 = pose.clone().requires_grad_(), trans.clone().requires_grad_()
                p2, t2 = pose.clone().requires_grad_(), trans.clone().requires_grad_()
                ref = model(betas=betas, pose=p1[None], trans=t1[None], shaped=shaped, with_vertices=with_vertices)
                got = posed_body(rig, p2, t2, with_vertices=with_vertices)
                assert (got.vertices is None) == (not with_vertices)
                for a, b in zip(_outputs(got, with_vertices), _outputs(ref, with_vertices)):
                    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
                # a random linear functional of every output: the gradients must agree
                g = torch.Generator().manual_seed(10 + k)
                weights = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in _outputs(ref, with_vertices)]
                sum(((w * x).sum() for w, x in zip(weights, _outputs(ref, with_vertices)))).backward()
                sum(((w * x).sum() for w, x in zip(weights, _outputs(got, with_vertices)))).backward()
                torch.testing.assert_close(p2.grad, p1.grad, rtol=1e-9, atol=1e-9)
                torch.testing.assert_close(t2.grad, t1.grad, rtol=1e-9, atol=1e-9)
    finally:
        model.posedirs = saved


def test_gradient_matches_finite_differences(toy_model):
    rig = make_rig(toy_model, toy_model.shaped(torch.zeros(1, 10, dtype=torch.float64)))
    sel = torch.arange(0, toy_model.num_vertices, 13)
    for pose in _poses(5)[:3]:
        trans = torch.tensor([0.1, 0.2, 3.0], dtype=torch.float64, requires_grad=True)

        def f(p, t):
            out = posed_body(rig, p, t)
            return out.vertices[0, sel], out.joints, out.transforms

        assert torch.autograd.gradcheck(f, (pose.clone().requires_grad_(), trans), eps=1e-6, atol=1e-6)


def test_only_the_outputs_used_carry_gradient(toy_model):
    rig = make_rig(toy_model, toy_model.shaped(None))
    pose = _poses(6)[0].requires_grad_()
    trans = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    out = posed_body(rig, pose, trans)
    out.joints[0, 5, 1].backward()
    ref_pose = pose.detach().clone().requires_grad_()
    ref = toy_model(pose=ref_pose[None], trans=trans.detach()[None], shaped=rig.shaped)
    ref.joints[0, 5, 1].backward()
    torch.testing.assert_close(pose.grad, ref_pose.grad, rtol=1e-9, atol=1e-12)
    assert torch.equal(trans.grad, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_float32_model_and_the_default_body():
    model = load_body_model()  # float32, no pose blend shapes
    betas = torch.zeros(1, 10)
    shaped = model.shaped(betas)
    rig = make_rig(model, shaped)
    pose = (0.4 * torch.randn(72, generator=torch.Generator().manual_seed(7))).requires_grad_()
    trans = torch.tensor([0.0, 0.1, 3.0], requires_grad=True)
    got = posed_body(rig, pose, trans)
    ref = model(betas=betas, pose=pose[None], trans=trans[None], shaped=shaped)
    assert got.vertices.dtype == torch.float32
    for a, b in zip(_outputs(got), _outputs(ref)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6)
    (g_got,) = torch.autograd.grad(got.vertices.square().sum(), pose)
    (g_ref,) = torch.autograd.grad(ref.vertices.square().sum(), pose)
    # the gradient's entries reach ~1.7e4 here; a small entry is a float32 sum of large terms
    # that cancel, so the absolute tolerance follows the largest entry (float32 rounding
    # differs between CPUs: one entry of ~2 moved by 1e-3 on one machine)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-4, atol=1e-6 * float(g_ref.abs().max()))


def test_non_finite_pose_is_the_models_input_error(toy_model):
    rig = make_rig(toy_model, toy_model.shaped(None))
    pose = torch.zeros(72, dtype=torch.float64)
    pose[7] = float("nan")
    with pytest.raises(InputError, match="pose contains NaN"):
        posed_body(rig, pose, torch.zeros(3, dtype=torch.float64))
    with pytest.raises(InputError, match="trans contains NaN"):
        posed_body(rig, torch.zeros(72, dtype=torch.float64), torch.tensor([0.0, np.inf, 1.0], dtype=torch.float64))
    with pytest.raises(InputError, match="one shape"):
        make_rig(toy_model, toy_model.shaped(torch.zeros(2, 10, dtype=torch.float64)))
