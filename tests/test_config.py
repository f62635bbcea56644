"""TrackerConfig: profiles and the order of layers, removed settings, checks on construction."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from flowmocap.errors import InputError
from flowmocap.fit.config import (
    PROFILES,
    REMOVED_SETTINGS,
    TrackerConfig,
    check_setting_names,
    profile_names,
)


def test_profiles():
    assert profile_names() == ["synthetic", "video"]
    assert PROFILES["synthetic"] == {}
    assert TrackerConfig.load() == TrackerConfig() == TrackerConfig.load(profile=None)
    video = TrackerConfig.load(profile="video")
    assert {k: v for k, v in video.to_dict().items() if v != TrackerConfig().to_dict()[k]} == PROFILES["video"]
    # the documented differences, no more
    assert set(PROFILES["video"]) == {"silhouette_model", "silhouette_weight", "silhouette_a", "reinit_min_iou",
                                      "reinit_patience", "init_keypoint_weight", "reinit_max_joint3d_error",
                                      "lifter_refit_shape_share", "lifter_refit_shape_girth",
                                      "lifter_refit_hidden_share", "reinit_3d_insist"}
    with pytest.raises(InputError, match=r"unknown settings profile 'real'.*synthetic, video"):
        TrackerConfig.load(profile="real")


def test_profiles_are_documented():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "settings.md").read_text()
    for f in dataclasses.fields(TrackerConfig):
        assert f"`{f.name}`" in doc, f.name
    for name in PROFILES:
        assert f"`{name}`" in doc, name
    for name in REMOVED_SETTINGS:
        assert f"`{name}`" in doc, name


def test_layer_order(tmp_path):
    """defaults < profile < base < file < keyword overrides (None ignored)."""
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps({"silhouette_weight": 7.0, "levels": 4, "flow_method": "dis"}))
    base = {"silhouette_weight": 9.0, "silhouette_a": 0.5, "iterations": 11}
    cfg = TrackerConfig.load(p, profile="video", base=base, levels=2, stages=[[1], [0, 1]], flow_method=None)
    assert cfg.silhouette_model == "mesh" and cfg.reinit_patience == 1  # the profile
    assert cfg.silhouette_a == 0.5 and cfg.iterations == 11             # base over the profile
    assert cfg.silhouette_weight == 7.0 and cfg.flow_method == "dis"    # the file over base
    assert cfg.levels == 2 and cfg.stages == ((1,), (0, 1))            # overrides over the file
    assert TrackerConfig.load(None, profile="video", base=base).silhouette_weight == 9.0
    assert TrackerConfig.load(None, profile="video").silhouette_weight == 20.0
    # a dict in place of a file
    assert TrackerConfig.load({"levels": 4}, levels=None).levels == 4
    assert TrackerConfig.load(None, flow_method=None).flow_method == "dis-fine"
    assert TrackerConfig.load(str(p)).levels == 4
    # the profile itself is not changed by loading
    assert PROFILES["video"]["silhouette_weight"] == 20.0


def test_bad_files(tmp_path):
    p = tmp_path / "cfg.json"
    with pytest.raises(InputError, match="does not exist"):
        TrackerConfig.load(p)
    p.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        TrackerConfig.load(p)
    p.write_text("[1, 2]")
    with pytest.raises(InputError, match="JSON object"):
        TrackerConfig.load(p)
    p.write_text(json.dumps({"flow_wieght": 2.0}))
    with pytest.raises(InputError, match=r"unknown config settings \['flow_wieght'\]"):
        TrackerConfig.load(p)
    with pytest.raises(InputError, match="unknown config settings"):
        TrackerConfig.load(None, base={"nope": 1})
    with pytest.raises(InputError, match="unknown config settings"):
        TrackerConfig.load(nope=1)
    with pytest.raises(InputError, match="JSON file's path or a dict"):
        TrackerConfig.load(3)


@pytest.mark.parametrize("name", sorted(REMOVED_SETTINGS))
def test_removed_settings_say_so(tmp_path, name):
    value = {"occlusion_temporal_gain": 0.0, "flow_occlusion_check": False, "temporal_reference": "prediction",
             "optimizer": "lbfgs"}[name]
    p = tmp_path / "cfg.json"
    p.write_text(json.dumps({name: value}))
    now = {"occlusion_temporal_gain": "every joint alike", "flow_occlusion_check": "without a forward-backward",
           "temporal_reference": "Kalman prediction", "optimizer": "L-BFGS"}[name]
    for call in (lambda: TrackerConfig.load(p), lambda: TrackerConfig.load(None, **{name: value}),
                 lambda: TrackerConfig.load(None, base={name: value}), lambda: TrackerConfig.from_dict({name: value}),
                 lambda: check_setting_names({name: value})):
        with pytest.raises(InputError, match=rf"'{name}' was removed: .*{re.escape(now)}") as e:
            call()
        assert "unknown" not in str(e.value)
    assert name not in TrackerConfig().to_dict()


@pytest.mark.parametrize("kwargs, pattern", [
    ({"iterations": -3}, r"'iterations' must be an integer >= 1; got -3"),
    ({"iterations": 0}, r"'iterations' must be an integer >= 1"),
    ({"iterations": 20.0}, r"'iterations' must be an integer >= 1; got 20.0"),     # no floats for ints
    ({"levels": True}, r"'levels' must be an integer"),                            # bool where int expected
    ({"torch_threads": "2"}, r"'torch_threads' must be an integer"),
    ({"flow_weight": -1.0}, r"'flow_weight' must be a number >= 0; got -1.0"),     # negative weight
    ({"anchor_weight": -0.5}, r"'anchor_weight' must be a number >= 0"),
    ({"init_rough_pose_weight": -1}, r"'init_rough_pose_weight' must be a number >= 0"),
    ({"keypoint_sigma": 0.0}, r"'keypoint_sigma' must be a number > 0"),           # sigmas > 0
    ({"kalman_rot_accel_noise": 0.0}, r"'kalman_rot_accel_noise' must be a number > 0"),
    ({"silhouette_weight": float("nan")}, r"'silhouette_weight' must be a finite number"),
    ({"temporal_weight": float("inf")}, r"'temporal_weight' must be a finite number"),
    ({"flow_weight": True}, r"'flow_weight' must be a finite number"),             # bool where float expected
    ({"flow_weight": "1.0"}, r"'flow_weight' must be a finite number"),
    ({"silhouette_a": 1.5}, r"'silhouette_a' must be a number in \[0, 1\]"),
    ({"reinit_min_iou": -0.1}, r"'reinit_min_iou' must be a number in \[0, 1\]"),
    ({"reinit_max_joint_error": 0.0}, r"'reinit_max_joint_error' must be a number > 0"),
    ({"reinit_patience": 0}, r"'reinit_patience' must be an integer >= 1"),
    ({"capsule_grid_step": 0}, r"'capsule_grid_step' must be an integer >= 1"),
    ({"kalman": 1}, r"'kalman' must be true or false; got 1"),                     # int where bool expected
    ({"flow_in_mask": "yes"}, r"'flow_in_mask' must be true or false"),
    ({"silhouette_model": "voxels"}, r"'silhouette_model' must be one of 'capsules', 'mesh'; got 'voxels'"),
    ({"silhouette_model": 1}, r"'silhouette_model' must be one of"),
    ({"flow_method": "magic"}, r"'flow_method' must be one of 'dis', 'dis-fine'"),
    ({"stages": []}, r"'stages' must be a non-empty list"),
    ({"stages": [[]]}, r"'stages' must be a non-empty list"),
    ({"stages": "012"}, r"'stages' must be a non-empty list"),
    ({"stages": [[0, 1.0]]}, r"'stages' must be a non-empty list"),
    ({"stages": [[-1]]}, r"'stages' must be a non-empty list"),
    ({"stages": [[0], [3]]}, r"'stages' must be lists of pyramid levels 0..2 \(levels is 3\); got \[\[0\], \[3\]\]"),
])
def test_checked_on_construction(tmp_path, kwargs, pattern):
    with pytest.raises(InputError, match=pattern):
        TrackerConfig(**kwargs)
    with pytest.raises(InputError, match=pattern):
        TrackerConfig.load(None, **kwargs)
    p = tmp_path / "cfg.json"
    if all(isinstance(v, (int, float, str, list)) for v in kwargs.values()):
        p.write_text(json.dumps(kwargs))
        with pytest.raises(InputError, match=pattern):
            TrackerConfig.load(p)
    with pytest.raises(InputError, match=pattern):  # dataclasses.replace constructs again
        dataclasses.replace(TrackerConfig(), **kwargs)


def test_every_number_setting_has_a_range():
    from flowmocap.fit.config import _CHOICES, _RANGES

    for f in dataclasses.fields(TrackerConfig):
        if f.type in ("int", "float"):
            assert f.name in _RANGES, f.name
        elif f.type == "str":
            assert f.name in _CHOICES, f.name
        else:
            assert f.type == "bool" or f.name == "stages", f.name


def test_normalised_values():
    cfg = TrackerConfig(flow_weight=2, levels=np.int64(4), silhouette_weight=np.float32(3.0),
                        stages=[[np.int64(3)], (0, 1, 2, 3)])
    assert type(cfg.flow_weight) is float and cfg.flow_weight == 2.0
    assert type(cfg.levels) is int and cfg.levels == 4
    assert type(cfg.silhouette_weight) is float
    assert cfg.stages == ((3,), (0, 1, 2, 3)) and all(type(l) is int for s in cfg.stages for l in s)


def test_to_dict_round_trip(tmp_path):
    for cfg in (TrackerConfig(), TrackerConfig.load(profile="video", stages=[[1], [0, 1]], levels=2)):
        d = cfg.to_dict()
        assert d["stages"] == [list(s) for s in cfg.stages]
        again = json.loads(json.dumps(d))
        assert TrackerConfig.from_dict(again) == cfg
        assert TrackerConfig.load(again) == cfg
        p = tmp_path / "cfg.json"
        p.write_text(json.dumps(d))
        assert TrackerConfig.load(p) == cfg
        assert set(d) == {f.name for f in dataclasses.fields(TrackerConfig)}


def test_the_depth_ambiguity_settings_are_on_by_default_can_be_turned_off_and_are_checked():
    """E_3d, the depth-flip test, the 3D re-initialisation criterion and the learned prior
    are on by default (chosen on the diverse, real3d and 35_01 suites together, see
    docs/experiments.md); each can be turned off; their values are checked like the others."""
    cfg = TrackerConfig()
    assert cfg.detector3d_weight > 0 and cfg.init_detector3d_weight > 0 and cfg.flip_test
    assert cfg.pose_prior_weight > 0 and cfg.init_learned_prior_weight > 0 and cfg.reinit_max_joint3d_error > 0
    off = TrackerConfig.load({"detector3d_weight": 0, "init_detector3d_weight": 0, "flip_test": False,
                              "pose_prior_weight": 0, "init_learned_prior_weight": 0, "reinit_max_joint3d_error": 0})
    assert not off.flip_test and off.uses_detector3d  # E_d still reads the 3D joints
    assert TrackerConfig.load({"detector3d_weight": 50, "detector3d_scale": 0.05, "flip_test": True,
                               "flip_iterations": 3, "reinit_max_joint3d_error": 0.1,
                               "reinit_3d_patience": 2}).flip_iterations == 3
    for bad, pattern in (({"detector3d_weight": -1.0}, r"'detector3d_weight' must be a number >= 0"),
                         ({"detector3d_scale": 0.0}, r"'detector3d_scale' must be a number > 0"),
                         ({"init_detector3d_weight": True}, r"'init_detector3d_weight' must be a finite number"),
                         ({"flip_test": 1}, r"'flip_test' must be true or false"),
                         ({"flip_iterations": -1}, r"'flip_iterations' must be an integer >= 0"),
                         ({"flip_iterations": 2.0}, r"'flip_iterations' must be an integer >= 0"),
                         ({"reinit_max_joint3d_error": -0.1}, r"'reinit_max_joint3d_error' must be a number >= 0"),
                         ({"reinit_3d_patience": 0}, r"'reinit_3d_patience' must be an integer >= 1")):
        with pytest.raises(InputError, match=pattern):
            TrackerConfig.load(bad)


def test_uses_detector3d_names_every_reader_of_the_3d_joints():
    from flowmocap.fit.config import TrackerConfig

    off = dict(limb_depth_weight=0.0, detector3d_weight=0.0, init_detector3d_weight=0.0, reinit_max_joint3d_error=0.0)
    assert not TrackerConfig.load(None, **off).uses_detector3d
    for k, v in (("limb_depth_weight", 1.0), ("detector3d_weight", 50.0), ("init_detector3d_weight", 1e4),
                 ("reinit_max_joint3d_error", 0.1)):
        assert TrackerConfig.load(None, **{**off, k: v}).uses_detector3d, k


def test_the_detectors_ray_share_is_a_share():
    """``detector3d_ray_share`` takes values in [0, 1]; 1, the default, keeps the ray's whole turn."""
    assert TrackerConfig().detector3d_ray_share == 1.0
    assert TrackerConfig.load(None, detector3d_ray_share=0.5).detector3d_ray_share == 0.5
    with pytest.raises(InputError, match="detector3d_ray_share"):
        TrackerConfig.load(None, detector3d_ray_share=1.5)
