"""Carrier detection and demodulation (thesis 3.3-3.4)."""

import numpy as np
import pytest

from sliscan import InputError, patterns, simulate
from sliscan.demodulate import Carriers, demodulate, demodulate_bandpass, demodulate_window, detect_carriers


def synthetic_lines(width=600, lines=4, *, window=50, amplitudes=(0.1, 0.0, 0.05, 0.02), slope=0.0005, dc=0.4,
                    noise=0.0, rng=None):
    """Lines of carriers k / window (k = 1..4) on a DC ramp, with random phases."""
    rng = rng or np.random.default_rng(0)
    x = np.arange(width)
    freqs = np.arange(1, len(amplitudes) + 1) / window
    phases = rng.uniform(0, 2 * np.pi, len(amplitudes))
    line = dc + slope * (x - width / 2) + sum(a * np.cos(2 * np.pi * f * x + p)
                                              for a, f, p in zip(amplitudes, freqs, phases))
    image = np.tile(line, (lines, 1)) + noise * rng.standard_normal((lines, width))
    return image.astype(np.float32), Carriers(frequencies=freqs, scale=1.0, window=window)


def test_window_fit_recovers_amplitudes_on_a_ramp():
    image, carriers = synthetic_lines()
    out = demodulate_window(image, carriers, adaptive=False)
    inner = slice(60, -60)
    # The fit is exact for a DC ramp, but the line is first divided by its box mean, which
    # turns the ramp into a slow change of the carriers' relative amplitude (6 % across a
    # window here): the amplitudes come back within 3 % (atol 3e-3 on 0.1).
    np.testing.assert_allclose(out.amplitude[:, 0, inner],
                               np.array([0.1, 0.0, 0.05, 0.02])[:, None] * np.ones((1, 480)), atol=3e-3)
    centre = np.arange(600)[inner] - 0.5  # an even window's centre is half a pixel left
    np.testing.assert_allclose(out.dc[0, inner], 0.4 + 0.0005 * (centre - 300), atol=2e-3)  # 0.5 %, as above
    assert np.all(out.residual[0, inner] < 1e-3)


def test_window_fit_noise_estimate_matches_noise():
    image, carriers = synthetic_lines(lines=50, noise=0.01, rng=np.random.default_rng(3))
    out = demodulate_window(image, carriers)
    # amplitude noise of a correlation over L samples: sigma * sqrt(2 / L)
    expected = 0.01 * np.sqrt(2 / 50)
    assert np.median(out.noise[:, 60:-60]) == pytest.approx(expected, rel=0.15)
    # a strong carrier's amplitude error is its in-phase noise, sigma * sqrt(2 / L); the
    # lowest carrier (one period per window) shares variance with the ramp, so skip it
    err = out.amplitude[2:, :, 60:-60] - np.array([0.05, 0.02])[:, None, None]
    np.testing.assert_allclose(np.std(err, axis=(1, 2)), expected, rtol=0.2)


def test_adaptive_window_keeps_a_step_out():
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.0, 0.0, 0.0), slope=0)
    image[:, 300:] = 0.1  # a shadow: ambient only, no carrier
    adaptive = demodulate_window(image, carriers)
    centred = demodulate_window(image, carriers, adaptive=False)
    near = slice(300 - 20, 300)  # lit pixels within half a window of the shadow
    # the decoder uses carrier over DC: 0.1 / 0.4 on the lit side
    adaptive_ratio = adaptive.amplitude[0, 0, near] / adaptive.dc[0, near]
    centred_ratio = centred.amplitude[0, 0, near] / centred.dc[0, near]
    # one-sided windows keep most of the shadow out: at most half the centred fit's error
    adaptive_error = np.abs(adaptive_ratio - 0.25).mean()
    assert adaptive_error < 0.5 * np.abs(centred_ratio - 0.25).mean()
    assert np.all(adaptive.amplitude[0, 0, 305:320] < 1e-3)  # shadow side stays dark


def test_bandpass_demodulator_recovers_amplitudes():
    image, carriers = synthetic_lines(width=1200, slope=0)
    out = demodulate_bandpass(image, carriers)
    inner = slice(200, -200)
    # Butterworth pass band is not flat and leaks between neighbours: a few per cent
    np.testing.assert_allclose(out.amplitude[[0, 2], 0, inner].mean(axis=1), [0.1, 0.05], rtol=0.05)


def test_detect_carriers_on_a_plane(small_rig):
    spec = patterns.thesis_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.plane_scene(), patterns.render_pattern(spec),
                              simulate.Conditions(seed=1, supersample=1))
    carriers = detect_carriers(capture.image, spec)
    truth = capture.truth.proj[..., 0]
    rows = np.nanmedian(np.diff(truth, axis=1), axis=1)  # projector px per camera px, per row
    ok = np.isfinite(rows)
    # the per-line scale follows the rig's perspective to a fraction of a per cent
    np.testing.assert_allclose(carriers.line_scale[ok], rows[ok], rtol=0.01)
    assert carriers.window == round(1024 / 32 / carriers.scale)


def test_detect_carriers_rejects_a_capture_without_them(rng):
    spec = patterns.thesis_spec((1024, 768))
    with pytest.raises(InputError, match="no carriers found near"):
        detect_carriers(rng.uniform(0.4, 0.6, (240, 320)).astype(np.float32), spec)


def test_columns_orientation_is_the_transpose():
    image, carriers = synthetic_lines(lines=64, width=256, window=32)
    spec = patterns.PatternSpec(projector_size=(256, 64), bits=4, carriers=(8.0, 16.0, 24.0, 32.0))
    rows, _ = demodulate(image, spec, carriers=carriers)
    cols, _ = demodulate(image.T.copy(), spec.with_(orientation="columns", projector_size=(64, 256)),
                         carriers=carriers)
    np.testing.assert_allclose(cols.amplitude, rows.amplitude.transpose(0, 2, 1), atol=1e-6)


def test_bad_method():
    with pytest.raises(InputError, match="method must be"):
        demodulate(np.zeros((10, 10)), patterns.thesis_spec((1024, 768)), method="fft")


@pytest.mark.parametrize("adaptive", [True, False])
def test_window_kernel_equals_the_numpy_fit(small_rig, adaptive):
    """The compiled per-line kernel computes what the straightforward numpy fit
    (`window_reference.fit_lines`, sliscan's implementation before the kernel) computes, on a
    realistic capture with shadows, edges and gamma, to float32 rounding."""
    from window_reference import fit_lines

    from sliscan.demodulate import _short_window

    spec = patterns.default_spec((1024, 768))
    conditions = simulate.Conditions(albedo=simulate.CheckerAlbedo(square_mm=40, low=0.25, high=0.9), ambient=0.1,
                                     projector_gamma=2.2, projector_blur_px=1.0, camera_blur_px=1.0, seed=2)
    image = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions).image
    carriers = detect_carriers(image, spec)
    out = demodulate_window(image, carriers, adaptive=adaptive, workers=2)
    windows = np.broadcast_to(carriers.line_windows(), (image.shape[0],))
    for window in np.unique(windows)[:3]:
        lines = np.flatnonzero(windows == window)[:40]
        unexplained, var, dc, amp, misfit = fit_lines(image, carriers, lines, int(window), _short_window(carriers),
                                                      adaptive=adaptive)
        np.testing.assert_allclose(out.dc[lines], dc, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out.amplitude[:, lines], amp, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out.misfit[lines], misfit, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out.residual[lines], unexplained / np.maximum(var, 1e-12), rtol=1e-4, atol=1e-6)
