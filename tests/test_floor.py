"""The people of one video on one floor (flowmocap.export.floor): a body scaled about the
camera centre, the factor that stands a person on another's floor, and the people folder's
exports, page and overlay video using it."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.body.stature import scaled_shape, stature, with_stature
from flowmocap.cli import main
from flowmocap.errors import DataError
from flowmocap.export import load_fitted_motion
from flowmocap.export.floor import (FLOOR_FILE, SCALE_RANGE, floor_in_camera, floor_owner, floor_scale, people_floor,
                                    scaled_about_camera, standing_feet_in_camera)
from flowmocap.io.results import write_motion, write_run

from test_ground import _walk_result


def _rest_mesh(model, betas) -> np.ndarray:
    """``(V, 3)`` the rest mesh of shape ``betas`` relative to its root joint (the template plus
    the shape's offsets, as the model shapes it)."""
    b = torch.as_tensor(np.asarray(betas, np.float64)[None])
    with torch.no_grad():
        out = model(betas=b, pose=torch.zeros(1, 72, dtype=torch.float64), trans=torch.zeros(1, 3, dtype=torch.float64))
    return (out.vertices[0] - out.joints[0, 0]).double().numpy()


def test_scaled_shape_is_nearly_the_body_scaled_about_its_root():
    model = load_body_model("default")
    betas = np.random.default_rng(3).normal(0.0, 1.0, 10)
    np.testing.assert_allclose(scaled_shape(model, betas, 1.0), betas, atol=1e-8)  # no scaling: the same shape
    base = _rest_mesh(model, betas)
    for s in (0.8, 1.25):
        fitted = np.linalg.norm(_rest_mesh(model, scaled_shape(model, betas, s)) - s * base, axis=1)
        along = with_stature(model, torch.as_tensor(betas[None]), s * stature(model, betas))[0].numpy()
        stature_only = np.linalg.norm(_rest_mesh(model, along) - s * base, axis=1)
        assert np.median(fitted) < 0.008 and fitted.max() < 0.04, (s, np.median(fitted), fitted.max())
        assert np.median(fitted) < np.median(stature_only) / 3  # why it is not the stature's direction alone
        assert stature(model, scaled_shape(model, betas, s)) == pytest.approx(s * stature(model, betas), rel=0.01)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The built-in walk (75 frames, feet on its floor) seen by a camera 1.5 m up, pitched
    10 degrees down; the result's world is the camera's frame, as for a video."""
    d = tmp_path_factory.mktemp("floor") / "person0"
    _walk_result(d, 10.0, height=1.5)
    return d


def _write(folder, motion, like):
    """``motion`` (the result's own frame, ``frame="world"``) written as a result folder."""
    from flowmocap.io.results import read_result

    arrays, run = read_result(like)
    j = motion.joints()
    write_motion(folder, {**arrays, "poses": motion.poses.astype(np.float32), "trans": motion.trans.astype(np.float32),
                          "betas": np.asarray(motion.betas, np.float32), "joints3d": j.astype(np.float32),
                          "joints2d": motion.camera.project(j).astype(np.float32)})
    write_run(folder, run)
    return folder


def test_a_body_scaled_about_the_camera_keeps_its_image(walk):
    m = load_fitted_motion(walk, frame="world")
    big = scaled_about_camera(m, 1.3)
    R, t = np.asarray(m.camera.R), np.asarray(m.camera.t)
    root = lambda x: x.joints()[:, 0] @ R.T + t  # noqa: E731 -- the root joint in camera coordinates
    np.testing.assert_allclose(root(big), 1.3 * root(m), atol=1e-6)  # the root: 1.3 times as far along its ray
    shift = np.linalg.norm(big.joints2d - m.camera.project(m.joints()), axis=-1)
    assert np.median(shift) < 1.0 and shift.max() < 3.0, (np.median(shift), shift.max())  # 320x240 px frames
    assert stature(m.model, big.betas) == pytest.approx(1.3 * stature(m.model, m.betas), rel=0.01)
    assert big.world is None
    with pytest.raises(DataError, match="positive"):
        scaled_about_camera(m, 0.0)


def test_a_person_scaled_off_the_floor_is_stood_back_on_it(walk):
    first = load_fitted_motion(walk, frame="ground")
    n, d = floor_in_camera(first)
    assert d == pytest.approx(-1.5, abs=0.03)  # the camera 1.5 m above the floor
    # the same walk 1.25 times as large and as far: its feet 1.25 x 1.5 m below the camera
    other = replace(scaled_about_camera(first, 1.25), world=first.world)  # still feet: the same frames
    feet = standing_feet_in_camera(other, n)
    assert len(feet) > 20 and np.median(feet @ n) == pytest.approx(1.25 * d, rel=0.02)
    fit = floor_scale(other, first)
    assert fit.scale == pytest.approx(0.8, rel=0.02) and fit.why is None
    assert fit.stature_m == pytest.approx(stature(first.model, first.betas), rel=0.02)
    back = replace(scaled_about_camera(other, fit.scale), world=first.world)
    assert np.median(np.abs(standing_feet_in_camera(back, n) @ n - d)) < 0.01  # on the floor to a centimetre

    # on a box: feet 0.7 m above the floor would need 1.5 / 0.8 of the size: refused
    up = first.camera.R.T @ n  # the floor's normal in the export frame
    boxed = replace(first, trans=first.trans + 0.7 * up)
    fit = floor_scale(boxed, first)
    assert fit.scale is None and "not the same floor" in fit.why and not SCALE_RANGE[0] <= 1.5 / 0.8 <= SCALE_RANGE[1]
    # never standing still: no factor
    still = replace(first.world, contacts=np.zeros_like(first.world.contacts))
    fit = floor_scale(replace(other, world=still), first)
    assert fit.scale is None and "too few" in fit.why
    # a first floor not fitted to standing feet is nobody's
    guessed = replace(first.world, plane=replace(first.world.plane, method="fallback"))
    assert "not fitted" in floor_scale(other, replace(first, world=guessed)).why
    with pytest.raises(DataError, match="frame='ground'"):
        floor_in_camera(load_fitted_motion(walk, frame="world"))


@pytest.fixture(scope="module")
def people(walk, tmp_path_factory):
    """A people folder: person0 the walk, person1 the same walk 1.25 times as large and far."""
    root = tmp_path_factory.mktemp("floor_people")
    import shutil

    shutil.copytree(walk, root / "person0")
    _write(root / "person1", scaled_about_camera(load_fitted_motion(walk, frame="world"), 1.25), walk)
    (root / "people.json").write_text(json.dumps({"input": "missing", "people": {
        "person0": {"rank": 0, "tracked": True}, "person1": {"rank": 1, "tracked": True}}}))
    return root


def test_people_folders_are_exported_on_one_floor(people, capsys):
    fits = people_floor([people / "person0", people / "person1"])
    assert fits[0].scale == 1.0 and fits[1].scale == pytest.approx(0.8, rel=0.02)

    def ankles(out):  # (T, 2, 3) the exported ankles, the first person's ground frame
        frames = json.loads((out / "person1.json").read_text())["frames"]
        return np.array([f["joints3d"] for f in frames])[:, [7, 8]]

    assert main(["export", str(people), "-f", "json", "--out", str(people / "a"), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "person1: stood on person0's floor: 0.8" in said and "on one floor (floor.json)" in said
    doc = json.loads((people / "a" / FLOOR_FILE).read_text())
    assert doc["shared"] and doc["people"]["person1"]["scale"] == pytest.approx(0.8, rel=0.02)
    first = np.array([f["joints3d"] for f in json.loads((people / "a" / "person0.json").read_text())["frames"]])
    # person1 carries its own foot contacts, found in its own ground frame
    contacts = [f["contact"] for f in json.loads((people / "a" / "person1.json").read_text())["frames"]]
    own = load_fitted_motion(people / "person1", frame="ground").world.contacts
    assert contacts == own.tolist() and own.any()
    # on one floor the two are the same walk again, to a centimetre or so
    assert np.median(np.abs(ankles(people / "a") - first[:, [7, 8]])) < 0.01
    assert main(["export", str(people), "-f", "json", "--out", str(people / "b"), "--own-size", "--quiet"]) == 0
    assert not json.loads((people / "b" / FLOOR_FILE).read_text())["shared"]
    own = ankles(people / "b")
    assert np.median(own[..., 1] - first[:, [7, 8], 1]) < -0.2  # its own size: its feet well below the floor
    assert main(["export", str(people / "person0"), "-f", "json", "--own-size"]) == 2  # one result: refused


def test_the_page_and_the_overlay_video_use_the_floor(people, tmp_path, capsys):
    import imageio.v3 as iio

    from flowmocap.commands.view import ViewerData

    data = ViewerData(people)
    assert data.floor[1].scale == pytest.approx(0.8, rel=0.02)
    a, b = (p["motion"].joints() for p in data.people)
    assert np.median(np.abs(a - b)) < 0.01  # the same walk, on one floor
    assert ViewerData(people, floor=False).floor is None
    frames = tmp_path / "frames"  # grey frames of the walk's size
    frames.mkdir()
    for i in range(75):
        iio.imwrite(frames / f"{i:06d}.png", np.full((240, 320, 3), 90, np.uint8))
    assert main(["render", str(people), "--out", str(tmp_path), "--quiet", "--input", str(frames)]) == 0
    said = capsys.readouterr().out
    assert "person1: stood on person0's floor: 0.8" in said and (tmp_path / "overlay.mp4").stat().st_size > 0
    assert main(["render", str(people), "--out", str(tmp_path), "--quiet", "--input", str(frames), "--own-size"]) == 0
    assert "stood on" not in capsys.readouterr().out


def test_the_page_puts_a_disc_under_every_persons_standing_feet(people):
    """meta.json gives each person their own foot contacts and lowest foot points (person1 on
    person0's floor: at its height), and the page shows a disc under each standing foot."""
    from test_view import _chromium, _chromium_run, _get, _serving

    from flowmocap.commands.view import ViewerData

    for data, url in _serving(ViewerData(people)):
        meta = json.loads(_get(url + "/api/meta.json")[2])
        p0, p1 = meta["people"]
        assert p1["contacts"] == load_fitted_motion(people / "person1", frame="ground").world.contacts.astype(int).tolist()
        standing = [k for k, c in enumerate(p1["contacts"]) if any(c)]
        assert standing and p0["contacts"] == meta["contacts"]
        heights = [p1["feet"][k][s][1] for k in standing for s in (0, 1) if p1["contacts"][k][s]]
        assert abs(np.median(heights)) < 0.02  # person1's standing feet on person0's floor (y = 0)
        if _chromium() is None:
            pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
        k = standing[0]
        dom = _chromium_run(url + f"/?frame={k}", "--dump-dom")
        assert 'data-ready="1"' in dom.stdout, dom.stderr[-2000:]
        want = "".join(str(c) for p in (p0, p1) for c in p["contacts"][k])
        assert f'data-feet="{want}"' in dom.stdout and want[2:] != "00"


@pytest.fixture(scope="module")
def reviewed_people(people, tmp_path_factory):
    """The people folder with the 3D sources' disagreement: person0's first frames part most,
    person1's last ones."""
    import shutil

    from flowmocap.io.results import read_result, write_motion

    root = tmp_path_factory.mktemp("floor_review")
    for name in ("person0", "person1"):
        shutil.copytree(people / name, root / name)
    shutil.copy(people / "people.json", root / "people.json")
    for name, ramp in (("person0", -1), ("person1", 1)):
        motion, _ = read_result(root / name)
        T = len(motion["poses"])
        dis = np.repeat((0.05 + 0.001 * ramp * np.arange(T))[:, None], 24, 1).astype(np.float32)
        write_motion(root / name, {**motion, "disagreement": dis})
    return root


def test_every_persons_frames_to_review_are_marked(reviewed_people, tmp_path):
    """Each person's frames to review are theirs on the page (meta per person, the union at the
    top, the label naming whose) and in the people overlay video (a red frame)."""
    import imageio.v3 as iio

    from test_view import _chromium, _chromium_run, _get, _serving

    from flowmocap.commands.view import ViewerData

    first, last = 2, 72  # among person0's and person1's flagged tenth; frame 40 is nobody's
    for data, url in _serving(ViewerData(reviewed_people)):
        meta = json.loads(_get(url + "/api/meta.json")[2])
        p0, p1 = meta["people"]
        assert p0["review"][first] == 1 and p1["review"][first] == 0
        assert p0["review"][last] == 0 and p1["review"][last] == 1
        assert sum(p0["review"]) == sum(p1["review"]) == 8  # the tenth of 75 frames each
        assert meta["review"] == [a | b for a, b in zip(p0["review"], p1["review"])] and meta["review"][40] == 0
        assert p1["disagreement_cm"][last] == pytest.approx(5.0 + 0.1 * last, abs=0.05)
        assert meta["disagreement_cm"] == p0["disagreement_cm"]
        if _chromium() is None:
            pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
        for k, want in ((first, "10"), (last, "01"), (40, "00")):
            dom = _chromium_run(url + f"/?frame={k}", "--dump-dom")
            assert 'data-ready="1"' in dom.stdout, dom.stderr[-2000:]
            assert f'data-review-people="{want}"' in dom.stdout and f'data-review="{int(want != "00")}"' in dom.stdout
            assert ("person1: 3D sources part" in dom.stdout) and (("(review)" in dom.stdout) == (want != "00"))
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(75):
        iio.imwrite(frames / f"{i:06d}.png", np.full((240, 320, 3), 90, np.uint8))
    assert main(["render", str(reviewed_people), "--out", str(tmp_path), "--quiet", "--input", str(frames)]) == 0
    video = iio.imread(tmp_path / "overlay.mp4", plugin="pyav").astype(int)
    edge = lambda f: np.concatenate([video[f, :2].reshape(-1, 3), video[f, -2:].reshape(-1, 3)])  # noqa: E731
    red = lambda px: ((px[:, 0] > 150) & (px[:, 1] < 100) & (px[:, 2] < 100)).mean()  # noqa: E731
    assert red(edge(first)) > 0.8 and red(edge(last)) > 0.8 and red(edge(40)) < 0.1


def test_the_floor_of_the_first_person_who_stands_is_shared_when_the_first_never_does(walk, tmp_path, capsys):
    """person0 jumps all through (never a still foot: their floor is a guess); person1 walks
    and person2 is the same walk 1.25 times as large and far. person1's floor is shared:
    person2 is stood on it, person0 keeps their size, and the people are exported and shown in
    person1's ground frame."""
    from flowmocap.commands.view import ViewerData

    m = load_fitted_motion(walk, frame="world")  # the camera's frame: y down
    up = np.asarray(m.camera.R) @ np.array([0.0, 1.0, 0.0])  # the walk's up in this frame
    bounce = 0.05 * (np.arange(m.num_frames) % 8)  # metres: up 1.5 m/s, then back down: feet never still
    jumper = scaled_about_camera(m, 1.2)
    _write(tmp_path / "person0", replace(jumper, trans=jumper.trans + bounce[:, None] * up), walk)
    import shutil

    shutil.copytree(walk, tmp_path / "person1")
    _write(tmp_path / "person2", scaled_about_camera(m, 1.25), walk)
    (tmp_path / "people.json").write_text(json.dumps({"input": "missing", "people": {
        f"person{k}": {"rank": k, "tracked": True} for k in range(3)}}))
    assert load_fitted_motion(tmp_path / "person0", frame="ground").world.plane.method == "fallback"
    fits = people_floor([tmp_path / f"person{k}" for k in range(3)])
    assert [f.floor_of for f in fits] == [1, 1, 1] and floor_owner(fits) == 1
    assert fits[0].scale is None and "too few" in fits[0].why  # no standing foot to stand anywhere
    assert fits[1].scale == 1.0 and fits[2].scale == pytest.approx(0.8, rel=0.02)
    assert main(["export", str(tmp_path), "-f", "json", "--out", str(tmp_path / "x"), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "person2: stood on person1's floor: 0.8" in said and "person1: its floor is everyone's" in said
    assert "3 people in one frame: person1's (ground)" in said
    assert json.loads((tmp_path / "x" / FLOOR_FILE).read_text())["first"] == "person1"

    def joints(name):
        return np.array([f["joints3d"] for f in json.loads((tmp_path / "x" / f"{name}.json").read_text())["frames"]])

    own = load_fitted_motion(tmp_path / "person1", frame="ground").joints()
    np.testing.assert_allclose(joints("person1"), own, atol=2e-4)  # person1's own ground frame holds everyone
    assert np.median(np.abs(joints("person2") - own)) < 0.01  # person2: the same walk, on person1's floor
    assert np.median(joints("person2")[:, [7, 8], 1].min(1)) < 0.12  # its lower ankle near the floor, y = 0
    data = ViewerData(tmp_path)
    assert data.owner == 1 and data.meta()["floor_of"] == 1
    assert np.median(np.abs(data.people[2]["motion"].joints() - own)) < 0.01
    assert np.abs(data.people[0]["motion"].joints2d - load_fitted_motion(tmp_path / "person0").joints2d).max() < 0.5
