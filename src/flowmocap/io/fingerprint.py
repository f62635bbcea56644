"""Fingerprints: short content hashes of everything that determines a result, so that a
resumed run, or stored detections, are only used for the very input and set-up they were
made from.

A fingerprint is a dict ``{part: hex digest}`` (parts such as ``input``, ``model``,
``camera``, ``init``, ``config``, ``detector``, ``code``); :func:`differing` names the
parts two fingerprints disagree on, for the error message.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

#: Bytes read per block when hashing files.
_BLOCK = 1 << 20


def digest_files(paths) -> str:
    """Hex digest (BLAKE2b, 16 bytes) of the names and contents of ``paths`` (files), in
    the order given. Raises OSError for an unreadable file."""
    h = hashlib.blake2b(digest_size=16)
    for p in paths:
        p = Path(p)
        h.update(p.name.encode() + b"\0")
        with open(p, "rb") as f:
            while block := f.read(_BLOCK):
                h.update(block)
        h.update(b"\1")
    return h.hexdigest()


def digest_input(source: str | Path) -> str:
    """Digest of an input's content: a video file's bytes, or every file under a folder
    (frames, masks, camera.json, ...; sorted by relative path). Cost: one read of the
    input (about 1 s per GB)."""
    source = Path(source)
    if source.is_file():
        return digest_files([source])
    files = sorted((p for p in source.rglob("*") if p.is_file()), key=lambda p: p.relative_to(source).as_posix())
    h = hashlib.blake2b(digest_size=16)
    for p in files:
        h.update(p.relative_to(source).as_posix().encode() + b"\0")
    h.update(digest_files(files).encode())
    return h.hexdigest()


def digest_value(value) -> str:
    """Digest of a JSON-like value (dicts, lists, numbers, strings, numpy arrays, paths):
    equal values give equal digests whatever the dicts' key order."""
    from flowmocap.io.results import json_default

    text = json.dumps(value, sort_keys=True, default=json_default, separators=(",", ":"))
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def digest_arrays(arrays) -> str:
    """Digest of numpy arrays (or tensors) in the order given: dtype, shape and bytes."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a))
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def digest_model(model) -> str:
    """Digest of a :class:`~flowmocap.body.BodyModel`'s arrays (template, shape and pose
    blend shapes, joint regressor, skin weights, faces) and gender: two files holding the
    same body give the same digest, two different bodies never."""
    return digest_arrays([b for _, b in sorted(model.named_buffers(), key=lambda kv: kv[0])] +
                         [np.frombuffer(str(model.gender).encode(), np.uint8)])


def differing(old: dict | None, new: dict) -> list[str]:
    """The parts of ``new`` whose digests differ from (or are missing in) ``old``."""
    old = old or {}
    return [k for k in new if old.get(k) != new[k]] + [k for k in old if k not in new]
