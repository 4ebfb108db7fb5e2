"""Where the phase channel's error comes from (issue 8): one factor of the capture at a time.

On the virtual rig's sphere scene (the sphere in front of a plane at 1000 mm), sliscan's
pattern with the phase channel (`patterns.phase_spec`) is rendered under the accuracy
benchmark's realistic conditions, then with one factor removed at a time (noise, blur, the
smooth albedo), then with all of them and the projector's gamma and the ambient light removed
("ideal"), and the plane alone under the ideal conditions.  Two decoders of the ideal sphere
scene ask what is left: the carriers detected on the plane alone (kept by a
`Scanner(reuse_carriers=True)`, so the background is demodulated at its own carrier
frequencies), and the capture demodulated in `--tiles` strips of columns, each with the
carriers detected in it.  Then the realistic capture once more, to locate the smooth
albedo's part (the uniform-albedo row gains the most at 5 MP): divided by the true albedo, and by the
true albedo smoothed over one demodulation window along the carriers or along the phase
direction (`divided_by_albedo`), which tells which direction's albedo detail costs; and
decoded with the phase carriers' envelopes refitted by a reference of the window fit that
solves the carriers' couplings exactly (`exact_envelopes`; the compiled fit neglected them
until the fortieth session and solves them since, so that row now checks the two agree),
without and with a correction for an albedo ramp common to all carriers in the window (the
fit's DC ramp, which the carriers share, leaks into their neighbours); and with the phase
carriers' envelopes from centred windows only (the Gray code from the usual placement, which
lets a window end or start at the pixel).  For each: the error
of the decoded projector line (`proj_map` against the truth's, in projector lines; RMS over
the pixels more than 50 px from any depth or shadow edge and less than 10 lines off, on the
sphere and on the background apart) and, for the first rows, the median 3D error of the
whole scan.

    python benchmarks/phase_error_sources.py                       # 1296x972, ~1 min
    python benchmarks/phase_error_sources.py --camera 2592x1944    # the thesis's size, ~7 min
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import scipy.ndimage

from sliscan import fringe, patterns, simulate
from sliscan.decode import decode
from sliscan.demodulate import (Carriers, Demodulated, demodulate, demodulate_window, detect_carriers, flat_field,
                                normalise_albedo)
from sliscan.evaluate import accuracy
from sliscan.pipeline import Scanner

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import conditions  # noqa: E402

PROJECTOR = (1024, 768)
#: Pixels nearer than this (camera pixels) to a depth or shadow edge are left out of the line RMS.
EDGE_DISTANCE = 50


def ideal(base: simulate.Conditions) -> simulate.Conditions:
    """`base` without noise, quantisation, blur, albedo texture, gamma and ambient light."""
    return dataclasses.replace(base, full_well_e=None, read_noise_e=0.0, bit_depth=None, projector_blur_px=0.0,
                               camera_blur_px=0.0, albedo=simulate.UniformAlbedo(0.8), projector_gamma=1.0,
                               ambient=0.0)


def tiled_lines(scanner: Scanner, image: np.ndarray, tiles: int) -> np.ndarray:
    """The scanner's decoded projector lines (``(H, W)``, NaN where none) with the capture
    demodulated in `tiles` strips of columns (rows orientation), each strip two windows wider
    on both sides and demodulated with the carriers detected in it."""
    spec = scanner.spec
    demod, carriers = demodulate(image, spec)
    width, pad = image.shape[1], 2 * int(carriers.window)
    edges = np.linspace(0, width, tiles + 1).astype(int)
    for first, last in zip(edges[:-1], edges[1:]):
        a, b = max(0, first - pad), min(width, last + pad)
        strip = np.ascontiguousarray(image[:, a:b])
        part, _ = demodulate(strip, spec, carriers=detect_carriers(strip, spec))
        for field in dataclasses.fields(demod):
            whole, piece = getattr(demod, field.name), getattr(part, field.name)
            if whole is not None and piece is not None:
                whole[..., first:last] = piece[..., first - a:last - a]
    decoded = fringe.refine(decode(demod, spec, **scanner.decode_options), demod, carriers, spec,
                            **scanner.fringe_options)
    return np.where(decoded.valid, decoded.proj_map, np.nan)


def divided_by_albedo(image: np.ndarray, albedo: np.ndarray, length: int, axis: int | None) -> np.ndarray:
    """`image` ``(H, W)`` over the true `albedo` (0 where no surface: left alone), the log
    albedo first averaged over `length` pixels along `axis` (None: not smoothed)."""
    log_albedo = np.log(np.where(albedo > 0, albedo, 1.0).astype(np.float64))
    if axis is not None:
        log_albedo = scipy.ndimage.uniform_filter1d(log_albedo, length, axis=axis)
    return (image / np.exp(log_albedo)).astype(np.float32)


def exact_envelopes(image: np.ndarray, demod: Demodulated, carriers: Carriers, channels: range, *,
                    albedo_ramp: bool) -> Demodulated:
    """`demod` (the window demodulator's, rows orientation) with the envelopes of `channels`
    refitted: every window start of every line by the exact least-squares fit of a DC, a ramp
    and the carriers (the pseudo-inverse of the window's design matrix, so the carriers'
    couplings are solved, as the compiled fit has solved them since the fortieth session),
    at the window placement `demod`
    chose for the pixel (`Demodulated.offset`), on the capture divided by its albedo steps as
    `demodulate_window` divides it.  A slow numpy reference, for measuring.

    With `albedo_ramp`, the albedo is taken to vary across the window as ``1 + rho t`` for
    every carrier alike, ``rho`` the fitted ramp over the fitted DC: each carrier's ramp
    ``rho t c_m`` projects onto the others' coefficients through a known matrix, which two
    fixed-point rounds take out."""
    normalised, gain = normalise_albedo(image, carriers, estimate="sharp-steps")  # as the phase pattern's demodulation
    lines = normalised.astype(np.float64)
    height, width = lines.shape
    omegas = 2 * np.pi * carriers.line_frequencies(slice(0, height))
    windows = np.broadcast_to(carriers.line_windows(), (height,))
    amplitude = demod.amplitude.copy()
    for y in range(height):
        length, omega = int(windows[y]), omegas[y]
        flat = np.maximum(flat_field(lines[y], length), 1e-4)
        j = np.arange(length)
        t = j - (length - 1) / 2
        waves = np.column_stack([f(w * j) for w in omega for f in (np.cos, np.sin)])
        inverse = np.linalg.pinv(np.column_stack([np.ones(length), t, waves]))
        fits = np.lib.stride_tricks.sliding_window_view(lines[y] / flat, length) @ inverse.T  # (starts, 2 + 2C)
        coefficients = fits[:, 2:]
        if albedo_ramp:
            rho = fits[:, 1] / np.maximum(fits[:, 0], 1e-6)
            leak = (inverse @ (t[:, None] * waves))[2:]  # (2C, 2C): ramped carriers seen as coefficients
            fitted = coefficients.copy()
            for _ in range(2):
                coefficients = fitted - rho[:, None] * (coefficients @ leak.T)
        pairs = coefficients.reshape(len(fits), omega.size, 2)
        magnitude = np.hypot(pairs[..., 0], pairs[..., 1])
        start = np.clip(np.round(np.arange(width) + demod.offset[y] - (length - 1) / 2).astype(int), 0, width - length)
        for channel in channels:
            amplitude[channel, y] = magnitude[start, channel] * flat * gain[y]
    return dataclasses.replace(demod, amplitude=amplitude)


def line_errors(lines: np.ndarray, truth: simulate.GroundTruth) -> tuple[float, float]:
    """RMS line error (projector lines) on the sphere's and the background's inner pixels."""
    error = lines - truth.proj[..., 1]
    inner = scipy.ndimage.distance_transform_edt(truth.lit & ~truth.edge) > EDGE_DISTANCE
    kept = np.isfinite(error) & inner & (np.abs(error) < 10)
    sphere = truth.points[..., 2] < 990  # the background plane is at 1000 mm
    return tuple(float(np.sqrt(np.mean(error[kept & part] ** 2))) if (kept & part).any() else float("nan")
                 for part in (sphere, ~sphere))


def print_row(name: str, lines: np.ndarray, truth: simulate.GroundTruth) -> None:
    """One table row: `name` and the `line_errors` of `lines` on the sphere and the background."""
    sphere, background = line_errors(lines, truth)
    print(f"{name:42s} {sphere:10.3f} {background:14.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="1296x972")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tiles", type=int, default=4)
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=PROJECTOR)
    spec = patterns.phase_spec(PROJECTOR)
    pattern = patterns.render_pattern(spec)
    realistic = conditions("smooth", args.seed)
    cases = {"realistic": realistic,
             "no noise": dataclasses.replace(realistic, full_well_e=None, read_noise_e=0.0, bit_depth=None),
             "no blur": dataclasses.replace(realistic, projector_blur_px=0.0, camera_blur_px=0.0),
             "uniform albedo": dataclasses.replace(realistic, albedo=simulate.UniformAlbedo(0.8)),
             "ideal": ideal(realistic)}
    print(f"{'capture, decoder':42s} {'sphere rms':>10s} {'background rms':>14s} {'median mm':>9s}  (lines)")
    sphere_scene = simulate.sphere_scene()
    captures, scene_lines = {}, {}  # the sphere scene's decoded lines per row, for the common pixels
    for name, conds in cases.items():
        captures[name] = capture = simulate.render(rig, sphere_scene, pattern, conds)
        result = Scanner(spec, rig.calibration).scan(capture.image)
        scene_lines[name] = result.proj_map
        sphere, background = line_errors(result.proj_map, capture.truth)
        median = accuracy(result, capture.truth, spec, rig.calibration).median_mm
        print(f"{name:42s} {sphere:10.3f} {background:14.3f} {median:9.3f}", flush=True)
    plane = simulate.render(rig, simulate.plane_scene(distance_mm=1000.0), pattern, ideal(realistic))
    result = Scanner(spec, rig.calibration).scan(plane.image)
    print(f"{'ideal, the plane alone':42s} {'-':>10s} {line_errors(result.proj_map, plane.truth)[1]:14.3f} "
          f"{accuracy(result, plane.truth, spec, rig.calibration).median_mm:9.3f}")
    capture = captures["ideal"]
    scanner = Scanner(spec, rig.calibration, reuse_carriers=True)
    scanner.scan(plane.image)  # keeps the plane's carriers for the next frame
    scene_lines["ideal, carriers detected on the plane"] = scanner.scan(capture.image).proj_map
    scene_lines[f"ideal, carriers detected in {args.tiles} strips"] = tiled_lines(Scanner(spec, rig.calibration),
                                                                                capture.image, args.tiles)
    for name in list(scene_lines)[-2:]:
        print_row(name, scene_lines[name], capture.truth)
    capture, scanner = captures["realistic"], Scanner(spec, rig.calibration)
    demod, carriers = scanner.demodulate(capture.image)
    window = int(carriers.window)
    for name, axis in (("realistic / true albedo", None), ("realistic / albedo smoothed along carriers", 1),
                       ("realistic / albedo smoothed along phase", 0)):
        scene_lines[name] = scanner.scan(divided_by_albedo(capture.image, capture.truth.albedo, window, axis)).proj_map
        print_row(name, scene_lines[name], capture.truth)
    decoded = decode(demod, spec, **scanner.decode_options)
    channels = range(spec.bits, spec.bits + len(spec.phase_carriers))
    for name, ramp in (("realistic, window fit solved exactly", False),
                       ("realistic, exactly and the albedo ramp", True)):
        refitted = exact_envelopes(capture.image, demod, carriers, channels, albedo_ramp=ramp)
        scene_lines[name] = fringe.refine(decoded, refitted, carriers, spec, **scanner.fringe_options).proj_map
        print_row(name, scene_lines[name], capture.truth)
    centred = demodulate_window(capture.image, carriers, adaptive=False)
    envelopes = demod.amplitude.copy()
    envelopes[channels] = centred.amplitude[channels]
    name = "realistic, the phase from centred windows"
    scene_lines[name] = fringe.refine(decoded, dataclasses.replace(centred, amplitude=envelopes), carriers, spec,
                                      **scanner.fringe_options).proj_map
    print_row(name, scene_lines[name], capture.truth)
    # Each row keeps its own pixels (noise, for one, changes which pass the decoder's tests), so
    # the rows above differ by their pixel sets too; the same on the pixels every row kept:
    common = np.logical_and.reduce([np.isfinite(lines) for lines in scene_lines.values()])
    print(f"\non the pixels that every sphere-scene row kept ({common.mean():.1%} of the frame):")
    for name, lines in scene_lines.items():
        print_row(name, np.where(common, lines, np.nan), capture.truth)


if __name__ == "__main__":
    main()
