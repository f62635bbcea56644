"""``flowmocap view RESULT``: a local web page with the input, the overlay and the body in 3D.

A small HTTP server (``http.server``, bound to 127.0.0.1 only) serves the page and its
JavaScript from the package (``flowmocap/viewer/``: the page, and three.js
:data:`THREE_VERSION` with its MIT licence; nothing comes from the network), the result's
skinned glb in the ground frame (the file ``flowmocap export --format glb`` writes), the
camera in that frame, and the input's frames as JPEG. Routes:

- ``/``: the page; ``/static/...``: the files of ``flowmocap/viewer/``;
- ``/api/meta.json``: :meth:`ViewerData.meta`;
- ``/motion.glb``: the skinned body (the first person's); ``/motion/N.glb``: person N's (the
  N-th of ``meta.people``); ``/frame/K.jpg``: the input frame of the page's frame ``K`` (a grey
  frame when the input is not found).

Given the folder of ``flowmocap track --person all`` (``people.json``), the page shows every
tracked person, each in their own colour, in the ground frame of the person whose floor they
all stand on (the first person's unless they never stand still,
:func:`flowmocap.export.floor.people_floor`; moved there through the camera they share,
:func:`flowmocap.export.motion.motion_in_frame_of`), over every input frame any of them was
tracked in.

Ctrl-C (SIGINT) or SIGTERM stops the server cleanly.
"""

from __future__ import annotations

import io
import json
import mimetypes
import tempfile
import threading
from dataclasses import replace
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from flowmocap.errors import FlowMocapError

THREE_VERSION = "0.187.0"
STATIC = Path(__file__).resolve().parents[1] / "viewer"
_TYPES = {".js": "text/javascript", ".css": "text/css", ".html": "text/html", ".md": "text/plain",
          ".json": "application/json"}


def gl_camera(camera, near: float = 0.05, far: float = 200.0, corner_depth: float = 0.6) -> dict:
    """A pinhole camera as OpenGL/three.js matrices (column-major lists of 16).

    ``projection`` maps OpenGL eye coordinates (x right, y up, looking down -z) to clip
    space so that a point lands on the pixel :meth:`PinholeCamera.project` gives it (the
    image spans NDC [-1, 1], v down becoming y up); ``matrix_world`` is the eye-to-world
    transform ``[R^T D | -R^T t]`` with ``D = diag(1, -1, -1)`` (OpenCV eye axes to
    OpenGL's). ``corners``: the image corners' rays at ``corner_depth`` metres, world frame.
    """
    W, H = camera.width, camera.height
    P = np.array([
        [2 * camera.fx / W, 0.0, 1 - 2 * camera.cx / W, 0.0],
        [0.0, 2 * camera.fy / H, 2 * camera.cy / H - 1, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])
    M = np.eye(4)
    M[:3, :3] = camera.R.T @ np.diag([1.0, -1.0, -1.0])
    M[:3, 3] = -camera.R.T @ camera.t
    corners = [camera.R.T @ (corner_depth * np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
                             - camera.t) for u, v in ((0, 0), (W, 0), (W, H), (0, H))]
    return {"projection": P.T.reshape(-1).tolist(), "matrix_world": M.T.reshape(-1).tolist(),
            "corners": [c.tolist() for c in corners]}


class ViewerData:
    """What the page shows, built once: the motion in the ground frame, its glb, the frames.

    Args:
        result_dir: the result folder. input: the tracked video or sequence folder (default:
            the one recorded in ``run.json``; grey frames when that one is not found or cannot
            be read).
        model: body model override. smooth: as for :func:`flowmocap.export.export_result`.

    Raises:
        DataError: an unreadable result, or an ``input`` given here that is missing, cannot
            be decoded or is not the tracked one (its size or length differs).
    """

    def __init__(self, result_dir, input=None, model=None, smooth: bool | dict = False, floor: bool = True):
        from flowmocap.export import load_fitted_motion, motion_in_frame_of, write_motion_glb
        from flowmocap.export.floor import floor_owner, people_floor, scaled_about_camera
        from flowmocap.io.results import people_results, unfinished_words
        from flowmocap.viz.overlay import PEOPLE_RGB

        self.result_dir = Path(result_dir)
        folders = people_results(self.result_dir)
        #: with several people and ``floor``: how each was stood on one floor
        #: (:func:`flowmocap.export.floor.people_floor`), else None
        self.floor = people_floor([d for _, d in folders], model=model) if floor and len(folders) > 1 else None
        #: the index of the person whose ground frame holds everyone: whose floor is shared
        #: (the first person unless they never stand still), else the first
        self.owner = floor_owner(self.floor)
        first = folders[self.owner][1] if folders else self.result_dir
        self._home = Path(first).parent  # where a moved input is looked for, beside the result folder
        #: that person's motion (the only one's for a result folder), ground frame
        self.motion = load_fitted_motion(first, frame="ground", model=model, smooth=smooth)
        motions = []
        for k, (_, d) in enumerate(folders):
            if k == self.owner:
                motions.append(self.motion)
                continue
            m = load_fitted_motion(d, frame="ground", model=model, smooth=smooth,  # its own foot contacts
                                   camera_move_of=self.motion)  # the camera's move undone as for the owner
            if self.floor is not None and self.floor[k].scale is not None:
                m = scaled_about_camera(m, self.floor[k].scale)
            motions.append(motion_in_frame_of(m, self.motion))
        motions = motions or [self.motion]
        names = [n for n, _ in folders] or [self.result_dir.name]
        #: the page's frames: the input frames any person was tracked in, ascending
        self.frame_index = np.unique(np.concatenate([m.frame_index for m in motions])).astype(np.int64)
        self.people = []
        for k, (name, m) in enumerate(zip(names, motions)):
            with tempfile.TemporaryDirectory() as tmp:
                # row k at k / fps, as the page steps through the rows (not a variable-rate video's own times)
                glb = write_motion_glb(Path(tmp) / "motion.glb", m, own_times=False).read_bytes()
            where = {int(i): r for r, i in enumerate(m.frame_index)}
            self.people.append({"name": name, "motion": m, "glb": glb,
                                "rows": [where.get(int(i), -1) for i in self.frame_index],
                                "colour": None if not folders else list(PEOPLE_RGB[k % len(PEOPLE_RGB)])})
        self.glb = self.people[0]["glb"]
        #: what the page's user should know: runs not finished, an input that is not the tracked one
        self.notes = [n for n in (unfinished_words(d, m.run, m.num_frames)
                                  for d, m in zip([d for _, d in folders] or [self.result_dir], motions)) if n]
        self.seq = self._open_input(input)
        self._jpeg: dict[int, bytes] = {}
        self._lock = threading.Lock()

    @property
    def num_frames(self) -> int:
        """The page's frame count (the result's rows; with several people, the input frames
        any of them was tracked in)."""
        return len(self.frame_index)

    def _open_input(self, given):
        from flowmocap.errors import DataError
        from flowmocap.io.sequence import load_sequence
        from flowmocap.io.video import VIDEO_SUFFIXES, load_video

        cam = self.motion.camera
        recorded = given or self.motion.run.get("input")
        if not recorded:
            return None
        home = self._home
        for p in (Path(recorded), home / str(recorded), home / Path(recorded).name):
            if not p.exists():
                continue
            try:
                seq = (load_video(p, max_side=max(cam.width, cam.height))
                       if p.is_file() or p.suffix.lower() in VIDEO_SUFFIXES else load_sequence(p, max_side=max(cam.width, cam.height)))
            except DataError as e:
                if given:  # the user's own --input: say why it cannot be shown rather than show grey frames
                    raise DataError(f"--input {given} cannot be read: {e}") from None
                return None
            if tuple(seq.size) == (cam.width, cam.height) and len(seq) > int(self.frame_index.max()):
                from flowmocap.io.fingerprint import digest_input

                from flowmocap.io.results import decoded_otherwise_words

                otherwise = decoded_otherwise_words(self.motion.run, getattr(seq, "meta", {}) or {}, p)
                if otherwise:
                    self.notes.append(otherwise)
                recorded_digest = (self.motion.run.get("fingerprint") or {}).get("input")
                if recorded_digest and digest_input(p) != recorded_digest:
                    self.notes.append(f"note: {p} is not the input that was tracked (its content differs from the one "
                                      "in run.json's fingerprint); the body is drawn over it all the same")
                return seq
            if given:
                raise DataError(f"{p} has {len(seq)} frames of {seq.size[0]}x{seq.size[1]} but the result is "
                                f"{cam.width}x{cam.height} up to frame {int(self.frame_index.max())}; "
                                "pass the input that was tracked.")
            return None
        if given:
            raise DataError(f"input {given} does not exist.")
        return None

    def meta(self) -> dict:
        """The page's data, per page frame (T of them, :attr:`num_frames`): ``name``, ``fps``,
        ``num_frames``, ``frame_index`` (T: input frame numbers), ``times`` (T: seconds since
        the input's first frame, a variable-rate video's own), ``width``, ``height``
        (pixels), ``gl_camera`` (:func:`gl_camera` of the camera in the ground frame),
        ``camera`` (its ``to_dict``; the first frame's where the camera turned), ``gl_cameras``
        (None, or where the camera turned during the clip each page frame's camera's
        ``matrix_world``), ``gl_projections`` (None, or where it zoomed each page frame's
        camera's ``projection``), ``centre`` (mean pelvis of everyone, metres), ``floor``
        (how the floor was found), ``floor_of`` (the index of the person whose ground frame
        and floor these are), ``people`` (per person: ``name``, ``glb`` (its URL),
        ``colour`` (RGB 0..1, or None: the glb's own), ``rows`` (T: the person's result row
        of each page frame, -1 where not tracked), ``path`` (T x 3: the pelvis, metres, None
        where not tracked), ``contacts`` (T x 2: left/right foot standing still, 0/1, their
        own), ``feet`` (T x 2 x 3: the lowest point of the left and right foot, metres; None
        where not tracked), ``unseen`` (T: "held", "between" or "flow" where the person was
        tracked without being seen: held at the last seen pose, filled in between the poses
        before and after, or by flow alone, :func:`flowmocap.io.results.unseen_frames`; ""
        elsewhere), and from their result's ``disagreement``
        (:mod:`flowmocap.fit.disagreement`; both None without one) ``disagreement_cm`` (T:
        per frame the mean over the scored joints, centimetres; None where there is none or
        the person is not tracked) and ``review`` (T, 0/1:
        :func:`~flowmocap.fit.disagreement.review_frames`, the tenth of their frames where
        the sources part most; 0 where not tracked)); the first person's ``contacts``,
        ``feet``, ``path`` and ``disagreement_cm`` again at the top level; ``review`` at the
        top level: 1 where anyone's frame is to be reviewed (None where nobody's result has a
        disagreement); ``smoothed``, ``has_input``. For one result the page frames are its rows."""
        from flowmocap.export.world import foot_vertex_sets

        m = self.motion
        w = m.world
        left, right = foot_vertex_sets(m.model.weights.cpu().numpy())

        def lowest_feet(motion) -> list:  # (T, 2, 3) per result row: the lowest point of each foot
            feet = []
            for s in range(0, motion.num_frames, 64):
                v = motion.body(s, s + 64)[0]
                feet.append(np.stack([v[np.arange(len(v)), f[np.argmin(v[:, f, 1], axis=1)]]
                                      for f in (left, right)], 1))
            return np.round(np.concatenate(feet), 4).tolist()

        floor = (f"{w.plane.method} ({w.plane.inliers} foot points)" if w.plane.method == "contacts"
                 else "fallback (lowest foot point)")
        people, pelvis = [], []
        for k, p in enumerate(self.people):
            pm = p["motion"]
            root = pm.joints()[:, 0]
            pelvis.append(root)
            path = np.round(root, 4).tolist()
            feet = lowest_feet(pm)
            own = pm.foot_contacts
            contacts = own.astype(int).tolist() if own is not None else [[0, 0]] * pm.num_frames
            people.append({"name": p["name"], "glb": "/motion.glb" if k == 0 else f"/motion/{k}.glb",
                           "colour": p["colour"], "rows": p["rows"],
                           "path": [None if r < 0 else path[r] for r in p["rows"]],
                           "contacts": [[0, 0] if r < 0 else contacts[r] for r in p["rows"]],
                           "feet": [None if r < 0 else feet[r] for r in p["rows"]],
                           "unseen": self._unseen(pm, self.frame_index),
                           **self._review(pm, p["rows"])})
        marked = [p["review"] for p in people if p["review"] is not None]
        from flowmocap.export.motion import input_times

        times = np.round(input_times(m.run, self.frame_index, m.fps), 6).tolist()
        return {"name": self.result_dir.name, "fps": m.fps, "num_frames": self.num_frames,
                "frame_index": [int(i) for i in self.frame_index], "times": times, "width": m.camera.width, "height": m.camera.height,
                "gl_camera": gl_camera(m.camera), "camera": m.camera.to_dict(),
                "gl_cameras": self._turned_cameras(), "gl_projections": self._zoomed_projections(),
                "centre": np.concatenate(pelvis).mean(0).tolist(), "floor": floor, "floor_of": self.owner,
                "people": people,
                "contacts": people[0]["contacts"], "feet": people[0]["feet"], "path": people[0]["path"],
                "smoothed": m.smoothed, "has_input": self.seq is not None,
                "disagreement_cm": people[0]["disagreement_cm"],
                "review": [int(any(r[k] for r in marked)) for k in range(self.num_frames)] if marked else None}

    def _turned_cameras(self) -> list | None:
        """Where the camera turned during the clip (the motion turned back into the world,
        :mod:`flowmocap.export.motion`): per page frame, that frame's camera as the OpenGL
        ``matrix_world`` of :func:`gl_camera`; else None (one camera for every frame)."""
        from flowmocap.export.motion import camera_shifts, camera_turns, turned_camera

        m = self.motion
        if m.turns is None:
            return None
        turns = camera_turns(m.run, self.frame_index, floor=m.shifts is not None)
        shifts = (camera_shifts(m.run, self.frame_index) * m.camera_height_m if m.shifts is not None
                  else [None] * len(turns))
        return [gl_camera(turned_camera(m.camera, T, s))["matrix_world"] for T, s in zip(turns, shifts)]

    def _zoomed_projections(self) -> list | None:
        """Where the camera zoomed during the clip (:mod:`flowmocap.export.motion`): per page
        frame, that frame's camera's OpenGL ``projection`` (:func:`gl_camera`); else None."""
        from flowmocap.export.motion import camera_zooms

        m = self.motion
        if m.zooms is None:
            return None
        return [gl_camera(replace(m.camera, fx=m.camera.fx * z, fy=m.camera.fy * z))["projection"]
                for z in camera_zooms(m.run, self.frame_index)]

    @staticmethod
    def _unseen(motion, frame_index) -> list[str]:
        """Per page frame, how the person was tracked where they were not seen
        (:func:`flowmocap.io.results.unseen_frames`): "held" (at the last seen pose), "flow"
        (by flow alone), "between" (filled in between the poses before and after), or ""
        (seen, or not tracked)."""
        from flowmocap.io.results import unseen_frames

        how = unseen_frames(motion.run)
        tracked = {int(i) for i in motion.frame_index}
        return [how.get(int(i), "") if int(i) in tracked else "" for i in frame_index]

    @staticmethod
    def _review(motion, rows: list[int]) -> dict:
        """A person's ``disagreement_cm`` and ``review`` by page frame (see :meth:`meta`;
        None and None where their result has no disagreement)."""
        from flowmocap.fit.disagreement import review_frames

        d = motion.disagreement
        if d is None or not np.isfinite(d).any():
            return {"disagreement_cm": None, "review": None}
        per_frame, flagged = review_frames(d)
        return {"disagreement_cm": [None if r < 0 or not np.isfinite(per_frame[r])
                                    else round(100 * float(per_frame[r]), 1) for r in rows],
                "review": [0 if r < 0 else int(flagged[r]) for r in rows]}

    def frame_jpeg(self, k: int) -> bytes:
        """JPEG of page frame ``k``'s input frame (grey without an input)."""
        from PIL import Image

        with self._lock:
            if k in self._jpeg:
                return self._jpeg[k]
        cam = self.motion.camera
        if self.seq is None:
            image = np.full((cam.height, cam.width, 3), 48, np.uint8)
        else:
            image = np.asarray(self.seq.frame(int(self.frame_index[k])))[..., :3]
        buf = io.BytesIO()
        Image.fromarray(image).save(buf, "JPEG", quality=88)
        data = buf.getvalue()
        with self._lock:
            if len(self._jpeg) > 512:
                self._jpeg.clear()
            self._jpeg[k] = data
        return data


class _Handler(BaseHTTPRequestHandler):
    server_version = "flowmocap-view"

    def __init__(self, *args, data: ViewerData, quiet: bool = True, **kw):
        self.data = data
        self.quiet = quiet
        super().__init__(*args, **kw)

    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        if not self.quiet:
            super().log_message(format, *args)

    def _send(self, body: bytes, ctype: str, status: int = 200) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _host_is_local(self) -> bool:
        """Whether the request names this machine (or no host, as HTTP/1.0 may): a page
        elsewhere that points its own name at 127.0.0.1 (DNS rebinding) is refused."""
        host = self.headers.get("Host")
        if host is None:
            return True
        name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
        return name.strip().lower() in ("127.0.0.1", "localhost", "[::1]")

    def do_HEAD(self):  # noqa: N802 (http.server's name)
        self.do_GET()

    def do_GET(self):  # noqa: N802 (http.server's name)
        path = self.path.split("?", 1)[0]
        if not self._host_is_local():
            return self._send(b"this viewer answers only http://127.0.0.1 and http://localhost", "text/plain", 403)
        try:
            return self._answer(path)
        except (BrokenPipeError, ConnectionResetError):
            return None
        except (ValueError, OSError):  # a path no file can have (too long, a NUL): not found
            return self._send(b"not found", "text/plain", 404)
        except FlowMocapError as e:  # the input cannot be read (moved, deleted, damaged since the start)
            return self._send(str(e).encode(), "text/plain; charset=utf-8", 500)

    def _answer(self, path: str):
        if path in ("/", "/index.html"):
            return self._send((STATIC / "index.html").read_bytes(), "text/html; charset=utf-8")
        if path == "/api/meta.json":
            return self._send(json.dumps(self.data.meta()).encode(), "application/json")
        if path == "/motion.glb":
            return self._send(self.data.glb, "model/gltf-binary")
        if path.startswith("/motion/") and path.endswith(".glb"):
            k = _index(path[len("/motion/"):-len(".glb")])
            if not 0 <= k < len(self.data.people):
                return self._send(b"no such person", "text/plain", 404)
            return self._send(self.data.people[k]["glb"], "model/gltf-binary")
        if path.startswith("/frame/") and path.endswith(".jpg"):
            k = _index(path[len("/frame/"):-len(".jpg")])
            if not 0 <= k < self.data.num_frames:
                return self._send(b"no such frame", "text/plain", 404)
            return self._send(self.data.frame_jpeg(k), "image/jpeg")
        if path.startswith("/static/"):
            f = (STATIC / path[len("/static/"):]).resolve()
            if STATIC in f.parents and f.is_file():
                ctype = _TYPES.get(f.suffix, mimetypes.guess_type(f.name)[0] or "application/octet-stream")
                return self._send(f.read_bytes(), ctype)
        return self._send(b"not found", "text/plain", 404)


def _index(text: str) -> int:
    """A URL's frame or person number (ASCII digits, at most nine of them), or -1 where it is
    not one (the caller answers 404)."""
    return int(text) if text.isascii() and text.isdigit() and len(text) <= 9 else -1


def make_server(data: ViewerData, port: int = 8765, quiet: bool = True) -> ThreadingHTTPServer:
    """The viewer's HTTP server on 127.0.0.1:``port`` (0: any free port; see
    ``server.server_address``). Call ``serve_forever()``; ``shutdown()`` from another thread.

    Raises:
        InputError: the port is taken or not allowed.
    """
    from flowmocap.errors import InputError

    try:
        server = ThreadingHTTPServer(("127.0.0.1", port), partial(_Handler, data=data, quiet=quiet))
    except OSError as e:
        raise InputError(f"cannot listen on 127.0.0.1:{port} ({e.strerror}); pass another --port, "
                         "or --port 0 for any free one.") from None
    server.daemon_threads = True
    return server


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="look at a result in the browser: input with the overlay, 3D body on the floor",
        description="Serve a local page (http://127.0.0.1:PORT, this machine only) that shows the input "
        "frames with the fitted body over them and the body in 3D in the world frame (floor at 0, "
        "the camera in place): orbit with the mouse, play/pause, step, frame slider. Works offline "
        f"(three.js {THREE_VERSION} ships inside the package). Ctrl-C stops it.")
    p.add_argument("result", help="result folder (motion.npz, run.json), or a `track --person all` folder: every "
                   "person in their own colour")
    p.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (default 8765; 0: any free port)")
    p.add_argument("--no-browser", action="store_true", help="only print the address, do not open a browser")
    p.add_argument("--input", help="the tracked video or sequence folder, if it moved since tracking")
    p.add_argument("--smooth", nargs="?", const="default", default=None, metavar="SECONDS",
                   help="show the motion smoothed offline (as flowmocap export --smooth)")
    p.add_argument("--model", default=None, help="body model (default: the one recorded in run.json)")
    p.add_argument("--own-size", action="store_true",
                   help="a `track --person all` folder: each person keeps the size and distance of their own fit "
                        "(by default everyone after the first is scaled about the camera to stand on the first "
                        "person's floor)")
    p.add_argument("--verbose", action="store_true", help="log every request")
    p.set_defaults(func=run_view)


def run_view(args) -> int:
    import signal
    import webbrowser

    from flowmocap.commands.export import smooth_option

    if not 0 <= args.port <= 65535:
        from flowmocap.errors import InputError

        raise InputError(f"--port must be 0..65535, got {args.port}.")
    from flowmocap.io.results import PEOPLE_MANIFEST

    if args.own_size and not (Path(args.result) / PEOPLE_MANIFEST).exists():
        from flowmocap.errors import InputError

        raise InputError(f"--own-size is for the folder of `track --person all`; {args.result} is one result.")
    print(f"preparing {args.result} ...", flush=True)
    data = ViewerData(args.result, input=args.input, model=args.model, smooth=smooth_option(args.smooth, 2),
                      floor=not args.own_size)
    if data.floor is not None:
        for p, fit in zip(data.people, data.floor):
            print(fit.describe(p["name"], data.people[data.owner]["name"]), flush=True)
    server = make_server(data, args.port, quiet=not args.verbose)
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    who = f"; {', '.join(p['name'] for p in data.people)}" if len(data.people) > 1 else ""
    print(f"flowmocap view: {url}  ({data.num_frames} frames{who}; Ctrl-C to stop)", flush=True)
    for note in data.notes:
        print(note, flush=True)
    if data.seq is None:
        print("the tracked input was not found: frames are grey (pass --input VIDEO_OR_FOLDER)", flush=True)
    if not args.no_browser:
        webbrowser.open(url)

    def stop(signum, frame):  # SIGTERM (kill, a service manager) stops as cleanly as Ctrl-C
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("\nstopped", flush=True)
    finally:
        signal.signal(signal.SIGTERM, previous)
        server.server_close()
    return 0
