"""Choosing the person to track (``person="largest" | N | "x,y"``): parsing, choosing among
candidate tracks, re-detecting the chosen one with the others blanked, and the plumbing
through ``flowmocap.track`` and ``flowmocap track --person``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flowmocap.errors import InputError
from flowmocap.vision.auto import detect_sequence
from flowmocap.vision.detect import Detection
from flowmocap.vision.person import box_distance, choose_person, describe_person, parse_person

from test_detect import stick_keypoints


@pytest.mark.parametrize("value, expected", [
    ("largest", ("largest", None)), (None, ("largest", None)), (" Largest ", ("largest", None)),
    (0, ("index", 0)), ("2", ("index", 2)), (np.int64(3), ("index", 3)),
    ("540,900", ("point", (540.0, 900.0))), (" 12.5 , 7 ", ("point", (12.5, 7.0))), ((3, 4), ("point", (3.0, 4.0))),
])
def test_parse_person(value, expected):
    assert parse_person(value) == expected


@pytest.mark.parametrize("value, match", [
    (-1, ">= 0"), ("-2", ">= 0"), ("tallest", "'largest', a rank"), ("1,2,3", "two numbers"), ("a,b", "two numbers"),
    (True, "'largest'"), (1.5, "'largest'"), ("nan,3", "finite"),
])
def test_bad_person_values_say_what_to_give(value, match):
    with pytest.raises(InputError, match=match):
        parse_person(value)


def test_describe_person_round_trips():
    for v in ("largest", "3", "540,900", "12.5,7"):
        assert describe_person(parse_person(v)) == v


def test_choose_person():
    boxes = [(0, 0, 10, 40), (50, 0, 70, 30), (5, 10, 25, 50)]
    scores = [30.0, 50.0, 10.0]
    assert choose_person(boxes, scores, ("largest", None)) == 1
    assert [choose_person(boxes, scores, ("index", n)) for n in range(3)] == [1, 0, 2]
    assert choose_person(boxes, scores, ("point", (60, 10))) == 1  # inside
    assert choose_person(boxes, scores, ("point", (100, 10))) == 1  # outside all: the nearest box
    assert choose_person(boxes, scores, ("point", (6, 15))) == 0  # inside two: the nearer centre, (5, 20)
    assert choose_person(boxes, scores, ("point", (9, 35))) == 2  # ... (15, 30)
    assert choose_person(boxes, [1.0, 1.0, 1.0], ("largest", None)) == 0  # ties: the first, as before
    with pytest.raises(InputError, match="only 3 people were found"):
        choose_person(boxes, scores, ("index", 3))
    assert box_distance((0, 0, 10, 10), (13, 14)) == pytest.approx(5.0)


# ------------------------------------------------------------------ detection with a chosen person


class People:
    """Frames with coloured rectangles for people; ``boxes[k][i]`` person k's box in frame i."""

    COLOURS = [(200, 30, 30), (30, 200, 30), (30, 30, 200)]

    def __init__(self, boxes, n=12, size=(128, 128)):
        self.boxes, self.n, self.size, self.root = boxes, n, size, "people"

    def __len__(self):
        return self.n

    def frame(self, i):
        img = np.zeros((self.size[1], self.size[0], 3), np.uint8)
        for k, b in enumerate(self.boxes):
            if i in b:
                x0, y0, x1, y1 = b[i]
                img[y0:y1, x0:x1] = self.COLOURS[k]
        return img


class ColourDetector:
    """Finds a person whose colour shows at their box centre; tracks the one it found
    first while visible (like MediaPipe's tracking mode); misses the frames in ``miss``."""

    name = "colour"

    def __init__(self, scene, miss=()):
        self.scene, self.miss = scene, set(miss)
        self.reset()

    def reset(self):
        self.locked, self.i = None, 0

    def detect(self, img):
        i = self.i
        self.i += 1
        visible = []
        for k, b in enumerate(self.scene.boxes):
            if i in b:
                x0, y0, x1, y1 = b[i]
                if tuple(img[(y0 + y1) // 2, (x0 + x1) // 2]) == People.COLOURS[k]:
                    visible.append(k)
        if i in self.miss or not visible:
            return None
        k = self.locked if self.locked in visible else visible[0]
        self.locked = k
        x0, y0, x1, y1 = self.scene.boxes[k][i]
        H, W = img.shape[:2]
        mask = np.zeros((H, W), bool)
        mask[y0:y1, x0:x1] = True
        return Detection(stick_keypoints(x0, y0, x1, y1), np.full(15, 0.9), mask)


def two_people():
    big = {i: (10 + 2 * i, 20, 50 + 2 * i, 126) for i in range(12)}
    small = {i: (90, 10, 110, 60) for i in range(12)}
    return People([big, small])


def test_largest_and_rank_zero_are_todays_behaviour(tmp_path):
    scene = two_people()
    a = detect_sequence(scene, tmp_path / "a", ColourDetector(scene), searcher=ColourDetector(scene), progress=False)
    b = detect_sequence(scene, tmp_path / "b", ColourDetector(scene), searcher=ColourDetector(scene), progress=False,
                        person=0)
    assert a.info["detector"] == b.info["detector"] == "colour+search:colour+follow"
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    assert a.found.all() and a.keypoints[3, 0, 1] > 60  # the big person's hip
    assert a.info["person"]["choice"] == "largest" and a.info["person"]["rank"] == 0
    assert len(a.info["person"]["people"]) == 2 and a.info["ignored_people"][0]["frames"] == [0, 11]


@pytest.mark.parametrize("person", [1, "1", "100,30", (95, 50)])
def test_the_chosen_person_is_followed_in_every_frame(tmp_path, person):
    """The searcher missed the small person in frames 4-6; re-detecting with the big one
    blanked finds them there too."""
    scene = two_people()
    track = detect_sequence(scene, tmp_path, ColourDetector(scene), searcher=ColourDetector(scene, miss={4, 5, 6}),
                            progress=False, person=person)
    assert track.found.all()
    np.testing.assert_allclose(track.keypoints[5], stick_keypoints(90, 10, 110, 60))
    assert "+person:" in track.info["detector"]
    assert track.info["person"]["rank"] == 1 and "not the one chosen" in track.info["ignored_people"][0]["why"]
    # a stored result for another person is not reused
    other = detect_sequence(scene, tmp_path, ColourDetector(scene), searcher=ColourDetector(scene), progress=False)
    assert other.keypoints[5, 0, 1] > 60


class FragmentDetector(ColourDetector):
    """A :class:`ColourDetector` that sees only the top ``rows`` pixels of the people it
    finds in the frames ``fragment`` (as a searcher does whose blanked box hides the
    chosen person's legs)."""

    def __init__(self, scene, fragment=(), rows=12):
        super().__init__(scene)
        self.fragment, self.rows = set(fragment), rows

    def detect(self, img):
        i = self.i
        det = super().detect(img)
        if det is None or i not in self.fragment:
            return det
        ys, xs = np.nonzero(det.mask)
        x0, y0, x1 = xs.min(), ys.min(), xs.max() + 1
        mask = np.zeros_like(det.mask)
        mask[y0:y0 + self.rows, x0:x1] = True
        return Detection(stick_keypoints(x0, y0, x1, y0 + self.rows), det.confidence, mask)


def test_a_fragment_from_the_searcher_does_not_refuse_the_whole_person(tmp_path):
    """Where the searcher's candidate of the chosen person is a fragment (a quarter of
    their height: more than halved), the re-detection of the whole person continues the
    pass's last detection and is kept, not the fragment."""
    scene = two_people()
    track = detect_sequence(scene, tmp_path, ColourDetector(scene), searcher=FragmentDetector(scene, {4, 5, 6, 7}),
                            progress=False, person=1)
    assert track.found.all()
    for i in (4, 5, 6, 7):
        np.testing.assert_allclose(track.keypoints[i], stick_keypoints(90, 10, 110, 60))
    assert track.info["person"]["rank"] == 1


class SlidingDetector(ColourDetector):
    """A :class:`ColourDetector` that, from the second pass on (the follow pass), takes
    person 1 over person 0 from frame ``slide`` wherever person 1 shows, as MediaPipe's
    tracking slid from the man onto the woman behind him on the real3d recording's cam03."""

    def __init__(self, scene, slide=6):
        self.passes, self.slide = 0, slide
        super().__init__(scene)

    def reset(self):
        super().reset()
        self.passes += 1

    def detect(self, img):
        if self.passes > 2 and self.i >= self.slide:  # made (1), reset by the search (2), by the follow pass (3)
            self.locked = 1
        return super().detect(img)


@pytest.mark.parametrize("person", ["30,70", "largest"])
def test_a_person_the_search_lost_stays_blanked_for_a_while(tmp_path, person):
    """The searcher stops finding the small person from frame 6 (merged with the big one,
    who stands beside them); the follow pass still blanks them at their last detection
    for LOST_HOLD frames, so its detector, which would slide onto them, keeps the big one.
    The largest person, the default, is followed too, since someone else shares frames."""
    big = {i: (10 + 2 * i, 20, 50 + 2 * i, 126) for i in range(12)}
    small = {i: (55, 40, 85, 100) for i in range(12)}
    scene = People([big, small])
    miss = set(range(6, 12))
    track = detect_sequence(scene, tmp_path, SlidingDetector(scene), searcher=ColourDetector(scene, miss=miss),
                            progress=False, person=person)
    assert track.info["person"]["rank"] == 0 and track.found.all()
    for i in range(12):
        x0, y0, x1, y1 = big[i]
        np.testing.assert_allclose(track.keypoints[i], stick_keypoints(x0, y0, x1, y1))


@pytest.mark.parametrize("stray_frames", [0, 2])
def test_a_person_alone_is_not_detected_again(tmp_path, stray_frames):
    """With nobody else in their frames, or someone in fewer than a quarter of them (a
    stray detection), the largest person's detections are the search's: the detector runs
    over the video once (made, then reset by the search only)."""
    big = {i: (10 + 2 * i, 20, 50 + 2 * i, 126) for i in range(12)}
    stray = {i: (90, 10, 110, 60) for i in range(stray_frames)}
    scene = People([big, stray])
    det = SlidingDetector(scene)
    track = detect_sequence(scene, tmp_path, det, searcher=ColourDetector(scene), progress=False)
    assert track.found.all() and det.passes == 2
    assert len(track.info["person"]["people"]) == (2 if stray_frames else 1)
    assert "re-detected" not in track.info["person"]["note"]


def test_a_rank_beyond_the_people_found(tmp_path):
    scene = two_people()
    with pytest.raises(InputError, match="only 2 people were found"):
        detect_sequence(scene, tmp_path, ColourDetector(scene), searcher=ColourDetector(scene), progress=False,
                        person=2)


def test_track_and_cli_take_the_person(tmp_path):
    from flowmocap.cli import build_parser
    from flowmocap.pipeline import track

    with pytest.raises(InputError, match="'largest', a rank"):
        track(tmp_path, tmp_path / "out", person="tallest")
    args = build_parser().parse_args(["track", "v.mp4", "--out", "o", "--person", "540,900"])
    assert args.person == "540,900"
    assert build_parser().parse_args(["track", "v.mp4", "--out", "o"]).person == "largest"


@pytest.mark.parametrize("point", ["9999,9999", "-1,5", "10,-0.5", "33,10"])
def test_a_person_pixel_outside_the_frames_is_refused_with_their_size(tmp_path, point):
    """person="x,y" outside the frames (negative, or beyond their width or height) is an
    InputError saying the frames' size, before the detector runs (it used to track the
    nearest person silently)."""
    import cv2

    from flowmocap.pipeline import track

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"{i:06d}.png"), np.zeros((24, 32, 3), np.uint8))
    with pytest.raises(InputError, match=rf"person={point} lies outside the 32x24 frames"):
        track(frames, tmp_path / "out", person=point, log=None, progress=False)


def test_a_person_pixel_is_in_the_frames_own_size_before_max_size(tmp_path):
    """The point is in the pixels of the frames before max_size (--max-size): a point
    inside them but outside the scaled frames passes the check (and meets the next one:
    own masks and init leave nobody to choose)."""
    import cv2

    from flowmocap.pipeline import track

    for sub in ("frames", "masks"):
        (tmp_path / sub).mkdir()
        for i in range(2):
            cv2.imwrite(str(tmp_path / sub / f"{i:06d}.png"), np.full((96, 160, 3), 255, np.uint8))
    with pytest.raises(InputError, match="chooses among the people the detector finds"):
        track(tmp_path / "frames", tmp_path / "out", masks=tmp_path / "masks", init={"joints2d": {}}, max_size=80,
              person="150,90", log=None, progress=False)
    with pytest.raises(InputError, match="outside the 160x96 frames"):
        track(tmp_path / "frames", tmp_path / "out", max_size=80, person="161,90", log=None, progress=False)


def test_the_searcher_finds_a_person_inside_the_box_of_the_one_found_first():
    """The searcher looks with the first person's body blanked, not their box: someone
    standing within that box (grown by 10 %) but off the body is still found."""
    from flowmocap.vision.auto import find_people

    first = {i: (10, 20, 50, 110) for i in range(6)}
    near = {i: (20, 110, 40, 126) for i in range(6)}  # centre (30, 118): inside the grown box's rows 11-118
    scene = People([first, near], n=6)
    got = find_people(scene, ColourDetector(scene), ColourDetector(scene), progress=False)
    assert all(len(g) == 2 for g in got)
    assert got[3][1].box[1] >= 100  # the second is the one below


def test_find_people_searches_beside_the_detector_as_one_after_the_other():
    """find_people runs the searchers of frame i on a thread while the detector looks at
    frame i + 1: each searcher must still see its images in frame order with the people
    found before it blanked, so the candidates equal a plain loop's (three people, two
    searchers, frames the detector misses)."""
    from flowmocap.vision.auto import _blank_people, _usable, find_people

    third = {i: (60, 70, 80, 120) for i in range(12) if i % 4 != 1}
    scene = People(two_people().boxes + [third])

    def serial():
        det, s1, s2 = ColourDetector(scene, miss=(5, 6)), ColourDetector(scene), ColourDetector(scene)
        out = []
        for i in range(len(scene)):
            img, got = scene.frame(i), []
            c = _usable(det.detect(img))
            if c is not None:
                got.append(c)
                for s in (s1, s2):
                    img = _blank_people(img, [got[-1]])
                    c = _usable(s.detect(img))
                    if c is None:
                        break
                    got.append(c)
            out.append(got)
        return out

    want = serial()
    got = find_people(scene, ColourDetector(scene, miss=(5, 6)), [ColourDetector(scene), ColourDetector(scene)],
                      progress=False)
    assert [len(g) for g in got] == [len(w) for w in want] and max(len(w) for w in want) == 3
    assert not got[5] and not got[6] and any(len(w) == 2 for w in want)
    for g, w in zip(got, want):
        for a, b in zip(g, w):
            assert a.box == b.box
            np.testing.assert_array_equal(a.keypoints, b.keypoints)


def test_the_other_peoples_pixels_are_stored_with_the_detections(tmp_path):
    """detect_sequence stores, per frame, where people nearer the camera than the kept one
    are seen (their bodies outside the kept person's mask; nearer: their feet lower in the
    image), and a rerun reads them back; someone further away, or a video of one person,
    stores none. Everyone else, nearer or further, is stored apart (``people``: not
    background, for the camera's motion)."""
    from flowmocap.vision.auto import load_detections, others_region

    scene = two_people()  # the big person's feet at row 126, the small one's at 60: the big one is nearer
    behind = detect_sequence(scene, tmp_path / "big", ColourDetector(scene), searcher=ColourDetector(scene),
                             progress=False)
    assert behind.info["frames_with_others"] == 0 and behind.others(3) is None
    # the small person behind hides nothing, but is not background either
    assert behind.info["frames_with_people"] == 12
    for i in (0, 7):
        people = behind.people(i)
        ys, xs = np.nonzero(people)
        x0, y0, x1, y1 = scene.boxes[1][i]  # the small person's box
        assert len(xs) > 100 and xs.min() >= x0 - 5 and xs.max() < x1 + 5 and ys.min() >= y0 - 5 and ys.max() < y1 + 5
        assert not (people & behind.mask(i)).any()
    np.testing.assert_array_equal(load_detections(tmp_path / "big").people(7), behind.people(7))
    # detections stored before the people were: none known (the camera's motion as before)
    info = tmp_path / "big" / "detections" / "detections.json"
    info.write_text(json.dumps({k: v for k, v in json.loads(info.read_text()).items() if k != "people_stored"}))
    assert load_detections(tmp_path / "big").people(7) is None
    track = detect_sequence(scene, tmp_path / "two", ColourDetector(scene), searcher=ColourDetector(scene),
                            progress=False, person=1)
    assert track.info["frames_with_others"] == 12
    for i in (0, 7):
        other = track.others(i)
        ys, xs = np.nonzero(other)
        x0, y0, x1, y1 = scene.boxes[0][i]  # the big person's box; their body, grown a little
        assert len(xs) > 500 and xs.min() >= x0 - 5 and xs.max() < x1 + 5 and ys.min() >= y0 - 5 and ys.max() < y1 + 5
        assert not (other & track.mask(i)).any()
        np.testing.assert_array_equal(track.people(i), other)  # the one other person is nearer
    again = load_detections(tmp_path / "two")
    np.testing.assert_array_equal(again.others(7), track.others(7))
    one = People([two_people().boxes[0]])
    alone = detect_sequence(one, tmp_path / "one", ColourDetector(one), searcher=ColourDetector(one), progress=False)
    assert alone.info["frames_with_others"] == 0 and all(alone.others(i) is None for i in range(12))
    assert alone.info["frames_with_people"] == 0 and all(alone.people(i) is None for i in range(12))
    # the kept person's own detection is not someone else
    own = two_people()
    det = ColourDetector(own).detect(own.frame(0))
    from flowmocap.vision.auto import _usable

    cand = _usable(det)
    assert not others_region([cand], det.mask).any()


def test_what_is_left_of_a_blanked_person_is_not_found_again():
    """A searcher that finds the first person again in what blanking left of them (a
    dress, hair) gives their own pose: that is not a second person."""
    from flowmocap.vision.auto import find_people

    class Echo(ColourDetector):
        """Sees the first person again wherever their colour still shows."""

        def detect(self, img):
            i = self.i
            self.i += 1
            x0, y0, x1, y1 = self.scene.boxes[0][i]
            if not (img[y0:y1, x0:x1] == People.COLOURS[0]).all(-1).any():
                return None
            mask = np.zeros(img.shape[:2], bool)
            mask[y0:y1, x0:x1] = True
            return Detection(stick_keypoints(x0, y0, x1, y1) + 1.0, np.full(15, 0.9), mask)

    scene = People([{i: (10, 20, 50, 126) for i in range(12)}])
    got = find_people(scene, ColourDetector(scene), Echo(scene), progress=False)
    assert all(len(g) == 1 for g in got)


# ------------------------------------------------------------------ a person seen again after a time out of sight


def _walker(frames, x0=10):
    """A person's boxes in ``frames``, walking right 1 px a frame."""
    return {i: (x0 + i, 20, x0 + 40 + i, 126) for i in frames}


@pytest.mark.parametrize("case", ["same", "other", "too_long", "fragment"])
def test_a_person_hidden_for_longer_than_a_gap_is_joined_again(tmp_path, case):
    """Someone out of sight for 20 frames (more than split_tracks' 15) comes back as a new
    track. The same clothes within LINK_MAX_S seconds: one person, tracked in both stretches;
    someone else, a longer time away, or a fragment of fewer than 10 detections: two."""
    before, after = range(0, 15), range(35, 50) if case != "fragment" else range(35, 43)
    if case == "other":  # green comes in where red left
        scene = People([_walker(before), _walker(after)], n=50, size=(128, 160))
    else:
        scene = People([{**_walker(before), **_walker(after)}], n=50, size=(128, 160))
    scene.meta = {"fps": 5.0 if case == "too_long" else 30.0}  # 20 frames: 4 s at 5 fps, above LINK_MAX_S
    track = detect_sequence(scene, tmp_path, ColourDetector(scene), searcher=ColourDetector(scene), progress=False)
    people = track.info["person"]["people"]
    if case == "same":
        assert track.found[list(before)].all() and track.found[list(after)].all() and not track.found[15:35].any()
        assert [p["frames"] for p in people] == [[0, 49]] and people[0]["detections"] == 30
        assert [lk["frames"] for lk in track.info["person"]["seen_again"]] == [[14, 35]]
        assert track.info["person"]["seen_again"][0]["distance"] < 0.01
        assert not track.info["ignored_people"]
    else:
        assert len(people) == 2 and not track.info["person"]["seen_again"]
        # only one stretch is tracked: the first (as large and long as the other, or longer)
        assert track.found[list(before)].all() and track.found.sum() == len(before)


def test_appearance_tells_clothes_apart():
    """The hue-saturation histograms of a person's upper and lower half: the same clothes
    moved elsewhere are 0 apart, another shirt over the same trousers about half, other
    clothes 1."""
    from flowmocap.vision.auto import Candidate, PackedMask, appearance, appearance_distance

    def person(top, bottom, x0=10):
        img = np.zeros((120, 100, 3), np.uint8)
        img[10:60, x0:x0 + 30], img[60:110, x0:x0 + 30] = top, bottom
        mask = np.zeros((120, 100), bool)
        mask[10:110, x0:x0 + 30] = True
        return img, Candidate((x0, 10, x0 + 30, 110), np.zeros((15, 2)), np.ones(15), PackedMask.pack(mask), None)

    red, blue, green = (200, 30, 30), (30, 30, 200), (30, 200, 30)
    a = appearance(*person(red, blue))
    assert appearance_distance(a, appearance(*person(red, blue, x0=50))) == pytest.approx(0.0, abs=1e-3)
    assert appearance_distance(a, appearance(*person(green, blue))) == pytest.approx(0.5, abs=0.01)
    assert appearance_distance(a, appearance(*person(green, red))) == pytest.approx(1.0, abs=0.01)
    img, cand = person(red, blue)
    tiny = np.zeros((120, 100), bool)
    tiny[10:14, 10:14] = True
    assert appearance(img, cand._replace(mask=PackedMask.pack(tiny))) is None  # too few pixels to say


DAVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "video" / "davis-dance-twirl"


@pytest.mark.skipif(not DAVIS.exists(), reason=f"shared data not found at {DAVIS} (real frames for MediaPipe)")
def test_the_dancer_is_joined_across_a_cut(tmp_path):
    """DAVIS dance-twirl with frames 20-44 grey (a cut of 25 frames): MediaPipe finds the
    dancer before and after, and the two stretches are one person by her clothes, so both are
    kept (before, only the longer one was)."""
    import imageio.v3 as iio

    from flowmocap.io.sequence import load_sequence

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(60):
        img = iio.imread(DAVIS / "JPEGImages" / f"{i:05d}.jpg")
        iio.imwrite(frames / f"{i:05d}.png", np.full_like(img, 110) if 20 <= i < 45 else img)
    track = detect_sequence(load_sequence(frames), tmp_path / "out", detector="unaugmented", progress=False)
    links = track.info["person"]["seen_again"]
    assert [lk["frames"] for lk in links] == [[19, 45]] and links[0]["distance"] < 0.45
    assert track.found[:20].sum() >= 18 and track.found[45:].sum() >= 13 and not track.found[20:45].any()
