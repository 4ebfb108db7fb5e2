"""The small frozen records that travel between stages.

`PatternSpec` says what was projected, `Calibration` how the camera and the projector see the
world, and `ScanResult` what a scan produced.  Conventions (DESIGN.md): images are ``(H, W)``,
pixel centres at integers, world coordinates in millimetres, ``(W, H)`` only at file and CLI
boundaries.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sliscan._validate import InputError, atomic_write_text, check_finite_matrix, check_size
from sliscan.lens import distort, has_distortion

#: The pattern kinds this version knows: single-frame composite kinds, then multi-frame ones.
COMPOSITE_KINDS = ("composite", "carrier_only", "modified_composite")
MULTI_FRAME_KINDS = ("pmp", "graycode")
PATTERN_KINDS = COMPOSITE_KINDS + MULTI_FRAME_KINDS
#: Projector coordinates a pattern can code (and triangulation can use).
ORIENTATIONS = ("rows", "columns")
#: Multi-frame kinds may also code both, columns first (OpenCV's order).
SEQUENCE_ORIENTATIONS = ORIENTATIONS + ("both",)
#: Fields only the composite kinds use, and fields only the multi-frame kinds use: each kind's
#: JSON leaves out the other group (they keep their defaults).
_COMPOSITE_FIELDS = ("bits", "carriers", "weights", "phase_carriers", "phase_period", "phase_weight", "pilot",
                     "pilot_weight", "skip_zero_code", "modified_frequency", "modified_amplitude", "image")
_MULTI_FRAME_FIELDS = ("steps", "frequencies", "code_width", "frames")
#: Scalar fields that must be finite numbers in every kind.
_NUMBER_FIELDS = ("a_p", "b_p", "gamma", "phase_period", "phase_weight", "pilot_weight", "modified_frequency",
                  "modified_amplitude")


def _is_finite_number(value: object) -> bool:
    """A finite int or float (not a bool, not a string)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class PatternSpec:
    """Everything needed to generate a pattern and to decode a capture of it.

    Attributes
    ----------
    kind : str
        ``"composite"`` (thesis eq. 3.1), ``"carrier_only"`` (fig. 3.9: every carrier on
        everywhere), or ``"modified_composite"`` (section 6.2: composite plus a sine along the
        phase direction); multi-frame: ``"pmp"`` (N-step phase shifting at one or more
        frequencies, eq. 2.1; `sliscan.pmp`) or ``"graycode"`` (pattern/inverse pairs in OpenCV's
        order, optionally with phase shifting; `sliscan.graycode`).
    projector_size : (W, H) tuple of int
        Projector resolution in pixels.
    bits : int
        Number of Gray code bits; the pattern has ``2**bits`` stripes (``2**bits - 1`` with
        `skip_zero_code`).  Bit 0 is the most significant (the coarsest stripes).
    carriers : tuple of float
        One carrier frequency per bit, in cycles per projector width (along the orthogonal
        direction), bit 0 first.
    weights : tuple of float
        Amplitude weight of each carrier (roll-off pre-compensation, fig. 3.13), same length
        as `carriers`; the pilot carrier, if any, has weight `pilot_weight`.
    phase_carriers : tuple of float
        The phase channel (issue 8; the PMP composite pattern of the thesis's lab): ``N >= 3``
        more carriers (cycles per projector width), carrier ``n`` modulated along the phase
        direction by the fringe ``(1 + cos(2 pi (line + 0.5) / phase_period - 2 pi n / N)) / 2``,
        so the envelopes of the N carriers are N phase-shifted samples of one fringe: its phase
        places a pixel inside a fringe period, and the Gray code stripe says which period.
        Empty (default): no phase channel, the pattern codes stripes only.
    phase_period : float
        Projector lines per fringe period along the phase direction; 0 (default) means two
        stripes (`fringe_period`), the shortest period whose unwrapping tolerates a Gray code
        decision off by a quarter period.  Must exceed one stripe.
    phase_weight : float
        Amplitude weight of each phase carrier, in the units of `weights`.
    a_p, b_p : float
        Projection constants of eq. 3.1: ``I = a_p + b_p * sum_n w_n I_n cos(2 pi f_n x)``,
        in [0, 1] units of full projector drive.
    gamma : float
        Gamma pre-correction applied to the pattern (``I ** (1 / gamma)``); 1 means none.
    response : tuple of float or None
        Measured projector response (`sliscan.photometry`): linear light, normalised to 0 at
        drive 0 and 1 at full drive, at evenly spaced drive levels from 0 to 1 (strictly
        increasing).  When given, the pattern is pre-corrected with its inverse instead of
        `gamma` (which must then be 1).  None: no measured response.
    orientation : str
        ``"rows"`` (default, DESIGN.md): stripes are horizontal bands that code the projector
        row `yp`, carriers run along `x`.  ``"columns"``: stripes code `xp`, carriers along `y`.
        ``"both"`` (multi-frame kinds only): the columns' frames, then the rows'.
    pilot : float or None
        Frequency (cycles per projector width) of a reference carrier that is on everywhere
        the projector lights; it tells a lit all-zero code from shadow and normalises every bit
        envelope.  None: no pilot (the thesis's pattern).
    pilot_weight : float
        Amplitude weight of the pilot carrier.
    skip_zero_code : bool
        If true, stripe ``k`` carries the Gray code of ``k + 1`` so the all-zero code (no
        carrier at all, indistinguishable from shadow in one frame) is never projected.
    modified_frequency : float
        Frequency of the sine along the phase direction of the modified composite pattern,
        in cycles per projector height (section 6.2 uses 15); used only by that kind.
    modified_amplitude : float
        Amplitude of that sine, in the same units as `b_p`.
    image : str or None
        File name of the pattern image, relative to the JSON file.
    steps : int
        Phase steps N per frequency (``pmp``: N >= 3); for ``graycode`` the steps of the
        phase-shifted fringes that refine each Gray code (0: none, else N >= 3).
    frequencies : tuple of float
        ``pmp`` fringe frequencies in cycles per projector extent along the coded direction
        (H for rows, W for columns), increasing.  Hierarchical unwrapping: the first is 1 (one
        fringe over the projector: unambiguous), each next one unwrapped by the previous, e.g.
        ``(1, 8, 64)``; ``(1, f)`` is the dual-frequency case.  Heterodyne start: if the first
        is not 1 the first two must differ by exactly 1 (their beat is the unit frequency),
        e.g. ``(15, 16)``.
    code_width : int
        ``graycode``: projector lines per Gray code, a power of two (1: one code per line,
        OpenCV's sequence); with `steps` the phase-shifted fringes have a period of two codes.
    frames : tuple of str
        Multi-frame kinds: the image files, relative to the JSON file, in projection order
        (empty: not written to files); `frame_count` of them.
    """

    kind: str = "composite"
    projector_size: tuple[int, int] = (1024, 768)
    bits: int = 4
    carriers: tuple[float, ...] = (32.0, 64.0, 96.0, 128.0)
    weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    a_p: float = 0.5
    b_p: float = 0.125
    gamma: float = 1.0
    response: tuple[float, ...] | None = None
    orientation: str = "rows"
    phase_carriers: tuple[float, ...] = ()
    phase_period: float = 0.0
    phase_weight: float = 1.0
    pilot: float | None = None
    pilot_weight: float = 1.0
    skip_zero_code: bool = False
    modified_frequency: float = 15.0
    modified_amplitude: float = 0.0
    image: str | None = None
    steps: int = 0
    frequencies: tuple[float, ...] = ()
    code_width: int = 1
    frames: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "projector_size", check_size("projector_size", self.projector_size, minimum=8))
        except InputError as exc:
            raise InputError(f"invalid pattern spec: {exc}") from None
        object.__setattr__(self, "carriers", tuple(float(v) for v in self.carriers))
        object.__setattr__(self, "weights", tuple(float(v) for v in self.weights))
        object.__setattr__(self, "phase_carriers", tuple(float(v) for v in self.phase_carriers))
        object.__setattr__(self, "frequencies", tuple(float(v) for v in self.frequencies))
        if isinstance(self.frames, str):
            raise InputError("invalid pattern spec: frames must be a list of file names")
        object.__setattr__(self, "frames", tuple(str(v) for v in self.frames))
        if self.response is not None:
            object.__setattr__(self, "response", tuple(float(v) for v in self.response))
        problems = self._problems()
        if problems:
            raise InputError(f"invalid pattern spec: {problems[0]}")

    def _problems(self) -> list[str]:
        out = []
        if self.kind not in PATTERN_KINDS:
            return [f"kind must be one of {PATTERN_KINDS}, got {self.kind!r}"]
        for name in _NUMBER_FIELDS:
            if not _is_finite_number(getattr(self, name)):
                return [f"{name} must be a finite number, got {getattr(self, name)!r}"]
        if not (self.image is None or isinstance(self.image, str)):
            return [f"image must be a file name, got {self.image!r}"]
        out += self._sequence_problems() if self.kind in MULTI_FRAME_KINDS else self._composite_problems()
        if not (self.gamma > 0 and math.isfinite(self.gamma)):
            out.append(f"gamma must be positive, got {self.gamma}")
        if self.response is not None:
            r = np.asarray(self.response)
            if r.size < 2 or not np.all(np.isfinite(r)) or r[0] != 0 or r[-1] != 1 or np.any(np.diff(r) <= 0):
                out.append("response must rise strictly from 0 to 1 over at least 2 evenly spaced drive levels")
            elif self.gamma != 1:
                out.append(f"give gamma or response, not both (gamma {self.gamma:g} with a measured response)")
        return out

    def _composite_problems(self) -> list[str]:
        """What is wrong with the fields of a single-frame composite kind."""
        out = []
        w, h = self.projector_size
        if self.frames:
            out.append(f"frames are for the multi-frame kinds {MULTI_FRAME_KINDS}, not {self.kind!r}")
        if not isinstance(self.skip_zero_code, bool):
            return [f"skip_zero_code must be true or false, got {self.skip_zero_code!r}"]
        if isinstance(self.bits, bool) or not isinstance(self.bits, int):
            return [f"bits must be an integer, got {self.bits!r}"]
        if not all(math.isfinite(v) for v in self.weights):
            return [f"weights must be finite numbers, got {list(self.weights)}"]
        if not (self.pilot is None or _is_finite_number(self.pilot)):
            return [f"pilot must be a finite number or null, got {self.pilot!r}"]
        if not 1 <= self.bits <= 16:
            out.append(f"bits must be in 1..16, got {self.bits}")
        if len(self.carriers) != self.bits:
            out.append(f"need one carrier per bit ({self.bits}), got {len(self.carriers)}")
        if len(self.weights) != len(self.carriers):
            out.append(f"need one weight per carrier ({len(self.carriers)}), got {len(self.weights)}")
        if self.phase_carriers and len(self.phase_carriers) < 3:
            out.append(f"a phase channel needs at least 3 phase carriers (0: none), got {len(self.phase_carriers)}")
        stripe_lines = (h if self.orientation == "rows" else w) / max(self.stripes, 1)
        if self.phase_period != 0 and not self.phase_period > stripe_lines:
            out.append(f"phase_period must exceed one stripe ({stripe_lines:g} lines), got {self.phase_period:g}")
        allc = self.all_carriers
        nyquist = (w if self.orientation == "rows" else h) / 2
        if any(not (0 < f < nyquist) for f in allc):
            out.append(f"carriers must lie in (0, {nyquist:g}) cycles per projector width, got {list(allc)}")
        if len(set(allc)) != len(allc):
            out.append(f"carriers must be distinct, got {list(allc)}")
        if self.orientation not in ORIENTATIONS:
            out.append(f"orientation must be one of {ORIENTATIONS}, got {self.orientation!r}")
        if self.stripes > (h if self.orientation == "rows" else w):
            out.append(f"{self.stripes} stripes do not fit in {h if self.orientation == 'rows' else w} projector lines")
        return out

    def _sequence_problems(self) -> list[str]:
        """What is wrong with the fields of a multi-frame kind (``pmp``, ``graycode``)."""
        if self.orientation not in SEQUENCE_ORIENTATIONS:
            return [f"orientation must be one of {SEQUENCE_ORIENTATIONS}, got {self.orientation!r}"]
        for name in ("steps", "code_width"):
            if isinstance(getattr(self, name), bool) or not isinstance(getattr(self, name), int):
                return [f"{name} must be an integer, got {getattr(self, name)!r}"]
        shortest = min(self.lines(d) for d in self.directions)
        out = self._pmp_problems(shortest) if self.kind == "pmp" else self._graycode_problems(shortest)
        if (self.kind == "pmp" or self.steps) and not (0 < self.b_p and 0 <= self.a_p - self.b_p
                                                       and self.a_p + self.b_p <= 1):
            out.append(f"fringes a_p +/- b_p must lie in [0, 1] with b_p > 0, got a_p {self.a_p:g}, b_p {self.b_p:g}")
        if self.frames and len(self.frames) != self.frame_count:
            out.append(f"frames must list {self.frame_count} files, got {len(self.frames)}")
        return out

    def _pmp_problems(self, lines: int) -> list[str]:
        f = self.frequencies
        if self.steps < 3:
            return [f"pmp needs steps >= 3, got {self.steps}"]
        if not f or not all(math.isfinite(v) for v in f) or any(b <= a for a, b in zip(f, f[1:])):
            return [f"pmp frequencies must be finite and increasing, got {list(f)}"]
        if not (0 < f[0] and f[-1] < lines / 2):
            return [f"pmp frequencies must lie in (0, {lines / 2:g}) cycles per projector extent, got {list(f)}"]
        if f[0] != 1 and not (len(f) >= 2 and f[1] - f[0] == 1):
            return [f"pmp frequencies must start at 1 (or with two differing by 1, a heterodyne pair), got {list(f)}"]
        return []

    def _graycode_problems(self, lines: int) -> list[str]:
        w = self.code_width
        if not (w >= 1 and w & (w - 1) == 0 and 2 * w <= lines):
            return [f"code_width must be a power of two up to {lines // 2} (half the projector), got {w}"]
        if self.steps and (self.steps < 3 or w < 2):
            return [f"graycode phase steps need steps >= 3 (0: none) and code_width >= 2, got {self.steps} and {w}"]
        return []

    @property
    def directions(self) -> tuple[str, ...]:
        """Projector coordinates coded, in projection order: ``("columns", "rows")`` for ``"both"``."""
        return ("columns", "rows") if self.orientation == "both" else (self.orientation,)

    def lines(self, direction: str) -> int:
        """Projector lines along a coded direction: W for ``"columns"``, H for ``"rows"``."""
        w, h = self.projector_size
        return w if direction == "columns" else h

    def gray_bits(self, direction: str) -> int:
        """``graycode``: Gray code bits that number the codes of `code_width` lines along `direction`.

        >>> PatternSpec(kind="graycode", orientation="both").gray_bits("rows")   # 768 rows
        10
        """
        return (math.ceil(self.lines(direction) / self.code_width) - 1).bit_length()

    @property
    def frame_count(self) -> int:
        """Frames a capture of this pattern has: 1 for the composite kinds; ``steps`` per
        frequency and direction for ``pmp``; a pattern/inverse pair per Gray code bit and
        direction, white, black and ``steps`` per direction for ``graycode``.

        >>> PatternSpec(kind="graycode", projector_size=(1024, 768), orientation="both").frame_count
        42
        """
        if self.kind == "pmp":
            return len(self.directions) * self.steps * len(self.frequencies)
        if self.kind == "graycode":
            return sum(2 * self.gray_bits(d) + self.steps for d in self.directions) + 2
        return 1

    @property
    def all_carriers(self) -> tuple[float, ...]:
        """Bit carriers, then the phase carriers, then the pilot carrier, if any (cycles per
        projector width)."""
        return self.carriers + self.phase_carriers + ((float(self.pilot),) if self.pilot is not None else ())

    @property
    def all_weights(self) -> tuple[float, ...]:
        """Weights parallel to `all_carriers`."""
        return (self.weights + (float(self.phase_weight),) * len(self.phase_carriers)
                + ((float(self.pilot_weight),) if self.pilot is not None else ()))

    @property
    def pilot_index(self) -> int | None:
        """Index of the pilot carrier in `all_carriers`, None without one."""
        return None if self.pilot is None else self.bits + len(self.phase_carriers)

    @property
    def fringe_period(self) -> float:
        """Projector lines per period of the phase channel's fringe (`phase_period`, or two
        stripes when that is 0).

        >>> PatternSpec(phase_carriers=(160, 192, 224)).fringe_period   # 768 rows, 16 stripes
        96.0
        """
        return self.phase_period or 2.0 * self.phase_lines / self.stripes

    @property
    def stripes(self) -> int:
        """Number of distinct stripes (codes actually projected)."""
        return 2**self.bits - (1 if self.skip_zero_code else 0)

    @property
    def phase_lines(self) -> int:
        """Projector lines along the phase direction (H for rows, W for columns)."""
        w, h = self.projector_size
        return h if self.orientation == "rows" else w

    @property
    def orthogonal_lines(self) -> int:
        """Projector lines along the carrier direction (W for rows, H for columns)."""
        w, h = self.projector_size
        return w if self.orientation == "rows" else h

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of this spec; fields the kind does not use are left out (defaults)."""
        unused = _COMPOSITE_FIELDS if self.kind in MULTI_FRAME_KINDS else _MULTI_FRAME_FIELDS
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items() if k not in unused}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "pattern spec") -> PatternSpec:
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"{source}: unknown keys {unknown}")
        try:
            return cls(**d)
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"{source}: {exc}") from None

    def save(self, path: str | os.PathLike) -> None:
        """Write the spec as JSON (atomically)."""
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> PatternSpec:
        """Read a spec written by `save`; raises `InputError` naming the file."""
        d = _load_json(path)
        return cls.from_dict(d, source=str(path))

    def with_(self, **changes: Any) -> PatternSpec:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Device:
    """One pinhole device (camera or projector): ``x ~ matrix @ [Xw, Yw, Zw, 1]``.

    Attributes
    ----------
    matrix : (3, 4) float64 array
        World (mm) -> pixel projection matrix, defined up to scale.
    size : (W, H) tuple of int
        Image size in pixels.
    intrinsics : (3, 3) float64 array or None
        K, when known; then ``matrix = K [R | t]``.
    distortion : (5,) float64 array or None
        OpenCV lens distortion ``k1, k2, p1, p2, k3`` (goes with `intrinsics`).
    """

    matrix: NDArray[np.float64]
    size: tuple[int, int]
    intrinsics: NDArray[np.float64] | None = None
    distortion: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "matrix", check_finite_matrix("matrix", self.matrix, (3, 4)))
        object.__setattr__(self, "size", check_size("size", self.size))
        if self.intrinsics is not None:
            object.__setattr__(self, "intrinsics", check_finite_matrix("intrinsics", self.intrinsics, (3, 3)))
        if self.distortion is not None:
            object.__setattr__(self, "distortion", check_finite_matrix("distortion", np.ravel(self.distortion), (5,)))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the device's images."""
        return (self.size[1], self.size[0])

    def project(self, xyz_w: NDArray[np.floating]) -> NDArray[np.float64]:
        """Pixel coordinates ``(..., 2)`` (x, y) of world points ``(..., 3)`` in mm: the pinhole
        `matrix`, then, if the device has distortion coefficients, the lens model
        (`sliscan.lens.distort`): the pixel the device really sees the point at.

        Raises
        ------
        InputError
            If the device has distortion coefficients but no intrinsics.
        """
        xyz_w = np.asarray(xyz_w, dtype=np.float64)
        h = xyz_w @ self.matrix[:, :3].T + self.matrix[:, 3]
        xy = h[..., :2] / h[..., 2:3]
        if not has_distortion(self.distortion):
            return xy
        if self.intrinsics is None:
            raise InputError("a device with lens distortion needs its intrinsics (K) to project")
        return distort(xy, self.intrinsics, self.distortion)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"matrix": self.matrix.tolist(), "size": list(self.size)}
        if self.intrinsics is not None:
            d["intrinsics"] = self.intrinsics.tolist()
        if self.distortion is not None:
            d["distortion"] = self.distortion.tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str) -> Device:
        if not isinstance(d, dict) or "matrix" not in d or "size" not in d:
            raise InputError(f"{source}: a device needs 'matrix' and 'size'")
        try:
            return cls(
                matrix=np.asarray(d["matrix"], dtype=np.float64),
                size=tuple(d["size"]),
                intrinsics=None if d.get("intrinsics") is None else np.asarray(d["intrinsics"], dtype=np.float64),
                distortion=None if d.get("distortion") is None else np.asarray(d["distortion"], dtype=np.float64),
            )
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (TypeError, ValueError) as exc:
            raise InputError(f"{source}: {exc}") from None


@dataclass(frozen=True, eq=False)
class Calibration:
    """Camera and projector projection matrices (thesis eqs. 4.3 and 4.6).

    Attributes
    ----------
    camera, projector : Device
    extra : dict
        Free-form extra keys written to the JSON (method, residuals, ...).
    """

    camera: Device
    projector: Device
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"camera": self.camera.to_dict(), "projector": self.projector.to_dict(), **self.extra}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "calibration") -> Calibration:
        if not isinstance(d, dict) or "camera" not in d or "projector" not in d:
            raise InputError(f"{source}: a calibration needs 'camera' and 'projector'")
        extra = {k: v for k, v in d.items() if k not in ("camera", "projector")}
        return cls(Device.from_dict(d["camera"], source=f"{source}: camera"),
                   Device.from_dict(d["projector"], source=f"{source}: projector"), extra)

    def save(self, path: str | os.PathLike) -> None:
        """Write the calibration JSON (DESIGN.md format), atomically."""
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        """Read a calibration JSON; raises `InputError` naming the file."""
        return cls.from_dict(_load_json(path), source=str(path))


@dataclass(frozen=True, eq=False)
class ScanResult:
    """What one scan produced, per camera pixel.

    Attributes
    ----------
    points : (H, W, 3) float32 array
        Xw, Yw, Zw in mm; NaN where invalid.
    valid : (H, W) bool array
    texture : (H, W) float32 array
        Albedo-like texture in [0, 1] (the capture's local mean), for colouring and mat5 ``C``.
    proj_map : (H, W) float32 array
        Projector coordinate along the phase direction seen by each pixel (`yp` for the rows
        orientation, `xp` for columns), in projector pixels; NaN where undecoded.
    stripe : (H, W) int16 array
        Decoded stripe index, -1 where undecoded.
    confidence : (H, W) float32 array
        Decision margin in [0, 1] (0 = a coin toss, 1 = every bit unambiguous).
    timings : dict of str -> float
        Seconds spent in each stage.
    """

    points: NDArray[np.float32]
    valid: NDArray[np.bool_]
    texture: NDArray[np.float32]
    proj_map: NDArray[np.float32]
    stripe: NDArray[np.int16]
    confidence: NDArray[np.float32]
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape  # type: ignore[return-value]

    def save_mat5(self, prefix: str | os.PathLike) -> list[Path]:
        """Write ``PREFIX{X,Y,Z}.byt``, ``PREFIXC.bmp``, ``PREFIXI.bmp``; returns the paths."""
        from sliscan.formats import mat5

        return mat5.write_mat5(prefix, self.points, self.valid, self.texture)

    def save_ply(self, path: str | os.PathLike) -> Path:
        """Write the valid points as a binary PLY point cloud with texture grey levels."""
        from sliscan.formats import ply

        return ply.write_point_cloud(path, self.points[self.valid], self.texture[self.valid])

    def save_npz(self, path: str | os.PathLike) -> Path:
        """Write every array of the result to one compressed npz file."""
        from sliscan.formats import npz

        return npz.write_scan_npz(path, self)


def _load_json(path: str | os.PathLike) -> dict[str, Any]:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(f"{p}: not valid JSON (not UTF-8 text)") from None
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (ValueError, RecursionError) as exc:  # a number of over 4300 digits, nesting too deep
        raise InputError(f"{p}: not valid JSON ({type(exc).__name__}: {exc})") from None
    if not isinstance(d, dict):
        raise InputError(f"{p}: expected a JSON object")
    return d
