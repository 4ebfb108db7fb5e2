"""Demodulation at baseband: every carrier's envelope from a narrow band of each line's spectrum.

The envelope of a carrier changes along the line no faster than the carriers' spacing allows,
so it needs only the part of the line's spectrum within about one spacing of the carrier.
Each line is Fourier transformed once (`scipy.fft.rfft`); per carrier the bins around it are
weighted by a window's transfer function, shifted to zero frequency and inverse transformed
at a short length ``L`` (a few times the band's width instead of the line's ``W`` pixels):
the envelope sampled every ``W / L`` pixels (27 at 5 MP), the decimated signal of issue
6.  The DC is the same low-pass around frequency 0.

The window is a triangle two spacing periods long (``sinc**2``: zero on every other carrier
when the carriers sit on multiples of one spacing, side lobes falling as ``1 / f**2``, so the
band can be cut at `REACH` spacings).  A box one period long (the window demodulator's
centred fit without its ramp) and a Hann window two periods long were measured as well, on
the 1296x972 smooth sphere (seed 1, per-pixel decisions): 71 % and 81 % of the lit pixels'
stripes right against 87 % with the triangle; the box's slowly falling side lobes pick up
the gamma's harmonics and the neighbouring carriers wherever the local frequency is off.
Each line gets its own carrier frequencies and window (`Carriers.line_frequencies`,
`line_windows`), so the zeros stay on the neighbours.  The transform takes the line as
periodic: within a window of either end the triangle reaches round to the other end, whose
carriers' phases do not continue this end's, and that jump lands in every band.  So, as the
window demodulator's windows stop at the line's ends, the samples within a window of either
end describe the window one window in (`BasebandPlan.ends`): on the 1296x972 sphere (seed 3)
the pixels within 12 pixels of the ends had 21 % of their stripes right before, and every
scene of the accuracy benchmark gained 1.5-3 points of right stripes (docs/speed.md,
twentieth session).  Padding the line with zeros to the next fast length was measured worse
(the padded edge is a step in every carrier), and so was mirroring it (the mirror reverses
the carriers' phases).

The capture is first divided by its albedo (`normalise_lines`, unless `Scanner.albedo` is
None).  A sharp step of the albedo multiplies the whole pattern, and its broadband spectrum
lands in every carrier's band, where no window tells it from the code: the steps are divided
out first (`sliscan.demodulate.albedo_estimate`).  A smooth albedo (and shading) varies the
DC within a window, and the triangle passes the DC's variation into the lowest carrier's band
(its response one spacing from a carrier at 0.3 spacings is ``sinc(0.7)**2 = 0.14``), where
the window demodulator's ramp would have fitted it: then the capture is divided by its flat
field, the DC under the same triangle, so its DC is one level along each line (which also
levels the line's two ends).  On the 1296x972 and 960x720 smooth-albedo captures this gained
0.2-3 points of right stripes, on uniform albedo it lost 0.0-0.5, on the checker it changed
nothing beyond 0.15 (docs/speed.md, twentieth session).

Next to a depth edge or a shadow border across the line, the centred window straddles it:
the carriers' phases jump there and the envelopes mix both sides' codes.  The window
demodulator then fits a one-sided window, where that explains the line better; here a sample
likewise takes the window of the sample `ONE_SIDED_SHIFT` of a window to either side (rounded
to whole samples: two at every rig measured) where that leaves less than `ONE_SIDED_GAIN` of
the centred window's unexplained energy, and the least.  The unexplained energy is the line's
mean square under the triangle (from running sums of its squares, one pass over the line)
less the DC's square and half of each envelope's square: what the DC and the carriers do not
explain (noise, the gamma's harmonics, and the phase jumps that lower the envelopes).  On the
1296x972 (seed 3) and 960x720 (seed 5) captures of every scene, both patterns and both albedos
it gained up to 4 points of right stripes (the smooth sphere 90.4 -> 93.0 and 91.5 -> 93.4 %,
the checkered one 88.0 -> 91.7 and 87.1 -> 91.1 %, the smooth steps 92.5 -> 95.2 and 93.1 ->
95.8 %) and 1-3 points of completeness, with fewer stripes more than one off but on the
smooth sphere (0.43 -> 0.56 and 0.44 -> 0.59 %: across its limb); a shift of 0.75 window
(three samples on some lines) gained 0.2-1 point more right stripes for more such stripes off
(0.81 %), and candidates between the samples (interpolated) gained less and cost three times
as much (docs/speed.md, twentieth session).

`demodulate_baseband` is the demodulator of `Scanner(method="baseband")`, whose decoding and
triangulation then run in one compiled pass over the pixels (`sliscan.fastscan`).  It fits no
model per pixel, so it has none of the window demodulator's misfit and noise estimates, and
its one-sided windows are chosen per sample: it trades accuracy for speed (docs/speed.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.fft
from numpy.typing import NDArray

from sliscan._threads import default_workers, over_rows
from sliscan.demodulate import STEP_SPREAD, Carriers, Demodulated, albedo_estimate

#: Half-width of each carrier's band, in carrier spacings: the triangle window's transfer
#: function is under 2.5 % of its peak beyond it (``sinc(1.5)**2``).
REACH = 1.5

#: `albedo_estimate` options of `normalise_lines` for the ``"steps"`` estimate: each line read
#: left to right only, half the detector's cost; on the 5 MP captures of the accuracy
#: benchmark reading both ways as well changed the right stripes by 0.0-0.5 points (docs/speed.md,
#: twentieth session); every step sharp (the window path's soft edges, `STEP_SPREAD`, gained
#: 0-0.3 points of completeness here on the 5 MP checker: docs/accuracy.md, "Soft albedo edges").
STEPS_OPTIONS: dict[str, bool | float] = {"both_ways": False, "blur": STEP_SPREAD, "soft": False}
#: The flat field's floor in `normalise_lines`, relative to the capture's bright level (its
#: 99th percentile): darker light (shadow, black surfaces) is divided by the floor instead,
#: so its noise is not raised to the lit level.  A floor of 0.05 (a tenth of the bright DC)
#: lost most of the flat field's gain on the smooth albedo (docs/speed.md, twentieth session).
FLAT_FLOOR = 0.01
#: A sample takes the window `ONE_SIDED_SHIFT` of a window (the triangle's half-width, rounded
#: to whole samples) to either side of its pixel instead of the centred one where that leaves
#: less than `ONE_SIDED_GAIN` of the centred window's unexplained energy (see the module
#: docstring; 0.75 and a gain of 0.3 or 0.7 were measured too).
ONE_SIDED_SHIFT = 0.6
ONE_SIDED_GAIN = 0.5


def triangle_response(frequency: NDArray[np.float64], window: NDArray[np.float64] | float) -> NDArray[np.float64]:
    """Transfer function of a triangle window ``2 * window`` pixels long, normalised to 1 at 0:
    ``sinc(frequency * window) ** 2`` (`frequency` in cycles per pixel).

    >>> [round(float(g), 3) for g in triangle_response(np.array([0.0, 0.5, 1.0, 2.0]) / 10, 10.0)]
    [1.0, 0.405, 0.0, 0.0]
    """
    return np.sinc(frequency * window) ** 2


@dataclass(frozen=True, eq=False)
class BasebandPlan:
    """What `demodulate_baseband` needs for one frame size and one set of carriers, prepared once.

    Attributes
    ----------
    width : int
        Line length (pixels along the carriers); the transform's length too.
    length : int
        Samples per line of every envelope (``L``).
    starts : (C + 1, H) int64 array
        First spectrum bin of each channel's band on each line (channel 0 is the DC, then the
        carriers in `Carriers.frequencies` order).
    gains : (C + 1, H, J) complex64 array
        Weight of each band bin (the window's transfer function times the transform's scale);
        bin ``j`` of a carrier's band lands at baseband bin ``j - J // 2`` (modulo `length`),
        the DC's at ``j``.
    ends : (H,) float64 array
        Each line's window (pixels): a sample nearer than this to either end of the line
        describes the pixel this far from it instead (see the module docstring).
    """

    width: int
    length: int
    starts: NDArray[np.int64]
    gains: NDArray[np.complex64]
    ends: NDArray[np.float64]

    @property
    def step(self) -> float:
        """Pixels between two samples of an envelope: sample ``m`` describes pixel ``m * step``."""
        return self.width / self.length

    @property
    def shifts(self) -> NDArray[np.int64]:
        """``(C + 1,)``: band bin ``j`` of channel ``c`` lands at baseband bin ``j - shifts[c]``
        (modulo `length`): the carrier's own bin at 0, the DC's bins where they are."""
        shifts = np.full(self.starts.shape[0], self.gains.shape[2] // 2, np.int64)
        shifts[0] = 0
        return shifts

    @classmethod
    def of(cls, height: int, width: int, carriers: Carriers) -> BasebandPlan:
        """The plan for `height` lines of `width` pixels and the `carriers` found in the capture."""
        windows = np.broadcast_to(carriers.line_windows(), (height,)).astype(np.float64)[None, :, None]
        freqs = np.asarray(carriers.line_frequencies(np.arange(height)), dtype=np.float64).T  # (C, H)
        half = int(np.ceil(REACH * width / windows.min()))
        length = scipy.fft.next_fast_len(2 * half + 1)
        centres = np.concatenate([np.zeros((1, height)), freqs])[:, :, None]  # (C + 1, H, 1), cycles per pixel
        starts = np.round(centres[:, :, 0] * width).astype(np.int64) - half
        starts[0] = 0
        bins = starts[:, :, None] + np.arange(2 * half + 1)[None, None, :]
        gains = triangle_response(bins / width - centres, windows) * ((bins >= 0) & (bins <= width // 2))
        # a carrier's envelope is 2 / W times the magnitude of its band's sum; the DC is the
        # real part of the one-sided sum (bin 0 once, the others twice) over W; L undoes the
        # inverse transform's 1 / L
        gains *= np.where(np.arange(gains.shape[0]) == 0, 1.0, 2.0)[:, None, None] * length / width
        gains[0] *= np.where(bins[0] == 0, 1.0, np.where(bins[0] <= half, 2.0, 0.0))
        return cls(width=width, length=length, starts=starts, gains=gains.astype(np.complex64),
                   ends=np.ascontiguousarray(windows[0, :, 0]))


@numba.njit(cache=True, nogil=True)
def _gather_rows(spectrum: NDArray[np.complex64], starts: NDArray[np.int64], gains: NDArray[np.complex64],
                 shifts: NDArray[np.int64], rows: NDArray[np.intp], out: NDArray[np.complex64]) -> None:
    """Each channel's weighted band of the given rows' `spectrum` ``(H, F)``, moved to
    baseband in `out` ``(C + 1, H, L)`` (see `BasebandPlan`)."""
    length, span, top = out.shape[2], gains.shape[2], spectrum.shape[1]
    for c in range(out.shape[0]):
        at = (np.arange(span) - shifts[c]) % length  # where each band bin lands
        for y in rows:
            out[c, y, :] = 0
            first = starts[c, y]
            for j in range(max(0, -first), min(span, top - first)):  # the band's bins inside the spectrum
                out[c, y, at[j]] = spectrum[y, first + j] * gains[c, y, j]


@numba.njit(cache=True, nogil=True)
def _samples_rows(periodic: NDArray[np.float32], image: NDArray[np.float32], step: float, ends: NDArray[np.float64],
                  one_sided: bool, rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """`Baseband.samples` of the given rows from `periodic` ``(C + 1, H, L)`` (sample ``m`` at
    pixel ``m * step`` of the line taken as periodic) into `out` ``(C + 1, H, L + 1)``: sample
    ``m`` is the window centred on pixel ``m * step`` moved to within ``ends[y] .. W - 1 -
    ends[y]`` (linear between the samples of `periodic`) or, if `one_sided`, that of the sample
    `ONE_SIDED_SHIFT` of a window to either side (rounded to whole samples) where that leaves
    less than `ONE_SIDED_GAIN` of the centred window's unexplained energy, and the least (see
    the module docstring)."""
    channels, length, width = periodic.shape[0], periodic.shape[2], image.shape[1]
    sums = np.empty(width + 1)  # sums[j]: the sum over i < j of the squares before pixel i
    unexplained, chosen = np.empty(length + 1), np.empty(length + 1, np.int64)
    centred = np.empty(length + 1, np.float32)  # one channel's centred samples of a line
    for y in rows:
        low = min(ends[y], 0.5 * (width - 1))
        high = width - 1 - low
        window = max(1, min(int(ends[y] + 0.5), width // 2))
        reach = int(ONE_SIDED_SHIFT * ends[y] / step + 0.5)
        squares = sums[0] = 0.0
        if one_sided:
            for x in range(width):
                sums[x + 1] = sums[x] + squares
                squares += np.float64(image[y, x]) * image[y, x]
        for m in range(length + 1):
            position = min(max(m * step, low), high) / step
            i = int(position)
            t = np.float32(position - i)
            j = i + 1 if i + 1 < length else 0
            explained = 0.0
            for c in range(channels):
                value = periodic[c, y, i] * (np.float32(1) - t) + periodic[c, y, j] * t
                out[c, y, m] = value
                explained += np.float64(value) * value if c == 0 else 0.5 * np.float64(value) * value
            if one_sided:
                # the line's mean square under the triangle (the boxes of `window` squares starting
                # at pixel - window + 1 .. pixel: weights window - |x - pixel|), less the explained
                centre = min(max(int(position * step + 0.5), window - 1), width - 1 - window)
                unexplained[m] = ((sums[centre + window + 1] - 2 * sums[centre + 1] + sums[centre - window + 1])
                                  / (window * window) - explained)
        if not one_sided or reach == 0:
            continue
        for m in range(length + 1):
            least, chosen[m] = unexplained[m], m
            bound = ONE_SIDED_GAIN * least
            for other in (m - reach, m + reach):
                if 0 <= other <= length and unexplained[other] < bound and unexplained[other] < least:
                    least, chosen[m] = unexplained[other], other
        for c in range(channels):
            centred[:] = out[c, y, :]
            for m in range(length + 1):
                out[c, y, m] = centred[chosen[m]]


@numba.njit(cache=True, nogil=True)
def _flattened_rows(image: NDArray[np.float32], albedo: NDArray[np.float32], windows: NDArray[np.intp],
                    floor: float, scale: float, rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """`normalise_lines` on the given `rows`: `image` over `albedo` ``(H, W)``, its flat field
    (the mean under a triangle two of the line's windows long, mirrored at the ends, at least
    `floor`, over `scale`) multiplied into `albedo` in place, and `image` over the product into
    `out`."""
    w = image.shape[1]
    for y in rows:
        t = max(1, min(windows[y], w - 1))
        padded = np.empty(w + 2 * t)  # the line over its albedo, mirrored by t at both ends
        for k in range(w + 2 * t):
            x = k - t
            x = -x - 1 if x < 0 else (2 * w - x - 1 if x >= w else x)
            padded[k] = image[y, x] / albedo[y, x]
        boxes = np.zeros(w + t + 2)  # boxes[i + 1] - boxes[i]: the sum of padded[i .. i + t - 1]
        total = 0.0
        for k in range(t):
            total += padded[k]
        for i in range(w + t + 1):
            boxes[i + 1] = boxes[i] + total
            if i + t < w + 2 * t:
                total += padded[i + t] - padded[i]
        norm = 1.0 / (t * t * scale)
        for x in range(w):
            # the triangle at x: the t boxes starting at x + 1 .. x + t (weights t - |k - x - t|)
            gain = max((boxes[x + t + 1] - boxes[x + 1]) * norm, floor / scale)
            a = np.float32(albedo[y, x] * gain)
            albedo[y, x] = a
            out[y, x] = image[y, x] / a


def normalise_lines(image: NDArray[np.floating], carriers: Carriers, *, estimate: str = "steps",
                    camera_blur: float | None = None,
                    workers: int | None = None) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """A capture divided by its albedo for `demodulate_baseband` (see the module docstring):
    `sliscan.demodulate.albedo_estimate` (``"steps"`` with `STEPS_OPTIONS`) times each line's
    flat field, the mean of the capture over it under a triangle two carrier spacing periods
    long (zero on every multiple of the spacing: it passes the DC and no carrier), floored at
    `FLAT_FLOOR` of the capture's bright level.

    Parameters
    ----------
    image : (H, W) array
        Capture with the carriers along axis 1.
    carriers : Carriers
        Found in it (each line's window).
    estimate : str
        One of `sliscan.demodulate.ALBEDO_ESTIMATES`.
    camera_blur : float, optional
        The camera's blur (Gaussian sigma, px) the steps are found for; default `STEP_SPREAD`
        (not measured on the capture: `STEPS_OPTIONS`).
    workers : int, optional
        Threads over the lines (default: `default_workers`).

    Returns
    -------
    (normalised, albedo) : two (H, W) float32 arrays
        ``image / albedo`` (where lit, about the capture's bright level) and the albedo with
        the flat field (relative: its scale is arbitrary).
    """
    img = np.ascontiguousarray(image, dtype=np.float32)
    options = STEPS_OPTIONS | ({} if camera_blur is None else {"blur": camera_blur})
    albedo = np.ascontiguousarray(albedo_estimate(img, carriers, estimate=estimate,
                                                  **(options if estimate in ("steps", "sharp-steps") else {})))
    windows = np.ascontiguousarray(np.broadcast_to(carriers.line_windows(), (img.shape[0],)), dtype=np.intp)
    scale = max(float(np.percentile(img[::4, ::4], 99)), 1e-6)
    out = np.empty_like(img)
    over_rows(lambda rows: _flattened_rows(img, albedo, windows, FLAT_FLOOR * scale, scale, rows, out), img.shape[0],
              workers)
    return out, albedo


@dataclass(frozen=True, eq=False)
class Baseband:
    """Envelopes and DC of a capture, sampled every `step` pixels along the carriers.

    Attributes
    ----------
    samples : (C + 1, H, L + 1) float32 array
        Channel 0 the DC, then each carrier's envelope (peak amplitude, image units), in
        `Carriers.frequencies` order; sample ``m`` of a line describes pixel ``m * step``
        (sample ``L`` the line's end), or within a window (`BasebandPlan.ends`) of either end
        the pixel a window in; each is the window centred there or a one-sided one's (see
        the module docstring).
    step : float
        Pixels between samples.
    albedo : (H, W) float32 array or None
        The relative albedo the capture was divided by before the transforms
        (`normalise_lines`), so `samples` describe the normalised capture; None if it was not.
    """

    samples: NDArray[np.float32]
    step: float
    albedo: NDArray[np.float32] | None = None

    def demodulated(self, width: int) -> Demodulated:
        """The envelopes at every pixel of lines `width` long (linear interpolation), as a
        `Demodulated` (residual 0: this demodulator fits no model to measure it by), multiplied
        back by `albedo` if there is one (image units; every ratio the decoder takes is the
        normalised capture's)."""
        position = np.arange(width) / self.step
        low = np.floor(position).astype(np.intp)
        t = (position - low).astype(np.float32)
        full = self.samples[:, :, low] * (1 - t) + self.samples[:, :, low + 1] * t
        if self.albedo is not None:
            full *= self.albedo[None]
        return Demodulated(amplitude=np.ascontiguousarray(full[1:]), dc=np.ascontiguousarray(full[0]),
                           residual=np.zeros(full.shape[1:], np.float32))

    def sampled_albedo(self) -> NDArray[np.float32] | None:
        """`albedo` ``(H, L + 1)`` at the pixels ``m * step`` of the samples (the nearest), or None."""
        if self.albedo is None:
            return None
        columns = np.minimum(np.round(np.arange(self.samples.shape[2]) * self.step).astype(np.intp),
                             self.albedo.shape[1] - 1)
        return self.albedo[:, columns]


def demodulate_baseband(image: NDArray[np.floating], plan: BasebandPlan, *, albedo: NDArray[np.float32] | None = None,
                        one_sided: bool = True, workers: int | None = None) -> Baseband:
    """The DC and every carrier's envelope of `image`, decimated (see the module docstring).

    Parameters
    ----------
    image : (H, W) float32 array
        Capture with the carriers along axis 1 (`sliscan.demodulate.along_carriers`), in [0, 1],
        divided by `albedo` if that is given.
    plan : BasebandPlan
        For this frame size and these carriers.
    albedo : (H, W) float32 array, optional
        The relative albedo `image` was divided by (`normalise_lines`), kept in the result
        (`Baseband.albedo`).
    one_sided : bool
        Whether a sample may take a one-sided window (see the module docstring); without, every
        sample is its centred window's.
    workers : int, optional
        Threads of the transforms and the band gathering (default: `default_workers`).
    """
    workers = default_workers() if workers is None else workers
    height = image.shape[0]
    spectrum = scipy.fft.rfft(image, axis=1, workers=workers)
    bands = np.empty((plan.gains.shape[0], height, plan.length), np.complex64)
    shifts = plan.shifts
    over_rows(lambda rows: _gather_rows(spectrum, plan.starts, plan.gains, shifts, rows, bands), height, workers)
    signal = scipy.fft.ifft(bands, axis=2, workers=workers, overwrite_x=True)
    periodic = np.empty(bands.shape, np.float32)
    periodic[0] = signal[0].real
    np.abs(signal[1:], out=periodic[1:])
    samples = np.empty((*bands.shape[:2], plan.length + 1), np.float32)
    over_rows(lambda rows: _samples_rows(periodic, image, plan.step, plan.ends, one_sided, rows, samples), height,
              workers)
    return Baseband(samples=samples, step=plan.step, albedo=albedo)
