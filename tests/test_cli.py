"""The command line: help lists the commands, the demo renders the body honestly."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np


def test_help_lists_commands():
    out = subprocess.run([sys.executable, "-m", "flowmocap.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("demo", "body", "synth"):
        assert cmd in out.stdout


def test_demo_renders_default_body_and_says_what_is_missing(tmp_path, capsys):
    import imageio.v3 as iio

    from flowmocap.cli import main

    assert main(["demo", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "Not built yet" in printed
    img = iio.imread(tmp_path / "default_body.png")
    assert img.ndim == 3 and img.shape[2] == 3
    # the body is there: a good share of pixels differ from the plain background
    assert (np.abs(img.astype(int) - 245).sum(2) > 30).mean() > 0.05
    info = json.loads((tmp_path / "demo.json").read_text())
    assert info["vertices"] > 5000


def test_body_command_errors_cleanly(tmp_path, capsys):
    from flowmocap.cli import main

    assert main(["body", "--pose", "cartwheel", "--out", str(tmp_path / "b.png")]) == 2
    assert "unknown pose" in capsys.readouterr().err
    assert main(["body", "--model", str(tmp_path / "missing.pkl"), "--out", str(tmp_path / "b.png")]) == 2
    assert "does not exist" in capsys.readouterr().err
