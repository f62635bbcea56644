"""benchmarks/post_steps_cost.py: the run's events follow the motion when it is repeated."""

from pathlib import Path

from conftest import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "post_steps_cost.py"


def _load():
    return load_script(SCRIPT)


def test_a_repeated_run_repeats_its_events_at_each_copy_and_drops_the_post_steps_records():
    run = {"config": {"pose_smoothing_s": 0.3}, "lifter_refit": {"seconds": 3.0}, "stance_depth": {}, "pose_smoothing": {},
           "events": [{"frame": 4, "event": "re-initialised"}, {"event": "note without a frame"},
                      {"frame": 9, "event": "limb flipped in depth"}]}
    out = _load().repeated_run(run, frames=10, repeat=3)
    assert not {"lifter_refit", "stance_depth", "pose_smoothing"} & set(out)
    assert out["config"] == run["config"]
    assert [e.get("frame") for e in out["events"]] == [4, None, 9, 14, None, 19, 24, None, 29]
    assert run["events"][0]["frame"] == 4  # the run itself is not changed
