"""The command line: help lists the commands, the demo renders the body honestly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def test_help_lists_commands():
    out = subprocess.run([sys.executable, "-m", "flowmocap.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for cmd in ("demo", "body", "synth"):
        assert cmd in out.stdout


def test_every_command_has_a_description_and_every_flag_a_help_text():
    import argparse

    from flowmocap.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    missing = [f"{name}: description" for name, p in sub.choices.items() if not p.description]
    missing += [f"{name} {a.option_strings or a.dest}" for name, p in sub.choices.items()
                for a in p._actions if a.help is None]
    assert not missing, missing


def test_demo_tracks_scores_and_points_to_the_next_commands(tmp_path, capsys):
    import imageio.v3 as iio

    from flowmocap.cli import main

    assert main(["demo", "--out", str(tmp_path), "--num-frames", "4", "--size", "240x180", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "3D joint error" in printed and "flowmocap render" in printed and "flowmocap export" in printed
    img = iio.imread(tmp_path / "default_body.png")
    assert img.ndim == 3 and (np.abs(img.astype(int) - 245).sum(2) > 30).mean() > 0.05
    scores = json.loads((tmp_path / "eval.json").read_text())
    for key in ("local_cm", "global_cm", "s_per_frame"):
        assert np.isfinite(scores[key])
    assert scores["frames"] == 4
    assert (tmp_path / "result" / "motion.npz").exists()
    # the demo's own earlier result made with other settings (an older version's defaults) is redone, not refused
    from flowmocap.eval.demo import run_demo

    again = run_demo(tmp_path, frames=4, size="240x180", progress=False, config={"iterations": 3})
    assert again["frames"] == 4
    assert json.loads((tmp_path / "result" / "run.json").read_text())["config"]["iterations"] == 3


def test_body_command_errors_cleanly(tmp_path, capsys):
    from flowmocap.cli import main

    assert main(["body", "--pose", "cartwheel", "--out", str(tmp_path / "b.png")]) == 2
    assert "unknown pose" in capsys.readouterr().err
    assert main(["body", "--model", str(tmp_path / "missing.pkl"), "--out", str(tmp_path / "b.png")]) == 2
    assert "does not exist" in capsys.readouterr().err
    for size in (["--width", "0"], ["--width", "100000", "--height", "100000"]):  # before: a NaN camera, a 28 GiB array
        assert main(["body", *size, "--out", str(tmp_path / "b.png")]) == 2
        assert "16..8192 pixels" in capsys.readouterr().err
    for angle in (["--azimuth", "nan"], ["--elevation", "90"]):  # before: messages about look_at's arguments
        assert main(["synth", "builtin:walk", *angle, "--num-frames", "2", "--size", "64x48",
                     "--out", str(tmp_path / "s")]) == 2
        assert "elevation strictly between -90 and 90" in capsys.readouterr().err


def test_track_takes_a_list_file_alone_and_says_when_there_is_no_input(tmp_path, capsys):
    """`track --list FILE` with no other input is a batch (argparse required an input
    before); `track` with neither says what to give."""
    from flowmocap.cli import main

    assert main(["track", "--out", str(tmp_path / "none")]) == 2
    assert "track needs an input" in capsys.readouterr().err
    todo = tmp_path / "todo.txt"
    todo.write_text(str(tmp_path / "missing.mp4") + "\n")
    assert main(["track", "--list", str(todo), "--out", str(tmp_path / "out")]) == 6  # a batch whose input failed
    assert "missing.mp4 does not exist" in capsys.readouterr().out



def _child_signals() -> None:
    """In the child: Ctrl-C as a shell gives it (a child can inherit an ignored SIGINT)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def test_ctrl_c_while_the_libraries_load_is_one_line_not_a_traceback(tmp_path):
    """Ctrl-C in the first second or two of any command came out as an import's traceback
    (scipy: 'ImportError: initialization failed', exit 1: a bug's status)."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "flowmocap.cli", "body", "--out", str(tmp_path / "b.png")],
                            stderr=subprocess.PIPE, text=True, preexec_fn=_child_signals)
    time.sleep(0.4)  # torch, scipy and OpenCV take seconds to load
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "Traceback" not in err and "interrupted" in err, (proc.returncode, err)


def test_sigterm_stops_a_command_as_ctrl_c_does_and_leaves_no_temporary(tmp_path):
    """SIGTERM ended every command but view at once: render's video and export's files left
    their temporaries, and no rerun removed them."""
    import signal
    import time

    out = tmp_path / "seq"
    proc = subprocess.Popen([sys.executable, "-m", "flowmocap.cli", "synth", "builtin:walk", "--out", str(out),
                             "--num-frames", "400", "--size", "160x120", "--no-flow"],
                            stderr=subprocess.PIPE, text=True, preexec_fn=_child_signals)
    deadline = time.time() + 300
    while time.time() < deadline and len(list((out / "frames").glob("*.png")) if (out / "frames").is_dir() else []) < 3:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, (proc.returncode, err)
    assert not [p for p in out.rglob("*.tmp")]


_READ_ONLY_INSTALL = r"""
import os, sys
real = os.access
blocked = (sys.argv[1], os.path.join(sys.argv[2], ".cache"))  # the package's folder, the home's cache
os.access = lambda p, mode, **kw: False if (mode & os.W_OK and str(p).startswith(blocked)) else real(p, mode, **kw)
os.environ.pop("NUMBA_CACHE_DIR", None)
os.environ["HOME"] = sys.argv[2]
os.environ.pop("XDG_CACHE_HOME", None)
import flowmocap
os.access = real
from numba.core import config
print(os.environ.get("NUMBA_CACHE_DIR"), config.CACHE_DIR)
"""


def test_a_read_only_install_keeps_numba_kernels_in_a_temporary_folder(tmp_path):
    # site-packages and the home both read-only (a container run as another user): numba could cache
    # nowhere and every command, --help included, was a numba traceback
    import flowmocap

    pkg = str(Path(flowmocap.__file__).parent)
    env = {**os.environ, "TMPDIR": str(tmp_path)}  # its folder in this test's, not the machine's /tmp
    out = subprocess.run([sys.executable, "-c", _READ_ONLY_INSTALL, pkg, str(tmp_path / "home")],
                         capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    env_dir, config_dir = out.stdout.split()
    assert env_dir == config_dir and env_dir.startswith(str(tmp_path)) and "flowmocap-numba" in env_dir
    assert os.access(env_dir, os.W_OK)
    if not os.access(pkg, os.W_OK):  # installed read-only: the choice above is this install's own
        return
    # a writable package folder leaves numba's own choice alone
    plain = subprocess.run([sys.executable, "-c", "import os, flowmocap; print(os.environ.get('NUMBA_CACHE_DIR'))"],
                           capture_output=True, text=True, timeout=120,
                           env={k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"})
    assert plain.stdout.strip() == "None", plain.stderr


def test_python_dash_m_flowmocap_is_the_command():
    out = subprocess.run([sys.executable, "-m", "flowmocap", "--version"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().startswith("flowmocap "), out.stderr


def test_a_numba_cache_folder_someone_else_could_write_is_not_used(tmp_path, monkeypatch):
    # numba loads pickled kernels from the folder: another user's, or one anyone can write, could run their code
    import flowmocap

    pkg = Path(flowmocap.__file__).parent
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if (mode & os.W_OK and (
        str(p) == str(pkg) or str(p).startswith(str(tmp_path / "home")))) else real(p, mode, **kw))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    shared = tmp_path / "tmp" / f"flowmocap-numba-{os.getuid()}"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)  # planted by someone else, writable by all
    chosen = flowmocap._numba_cache_dir()
    assert chosen != str(shared) and Path(chosen).parent == tmp_path / "tmp"
    assert (os.stat(chosen).st_mode & 0o777) == 0o700
    shared.rmdir()
    (tmp_path / "elsewhere").mkdir()
    shared.symlink_to(tmp_path / "elsewhere")  # a link to a folder of another's choosing
    assert flowmocap._numba_cache_dir() != str(shared)
    shared.unlink()
    assert flowmocap._numba_cache_dir() == str(shared)  # made here: this user's, 0700
    assert (os.stat(shared).st_mode & 0o777) == 0o700


def test_a_home_that_cannot_be_written_gets_matplotlib_a_folder_of_its_own(tmp_path, monkeypatch):
    # matplotlib warned on every run ("mkdir -p failed ... set the MPLCONFIGDIR") with a read-only home
    import flowmocap

    home = tmp_path / "home"
    home.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if (mode & os.W_OK and str(p).startswith(
        str(home))) else real(p, mode, **kw))
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    monkeypatch.delenv("MPLCONFIGDIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    chosen = flowmocap._matplotlib_config_dir()
    assert chosen == str(tmp_path / "tmp" / f"flowmocap-matplotlib-{os.getuid()}")
    assert (os.stat(chosen).st_mode & 0o777) == 0o700
    monkeypatch.setattr(os, "access", real)
    assert flowmocap._matplotlib_config_dir() is None  # a writable home: matplotlib's own
    monkeypatch.setenv("MPLCONFIGDIR", str(tmp_path / "mine"))
    assert flowmocap._matplotlib_config_dir() is None
