"""One floor for the people of one video (``flowmocap track --person all``).

One camera leaves each body's absolute size open: a body ``s`` times larger, ``s`` times
further from the camera, gives nearly the same image. Each person of a video is fitted
alone, so each body's size is what its own fit and the shape prior settle on (about 1.6 m
for anyone), and two people of different heights come out the same height, at depths that
do not stand them on one floor. The people of one video do share a floor. This module puts
everyone on the first person's floor (or, where the first person never stands still, on the
floor of the next person in rank order who does: :func:`people_floor`):

- :func:`floor_in_camera`: a person's floor (their ground frame,
  :mod:`flowmocap.export.world`, fitted to their standing feet) as a plane in camera
  coordinates;
- :func:`floor_scale`: the factor ``s`` that scales another person about the camera centre
  so that their standing feet (the lowest vertex of each foot in the frames it stands still)
  rest on that plane, the median over those points of ``d / (n . p)``;
- :func:`scaled_about_camera`: the person's body scaled by ``s`` (the shape nearest to it
  scaled, :func:`flowmocap.body.stature.scaled_shape`) with the root ``s`` times as far from
  the camera along its ray: the image stays, up to the few millimetres by which a shape
  space misses an exact scaling.

Measured on the four-camera recording (``benchmarks/people_floor.py``; ``docs/experiments.md``,
"The people of one video on one floor"): the second person's depth relative to the first's is
nearer the four-camera reference in 23 of 24 camera / floor pairs, and their size relative to
the first comes out 0.77-0.87x (the reference's bones 0.81x), where each fit alone makes them
0.91-1.10x.

The floor is not shared where a person stands on something else (a box, stairs, a step):
a factor outside :data:`SCALE_RANGE` is refused and that person keeps their own size.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from flowmocap.errors import DataError

__all__ = ["FloorFit", "floor_owner", "SCALE_RANGE", "MIN_POINTS", "floor_in_camera", "standing_feet_in_camera", "floor_scale",
           "scaled_about_camera", "people_floor", "write_floor", "FLOOR_FILE"]

#: What :func:`write_floor` writes beside a people folder's exports.
FLOOR_FILE = "floor.json"

#: Factors a person may be scaled by to stand on the shared floor; one outside is
#: refused (the person keeps their own fit's size): more than half again or a third less
#: than the body's fitted size is a person on something else, or a floor fitted wrong.
SCALE_RANGE = (0.67, 1.5)

#: Standing-foot points (one per foot and frame it stands still) a person needs for a factor.
MIN_POINTS = 10


@dataclass
class FloorFit:
    """How a person was put on the shared floor.

    Attributes:
        scale: the factor about the camera centre (1.0 for the person whose floor it is), or None
            where it was refused or could not be found (``why`` says which): the person
            then keeps their own size.
        points: standing-foot points it was found from.
        stature_m: the body's stature after scaling (its own where ``scale`` is None), metres.
        own_stature_m: the stature of the person's own fit, metres.
        why: None, or why the person keeps their own size.
        floor_of: the index (rank order) of the person whose floor is shared; None where
            nobody's is.
        camera_move: where the camera was carried and this person's own body decided
            otherwise than the owner's, what was done instead: the owner's decision, for
            everyone (:func:`~flowmocap.export.motion.shared_move_refusal`); else None.
    """

    scale: float | None
    points: int
    stature_m: float
    own_stature_m: float
    why: str | None = None
    floor_of: int | None = None
    camera_move: str | None = None

    def to_dict(self) -> dict:
        """A JSON summary: ``scale`` (or None), ``points``, ``stature_m`` and ``own_stature_m``
        (metres, to the millimetre), ``why`` and ``camera_move``."""
        return {"scale": None if self.scale is None else round(self.scale, 4), "points": self.points,
                "stature_m": round(self.stature_m, 3), "own_stature_m": round(self.own_stature_m, 3),
                "why": self.why, "camera_move": self.camera_move}

    def describe(self, name: str, owner: str) -> str:
        """One line for the user; ``owner``: the name of the person whose floor is shared."""
        move = "" if self.camera_move is None else f"; the camera's move {self.camera_move}"
        if self.scale is None:
            return f"{name}: kept the size of its own fit ({self.own_stature_m:.2f} m tall): {self.why}{move}"
        if name == owner:
            return f"{name}: its floor is everyone's ({self.own_stature_m:.2f} m tall){move}"
        return (f"{name}: stood on {owner}'s floor: {self.scale:.2f}x the size and distance of its own fit "
                f"({self.own_stature_m:.2f} -> {self.stature_m:.2f} m tall; {self.points} standing-foot points){move}")


def floor_owner(fits: list[FloorFit] | None) -> int:
    """The index of the person whose floor :func:`people_floor` shared (and whose frame the
    people are shown and exported in); 0 where nobody's was (``fits`` None or no floor)."""
    for f in fits or []:
        if f.floor_of is not None:
            return f.floor_of
    return 0


def floor_in_camera(motion) -> tuple[np.ndarray, float]:
    """The floor of ``motion`` as the plane ``n . X = d`` in its camera's coordinates.

    Args:
        motion: a :class:`~flowmocap.export.motion.FittedMotion` loaded with
            ``frame="ground"`` (its ``world`` holds the floor).

    Returns:
        ``n`` ``(3,)`` the unit normal pointing up, and ``d`` (metres; negative when the
        camera is above the floor).

    Raises:
        DataError: ``motion`` has no floor (loaded in another frame).
    """
    if motion.world is None:
        raise DataError("this motion has no floor: load it with frame='ground'.")
    plane = motion.world.plane
    n_e = motion.rotation @ np.asarray(plane.normal, np.float64)  # the result's frame -> the export frame
    h_e = float(plane.height) + n_e @ np.asarray(motion.offset, np.float64)
    R, t = np.asarray(motion.camera.R, np.float64), np.asarray(motion.camera.t, np.float64)
    n_c = R @ n_e
    return n_c, h_e + float(n_c @ t)


def standing_feet_in_camera(motion, up_camera: np.ndarray, chunk: int = 64) -> np.ndarray:
    """The lowest vertex along ``up_camera`` of each foot in the frames it stands still.

    Args:
        motion: a :class:`~flowmocap.export.motion.FittedMotion` loaded with
            ``frame="ground"`` (its ``world.contacts``, ``(T, 2)`` left/right).
        up_camera: ``(3,)`` the up direction in camera coordinates.

    Returns:
        ``(P, 3)`` camera coordinates, metres; P = the number of standing feet over the frames.
    """
    from flowmocap.export.world import foot_vertex_sets

    if motion.world is None:
        raise DataError("this motion has no foot contacts: load it with frame='ground'.")
    contacts = np.asarray(motion.world.contacts, bool)
    R, t = np.asarray(motion.camera.R, np.float64), np.asarray(motion.camera.t, np.float64)
    up = R.T @ np.asarray(up_camera, np.float64)  # in the motion's export frame
    feet = foot_vertex_sets(motion.model.weights.cpu().numpy())
    out = []
    start = 0
    for body in motion.posed(chunk=chunk, with_vertices=True):
        v = body.vertices.numpy()
        for k, idx in enumerate(feet):
            rows = np.flatnonzero(contacts[start:start + len(v), k])
            if rows.size:
                f = v[rows][:, idx]
                out.append(np.take_along_axis(f, np.argmin(f @ up, axis=1)[:, None, None], axis=1)[:, 0])
        start += len(v)
    pts = np.concatenate(out) if out else np.zeros((0, 3))
    return pts @ R.T + t


def floor_scale(motion, first, scale_range: tuple[float, float] = SCALE_RANGE,
                min_points: int = MIN_POINTS) -> FloorFit:
    """The factor about the camera centre that stands ``motion`` on ``first``'s floor.

    Args:
        motion, first: two :class:`~flowmocap.export.motion.FittedMotion` of one input (one
            camera), both loaded with ``frame="ground"``.
        scale_range: the factors accepted (:data:`SCALE_RANGE`).
        min_points: the standing-foot points needed (:data:`MIN_POINTS`).

    Returns:
        :class:`FloorFit`; ``scale`` None (with ``why``) where ``first``'s floor is not
        fitted to standing feet, the camera is not above it, ``motion`` stands still on too
        few feet, or the factor lies outside ``scale_range``.
    """
    from flowmocap.body.stature import STATURE_RANGE_M, scaled_shape, stature

    own = stature(motion.model, motion.betas)
    keep = lambda why, points=0: FloorFit(None, points, own, own, why)  # noqa: E731
    if first.world is None or first.world.plane.method != "contacts":
        return keep("the shared floor is not fitted to standing feet")
    n_c, d_c = floor_in_camera(first)
    if d_c >= 0:
        return keep("the camera is not above the shared floor")
    pts = standing_feet_in_camera(motion, n_c)
    below = pts[pts @ n_c < 0]  # a point level with the camera or above it cannot be scaled onto the floor
    if len(below) < min_points:
        return keep(f"it stands still on a foot in too few frames ({len(below)} foot points, {min_points} needed)",
                    len(below))
    s = float(np.median(d_c / (below @ n_c)))
    if not scale_range[0] <= s <= scale_range[1] or not STATURE_RANGE_M[0] <= s * own <= STATURE_RANGE_M[1]:
        return keep(f"its standing feet would need {s:.2f}x its size and distance to rest on the shared "
                    "floor: not the same floor (a box, stairs, a step?)", len(below))
    return FloorFit(s, len(below), stature(motion.model, scaled_shape(motion.model, motion.betas, s)), own)


def scaled_about_camera(motion, scale: float):
    """``motion`` scaled about its camera's centre by ``scale``: the body given the shape
    nearest to it scaled by ``scale`` (:func:`flowmocap.body.stature.scaled_shape`) and its
    root ``scale`` times as far from the camera along the same ray, in every frame.

    Args:
        motion: a :class:`~flowmocap.export.motion.FittedMotion` (any frame).
        scale: the factor (> 0).

    Returns:
        A new :class:`FittedMotion` in the same frame: ``betas``, ``trans`` and ``joints2d``
        (re-projected) changed, ``world`` None (its floor moved with it), ``contacts`` its
        foot contacts (:attr:`~flowmocap.export.motion.FittedMotion.foot_contacts`). Where the
        camera moved (``shifts``), its path and ``camera_height_m`` are scaled too: the whole
        world scales about the first frame's camera centre, so each frame's camera still sees
        the body where it did.
    """
    import torch

    from flowmocap.body.stature import scaled_shape

    if not scale > 0:
        raise DataError(f"a scale must be positive; got {scale!r}.")
    betas = np.asarray(motion.betas, np.float64)
    new = scaled_shape(motion.model, betas, scale)
    with torch.no_grad():
        root_old = motion.model(betas=torch.as_tensor(betas[None])).rest_joints[0, 0].double().numpy()
        root_new = motion.model(betas=torch.as_tensor(new[None])).rest_joints[0, 0].double().numpy()
    R, t = np.asarray(motion.camera.R, np.float64), np.asarray(motion.camera.t, np.float64)
    root_cam = (np.asarray(motion.trans, np.float64) + root_old) @ R.T + t  # (T, 3): the posed root, camera
    trans = (scale * root_cam - t) @ R - root_new
    moved = motion.shifts is not None  # the camera's path scales with the world (x_k = turns_k (x_0 + shifts_k))
    out = replace(motion, betas=new, trans=trans, world=None, contacts=motion.foot_contacts,
                  shifts=scale * np.asarray(motion.shifts, np.float64) if moved else None,
                  camera_height_m=(scale * motion.camera_height_m if moved and motion.camera_height_m is not None
                                   else motion.camera_height_m))
    out.joints2d = out.project(out.joints())
    return out


def people_floor(folders, model=None) -> list[FloorFit]:
    """:func:`floor_scale` for each result of one input against the floor of the first
    person whose floor is fitted to their standing feet.

    That is the first person's (the largest) unless they never stand still (a jump, a
    dance, a person seen only from the waist up), whose floor is then only a guess (through
    their lowest foot point): the floor of the next person in order who does stand is
    shared, and the first person is stood on it like anyone else.

    Under a carried camera, the move found from the floor is undone for everyone as it is
    for that person (the first where nobody stands), or for nobody
    (:func:`~flowmocap.export.motion.shared_move_refusal`): each person's run found the
    camera's motion again and judged its floor against their own upright body, and one
    camera cannot have moved for one person and not for another.

    Args:
        folders: result folders of one input (``track --person all``'s ``person0``, ...),
            in rank order.
        model: body model override.

    Returns:
        one :class:`FloorFit` per folder, each with ``floor_of`` the index of the person
        whose floor is shared (:func:`floor_owner`); that person's scale 1.0. Where nobody's
        floor is fitted to standing feet, every scale is None and nobody is moved.
    """
    from flowmocap.body.stature import stature
    from flowmocap.export.motion import load_fitted_motion

    motions = [load_fitted_motion(d, frame="ground", model=model) for d in folders]
    standing = [k for k, m in enumerate(motions) if m.world.plane.method == "contacts"]
    owner = standing[0] if standing else 0
    moves = [None] * len(motions)
    for k, m in enumerate(motions):  # one camera: its move undone for everyone as for the owner, or for nobody
        if k != owner and (m.shifts is not None or motions[owner].shifts is not None):
            motions[k] = load_fitted_motion(folders[k], frame="ground", model=model, camera_move_of=motions[owner])
            if motions[k].shifts is not None and m.shifts is None:
                alone = m.camera_move_refused or "its own run found no move of the camera"
                moves[k] = f"undone as for the person whose floor is shared (alone it would not be: {alone})"
            elif motions[k].shifts is None and motions[k].camera_move_refused != m.camera_move_refused:
                moves[k] = f"not undone: {motions[k].camera_move_refused}"
    fits = []
    for k, (m, move) in enumerate(zip(motions, moves)):
        own = stature(m.model, m.betas)
        if not standing:
            fits.append(FloorFit(None, 0, own, own, "nobody's floor is fitted to standing feet: nobody is moved",
                                 camera_move=move))
        elif k == owner:
            fits.append(FloorFit(1.0, int(np.asarray(m.world.contacts).sum()), own, own, floor_of=k))
        else:
            fits.append(replace(floor_scale(m, motions[owner]), floor_of=owner, camera_move=move))
    return fits


def write_floor(path, names: list[str], fits: list[FloorFit] | None):
    """Write how the people were put on one floor (``fits`` from :func:`people_floor`, or
    None where they were not) as JSON, atomically: ``{"format": "flowmocap-floor",
    "version": 1, "shared": bool, "first": name (whose floor is shared and whose frame the
    exports are in), "people": {name: FloorFit.to_dict()}}``. Returns the path."""
    import json
    from pathlib import Path

    from flowmocap.atomic import atomic_write

    doc = {"format": "flowmocap-floor", "version": 1, "shared": fits is not None,
           "first": names[floor_owner(fits)] if names else None,
           "people": {} if fits is None else {n: f.to_dict() for n, f in zip(names, fits)}}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(doc, indent=2)))
    return path
