"""A body's stature and the nearest shape of a stated one (flowmocap.body.stature), the first
frame's body moved with it (flowmocap.fit.init.given_stature), and ``track --height``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import flowmocap
from flowmocap.body import load_body_model
from flowmocap.body.stature import check_height, stature, stature_vertices, with_stature
from flowmocap.cli import main
from flowmocap.errors import InputError
from flowmocap.fit.init import given_stature
from flowmocap.geometry import PinholeCamera, look_at

from test_pipeline import QUICK, seq_dir  # noqa: F401  (fixture)


@pytest.fixture(scope="module", params=["neutral", "male", "female"])
def model(request):
    return load_body_model("default", gender=request.param, dtype=torch.float64)


def test_stature_is_the_rest_mesh_from_sole_to_crown(model):
    top, bottom = stature_vertices(model)
    for seed in range(4):
        b = torch.as_tensor(np.random.default_rng(seed).normal(size=(1, 10)) * (seed > 0))
        v = model.shaped(b)[0][0].numpy()  # the shaped rest mesh, through the body model
        assert stature(model, b) == pytest.approx(v[top, 1] - v[bottom, 1], abs=1e-9)
        # the two vertices are where the mesh ends, for the mean shape and near it for others
        assert v[:, 1].max() - v[:, 1].min() - stature(model, b) < 0.01
    assert 1.5 < stature(model, torch.zeros(10)) < 1.9  # an adult


def test_with_stature_gives_the_height_by_the_smallest_change_of_shape(model):
    b = torch.as_tensor(np.random.default_rng(7).normal(size=(1, 10)))
    new = with_stature(model, b, 1.85)
    assert new.shape == b.shape and new.dtype == b.dtype
    assert stature(model, new) == pytest.approx(1.85, abs=1e-9)
    # the change is along the stature's gradient (finite differences of the stature per coefficient) ...
    grad = np.array([(stature(model, b + 1e-3 * torch.eye(10)[k]) - stature(model, b - 1e-3 * torch.eye(10)[k])) / 2e-3
                     for k in range(10)])
    change = (new - b).numpy().reshape(-1)
    assert abs(abs(change @ grad) / (np.linalg.norm(change) * np.linalg.norm(grad)) - 1.0) < 1e-9
    # ... so any other shape of that stature is further from the fitted one
    other = new.numpy().reshape(-1) + np.concatenate([np.cross(grad[:3], [0.3, -0.2, 0.5]), np.zeros(7)])
    assert stature(model, torch.as_tensor(other)) == pytest.approx(1.85, abs=1e-9)
    assert np.linalg.norm(other - b.numpy().reshape(-1)) > np.linalg.norm(change)
    same = with_stature(model, b, stature(model, b))
    np.testing.assert_allclose(same.numpy(), b.numpy(), atol=1e-12)


@pytest.mark.parametrize("bad", [0.3, 3.0, float("nan"), "tall", None])
def test_a_height_outside_what_people_measure_is_refused(bad):
    with pytest.raises(InputError, match="standing height in metres, between 0.5 and 2.5"):
        check_height(bad)
    assert check_height("1.7") == 1.7


def test_the_first_frames_body_keeps_its_place_in_the_image(model):
    R, t = look_at([2.0, 1.0, 3.0], [0.1, 0.9, 0.0])
    cam = PinholeCamera.from_focal(640, 480, 600.0, R=R, t=t)
    b = torch.as_tensor(np.random.default_rng(3).normal(size=(1, 10)), dtype=torch.float32)
    trans = torch.tensor([0.2, 0.95, 0.1])
    m32 = load_body_model("default", gender=model.gender, dtype=torch.float32)
    new, moved = given_stature(m32, cam, b, trans, 1.90)
    with torch.no_grad():
        root_old = (m32(betas=b, with_vertices=False).joints[0, 0] + trans).double().numpy()
        root_new = (m32(betas=new, with_vertices=False).joints[0, 0] + moved).double().numpy()
    assert moved.dtype == trans.dtype
    np.testing.assert_allclose(cam.project(root_new[None]), cam.project(root_old[None]), atol=1e-3)  # px
    dist = lambda p: np.linalg.norm(R @ p + t)  # noqa: E731
    assert dist(root_new) / dist(root_old) == pytest.approx(1.90 / stature(m32, b), rel=1e-5)


def test_track_with_a_height_gives_the_body_that_stature(seq_dir, tmp_path, capsys):  # noqa: F811
    init = seq_dir.parent / "init.json"
    args = ["track", str(seq_dir), "--init", str(init), "--config", str(seq_dir.parent / "quick.json"),
            "--joints3d", "off", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "bad"), "--height", "17.5"]) == 2
    assert "standing height in metres" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()  # refused before any work
    assert main([*args, "--out", str(tmp_path / "own")]) == 0
    own = flowmocap.load_result(tmp_path / "own")
    assert "one camera's estimate: give --height" in capsys.readouterr().out
    body = load_body_model("default")
    assert own.run["body"] == {"stature_m": round(stature(body, own.betas), 4), "height_given_m": None}
    assert main([*args, "--out", str(tmp_path / "tall"), "--height", "1.93"]) == 0
    tall = flowmocap.load_result(tmp_path / "tall")
    assert stature(body, tall.betas) == pytest.approx(1.93, abs=1e-4)  # float32 betas
    assert tall.run["body"]["height_given_m"] == 1.93 and tall.run["config"]["body_height_m"] == 1.93
    assert json.loads((tmp_path / "tall" / "run.json").read_text())["body"]["stature_m"] == pytest.approx(1.93, abs=1e-4)
    # a taller body for the same images stands further from the camera
    cam = tall.camera
    depth = lambda r: np.median((r.joints3d[:, 0] @ np.asarray(cam.R).T + np.asarray(cam.t))[:, 2])  # noqa: E731
    ratio = 1.93 / own.run["body"]["stature_m"]
    assert depth(tall) / depth(own) == pytest.approx(ratio, rel=0.05)
    # and is seen where the other was
    assert np.median(np.linalg.norm(tall.joints2d - own.joints2d, axis=-1)) < 3.0


def test_a_fitted_stature_is_held_within_what_people_measure(model):
    from flowmocap.body.stature import FITTED_STATURE_M, held_stature

    b = np.zeros(10)
    assert held_stature(model, b) is None  # the mean shape is a person
    a = np.zeros(10)
    a[0] = 1.0
    slope = stature(model, a) - stature(model, b)  # the stature is linear in the shape
    lo, hi = FITTED_STATURE_M
    for target, held in ((hi + 0.3, hi), (lo - 0.2, lo), (0.5 * (lo + hi), None)):
        a[0] = (target - stature(model, b)) / slope
        assert stature(model, a) == pytest.approx(target, abs=1e-9)
        assert held_stature(model, a) == held


def test_a_first_frame_no_person_could_be_is_held_at_the_nearer_bound(seq_dir, tmp_path, capsys,  # noqa: F811
                                                                       monkeypatch):
    """A first frame's fit that makes a giant (as a mask holding a tree does): the body is held
    at 2.2 m, where the image put it, and the run says so."""
    from flowmocap.fit import init as init_module

    fit = init_module.fit_frame0

    def giant(*args, **kwargs):
        pose, trans, betas, terms = fit(*args, **kwargs)
        betas = betas.clone()
        betas[0, 0] += 14.0  # about 3.3 m
        return pose, trans, betas, terms

    monkeypatch.setattr(init_module, "fit_frame0", giant)
    args = ["track", str(seq_dir), "--init", str(seq_dir.parent / "init.json"), "--config",
            str(seq_dir.parent / "quick.json"), "--joints3d", "off", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "held")]) == 0
    said = capsys.readouterr().out
    res = flowmocap.load_result(tmp_path / "held")
    held = res.run["init_stature_held"]
    assert held["fitted_m"] > 3.0 and held["held_m"] == 2.2
    assert stature(load_body_model("default"), res.betas) == pytest.approx(2.2, abs=1e-3)
    assert "which no person is" in said and "held at 2.20 m" in said
    # a stated height is the person's, whatever the fit made
    assert main([*args, "--out", str(tmp_path / "stated"), "--height", "1.7"]) == 0
    stated = flowmocap.load_result(tmp_path / "stated")
    assert "init_stature_held" not in stated.run
    assert stature(load_body_model("default"), stated.betas) == pytest.approx(1.7, abs=1e-3)
