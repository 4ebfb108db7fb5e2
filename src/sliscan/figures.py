"""Figures a user looks at: reprojection residual plots of a calibration (issue 5).

matplotlib is the optional ``plot`` extra (``pip install 'sliscan[plot]'``); it is imported only
when a figure is drawn, through matplotlib's object-oriented API (no pyplot state, no display).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from sliscan._validate import InputError, atomic_path
from sliscan.calibrate import Residuals

_DEVICES = ("camera", "projector")
# Inches per panel; dots per inch of the PNG.
_PANEL_IN = 3.6
_DPI = 100
# Circles with more points than this are not numbered (the labels would hide the points).
_MAX_NUMBERED = 40


def require_matplotlib() -> Any:
    """The `matplotlib.figure` module, or a one-line `InputError` telling how to install it."""
    try:
        import matplotlib.figure
    except ImportError:
        raise InputError("plotting needs matplotlib: pip install 'sliscan[plot]'") from None
    return matplotlib.figure


def plot_residuals(path: str | os.PathLike, residuals: Residuals, *, title: str = "") -> list[dict[str, Any]]:
    """Write a PNG of reprojection residual vectors: one row per view, camera and projector.

    Each panel scatters the ``(dx, dy)`` residuals (``projected - observed``, px) of one device in
    one view, with a dashed circle at their RMS length, which the panel's title gives; a target's
    circles are numbered.  The file is written atomically.

    Parameters
    ----------
    path : path
        The PNG to write.
    residuals : Residuals
        From ``calibrate_board(..., with_residuals=True)`` or `sliscan.calibrate.target_residuals`.
    title : str
        The figure's title.

    Returns
    -------
    panels : list of dict
        What was plotted, row by row: ``view``, ``device``, ``rms_px`` and ``points`` (the
        number of residuals).

    Raises
    ------
    InputError
        matplotlib is not installed.
    """
    figure_module = require_matplotlib()
    rows = len(residuals.labels)
    fig = figure_module.Figure(figsize=(2 * _PANEL_IN, rows * _PANEL_IN + (0.4 if title else 0.0)),
                               layout="constrained")
    if title:
        fig.suptitle(title)
    axes = np.asarray(fig.subplots(rows, 2, squeeze=False))
    panels: list[dict[str, Any]] = []
    for k, label in enumerate(residuals.labels):
        for j, device in enumerate(_DEVICES):
            d = np.asarray(getattr(residuals, device)[k], dtype=np.float64).reshape(-1, 2)
            rms = residuals.rms(device)[k]
            ax = axes[k, j]
            ax.axhline(0.0, color="0.8", lw=0.8)
            ax.axvline(0.0, color="0.8", lw=0.8)
            ax.scatter(d[:, 0], d[:, 1], s=12, color="C0" if device == "camera" else "C1")
            angle = np.linspace(0.0, 2 * np.pi, 181)
            ax.plot(rms * np.cos(angle), rms * np.sin(angle), "k--", lw=0.8)
            if residuals.points == "circle" and len(d) <= _MAX_NUMBERED:
                for n, (dx, dy) in enumerate(d):
                    ax.annotate(str(n), (dx, dy), fontsize=7, xytext=(3, 3), textcoords="offset points")
            lim = 1.15 * max(float(np.abs(d).max()) if d.size else 0.0, rms, 1e-3)
            ax.set_xlim(-lim, lim)
            ax.set_ylim(lim, -lim)  # image rows grow downwards
            ax.set_aspect("equal")
            ax.set_xlabel("dx (px)")
            ax.set_ylabel("dy (px)")
            ax.set_title(f"{label}, {device}\nRMS {rms:.3f} px, {len(d)} {residuals.points}s", fontsize=9)
            panels.append({"view": label, "device": device, "rms_px": rms, "points": len(d)})
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI)
    return panels
