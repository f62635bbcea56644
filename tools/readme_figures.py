#!/usr/bin/env python3
"""Regenerate the pictures in the README with the project's own code.

    python tools/readme_figures.py            # writes docs/*.png

- docs/default_body.png: the default body (mean, +-2 sd on the first two shape
  components, a posed example), as `flowmocap demo` renders it.
- docs/flow_figure.png: observed (OpenCV DIS) vs rendered backward flow of the default body
  in the built-in walk, Middlebury colour coding with its colour key.
- docs/cmu35_01_sheet.png: 8 of 130 frames (60 fps) of `flowmocap synth` on CMU 35_01 (needs
  ../shared/data; skipped with a message when it is absent).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CMU = ROOT.parent / "shared" / "data" / "mocap" / "cmu" / "35_01.amc"


def main() -> int:
    from flowmocap.viz.body_figure import body_sheet

    DOCS.mkdir(exist_ok=True)
    iio.imwrite(DOCS / "default_body.png", body_sheet())
    print(f"wrote {DOCS / 'default_body.png'}")
    from flowmocap.viz.flow_figure import flow_figure

    iio.imwrite(DOCS / "flow_figure.png", flow_figure())
    print(f"wrote {DOCS / 'flow_figure.png'}")
    if not CMU.exists():
        print(f"skipped the CMU contact sheet: {CMU} not found")
        return 0
    from flowmocap.synth import synthesize

    with tempfile.TemporaryDirectory() as tmp:
        res = synthesize(str(CMU), Path(tmp) / "seq", fps=60, frames=130, size=(640, 480), azimuth=70,
                         betas="random", seed=0, flow=False)
        n = res.meta["num_frames"]
        picks = np.linspace(0, n - 1, 8).round().astype(int)
        tiles = [iio.imread(Path(tmp) / "seq" / "frames" / f"{i:06d}.png")[::2, ::2] for i in picks]
    rows = [np.concatenate(tiles[r * 4:(r + 1) * 4], axis=1) for r in range(2)]
    iio.imwrite(DOCS / "cmu35_01_sheet.png", np.concatenate(rows, axis=0))
    print(f"wrote {DOCS / 'cmu35_01_sheet.png'} (frames {picks.tolist()} of {n})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
