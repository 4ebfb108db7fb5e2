"""One frame to a point cloud: demodulate -> decode -> reconstruct (thesis section 6.1).

`Scanner` holds what does not change from frame to frame (the pattern, the calibration, the
carriers once found) so a stream of frames from one rig pays for it once.  A multi-frame
pattern (``pmp``, ``graycode``) goes the same way from a whole capture sequence: decode
(`sliscan.sequences`) -> the same triangulation and filters.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan import fastscan, fringe
from sliscan._threads import over_rows, side_by_side
from sliscan._validate import InputError, check_image
from sliscan.baseband import Baseband, BasebandPlan, demodulate_baseband, normalise_lines
from sliscan.decode import Decoded, decode
from sliscan.demodulate import (ALBEDO_ESTIMATES, Carriers, Demodulated, along_carriers, check_exposure, demodulate,
                                detect_carriers)
from sliscan.outliers import (default_max_jump, remove_jump_edges, remove_narrow_runs, remove_run_ends,
                               remove_shadow_sides, remove_speckles)
from sliscan.pmp import ProjectorMap
from sliscan.reconstruct import MeasurableTest, TestArgs, Triangulator, device_centre, is_measurable
from sliscan.sequences import decode_frames
from sliscan.staircase import BESIDE_REACH, interpolate_lines, prefer_borders, prefer_centred
from sliscan.stripe_order import rig_direction
from sliscan.types import MULTI_FRAME_KINDS, Calibration, PatternSpec, ScanResult


def texture_from_dc(dc: NDArray[np.floating]) -> NDArray[np.float32]:
    """Texture in [0, 1] from the local mean: scaled so the 99.5th percentile is white."""
    top = float(np.percentile(dc[::4, ::4], 99.5)) if dc.size else 1.0
    return np.clip(dc / max(top, 1e-6), 0, 1).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _measurable_rows(points: NDArray[np.float32], valid: NDArray[np.bool_], test: TestArgs, rows: NDArray[np.intp],
                     out: NDArray[np.bool_]) -> None:
    """`measurable` for the given rows: `valid` and `is_measurable` with `test` (`MeasurableTest.args`)."""
    for y in rows:
        for x in range(points.shape[1]):
            out[y, x] = valid[y, x] and is_measurable(np.float64(points[y, x, 0]), np.float64(points[y, x, 1]),
                                                      np.float64(points[y, x, 2]), test)


def measurable(points: NDArray[np.float32], valid: NDArray[np.bool_], calibration: Calibration, direction: str, *,
               min_angle_deg: float) -> NDArray[np.bool_]:
    """Valid points that are measurements: finite, in front of the camera and the projector,
    projecting inside the projector's image (through its lens, if it has distortion) along
    the direction the stripes do not code, and seen by camera and projector rays meeting at
    `min_angle_deg` or more.

    A wrong stripe on a pixel the projector never reached (above its frustum, in shadow)
    otherwise triangulates to a point metres away, where the camera ray meets that stripe's
    plane outside the projector's image; and depth precision falls with the angle between the
    rays, so a wrong stripe on a ray almost parallel to its plane lands metres away too.  The
    projector's image counts with a margin of 2 % of its lines.  One compiled pass, rows in
    threads (`sliscan.reconstruct.Triangulator.measure` runs the same test as it triangulates).

    Parameters
    ----------
    points : (H, W, 3) float32 array
        World points in mm, NaN where invalid.
    valid : (H, W) bool array
        The points to test; the others are not measurable.
    direction : {"rows", "columns"}
        The projector coordinate the stripes code.

    Returns
    -------
    (H, W) bool array
    """
    test = MeasurableTest.of(calibration, direction, min_angle_deg).args
    out = np.empty(valid.shape, dtype=bool)
    pts, mask = np.ascontiguousarray(points, dtype=np.float32), np.ascontiguousarray(valid)
    over_rows(lambda rows: _measurable_rows(pts, mask, test, rows, out), valid.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _finish_rows(points: NDArray[np.float32], valid: NDArray[np.bool_], proj_map: NDArray[np.floating],
                 index: NDArray[np.integer], rows: NDArray[np.intp], proj_out: NDArray[np.float32],
                 index_out: NDArray[np.int16]) -> None:
    """`_finish` for the given rows."""
    for y in rows:
        for x in range(valid.shape[1]):
            if valid[y, x]:
                proj_out[y, x], index_out[y, x] = np.float32(proj_map[y, x]), np.int16(index[y, x])
            else:
                points[y, x, :] = np.nan
                proj_out[y, x], index_out[y, x] = np.nan, -1


def inverse_depths(points: NDArray[np.floating], matrix: NDArray[np.floating]) -> NDArray[np.float32]:
    """Inverse depth (1/mm) along the axis of the device of 3x4 `matrix` of world points
    ``(..., 3)`` (mm): ``(...)`` float32, NaN where a point is NaN.

    >>> P = np.hstack([np.eye(3), [[0.0], [0.0], [0.0]]]) * 2  # a scaled pinhole at the origin
    >>> 1 / inverse_depths(np.array([[0.0, 10.0, 800.0], [5.0, 0.0, 400.0]]), P)
    array([800., 400.], dtype=float32)
    """
    m = np.asarray(matrix, dtype=np.float64)
    row = m[2] * np.sign(np.linalg.det(m[:, :3])) / np.linalg.norm(m[2, :3])
    with np.errstate(divide="ignore", invalid="ignore"):
        return (1.0 / (np.asarray(points, dtype=np.float64) @ row[:3] + row[3])).astype(np.float32)


def _finish(points: NDArray[np.float32], valid: NDArray[np.bool_], proj_map: NDArray[np.floating],
            index: NDArray[np.integer], *, in_place: bool = False) -> tuple[NDArray[np.float32], NDArray[np.int16]]:
    """A scan's outputs, restricted to `valid` ``(H, W)``: sets `points` ``(H, W, 3)`` to NaN
    outside it, and returns `proj_map` ``(H, W)`` as float32 (NaN outside) and the stripe or
    fringe `index` ``(H, W)`` as int16 (-1 outside): new arrays, or with `in_place` the given
    ones (which must then be float32 and int16)."""
    if in_place:
        proj_out, index_out = proj_map, index
    else:
        proj_out, index_out = np.empty(valid.shape, np.float32), np.empty(valid.shape, np.int16)
    over_rows(lambda rows: _finish_rows(points, valid, proj_map, index, rows, proj_out, index_out), valid.shape[0])
    return proj_out, index_out


def baseline_direction(calibration: Calibration) -> str:
    """The projector coordinate that triangulates best on this rig: ``"rows"`` when the camera
    lies above or below the projector, ``"columns"`` when beside it.

    Decided by the epipole (the camera centre seen by the projector): the epipolar lines run
    from it, and the coded lines should cross them, so rows are coded when the epipole lies
    farther from the image centre along the projector's y axis than along its x axis.
    """
    epipole = calibration.projector.matrix @ np.append(device_centre(calibration.camera.matrix), 1.0)
    w, h = calibration.projector.size
    offset = epipole[:2] - epipole[2] * np.array([(w - 1) / 2, (h - 1) / 2])
    return "rows" if abs(offset[1]) >= abs(offset[0]) else "columns"


#: Coded lines crossing the camera's carrier direction at more than this angle (degrees,
#: `stripe_tilt_deg`) cost single-shot accuracy: on the virtual rig (1296x972, the sphere, the
#: projector turned about its axis; docs/accuracy.md, "Projector roll") the median error of
#: sliscan's pattern grows 1.1x at 2 degrees, 1.3x at 3, 1.7x at 5 and 3.1x at 10 (the phase
#: pattern's 1.2x, 1.4x, 1.7x, 2.5x).
MAX_STRIPE_TILT_DEG = 2.0

#: A carrier finer than this many camera pixels per period (`carrier_period_px`) is not
#: demodulated reliably: the phase pattern (finest carrier 224 cycles per 1024 px) on the
#: virtual rig's sphere (smooth albedo, 1 px blurs, gamma 2.2) was 45 / 50 / 84 / 90 % complete
#: at 3.1 / 3.4 / 3.7 / 4.2 camera pixels per period (cameras 704x528 to 960x720; 5.7 at
#: 1296x972, 93 %).
MIN_CARRIER_PERIOD_PX = 3.5

#: A projector this far (degrees) off the camera's column through it (row, for columns: the
#: angle of the camera's epipolar lines to its phase direction, `baseline_angle_deg`) moves the
#: carriers with depth: on the virtual rig's sphere (1296x972, seeds 0 and 1, the projector
#: 200 mm above and moved sideways, its field of view kept; docs/accuracy.md, "Projector
#: offset") sliscan's pattern is 96.2 % complete level, 95.2 / 94.5 / 93.2 / 91.4 / 89.2 % at
#: 7 / 14 / 18 / 22 / 27 degrees; the phase pattern 91.0 -> 89.6 / 88.2 / 84.9 / 80.1 / 79.0 %,
#: its RMS error 3.0 -> 3.8 / 4.1 / 5.4 / 5.5 / 7.4 mm.
MAX_BASELINE_ANGLE_DEG = 10.0


def _frame_lattice(calibration: Calibration) -> NDArray[np.float64]:
    """``(3, 25)`` homogeneous camera pixels of a 5 x 5 lattice spanning the camera's frame."""
    w, h = calibration.camera.size
    u, v = np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5))
    return np.stack([u.ravel(), v.ravel(), np.ones(u.size)])


def baseline_angle_deg(calibration: Calibration, orientation: str = "rows") -> float:
    """The largest angle, in degrees, between the camera's epipolar lines (the lines depth
    moves a point's image along) and its phase direction (camera ``y`` for ``"rows"``, ``x``
    for ``"columns"``), over a 5 x 5 lattice spanning the camera's frame.  Zero on the thesis's
    rig (the projector straight above the camera); ``atan(offset / baseline)`` for a projector
    moved sideways.  Beyond `MAX_BASELINE_ANGLE_DEG` depth moves the carriers too.

    >>> from sliscan import simulate
    >>> rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768), projector_offset_mm=50.0)
    >>> round(baseline_angle_deg(rig.calibration), 2)  # atan(50 / 200)
    14.04
    """
    epipole = calibration.camera.matrix @ np.append(device_centre(calibration.projector.matrix), 1.0)
    pixels = _frame_lattice(calibration)
    away = pixels[:2] * epipole[2] - epipole[:2, None]  # from the epipole to each pixel (it may lie at infinity)
    phase, carrier = (away[1], away[0]) if orientation == "rows" else (away[0], away[1])
    return float(np.degrees(np.arctan2(np.abs(carrier), np.abs(phase))).max())


def _projector_gradients(calibration: Calibration,
                         orientation: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How the projector's ``(xp, yp)`` change with the camera pixel on distant surfaces (the
    homography of the plane at infinity, ``P_p[:, :3] P_c[:, :3]^-1``: the rig's rotation
    between the two devices, whatever the scene adds; lenses taken as ideal), at the
    `_frame_lattice`: along the camera's carrier direction (``x`` for `orientation` ``"rows"``,
    ``y`` for ``"columns"``) and along its phase direction, each ``(2, 25)``."""
    to_projector = calibration.projector.matrix[:, :3] @ np.linalg.inv(calibration.camera.matrix[:, :3])
    q = to_projector @ _frame_lattice(calibration)
    # quotient rule on (q[0] / q[2], q[1] / q[2]); axis 1 of `to_projector[:, :2]` is d/dx, d/dy
    gradient = (to_projector[:2, :2, None] * q[2] - to_projector[2, None, :2, None] * q[:2, None]) / q[2] ** 2
    return (gradient[:, 0], gradient[:, 1]) if orientation == "rows" else (gradient[:, 1], gradient[:, 0])


def stripe_tilt_deg(calibration: Calibration, orientation: str = "rows") -> float:
    """The largest angle, in degrees, at which the projector's coded lines (its rows for
    ``"rows"``, its columns for ``"columns"``) cross the camera's carrier direction (camera
    ``x``, or ``y``), over a 5 x 5 lattice spanning the camera's frame (`_projector_gradients`).

    A single-shot pattern is demodulated along the camera's lines: the more its stripes cross
    them, the more a window straddles a stripe border (`MAX_STRIPE_TILT_DEG`).

    >>> from sliscan import simulate
    >>> rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768), projector_roll_deg=4.0)
    >>> round(stripe_tilt_deg(rig.calibration), 1)  # 4 at the centre, a little more at the corners
    4.1
    """
    along, across = _projector_gradients(calibration, orientation)
    coded = 1 if orientation == "rows" else 0
    return float(np.degrees(np.arctan2(np.abs(along[coded]), np.abs(across[coded]))).max())


def carrier_period_px(spec: PatternSpec, calibration: Calibration) -> float:
    """Camera pixels per period of `spec`'s finest carrier along the camera's carrier direction,
    the least over a 5 x 5 lattice spanning the frame (`_projector_gradients`: distant
    surfaces; a surface turned away compresses it further).  Under `MIN_CARRIER_PERIOD_PX`
    the camera does not resolve the pattern.

    >>> from sliscan import patterns, simulate
    >>> rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768))
    >>> round(carrier_period_px(patterns.default_spec((1024, 768)), rig.calibration), 1)  # 128 cycles
    4.9
    """
    along, _ = _projector_gradients(calibration, spec.orientation)
    other = 0 if spec.orientation == "rows" else 1  # the projector coordinate the carriers run along
    finest = max(spec.all_carriers) / spec.orthogonal_lines  # cycles per projector pixel
    return float(1.0 / (finest * np.abs(along[other]).max()))


#: `Scanner` methods (`sliscan scan --method`): the demodulators of `sliscan.demodulate` and the
#: real-time path of `sliscan.fastscan`.
METHODS = ("window", "bandpass", "baseband")

#: How a single-shot pattern's stripes are decided (`sliscan scan --decisions`): the
#: `decode.decode` options of each choice.  ``auto``: `decode.decode`'s default, by order (the
#: real-time path decides per pixel whatever is asked); ``order``: down each column as a whole
#: (`sliscan.stripe_order`), the more complete and about 2-3x slower decoding; ``pixel``: each
#: pixel from its own bits, the faster one.
DECISIONS: dict[str, dict[str, Any]] = {"auto": {}, "order": {"order": True}, "pixel": {"order": False}}


def decision_options(spec: PatternSpec, decisions: str) -> dict[str, Any]:
    """`Scanner.decode_options` for one of the `DECISIONS` on `spec`.

    Raises
    ------
    InputError
        For an unknown choice, or a choice other than ``auto`` with a multi-frame pattern
        (its frames are decoded pixel by pixel).
    """
    if decisions not in DECISIONS:
        raise InputError(f"decisions must be one of {', '.join(DECISIONS)}, got {decisions!r}")
    if spec.kind in MULTI_FRAME_KINDS and decisions != "auto":
        raise InputError(f"decisions {decisions!r} is for single-shot patterns; a {spec.kind} sequence is decoded "
                         f"pixel by pixel")
    return dict(DECISIONS[decisions])


@dataclass(frozen=True)
class ScanChoices:
    """How the command line scans a single-shot frame (`sliscan scan`, `sliscan report`,
    `sliscan live` and the batch `sliscan.batch.Job`).

    Attributes
    ----------
    decisions : str
        One of `DECISIONS` (`decision_options`).
    albedo_steps : bool
        Whether the window and baseband demodulators divide the capture by its sharp
        reflectance steps first (``Scanner.albedo`` ``"steps"``, the default) or by nothing
        (None: the faster scan for surfaces without sharp texture, docs/speed.md; the band-pass
        demodulator and multi-frame patterns divide by nothing either way).
    stripe_lines : bool
        Whether each pixel's projector line is interpolated between its stripe's located borders
        (``Scanner.interpolate_stripes``, the default: no staircase) or is its stripe's centre
        (the thesis's output).
    trim_edges : int
        Camera pixels trimmed off each end of every run along the carriers
        (``Scanner.trim_edges``; 0, the default, keeps them).
    camera_blur : float or None
        The camera's blur the albedo steps are found and blurred with (``Scanner.camera_blur``;
        None, the default, measured on each capture).
    """

    decisions: str = "auto"
    albedo_steps: bool = True
    stripe_lines: bool = True
    trim_edges: int = 0
    camera_blur: float | None = None

    def scanner_options(self, spec: PatternSpec) -> dict[str, Any]:
        """`Scanner` keyword arguments of these choices for `spec`.

        Raises
        ------
        InputError
            For an unknown or inapplicable `decisions`.
        """
        return dict(decode_options=decision_options(spec, self.decisions),
                    albedo="steps" if self.albedo_steps else None, interpolate_stripes=self.stripe_lines,
                    trim_edges=self.trim_edges, camera_blur=self.camera_blur)


@dataclass(frozen=True, eq=False)
class ScanStages:
    """What `Scanner.scan_stages` computed on the way to the points (for `sliscan.report`).

    Attributes
    ----------
    direction : {"rows", "columns"}
        The projector coordinate that was triangulated.
    demodulated : Demodulated or None
        Composite kinds: the carrier envelopes, DC and residuals (camera orientation).
    carriers : Carriers or None
        Composite kinds: the carriers found in the capture.
    decoded : Decoded or None
        Composite kinds: bit levels, lit mask, stripes before the 3D filters.
    maps : dict of str -> ProjectorMap, or None
        Multi-frame kinds: every coded projector coordinate (``{"rows": ..., "columns": ...}``).
    """

    direction: str
    demodulated: Demodulated | None = None
    carriers: Carriers | None = None
    decoded: Decoded | None = None
    maps: dict[str, ProjectorMap] | None = None


@dataclass
class Scanner:
    """A reusable scanner for one pattern and one calibrated rig.

    Parameters
    ----------
    spec : PatternSpec
        The projected pattern: a composite kind (one frame per scan) or a multi-frame kind
        (``pmp``, ``graycode``: a capture sequence per scan).  For orientation ``"both"`` the
        scan triangulates the direction of the rig's `baseline_direction` (rows on the thesis's
        rig, columns with the projector beside the camera); `sliscan.sequences.decode_frames`
        gives both projector coordinates; with projector lens distortion the other one
        undistorts the projector exactly (`sliscan.reconstruct.triangulate`).
    calibration : Calibration
        Camera and projector matrices; the capture must have the camera's size.
    method : {"window", "bandpass", "baseband"}
        Demodulator: `sliscan.demodulate`'s window (default) or band-pass, or the real-time
        path of `sliscan.fastscan` (``"baseband"``: decimated envelopes, then each pixel's
        stripe and point in one compiled pass; stripe patterns only, per-pixel decisions,
        `decode_options` limited to ``min_modulation``, ``min_confidence`` and
        ``stripe_borders``).  Its setup (`stripe_geometry`) measures every stripe's points
        once: about 2 s at 5 MP, on the first scan.
    decode_options : dict
        Keyword arguments for `sliscan.decode.decode` (thresholds), or for multi-frame kinds
        `sliscan.pmp.decode_pmp` / `sliscan.graycode.decode_graycode`.
    fringe_options : dict
        Patterns with a phase channel: keyword arguments for `sliscan.fringe.refine`.
    reuse_carriers : bool
        Detect the carriers in the first frame and reuse them for later frames.
    min_angle_deg : float
        Points whose camera and projector rays meet at less than this angle are dropped
        (`measurable`).
    remove_speckles : bool
        Drop small regions of the projector map that jump away from their neighbours (wrong
        codes: `sliscan.outliers.remove_speckles`, with `default_max_jump` and
        `default_min_region`).  On by default.
    remove_narrow_runs : bool
        Composite kinds: drop the runs narrower than the demodulation window that jump away
        from both sides along the carriers (wrong codes across a depth edge:
        `sliscan.outliers.remove_narrow_runs`, with `default_max_jump`).  On by default.
    remove_jump_edges : bool
        Multi-frame kinds: drop the pixels beside a jump of more than `default_max_jump` in the
        projector map, on both sides, and those beside a gap with another surface across it
        (the blur's mixed pixels along a depth edge: `sliscan.outliers.remove_jump_edges`).  On
        by default.  The composite kinds have their
        own (the narrow runs; with a phase channel, `sliscan.fringe.refine`'s ring beside its
        gaps), after which this one changed the phase pattern's scans not at all and cost the
        stripe patterns' right stripes 0.01-0.04 points for 0.1-0.3 % of RMS.
    remove_shadow_sides : bool
        Multi-frame kinds: drop the pixels at the ends of runs (along both image axes) whose
        light puts their centre on the shadow's side of a light edge (`sliscan.outliers.
        remove_shadow_sides`; the phase channel has its own in `sliscan.fringe.refine`).  On by
        default.
    interpolate_stripes : bool
        Methods ``window`` and ``bandpass``: each pixel's projector line interpolated between
        the located borders of its stripe instead of the stripe's centre
        (`sliscan.staircase.interpolate_lines`: removes the staircase); with a phase channel,
        the interpolated line where it agrees with the phase's (`sliscan.staircase.
        prefer_borders`).  On by default; false gives the stripe centres (the thesis's output),
        or the phase's lines.
    centred_borders : bool
        Method ``window``, with `interpolate_stripes`: where a border crosses the carriers
        obliquely, place it from the centred windows' envelopes as well (`sliscan.staircase.
        prefer_centred`: a second decoding and interpolation, run side by side with the first
        (`sliscan._threads.side_by_side`), about 0.4 s more at 5 MP on 2 cores;
        docs/accuracy.md, "Removing the staircase": medians 10-40 % lower on spheres and on
        surfaces turned about the phase direction).  On by default; false: the chosen windows'
        borders only.
    typical_slope : bool
        With `interpolate_stripes`, a pattern without a phase channel: a run with one border and
        no slope near it is extended from its border with the median slope of the frame's
        two-border runs instead of keeping its stripe's centre (`sliscan.staircase.
        interpolate_lines`; docs/accuracy.md, "Removing the staircase": RMS 0-32 % lower).  On
        by default; with a phase channel always off (the phase places those pixels better).
    lines_beside : bool
        With `interpolate_stripes`: a run with no border takes the mean line of its stripe's
        pixels beside it along the carriers (`sliscan.staircase.lines_beside`) instead of its
        stripe's centre (docs/accuracy.md, "Removing the staircase": RMS 0-7 % lower).  On by
        default; with a phase channel always off (the phase places those pixels; with it the
        phase pattern's RMS rose by up to 4 %).
    trim_edges : int
        Drop the points within this many camera pixels of either end of their run along the
        carriers (camera x for patterns coding rows, y for columns; a run ends at a depth or
        shadow edge, a gap or the frame's edge: `sliscan.outliers.remove_run_ends`), last of the
        3D filters: where a single-shot pattern's windows reach across the edge, most of the
        error left lies.  0 (default) keeps them.  Measured (docs/accuracy.md, "Points near
        run ends"): 10 px at 5 MP (about a ninth of the demodulation window) takes the phase
        pattern's RMS on the smooth sphere 2.48 -> 1.96 mm for 3.9 points of completeness, the
        thesis pattern's 14.5 -> 7.4 mm for 4.9.
    albedo : str or None
        Methods ``window`` and ``baseband``: the albedo estimate the capture is divided by
        before demodulation (`sliscan.demodulate.normalise_albedo`; ``"steps"``, the default,
        the sharp reflectance steps, which no demodulation window can fit, each albedo edge
        among them blurred as the camera blurs it on the window path of a stripe pattern;
        ``"sharp-steps"`` none blurred, as with a phase channel and on the baseband path:
        docs/accuracy.md, "Soft albedo edges"); None for none (the fastest baseband scan, for
        surfaces without sharp texture: docs/speed.md).  The baseband path divides by each
        line's flat field as well (`sliscan.baseband.normalise_lines`).
    camera_blur : float or None
        With the ``"steps"`` albedo estimates: the camera's blur (a Gaussian's sigma in camera
        pixels, the pixels' aperture included) the steps are tested for (an albedo edge is as
        sharp as the camera blurs it) and blurred with.  None (default): measured on each
        capture's tall albedo edges on the window path (`sliscan.edge_blur`; a 1 px camera
        measures 1.03-1.06, within `sliscan.demodulate.STEP_BLUR_BAND` of the 1 px assumed, so
        nothing changes; a blurrier one is found again with its own blur: docs/accuracy.md, "A
        camera blurrier than assumed"), 1 px on the baseband path.
    depth_levels : bool
        Patterns with a phase channel, window and band-pass methods: fit the phase carriers'
        gains as functions of depth (the Gray code's lines triangulated first: `inverse_depths`,
        `sliscan.fringe.refine`'s ``inverse_depth``), since a projector focused at one depth
        blurs its finest carriers more everywhere else.  Default True; False fits one gain per
        carrier (for the benchmark's record; docs/accuracy.md, "A lens's depth of field").

    Examples
    --------
    >>> from sliscan import simulate, patterns
    >>> rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768))
    >>> spec = patterns.default_spec((1024, 768))
    >>> capture = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec),
    ...                           simulate.Conditions(seed=1))
    >>> result = Scanner(spec, rig.calibration).scan(capture.image)
    >>> bool(abs(np.nanmedian(result.points[..., 2]) - 800) < 20)
    True
    """

    spec: PatternSpec
    calibration: Calibration
    method: str = "window"
    decode_options: dict[str, Any] = field(default_factory=dict)
    fringe_options: dict[str, Any] = field(default_factory=dict)
    reuse_carriers: bool = False
    min_angle_deg: float = 2.0
    remove_speckles: bool = True
    remove_narrow_runs: bool = True
    remove_jump_edges: bool = True
    remove_shadow_sides: bool = True
    interpolate_stripes: bool = True
    centred_borders: bool = True
    typical_slope: bool = True
    lines_beside: bool = True
    trim_edges: int = 0
    albedo: str | None = "steps"
    camera_blur: float | None = None
    depth_levels: bool = True
    _carriers: Carriers | None = field(default=None, init=False, repr=False)
    _triangulators: dict[str, Triangulator] = field(default_factory=dict, init=False, repr=False)
    _tests: dict[tuple[str, float], MeasurableTest] = field(default_factory=dict, init=False, repr=False)
    _plan: tuple[Carriers, BasebandPlan] | None = field(default=None, init=False, repr=False)
    _geometry: fastscan.StripeGeometry | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not (isinstance(self.trim_edges, (int, np.integer)) and self.trim_edges >= 0):
            raise InputError(f"trim_edges must be a whole number of pixels >= 0, got {self.trim_edges!r}")
        if self.albedo is not None and self.albedo not in ALBEDO_ESTIMATES:
            raise InputError(f"albedo must be one of {', '.join(ALBEDO_ESTIMATES)} or None, got {self.albedo!r}")
        if self.camera_blur is not None and (isinstance(self.camera_blur, bool)
                                             or not (isinstance(self.camera_blur, (int, float)) and self.camera_blur > 0)):
            raise InputError(f"camera_blur must be a positive number of pixels or None, got {self.camera_blur!r}")
        if self.method == "baseband" and self.spec.kind not in MULTI_FRAME_KINDS:
            if self.spec.phase_carriers:
                raise InputError("method 'baseband' decodes stripes only; a pattern with a phase channel needs the "
                                 "'window' method")
            unknown = set(self.decode_options) - {"min_modulation", "min_confidence", "stripe_borders", "zero_code_dc",
                                                  "order"}
            if unknown or self.decode_options.get("order"):
                raise InputError(f"method 'baseband' decides each pixel on its own and takes only min_modulation, "
                                 f"min_confidence, stripe_borders and zero_code_dc, got {sorted(self.decode_options)}")
        if tuple(self.calibration.projector.size) != tuple(self.spec.projector_size):
            w, h = self.calibration.projector.size
            pw, ph = self.spec.projector_size
            raise InputError(f"pattern is for a {pw}x{ph} projector but the calibration's projector is {w}x{h}")

    def demodulate(self, image: ArrayLike) -> tuple[Demodulated, Carriers]:
        """Carrier envelopes of one frame (checked against the camera size); for ``baseband``
        interpolated to every pixel (`Baseband.demodulated`)."""
        if self.method == "baseband":
            baseband, carriers = self.demodulate_baseband(image)
            return self._interpolated(baseband), carriers
        img = check_image("capture", image, shape=self.calibration.camera.shape)
        demod, found = demodulate(img, self.spec, method=self.method, carriers=self._known_carriers(),
                                  albedo=self.albedo, centred=self.interpolate_stripes and self.centred_borders
                                  and self.method == "window", camera_blur=self.camera_blur)
        self._keep_carriers(found)
        return demod, found

    def _interpolated(self, baseband: Baseband) -> Demodulated:
        """`Baseband.demodulated` at every camera pixel, in camera orientation."""
        demod = baseband.demodulated(self.calibration.camera.shape[1 if self.spec.orientation == "rows" else 0])
        if self.spec.orientation == "rows":
            return demod
        return demod.mapped(lambda a: np.ascontiguousarray(np.swapaxes(a, -1, -2)))

    def _known_carriers(self) -> Carriers | None:
        return self._carriers if self.reuse_carriers else None

    def _keep_carriers(self, found: Carriers) -> None:
        if self.reuse_carriers:
            self._carriers = found

    def demodulate_baseband(self, image: ArrayLike) -> tuple[Baseband, Carriers]:
        """`sliscan.baseband.demodulate_baseband` of one frame (checked against the camera size
        and its exposure), with the plan of its carriers (kept while they stay the same)."""
        img = check_image("capture", image, shape=self.calibration.camera.shape, copy=False)  # only read
        check_exposure(img)
        carriers = self._known_carriers() or detect_carriers(img, self.spec)
        self._keep_carriers(carriers)
        view = along_carriers(img, self.spec)
        if self._plan is None or self._plan[0] is not carriers:
            self._plan = carriers, BasebandPlan.of(*view.shape, carriers)
        gain = None
        if self.albedo is not None:
            view, gain = normalise_lines(view, carriers, estimate=self.albedo, camera_blur=self.camera_blur)
        return demodulate_baseband(view, self._plan[1], albedo=gain), carriers

    def phase_direction(self) -> int:
        """Whether the stripe numbers grow (+1) or fall (-1) down the camera's lines along the
        phase direction, from the rig (`sliscan.stripe_order.rig_direction`): what `decode`
        decides the stripes by order with."""
        return rig_direction(self.calibration, self.spec)

    def stripe_geometry(self) -> fastscan.StripeGeometry:
        """The rig's `sliscan.fastscan.StripeGeometry` for the pattern, built on first use and kept."""
        if self._geometry is None:
            direction = self.spec.orientation
            self._geometry = fastscan.StripeGeometry.of(self.triangulator(direction), self.measurable_test(direction),
                                                        self.spec)
        return self._geometry

    def scan(self, image: ArrayLike, out: ScanResult | None = None) -> ScanResult:
        """Point cloud of one camera frame of the composite pattern, or of one capture sequence
        of a multi-frame pattern.

        Parameters
        ----------
        image : (H, W) array, or for ``pmp`` / ``graycode`` ``spec.frame_count`` of them
            uint8, uint16 or float in [0, 1], of the calibrated camera's size, frames in the
            spec's order (a sequence or a ``(K, H, W)`` array); not modified.
        out : ScanResult, optional
            Method ``baseband`` only: an earlier result of this camera size whose arrays this
            scan overwrites (and returns, with its own timings), as a frame-after-frame loop
            does once it is done with a frame.  New memory costs its first write: at 5 MP the
            ~135 MB of outputs take ~20 ms more to fill fresh than reused (docs/speed.md).

        Returns
        -------
        ScanResult
            For multi-frame kinds `stripe` holds the fringe order (PMP) or the Gray code index,
            `confidence` the fringe visibility or the Gray code contrast, `texture` the DC or
            the white frame.

        Raises
        ------
        InputError
            If a frame is not of the camera's size, or a sequence has the wrong number of frames,
            or `out` is given to another method or does not fit.
        """
        if self.method == "baseband" and self.spec.kind not in MULTI_FRAME_KINDS:
            return self._scan_baseband(image, out)[0]
        if out is not None:
            raise InputError(f"out= needs method 'baseband' and a single-frame pattern, not {self.method!r} "
                             f"with a {self.spec.kind!r} pattern")
        return self.scan_stages(image)[0]

    def scan_stages(self, image: ArrayLike) -> tuple[ScanResult, ScanStages]:
        """`scan`, also returning the intermediate products it computed anyway (envelopes,
        carriers, bit levels; the projector maps of a sequence), e.g. for a report.

        Costs nothing over `scan` but the memory of keeping them.
        """
        if self.spec.kind in MULTI_FRAME_KINDS:
            return self._scan_sequence(image)
        if self.method == "baseband":
            result, baseband, carriers = self._scan_baseband(image)
            demod = self._interpolated(baseband)
            options = dict(self.decode_options, order=False, border_reach=0, neighbour_radius=0)
            return result, ScanStages(self.spec.orientation, demodulated=demod, carriers=carriers,
                                      decoded=decode(demod, self.spec, **options))
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        demod, carriers = self.demodulate(image)
        t1 = time.perf_counter()
        stripe_px = self.spec.phase_lines / self.spec.stripes / carriers.scale

        def decoded_lines(envelopes: Demodulated) -> tuple[Decoded, Decoded | None]:
            """One set of envelopes decoded, and its lines between the located stripe borders."""
            found = decode(envelopes, self.spec, **{"direction": self.phase_direction(), **self.decode_options})
            if not self.interpolate_stripes:
                return found, None
            stripes_only = not self.spec.phase_carriers  # else the phase places the runs without two borders
            return found, interpolate_lines(found, self.spec, stripe_px=stripe_px, offset=envelopes.offset,
                                            window=carriers.window, typical_slope=self.typical_slope and stripes_only,
                                            beside_reach=BESIDE_REACH if self.lines_beside and stripes_only else 0)

        # the chosen windows' decoding and the centred ones' are independent: side by side
        sources = [demod] if demod.centred is None else [demod, demod.centred]
        (stripes, lines), *centred = side_by_side([functools.partial(decoded_lines, s) for s in sources])
        if lines is not None and centred:
            lines = prefer_centred(lines, centred[0][1], demod.centred.offset, self.spec, stripe_px=stripe_px,
                                   window=carriers.window)
        del centred  # its decoding's frames, before the phase channel's
        inverse_depth = None
        if self.spec.phase_carriers and self.depth_levels:
            coarse = stripes if lines is None else lines
            inverse_depth = inverse_depths(self.triangulator(self.spec.orientation)(coarse.proj_map, coarse.valid),
                                           self.calibration.projector.matrix)
        decoded = fringe.refine(stripes, demod, carriers, self.spec, image=image, inverse_depth=inverse_depth,
                                border_line=None if lines is None else lines.proj_map, **self.fringe_options)
        if lines is not None:
            decoded = prefer_borders(decoded, lines.proj_map, self.spec) if self.spec.phase_carriers else lines
        t2 = time.perf_counter()
        points, valid = self._measured(decoded.proj_map, decoded.valid, self.spec.orientation, carriers.window)
        proj_map, stripe = _finish(points, valid, decoded.proj_map, decoded.stripe)
        t3 = time.perf_counter()
        timings.update(demodulate=t1 - t0, decode=t2 - t1, triangulate=t3 - t2, total=t3 - t0)
        result = ScanResult(points=points, valid=valid, texture=texture_from_dc(demod.dc), proj_map=proj_map,
                            stripe=stripe, confidence=decoded.confidence, timings=timings)
        return result, ScanStages(self.spec.orientation, demodulated=demod, carriers=carriers, decoded=decoded)

    def triangulator(self, orientation: str) -> Triangulator:
        """The rig's `Triangulator` for one orientation, built on first use and kept."""
        if orientation not in self._triangulators:
            self._triangulators[orientation] = Triangulator(self.calibration, orientation)
        return self._triangulators[orientation]

    def measurable_test(self, direction: str) -> MeasurableTest:
        """The rig's `MeasurableTest` for one coded direction and `min_angle_deg` (`measurable`),
        built on first use and kept."""
        key = direction, self.min_angle_deg
        if key not in self._tests:
            self._tests[key] = MeasurableTest.of(self.calibration, direction, self.min_angle_deg)
        return self._tests[key]

    def _measured(self, proj_map: NDArray[np.floating], valid: NDArray[np.bool_], direction: str,
                  window: int | None = None, other: NDArray[np.floating] | None = None,
                  light: NDArray[np.floating] | None = None) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """World points ``(H, W, 3)`` float32 of `proj_map` (the projector coordinate along
        `direction`, "rows" or "columns"; `other`: the other one, if decoded) and the mask of
        the ones kept, NaN but there: `valid` less the points that are not measurements
        (`measurable`: outside the projector's light, seen at under `min_angle_deg`) or wrong
        codes: with `remove_narrow_runs`, runs narrower than the demodulation `window` (camera
        pixels; composite kinds) across a depth edge; with `remove_speckles`, small regions
        that jump away from their neighbours; for multi-frame kinds, with `remove_jump_edges`
        the pixels beside a jump or a gap to another surface, with `remove_shadow_sides` and
        `light` (each pixel's light) those on a shadow's side of a light edge; with `trim_edges`
        the points near their run's ends.  The points the filters drop are set to NaN by
        `_finish`."""
        points, valid = self.triangulator(direction).measure(proj_map, valid, self.measurable_test(direction),
                                                             other=other)
        return points, self._filtered(proj_map, valid, direction, window, light)

    def _filtered(self, proj_map: NDArray[np.floating], valid: NDArray[np.bool_], direction: str,
                  window: int | None, light: NDArray[np.floating] | None = None) -> NDArray[np.bool_]:
        """`valid` less what the 3D filters of `_measured` drop."""
        max_jump = default_max_jump(self.spec, direction)

        def despeckle(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
            if not self.remove_speckles:
                return mask
            return remove_speckles(proj_map, mask, lines=self.spec.lines(direction), max_jump=max_jump)

        valid = despeckle(valid)
        if self.remove_narrow_runs and window is not None:
            # speckles first (cutting runs out of small fragments would only cost surface), then
            # the runs, then speckles again: a run cut away may have joined a wrong patch to a surface
            narrowed = remove_narrow_runs(proj_map, valid, max_jump=max_jump, window=window,
                                          axis=1 if direction == "rows" else 0)
            valid = despeckle(narrowed) if (narrowed != valid).any() else valid
        if self.spec.kind in MULTI_FRAME_KINDS:
            if self.remove_jump_edges:
                valid = remove_jump_edges(proj_map, valid, max_jump=max_jump)
            if self.remove_shadow_sides and light is not None:
                valid = remove_shadow_sides(proj_map, valid, light, max_jump=max_jump)
        if self.trim_edges:
            valid = remove_run_ends(proj_map, valid, margin=self.trim_edges, max_jump=max_jump,
                                    axis=1 if direction == "rows" else 0)
        return valid

    def _scan_baseband(self, image: ArrayLike, out: ScanResult | None = None) -> tuple[ScanResult, Baseband, Carriers]:
        """`scan` with method ``baseband`` (`sliscan.fastscan`) into `out` if given, then the 3D
        filters that are on; also the baseband envelopes and the carriers."""
        t0 = time.perf_counter()
        baseband, carriers = self.demodulate_baseband(image)
        t1 = time.perf_counter()
        options = {k: v for k, v in self.decode_options.items() if k != "order"}
        levels = fastscan.frame_levels(baseband, self.spec, **{k: v for k, v in options.items()
                                                                if k == "min_modulation"})
        t2 = time.perf_counter()
        result = fastscan.scan_baseband(baseband, levels, self.spec, self.stripe_geometry(),
                                        self.calibration.camera.shape, out=out, **options)
        valid = self._filtered(result.proj_map, result.valid, self.spec.orientation, carriers.window)
        if valid is not result.valid:
            result.valid[...] = valid
            _finish(result.points, result.valid, result.proj_map, result.stripe, in_place=True)
        t3 = time.perf_counter()
        # the stripes and the points come from one pass: "triangulate" times it, with the filters
        result.timings.update(demodulate=t1 - t0, decode=t2 - t1, triangulate=t3 - t2, total=t3 - t0)
        return result, baseband, carriers

    def _scan_sequence(self, frames: ArrayLike) -> tuple[ScanResult, ScanStages]:
        """`scan_stages` of a multi-frame capture: decode every coded direction, triangulate one."""
        t0 = time.perf_counter()
        maps = decode_frames(frames, self.spec, shape=self.calibration.camera.shape, **self.decode_options)
        direction = baseline_direction(self.calibration) if self.spec.orientation == "both" else self.spec.orientation
        decoded = maps[direction]
        # Orientation "both": the other coordinate lets a distorted projector be undistorted exactly.
        other = next((m.coord for d, m in maps.items() if d != direction), None)
        t1 = time.perf_counter()
        points, valid = self._measured(decoded.coord, decoded.valid, direction, other=other, light=decoded.brightness)
        proj_map, stripe = _finish(points, valid, decoded.coord, decoded.index)
        t2 = time.perf_counter()
        result = ScanResult(points=points, valid=valid, texture=texture_from_dc(decoded.brightness),
                            proj_map=proj_map, stripe=stripe, confidence=decoded.confidence,
                            timings={"decode": t1 - t0, "triangulate": t2 - t1, "total": t2 - t0})
        return result, ScanStages(direction, maps=maps)


def scan(image: ArrayLike, spec: PatternSpec, calibration: Calibration, **options: Any) -> ScanResult:
    """Scan one frame: ``Scanner(spec, calibration, **options).scan(image)``."""
    return Scanner(spec, calibration, **options).scan(image)
