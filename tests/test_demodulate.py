"""Carrier detection and demodulation (thesis 3.3-3.4)."""

import functools
from dataclasses import replace

import numpy as np
import pytest
import scipy.ndimage

from sliscan import InputError, patterns, simulate
from sliscan.decode import decode
from sliscan.demodulate import (STEP_FLAT_BELOW, STEP_SPREAD, Carriers, _albedo_steps, demodulate, demodulate_bandpass,
                                 demodulate_window, detect_carriers, normalise_albedo)
from sliscan.evaluate import true_stripes


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


def phase_channel_lines(envelopes, *, window=40, lines=2, jump_at=None, noise=0.0):
    """Lines of seven carriers k / window (k = 1..7) with the given envelopes ``(7, W)`` on a
    DC of 0.5; past `jump_at` every carrier's phase jumps (a depth edge)."""
    rng = np.random.default_rng(5)
    width = envelopes.shape[1]
    x = np.arange(width)
    phases = rng.uniform(0, 2 * np.pi, (7, 1)) + (0 if jump_at is None else rng.uniform(1, 5, (7, 1)) * (x >= jump_at))
    freqs = np.arange(1, 8) / window
    line = 0.5 + np.sum(envelopes * np.cos(2 * np.pi * freqs[:, None] * x + phases), axis=0)
    image = np.tile(line, (lines, 1)) + noise * rng.standard_normal((lines, width))
    return image.astype(np.float32), Carriers(frequencies=freqs, scale=1.0, window=window)


def test_ramped_fit_follows_envelopes_that_change_along_its_window():
    # a phase channel (the last three carriers) whose envelopes change linearly along the line,
    # as where its fringe crosses the line obliquely: the two-period fit with a ramp per
    # carrier models exactly that, and leaves only the flat field's own error (the box mean of
    # carriers whose envelopes change is not quite the DC); the one-period fit takes each
    # envelope for constant within its window and leaks the change into its neighbours
    width = 640
    x = np.arange(width)
    bits = np.array([0.1, 0.05, 0.08, 0.04])[:, None] * np.ones(width)
    for change, own_error, ramped_error in ((0.0, 1e-5, 1e-5), (0.5, 1e-2, 2.5e-3)):
        phase = np.array([0.08, 0.06, 0.05])[:, None] * (1 + change * (x - width / 2) / width)
        image, carriers = phase_channel_lines(np.vstack([bits, phase]))
        out = demodulate_window(image, carriers, adaptive=False, albedo=None, ramped=range(4, 7))
        inner = slice(50, -50)
        # measured: 1.9e-7 / 6e-8 (constant) and 1.3e-2 / 1.7e-3 of the weakest envelope (0.05)
        own = np.abs(out.amplitude[4:, 0, inner] - phase[:, inner]).max() / 0.05
        ramped = np.abs(out.ramped[:, 0, inner] - phase[:, inner]).max() / 0.05
        assert ramped < ramped_error and (change == 0 or own > max(own_error, 4 * ramped))
    # the window is two periods: the pixels within one period of either end have none
    assert np.isnan(out.ramped[:, :, :39]).all() and np.isnan(out.ramped[:, :, -40:]).all()
    assert np.isfinite(out.ramped[:, :, 39:-40]).all()


def test_one_sided_ramped_fit_gives_an_oblique_fringes_phase_at_the_pixel_next_to_an_edge():
    # the carriers' phases jump at pixel 320 (a depth edge) and the phase channel carries a
    # fringe whose phase changes by 0.01 rad per pixel along the line (its stripes cross the
    # line obliquely): next to the edge the one-period windows that fit best end or start at
    # the pixel and describe the fringe half a window (20 px) away, 0.2 rad off; the two-period
    # window with a ramp per carrier on the same side, evaluated at the pixel
    # (`Demodulated.sided`), is not
    width, x = 640, np.arange(640)
    shifts = 2 * np.pi * np.arange(3)[:, None] / 3
    phase = 1.0 + 0.01 * x
    bits = np.array([0.1, 0.05, 0.08, 0.04])[:, None] * np.ones(width)
    image, carriers = phase_channel_lines(np.vstack([bits, 0.06 * (1 + 0.8 * np.cos(phase - shifts))]), jump_at=320,
                                          lines=4)
    out = demodulate_window(image, carriers, albedo=None, ramped=range(4, 7))

    def error(envelopes: np.ndarray, side: np.ndarray) -> np.ndarray:
        fringe = np.angle(np.sum(envelopes[:, 0, side] * np.exp(1j * shifts), axis=0))
        return np.abs(np.angle(np.exp(1j * (fringe - phase[side]))))

    for side in ((x >= 320) & (x < 335), (x >= 305) & (x < 320)):
        assert np.abs(out.offset[:, side]).min() > 15  # one-sided windows
        # measured: 0.23 rad median (one-period), at most 0.09 (one-sided ramped)
        assert np.median(error(out.amplitude[4:], side)) > 0.2 and error(out.sided, side).max() < 0.12
    # none where the chosen window is centred, nor where the two periods would leave the line
    assert np.isnan(out.sided[:, np.abs(out.offset) < 0.5]).all()
    leaving = ((out.offset > 0.5) & (x + 80 > width)) | ((out.offset < -0.5) & (x - 79 < 0))
    assert np.isnan(out.sided[:, leaving]).all()


def test_ramped_fit_leaves_out_windows_with_an_edge_the_one_period_windows_avoid():
    # the carriers' phases jump at pixel 320 (a depth edge): exactly the pixels whose two-period
    # window (pixel - 39 .. pixel + 40) holds both sides of it have no ramped envelopes
    envelopes = np.array([0.1, 0.05, 0.08, 0.04, 0.08, 0.06, 0.05])[:, None] * np.ones(640)
    image, carriers = phase_channel_lines(envelopes, jump_at=320, noise=0.002, lines=20)
    out = demodulate_window(image, carriers, adaptive=False, albedo=None, ramped=range(4, 7))
    pixel = np.arange(640)
    expected = (pixel >= 39) & (pixel < 640 - 40) & ~((pixel - 39 < 320) & (pixel + 40 >= 320))
    assert np.array_equal(np.isfinite(out.ramped[0]), np.broadcast_to(expected, (20, 640)))


@pytest.mark.parametrize("mean", [0.0, 0.03, -0.03])
def test_lines_whose_carriers_chirp_are_fitted_along_their_scale(mean):
    # seven carriers whose local frequency runs from +5 % to -5 % of the line's along it (a
    # surface turned steeply about the phase direction, seen by a pitched projector): fitted at
    # the line's frequencies, each envelope is 9-16 % off on average; measured and followed
    # (`along_scale`), 0.7-1.8 % (what is left: the scale smoothed over two windows, the cubic
    # resampling).  The same with the whole line 3 % off its scale as well (a projector beside
    # the camera: depth moves the carriers, and a line's scale is its lit surfaces' mean):
    # 10-27 % fitted at the line's frequencies; 0.9-3.0 % followed (15-26 % until the
    # thirty-ninth session, when each line was fitted at its own frequencies after the
    # resampling, so its mean error stayed).  3 % keeps the window whole (34 / 1.03 = 33.0
    # samples); 2 % would leave 0.3 of a sample, and 2.5-7 % of leakage, as on any line whose
    # carriers' spacing is no whole number of pixels
    width, window = 960, 34
    x = np.arange(width)
    warp = x + np.cumsum(mean + 0.05 - 0.1 * x / width)  # the coordinate in which the carriers keep their frequency
    freqs = np.arange(1, 8) / window
    amplitudes = np.array([0.1, 0.05, 0.08, 0.04, 0.08, 0.06, 0.05])
    phases = np.random.default_rng(5).uniform(0, 2 * np.pi, 7)
    line = 0.5 + np.sum(amplitudes[:, None] * np.cos(2 * np.pi * freqs[:, None] * warp + phases[:, None]), axis=0)
    image = np.tile(line, (32, 1)).astype(np.float32)
    carriers = Carriers(frequencies=freqs, scale=1.0, window=window)
    errors = [np.mean(np.abs(demodulate_window(image, carriers, albedo=None, follow_scale=follow).amplitude
                             - amplitudes[:, None, None])[:, :, 50:-50], axis=(1, 2)) / amplitudes
              for follow in (False, True)]
    assert errors[0].min() > 0.08 and errors[1].max() < (0.03 if mean == 0 else 0.04)


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


def test_a_shadow_between_two_edges_stays_dark():
    """A cast shadow on a bright square, a window and 4 px wide between the lit carriers and a
    dark square: its centred windows hold no carrier, but only a box between the three
    placements of the flat field is clean for most of its pixels.  Before the flat field
    looked at every box holding the pixel (fifty-fifth session), the line divided by a flat
    field that ramped across the stretch read 0.17 of the DC on the lowest carrier in its
    middle (a 1280x960 capture's stripe 0 decoded in such a shadow, more than 1 m off); now nothing."""
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.04), slope=0)
    image[:, 300:354] = 0.11  # the window is 50 px
    image[:, 354:] = 0.03
    out = demodulate_window(image, carriers, albedo=None)
    middle = slice(318, 336)
    assert np.all(out.amplitude[:, :, middle] < 1e-3 * out.dc[:, middle])


@pytest.mark.parametrize("follow_scale", [False, True])
def test_the_centred_envelopes_are_those_of_the_centred_fit(follow_scale):
    # a shadow at x = 300 makes the windows next to it one-sided; `Demodulated.centred` keeps
    # what the centred fit (adaptive=False) gives there, with its offsets (0 but within half a
    # window of the line's ends, -0.5 for an even window), and shares the chosen windows' DC;
    # with chirped carriers the lines are resampled (`along_scale`) and taken back alike
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.0, 0.05, 0.02), slope=0)
    if follow_scale:
        x = np.arange(image.shape[1])
        image = np.asarray([np.interp(x + np.cumsum(np.full(x.size, 0.03)) * (x / x.size), x, row) for row in image],
                           np.float32)
    image[:, 300:] = 0.1
    both = demodulate_window(image, carriers, centred=True, follow_scale=follow_scale)
    centred = demodulate_window(image, carriers, adaptive=False, follow_scale=follow_scale)
    assert np.any(both.offset[:, 250:300] != 0)  # one-sided windows next to the shadow
    np.testing.assert_allclose(both.centred.amplitude, centred.amplitude, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(both.centred.offset, centred.offset)
    assert both.centred.dc is both.dc or follow_scale
    np.testing.assert_array_equal(both.centred.dc, both.dc)
    assert demodulate_window(image, carriers).centred is None
    one_line = demodulate_window(image[:1], carriers, centred=True, follow_scale=False)  # a single line too
    np.testing.assert_allclose(one_line.centred.amplitude,
                               demodulate_window(image[:1], carriers, adaptive=False, follow_scale=False).amplitude,
                               rtol=1e-5, atol=1e-7)


def test_columns_orientation_transposes_the_centred_envelopes_too():
    image, carriers = synthetic_lines(lines=64, width=256, window=32)
    spec = patterns.PatternSpec(projector_size=(256, 64), bits=4, carriers=(8.0, 16.0, 24.0, 32.0))
    rows, _ = demodulate(image, spec, carriers=carriers, centred=True)
    cols, _ = demodulate(image.T.copy(), spec.with_(orientation="columns", projector_size=(64, 256)),
                         carriers=carriers, centred=True)
    np.testing.assert_allclose(cols.centred.amplitude, rows.centred.amplitude.transpose(0, 2, 1), atol=1e-6)
    np.testing.assert_array_equal(cols.centred.offset, rows.centred.offset.T)


def test_misfit_judges_a_pixel_from_its_windows_side_of_a_depth_edge():
    """A depth edge at x = 300: another code, other carrier phases and a darker, farther surface
    behind it.  The pixels next to it decode from the window on their own side, and the misfit
    (`Demodulated.misfit`) looks at that side too, so it stays near 0 on both sides; a short
    window centred on them reached across the edge (misfit up to 0.31, above the decoder's
    0.25, before the eleventh session)."""
    left, carriers = synthetic_lines(amplitudes=(0.1, 0.0, 0.05, 0.02), slope=0, rng=np.random.default_rng(1))
    right, _ = synthetic_lines(amplitudes=(0.0, 0.04, 0.02, 0.0), slope=0, dc=0.15, rng=np.random.default_rng(2))
    out = demodulate_window(np.where(np.arange(600) < 300, left, right).astype(np.float32), carriers)
    near = slice(288, 312)  # within a short window (12 px) of the edge on either side
    assert np.all(out.misfit[0, near] < 0.05)


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


def test_a_projector_beside_the_camera_still_shows_every_carrier(monkeypatch):
    """A projector 200 mm above and 65 mm beside the camera (18 degrees off a straight rig; the
    shared data's real rig has 13.6): depth moves the carriers along the lines, and on a sphere
    the frame's spectrum smears the phase channel's carriers into plateaus.  Until the
    thirty-ninth session such captures were refused; each tile's spectrum taken at its own
    scale (`_depth_normalised_contrast`) shows the carriers, and the phase pattern decodes.  A
    capture without the phase carriers (the stripe pattern's, whose four carriers are the phase
    pattern's first four) is still refused: each carrier is left out of its tiles' scale search,
    so noise cannot be lined up on it.  (Through an uncorrected gamma it is not: the projector
    squares the pattern, and the sums of its carriers, 160, 192 and 224 cycles, are there.)"""
    from sliscan import demodulate as module
    from sliscan import evaluate
    from sliscan.pipeline import Scanner

    straight = simulate.virtual_rig(camera_size=(1296, 972), projector_size=(1024, 768))
    fov = float(np.degrees(2 * np.arctan(512 / straight.projector.K[0, 0])))
    rig = simulate.virtual_rig(camera_size=(1296, 972), projector_size=(1024, 768), projector_fov_deg=fov,
                               projector_offset_mm=65.0)
    conditions = simulate.Conditions(albedo=simulate.SmoothAlbedo(low=0.15, high=1.0, seed=7), ambient=0.1,
                                     projector_gamma=2.2, projector_blur_px=1.0, camera_blur_px=1.0, seed=7,
                                     supersample=1)
    spec = patterns.phase_spec((1024, 768))
    capture = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions)
    accuracy = evaluate.accuracy(Scanner(spec, rig.calibration).scan(capture.image), capture.truth, spec,
                                 rig.calibration)
    # measured (seed 7): 86.5 % complete, median 0.56 mm, RMS 5.1 mm (robustness benchmark at 65 mm, seeds 0-1:
    # 84.0 %, 0.77, 5.6; the straight rig 90.9 %, 0.57, 2.9)
    assert accuracy.completeness > 0.75 and accuracy.median_mm < 1.5 and accuracy.rms_mm < 8
    stripes = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(patterns.default_spec((1024, 768))),
                              replace(conditions, projector_gamma=1.0))  # a gamma would put their products there
    with pytest.raises(InputError, match="carriers near 160, 192, 224 cycles/width not found"):
        detect_carriers(stripes.image, spec)
    monkeypatch.setattr(module, "_depth_normalised_contrast", lambda img, proj, scale, which: np.zeros(len(which)))
    with pytest.raises(InputError, match="not found"):
        detect_carriers(capture.image, spec)


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
    (`window_reference.fit_lines`: a pseudo-inverse per window, the model evaluated sample by
    sample) computes, on a realistic capture with shadows, edges and gamma, to float32
    rounding, on lines of several window lengths."""
    from window_reference import fit_lines

    from sliscan.demodulate import _short_window

    spec = patterns.default_spec((1024, 768))
    conditions = simulate.Conditions(albedo=simulate.CheckerAlbedo(square_mm=40, low=0.25, high=0.9), ambient=0.1,
                                     projector_gamma=2.2, projector_blur_px=1.0, camera_blur_px=1.0, seed=2)
    image = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions).image
    carriers = detect_carriers(image, spec)
    out = demodulate_window(image, carriers, adaptive=adaptive, albedo=None, follow_scale=False, workers=2)
    assert np.ptp(carriers.line_windows()) >= 2  # windows of several lengths
    for lines in (np.arange(0, 480, 12), np.arange(5, 480, 12)):
        unexplained, var, dc, amp, misfit, offset = fit_lines(image, carriers, lines, _short_window(carriers),
                                                              adaptive=adaptive)
        np.testing.assert_allclose(out.dc[lines], dc, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out.amplitude[:, lines], amp, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(out.misfit[lines], misfit, rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(out.offset[lines], offset)
        np.testing.assert_allclose(out.residual[lines], unexplained / np.maximum(var, 1e-12), rtol=1e-4, atol=1e-6)


def test_albedo_steps_are_found_and_divided_out():
    """A reflectance step (0.25 -> 0.9) under the carriers, blurred as a camera blurs it (a
    Gaussian of 1 px about 309.5), is found with its height where its log is half-way (the
    level changes at 309: the log is half-way 0.4 px before the edge's middle, and the
    detector's boxes place it half a pixel earlier still); the estimate renders it blurred
    (`STEP_SPREAD`, the ratio being flat over it) 0.4 px toward its bright side, which halves
    the estimate's error beside it (RMS over 20 px 24 % -> 11 %, at worst 102 % -> 35 %), and
    dividing it out gives back the envelope ratios the decoder uses."""
    amplitudes = np.array([0.1, 0.05, 0.08, 0.1])
    image, carriers = synthetic_lines(amplitudes=tuple(amplitudes), slope=0, dc=0.35, noise=0.003,
                                      rng=np.random.default_rng(1))
    albedo = scipy.ndimage.gaussian_filter1d(np.where(np.arange(600) >= 310, 0.9, 0.25), 1.0).astype(np.float32)
    _, sharp = normalise_albedo(image * albedo, carriers, estimate="sharp-steps")
    jumps = np.diff(np.log(sharp), axis=1)
    assert np.array_equal(np.nonzero(jumps)[1], [308] * 4)  # every line: one step, at 309
    np.testing.assert_allclose(jumps[:, 308], np.log(0.9 / 0.25), atol=0.02)
    _, soft = normalise_albedo(image * albedo, carriers)
    error = {name: (estimate / estimate[:, :1] / (albedo / 0.25) - 1)[:, 300:320] for name, estimate in
             (("sharp", sharp), ("soft", soft))}
    assert np.sqrt(np.mean(error["soft"] ** 2)) < 0.5 * np.sqrt(np.mean(error["sharp"] ** 2))
    assert np.abs(error["soft"]).max() < 0.4
    # around the step the window straddling it is what it is: the ratio's worst error there
    # drops from 0.27 (lowest carrier) to 0.11 with the sharp step, 0.06 with the soft one
    # (means 0.023, 0.0034, 0.0028)
    near = slice(280, 340)
    expected = amplitudes[:, None] / 0.35

    def ratio_error(estimate):
        out = demodulate_window(image * albedo, carriers, albedo=estimate)
        return np.abs(out.amplitude[:, 0, near] / out.dc[0, near] - expected).max()

    assert ratio_error("steps") < 0.08
    assert ratio_error("sharp-steps") > 1.5 * ratio_error("steps")
    assert ratio_error(None) > 0.2


def _steps_found(estimate):
    """(line, pixel, log height) of every step of a `normalise_albedo` estimate."""
    jumps = np.diff(np.log(estimate), axis=1)
    lines, at = np.nonzero(jumps)
    return [(int(r), int(x) + 1, float(jumps[r, x])) for r, x in zip(lines, at)]


def test_albedo_steps_keep_both_edges_of_a_strip_narrower_than_a_window():
    """A dark strip 0.6 windows wide (a checker square seen obliquely): both edges are found,
    at their pixels, with their heights.  (The detector before the twelfth session summed the
    lag ratio over whole windows, where the two edges' signs cancel, and found neither.)"""
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003,
                                      rng=np.random.default_rng(4))
    albedo = np.where((np.arange(600) >= 300) & (np.arange(600) < 330), 0.25, 0.9).astype(np.float32)
    found = _steps_found(normalise_albedo(image * albedo, carriers, estimate="sharp-steps")[1])
    assert [(r, x) for r, x, _ in found] == [(r, x) for r in range(4) for x in (300, 330)]
    np.testing.assert_allclose([abs(h) for _, _, h in found], np.log(0.9 / 0.25), atol=0.03)


def test_albedo_steps_find_the_edges_of_a_lower_contrast_checker():
    """A square of 0.3 under a checker's 0.8 (a log step of 0.98, under the threshold of 1.0
    until the forty-seventh session, when such a checker was the worst decoded of all) 1.5
    windows wide: both edges found, at their pixels, with their heights; a step of a third
    of that (0.6 / 0.8: a reflectance ratio of 1.33) is left to the flat field."""
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003,
                                      rng=np.random.default_rng(6))
    x = np.arange(600)
    albedo = np.where((x >= 250) & (x < 325), 0.3, 0.8).astype(np.float32)
    found = _steps_found(normalise_albedo(image * albedo, carriers, estimate="sharp-steps")[1])
    assert [(r, at) for r, at, _ in found] == [(r, at) for r in range(4) for at in (250, 325)]
    np.testing.assert_allclose([abs(h) for _, _, h in found], np.log(0.8 / 0.3), atol=0.03)
    faint = np.where((x >= 250) & (x < 325), 0.6, 0.8).astype(np.float32)
    assert np.all(normalise_albedo(image * faint, carriers)[1] == 1)


def test_albedo_steps_must_be_as_sharp_as_the_optics_blur_them():
    """`STEP_SHARPNESS`: a 0.3 / 0.8 edge blurred by a Gaussian of 1.5 px is found on every line
    (of 20; 2 px: 37 of 40 edges, 2.5 px: 5, measured), but the same rise as a linear ramp over
    a fifth of a window (10 px: a steep smooth albedo) on none, which without the test is found
    on every line; a ramp of 1.3 over 10 px, found with the threshold of 1.0 before the
    forty-seventh session, neither."""
    image, _ = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003,
                               rng=np.random.default_rng(8), lines=20)
    x, windows = np.arange(600), np.full(20, 50)

    def lines_with_steps(albedo, **options):
        estimate = _albedo_steps(image * albedo.astype(np.float32), windows, soft=False, **options)
        return int(np.any(np.diff(np.log(estimate), axis=1) != 0, axis=1).sum())

    edge = scipy.ndimage.gaussian_filter1d(np.where((x >= 300) & (x < 375), 0.3, 0.8), 1.5)
    assert lines_with_steps(edge) == 20

    def ramp(height):
        return np.exp(height * np.clip((x - 300) / 10, 0, 1) - height * np.clip((x - 380) / 10, 0, 1))

    assert lines_with_steps(ramp(np.log(0.8 / 0.3))) == 0
    assert lines_with_steps(ramp(np.log(0.8 / 0.3)), sharpness=0.0) == 20
    assert lines_with_steps(ramp(1.3)) == 0


def test_albedo_steps_must_rise_within_a_box():
    """`STEP_CONCENTRATION`: on noisier lines (noise 0.01 on a DC of 0.35) a 0.55 / 0.9 edge (a
    log step of 0.49, under the threshold of 0.8 until the forty-eighth session) blurred by
    1 px is found on every line, within a pixel of its own; smooth rises of 0.8 over 15 px and
    1.3 over 20 px, whose noise gets some candidates past the sharpness test, on none, where
    without the concentration test on 6 and 9 lines of 20 (measured): their change across the
    6 px boxes is about a third of their height."""
    image, _ = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.01,
                               rng=np.random.default_rng(10), lines=20)
    x, windows = np.arange(600), np.full(20, 50)

    def steps(albedo, **options):
        estimate = _albedo_steps(image * albedo.astype(np.float32), windows, soft=False, **options)
        return np.diff(np.log(estimate), axis=1) != 0

    edge = steps(scipy.ndimage.gaussian_filter1d(np.where((x >= 300) & (x < 375), 0.55, 0.9), 1.0))
    assert edge[:, 298:301].any(axis=1).all()  # at its pixel or the next (noise)
    for height, length in ((0.8, 15), (1.3, 20)):
        rise = np.exp(height * np.clip((x - 300) / length, 0, 1) - height * np.clip((x - 380) / length, 0, 1))
        assert steps(rise).sum() == 0
        assert steps(rise, concentration=0.0).any(axis=1).sum() >= 4


def test_albedo_steps_under_the_old_threshold_must_be_flat():
    """`STEP_FLAT_BELOW`: light without the pattern added right of a pixel (a pedestal of 0.5 on
    the lines' 0.35, as at a limb or a shadow's border: the ratio one window back swings with
    the pattern) rises by a log step of 0.86, sharply; it is no albedo edge and is not kept,
    where without the flatness test every line keeps it."""
    image, _ = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003,
                               rng=np.random.default_rng(9), lines=20)
    lit = np.where(np.arange(600) >= 300, image + 0.5, image).astype(np.float32)
    windows = np.full(20, 50)

    def lines_with_steps(**options):
        estimate = _albedo_steps(lit, windows, soft=False, **options)
        return int(np.any(np.diff(np.log(estimate), axis=1) != 0, axis=1).sum())

    assert lines_with_steps() == 0
    assert lines_with_steps(flat_below=0.0) == 20


def test_albedo_steps_ignore_a_depth_edge_and_a_steps_echo_at_a_line_end():
    """The pattern shifted by 0.3 windows (a depth edge: the ratio one window back oscillates
    with the pattern) is no step; a step 20 px before the last window is found once, not again
    where its echo falls a window later (only one view of that exists so close to the end);
    and a step within the first window (seen only one window later) is found."""
    rng = np.random.default_rng(5)
    x = np.arange(600)
    shift = np.where(x >= 300, 0.3 * 50, 0.0)
    line = 0.35 + sum(a * np.cos(2 * np.pi * k * (x + shift) / 50 + p)
                      for k, a, p in zip(range(1, 5), (0.1, 0.05, 0.08, 0.1), rng.uniform(0, 2 * np.pi, 4)))
    shifted = (np.tile(line, (4, 1)) + 0.003 * rng.standard_normal((4, 600))).astype(np.float32)
    carriers = Carriers(frequencies=np.arange(1, 5) / 50, scale=1.0, window=50)
    assert np.all(normalise_albedo(shifted, carriers)[1] == 1)
    image, _ = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003, rng=rng)
    for edge in (530, 30):
        albedo = np.where(x >= edge, 0.9, 0.25).astype(np.float32)
        found = _steps_found(normalise_albedo(image * albedo, carriers, estimate="sharp-steps")[1])
        assert [(r, at) for r, at, _ in found] == [(r, edge) for r in range(4)]
        np.testing.assert_allclose([h for _, _, h in found], np.log(0.9 / 0.25), atol=0.03)


def test_albedo_steps_leave_a_smooth_albedo_alone():
    """No step on plain lines, nor on a smooth reflectance bump as high as the step above
    (a factor 3.3) and about a window wide, which the flat field handles."""
    image, carriers = synthetic_lines(amplitudes=(0.1, 0.05, 0.08, 0.1), slope=0, dc=0.35, noise=0.003,
                                      rng=np.random.default_rng(2))
    assert np.all(normalise_albedo(image, carriers)[1] == 1)
    bump = np.exp(1.2 * np.exp(-0.5 * ((np.arange(600) - 300) / 40.0) ** 2)).astype(np.float32)
    assert np.all(normalise_albedo(image * bump, carriers)[1] == 1)


def test_albedo_normalisation_decodes_a_checker_better(small_rig):
    """On a sharp checker (0.25 / 0.9, 40 mm squares: ~50 camera pixels, two windows) the
    default albedo step normalisation decodes more pixels right and fewer more than a stripe
    wrong than the plain window demodulator, and changes nothing on a smooth albedo.

    Measured on this tilted plane, seeds 0-3 (the checker is fixed, only the noise changes):
    stripe accuracy 0.62-0.63 -> 0.71-0.72, wrong stripes 0.6 % -> 0.02-0.03 %; smooth albedo
    within 0.002 either way (seed 3, this test: 0.904 both).  The margins (0.05, half the wrong stripes, 0.01)
    leave room for noise, not for the normalisation doing nothing.
    """
    spec = patterns.default_spec((1024, 768))

    def figures(albedo, estimate):
        texture = (simulate.CheckerAlbedo(square_mm=40, low=0.25, high=0.9) if albedo == "checker"
                   else simulate.SmoothAlbedo(low=0.15, high=1.0, seed=3))
        conditions = simulate.Conditions(albedo=texture, ambient=0.1, projector_gamma=2.2, seed=3, supersample=2)
        capture = simulate.render(small_rig, simulate.tilted_plane_scene(25), patterns.render_pattern(spec), conditions)
        truth = true_stripes(capture.truth, spec)
        lit = truth >= 0
        decoded = decode(demodulate(capture.image, spec, albedo=estimate)[0], spec)
        valid = decoded.valid & lit
        return ((valid & (decoded.stripe == truth)).sum() / lit.sum(),
                (valid & (np.abs(decoded.stripe - truth) > 1)).sum() / lit.sum())

    (plain, plain_wrong), (steps, steps_wrong) = figures("checker", None), figures("checker", "steps")
    assert steps >= plain + 0.05
    assert steps_wrong <= 0.5 * plain_wrong
    assert figures("smooth", "steps")[0] == pytest.approx(figures("smooth", None)[0], abs=0.01)


@functools.lru_cache(maxsize=1)
def _checkered_sphere_640():
    """The sphere under a 0.25 / 0.9 checker on the 640x480 rig: (capture, image in [0, 1],
    windows per line).  Squares narrower than a window along its limb, steps near the lines'
    ends."""
    rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768))
    spec = patterns.default_spec((1024, 768))
    conditions = simulate.Conditions(albedo=simulate.CheckerAlbedo(square_mm=40, low=0.25, high=0.9), seed=2)
    capture = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions)
    image = capture.image
    img = np.asarray(image, np.float32) / np.float32(255) if image.dtype == np.uint8 else np.asarray(image, np.float32)
    return capture, img, np.broadcast_to(detect_carriers(img, spec).line_windows(), (img.shape[0],))


@pytest.mark.parametrize("blur", [STEP_SPREAD, 2.0])
def test_albedo_steps_kernel_equals_the_numpy_form(blur):
    """At the assumed blur and at a blurrier camera's, whose tests are looser."""
    from albedo_reference import albedo_steps

    _, img, windows = _checkered_sphere_640()
    kernel, reference = _albedo_steps(img, windows, blur=blur, soft=False), albedo_steps(img, windows, blur=blur)
    assert np.mean(reference != 1) > 0.2  # the checker's steps were found
    # the same sums in another order: a step at a threshold may flip
    assert np.mean(np.isclose(kernel, reference, rtol=1e-4)) > 0.999


def test_albedo_steps_blur_the_albedo_edges_and_keep_the_others_sharp():
    """The steps over which the lag ratio is flat are blurred (`STEP_FLAT`): on the checkered
    sphere nearly all of those within 2 px of a true albedo edge (measured 96.0 %, 5903 of 6146;
    93-95 % before the forty-eighth session), few of the others at least as high as
    `STEP_FLAT_BELOW` (at the limb and the shadows, where the ratio swings with the pattern:
    28 %, 38 of 134; 25 %, 35 of 138, before).  A lower step is kept only if flat, so always
    blurred (256 of them, 54 not near a true edge, mostly beside the limb and the shadows; 84
    and 13 before the threshold was lowered).  A blurred step keeps its levels either side of
    the blur."""
    capture, img, windows = _checkered_sphere_640()
    h, w = img.shape
    sharp, soft = _albedo_steps(img, windows, soft=False), _albedo_steps(img, windows)
    heights = np.zeros((h, w))
    heights[:, 1:] = np.diff(np.log(sharp), axis=1)
    step = heights != 0
    tall = np.abs(heights) >= STEP_FLAT_BELOW
    blurred = step & scipy.ndimage.maximum_filter1d(~np.isclose(soft, sharp, rtol=1e-6), 3, axis=1)
    log_albedo = np.log(np.where(np.isfinite(capture.truth.albedo), capture.truth.albedo, 1.0))
    edge = np.zeros((h, w), bool)
    edge[:, 1:] = np.abs(np.diff(log_albedo, axis=1)) > 0.5
    near = scipy.ndimage.maximum_filter1d(edge, 5, axis=1)
    assert (blurred & near).sum() >= 0.85 * (step & near).sum()
    assert (blurred & tall & ~near).sum() <= 0.4 * (tall & ~near).sum()
    beyond = ~scipy.ndimage.maximum_filter1d(step, 2 * 4 + 1, axis=1)  # farther from a step than the blur's reach
    np.testing.assert_allclose(soft[beyond], sharp[beyond], rtol=1e-4)  # the blur's tails under 1e-4


def test_albedo_steps_read_both_ways_find_more_true_edges():
    """A step missed along a line spoils the heights of the next ones within a window; read
    the other way, the heights are measured on the other side.  On the checkered sphere the
    two ways find more of the true edges (steps of the rendered albedo by more than a factor
    1.65) than the left-to-right reading alone, within 2 px: measured 72.9 -> 75.4 % (with the
    threshold of 1.0 until the forty-seventh session 69.6 -> 71.9 %; seed 3: 69.5 -> 71.8 %;
    800x600: 74.1 -> 76.1 %), with 2.5 % of the steps more than 2 px from a true edge (one
    way: 1.5 %; 1.7 and 1.1 % with the threshold of 1.0).  Margins: 1.5 points gained, 3.5 %
    stray."""
    capture, img, windows = _checkered_sphere_640()
    h, w = img.shape

    def steps(both_ways):
        found = np.zeros((h, w), bool)
        found[:, 1:] = np.diff(np.log(_albedo_steps(img, windows, both_ways=both_ways, soft=False)), axis=1) != 0
        return found

    one_way, two_ways = steps(False), steps(True)
    log_albedo = np.log(np.where(np.isfinite(capture.truth.albedo), capture.truth.albedo, 1.0))
    true_edge = np.zeros((h, w), bool)
    true_edge[:, 1:] = np.abs(np.diff(log_albedo, axis=1)) > 0.5
    near = functools.partial(scipy.ndimage.maximum_filter1d, size=5, axis=1)

    def found_and_stray(steps):
        return (true_edge & near(steps)).sum() / true_edge.sum(), (steps & ~near(true_edge)).sum() / steps.sum()

    (found_one, _), (found_two, stray_two) = found_and_stray(one_way), found_and_stray(two_ways)
    assert found_two >= found_one + 0.015
    assert stray_two <= 0.035


def test_the_scale_map_is_the_mean_of_the_measurements_in_its_box():
    """`scale_map` against a direct sum over each box, the frame's ends repeated (sparse
    measurements, as `_fit_line` leaves them: every 8th line and pixel, some missing)."""
    from numpy.lib.stride_tricks import sliding_window_view

    from sliscan.demodulate import FOLLOW_SCALE_LINES, FOLLOW_SCALE_WINDOWS, Carriers, scale_map

    rng = np.random.default_rng(3)
    scale = np.full((61, 150), np.nan, np.float32)
    scale[::8, ::8] = rng.normal(0.0, 0.02, scale[::8, ::8].shape)
    scale[rng.random(scale.shape) < 0.3] = np.nan
    carriers = Carriers(frequencies=np.array([0.1, 0.2]), scale=1.0, window=10)
    across, along = FOLLOW_SCALE_LINES, FOLLOW_SCALE_WINDOWS * 10
    finite = np.isfinite(scale)
    padded = [np.pad(a, ((across // 2, across - across // 2 - 1), (along // 2, along - along // 2 - 1)), mode="edge")
              for a in (np.where(finite, scale, 0.0).astype(np.float64), finite.astype(np.float64))]
    total, count = (sliding_window_view(a, (across, along)).sum(axis=(-2, -1)) for a in padded)
    error, measured = scale_map(scale, carriers)
    assert np.array_equal(measured, count > 0) and 0 < measured.mean() < 1  # some boxes hold none
    np.testing.assert_allclose(error[measured], total[measured] / count[measured], rtol=1e-9, atol=1e-15)
    assert (error[~measured] == 0).all()
