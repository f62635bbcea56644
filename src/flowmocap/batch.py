"""Many inputs, one result folder each: :func:`track_many` runs :func:`flowmocap.track` on
every video (or frames or sequence folder) one by one, in parallel processes on this
machine, or as tasks on a Ray cluster, and the same result folders come out either way.

Layout under the output folder ``out_root``::

    out_root/batch.json      which input each result folder belongs to, and the last status of each
    out_root/<name>/         one result folder per input (motion.npz, run.json, ...)

``<name>`` is the input's file or folder name without its suffix (``clips/walk.mp4`` ->
``walk``); where two inputs would get one name (``a/walk.mp4`` and ``b/walk.mp4``, or
``walk.mp4`` and ``walk.mov``), each of them gets ``walk-<8 hex digits>`` from its absolute
path. ``batch.json`` keeps every name it gave, so an input keeps its folder when the
command is run again with more or fewer inputs.

Run again, the same command skips every finished result (whatever settings made it;
``force`` tracks them anew), resumes every interrupted one (with the same settings; other
settings make that input fail with a message) and tracks the rest. One input's failure does
not stop the others; it is reported in the summary.

Every person in one input (:func:`track_people`, ``flowmocap track VIDEO --person all``)::

    out_root/people.json     the people the detector found, which were tracked, each one's status
    out_root/person0/        the largest person's result folder (``--person largest``)
    out_root/person1/ ...    the next by the same rank (``--person 1``), ...

The same skipping, resuming, failure handling and parallel runs as for many inputs.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import numbers
import os
import re
import shutil
import socket
import sys
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from flowmocap.atomic import atomic_write
from flowmocap.errors import DataError, FlowMocapError, InputError
from flowmocap.io.lock import FolderLock
from flowmocap.io.results import PEOPLE_MANIFEST
from flowmocap.io.sequence import IMAGE_SUFFIXES
from flowmocap.io.video import VIDEO_SUFFIXES
from flowmocap.pipeline import load_result, track
from flowmocap.version import __version__

__all__ = ["BATCH_FAILED", "MANIFEST", "PEOPLE_MANIFEST", "PEOPLE_MIN_SHARE", "BatchItem", "expand_inputs",
           "is_batch", "people_to_track", "plan", "summary_table", "track_many", "track_people", "track_people_many"]

#: The file under ``out_root`` that maps result folder names to inputs.
MANIFEST = "batch.json"

#: The command line's exit status when some inputs of a batch failed and the others finished.
BATCH_FAILED = 6


#: :func:`track_people` tracks, besides the largest person, every person the detector follows
#: in at least this share of as many frames as the largest one: someone really there, not a
#: stray detection (on DAVIS dance-twirl the audience gives tracks of 3-15 frames against the
#: dancer's 90; the same share decides when the largest person is re-detected with the others
#: blanked, :data:`flowmocap.vision.auto.LARGEST_FOLLOW_SHARE`).
PEOPLE_MIN_SHARE = 0.25

#: The folder in :func:`track_people`'s output where the detector's search for everyone is
#: kept while people remain to be tracked: each person's run reads it instead of searching
#: the video again (about half of each detection pass); removed once everyone is tracked.
PEOPLE_SEARCH = "search"

#: Arguments of :func:`flowmocap.track` that may name a file or folder: made absolute before
#: they go to another process (a Ray worker need not share this process's working folder).
_PATH_ARGS = ("init", "masks", "camera", "config", "model")

#: What :func:`track_many` sets itself: each input's ``source``, ``out`` and log, and
#: ``resume`` and ``force`` from its own ``force``.
_OWN_ARGS = ("source", "out", "resume", "force", "log")

_WORKER_DIED = ("the worker process running it died twice (it crashed or was killed, e.g. for lack of memory); "
                "run the same command again to resume it")


@dataclass
class BatchItem:
    """One input of a batch and what became of it.

    Attributes:
        input: the input as given (a video file, a frames folder or a sequence folder).
        name: its result folder's name under the batch's output folder.
        out: its result folder.
        status: before a run (:func:`plan`): ``"new"``, ``"resume"`` (an interrupted result
            is there) or ``"finished"``; after it (:func:`track_many`): ``"tracked"``,
            ``"resumed"``, ``"skipped"`` (finished before) or ``"failed"``.
        frames: rows in its result (0 where there is none).
        new_frames: rows this run added.
        seconds: wall-clock seconds this run spent on it (reading, detection, init, tracking).
        reinits: re-initialisations recorded in its result.
        error: why it failed (``""`` unless ``status == "failed"``).
        details: a traceback where the failure was not one of flowmocap's own errors (a bug
            worth reporting), else ``""``.
        person: the person to track in the input, as :func:`flowmocap.track`'s ``person``
            (a rank; :func:`track_people` sets it); None: the batch's own setting.
        exit_code: the exit status the failure would have given alone (``flowmocap.errors``'
            kinds: 2 bad input, 3 optimiser, ...; 1 for any other exception); 0 unless failed.
    """

    input: str
    name: str
    out: Path
    status: str
    frames: int = 0
    new_frames: int = 0
    seconds: float = 0.0
    reinits: int = 0
    error: str = ""
    details: str = ""
    person: int | None = None
    exit_code: int = 0

    @property
    def s_per_frame(self) -> float:
        """Wall-clock seconds per frame this run added (NaN where it added none)."""
        return self.seconds / self.new_frames if self.new_frames else float("nan")

    @property
    def ok(self) -> bool:
        """Whether the input has a finished result."""
        return self.status in ("tracked", "resumed", "skipped", "finished")


def is_batch(inputs: Sequence[str | Path], list_files: Sequence[str | Path] = ()) -> bool:
    """Whether the inputs ask for a batch (one result folder per input under ``--out``)
    rather than one result folder: several inputs, a list file (``@list.txt`` or
    ``list_files``), or a folder of videos or sequence folders. One video, frames folder or
    sequence folder is not a batch: ``--out`` is then the result folder itself."""
    if list_files or len(inputs) != 1:
        return True
    x = str(inputs[0])
    return x.startswith("@") or _is_collection(Path(x))


def expand_inputs(inputs: Sequence[str | Path], list_files: Sequence[str | Path] = ()) -> list[Path]:
    """The inputs of a batch, each once, in the order given.

    Args:
        inputs: video files, frames folders, sequence folders, folders of videos and
            sequence folders (expanded to their entries, sorted by name; not recursively)
            and ``@FILE`` list files.
        list_files: more list files: one input per line; blank lines and lines starting with
            ``#`` are skipped; a relative path is relative to the list file's folder.

    Returns:
        the inputs' paths; a path that does not exist is kept (it fails on its own, as one
        input of the batch, without stopping the others).

    Raises:
        InputError: a list file that cannot be read, a folder that holds nothing to track,
            or no inputs at all.
    """
    inputs = _as_inputs(inputs)
    list_files = _as_inputs(list_files)
    found: list[Path] = []
    for x in inputs:
        s = str(x)
        if s.startswith("@"):
            found += _read_list(Path(s[1:]))
        elif _is_collection(Path(s)):
            found += _collection(Path(s))
        elif Path(s).is_dir() and not _is_single(Path(s)):
            raise InputError(f"{s} holds no videos ({', '.join(VIDEO_SUFFIXES)}), frames or sequence folders; "
                             "give video files, frames folders or sequence folders (with frames/).")
        else:
            found.append(Path(s))
    for f in list_files:
        found += _read_list(Path(f))
    seen, unique = set(), []
    for p in found:
        key = _absolute(p)
        if key not in seen:
            seen.add(key)
            unique.append(p)
    if not unique:
        raise InputError("no inputs to track: give video files, frames or sequence folders, a folder of videos, "
                         "or a list file (@list.txt) with one per line.")
    return unique


def _as_inputs(inputs) -> list:
    """``inputs`` as a list of paths: one path (a ``str`` is a sequence of letters, which
    made a batch of the inputs "s", "e", "q") becomes a list of it.

    Raises:
        InputError: not a path or a sequence of paths.
    """
    if isinstance(inputs, (str, os.PathLike)):
        return [inputs]
    try:
        items = list(inputs)
    except TypeError:
        raise InputError(f"inputs must be a path or a list of paths; got {type(inputs).__name__}.") from None
    bad = [x for x in items if not isinstance(x, (str, os.PathLike))]
    if bad:
        raise InputError(f"inputs must be paths (str or Path); got {type(bad[0]).__name__} ({bad[0]!r}).")
    return items


def plan(inputs: Sequence[str | Path], out_root: str | Path) -> list[BatchItem]:
    """Each input's result folder under ``out_root`` and what is there (status ``"new"``,
    ``"resume"`` or ``"finished"``); records new names in ``out_root/batch.json``.

    Args:
        inputs: the inputs, as :func:`expand_inputs` gives them (an input given twice
            counts once).
        out_root: the batch's output folder (created).

    Raises:
        InputError: ``out_root`` is one input's result folder, not a batch's.
    """
    inputs = _as_inputs(inputs)
    root = Path(out_root)
    _refuse_single_result(root)
    root.mkdir(parents=True, exist_ok=True)
    manifest = _read_manifest(root)
    names = _names([Path(p) for p in inputs], root, manifest)
    items, seen = [], set()
    for p in inputs:
        name = names[_absolute(Path(p))]
        if name in seen:
            continue
        seen.add(name)
        out = root / name
        item = BatchItem(input=str(p), name=name, out=out, status="new")
        if out.is_dir():
            try:
                res = load_result(out)
            except FlowMocapError:  # no result yet (or one that failed before its first frame)
                res = None
            if res is not None:
                item.frames, item.reinits = len(res), _reinits(res)
                item.status = "finished" if res.run.get("status") == "finished" else "resume"
        items.append(item)
    _update_manifest(root, {it.name: {"input": _absolute(Path(it.input))} for it in items})
    return items


def track_many(inputs: Sequence[str | Path], out_root: str | Path, workers: int = 1, ray: bool | str = False,
               force: bool = False, progress: bool = True, log: Callable[[str], None] | None = print,
               **track_kwargs) -> list[BatchItem]:
    """Track every input into its own result folder under ``out_root`` (see the module's
    docstring for the layout, names, skipping and resuming).

    Args:
        inputs: video files, frames folders or sequence folders (:func:`expand_inputs`
            expands folders of videos and list files first; this function does not).
        out_root: the batch's output folder.
        workers: how many inputs to track at once in separate processes on this machine
            (1: one after the other, in this process). Each process gets an equal share of
            the cores for torch's threads.
        ray: False (no Ray), True (the Ray instance this process is connected to, else the
            one ``RAY_ADDRESS`` names, else a new local one) or a Ray address (``"auto"``,
            ``"HOST:PORT"``, ``"ray://HOST:10001"``): each input is one Ray task with one
            CPU. flowmocap must be installed on the cluster's nodes and the inputs and
            ``out_root`` must lie at the same paths on each node (a shared file system).
        force: track every input anew, starting its result folder over, finished and
            interrupted ones too (:func:`flowmocap.track`'s ``force``).
        progress: progress bars (one input at a time in this process only; parallel runs
            report one line per input instead).
        log: where the one-line messages go (each prefixed with the input's name; None:
            nowhere).
        **track_kwargs: settings for every input, as :func:`flowmocap.track` takes them
            (``init``, ``masks``, ``config``, ``frames``, ...) except ``source``, ``out``,
            ``resume``, ``force`` and ``log``.

    Returns:
        one :class:`BatchItem` per input, in the inputs' order; failed inputs have status
        ``"failed"`` and say why. Without ``force``, a finished result is skipped whatever
        settings made it.

    Raises:
        InputError: bad ``workers``, ``ray`` and ``workers`` together, Ray not installed or
            its cluster not reachable, ``track_kwargs`` naming an argument this function
            sets itself, or an ``out_root`` that is a single result folder.
        FolderBusyError: another batch holds ``out_root`` (one at a time writes it).
    """
    kwargs = _checked_kwargs("track_many", _OWN_ARGS, track_kwargs, workers, ray, force)
    inputs = _as_inputs(inputs)
    _refuse_single_result(Path(out_root))  # before the lock makes a folder
    with FolderLock(out_root):  # one batch at a time writes batch.json and decides what is left to do
        return _track_many(inputs, Path(out_root), kwargs, workers, ray, force, progress, log)


def _track_many(inputs, root: Path, kwargs: dict, workers, ray, force: bool, progress: bool, log) -> list[BatchItem]:
    say = log if log is not None else (lambda _msg: None)
    items = plan(inputs, root)
    if force:  # every input starts over
        items = [replace(it, status="new", frames=0, reinits=0) for it in items]
    todo = [it for it in items if it.status != "finished"]
    counts = {s: sum(it.status == s for it in items) for s in ("new", "resume", "finished")}
    how = ("one after the other" if (workers == 1 and ray in (False, None)) else
           "as Ray tasks" if ray not in (False, None) else f"in {min(workers, max(len(todo), 1))} worker processes")
    say(f"{len(items)} inputs into {root}: " + ("all tracked anew (force)" if force else
        f"{counts['new']} new, {counts['resume']} to resume, {counts['finished']} finished before (skipped)")
        + f"; tracking {how}")
    results = {it.name: replace(it, status="skipped") for it in items if it.status == "finished"}
    done = 0

    def report(res: BatchItem) -> None:
        nonlocal done
        done += 1
        results[res.name] = res
        _update_manifest(root, {res.name: _manifest_entry(res)})
        _say_result(say, f"[{done}/{len(todo)}] ", res)

    _dispatch(todo, kwargs, workers, ray, report, say, progress, log)
    return [results[it.name] for it in items]


def _say_result(say: Callable[[str], None], prefix: str, res: BatchItem) -> None:
    """One line on how an item's run ended (a failure's traceback, if any, to stderr)."""
    if res.status == "failed":
        say(f"{prefix}{res.name}: FAILED after {res.seconds:.1f} s: {res.error}")
        if res.details:
            print(res.details, file=sys.stderr, end="" if res.details.endswith("\n") else "\n")
    else:
        say(f"{prefix}{res.name}: {res.status}, {res.frames} frames "
            f"({res.new_frames} new, {res.s_per_frame:.2f} s per frame, {res.seconds:.1f} s)")


def _checked_kwargs(who: str, own: Sequence[str], track_kwargs: dict, workers, ray, force: bool) -> dict:
    """``track_kwargs`` checked (none of ``own``; ``workers`` and ``ray`` valid, Ray
    importable and reachable), with paths made absolute and ``force`` added."""
    clash = sorted(set(track_kwargs) & set(own))
    if clash:
        raise InputError(f"{who} sets {', '.join(clash)} for each result itself; leave them out.")
    if "search_dir" in track_kwargs:  # one input's search, shared by its people: never by several inputs
        raise InputError(f"{who} does not take search_dir: it is for the runs of one input that choose different "
                         "people (track_people keeps one for them itself); leave it out.")
    import inspect

    from flowmocap import pipeline

    unknown = sorted(set(track_kwargs) - set(inspect.signature(pipeline.track).parameters))
    if unknown:  # each input would fail alone, as a bug (exit 1, a traceback)
        raise InputError(f"{who} passes settings to flowmocap.track, which takes no {', '.join(unknown)}; check the "
                         "names (e.g. frames, config, init).")
    if not isinstance(workers, numbers.Integral) or isinstance(workers, bool) or workers < 1:
        raise InputError(f"workers must be a whole number >= 1; got {workers!r}.")
    if not isinstance(force, (bool, np.bool_)):  # force="no" would be true, and start every input over
        raise InputError(f"force must be True or False; got {force!r}.")
    if ray is not False and ray is not None and workers != 1:
        raise InputError("choose either Ray (--ray) or local worker processes (--workers), not both.")
    if ray not in (False, None):  # before anything is written: say at once when Ray is missing or unreachable
        _import_ray()
        if isinstance(ray, str):
            _check_reachable(ray)
    kwargs = {k: _absolute_arg(v) if k in _PATH_ARGS else v for k, v in track_kwargs.items()}
    kwargs["force"] = bool(force)
    return kwargs


def _dispatch(todo: list[BatchItem], kwargs: dict, workers: int, ray, report: Callable[[BatchItem], None],
              say: Callable[[str], None], progress: bool, log: Callable[[str], None] | None) -> None:
    """Track ``todo`` one after the other in this process, in worker processes or as Ray
    tasks, and ``report`` each as it ends."""
    if not todo:
        return
    if ray not in (False, None):
        _run_ray(todo, kwargs, ray, report)
    elif workers > 1:
        _run_processes(todo, kwargs, workers, report, say)
    else:
        for it in todo:
            report(_track_one(it, kwargs, progress=progress, log=log))


# --- every person in one input ------------------------------------------------------------------------------------

def people_to_track(info: dict, min_share: float = PEOPLE_MIN_SHARE) -> list[dict]:
    """The people of a detection pass that :func:`track_people` tracks.

    Args:
        info: a result folder's ``detections/detections.json``, or its path (its ``person.people``: per
            person ``rank`` (0 = the largest), ``frames`` [first, last], ``detections`` (frames
            the detector followed them in), ``score``, ``first_box`` px).
        min_share: a person is tracked when followed in at least this share of as many frames
            as the largest person (0..1; 0 tracks everyone the detector found).

    Returns:
        their entries, by rank; the largest person always.

    Raises:
        DataError: ``info`` lists no people (detections of an older flowmocap, or of a run
            with its own masks and init, which chooses nobody).
    """
    if not 0.0 <= float(min_share) <= 1.0:
        raise InputError(f"min_share must lie in 0..1; got {min_share!r}.")
    if isinstance(info, (str, os.PathLike)):  # the detections.json file itself
        try:
            info = json.loads(Path(info).read_text())
        except (OSError, ValueError) as e:
            raise DataError(f"cannot read {info} as a detections.json ({e}).") from None
    if not isinstance(info, dict):
        raise InputError(f"info must be a detections.json's dict, or its path; got {type(info).__name__}.")
    people = sorted((info.get("person") or {}).get("people") or [], key=lambda p: p["rank"])
    if not people:
        raise DataError("the detections list no people to choose from (made by an older flowmocap, or with your own "
                        "masks and init); track anew with automatic masks (--force).")
    least = float(min_share) * people[0]["detections"]
    return [people[0]] + [p for p in people[1:] if p["detections"] >= least]


def track_people(source: str | Path, out_root: str | Path, min_share: float = PEOPLE_MIN_SHARE, workers: int = 1,
                 ray: bool | str = False, force: bool = False, progress: bool = True,
                 log: Callable[[str], None] | None = print, **track_kwargs) -> list[BatchItem]:
    """Track every person in view of one input, each into its own result folder.

    The largest person (:func:`flowmocap.track`'s ``person="largest"``) is tracked first,
    into ``out_root/person0``; its detection pass ranks everyone the detector follows
    (``detections/detections.json``). Then each person followed in at least ``min_share``
    of as many frames (:func:`people_to_track`) is tracked by their rank N into
    ``out_root/personN``, with the others blanked for the detector. ``out_root/people.json``
    lists the people found, which were tracked and how each run ended. Run again, finished
    people are skipped and interrupted ones resumed, as in :func:`track_many`. The
    detector's search for everyone is made once, in ``out_root/search``
    (:data:`PEOPLE_SEARCH`), read by every person's run, and removed once all are tracked.

    Args:
        source: one video, frames folder or sequence folder (its masks are not used: the
            detector finds the people).
        out_root: the output folder (created); not a single result folder.
        min_share: see :func:`people_to_track` (default :data:`PEOPLE_MIN_SHARE`).
        workers, ray, force, progress, log: as :func:`track_many`; the people after the
            largest are tracked in parallel with ``workers`` > 1 or ``ray``.
        **track_kwargs: settings for every person, as :func:`flowmocap.track` takes them,
            except ``source``, ``out``, ``resume``, ``force``, ``log``, ``person``, and
            ``masks`` or ``init`` other than ``"auto"`` (they would say who is tracked). A
            ``height`` is the first (largest) person's alone: the others' sizes then follow
            from standing on their floor (:mod:`flowmocap.export.floor`).

    Returns:
        one :class:`BatchItem` per person tracked, by rank (``person`` holds the rank). A
        person to the eye may be two here: someone who comes back into view more than two
        body heights from where they were last seen is followed as two
        (:func:`flowmocap.vision.person.same_person`).

    Raises:
        InputError: bad arguments (as :func:`track_many`), own masks or init, or an
            ``out_root`` that is a single result folder or a batch's folder.
        FolderBusyError: another run holds ``out_root``.
    """
    kwargs = _checked_people_kwargs(track_kwargs, min_share, workers, ray, force)
    root = Path(out_root)
    if _holds_result(root):
        raise InputError(f"{root} is the result folder of a single run; give another --out folder for every person "
                         "(each gets its own result folder inside it).")
    if (root / MANIFEST).exists():
        raise InputError(f"{root} holds a batch of inputs ({MANIFEST}); give another --out folder for the people "
                         "of one input.")
    with FolderLock(root):  # one run at a time writes people.json and decides who is left to track
        return _track_people(str(source), root, kwargs, min_share, workers, ray, force, progress, log)


def _track_people(src: str, root: Path, kwargs: dict, min_share: float, workers, ray, force: bool, progress: bool,
                  log) -> list[BatchItem]:
    """:func:`track_people`'s work, with ``root`` held."""
    say = log if log is not None else (lambda _msg: None)
    try:
        before = json.loads((root / PEOPLE_MANIFEST).read_text()).get("input")
    except (OSError, ValueError, AttributeError):
        before = None
    if before is not None and before != _absolute(Path(src)):
        tracked = sorted(d.name for d in root.glob("person*") if _holds_result(d))
        if tracked:  # a run that failed before anyone was tracked leaves only people.json: used again
            raise InputError(f"{root} holds the people of another input ({before}: {', '.join(tracked)}); give "
                             "another --out folder, the same input to go on with it, or delete the folder first to "
                             "use it for this input.")
        (root / PEOPLE_MANIFEST).unlink()  # the other input's list of people, none of them tracked
    _update_people(root, src, min_share, {})
    kwargs["search_dir"] = str((root / PEOPLE_SEARCH).resolve())
    first = _person_item(root, src, 0, force)
    results: dict[int, BatchItem] = {}

    def report(res: BatchItem) -> None:
        results[res.person] = res
        entry = _manifest_entry(res)
        del entry["input"]  # people.json names it once
        _update_people(root, src, min_share, {res.name: entry})
        _say_result(say, "", res)

    if first.status == "finished":
        say(f"{first.name} (the largest person) finished before: skipped")
        results[0] = replace(first, status="skipped")
    else:
        say(f"tracking the largest person into {first.out}; then everyone else the detector follows in at least "
            f"{min_share:g} of as many frames")
        report(_track_one(first, kwargs, progress=progress, log=log))
    found = root / first.name / "detections" / "detections.json"
    try:
        info = json.loads(found.read_text())
    except (OSError, ValueError):  # the first run failed before its detection pass ended: nobody else is known
        return [results[0]]
    if not (info.get("person") or {}).get("people"):  # nobody found (the first run failed for it)
        return [results[0]]
    chosen = people_to_track(info, min_share)
    listed = {f"person{p['rank']}": {"rank": p["rank"], "seen_frames": p["frames"], "detections": p["detections"],
                                     "first_box": p["first_box"], "tracked": p in chosen}
              for p in (info.get("person") or {}).get("people", [])}
    _update_people(root, src, min_share, listed)
    items = [_person_item(root, src, p["rank"], force) for p in chosen[1:]]
    for it in items:
        if it.status == "finished":
            results[it.person] = replace(it, status="skipped")
    todo = [it for it in items if it.status != "finished"]
    skipped = len(items) - len(todo)
    found_n = len(info["person"]["people"])
    say(f"{found_n} {'person' if found_n == 1 else 'people'} found, {len(chosen)} followed long enough to track"
        + (f"; {len(todo)} more to track" if todo else "")
        + (f", {skipped} finished before (skipped)" if skipped else ""))
    # a stated height is the first (largest) person's; the others' sizes come from standing on
    # that person's floor where the people are viewed or exported together (flowmocap.export.floor)
    _dispatch(todo, {k: v for k, v in kwargs.items() if k != "height"}, workers, ray, report, say, progress, log)
    if all(results[r].status != "failed" for r in results):  # nobody left to search for
        shutil.rmtree(root / PEOPLE_SEARCH, ignore_errors=True)
    return [results[r] for r in sorted(results)]


def track_people_many(inputs: Sequence[str | Path], out_root: str | Path, min_share: float = PEOPLE_MIN_SHARE,
                      workers: int = 1, ray: bool | str = False, force: bool = False, progress: bool = True,
                      log: Callable[[str], None] | None = print, **track_kwargs) -> list[BatchItem]:
    """:func:`track_people` for each of several inputs, one after the other: input ``x``'s
    people go to ``out_root/<name>/person0``, ... (``<name>`` as :func:`track_many` names
    result folders; ``out_root/batch.json`` keeps the names and each input's status). One
    input's failure does not stop the others; run again, finished people are skipped.

    Args:
        inputs: as :func:`track_many` (:func:`expand_inputs` first).
        out_root, min_share, workers, ray, force, progress, log, track_kwargs: as
            :func:`track_people` (``workers`` and ``ray`` share out each input's people).

    Returns:
        one :class:`BatchItem` per person tracked (``name`` is ``<name>/personN``), input by
        input; an input that failed before anyone was tracked gives one failed item.

    Raises:
        InputError: as :func:`track_people`, before anything runs.
        FolderBusyError: another run holds ``out_root``.
    """
    _checked_people_kwargs(track_kwargs, min_share, workers, ray, force)
    root = Path(out_root)
    if _holds_result(root):
        raise InputError(f"{root} is the result folder of a single input; give another --out folder for several "
                         "inputs (each gets its own folder of people inside it).")
    with FolderLock(root):  # one run at a time writes batch.json and decides what is left to do
        return _track_people_many(_as_inputs(inputs), root, min_share, workers, ray, force, progress, log,
                                  track_kwargs)


def _track_people_many(inputs: list, root: Path, min_share: float, workers, ray, force: bool, progress: bool, log,
                       track_kwargs: dict) -> list[BatchItem]:
    """:func:`track_people_many`'s work, with ``root`` held."""
    say = log if log is not None else (lambda _msg: None)
    paths = [Path(p) for p in inputs]
    names = _names(paths, root, _read_manifest(root))
    _update_manifest(root, {names[_absolute(p)]: {"input": _absolute(p)} for p in paths})
    done: set[str] = set()
    items: list[BatchItem] = []
    for p in paths:
        name = names[_absolute(p)]
        if name in done:
            continue
        done.add(name)
        say(f"[{len(done)}/{len(names)}] {p}: every person into {root / name}")
        t0 = time.perf_counter()
        try:
            if not p.exists():
                raise DataError(f"{p} does not exist; give a video file, a folder of frames or a sequence folder.")
            people = track_people(p, root / name, min_share=min_share, workers=workers, ray=ray, force=force,
                                  progress=progress, log=log, **track_kwargs)
        except FlowMocapError as e:  # this input's own trouble (e.g. its folder holds another input's people)
            people = [BatchItem(input=str(p), name="person0", out=root / name / "person0", status="failed",
                                seconds=time.perf_counter() - t0, error=str(e), person=0)]
        items += [replace(it, name=f"{name}/{it.name}") for it in people]
        failed = [it.name for it in people if it.status == "failed"]
        _update_manifest(root, {name: {"status": "failed" if failed else "finished", "people": len(people),
                                       **({"failed": failed} if failed else {}),
                                       "when": time.strftime("%Y-%m-%dT%H:%M:%S%z")}})
    return items


def _checked_people_kwargs(track_kwargs: dict, min_share: float, workers, ray, force: bool) -> dict:
    """:func:`_checked_kwargs` for :func:`track_people`: no person, masks or init of one's own,
    ``min_share`` in 0..1."""
    for key in ("masks", "init"):
        if track_kwargs.get(key) not in (None, "auto"):
            raise InputError(f"every person is tracked with automatic {key}: your own {key} ({track_kwargs[key]}) "
                             "would say who is tracked; leave it out, or track that person alone.")
    if not 0.0 <= float(min_share) <= 1.0:
        raise InputError(f"min_share must lie in 0..1; got {min_share!r}.")
    return _checked_kwargs("track_people", (*_OWN_ARGS, "person"), track_kwargs, workers, ray, force)


def _person_item(root: Path, source: str, rank: int, force: bool) -> BatchItem:
    """The :class:`BatchItem` of the person of ``rank`` under ``root`` and what is there."""
    name = f"person{rank}"
    item = BatchItem(input=source, name=name, out=root / name, status="new", person=rank)
    if force or not item.out.is_dir():
        return item
    try:
        res = load_result(item.out)
    except FlowMocapError:
        return item
    return replace(item, frames=len(res), reinits=_reinits(res),
                   status="finished" if res.run.get("status") == "finished" else "resume")


def _update_people(root: Path, source: str, min_share: float, entries: dict) -> None:
    """Merge ``{name: entry}`` into ``root/people.json`` (atomically; keeps the others)."""
    path = root / PEOPLE_MANIFEST
    try:
        old = json.loads(path.read_text()) if path.exists() else {}
    except (OSError, ValueError):
        old = {}
    people = old.get("people") if isinstance(old.get("people"), dict) else {}
    for name, entry in entries.items():
        people[name] = {**people.get(name, {}), **entry}
    data = {"flowmocap": __version__, "input": _absolute(Path(source)), "min_share": float(min_share),
            "people": dict(sorted(people.items(), key=lambda kv: int(kv[0].removeprefix("person"))))}
    atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(data, indent=2)))


def summary_table(items: Iterable[BatchItem], root: str | Path | None = None, noun: str = "inputs") -> str:
    """A plain-text table of a batch's items (input, result folder, status, frames, new
    frames, s per frame, seconds, re-initialisations), a count line (of ``noun``: "inputs",
    or "people" for :func:`track_people`) and each failure's reason."""
    items = list(items)
    rows = [("input", "result", "status", "frames", "new", "s/frame", "time s", "reinits")]
    for it in items:
        spf = f"{it.s_per_frame:.2f}" if it.new_frames else "-"
        rows.append((it.input, it.name, it.status, str(it.frames), str(it.new_frames), spf,
                     f"{it.seconds:.1f}" if it.status != "skipped" else "-", str(it.reinits)))
    width = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    numeric = {3, 4, 5, 6, 7}
    lines = ["  ".join(c.rjust(w) if k in numeric else c.ljust(w) for k, (c, w) in enumerate(zip(r, width))).rstrip()
             for r in rows]
    lines.insert(1, "  ".join("-" * w for w in width))
    n = {s: sum(it.status == s for it in items) for s in ("tracked", "resumed", "skipped", "failed")}
    if len(items) == 1:
        noun = {"inputs": "input", "people": "person"}.get(noun, noun)
    lines.append(f"{len(items)} {noun}: {n['tracked']} tracked, {n['resumed']} resumed, {n['skipped']} finished "
                 f"before (skipped), {n['failed']} failed" + (f"; results in {root}" if root is not None else ""))
    lines += [f"failed: {it.input}: {it.error}" for it in items if it.status == "failed"]
    return "\n".join(lines)


# --- one input, wherever it runs ----------------------------------------------------------------------------------

def _track_one(item: BatchItem, kwargs: dict, progress: bool = False,
               log: Callable[[str], None] | None = print, threads: int | None = None) -> BatchItem:
    """Track one planned item (status ``"new"`` or ``"resume"``) and say what became of it;
    never raises for a failure of this input (KeyboardInterrupt still stops it)."""
    if threads is not None:
        _set_threads(threads)
    t0 = time.perf_counter()
    before = item.frames if item.status == "resume" else 0
    prefix = f"[{item.name}] "
    say = None if log is None else (lambda msg: log(prefix + msg))
    try:
        src = Path(item.input)
        if not src.exists():
            raise DataError(f"{src} does not exist; give a video file, a folder of frames or a sequence folder.")
        # resume=True also starts afresh a folder without tracked frames (a run that stopped before its first one)
        if item.person is not None:
            kwargs = {**kwargs, "person": item.person}
        if not kwargs.get("force") and _finished(item.out):  # finished since the plan (by another run)
            return replace(item, status="skipped", frames=len(load_result(item.out)), new_frames=0,
                           seconds=time.perf_counter() - t0)
        res = track(src, item.out, resume=not kwargs.get("force"), progress=progress, log=say, **kwargs)
        return replace(item, status="resumed" if item.status == "resume" else "tracked", frames=len(res),
                       new_frames=len(res) - before, seconds=time.perf_counter() - t0, reinits=_reinits(res))
    except Exception as e:  # noqa: BLE001 -- one input's failure, whatever it is, must not stop the others
        details = "" if isinstance(e, FlowMocapError) else traceback.format_exc()
        frames = 0
        try:
            frames = len(load_result(item.out))
        except FlowMocapError:
            pass
        return replace(item, status="failed", frames=frames, new_frames=max(frames - before, 0),
                       seconds=time.perf_counter() - t0, error=_describe(e), details=details,
                       exit_code=e.exit_code if isinstance(e, FlowMocapError) else 1)


def _track_in_worker(item: BatchItem, kwargs: dict, threads: int) -> BatchItem:
    """:func:`_track_one` in a worker process or a Ray task: no progress bars; the one-line
    messages go to this process's stdout at once (the parent's or Ray's log shows them)."""
    return _track_one(item, kwargs, progress=False, log=lambda msg: print(msg, flush=True), threads=threads)


def _set_threads(n: int) -> None:
    """Limit torch's thread pool of this process to ``n`` threads (the tracker itself uses
    the settings' ``torch_threads`` while it runs). OpenCV keeps its own: its DIS flow
    differs in the last bits with its thread count, and a worker's results must equal those
    of the same input tracked in the main process."""
    torch.set_num_threads(n)


def _describe(e: BaseException) -> str:
    return str(e) if isinstance(e, FlowMocapError) else f"{type(e).__name__}: {e}"


def _reinits(res) -> int:
    return sum(1 for e in res.events if e.get("event") == "re-initialised")


# --- local worker processes ---------------------------------------------------------------------------------------

def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _run_processes(todo: list[BatchItem], kwargs: dict, workers: int, report: Callable[[BatchItem], None],
                   say: Callable[[str], None]) -> None:
    """Track ``todo`` in ``workers`` spawned processes, at most ``workers`` inputs handed out
    at a time. When a process dies (a crash, the out-of-memory killer) the pool goes down with
    it; the inputs it was running cannot be told apart, so each of them is tried once more in
    a fresh pool (resuming from its last committed frame) and fails if its second try dies
    too."""
    workers = min(workers, len(todo))
    threads = max(1, _cores() // workers)
    pending = deque(todo)
    context = multiprocessing.get_context("spawn")  # no fork of a process that holds torch's and OpenCV's threads
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=context)
    running: dict = {}  # future -> (item, when it was handed out)
    tries: dict[str, int] = {}
    spent: dict[str, float] = {}  # seconds of tries that died
    try:
        while pending or running:
            broken = False  # the pool died after the last wait and refuses new work
            while pending and len(running) < workers:
                it = pending.popleft()
                try:
                    fut = pool.submit(_track_in_worker, it, kwargs, threads)
                except BrokenProcessPool:  # never handed out: no try spent
                    pending.appendleft(it)
                    broken = True
                    break
                tries[it.name] = tries.get(it.name, 0) + 1
                running[fut] = (it, time.perf_counter())
            finished = wait(running, return_when=FIRST_COMPLETED)[0] if running else set()
            lost = []
            for fut in finished:
                it, t0 = running.pop(fut)
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    lost.append((it, t0))
                else:
                    report(replace(res, seconds=res.seconds + spent.get(res.name, 0.0)))
            if lost or broken:  # every input still in the dead pool is lost with it
                lost += list(running.values())
                running.clear()
                pool.shutdown(wait=True, cancel_futures=True)
                pool = ProcessPoolExecutor(max_workers=workers, mp_context=context)
            if lost:
                again = [it.name for it, _ in lost if tries[it.name] < 2]
                say(f"a worker process died while tracking {', '.join(it.name for it, _ in lost)}"
                    + (f"; trying {', '.join(again)} once more (resuming)" if again else ""))
                for it, t0 in reversed(lost):
                    spent[it.name] = spent.get(it.name, 0.0) + time.perf_counter() - t0
                    if tries[it.name] < 2:
                        pending.appendleft(it)
                    else:
                        report(_died(it, spent[it.name]))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _died(item: BatchItem, seconds: float, error: str = _WORKER_DIED) -> BatchItem:
    """``item`` failed because its process died; with the frames its result folder kept."""
    before = item.frames if item.status == "resume" else 0
    try:
        frames = len(load_result(item.out))
    except FlowMocapError:
        frames = 0
    return replace(item, status="failed", frames=frames, new_frames=max(frames - before, 0), seconds=seconds,
                   error=error)


# --- Ray ----------------------------------------------------------------------------------------------------------

def _import_ray():
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs the Ray package, which is not installed: pip install 'flowmocap[cluster]' "
                         "(or pip install 'ray[client]'), or use --workers N to run in processes on this "
                         "machine.") from None
    return ray


def _check_reachable(address: str, timeout: float = 5.0) -> None:
    """Raise InputError when nothing answers at a ``HOST:PORT`` or ``ray://HOST:PORT``
    address (Ray itself would retry for minutes); other forms (``auto``, ``local``) are left
    to ``ray.init``."""
    hostport = address.removeprefix("ray://")
    host, sep, port = hostport.rpartition(":")
    if not (sep and host and port.isdigit()):
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise InputError(f"no Ray cluster answers at {address} ({e}); start one with `ray start --head` on its head "
                         "node, or check the address and port (6379 for the head node, 10001 for ray://).") from None


def _run_ray(todo: list[BatchItem], kwargs: dict, address: bool | str, report: Callable[[BatchItem], None]) -> None:
    """Track each of ``todo`` as one Ray task (one CPU each) and report each as it ends."""
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        where = None if address is True or address == "" else str(address)
        # a new local instance: no dashboard, fewer log lines; Ray Client (ray://) takes neither
        options = {} if (where or "").startswith("ray://") else {"include_dashboard": False, "logging_level": "WARNING"}
        try:
            ray.init(address=where, **options)
        except Exception as e:  # noqa: BLE001 -- ray raises ConnectionError, RuntimeError, ValueError, ...
            raise InputError(f"cannot start or reach the Ray cluster{f' at {where}' if where else ''}: "
                             f"{type(e).__name__}: {str(e).rstrip('.')}; start one with `ray start --head` on its "
                             "head node and pass its address (--ray HOST:6379, or --ray auto on a node of "
                             "it).") from None
        started = True
    try:
        task = ray.remote(num_cpus=1, max_retries=1)(_track_in_worker)
        t0 = time.perf_counter()
        refs = {task.remote(it, kwargs, 1): it for it in todo}
        waiting = list(refs)
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=1)
            ref = ready[0]
            try:
                report(ray.get(ref))
            except ray.exceptions.RayError as e:  # its process died (twice: Ray retried it once), or it could not run
                report(_died(refs[ref], time.perf_counter() - t0,
                             f"the Ray task failed: {type(e).__name__}: {e}; run the same command again to resume it"))
    finally:
        if started:
            ray.shutdown()


# --- names and the manifest ---------------------------------------------------------------------------------------

def _absolute(p: Path) -> str:
    return str(Path(os.path.abspath(Path(p).expanduser())))


def _absolute_arg(v):
    """A path-like argument made absolute where it names an existing file or folder;
    anything else (``"auto"``, ``"default"``, a number, an object) unchanged."""
    if isinstance(v, (str, Path)) and Path(v).expanduser().exists():
        return _absolute(Path(v))
    return v


def _refuse_single_result(root: Path) -> None:
    """InputError where ``root``, given as a batch's folder, is one input's result folder."""
    if _holds_result(root):
        raise InputError(f"{root} is the result folder of a single input; give another --out folder for several "
                         "inputs (each gets its own result folder inside it).")


def _finished(folder: Path) -> bool:
    """Whether ``folder`` holds a finished result: its ``run.json`` says so beside a
    ``motion.npz``, with no run in progress (read without loading the motion: it is asked
    before every input's run)."""
    if (folder / "progress.json").exists() or not (folder / "motion.npz").is_file():
        return False
    try:
        run = json.loads((folder / "run.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(run, dict) and run.get("status") == "finished"


def _holds_result(folder: Path) -> bool:
    if not folder.is_dir():
        return False
    try:
        load_result(folder)
    except FlowMocapError:
        return False
    return True


def _is_single(p: Path) -> bool:
    """A sequence folder (``frames/``) or a folder of images: one input."""
    return p.is_dir() and ((p / "frames").is_dir() or any(q.suffix.lower() in IMAGE_SUFFIXES for q in p.iterdir()))


def _collection(p: Path) -> list[Path]:
    """The videos, sequence folders and frames folders in folder ``p``, sorted by name."""
    return sorted(q for q in p.iterdir() if (q.is_file() and q.suffix.lower() in VIDEO_SUFFIXES) or _is_single(q))


def _is_collection(p: Path) -> bool:
    return p.is_dir() and not _is_single(p) and bool(_collection(p))


def _read_list(path: Path) -> list[Path]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read the list file {path}: {e}; give a text file with one input per line.") from None
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            p = Path(line).expanduser()
            out.append(p if p.is_absolute() else path.parent / p)
    return out


_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _base_name(p: Path) -> str:
    p = Path(os.path.normpath(p))
    stem = p.stem if p.suffix.lower() in VIDEO_SUFFIXES else p.name
    return _SAFE.sub("_", stem).strip("._") or "input"


def _hashed(p: Path) -> str:
    return f"{_base_name(p)}-{hashlib.sha1(_absolute(p).encode()).hexdigest()[:8]}"


def _names(paths: list[Path], root: Path, manifest: dict) -> dict[str, str]:
    """``{absolute input: result folder name}``: names ``batch.json`` gave before are kept;
    a new input gets its base name unless another input of this batch or of ``batch.json``
    (compared ignoring case) or a folder ``batch.json`` does not know has it, else the
    base name with a hash of its path."""
    given = {v["input"]: k for k, v in manifest.items()}
    taken = {k.lower() for k in manifest} | {MANIFEST.lower()}
    taken |= {q.name.lower() for q in root.iterdir()} if root.is_dir() else set()
    new = {_absolute(p): p for p in paths if _absolute(p) not in given}
    count: dict[str, int] = {}
    for p in new.values():
        count[_base_name(p).lower()] = count.get(_base_name(p).lower(), 0) + 1
    names = {}
    for p in paths:
        key = _absolute(p)
        if key in names:
            continue
        if key in given:
            names[key] = given[key]
            continue
        base = _base_name(p)
        name = base if (count[base.lower()] == 1 and base.lower() not in taken) else _hashed(p)
        taken.add(name.lower())
        names[key] = name
    return names


def _read_manifest(root: Path) -> dict:
    path = root / MANIFEST
    if not path.exists():
        return {}
    try:
        items = json.loads(path.read_text())["results"]
    except (OSError, ValueError, KeyError, TypeError):
        items = None
    if not (isinstance(items, dict) and all(isinstance(v, dict) and isinstance(v.get("input"), str)
                                            for v in items.values())):
        raise InputError(f"{path} is not a flowmocap batch file; give another --out folder, or delete it (the "
                         "result folders beside it are then named anew from their inputs).")
    return items


def _manifest_entry(it: BatchItem) -> dict:
    entry = {"input": _absolute(Path(it.input)), "status": it.status, "frames": it.frames,
             "new_frames": it.new_frames, "seconds": round(it.seconds, 3), "reinits": it.reinits,
             "when": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if it.error:
        entry["error"] = it.error
    return entry


def _update_manifest(root: Path, entries: dict) -> None:
    """Merge ``{name: entry}`` into ``root/batch.json`` (atomically; keeps the others)."""
    items = _read_manifest(root)
    for name, entry in entries.items():
        items[name] = {**items.get(name, {}), **entry}
    data = {"flowmocap": __version__, "results": items}

    def write(tmp):
        Path(tmp).write_text(json.dumps(data, indent=2))

    atomic_write(root / MANIFEST, write)
