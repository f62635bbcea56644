"""Mocap readers: ASF/AMC and BVH agree with their own forward kinematics; errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from flowmocap.errors import DataError
from flowmocap.io import read_asf_amc, read_bvh, read_mocap, resample, write_bvh
from flowmocap.io.mocap import find_asf

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CMU = SHARED_DATA / "mocap" / "cmu"
needs_cmu = pytest.mark.skipif(
    not (CMU / "35_01.amc").exists(), reason=f"CMU mocap not found at {CMU} (shared data absent)"
)


@pytest.fixture(scope="module")
def cmu_clip():
    if not (CMU / "35_01.amc").exists():
        pytest.skip(f"CMU mocap not found at {CMU} (shared data absent)")
    return read_mocap(CMU / "35_01.amc")


# ------------------------------------------------------------------------ ASF / AMC


@needs_cmu
def test_asf_amc_units_and_plausibility(cmu_clip):
    c = cmu_clip
    assert c.num_frames == 358 and c.fps == 120.0
    assert c.info["length_unit_m"] == pytest.approx(0.0254 / 0.45)
    rest = c.rest_positions()
    # Toe tips to the end of the head bone: the person is about 1.6-1.8 m tall.
    assert 1.5 < rest[:, 1].max() - rest[:, 1].min() < 1.8
    P = c.positions
    # Straight walk along +z at about 1.27 m/s, pelvis about 1 m up, feet near y = 0.
    d = P[-1, 0] - P[0, 0]
    speed = np.hypot(d[0], d[2]) / c.duration
    assert 1.2 < speed < 1.35
    assert 0.9 < P[:, 0, 1].mean() < 1.1
    assert -0.02 < P[:, :, 1].min() < 0.05
    # Knee flexion during walking, from the clip's own joints.
    i = [c.index(n) for n in ("lfemur", "ltibia", "lfoot")]
    u, v = P[:, i[1]] - P[:, i[0]], P[:, i[2]] - P[:, i[1]]
    knee = np.degrees(np.arccos((u * v).sum(-1) / np.linalg.norm(u, axis=-1) / np.linalg.norm(v, axis=-1)))
    assert knee.min() < 20 and 50 < knee.max() < 85
    # Left is +x when walking +z: the ASF rest faces +z with y up.
    assert (P[:, c.index("lfemur"), 0] - P[:, c.index("rfemur"), 0]).mean() > 0.1


@needs_cmu
def test_asf_amc_to_bvh_round_trip(cmu_clip, tmp_path):
    c = cmu_clip
    for upm, order, unit in ((1.0, "ZYX", "m"), (100.0, "ZXY", "cm"), (1 / c.info["length_unit_m"], "YXZ", "cmu_asf_unit")):
        path = write_bvh(c, tmp_path / f"35_01_{order}.bvh", units_per_metre=upm, order=order)
        b = read_bvh(path)
        assert b.info["unit"] == unit
        assert b.names == c.names
        assert np.array_equal(b.parents, c.parents)
        assert b.fps == pytest.approx(120.0)
        assert np.abs(b.positions - c.positions).max() < 1e-6
        assert np.abs(b.rotations - c.rotations).max() < 1e-6


@needs_cmu
def test_find_asf_and_read_mocap(tmp_path):
    assert find_asf(CMU / "35_01.amc") == CMU / "35.asf"
    with pytest.raises(DataError, match="no ASF skeleton"):
        find_asf(tmp_path / "01_01.amc")
    with pytest.raises(DataError, match="skeleton"):
        read_mocap(CMU / "35.asf")


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


ASF = """:version 1.10
:name test
:units
  mass 1.0
  length 0.45
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name thigh
     direction 0 -1 0
     length 9
     axis 0 0 90 XYZ
    dof rx ry rz
    limits (-160.0 20.0)
           (-70.0 70.0)
           (-60.0 70.0)
  end
  begin
     id 2
     name shin
     direction 0 -1 0
     length 9
     axis 0 0 0 XYZ
    dof rx
  end
:hierarchy
  begin
    root thigh
    thigh shin
  end
"""


def test_asf_amc_hand_computed(tmp_path):
    """A two-bone leg: the bone axis C = Rz(90) turns the AMC's rx into a rotation about y."""
    asf = _write(tmp_path, "t.asf", ASF)
    amc = _write(tmp_path, "t_01.amc", ":FULLY-SPECIFIED\n:DEGREES\n"
                 "1\nroot 0 18 0 0 0 0\nthigh 0 0 0\nshin 0\n"
                 "2\nroot 0 18 0 0 90 0\nthigh 90 0 0\nshin 90\n")
    c = read_asf_amc(asf, amc, fps=60)
    u = 0.0254 / 0.45
    assert c.names == ("root", "thigh", "shin", "shin_end")
    P = c.positions / u
    np.testing.assert_allclose(P[0], [[0, 18, 0], [0, 18, 0], [0, 9, 0], [0, 0, 0]], atol=1e-9)
    # Frame 2: the thigh's rx = 90 is about its local x, which C = Rz(90) maps to the
    # world y: L_thigh = Ry(90), and the downward thigh does not move. With the root's
    # RY = 90, G_thigh = Ry(180). The shin's rx = 90 (axis 0 0 0) swings it from -y to -z
    # in the thigh's frame, which Ry(180) turns to +z.
    np.testing.assert_allclose(P[1], [[0, 18, 0], [0, 18, 0], [0, 9, 0], [0, 9, 9]], atol=1e-9)
    assert c.fps == 60


def test_asf_amc_errors(tmp_path):
    asf = _write(tmp_path, "t.asf", ASF)
    with pytest.raises(DataError, match="not found"):
        read_asf_amc(tmp_path / "missing.asf", tmp_path / "x.amc")
    amc = _write(tmp_path, "a.amc", "1\nroot 0 0 0 0 0 0\nthigh 1 2\n")
    with pytest.raises(DataError, match=r"a\.amc:3: bone 'thigh' has 2 values"):
        read_asf_amc(asf, amc)
    amc = _write(tmp_path, "b.amc", "1\nroot 0 0 0 0 0 0\nfoot 1\n")
    with pytest.raises(DataError, match=r"b\.amc:3: bone 'foot' is not in the ASF"):
        read_asf_amc(asf, amc)
    amc = _write(tmp_path, "c.amc", "1\nroot 0 0 0 0 0 0\n3\nroot 0 0 0 0 0 0\n")
    with pytest.raises(DataError, match=r"c\.amc:3: frame 3 follows frame 1"):
        read_asf_amc(asf, amc)
    bad = _write(tmp_path, "bad.asf", ASF.replace("    thigh shin\n", "    thigh knee\n"))
    with pytest.raises(DataError, match=r"bad\.asf:\d+: hierarchy names bone 'knee'"):
        read_asf_amc(bad, amc)
    bad = _write(tmp_path, "bad2.asf", ASF.split(":hierarchy")[0])
    with pytest.raises(DataError, match="no :hierarchy section"):
        read_asf_amc(bad, amc)


# ------------------------------------------------------------------------------ BVH

TINY_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 50 0
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 10 0 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT LeftLeg
    {
      OFFSET 0 -45 0
      CHANNELS 1 Xrotation
      End Site
      {
        OFFSET 0 -45 5
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.04
0 100 0  0 0 0  0 0 0  0 0 0  0
1 100 2  90 0 0  0 90 0  0 0 0  0
0 100 0  0 0 0  0 0 0  90 0 0  -90
"""


def test_bvh_hand_computed(tmp_path):
    c = read_bvh(_write(tmp_path, "tiny.bvh", TINY_BVH))
    assert c.info["unit"] == "cm"  # the rest skeleton is 150 units tall
    assert c.fps == pytest.approx(25.0)
    assert c.names == ("Hips", "Chest", "Chest_end", "LeftUpLeg", "LeftLeg", "LeftLeg_end")
    assert list(c.end_site) == [False, False, True, False, False, True]
    P = c.positions * 100  # back to cm
    # Frame 0: rest pose at the root position.
    np.testing.assert_allclose(P[0], [[0, 100, 0], [0, 110, 0], [0, 160, 0],
                                      [10, 100, 0], [10, 55, 0], [10, 10, 5]], atol=1e-9)
    # Frame 1: root Rz(90) (x -> y, y -> -x); chest Rz(0) Rx(90) Ry(0): its y -> z.
    np.testing.assert_allclose(P[1], [[1, 100, 2], [-9, 100, 2], [-9, 100, 52],
                                      [1, 110, 2], [46, 110, 2], [91, 110, 7]], atol=1e-9)
    # Frame 2: hip Rx(90) (-y -> -z, z -> -y), knee Rx(-90) undoes it for the shin.
    np.testing.assert_allclose(P[2], [[0, 100, 0], [0, 110, 0], [0, 160, 0],
                                      [10, 100, 0], [10, 100, -45], [10, 55, -40]], atol=1e-9)


def test_bvh_z_up_and_scale(tmp_path):
    y_up = read_bvh(_write(tmp_path, "tiny.bvh", TINY_BVH), scale=0.01)
    # The same skeleton written z-up: (x, y, z)_yup = (x, z, -y)_zup.
    z_up = read_bvh(write_bvh(_z_up(y_up), tmp_path / "zup.bvh", units_per_metre=100), up="z")
    np.testing.assert_allclose(z_up.positions, y_up.positions, atol=1e-9)


def _z_up(clip):
    from dataclasses import replace

    B = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # y-up -> z-up coordinates
    return replace(clip, offsets=clip.offsets @ B.T, translations=clip.translations @ B.T,
                   rotations=B @ clip.rotations @ B.T, positions=clip.positions @ B.T)


def test_bvh_errors(tmp_path):
    with pytest.raises(DataError, match="not found"):
        read_bvh(tmp_path / "nothing.bvh")
    p = _write(tmp_path, "a.bvh", TINY_BVH.replace("Frames: 3", "Frames: 4"))
    with pytest.raises(DataError, match=r"a\.bvh:\d+: the header says 4 frames but 3"):
        read_bvh(p)
    p = _write(tmp_path, "b.bvh", TINY_BVH.replace("0 100 0  0 0 0  0 0 0  90 0 0  -90", "0 100 0  0 0"))
    with pytest.raises(DataError, match=r"b\.bvh:35: frame 2 has 5 values, the hierarchy declares 13"):
        read_bvh(p)
    p = _write(tmp_path, "c.bvh", TINY_BVH.replace("CHANNELS 3 Zrotation Xrotation Yrotation",
                                                   "CHANNELS 3 Zrotation Xrotation Wrotation"))
    with pytest.raises(DataError, match=r"c\.bvh:9: unknown channel 'Wrotation'"):
        read_bvh(p)
    p = _write(tmp_path, "d.bvh", TINY_BVH.replace("HIERARCHY", "HIERARCHIE"))
    with pytest.raises(DataError, match=r"d\.bvh:1: a BVH file starts with HIERARCHY"):
        read_bvh(p)
    p = _write(tmp_path, "e.bvh", TINY_BVH.replace("OFFSET 0 -45 0", "OFFSET 0 -45"))
    with pytest.raises(DataError, match=r"e\.bvh:\d+: expected numbers for OFFSET"):
        read_bvh(p)
    p = _write(tmp_path, "f.bvh", TINY_BVH.replace("OFFSET 0 10 0", "OFFSET 0 10000 0"))
    with pytest.raises(DataError, match="cannot tell the length unit"):
        read_bvh(p)
    with pytest.raises(DataError, match="unknown mocap file type"):
        read_mocap(_write(tmp_path, "x.c3d", ""))


# ------------------------------------------------------------------------ resampling


@needs_cmu
def test_resample(cmu_clip):
    c = cmu_clip
    r = resample(c, 30.0)
    assert r.fps == 30.0 and r.num_frames == 90  # 357/120 s -> frames at 0 .. 89/30 s
    np.testing.assert_allclose(r.positions, c.positions[::4][:90], atol=1e-9)
    r = resample(c, 50.0)
    t = np.arange(r.num_frames) / 50.0 * 120.0
    i0 = np.floor(t).astype(int)
    i1 = np.minimum(i0 + 1, c.num_frames - 1)
    w = (t - i0)[:, None, None]
    lin = (1 - w) * c.positions[i0] + w * c.positions[i1]
    err = np.abs(r.positions - lin).max(-1)
    # slerp vs chord: within 1 mm almost everywhere at 120 Hz (a toe tip jumps 12 cm
    # between two frames of this clip, where the two differ by 1.4 cm)
    assert np.percentile(err, 99) < 1e-3 and err.max() < 0.02
