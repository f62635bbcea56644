"""Every person in one input (``flowmocap track VIDEO --person all``,
:func:`flowmocap.batch.track_people`): who is tracked, one result folder per person,
``people.json``, finished people skipped and a failed one retried on the next run, bad
arguments refused; and on the real two-person recording, two different people."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import flowmocap
from flowmocap import batch
from flowmocap.batch import PEOPLE_MANIFEST, PEOPLE_SEARCH, people_to_track, track_people
from flowmocap.cli import main
from flowmocap.errors import DataError, InputError
from flowmocap.eval.protocol import noisy_init
from flowmocap.io.sequence import load_sequence
from flowmocap.synth import synthesize
from flowmocap.vision.person import parse_person

from conftest import SHARED_DATA

QUICK = {"iterations": 4, "init_iterations": 6, "init_flow_iterations": 4}


def _info(*detections):
    return {"person": {"people": [{"rank": r, "frames": [0, n - 1], "detections": n, "score": 100.0 - r,
                                   "first_box": [10.0 * r, 0.0, 10.0 * r + 8, 30.0]}
                                  for r, n in enumerate(detections)]}}


def test_people_to_track_keeps_the_largest_and_everyone_followed_long_enough():
    info = _info(40, 30, 10, 9, 3)
    assert [p["rank"] for p in people_to_track(info)] == [0, 1, 2]  # 10 >= 0.25 * 40; 9 and 3 are not
    assert [p["rank"] for p in people_to_track(info, min_share=0.0)] == [0, 1, 2, 3, 4]
    assert [p["rank"] for p in people_to_track(info, min_share=1.0)] == [0]
    # the largest by score may be followed in fewer frames than the next: the share is of its frames
    assert [p["rank"] for p in people_to_track(_info(10, 40, 2))] == [0, 1]
    with pytest.raises(DataError, match="no people"):
        people_to_track({"person": {"people": []}})
    with pytest.raises(DataError, match="no people"):
        people_to_track({})
    with pytest.raises(InputError, match="0..1"):
        people_to_track(info, min_share=1.5)


def test_a_single_run_asked_for_everyone_says_where_that_is():
    with pytest.raises(InputError, match="track_people"):
        parse_person("all")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 4-frame 160x120 walk and an init.json for it."""
    d = tmp_path_factory.mktemp("people")
    synthesize("builtin:walk", d / "walk", fps=30, frames=4, size="160x120", seed=1, azimuth=60.0, flow=False)
    (d / "init.json").write_text(json.dumps(noisy_init(load_sequence(d / "walk").gt, frame=0, seed=1)))
    return d


class FakeDetections:
    """Stands in for flowmocap.track inside track_people: tracks the synthetic clip for real
    (with its known init, masks and the quick settings) whatever person is asked, and writes
    the detection pass's people list as the detector would, three people with 40, 20 and 5
    frames; fails person ``fail`` once."""

    def __init__(self, clip, fail=None):
        self.clip, self.fail, self.asked = clip, fail, []

    def __call__(self, src, out, person="largest", resume=False, progress=False, log=None, **kwargs):
        self.asked.append(person)
        self.heights = getattr(self, "heights", []) + [kwargs.get("height")]
        assert kwargs.get("masks") in (None, "auto") and kwargs.get("init") in (None, "auto")
        search = Path(kwargs["search_dir"])  # every person's run is given the same search folder
        assert search == (Path(out).parent / PEOPLE_SEARCH).resolve()
        search.mkdir(exist_ok=True)  # as the detector's search would be stored there
        (search / "find-000000-000004.npz").touch()
        if person == self.fail:
            self.fail = None
            raise DataError(f"person {person} could not be tracked (a test's failure)")
        res = flowmocap.track(self.clip / "walk", out, init=self.clip / "init.json", config=QUICK, joints3d="off",
                              resume=resume, progress=False, log=None, force=kwargs.get("force", False))
        Path(out, "detections").mkdir(parents=True, exist_ok=True)  # after: the run clears a foreign detections/
        Path(out, "detections", "detections.json").write_text(json.dumps(_info(40, 20, 5)))
        return res


def test_every_person_gets_a_result_folder_and_a_failure_is_retried_on_the_next_run(clip, tmp_path, monkeypatch):
    fake = FakeDetections(clip, fail=1)
    monkeypatch.setattr(batch, "track", fake)
    out = tmp_path / "people"
    items = track_people(clip / "walk", out, log=None, progress=False)
    assert fake.asked == [0, 1]  # the largest, then rank 1; rank 2 (5 of 40 frames) is left out
    assert [(it.name, it.person, it.status) for it in items] == [("person0", 0, "tracked"), ("person1", 1, "failed")]
    assert "a test's failure" in items[1].error
    assert flowmocap.load_result(out / "person0").run["status"] == "finished"
    manifest = json.loads((out / PEOPLE_MANIFEST).read_text())
    assert manifest["input"] == str((clip / "walk").resolve()) and manifest["min_share"] == 0.25
    people = manifest["people"]
    assert list(people) == ["person0", "person1", "person2"]
    assert [people[n]["tracked"] for n in people] == [True, True, False]
    assert people["person0"]["status"] == "tracked" and people["person1"]["status"] == "failed"
    assert people["person2"]["detections"] == 5 and "status" not in people["person2"]
    assert (out / PEOPLE_SEARCH).is_dir()  # someone is left to track: the search is kept for them

    # run again: the finished largest person is skipped, the failed one tracked
    items = track_people(clip / "walk", out, log=None, progress=False)
    assert fake.asked == [0, 1, 1]
    assert [(it.name, it.status) for it in items] == [("person0", "skipped"), ("person1", "tracked")]
    assert not (out / PEOPLE_SEARCH).exists()  # everyone tracked: no longer needed
    np.testing.assert_array_equal(flowmocap.load_result(out / "person0").poses,
                                  flowmocap.load_result(out / "person1").poses)  # the fake tracks one clip
    # and again: nothing to do
    items = track_people(clip / "walk", out, log=None, progress=False)
    assert fake.asked == [0, 1, 1] and [it.status for it in items] == ["skipped", "skipped"]
    assert "2 people: 0 tracked" in batch.summary_table(items, out, noun="people")
    # another input into the same folder is refused, the results kept
    with pytest.raises(InputError, match="people of another input"):
        track_people(clip / "init.json", out, log=None, progress=False)
    assert flowmocap.load_result(out / "person1").run["status"] == "finished"


def test_a_first_run_that_finds_nobody_ends_there(clip, tmp_path, monkeypatch):
    def nobody(src, out, person="largest", **kwargs):
        Path(out, "detections").mkdir(parents=True, exist_ok=True)
        Path(out, "detections", "detections.json").write_text(json.dumps({"person": {"people": []}}))
        raise flowmocap.NoPersonError("no person found in any of the 4 frames")

    monkeypatch.setattr(batch, "track", nobody)
    items = track_people(clip / "walk", tmp_path / "out", log=None, progress=False)
    assert [(it.name, it.status) for it in items] == [("person0", "failed")]
    assert "no person found" in items[0].error


def test_bad_arguments_are_refused_before_anything_runs(clip, tmp_path):
    with pytest.raises(InputError, match="automatic masks"):
        track_people(clip / "walk", tmp_path / "a", masks=clip / "walk" / "masks", log=None)
    with pytest.raises(InputError, match="automatic init"):
        track_people(clip / "walk", tmp_path / "a", init=clip / "init.json", log=None)
    with pytest.raises(InputError, match="person"):
        track_people(clip / "walk", tmp_path / "a", person=1, log=None)
    with pytest.raises(InputError, match="0..1"):
        track_people(clip / "walk", tmp_path / "a", min_share=-0.1, log=None)
    # one input's search is shared by its people, never by several inputs
    for run in (track_people, batch.track_many):
        with pytest.raises(InputError, match="search_dir"):
            run(clip / "walk" if run is track_people else [clip / "walk"], tmp_path / "a", search_dir=tmp_path / "s",
                log=None)
    single = tmp_path / "single"
    flowmocap.track(clip / "walk", single, init=clip / "init.json", config=QUICK, joints3d="off", log=None,
                    progress=False)
    with pytest.raises(InputError, match="result folder of a single run"):
        track_people(clip / "walk", single, log=None)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / batch.MANIFEST).write_text("{}")
    with pytest.raises(InputError, match="batch of inputs"):
        track_people(clip / "walk", tmp_path / "b", log=None)
    assert not (tmp_path / "a").exists()


def test_several_inputs_each_get_a_folder_of_people_and_a_missing_one_stops_nothing(clip, tmp_path, monkeypatch):
    import shutil

    from flowmocap.batch import MANIFEST, track_people_many

    fake = FakeDetections(clip)
    monkeypatch.setattr(batch, "track", fake)
    shutil.copytree(clip / "walk", tmp_path / "dance")
    out = tmp_path / "out"
    items = track_people_many([clip / "walk", tmp_path / "missing.mp4", tmp_path / "dance"], out, log=None,
                              progress=False)
    assert [(it.name, it.status) for it in items] == [("walk/person0", "tracked"), ("walk/person1", "tracked"),
                                                      ("missing/person0", "failed"), ("dance/person0", "tracked"),
                                                      ("dance/person1", "tracked")]
    assert "does not exist" in items[2].error
    assert fake.asked == [0, 1, 0, 1]
    manifest = json.loads((out / MANIFEST).read_text())["results"]
    assert manifest["walk"]["status"] == "finished" and manifest["walk"]["people"] == 2
    assert manifest["missing"]["status"] == "failed"
    for name in ("walk", "dance"):
        assert json.loads((out / name / PEOPLE_MANIFEST).read_text())["people"]["person1"]["status"] == "tracked"
    # again: everyone finished is skipped
    items = track_people_many([clip / "walk", tmp_path / "dance"], out, log=None, progress=False)
    assert fake.asked == [0, 1, 0, 1] and {it.status for it in items} == {"skipped"}
    # the command line takes several inputs with --person all
    assert main(["track", str(clip / "walk"), str(tmp_path / "dance"), "--out", str(out), "--person", "all",
                 "--quiet"]) == 0


_CAM01 = SHARED_DATA / "video" / "pose2sim-multi" / "videos" / "cam01.mp4"


@pytest.mark.skipif(not _CAM01.exists(), reason="the Pose2Sim recording (../shared/data/video/pose2sim-multi) is "
                    "not here; it holds the two people this test tracks")
def test_both_people_of_the_real_recording_are_tracked(tmp_path, capsys, monkeypatch):
    """cam01 of the two-person recording, its first 4 frames at a third of their size: two
    result folders, on two different people (their fitted 2D joints lie apart by more than
    a body's width), each where its own detections put it, the second the same as tracked
    alone with ``--person 1``. The detector searches the frames for everyone once: the
    second person's run only follows them, and the search is removed at the end."""
    import av
    import cv2

    from flowmocap.vision import auto

    passes = []
    run_process = auto._run_detector_process

    def counted(task, folder, a, b):
        passes.append((Path(task["path"]).parent.name, task["kind"]))
        return run_process(task, folder, a, b)

    monkeypatch.setattr(auto, "_run_detector_process", counted)

    frames = tmp_path / "frames"
    frames.mkdir()
    with av.open(str(_CAM01)) as video:
        for i, f in enumerate(video.decode(video=0)):
            if i == 4:
                break
            img = f.to_ndarray(format="bgr24")
            cv2.imwrite(str(frames / f"{i:06d}.png"),
                        cv2.resize(img, (img.shape[1] // 3, img.shape[0] // 3), interpolation=cv2.INTER_AREA))
    (tmp_path / "quick.json").write_text(json.dumps(QUICK))
    out = tmp_path / "out"
    assert main(["track", str(frames), "--out", str(out), "--person", "all", "--config", str(tmp_path / "quick.json"),
                 "--quiet"]) == 0
    assert "2 people: 2 tracked" in capsys.readouterr().out
    # one search, in the shared folder; each person followed in their own run's folder
    assert passes == [(PEOPLE_SEARCH, "find"), ("chunks", "follow"), ("chunks", "follow")], passes
    assert not (out / PEOPLE_SEARCH).exists()
    people = json.loads((out / PEOPLE_MANIFEST).read_text())["people"]
    assert [people[n]["tracked"] for n in ("person0", "person1")] == [True, True]
    centres = []
    for name in ("person0", "person1"):
        res = flowmocap.load_result(out / name)
        assert res.run["status"] == "finished" and len(res) == 4
        centre = res.joints2d.mean(axis=(0, 1))
        box = people[name]["first_box"]
        assert box[0] <= centre[0] <= box[2] and box[1] <= centre[1] <= box[3], (name, centre, box)
        centres.append(centre)
    assert np.linalg.norm(centres[0] - centres[1]) > 80.0
    # the second person's result is the one `--person 1` gives alone, to the last bit
    alone = tmp_path / "alone"
    assert main(["track", str(frames), "--out", str(alone), "--person", "1", "--config", str(tmp_path / "quick.json"),
                 "--quiet"]) == 0
    for k in ("poses", "trans", "betas", "joints3d", "joints2d"):
        np.testing.assert_array_equal(getattr(flowmocap.load_result(alone), k),
                                      getattr(flowmocap.load_result(out / "person1"), k), err_msg=k)


# ------------------------------------------------------------------ drawing several people


def _square(z, x0, size=1.0):
    """A square facing the camera at depth ``z`` metres, left edge at ``x0``: 4 vertices, 2 triangles."""
    v = np.array([[x0, -size / 2, z], [x0 + size, -size / 2, z], [x0 + size, size / 2, z], [x0, size / 2, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_overlay_bodies_draws_the_nearer_body_where_two_overlap():
    from flowmocap.geometry.camera import PinholeCamera
    from flowmocap.viz.overlay import overlay_bodies, overlay_body

    cam = PinholeCamera(fx=100.0, fy=100.0, cx=50.0, cy=40.0, width=100, height=80)
    img = np.full((80, 100, 3), 40, np.uint8)
    near, far = _square(2.0, -0.6), _square(4.0, -0.2, size=2.0)  # near: x -0.6..0.4 at 2 m; far: -0.2..1.8 at 4 m
    red, green = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    out = overlay_bodies(img, [far, near], cam, alpha=1.0, colours=[green, red])
    # pixel columns: near spans x = 50 + 100 * (-0.6..0.4) / 2 = 20..70; far 50 + 100 * (-0.2..1.8) / 4 = 45..95
    both, far_only, none = out[40, 60], out[40, 85], out[40, 5]
    assert both[0] > 3 * both[1]  # the near (red) square hides the far one, drawn first
    assert far_only[1] > 3 * far_only[0]
    np.testing.assert_array_equal(none, img[40, 5])
    # the order of the list does not matter, only depth
    np.testing.assert_array_equal(out, overlay_bodies(img, [near, far], cam, alpha=1.0, colours=[red, green]))
    # one body: exactly overlay_body's picture
    np.testing.assert_array_equal(overlay_bodies(img, [near], cam, alpha=0.6, colours=[red]),
                                  overlay_body(img, near[0], near[1], cam, alpha=0.6, colour=red))
    # a body behind the camera is left out; none left: the image as it was
    behind = _square(-2.0, 0.0)
    np.testing.assert_array_equal(overlay_bodies(img, [behind], cam), img)
    np.testing.assert_array_equal(overlay_bodies(img, [behind, near], cam, colours=[green, red]),
                                  overlay_bodies(img, [near], cam, colours=[red]))
    with pytest.raises(InputError, match="one colour per body"):
        overlay_bodies(img, [near, far], cam, colours=[red])
    with pytest.raises(InputError, match="RGB for this camera"):
        overlay_bodies(img[:10], [near], cam)


def test_render_draws_every_person_of_a_people_folder(clip, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(batch, "track", FakeDetections(clip))
    out = tmp_path / "people"
    track_people(clip / "walk", out, log=None, progress=False)
    assert main(["render", str(out), "--quiet"]) == 0
    assert "person0, person1; frames 0-3" in capsys.readouterr().out
    import av

    with av.open(str(out / "render" / "overlay.mp4")) as video:
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(video=0)]
    assert len(frames) == 4 and frames[0].shape == (120, 160, 3)
    assert main(["render", str(out), "--figure1", "--quiet"]) != 0
    assert "render a person's folder" in capsys.readouterr().err
    # export writes everyone (in one frame: tests/test_view.py); what takes one result says which to give
    assert main(["export", str(out), "--format", "bvh", "--quiet"]) == 0
    assert (out / "export" / "person0.bvh").is_file() and (out / "export" / "person1.bvh").is_file()
    with pytest.raises(DataError, match="give one of its person folders"):
        flowmocap.load_result(out)


def test_someone_back_in_view_far_from_where_they_left_is_a_second_track():
    """What the docs say of --person all: a person back after a gap is the same track when
    they come back near where they left, a second one when more than two body heights away."""
    from flowmocap.vision.auto import find_people, split_tracks

    from test_person_choice import ColourDetector, People

    for x_back, tracks in ((30, 1), (400, 2)):
        seen = {i: (10, 20, 24, 60) for i in range(5)}  # 40 px tall; gone in frames 5-14
        seen.update({i: (x_back, 20, x_back + 14, 60) for i in range(15, 20)})
        scene = People([seen], n=20, size=(512, 128))
        found = find_people(scene, ColourDetector(scene), ColourDetector(scene), progress=False)
        assert len(split_tracks(found)) == tracks, x_back


def test_track_with_export_writes_everyone_in_one_frame_and_says_how_they_share_a_floor(clip, tmp_path, monkeypatch,
                                                                                          capsys):
    fake = FakeDetections(clip)
    monkeypatch.setattr(batch, "track", fake)
    out = tmp_path / "people"
    assert main(["track", str(clip / "walk"), "--out", str(out), "--person", "all", "--export", "json",
                 "--height", "1.8", "--quiet"]) == 0
    assert fake.heights == [1.8, None]  # a stated height is the largest person's alone
    said = capsys.readouterr().out
    assert (out / "export" / "person0.json").exists() and (out / "export" / "person1.json").exists()
    floor = json.loads((out / "export" / "floor.json").read_text())
    assert floor["shared"] and set(floor["people"]) == {"person0", "person1"}
    # one line per person on how they stand on one floor (4 frames: nobody's foot stands, no floor)
    assert "person0: kept the size of its own fit" in said and "person1: kept the size of its own fit" in said
    assert floor["people"]["person1"]["scale"] is None and "nobody's floor" in floor["people"]["person1"]["why"]


def test_a_people_folder_whose_first_run_failed_at_once_takes_the_corrected_input(clip, tmp_path, monkeypatch):
    """A mistyped or broken input for --person all left people.json alone in the folder, and
    every other input was refused there, even with --force; a folder holding another input's
    tracked people is still refused, and says how to reuse it."""
    fake = FakeDetections(clip)
    monkeypatch.setattr(batch, "track", fake)
    out = tmp_path / "people"
    items = track_people(tmp_path / "typo.mp4", out, log=None, progress=False)
    assert [it.status for it in items] == ["failed"] and (out / PEOPLE_MANIFEST).exists()
    items = track_people(clip / "walk", out, log=None, progress=False)
    assert [it.status for it in items] == ["tracked", "tracked"]
    manifest = json.loads((out / PEOPLE_MANIFEST).read_text())
    assert manifest["input"] == str((clip / "walk").resolve()) and "typo" not in json.dumps(manifest)
    with pytest.raises(InputError, match=r"holds the people of another input .*person0, person1.*delete the folder"):
        track_people(tmp_path / "typo.mp4", out, log=None, progress=False)
    with pytest.raises(InputError, match=r"holds the people of `track --person all` .*pass --person all"):
        flowmocap.track(clip / "walk", out, force=True, log=None, progress=False)
