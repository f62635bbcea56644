"""Per-frame plots of a result: energy terms, the 3D sources' disagreement and, with ground
truth, the 3D joint error."""

from __future__ import annotations

import numpy as np

from flowmocap.errors import InputError

__all__ = ["energy_error_plot"]


def energy_error_plot(frame_index: np.ndarray, energies: np.ndarray, names, errors: dict | None = None,
                      title: str = "", dpi: int = 100, disagreement: np.ndarray | None = None) -> np.ndarray:
    """A figure of the per-frame energies (one panel per term), the 3D sources'
    disagreement and the 3D joint error.

    Args:
        frame_index: ``(T,)`` frame numbers.
        energies: ``(T, K)`` energy values per frame (NaN where a term was not computed);
            terms that are NaN or zero on every frame are left out.
        names: ``K`` term names.
        errors: optional ``{label: (T,) centimetres}`` joint errors to plot in a last panel
            (e.g. local Procrustes, MPJPE).
        title: figure title.
        dpi: resolution.
        disagreement: optional ``(T, J)`` metres, the result's ``disagreement``
            (:mod:`flowmocap.fit.disagreement`; NaN where none): a panel of its per-frame
            mean and largest value over the joints, centimetres.

    Returns:
        ``(h, w, 3)`` uint8 RGB image of the figure.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    x = np.asarray(frame_index)
    e = np.asarray(energies, np.float64).reshape(len(x), -1)
    names = [str(n) for n in names]
    if e.shape[1] != len(names):
        raise InputError(f"energies have {e.shape[1]} columns but {len(names)} names were given.")
    keep = [k for k in range(e.shape[1]) if np.any(np.isfinite(e[:, k]) & (e[:, k] != 0))]
    dis = None
    if disagreement is not None:
        dis = 100 * np.asarray(disagreement, np.float64).reshape(len(x), -1)
        dis = dis if np.isfinite(dis).any() else None
    panels = len(keep) + (1 if errors else 0) + (1 if dis is not None else 0)
    if panels == 0:
        raise InputError("nothing to plot: every energy is NaN or zero and there is no ground truth.")
    cols = min(3, panels)
    rows = int(np.ceil(panels / cols))
    fig = Figure(figsize=(4.2 * cols, 2.6 * rows), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(rows, cols, i + 1) for i in range(panels)]
    for ax, k in zip(axes, keep):
        y = e[:, k]
        ax.plot(x, y, ".-", lw=1.2, ms=3, color="tab:blue")
        ax.set_title(f"E: {names[k]}", fontsize=10)
        pos = y[np.isfinite(y)]
        if pos.size and np.all(pos > 0) and pos.max() / max(pos.min(), 1e-300) > 50:
            ax.set_yscale("log")
        ax.set_xlabel("frame", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    if dis is not None:
        ax = axes[len(keep)]
        have = np.isfinite(dis).any(1)
        mean = np.full(len(x), np.nan)
        top = np.full(len(x), np.nan)
        mean[have], top[have] = np.nanmean(dis[have], 1), np.nanmax(dis[have], 1)
        ax.plot(x, top, ".-", lw=1.0, ms=2, color="tab:red", label="largest joint")
        ax.plot(x, mean, ".-", lw=1.2, ms=3, color="tab:purple", label="mean of the joints")
        _finish_curves(ax, "3D sources' disagreement [cm]")
    if errors:
        ax = axes[-1]
        for label, err in errors.items():
            err = np.asarray(err, np.float64)
            ax.plot(x, err, ".-", lw=1.2, ms=3, label=f"{label} (mean {np.nanmean(err):.2f})")
        _finish_curves(ax, "3D joint error vs ground truth [cm]")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _finish_curves(ax, title: str) -> None:
    """Title, axis from zero, legend and grid of a panel of labelled per-frame curves."""
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("frame", fontsize=8)
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=8)
