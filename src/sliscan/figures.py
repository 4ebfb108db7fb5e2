"""Figures a user looks at: reprojection residual plots of a calibration (issue 5) and the
stage figures of a scan report (issue 10: `sliscan.report`).

matplotlib is the optional ``plot`` extra (``pip install 'sliscan[plot]'``); it is imported only
when a figure is drawn, through matplotlib's object-oriented API (no pyplot state, no display).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

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


def residual_figure(residuals: Residuals, *, title: str = "") -> tuple[Any, list[dict[str, Any]]]:
    """A figure of reprojection residual vectors: one row per view, camera and projector.

    Each panel scatters the ``(dx, dy)`` residuals (``projected - observed``, px) of one device in
    one view, with a dashed circle at their RMS length, which the panel's title gives; a target's
    circles are numbered.

    Parameters
    ----------
    residuals : Residuals
        From ``calibrate_board(..., with_residuals=True)`` or `sliscan.calibrate.target_residuals`.
    title : str
        The figure's title.

    Returns
    -------
    figure : matplotlib.figure.Figure
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
    return fig, panels


def plot_residuals(path: str | os.PathLike, residuals: Residuals, *, title: str = "") -> list[dict[str, Any]]:
    """Write a PNG of `residual_figure` (atomically); returns its panels.

    Raises
    ------
    InputError
        matplotlib is not installed.
    """
    fig, panels = residual_figure(residuals, title=title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI)
    return panels


# --------------------------------------------------------------------------------------------
# Stage figures of a scan (sliscan.report): every function returns a matplotlib Figure
# --------------------------------------------------------------------------------------------

#: Longest side (px) a map is reduced to before plotting: a figure panel shows far fewer.
MAX_MAP_SIDE = 800
#: Where a map has no value (NaN): the panel's background, distinct from every colour map used.
NO_VALUE_COLOUR = "#b9d3e8"


@dataclass(frozen=True)
class Panel:
    """One image panel of `maps_figure`.

    Attributes
    ----------
    title : str
    image : (H, W) array
        Shown with row 0 at the top; NaN shows as the background (`NO_VALUE_COLOUR`, pale blue).
    cmap : str
        matplotlib colormap name.
    vmin, vmax : float, optional
        Colour range; default the 1st and 99th percentiles of the finite values.
    label : str
        Colour bar label; empty: no colour bar.
    extent : (W, H), optional
        Camera pixels the image spans (when it was reduced before); default its own shape.
    """

    title: str
    image: NDArray
    cmap: str = "gray"
    vmin: float | None = None
    vmax: float | None = None
    label: str = ""
    extent: tuple[int, int] | None = None


def png_bytes(fig: Any, *, dpi: int = _DPI) -> bytes:
    """The figure as PNG file bytes."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def reduce_map(image: NDArray, max_side: int = MAX_MAP_SIDE) -> NDArray:
    """`image` sampled every ``ceil(max(H, W) / max_side)`` pixels (nearest: NaN, masks and
    integer maps keep their values).

    >>> reduce_map(np.zeros((1944, 2592)), 800).shape
    (486, 648)
    """
    step = max(1, -(-max(image.shape[:2]) // max_side))
    return image[::step, ::step]


def maps_figure(panels: list[Panel], *, columns: int = 2, title: str = "") -> Any:
    """A grid of image panels (camera pixels), each with its own colour bar.

    Parameters
    ----------
    panels : list of Panel
    columns : int
        Panels per row.
    title : str
        The figure's title.
    """
    figure_module = require_matplotlib()
    columns = min(columns, len(panels))
    rows = -(-len(panels) // columns)
    h, w = panels[0].image.shape[:2]
    fig = figure_module.Figure(figsize=(4.2 * columns, rows * (4.2 * h / w + 0.6) + (0.4 if title else 0.0)),
                               layout="constrained")
    if title:
        fig.suptitle(title)
    axes = np.asarray(fig.subplots(rows, columns, squeeze=False)).ravel()
    for ax, panel in zip(axes, panels):
        image = reduce_map(np.asarray(panel.image))
        shown = image.astype(np.float32) if image.dtype == bool else image
        finite = shown[np.isfinite(shown)] if shown.dtype.kind == "f" else shown.ravel()
        lo = panel.vmin if panel.vmin is not None else (float(np.percentile(finite, 1)) if finite.size else 0.0)
        hi = panel.vmax if panel.vmax is not None else (float(np.percentile(finite, 99)) if finite.size else 1.0)
        pw, ph = panel.extent if panel.extent is not None else panel.image.shape[1::-1]
        drawn = ax.imshow(shown, cmap=panel.cmap, vmin=lo, vmax=max(hi, lo + 1e-9), interpolation="nearest",
                          extent=(-0.5, pw - 0.5, ph - 0.5, -0.5))
        ax.set_facecolor(NO_VALUE_COLOUR)
        ax.set_title(panel.title, fontsize=9)
        ax.tick_params(labelsize=7)
        if panel.label:
            fig.colorbar(drawn, ax=ax, shrink=0.8).set_label(panel.label, fontsize=8)
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    return fig


def spectrum_figure(frequency: NDArray[np.floating], power: NDArray[np.floating], carriers: NDArray[np.floating],
                    labels: list[str], passbands: NDArray[np.floating] | None, passband_label: str) -> Any:
    """The mean line spectrum of a capture with its carriers and pass bands (figs. 3.19-3.22).

    Parameters
    ----------
    frequency, power : (F,) arrays
        Cycles per camera pixel along the carriers, and the mean power there
        (`sliscan.demodulate.line_spectrum`).
    carriers : (C,) array
        The detected carriers, cycles per camera pixel.
    labels : list of str
        One name per carrier ("bit 0", "pilot", ...).
    passbands : (C, F) array, optional
        Each carrier's pass band (magnitude 0..1) over `frequency`.
    passband_label : str
        What the pass bands are.
    """
    figure_module = require_matplotlib()
    fig = figure_module.Figure(figsize=(9.0, 4.2), layout="constrained")
    ax = fig.subplots()
    ax.semilogy(frequency, np.maximum(power, power.max() * 1e-9), color="0.3", lw=0.8, label="mean line spectrum")
    top = float(power.max())
    for n, (f, label) in enumerate(zip(carriers, labels)):
        ax.axvline(f, color=f"C{n}", lw=0.8, ls="--")
        ax.annotate(f"{label}\n{f:.4f}", (f, top), fontsize=7, color=f"C{n}", ha="center", va="bottom",
                    xytext=(0, 2), textcoords="offset points")
    ax.set_xlabel("frequency along the carriers (cycles per camera pixel)")
    ax.set_ylabel("power")
    ax.set_xlim(0, min(0.5, 1.6 * float(np.max(carriers))))
    if passbands is not None:
        twin = ax.twinx()
        for n, band in enumerate(passbands):
            twin.plot(frequency, band, color=f"C{n}", lw=1.2)
        twin.set_ylim(0, 1.35)
        twin.set_ylabel(passband_label)
    ax.legend(loc="upper right", fontsize=8)
    return fig


def histogram_figure(values: NDArray[np.floating], *, bins: int = 60, label: str = "",
                     title: str = "") -> tuple[Any, NDArray[np.int64]]:
    """A histogram of the finite `values` up to their 99.5th percentile (the rest in the last
    bin); returns the figure and the counts, which add up to the finite values."""
    figure_module = require_matplotlib()
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    top = float(np.percentile(v, 99.5)) if v.size else 1.0
    counts, edges = np.histogram(np.clip(v, 0.0, top), bins=bins, range=(0.0, max(top, 1e-9)))
    fig = figure_module.Figure(figsize=(6.0, 3.6), layout="constrained")
    ax = fig.subplots()
    ax.stairs(counts, edges, fill=True, color="C0")
    ax.set_xlabel(label)
    ax.set_ylabel("pixels")
    ax.set_title(title, fontsize=9)
    return fig, counts


def batch_figure(frames: list[str], points: NDArray[np.floating], seconds: NDArray[np.floating]) -> Any:
    """Points and seconds per frame of a batch: two bar charts over the frames, in order."""
    figure_module = require_matplotlib()
    fig = figure_module.Figure(figsize=(9.0, 5.0), layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    x = np.arange(len(frames))
    top.bar(x, points, color="C0")
    top.set_ylabel("points")
    bottom.bar(x, seconds, color="C1")
    bottom.set_ylabel("seconds")
    bottom.set_xlabel("frame")
    step = max(1, len(frames) // 20)
    bottom.set_xticks(x[::step], [str(f) for f in frames[::step]], rotation=45, ha="right", fontsize=7)
    return fig
