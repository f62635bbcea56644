"""flowmocap render: overlay MP4, Fig.-1 panel, joint traces, energy plot."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from flowmocap.body import load_body_model
from flowmocap.cli import main
from flowmocap.errors import DataError, InputError
from flowmocap.io.results import write_motion, write_run
from flowmocap.synth import synthesize
from flowmocap.viz.traces import TRACE_RGB, draw_traces

W, H, T = 96, 72, 5


def write_result(folder: Path, seq_dir: Path, camera, gt: dict, pose_noise: float = 0.0, seed: int = 0) -> None:
    """A result folder for the sequence, from its ground truth (plus noise on the pose)."""
    rng = np.random.default_rng(seed)
    poses = (gt["poses"] + pose_noise * rng.normal(size=gt["poses"].shape)).astype(np.float32)
    model = load_body_model("default", gender=str(gt["gender"]))
    with torch.no_grad():
        j3 = model(betas=torch.as_tensor(gt["betas"], dtype=torch.float32), pose=torch.as_tensor(poses),
                   trans=torch.as_tensor(gt["trans"], dtype=torch.float32)).joints.numpy()
    n = len(poses)
    write_motion(folder, {
        "poses": poses, "trans": gt["trans"].astype(np.float32), "betas": gt["betas"].astype(np.float32),
        "gender": np.array(str(gt["gender"])), "fps": np.array(30.0),
        "camera": np.array(json.dumps(camera.to_dict())), "joints3d": j3, "joints2d": camera.project(j3),
        "energies": np.column_stack([np.linspace(1, 2, n), np.full(n, np.nan)]),
        "energy_names": np.array(["total", "unused"]), "frame_index": np.arange(n),
    })
    write_run(folder, {"input": str(seq_dir), "model": "default", "gender": str(gt["gender"]),
                      "config": {"flow_method": "dis"}})


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("render")
    seq = root / "seq"
    res = synthesize("builtin:walk", seq, frames=T, size=f"{W}x{H}", betas="random", seed=4, flow=True)
    with np.load(seq / "gt.npz") as z:
        gt = {k: z[k] for k in z.files}
    write_result(root / "exact", seq, res.camera, gt)
    write_result(root / "noisy", seq, res.camera, gt, pose_noise=0.08)
    return root, seq, gt


def test_overlay_mp4_has_the_inputs_frame_count_and_size(demo, tmp_path):
    import imageio.v3 as iio

    root, seq, _ = demo
    assert main(["render", str(root / "exact"), "--video", str(tmp_path / "o.mp4"), "--quiet"]) == 0
    video = iio.imread(tmp_path / "o.mp4", plugin="pyav")
    assert video.shape == (T, H, W, 3)
    # the body is drawn: frames differ from the input where the body is, not elsewhere
    frame = iio.imread(seq / "frames" / "000002.png")[..., :3].astype(float)
    mask = iio.imread(seq / "masks" / "000002.png") > 0
    diff = np.abs(video[2].astype(float) - frame).mean(-1)
    assert diff[mask].mean() > 4 * diff[~mask].mean()
    assert main(["render", str(root / "exact"), "--video", str(tmp_path / "s.mp4"), "--side", "--quiet"]) == 0
    assert iio.imread(tmp_path / "s.mp4", plugin="pyav").shape == (T, H, 2 * W, 3)


def test_render_without_options_writes_all_four_outputs(demo):
    import imageio.v3 as iio

    root, _, _ = demo
    out = root / "exact" / "render"
    shutil.rmtree(out, ignore_errors=True)
    assert main(["render", str(root / "exact"), "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["energies.png", "figure1.png", "joint_traces.png", "overlay.mp4"]
    fig = iio.imread(out / "figure1.png")
    assert fig.ndim == 3 and fig.shape[1] > 4 * fig.shape[0] / 2  # one row of five tiles


def test_rendered_flow_of_the_true_motion_matches_the_true_flow(demo):
    """Figure 1's rendered flow is the model's flow between consecutive fitted frames."""
    from flowmocap.viz.result_render import ResultScene

    root, seq, _ = demo
    scene = ResultScene(root / "exact")
    flow, mask = scene.rendered_flow(3)
    with np.load(seq / "flow" / "000003.npz") as z:
        true = z["flow"]
    assert mask.sum() > 50
    assert np.linalg.norm(flow[mask] - true[mask], axis=1).mean() < 0.05
    assert np.abs(true[mask]).max() > 0.3  # the body moves, so a wrong flow would show
    obs = scene.observed_flow(3)
    assert obs.shape == (H, W, 2)
    with pytest.raises(InputError, match="previous frame"):
        scene.rendered_flow(0)


def test_figure1_colours_the_flow_on_the_body(demo):
    from flowmocap.viz.result_render import ResultScene, figure1

    root, _, _ = demo
    scene = ResultScene(root / "exact")
    one = figure1(scene, [3], crop=False, min_height=H)
    two = figure1(scene, [2, 4], crop=False, min_height=H)
    assert two.shape[0] > 1.8 * one.shape[0]
    tile = one[26:26 + H, 2 * (W + 6):2 * (W + 6) + W]  # rendered flow tile, below its caption
    body = scene.silhouette(scene.k_of(3))
    assert (tile[body] < 250).any(axis=-1).mean() > 0.8  # coloured on the body
    assert (tile[~body] == 255).all()  # white (zero flow) elsewhere
    with pytest.raises(InputError, match="not tracked"):
        figure1(scene, [77])


def test_joint_errors_are_zero_for_the_truth_and_not_for_noise(demo):
    from flowmocap.viz.result_render import ResultScene, energy_figure

    root, _, _ = demo
    exact = ResultScene(root / "exact").errors_cm()
    noisy = ResultScene(root / "noisy").errors_cm()
    assert max(v.max() for v in exact.values()) < 0.01
    assert noisy["MPJPE"].mean() > 1.0
    img = energy_figure(ResultScene(root / "noisy"))
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8


def test_draw_traces_draws_the_joint_path():
    img = np.zeros((40, 60, 3), np.uint8)
    j = np.zeros((3, 24, 2))
    j[:, 15] = [[10.5, 20.5], [30.5, 20.5], [50.5, 20.5]]  # the head moves right along row 20
    out = draw_traces(img, j, upto=2, joints=[15], fade=False, dots=False)
    assert tuple(out[20, 20]) == TRACE_RGB and tuple(out[20, 40]) == TRACE_RGB
    assert (out[5] == 0).all() and (out[35] == 0).all()
    partial = draw_traces(img, j, upto=1, joints=[15], fade=False, dots=False)
    assert (partial[20, 45] == 0).all()  # not drawn past frame `upto`


def test_joint_traces_image(demo, tmp_path):
    import imageio.v3 as iio

    root, _, _ = demo
    path = tmp_path / "tr.png"
    assert main(["render", str(root / "noisy"), "--traces", str(path), "--frames", "2,4"]) == 0
    img = iio.imread(path)
    green = (img[..., 1] > 180) & (img[..., 0] < 120) & (img[..., 2] < 120)
    orange = (img[..., 0] > 200) & (img[..., 1] < 140) & (img[..., 2] < 90)
    assert green.sum() > 50 and orange.sum() > 5  # fitted and ground-truth traces


def test_render_errors_tell_what_to_do(demo, tmp_path, capsys):
    from flowmocap.viz.result_render import ResultScene

    root, seq, gt = demo
    assert main(["render", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    moved = tmp_path / "moved"
    shutil.copytree(root / "exact", moved, ignore=shutil.ignore_patterns("render"))
    run = json.loads((moved / "run.json").read_text())
    run["input"] = str(tmp_path / "gone")
    (moved / "run.json").write_text(json.dumps(run))
    with pytest.raises(DataError, match="--input"):
        ResultScene(moved)
    assert ResultScene(moved, input=seq).num_frames == T
    assert main(["render", str(root / "exact"), "--figure1", str(tmp_path / "f.png"), "--frames", "a,b"]) == 2
    assert main(["render", str(root / "exact"), "--video", str(tmp_path / "v.mp4"), "--alpha", "2"]) == 2
    assert main(["render", str(root / "exact"), "--traces", str(tmp_path / "t.png"), "--history", "-3"]) == 2
    assert "--history" in capsys.readouterr().err
    # names of the wrong kind: refused before any drawing (p.xyz failed after the work as a full disk
    # would, exit 5, naming a temporary file; v.png got an MP4 under a picture's name)
    for option, name, kind in (("--plot", "p.xyz", "a picture"), ("--video", "v.png", "a video"),
                               ("--traces", "t", "a picture")):
        assert main(["render", str(root / "exact"), option, str(tmp_path / name), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"{option} {tmp_path / name}: give a name ending in" in err and f"({kind})" in err
        assert not (tmp_path / name).exists()
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_the_energy_plot_gains_a_panel_for_the_sources_disagreement():
    from flowmocap.viz.plots import energy_error_plot

    x = np.arange(6)
    e = np.ones((6, 2))
    plain = energy_error_plot(x, e, ["total", "flow"])
    dis = np.full((6, 24), np.nan)
    dis[1:, :13] = np.linspace(0.02, 0.2, 5 * 13).reshape(5, 13)  # frame 0: none
    more = energy_error_plot(x, e, ["total", "flow"], disagreement=dis)
    assert more.shape[1] > plain.shape[1]  # a third panel beside the two energies
    red = (more[..., 0] > 200) & (more[..., 1] < 80) & (more[..., 2] < 80)
    assert red.sum() > 20 and not ((plain[..., 0] > 200) & (plain[..., 1] < 80) & (plain[..., 2] < 80)).any()
    same = energy_error_plot(x, e, ["total", "flow"], disagreement=np.full((6, 24), np.nan))
    assert same.shape == plain.shape  # nothing to show: no panel


def test_overlay_video_frames_the_frames_to_review_in_red(demo, tmp_path):
    import shutil

    import imageio.v3 as iio

    from flowmocap.io.results import read_result

    root, _, _ = demo
    res = tmp_path / "flagged"
    shutil.copytree(root / "exact", res)
    motion, _ = read_result(res)
    dis = np.full((T, 24), 0.02, np.float32)
    dis[3] = 0.3  # the one frame of five at the run's 90th percentile
    write_motion(res, {**motion, "disagreement": dis})
    assert main(["render", str(res), "--video", str(tmp_path / "f.mp4"), "--quiet"]) == 0
    video = iio.imread(tmp_path / "f.mp4", plugin="pyav").astype(int)
    edge = lambda f: np.concatenate([video[f, :2].reshape(-1, 3), video[f, -2:].reshape(-1, 3)])  # noqa: E731
    red = lambda px: ((px[:, 0] > 150) & (px[:, 1] < 100) & (px[:, 2] < 100)).mean()  # noqa: E731
    assert red(edge(3)) > 0.8 and all(red(edge(f)) < 0.1 for f in (0, 1, 2, 4))


def test_overlay_video_says_which_frames_were_not_seen(demo, tmp_path):
    """Frames tracked by flow alone (run.json's gaps) carry "not seen" at the top left."""
    import shutil

    import imageio.v3 as iio

    from flowmocap.io.results import read_result, write_run

    root, _, _ = demo
    res = tmp_path / "unseen"
    shutil.copytree(root / "exact", res)
    _, run = read_result(res)
    write_run(res, {**run, "gaps": [{"frames": [1, 2], "why": "no person found"}]})
    assert main(["render", str(res), "--video", str(tmp_path / "u.mp4"), "--quiet"]) == 0
    plain = main(["render", str(root / "exact"), "--video", str(tmp_path / "p.mp4"), "--quiet"])
    assert plain == 0
    a = iio.imread(tmp_path / "u.mp4", plugin="pyav").astype(int)
    b = iio.imread(tmp_path / "p.mp4", plugin="pyav").astype(int)
    corner = lambda v, f: v[f, :30, :200]  # noqa: E731 -- where the words go
    changed = [np.abs(corner(a, f) - corner(b, f)).max(-1).__gt__(60).mean() for f in range(T)]
    assert changed[1] > 0.02 and changed[2] > 0.02 and changed[0] < 0.005 and changed[3] < 0.005, changed


def test_the_framing_side_camera_keeps_a_long_path_in_view():
    """Points along the input camera's view, 3 to 9 m away and 1 m either side of its axis
    vertically: orbited 90 degrees at the input's distance, the side camera sees the path
    end-on too close, and points fall outside the image; the framing camera moves back
    along its view until every point lies within 0.9 of the half-image, and no further
    than that needs (the farthest-out point is at the edge). Points that already fit keep
    the plain orbit."""
    from flowmocap.geometry.camera import PinholeCamera, look_at
    from flowmocap.viz.overlay import framing_side_camera, side_camera

    R, t = look_at((0.0, 1.0, 0.0), (0.0, 1.0, 5.0))
    cam = PinholeCamera(fx=200.0, fy=200.0, cx=80.0, cy=60.0, width=160, height=120, R=R, t=t)
    z = np.linspace(3.0, 9.0, 25)
    pts = np.concatenate([np.c_[np.zeros_like(z), np.full_like(z, y), z] for y in (0.0, 1.0, 2.0)])

    def reach(c):  # the largest share of the half-image a point reaches, and whether all lie in front
        x = pts @ np.asarray(c.R).T + np.asarray(c.t)
        uv = c.project(pts)
        share = np.maximum(np.abs(uv[:, 0] - c.width / 2) / (c.width / 2), np.abs(uv[:, 1] - c.height / 2) / (c.height / 2))
        return share.max(), bool(np.all(x[:, 2] > 0))

    plain = side_camera(cam, 0.5 * (pts.min(0) + pts.max(0)))
    assert reach(plain)[0] > 1.0  # the path's ends leave the image
    framed = framing_side_camera(cam, pts)
    share, front = reach(framed)
    assert front and share == pytest.approx(0.9, abs=1e-6)
    np.testing.assert_allclose(framed.R, plain.R)  # the same view direction, only further back
    small = pts[np.abs(pts[:, 2] - 6.0) < 0.2] * [1, 0.1, 1] + [0, 0.9, 0]  # a few points near the middle
    near = framing_side_camera(cam, small)
    np.testing.assert_allclose(near.t, side_camera(cam, 0.5 * (small.min(0) + small.max(0))).t)
    with pytest.raises(InputError, match="finite point"):
        framing_side_camera(cam, np.full((3, 3), np.nan))
    with pytest.raises(InputError, match="fill"):
        framing_side_camera(cam, pts, fill=1.5)


def test_the_side_view_shows_the_motion_with_the_cameras_turn_undone(demo, tmp_path):
    """A result whose camera turned (run.json's camera_motion: 10 degrees about the vertical a
    frame): the side view's motion is the export's "up" frame, where each frame's body is
    turned back by the camera's turn, not the result's own frame (the camera's view), and its
    camera keeps every joint of every frame inside the image."""
    from flowmocap.export.motion import load_fitted_motion
    from flowmocap.viz.result_render import ResultScene

    root, _, _ = demo
    res = tmp_path / "turned"
    shutil.copytree(root / "exact", res)
    run = json.loads((res / "run.json").read_text())
    run["camera_motion"] = {"moving": True, "frames": list(range(T)),
                            "rotvecs": [[0.0, np.radians(10.0 * i), 0.0] for i in range(T)]}
    (res / "run.json").write_text(json.dumps(run))
    scene = ResultScene(res)
    motion, cam = scene.side_view()
    up = load_fitted_motion(res, frame="up")
    np.testing.assert_allclose(motion.joints(), up.joints(), atol=1e-9)
    own = load_fitted_motion(res, frame="world").joints()
    turned = own @ up.rotation.T  # the result's own frame, only turned y up
    assert np.abs(motion.joints() - turned).max() > 0.1  # the turn was undone: the path differs
    uv = cam.project(motion.joints().reshape(-1, 3))
    assert np.all((uv >= 0) & (uv <= [cam.width, cam.height]))


def test_render_of_a_one_frame_result_leaves_out_only_the_figure(demo, tmp_path, capsys):
    """Fig. 1 shows the flow from the frame before; a one-frame result has none. Asked for
    every output, render used to stop with "choose a later frame", which there is not."""
    root, seq, gt = demo
    one = tmp_path / "one"
    write_result(one, seq, load_fitted_camera(root / "exact"), {**gt, "poses": gt["poses"][:1], "trans": gt["trans"][:1]})
    assert main(["render", str(one), "--quiet"]) == 0
    assert sorted(p.name for p in (one / "render").iterdir()) == ["energies.png", "joint_traces.png", "overlay.mp4"]
    assert "holds one frame: no Fig. 1" in capsys.readouterr().out
    assert main(["render", str(one), "--figure1", str(tmp_path / "f.png"), "--quiet"]) == 2  # asked for: said why


def load_fitted_camera(result):
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.io.results import read_result

    motion, _ = read_result(result)
    return PinholeCamera.from_dict(json.loads(str(motion["camera"])))


def test_render_says_when_the_input_is_not_the_one_tracked(demo, tmp_path, capsys):
    """Another clip of the same size and length used to be drawn over without a word; the
    input's digest in run.json's fingerprint tells them apart."""
    from flowmocap.io.fingerprint import digest_input

    root, seq, _ = demo
    res = tmp_path / "res"
    shutil.copytree(root / "exact", res, ignore=shutil.ignore_patterns("render"))
    run = json.loads((res / "run.json").read_text())
    write_run(res, {**run, "fingerprint": {"input": digest_input(seq)}})
    other = tmp_path / "other"
    synthesize("builtin:walk", other, frames=T, size=f"{W}x{H}", betas="random", seed=5)
    assert main(["render", str(res), "--video", str(tmp_path / "a.mp4"), "--quiet"]) == 0
    assert "not the input that was tracked" not in capsys.readouterr().out
    assert main(["render", str(res), "--video", str(tmp_path / "b.mp4"), "--input", str(other), "--quiet"]) == 0
    assert "not the input that was tracked" in capsys.readouterr().out


def test_a_video_that_cannot_be_written_whole_leaves_nothing_under_its_name(tmp_path):
    """A full disk or a file size limit (here ``ulimit -f``) used to leave a cut-off MP4
    under the name, with a message that named no file."""
    import subprocess
    import sys

    target = tmp_path / "v.mp4"
    target.write_bytes(b"the old video")
    code = (f"import numpy as np; from flowmocap.viz.video import VideoWriter\n"
            f"rng = np.random.default_rng(0)\n"
            f"with VideoWriter({str(target)!r}, 30, quality=0) as w:\n"
            f"    for k in range(40): w.write(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))\n")
    done = subprocess.run(["bash", "-c", f"ulimit -f 64; {sys.executable} -c \"$0\"", code],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert str(target) in done.stderr  # the error names the video
    assert target.read_bytes() == b"the old video"
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]  # no temporary file left



def test_a_video_whose_last_packets_cannot_be_written_leaves_no_temporary_file(tmp_path):
    """When the write failed in the encoder's flush at the end (a full disk), the temporary
    file was left beside the video, one more each try, holding the space to be freed."""
    import numpy as np

    from flowmocap.viz.video import VideoWriter

    class FullAtTheEnd:  # the container, whose writes fail from the flush on
        def __init__(self, real):
            self.real = real

        def mux(self, packet):
            raise OSError(27, "File too large")

        def close(self):
            self.real.close()

    target = tmp_path / "v.mp4"
    with pytest.raises(OSError, match="File too large"):
        with VideoWriter(target, 30) as w:
            for k in range(3):
                w.write(np.full((48, 64, 3), 40 * k, np.uint8))
            w._container = FullAtTheEnd(w._container)
    assert list(tmp_path.iterdir()) == []


def test_an_odd_frame_size_is_written_in_the_format_every_player_plays(tmp_path):
    # 363x640 frames (a 1088x1920 phone video at --max-size 640) were written yuv444p, which QuickTime, Safari,
    # browsers and hardware decoders do not play
    import av

    from flowmocap.viz.video import VideoWriter

    ys, xs = np.mgrid[0:41, 0:63]
    frames = [np.repeat(((xs * 3 + ys * 2 + 80 * k) % 256).astype(np.uint8)[..., None], 3, 2) for k in range(3)]
    with VideoWriter(tmp_path / "odd.mp4", 30, quality=0) as w:
        for f in frames:
            w.write(f)
    with av.open(str(tmp_path / "odd.mp4")) as c:
        s = c.streams.video[0]
        assert (s.codec_context.pix_fmt, s.width, s.height) == ("yuv420p", 64, 42)
        first = next(c.decode(s)).to_ndarray(format="rgb24").astype(float)
    # the frame's pixels where they were, and the added column and row repeat its last ones
    assert np.abs(first[:41, :63] - frames[0]).mean() < 4 and np.abs(first[:41, :63] - frames[1]).mean() > 40
    assert np.abs(first[:41, 63] - first[:41, 62]).mean() < 6
