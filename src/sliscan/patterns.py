"""Gray code and the composite pattern (thesis section 3.1, eq. 3.1; section 6.2).

A composite pattern puts every Gray code bit plane on its own cosine carrier along the
orthogonal direction and sums them into one projected image::

    I_p(x_p, y_p) = A_p + B_p * sum_n w_n * I_n(y_p) * cos(2 pi f_n x_p / W_p)        (eq. 3.1)

`I_n(y_p)` is bit `n` (0 = most significant) of the Gray code of the stripe that projector
row `y_p` belongs to; `f_n` is in cycles per projector width.  With ``orientation="columns"``
the roles of x and y swap.  Stripe ``k`` covers the projector lines
``[k * L / S, (k + 1) * L / S)`` of the `L` lines along the phase direction (`S` stripes), so
its centre line is ``(k + 0.5) * L / S - 0.5`` (pixel centres at integers).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_path, to_uint8
from sliscan.types import PatternSpec

#: The thesis's carriers (section 3.1) for a 1024-pixel-wide projector, cycles per width.
THESIS_CARRIERS = (32.0, 64.0, 96.0, 128.0)


def gray_encode(n: ArrayLike) -> NDArray[np.int64]:
    """Binary-reflected Gray code of non-negative integers (table 3.1).

    >>> gray_encode([0, 1, 2, 3, 4, 5, 6, 7]).tolist()
    [0, 1, 3, 2, 6, 7, 5, 4]
    """
    n = np.asarray(n, dtype=np.int64)
    if np.any(n < 0):
        raise InputError("Gray code is defined for non-negative integers")
    return n ^ (n >> 1)


def gray_decode(g: ArrayLike) -> NDArray[np.int64]:
    """Inverse of `gray_encode` (table 3.3's look-up, as a prefix XOR).

    >>> gray_decode([0, 1, 3, 2, 6, 7, 5, 4]).tolist()
    [0, 1, 2, 3, 4, 5, 6, 7]
    """
    n = np.asarray(g, dtype=np.int64).copy()
    if np.any(n < 0):
        raise InputError("Gray code is defined for non-negative integers")
    shift = 1
    while shift < 63:
        n ^= n >> shift
        shift *= 2
    return n


def code_bits(codes: ArrayLike, bits: int) -> NDArray[np.uint8]:
    """Bits of integer codes, most significant first: ``(..., bits)`` uint8."""
    codes = np.asarray(codes, dtype=np.int64)
    shifts = np.arange(bits - 1, -1, -1, dtype=np.int64)
    return ((codes[..., None] >> shifts) & 1).astype(np.uint8)


def bits_to_code(planes: ArrayLike) -> NDArray[np.int64]:
    """Integer code from 0/1 bit planes ``(K, ...)``, plane 0 the most significant.

    One shift-and-or per plane (Horner), so no ``(K, ...)`` int64 temporary.

    >>> bits_to_code([[1, 0], [0, 1], [1, 1]]).tolist()
    [5, 3]
    """
    planes = np.asarray(planes)
    code = np.zeros(planes.shape[1:], dtype=np.int64)
    for plane in planes:
        code <<= 1
        code |= plane.astype(np.int64)
    return code


def stripe_codes(spec: PatternSpec) -> NDArray[np.int64]:
    """Gray code projected on each stripe, ``(S,)``; skips the all-zero code if asked."""
    return gray_encode(np.arange(spec.stripes) + (1 if spec.skip_zero_code else 0))


def code_to_stripe(codes: ArrayLike, spec: PatternSpec) -> NDArray[np.int64]:
    """Stripe index of decoded Gray codes; -1 where the code is never projected."""
    stripe = gray_decode(codes) - (1 if spec.skip_zero_code else 0)
    return np.where((stripe >= 0) & (stripe < spec.stripes), stripe, -1)


def stripe_of_line(line: ArrayLike, spec: PatternSpec) -> NDArray[np.int64]:
    """Stripe index of (fractional) projector lines along the phase direction; -1 outside.

    Line ``r`` (an integer) belongs to stripe ``floor((r + 0.5) S / L)``; a fractional line
    belongs to the stripe of the nearest whole line, since the projected light changes
    stripe half way between two lines.
    """
    line = np.asarray(line, dtype=np.float64)
    lines = spec.phase_lines
    with np.errstate(invalid="ignore"):
        nearest = np.floor(line + 0.5)
        k = np.floor((nearest + 0.5) * spec.stripes / lines)
        ok = np.isfinite(k) & (nearest >= 0) & (nearest < lines)
    return np.where(ok, np.nan_to_num(k), -1).astype(np.int64)


def stripe_center(stripe: ArrayLike, spec: PatternSpec) -> NDArray[np.float64]:
    """Projector line at the centre of each stripe (NaN for stripe -1), in projector pixels:
    half way between the stripe's first and last line.

    >>> stripe_center([0, 15], PatternSpec()).tolist()
    [23.5, 743.5]
    """
    stripe = np.asarray(stripe)
    per = spec.phase_lines / spec.stripes
    first = np.ceil(stripe * per - 0.5)
    last = np.ceil((stripe + 1) * per - 0.5) - 1
    return np.where(stripe >= 0, 0.5 * (first + last), np.nan)


def bit_planes(spec: PatternSpec) -> NDArray[np.uint8]:
    """Which bits are on along the phase direction: ``(bits, L)`` uint8, one column per line."""
    stripe = stripe_of_line(np.arange(spec.phase_lines), spec)
    return code_bits(stripe_codes(spec)[stripe], spec.bits).T.copy()


def fringe_phase(line: ArrayLike, spec: PatternSpec) -> NDArray[np.float64]:
    """Phase of the phase channel's fringe at (fractional) projector lines along the phase
    direction, radians, unwrapped: 0 at the top edge of line 0 (line -0.5), ``2 pi`` one
    `PatternSpec.fringe_period` later, so every second stripe border (of the default period)
    is a period border.

    >>> fringe_phase([-0.5, 47.5, 95.5], PatternSpec(phase_carriers=(1, 2, 3))).round(4).tolist()
    [0.0, 3.1416, 6.2832]
    """
    return 2 * np.pi * (np.asarray(line, dtype=np.float64) + 0.5) / spec.fringe_period


def fringe_line(phase: ArrayLike, spec: PatternSpec) -> NDArray[np.float64]:
    """Inverse of `fringe_phase`: projector line of an unwrapped fringe phase (radians)."""
    return np.asarray(phase, dtype=np.float64) * spec.fringe_period / (2 * np.pi) - 0.5


def phase_shifts(spec: PatternSpec) -> NDArray[np.float64]:
    """Phase shift of each phase carrier's fringe, ``2 pi n / N`` radians, ``(N,)``."""
    n = len(spec.phase_carriers)
    return 2 * np.pi * np.arange(n) / max(n, 1)


def phase_planes(spec: PatternSpec) -> NDArray[np.float64]:
    """The fringes on the phase carriers along the phase direction: ``(N, L)`` in [0, 1],
    ``(1 + cos(fringe_phase - 2 pi n / N)) / 2`` (N = 0 without a phase channel)."""
    phase = fringe_phase(np.arange(spec.phase_lines), spec)
    return 0.5 * (1 + np.cos(phase[None, :] - phase_shifts(spec)[:, None]))


def carrier_waves(spec: PatternSpec) -> NDArray[np.float64]:
    """``cos(2 pi f_n x / W)`` for every carrier (bits, phase, pilot) along the orthogonal direction.

    Returns ``(len(spec.all_carriers), spec.orthogonal_lines)``.
    """
    x = np.arange(spec.orthogonal_lines, dtype=np.float64)
    f = np.asarray(spec.all_carriers, dtype=np.float64)[:, None] / spec.orthogonal_lines
    return np.cos(2 * np.pi * f * x)


def pattern_range(spec: PatternSpec) -> tuple[float, float]:
    """Smallest and largest value eq. 3.1 reaches before gamma and quantisation.

    The pattern's own extremes, not the bound ``a_p +/- b_p * sum(|w_n|)`` of every carrier
    peaking at once, which the bits' codes and the fringes never reach together: sliscan's
    phase pattern with an equal share of that bound's [0, 1] per carrier spans 0.25-0.89
    (`phase_spec` stretches it: `stretch_drive`).

    >>> [round(v, 3) for v in pattern_range(phase_spec((1024, 768), a_p=0.5, b_p=0.5 / 7))]
    [0.25, 0.893]
    """
    image = _eq31(spec)
    return float(image.min()), float(image.max())


def stretch_drive(spec: PatternSpec, low: float = 0.0, high: float = 1.0) -> PatternSpec:
    """`spec` with `a_p` and `b_p` set so that the pattern spans exactly ``[low, high]``.

    More modulation for the same projector: every carrier's amplitude grows by the same
    factor (the decoder measures the levels and the projector's crosstalk from each capture).

    >>> equal_shares = phase_spec((1024, 768), a_p=0.5, b_p=0.5 / 7)
    >>> spec = stretch_drive(equal_shares, 0.2)
    >>> [round(v, 3) for v in pattern_range(spec)], round(spec.b_p / equal_shares.b_p, 3)
    ([0.2, 1.0], 1.244)
    """
    if not 0 <= low < high <= 1:
        raise InputError(f"the drive range must satisfy 0 <= low < high <= 1, got [{low:g}, {high:g}]")
    lowest, highest = pattern_range(spec)
    scale = (high - low) / (highest - lowest)
    return spec.with_(b_p=spec.b_p * scale, a_p=low + (spec.a_p - lowest) * scale)


def _eq31(spec: PatternSpec) -> NDArray[np.float64]:
    """Eq. 3.1 (and the modified pattern's sine), unchecked: `linear_pattern`'s image."""
    waves = carrier_waves(spec)  # (C, O)
    weights = np.asarray(spec.all_weights)[:, None]
    if spec.kind == "carrier_only":
        on = np.ones((len(spec.all_carriers), spec.phase_lines))
    else:
        on = np.vstack([bit_planes(spec), phase_planes(spec), np.ones((int(spec.pilot is not None), spec.phase_lines))])
    # (L, O): sum over carriers of on[n, line] * w_n * wave[n, x]
    image = spec.a_p + spec.b_p * (on.T @ (weights * waves))
    if spec.kind == "modified_composite":
        line = np.arange(spec.phase_lines, dtype=np.float64)
        image += spec.modified_amplitude * np.sin(2 * np.pi * spec.modified_frequency * line / spec.phase_lines)[:, None]
    return image if spec.orientation == "rows" else image.T


def linear_pattern(spec: PatternSpec) -> NDArray[np.float64]:
    """Eq. 3.1 as linear projector drive, ``(H_p, W_p)`` float64, before gamma and quantisation.

    ``carrier_only`` turns every bit on everywhere (fig. 3.9); ``modified_composite`` adds
    ``modified_amplitude * sin(2 pi modified_frequency y / L)`` along the phase direction (6.2).
    Raises `InputError` where the pattern leaves [0, 1] (`pattern_range`).
    """
    image = _eq31(spec)
    low, high = float(image.min()), float(image.max())
    if low < -1e-9 or high > 1 + 1e-9:
        raise InputError(
            f"pattern leaves [0, 1]: a_p {spec.a_p:g} and b_p {spec.b_p:g} make it span [{low:.3f}, {high:.3f}]; "
            "lower b_p or the weights, or move a_p (patterns.stretch_drive fits them to a range)"
        )
    return image


def precorrect(linear: ArrayLike, spec: PatternSpec) -> NDArray[np.float64]:
    """Projector drive that gives `linear` light: the inverse of the spec's measured
    `response` (evenly spaced drive levels), else ``linear ** (1 / gamma)``.

    Parameters
    ----------
    linear : array
        Wanted linear light in [0, 1] (clipped), any shape.

    Returns
    -------
    float64 array of the same shape
        Drive in [0, 1], before quantisation.

    >>> spec = PatternSpec(response=(0.0, 0.25, 1.0))   # drive 0.5 gives a quarter of the light
    >>> precorrect([0.0, 0.25, 0.625, 1.0], spec).tolist()
    [0.0, 0.5, 0.75, 1.0]
    """
    light = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    if spec.response is None:
        return light ** (1.0 / spec.gamma)
    return np.interp(light, spec.response, np.linspace(0.0, 1.0, len(spec.response)))


def render_pattern(spec: PatternSpec) -> NDArray[np.float32]:
    """The image to project: eq. 3.1, pre-corrected (`precorrect`), quantised to 8 bits.

    Returns
    -------
    (H_p, W_p) float32 array
        Values on the 1/255 grid in [0, 1].
    """
    drive = precorrect(linear_pattern(spec), spec)
    return (to_uint8(drive).astype(np.float32) / np.float32(255)).astype(np.float32)


def scale_carriers(carriers: tuple[float, ...], width: int, *, reference_width: int = 1024) -> tuple[float, ...]:
    """Carriers given per `reference_width` pixels, rescaled to keep their period for `width`.

    >>> scale_carriers((32, 64, 96, 128), 512)
    (16.0, 32.0, 48.0, 64.0)
    """
    return tuple(float(f) * width / reference_width for f in carriers)


def thesis_spec(projector_size: tuple[int, int] = (1024, 768), **changes) -> PatternSpec:
    """The thesis's pattern: 4 bits on carriers 32, 64, 96, 128 per 1024 px, A_p = 0.5."""
    width = projector_size[0] if changes.get("orientation", "rows") == "rows" else projector_size[1]
    base = dict(kind="composite", projector_size=tuple(projector_size), bits=4,
                carriers=scale_carriers(THESIS_CARRIERS, width), weights=(1.0,) * 4, a_p=0.5, b_p=0.125)
    base.update(changes)
    return PatternSpec(**base)


def spread_carriers(bits: int, width: int, *, highest: float | None = None, pilot: bool = False) -> tuple[float, ...]:
    """Carriers free of second-order intermodulation: ``k * d`` for ``k = n .. 2n - 1``.

    With the `n` consecutive multiples ``k = n, ..., 2n - 1`` of a spacing `d`, every difference ``f_i - f_j`` lies below the lowest carrier and every sum ``f_i + f_j``
    (harmonics included) above the highest, so the products that projector gamma creates
    never land on a carrier (the cause of the thesis's lost lowest carrier, section 3.2.2).

    Parameters
    ----------
    bits : int
        Number of bit carriers; one more is planned when `pilot` is true (the pilot is last).
    width : int
        Projector pixels along the orthogonal direction.
    highest : float, optional
        Highest carrier in cycles per width; default ``width / 8`` (an 8 px period, the
        thesis's highest carrier).

    Returns
    -------
    tuple of float
        Carrier frequencies in cycles per width, lowest first.

    >>> [round(f, 2) for f in spread_carriers(4, 1024)]
    [73.14, 91.43, 109.71, 128.0]
    """
    n = bits + (1 if pilot else 0)
    top = width / 8 if highest is None else highest
    d = top / (2 * n - 1)
    return tuple(k * d for k in range(n, 2 * n))


def default_spec(projector_size: tuple[int, int] = (1024, 768), **changes) -> PatternSpec:
    """The best single-shot composite pattern sliscan knows for this projector.

    The thesis's carriers (32, 64, 96, 128 cycles per 1024 px: one spacing period is the
    shortest window that separates them, which keeps depth and albedo edges from spreading),
    with two changes measured on the virtual rig (benchmarks/accuracy.py):

    * the most significant bit rides on the highest carrier: an edge inside the window leaks
      into every carrier roughly as ``1 / (pi k)`` for a carrier with `k` periods per window,
      so the bit whose error costs half the depth range gets the least leakage and the
      lowest carrier is left to the least significant bit, whose error costs one stripe;
    * the all-zero code is never projected, so every lit pixel carries at least one carrier
      and cannot be mistaken for shadow (15 stripes instead of 16).

    Patterns that trade a longer window for immunity to gamma's intermodulation
    (`spread_carriers`) or add a pilot carrier measured worse on textured surfaces.
    """
    orientation = changes.get("orientation", "rows")
    width = projector_size[0] if orientation == "rows" else projector_size[1]
    bits = int(changes.pop("bits", 4))
    carriers = tuple(reversed(scale_carriers(tuple(128.0 * k / bits for k in range(1, bits + 1)), width)))
    base = dict(kind="composite", projector_size=tuple(projector_size), bits=bits, carriers=carriers,
                weights=(1.0,) * bits, skip_zero_code=True, a_p=0.5, b_p=0.5 / bits)
    base.update(changes)
    return PatternSpec(**base)


def carriers_above(carriers: tuple[float, ...], count: int = 3) -> tuple[float, ...]:
    """`count` carriers continuing `carriers`' spacing (taken as their lowest) above the highest.

    >>> carriers_above((128.0, 96.0, 64.0, 32.0))
    (160.0, 192.0, 224.0)
    """
    spacing, top = min(carriers), max(carriers)
    return tuple(top + spacing * k for k in range(1, count + 1))


#: The linear drive range `phase_spec` stretches its pattern over (`stretch_drive`).  With zero
#: carrier phases the seven carriers of the 4-bit phase pattern seldom peak together: given
#: an equal share of [0, 1] each (``b_p = 0.5 / 7``) the pattern spans only 0.25-0.89.
#: Stretched over 0.2-1.0 every carrier is 1.24 times stronger; measured on the virtual rig
#: (docs/accuracy.md, "Sub-stripe depth from one frame", 23 captures on three rigs) together with the
#: ring beside the gaps (`fringe.GAP_RING`), against neither: RMS error 1-38 % lower on all 23,
#: median 4-23 % lower on all 23, completeness -1.4 to +1.0 points.  The low end stays at 0.2,
#: where an uncorrected gamma of 2.2 leaves 3 % of the light.
PHASE_DRIVE = (0.2, 1.0)

#: The light range a composite stripe pattern pre-corrected for the projector's response spans
#: (`stretch_drive` on the linear pattern; `sliscan pattern composite --gamma` or
#: `--from-characterization`).  An uncorrected gamma of 2.2 halves the mean light of eq. 3.1's
#: A_p = 0.5 and doubles each carrier's modulation over it (0.51-0.54 against 0.25), contrast a
#: pre-correction gives back unless the pattern uses the light's whole range: its four carriers
#: never all trough together, so eq. 3.1 spans only 0.24-1 of it.  Stretched over 0-1 (A_p
#: 0.34, B_p 0.165) the pre-corrected pattern decodes more of the virtual rig's captures than
#: the uncorrected one (all 12 at 1296x972, seeds 5-7; 7 of 8 at 5 MP: not sliscan's checkered
#: steps), and the unstretched pre-corrected one fewer (docs/accuracy.md, "Robustness").
PRECORRECTED_DRIVE = (0.0, 1.0)


def phase_spec(projector_size: tuple[int, int] = (1024, 768), **changes) -> PatternSpec:
    """`default_spec` plus a 3-step phase channel (issue 8): sub-stripe depth from one frame.

    The bits keep their carriers (for 4 bits 32-128 per 1024 px, the most significant on the
    highest); the fringe's three phase-shifted copies go on the next three multiples of their
    spacing (160, 192, 224), so the window stays one spacing period.  Every carrier gets an
    equal share of the drive, stretched so that the pattern spans `PHASE_DRIVE` (``a_p``
    0.511, ``b_p`` 0.0889 for 4 bits) unless `changes` set ``a_p`` or ``b_p``.  Measured
    alternatives (benchmarks/accuracy.py): the phase on the lowest carriers and the bits above
    lost the Gray code (the bits' decisions need the stronger low carriers), and the projector
    gamma's products of the low phase carriers (32 + 64 = 96) land on each other.

    >>> spec = phase_spec((1024, 768))
    >>> round(spec.a_p, 3), round(spec.b_p, 4), [round(v, 3) for v in pattern_range(spec)]
    (0.511, 0.0889, [0.2, 1.0])
    >>> phase_spec((1024, 768), a_p=0.5, b_p=0.5 / 7).b_p == 0.5 / 7  # the equal shares of [0, 1]
    True
    """
    orientation = changes.get("orientation", "rows")
    base = default_spec(projector_size, orientation=orientation, bits=int(changes.pop("bits", 4)))
    phase = carriers_above(base.carriers)
    spec = base.with_(phase_carriers=phase, b_p=0.5 / (base.bits + len(phase)))
    spec = spec.with_(**changes) if changes else spec
    return spec if "a_p" in changes or "b_p" in changes else stretch_drive(spec, *PHASE_DRIVE)


def save_pattern(path: str | os.PathLike, spec: PatternSpec) -> tuple[Path, Path]:
    """Write the pattern image (8-bit PNG/BMP) and its PatternSpec JSON beside it.

    ``cp.png`` gets ``cp.json``; the JSON's ``image`` key names the image file.  Both are
    written atomically.  Returns ``(image_path, json_path)``.
    """
    import cv2

    image_path = Path(path)
    json_path = image_path.with_suffix(".json")
    if image_path.suffix.lower() == ".json":
        raise InputError(f"{image_path}: give the image file name (e.g. cp.png); the JSON goes beside it")
    spec = spec.with_(image=image_path.name)
    image = to_uint8(render_pattern(spec))
    with atomic_path(image_path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise InputError(f"{image_path}: cannot write an image with this file extension")
    spec.save(json_path)
    return image_path, json_path
