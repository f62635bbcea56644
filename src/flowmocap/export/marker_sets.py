"""Which points of the fitted body a marker export holds: the joints, or Pose2Sim's HALPE_26.

Two marker sets (:data:`MARKER_SETS`):

- ``joints``: the body model's 24 joint centres, named as :data:`~flowmocap.body.skeleton.JOINT_NAMES`.
- ``halpe26``: the 22 body and foot keypoints of the HALPE_26 skeleton as Pose2Sim names and
  orders them (``Hip``, ``RHip``, ``RKnee``, ..., ``LWrist``: :data:`HALPE26_NAMES`), the
  marker set of Pose2Sim's default pose model and of its OpenSim model
  (``Model_Pose2Sim_Halpe26.osim``), so that a ``.trc`` of it goes into Pose2Sim's
  scaling and inverse kinematics as its own triangulation would. The points are where a 2D
  detector puts those keypoints on a body, not joint centres:

  * hips, knees, ankles, shoulders, elbows, wrists: the detector's keypoints by the learned
    keypoint offsets (:mod:`flowmocap.vision.keypoint_map`: MediaPipe's hips sit higher and
    wider than the hip joints, its shoulders nearer the surface);
  * ``Hip``: the middle of the two hip keypoints (as Pose2Sim's model places it);
    ``Neck``: the body's neck joint, the base of the neck, 7.5 cm above the shoulders' line
    in the default body's rest pose (8 cm in Pose2Sim's model);
  * ``Head`` (the top of the head), ``Nose``, ``*BigToe``, ``*SmallToe``, ``*Heel``: mesh
    vertices of the fitted body, chosen once per body model by :func:`surface_vertices` from
    the rest pose's geometry.

  The limb keypoints' offsets were learned for MediaPipe, whose hips, knees, ankles and arm
  joints follow the same COCO annotation as HALPE's; the surface points are geometric
  (the most forward point of the face, ...), not learned from HALPE's annotators.
"""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError

__all__ = ["MARKER_SETS", "HALPE26_NAMES", "surface_vertices", "marker_names", "marker_trajectories"]

#: marker set name -> what it holds (for help texts).
MARKER_SETS: dict[str, str] = {
    "joints": "the 24 joint centres, named pelvis, left_hip, ...",
    "halpe26": "Pose2Sim's HALPE_26 keypoints (Hip, RHip, RKnee, ..., heels and toes), for its OpenSim model",
}

#: The HALPE_26 markers of Pose2Sim's skeleton tree (``Pose2Sim.skeletons.HALPE_26``), in
#: its tree order; the eyes and ears of the detector's 26 keypoints are not in the tree.
HALPE26_NAMES: tuple[str, ...] = (
    "Hip", "RHip", "RKnee", "RAnkle", "RBigToe", "RSmallToe", "RHeel",
    "LHip", "LKnee", "LAnkle", "LBigToe", "LSmallToe", "LHeel",
    "Neck", "Head", "Nose",
    "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist",
)

#: HALPE_26 limb keypoint -> the body joint whose detector keypoint it is.
_KEYPOINT_JOINT = {
    f"{s}{part}": f"{side}_{joint}"
    for s, side in (("R", "right"), ("L", "left"))
    for part, joint in (("Hip", "hip"), ("Knee", "knee"), ("Ankle", "ankle"),
                        ("Shoulder", "shoulder"), ("Elbow", "elbow"), ("Wrist", "wrist"))
}

#: A toe's share of the foot's front: vertices within this of the foot's most forward point
#: (metres) count as the front of the foot, where the big toe is the most medial.
_TOE_FRONT_M = 0.01


def _check_set(marker_set: str) -> None:
    if marker_set not in MARKER_SETS:
        raise InputError(f"unknown marker set {marker_set!r}; choose one of {', '.join(MARKER_SETS)}.")


def marker_names(marker_set: str = "joints") -> tuple[str, ...]:
    """The marker names of ``marker_set``, in the order :func:`marker_trajectories` gives them.

    Raises:
        InputError: an unknown marker set.
    """
    from flowmocap.body.skeleton import JOINT_NAMES

    _check_set(marker_set)
    return tuple(JOINT_NAMES) if marker_set == "joints" else HALPE26_NAMES


def surface_vertices(model) -> dict[str, int]:
    """The mesh vertices of the HALPE_26 surface points, chosen from the rest pose's geometry.

    Rules on the mean shape's rest (T-) pose, in the model's axes (y up, facing +z, the body's
    left at +x; every SMPL-format model): for each foot, the vertices below its ankle joint on
    its side of the body are the foot; its heel is the foot's rearmost vertex, its big toe the
    most medial vertex within 1 cm of the foot's most forward point, its small toe the vertex
    furthest forward and outward (largest ``z + |x|``). Of the vertices within 2 cm of the
    body's midline above the neck joint, ``Nose`` is the most forward; ``Head`` is the top of
    the stature (:func:`flowmocap.body.stature.stature_vertices`), the highest on the midline.

    Args:
        model: a :class:`~flowmocap.body.BodyModel`.

    Returns:
        ``{name: vertex index}`` for ``Head``, ``Nose``, ``LHeel``, ``LBigToe``,
        ``LSmallToe``, ``RHeel``, ``RBigToe``, ``RSmallToe``.

    Raises:
        ModelFileError: a model in which a foot or the face cannot be found (not an upright
            body in the SMPL axes).
    """
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.body.stature import MIDLINE_M, stature_vertices
    from flowmocap.errors import ModelFileError

    v = model.v_template.detach().double().cpu().numpy()
    joints = model.J_regressor.detach().double().cpu().numpy() @ v
    face = np.flatnonzero((v[:, 1] > joints[JOINT_INDEX["neck"], 1]) & (np.abs(v[:, 0]) < MIDLINE_M))
    if face.size == 0:
        raise ModelFileError("no mesh vertex on the body's midline above its neck joint; the model is not an "
                             "upright body in the SMPL axes (y up, facing +z).")
    out = {"Head": stature_vertices(model)[0], "Nose": int(face[np.argmax(v[face, 2])])}
    for s, side, sign in (("L", "left", 1.0), ("R", "right", -1.0)):
        ankle = joints[JOINT_INDEX[f"{side}_ankle"]]
        foot = np.flatnonzero((v[:, 1] < ankle[1]) & (sign * v[:, 0] > 0))
        if foot.size < 3:
            raise ModelFileError(f"no mesh vertices below the {side} ankle joint; the model is not an upright "
                                 "body in the SMPL axes (y up, facing +z, its left at +x).")
        fv = v[foot]
        out[f"{s}Heel"] = int(foot[np.argmin(fv[:, 2])])
        front = np.flatnonzero(fv[:, 2] > fv[:, 2].max() - _TOE_FRONT_M)
        out[f"{s}BigToe"] = int(foot[front[np.argmin(sign * fv[front, 0])]])
        out[f"{s}SmallToe"] = int(foot[np.argmax(fv[:, 2] + sign * fv[:, 0])])
    return out


def marker_trajectories(motion, marker_set: str = "joints", chunk: int = 256) -> tuple[tuple[str, ...], np.ndarray]:
    """The markers of ``marker_set`` on every frame of a fitted motion.

    Args:
        motion: a :class:`~flowmocap.export.motion.FittedMotion` (its export frame).
        marker_set: one of :data:`MARKER_SETS`.
        chunk: frames posed at a time (``halpe26`` poses the mesh).

    Returns:
        ``(names, positions)``: :func:`marker_names` and ``(T, M, 3)`` float64 metres in the
        motion's export frame.

    Raises:
        InputError: an unknown marker set.
    """
    from flowmocap.body.skeleton import JOINT_INDEX
    from flowmocap.vision.keypoint_map import load_keypoint_map

    names = marker_names(marker_set)
    if marker_set == "joints":
        return names, motion.joints()
    surface = surface_vertices(motion.model)
    kmap = load_keypoint_map()
    frames = []
    for out in motion.posed(chunk, with_vertices=True):
        keypoints = kmap.apply(out.joints, out.transforms).numpy()
        vertices = out.vertices.numpy()
        points = {}
        for name, joint in _KEYPOINT_JOINT.items():
            points[name] = keypoints[:, JOINT_INDEX[joint]]
        for name, index in surface.items():
            points[name] = vertices[:, index]
        points["Hip"] = 0.5 * (points["LHip"] + points["RHip"])
        points["Neck"] = out.joints[:, JOINT_INDEX["neck"]].numpy()
        frames.append(np.stack([points[n] for n in names], axis=1))
    return names, (np.concatenate(frames) if frames else np.zeros((0, len(names), 3)))
