"""flowmocap view: the camera matrices, the local server, and the page in headless Chromium."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from flowmocap.commands.view import STATIC, THREE_VERSION, ViewerData, gl_camera, make_server
from flowmocap.errors import DataError, InputError
from flowmocap.geometry.camera import PinholeCamera, look_at

from test_export import make_result


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """A result with a 320x240 camera 3.2 m from the body; its input is missing (grey frames)."""
    d = tmp_path_factory.mktemp("view") / "result"
    R, t = look_at([2.2, 1.2, 2.2], [0.25, 0.5, 0.2])
    make_result(d, PinholeCamera.from_focal(320, 240, 330.0, R=R, t=t), seed=5)
    return d


@pytest.fixture(scope="module")
def served(result):
    yield from _serving(ViewerData(result))


def _serving(data):
    """Serve ``data`` on a free port while the fixture lasts: yields ``(data, url)``."""
    server = make_server(data, port=0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield data, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def _get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as r:
            return r.status, r.headers["Content-Type"], r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers["Content-Type"], e.read()


def test_gl_camera_puts_points_on_the_pixels_the_camera_projects_them_to():
    rng = np.random.default_rng(0)
    R, t = look_at([1.5, 1.1, 3.0], [0.1, 0.9, 0.0])
    cam = PinholeCamera(fx=400.0, fy=380.0, cx=170.0, cy=110.0, width=320, height=240, R=R, t=t)
    m = gl_camera(cam)
    P = np.array(m["projection"]).reshape(4, 4).T  # column-major lists
    M = np.array(m["matrix_world"]).reshape(4, 4).T
    x = rng.normal(0, 0.4, (20, 3)) + [0.1, 0.9, 0.0]
    clip = (P @ np.linalg.inv(M) @ np.c_[x, np.ones(20)].T).T
    ndc = clip[:, :3] / clip[:, 3:]
    px = np.c_[(ndc[:, 0] + 1) / 2 * cam.width, (1 - ndc[:, 1]) / 2 * cam.height]
    np.testing.assert_allclose(px, cam.project(x), atol=1e-6)
    assert np.all(np.abs(ndc[:, 2]) < 1)  # inside the depth range
    np.testing.assert_allclose(M[:3, 3], cam.center, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(M[:3, :3]), 1.0)
    corners = np.array(m["corners"])
    np.testing.assert_allclose(cam.project(corners), [[0, 0], [320, 0], [320, 240], [0, 240]], atol=1e-6)


def test_server_routes(served):
    data, url = served
    status, ctype, body = _get(url + "/")
    assert status == 200 and "text/html" in ctype and b"importmap" in body
    status, ctype, body = _get(url + "/api/meta.json")
    meta = json.loads(body)
    assert meta["num_frames"] == data.motion.num_frames and meta["width"] == 320 and not meta["has_input"]
    assert len(meta["contacts"]) == meta["num_frames"]
    status, ctype, body = _get(url + "/motion.glb")
    assert status == 200 and body[:4] == b"glTF" and ctype == "model/gltf-binary"
    status, ctype, body = _get(url + "/frame/2.jpg")
    assert status == 200 and body[:2] == b"\xff\xd8"
    status, ctype, body = _get(url + "/static/three/three.module.js")
    assert status == 200 and ctype == "text/javascript" and b"REVISION" in _get(url + "/static/three/three.core.js")[2]
    assert _get(url + "/frame/99.jpg")[0] == 404
    assert _get(url + "/frame/abc.jpg")[0] == 404  # not a frame number: a reply, not a dropped connection
    assert _get(url + "/frame/-1.jpg")[0] == 404
    assert _get(url + "/motion/x.glb")[0] == 404
    assert _get(url + "/static/../commands/view.py")[0] == 404
    assert _get(url + "/static/%2e%2e/commands/view.py")[0] == 404
    assert _get(url + "/nothing")[0] == 404


def test_vendored_three_is_the_version_we_say_with_its_licence():
    assert f"REVISION = '{THREE_VERSION.split('.')[1]}'" in (STATIC / "three" / "three.core.js").read_text()
    assert "MIT License" in (STATIC / "three" / "LICENSE").read_text()
    assert THREE_VERSION in (STATIC / "three" / "README.md").read_text()
    for rel in ("addons/loaders/GLTFLoader.js", "addons/controls/OrbitControls.js", "addons/utils/SkeletonUtils.js",
                "addons/utils/BufferGeometryUtils.js"):
        assert (STATIC / "three" / rel).is_file()
    page = (STATIC / "index.html").read_text() + (STATIC / "viewer.js").read_text()
    assert "http://" not in page.replace("http://127.0.0.1", "") and "https://" not in page  # nothing from a CDN


def test_a_taken_port_says_what_to_do(served):
    data, url = served
    port = int(url.rsplit(":", 1)[1])
    with pytest.raises(InputError, match="--port 0"):
        make_server(data, port=port)



def test_an_input_given_that_cannot_be_decoded_is_an_error_not_grey_frames(result, tmp_path):
    """--input given explicitly but not decodable (random bytes named .mp4) is a DataError
    naming it; only the input recorded in run.json falls back to grey frames."""
    import shutil

    bad = tmp_path / "random.mp4"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(DataError, match=r"--input .*random\.mp4 cannot be read"):
        ViewerData(result, input=bad)
    copy = tmp_path / "result"
    shutil.copytree(result, copy)
    run = json.loads((copy / "run.json").read_text())
    (copy / "run.json").write_text(json.dumps({**run, "input": str(bad)}))
    assert ViewerData(copy).seq is None  # recorded, not given: grey frames as before


def _shell_signals() -> None:
    """In the child: ctrl-c as a shell gives it (default action, not blocked). A child
    inherits an ignored SIGINT, and Python then never raises KeyboardInterrupt; in the
    full suite something before this test leaves the test process ignoring it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_cli_serves_until_ctrl_c_and_stops_cleanly(result, sig):
    code = "import sys; from flowmocap.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, "view", str(result), "--no-browser", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=_shell_signals)
    try:
        url = None
        for _ in range(20):
            line = proc.stdout.readline()
            if "http://127.0.0.1:" in line:
                url = line.split()[2]
                break
        assert url and url.startswith("http://127.0.0.1:"), line
        assert _get(url)[0] == 200
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=120)  # a loaded machine is slow to unwind
        assert proc.returncode == 0 and "stopped" in out and "Traceback" not in out
    finally:
        if proc.poll() is None:
            proc.kill()


def _chromium_run(url: str, *extra: str, timeout: int = 120, window: str = "1000,420") -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run([
            _chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--enable-unsafe-swiftshader", f"--user-data-dir={profile}", f"--window-size={window}",
            "--virtual-time-budget=20000", *extra, url], capture_output=True, text=True, timeout=timeout)


def test_page_in_headless_chromium_draws_the_body_where_the_camera_sees_it(served, tmp_path):
    """Load the page at frame 3, take a screenshot, and compare the overlay's body pixels with
    the fitted body's silhouette rasterised by flowmocap's own renderer from the same camera."""
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
    import imageio.v3 as iio

    from flowmocap.render import body_mask

    data, url = served
    iou = _overlay_iou(data, url, 3, tmp_path)[0]
    print("overlay IoU", iou)
    assert iou > 0.85, iou


def _overlay_iou(data, url: str, k: int, tmp_path, cameras=None, min_share: float = 0.03) -> list[float]:
    """The page's overlay at page frame ``k`` (a screenshot of headless Chromium) against the
    body's silhouette rasterised by flowmocap's renderer from each of ``cameras`` (default the
    motion's camera): their IoUs. The first camera must see the body over at least
    ``min_share`` of the image."""
    import imageio.v3 as iio

    from flowmocap.render import body_mask

    page = url + f"/?frame={k}&scale=1"  # the input at its own size: the same place in both runs
    dom = _chromium_run(page, "--dump-dom")
    assert 'data-ready="1"' in dom.stdout and f'data-frame="{k}"' in dom.stdout, (dom.stdout[-2000:], dom.stderr[-2000:])
    assert "data-error" not in dom.stdout
    left, top, width, height = json.loads(dom.stdout.split('data-overlay="')[1].split('"')[0])
    cam0 = data.motion.camera
    assert (width, height) == (cam0.width, cam0.height)
    shot = tmp_path / f"shot{k}.png"
    _chromium_run(page, f"--screenshot={shot}")
    img = iio.imread(shot)[..., :3].astype(np.int16)
    verts = data.motion.body(k, k + 1)[0][0]
    out = []
    for n, cam in enumerate(cameras or [cam0]):
        mask = body_mask(cam.project(verts), cam.depth(verts), data.motion.model.faces_np, cam.height, cam.width)
        assert n > 0 or mask.mean() > min_share  # the body is in the first camera's view, so the test can fail
        # the overlay's pixels, sampled at each camera pixel's centre
        ys, xs = np.mgrid[0:cam.height, 0:cam.width] + 0.5
        sx = np.clip((left + xs * width / cam.width).astype(int), 0, img.shape[1] - 1)
        sy = np.clip((top + ys * height / cam.height).astype(int), 0, img.shape[0] - 1)
        seen = np.abs(img[sy, sx] - 48).max(-1) > 30  # differs from the grey frame
        out.append(float((seen & mask).sum() / (seen | mask).sum()))
    return out


@pytest.fixture(scope="module")
def reviewed(tmp_path_factory, result):
    """The same result with the 3D sources' disagreement: frame 4 parts most."""
    from flowmocap.body.skeleton import EVAL_JOINTS
    from flowmocap.io.results import read_result, write_motion

    d = tmp_path_factory.mktemp("view_review") / "result"
    shutil.copytree(result, d)
    motion, _ = read_result(d)
    T = len(motion["poses"])
    dis = np.full((T, 24), np.nan, np.float32)
    dis[:, list(EVAL_JOINTS)] = 0.03
    dis[4, list(EVAL_JOINTS)] = np.linspace(0.1, 0.3, 13)  # mean 20 cm
    dis[1] = np.nan  # a frame without sources
    write_motion(d, {**motion, "disagreement": dis})
    data = ViewerData(d)
    yield from _serving(data)


def test_meta_marks_the_frames_where_the_3d_sources_part_most(served, reviewed):
    plain = json.loads(_get(served[1] + "/api/meta.json")[2])
    assert plain["disagreement_cm"] is None and plain["review"] is None
    meta = json.loads(_get(reviewed[1] + "/api/meta.json")[2])
    d, review = meta["disagreement_cm"], meta["review"]
    assert len(d) == len(review) == meta["num_frames"]
    assert d[4] == 20.0 and d[0] == 3.0 and d[1] is None
    assert review[4] == 1 and sum(review) == 1  # the one frame above the 90th percentile


def test_page_says_which_frames_to_review(reviewed, tmp_path):
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
    for k, flag in ((4, "1"), (2, "0")):
        dom = _chromium_run(reviewed[1] + f"/?frame={k}", "--dump-dom")
        assert 'data-ready="1"' in dom.stdout and "data-error" not in dom.stdout, (dom.stdout[-2000:], dom.stderr[-2000:])
        assert f'data-review="{flag}"' in dom.stdout
        assert "3D sources part" in dom.stdout and (("(review)" in dom.stdout) == (flag == "1"))


# ------------------------------------------------------------------ several people (track --person all)


@pytest.fixture(scope="module")
def people(tmp_path_factory):
    """A `track --person all` folder: person0 in a y-up world seen by a placed camera, person1
    tracked by the same camera in its own camera frame (world = camera), two frames later."""
    from flowmocap.io.results import read_result, write_motion

    root = tmp_path_factory.mktemp("view_people") / "people"
    R, t = look_at([2.2, 1.2, 2.2], [0.25, 0.5, 0.2])
    placed = PinholeCamera.from_focal(320, 240, 330.0, R=R, t=t)
    make_result(root / "person0", placed, seed=5)
    # the same physical camera with the world at its centre: person1 stands 4 m in front of it
    make_result(root / "person1", PinholeCamera.from_focal(320, 240, 330.0), seed=6, gender="male")
    motion, _ = read_result(root / "person1")
    write_motion(root / "person1", {**motion, "frame_index": motion["frame_index"] + 2})
    (root / "people.json").write_text(json.dumps({"input": "missing", "people": {
        "person0": {"rank": 0, "tracked": True}, "person1": {"rank": 1, "tracked": True},
        "person2": {"rank": 2, "tracked": False}}}))
    data = ViewerData(root)
    yield from _serving(data)


def test_a_person_moved_into_anothers_frame_projects_onto_the_same_pixels(people):
    from flowmocap.export import load_fitted_motion, motion_in_frame_of

    data, _ = people
    own = load_fitted_motion(data.result_dir / "person1", frame="world")
    moved = motion_in_frame_of(own, data.motion)
    assert moved.frame == "ground" and moved.camera is data.motion.camera
    np.testing.assert_allclose(moved.camera.project(moved.joints()), own.camera.project(own.joints()), atol=1e-6)
    # the body itself is only moved: its bones keep their lengths
    a, b = own.joints(), moved.joints()
    np.testing.assert_allclose(np.linalg.norm(a[:, 1:] - a[:, :1], axis=-1),
                               np.linalg.norm(b[:, 1:] - b[:, :1], axis=-1), atol=1e-9)
    other = load_fitted_motion(data.result_dir / "person0", frame="world")
    other.camera = PinholeCamera.from_focal(160, 120, 165.0)
    with pytest.raises(DataError, match="other cameras"):
        motion_in_frame_of(own, other)


def test_meta_of_a_people_folder_spans_every_tracked_frame(people):
    data, url = people
    meta = json.loads(_get(url + "/api/meta.json")[2])
    T = data.people[0]["motion"].num_frames
    assert meta["num_frames"] == T + 2 and meta["frame_index"] == list(range(3, 3 + T + 2))
    assert [p["name"] for p in meta["people"]] == ["person0", "person1"]  # person2 has no result
    rows0, rows1 = meta["people"][0]["rows"], meta["people"][1]["rows"]
    assert rows0 == list(range(T)) + [-1, -1] and rows1 == [-1, -1] + list(range(T))
    assert meta["feet"][-1] is None and meta["feet"][0] is not None and meta["people"][1]["path"][0] is None
    assert meta["people"][1]["colour"] != meta["people"][0]["colour"]
    assert _get(url + "/motion/1.glb")[0] == 200 and _get(url + "/motion/2.glb")[0] == 404
    assert _get(url + f"/frame/{T + 1}.jpg")[0] == 200 and _get(url + f"/frame/{T + 2}.jpg")[0] == 404


def test_page_draws_every_person_in_their_colour_where_the_camera_sees_them(people, tmp_path):
    """At a frame both people were tracked in, the overlay's body pixels are the union of the
    two silhouettes flowmocap's renderer gives from the first person's camera, each person in
    their own colour; at the last frame, which only the second was tracked in, only the second
    is drawn."""
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
    import imageio.v3 as iio

    from flowmocap.render import body_mask

    data, url = people
    k = 3  # input frame 6: person0's row 3, person1's row 1
    page = url + f"/?frame={k}&scale=1"
    dom = _chromium_run(page, "--dump-dom")
    assert 'data-ready="1"' in dom.stdout and 'data-people="11"' in dom.stdout, (dom.stdout[-2000:], dom.stderr[-2000:])
    assert "data-error" not in dom.stdout
    left, top, width, height = json.loads(dom.stdout.split('data-overlay="')[1].split('"')[0])
    shot = tmp_path / "shot.png"
    _chromium_run(page, f"--screenshot={shot}")
    img = iio.imread(shot)[..., :3].astype(np.int16)
    cam = data.motion.camera
    masks = []
    for p in data.people:
        r = p["rows"][k]
        v = p["motion"].body(r, r + 1)[0][0]
        masks.append(body_mask(cam.project(v), cam.depth(v), p["motion"].model.faces_np, cam.height, cam.width))
    assert all(m.mean() > 0.01 for m in masks)  # both in view, so the test can fail
    ys, xs = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    sx = np.clip((left + xs * width / cam.width).astype(int), 0, img.shape[1] - 1)
    sy = np.clip((top + ys * height / cam.height).astype(int), 0, img.shape[0] - 1)
    px = img[sy, sx]
    seen = np.abs(px - 48).max(-1) > 30
    union = masks[0] | masks[1]
    iou = (seen & union).sum() / (seen | union).sum()
    assert iou > 0.85, iou
    only0, only1 = masks[0] & ~masks[1] & seen, masks[1] & ~masks[0] & seen
    assert only0.sum() > 50 and only1.sum() > 50
    # person0 light blue (more blue than red), person1 orange (more red than blue)
    assert np.median(px[only0][:, 2] - px[only0][:, 0]) > 20
    assert np.median(px[only1][:, 0] - px[only1][:, 2]) > 20
    dom = _chromium_run(url + f"/?frame={len(data.frame_index) - 1}", "--dump-dom")
    assert 'data-ready="1"' in dom.stdout and 'data-people="01"' in dom.stdout


def test_export_of_a_people_folder_puts_everyone_in_the_first_persons_frame(people, tmp_path, capsys):
    """`flowmocap export PEOPLE -f json`: one file per person, all with the first person's
    camera, and each person's exported joints project through it onto their own pixels."""
    from flowmocap.cli import main
    from flowmocap.export import load_fitted_motion

    data, _ = people
    out = tmp_path / "export"
    assert main(["export", str(data.result_dir), "--format", "json", "--out", str(out), "--quiet"]) == 0
    assert "2 people in one frame" in capsys.readouterr().out
    files = [json.loads((out / f"person{k}.json").read_text()) for k in range(2)]
    assert files[0]["camera"] == files[1]["camera"] and files[0]["frame"] == "ground"
    cam = PinholeCamera.from_dict(files[1]["camera"])
    own = load_fitted_motion(data.result_dir / "person1", frame="world")
    j3 = np.array([f["joints3d"] for f in files[1]["frames"]])
    np.testing.assert_allclose(cam.project(j3), own.camera.project(own.joints()), atol=0.01)  # json keeps 4-6 digits
    # each person's own foot contacts, as exporting that person alone in their own ground frame gives them
    alone = load_fitted_motion(data.result_dir / "person1", frame="ground")
    assert [f["contact"] for f in files[1]["frames"]] == alone.world.contacts.tolist()
    assert "contact" in files[0]["frames"][0]


def test_the_page_says_where_the_person_was_not_seen(result, tmp_path):
    """run.json's gaps: input frames 4-5 held, frame 7 by flow alone (the result's rows start at
    input frame 3); meta says so per person and the page's label and data-unseen say so in
    those frames."""
    from flowmocap.io.results import read_result, write_run

    d = tmp_path / "result"
    shutil.copytree(result, d)
    _, run = read_result(d)
    write_run(d, {**run, "gaps": [{"frames": [4, 5], "why": "no person found: held at the last seen pose"},
                                  {"frames": [7, 7], "why": "no person found: tracked by flow alone, no silhouette term"}]})
    for data, url in _serving(ViewerData(d)):
        meta = json.loads(_get(url + "/api/meta.json")[2])
        unseen = meta["people"][0]["unseen"]
        assert meta["frame_index"] == [3, 4, 5, 6, 7]
        assert unseen == ["", "held", "held", "", "flow"]
        if _chromium() is None:
            pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
        for k, want, words in ((1, "held", "not seen (held at the last seen pose)"),
                               (4, "flow", "not seen (tracked by flow alone)"), (0, "-", None)):
            dom = _chromium_run(url + f"/?frame={k}", "--dump-dom")
            assert 'data-ready="1"' in dom.stdout and "data-error" not in dom.stdout, dom.stderr[-2000:]
            assert f'data-unseen="{want}"' in dom.stdout
            assert (words in dom.stdout) if words else "not seen (" not in dom.stdout


def _raw(url: str, request: bytes) -> bytes:
    """Send ``request`` as it is to the server at ``url``; the reply's bytes ("" when the
    connection is dropped without one)."""
    import socket

    host, port = url.rsplit("/", 1)[1].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=30) as s:
        s.sendall(request)
        chunks = []
        while chunk := s.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def test_odd_requests_get_an_answer_not_a_dropped_connection(served):
    """A frame number int() refuses (5000 digits, a superscript digit that str.isdigit takes),
    a NUL or a too-long name in a static path: each was a dropped connection, some with a
    traceback on the server's terminal."""
    data, url = served
    assert _get(url + "/frame/" + "9" * 5000 + ".jpg")[0] == 404
    assert _get(url + "/static/" + "a" * 300)[0] == 404
    for path in (b"/frame/\xb2.jpg", b"/static/a\x00b", b"/frame/\xd9\xa1.jpg"):
        reply = _raw(url, b"GET " + path + b" HTTP/1.0\r\n\r\n")
        assert reply.startswith(b"HTTP/1.0 404"), (path, reply[:60])
    head = _raw(url, b"HEAD /motion.glb HTTP/1.0\r\n\r\n")  # curl -I: the GET's headers, no body
    assert head.startswith(b"HTTP/1.0 200") and head.endswith(b"\r\n\r\n")
    assert f"Content-Length: {len(data.glb)}".encode() in head


def test_a_page_elsewhere_cannot_read_the_viewer_through_its_own_name(served):
    """DNS rebinding: a page the user visits points its own name at 127.0.0.1 and reads the
    user's frames; the viewer answers only requests that name this machine."""
    data, url = served
    port = url.rsplit(":", 1)[1]
    for host in (b"evil.example", b"evil.example:" + port.encode(), b"127.0.0.1.evil.example"):
        reply = _raw(url, b"GET /frame/0.jpg HTTP/1.1\r\nHost: " + host + b"\r\nConnection: close\r\n\r\n")
        assert reply.startswith(b"HTTP/1.0 403") and b"\xff\xd8" not in reply, host
    for host in (b"127.0.0.1:" + port.encode(), b"localhost:" + port.encode(), b"LOCALHOST", b"[::1]:" + port.encode()):
        reply = _raw(url, b"GET /frame/0.jpg HTTP/1.1\r\nHost: " + host + b"\r\nConnection: close\r\n\r\n")
        assert reply.startswith(b"HTTP/1.0 200"), host


def test_an_input_that_goes_away_while_serving_is_a_500_with_the_reason(served):
    data, url = served

    class Gone:  # the input was deleted after the viewer started: the frames it has not sent fail
        def frame(self, i):
            raise DataError("cannot read image seq/frames/000003.png")

    seq, cached = data.seq, dict(data._jpeg)
    data.seq, data._jpeg = Gone(), {}
    try:
        status, ctype, body = _get(url + "/frame/3.jpg")
    finally:
        data.seq, data._jpeg = seq, cached
    assert status == 500 and b"cannot read image seq/frames/000003.png" in body


def test_view_says_when_the_run_is_not_finished_or_the_input_not_the_tracked_one(result, tmp_path):
    import shutil

    copy = tmp_path / "result"
    shutil.copytree(result, copy)
    run = json.loads((copy / "run.json").read_text())
    assert ViewerData(copy).notes == []
    (copy / "run.json").write_text(json.dumps({**run, "status": "interrupted"}))
    notes = ViewerData(copy).notes
    assert len(notes) == 1 and "is interrupted" in notes[0] and "--resume" in notes[0]
    (copy / "run.json").write_text(json.dumps(run))
    data = ViewerData(copy)
    frames = tmp_path / "other"  # another clip of the result's size and length
    frames.mkdir()
    for i in range(int(data.frame_index.max()) + 1):
        cv2.imwrite(str(frames / f"{i:06d}.png"), np.full((240, 320, 3), 30 + i, np.uint8))
    (copy / "run.json").write_text(json.dumps({**run, "fingerprint": {"input": "0" * 16}}))
    notes = ViewerData(copy, input=frames).notes
    assert len(notes) == 1 and "is not the input that was tracked" in notes[0]


def test_the_slider_keeps_its_width_in_a_narrow_window_and_on_every_frame(reviewed):
    """At 800 px the slider was 0 px wide (the label and the result's name took the bar), and
    it moved sideways from frame to frame as the label grew ' (review)'."""
    if _chromium() is None:
        pytest.skip("chromium is not installed (apt-get install chromium); the viewer's browser test needs it")
    data, url = reviewed
    widths = []
    for k in (0, 4):  # frame 4 is to be reviewed: its label is longer
        dom = _chromium_run(url + f"/?frame={k}", "--dump-dom", window="800,420").stdout
        assert 'data-ready="1"' in dom and f'data-frame="{k}"' in dom, dom[-2000:]
        widths.append(int(dom.split('data-slider="')[1].split('"')[0]))
    assert min(widths) >= 120 and widths[0] == widths[1], widths
    dom = _chromium_run(url + "/?frame=abc", "--dump-dom").stdout  # not a number: the first frame, not NaN
    assert 'data-frame="0"' in dom and "NaN" not in dom.split("<header")[1].split("</header>")[0]
