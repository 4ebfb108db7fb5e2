"""Phase measuring profilometry: patterns (eq. 2.1), phase (eq. 2.3), unwrapping, and scans of the virtual rig."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.ndimage

from sliscan import InputError, PatternSpec, Scanner, evaluate, patterns, simulate
from sliscan.pmp import _atan2_turns, decode_pmp, fit_fringes, fringe_profile, noise_level, pattern_frames, unwrap_step
from sliscan.sequences import render_frames

PROJECTOR = (1024, 768)
#: 3 frequencies x 4 steps: the finest fringe has a period of 768 / 64 = 12 projector rows.
SPEC = PatternSpec(kind="pmp", projector_size=PROJECTOR, steps=4, frequencies=(1.0, 8.0, 64.0), b_p=0.5)
FINEST_PERIOD = 768 / 64


def realistic(seed: int) -> simulate.Conditions:
    """Issue 2's conditions (smooth albedo 0.15-1, ambient 10 %, uncorrected gamma 2.2, 1 px blur, shot and read
    noise, 8 bits) at one sample per pixel, to keep the renders quick."""
    return simulate.Conditions(albedo=simulate.SmoothAlbedo(seed=seed), seed=seed, supersample=1)


def true_rows(truth: simulate.GroundTruth) -> np.ndarray:
    return np.where(truth.lit, truth.proj[..., 1], np.nan)


def smooth_region(truth: simulate.GroundTruth) -> np.ndarray:
    """Lit pixels whose 7x7 neighbourhood is lit, free of edges and of steps of the true row of half a finest period
    or more between neighbours: there a period jump is the decoder's fault, not a pixel seeing two surfaces (the
    camera blur, sigma 1 px, mixes light from about 3 px away)."""
    yp = true_rows(truth)
    step = np.fmax(np.abs(np.diff(yp, axis=0, prepend=np.nan)), np.abs(np.diff(yp, axis=1, prepend=np.nan)))
    rough = ~truth.lit | truth.edge | ~(step < FINEST_PERIOD / 2)
    return ~scipy.ndimage.binary_dilation(rough, iterations=3)


@pytest.fixture(scope="module")
def sphere(small_rig):
    return simulate.render_sequence(small_rig, simulate.sphere_scene(), render_frames(SPEC), realistic(0))


# ------------------------------------------------------------------------------------ the spec


def test_spec_json_round_trip_and_frame_count(tmp_path):
    spec = SPEC.with_(orientation="both", gamma=2.2)
    spec.save(tmp_path / "pmp.json")
    assert PatternSpec.load(tmp_path / "pmp.json") == spec
    assert spec.frame_count == 2 * 3 * 4
    saved = json.loads((tmp_path / "pmp.json").read_text())
    assert "carriers" not in saved and saved["frequencies"] == [1.0, 8.0, 64.0]  # the composite fields are not its


@pytest.mark.parametrize("changes, message", [
    (dict(steps=2), "steps >= 3"),
    (dict(frequencies=()), "increasing"),
    (dict(frequencies=(1.0, 8.0, 8.0)), "increasing"),
    (dict(frequencies=(2.0, 8.0)), "start at 1"),
    (dict(frequencies=(1.0, 400.0)), "(0, 384)"),
    (dict(b_p=0.6), "a_p +/- b_p"),
    (dict(orientation="diagonal"), "orientation"),
    (dict(frames=("a.png",)), "frames must list 12 files"),
])
def test_spec_refuses(changes, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace("+", r"\+")) as exc:
        SPEC.with_(**changes)
    assert "\n" not in str(exc.value)


# ------------------------------------------------------------------------------------ patterns


def test_frames_follow_eq_2_1_in_projection_order():
    spec = SPEC.with_(projector_size=(64, 48), frequencies=(1.0, 4.0), orientation="both")
    frames = pattern_frames(spec)
    assert frames.shape == (spec.frame_count, 48, 64) and frames.dtype == np.float32
    k = 0
    for direction, lines in (("columns", 64), ("rows", 48)):
        for f in spec.frequencies:
            for n in range(spec.steps):
                profile = frames[k][0] if direction == "columns" else frames[k][:, 0]
                # 8-bit quantisation: within half a level of eq. 2.1, and constant across the lines
                np.testing.assert_allclose(profile, fringe_profile(lines, f, n, 4, 0.5, 0.5), atol=0.5 / 255 + 1e-7)
                assert np.ptp(frames[k], axis=1 if direction == "rows" else 0).max() == 0
                k += 1


def test_gamma_precorrection():
    frames = pattern_frames(SPEC.with_(gamma=2.2, projector_size=(64, 48), frequencies=(1.0,)))
    linear = fringe_profile(48, 1.0, 0, 4, 0.5, 0.5)
    # the drive raised to the gamma gives the wanted light back, up to the quantisation of the drive
    # (d ** 2.2 has slope at most 2.2, so half a level of drive is at most 1.1 levels of light)
    np.testing.assert_allclose(frames[0][:, 0].astype(np.float64) ** 2.2, linear, atol=1.1 / 255)


# ------------------------------------------------------------------------------------ phase


@pytest.mark.parametrize("steps", [3, 4, 5, 8])
def test_fit_recovers_phase_modulation_and_dc(steps, rng):
    phase = rng.uniform(0, 2 * np.pi, (7, 9))
    a, b = rng.uniform(0.3, 0.5, (7, 9)), rng.uniform(0.05, 0.3, (7, 9))
    frames = np.stack([a + b * np.cos(phase - 2 * np.pi * n / steps) for n in range(steps)]).astype(np.float32)
    fit = fit_fringes(frames)
    # float32 arithmetic: 1e-5 of a cycle, 1e-5 of the unit intensity
    assert np.abs((fit.cycles - phase / (2 * np.pi) + 0.5) % 1 - 0.5).max() < 1e-5
    np.testing.assert_allclose(fit.modulation, b, atol=1e-5)
    np.testing.assert_allclose(fit.dc, a, atol=1e-5)
    assert fit.residual.max() < 1e-9


def test_noise_level_of_gaussian_noise(rng):
    shape = (200, 200)
    phase = rng.uniform(0, 2 * np.pi, shape)
    sigma = 0.01
    fits = [fit_fringes(np.stack([0.4 + 0.2 * np.cos(f * phase - np.pi * n / 2) + rng.normal(0, sigma, shape)
                                  for n in range(4)]).astype(np.float32)) for f in (1, 8, 64)]
    # 40000 pixels: the median of the chi-square estimate is within a few % of sigma
    assert noise_level(fits, 4) == pytest.approx(sigma, rel=0.05)


def test_unwrap_step_picks_the_nearest_order():
    coarse = np.float32([[100.0, 105.9, 94.1]])  # all within half a period (6) of row 100
    cycles = np.float32([[(100 % 12) / 12] * 3])
    coord, order, distance = unwrap_step(coarse, cycles, 12.0)
    np.testing.assert_allclose(coord, 100.0, atol=1e-4)
    assert order.tolist() == [[8, 8, 8]]
    np.testing.assert_allclose(distance, [[0.0, 5.9 / 12, -5.9 / 12]], atol=1e-5)


def test_compiled_arctangent_is_within_its_stated_error(rng):
    """The kernel's polynomial atan2 (in turns, [0, 1)) against numpy's, on random points and the axes."""
    y, x = rng.normal(size=(2, 5000))
    y, x = np.append(y, [0.0, 0.0, 1.0, -1.0, -1e-9]), np.append(x, [1.0, -1.0, 0.0, 0.0, 1.0])
    ours = np.array([_atan2_turns(a, b) for a, b in zip(y, x)])
    exact = np.arctan2(y, x) / (2 * np.pi)
    assert np.all((ours >= 0) & (ours < 1))
    assert np.abs((ours - exact + 0.5) % 1 - 0.5).max() < 3e-7


@pytest.mark.parametrize("frequencies, steps", [((1.0, 8.0, 64.0), 4), ((1.0, 16.0), 3), ((15.0, 16.0), 4)])
def test_compiled_decoding_equals_the_numpy_composition(small_rig, sphere, frequencies, steps):
    """The one-pass kernel against `fringe_fits` + `noise_level` + `unwrap_step` in numpy (tests/pmp_reference.py):
    equal to float32 rounding and the polynomial arctangent (1e-3 lines at these periods); the validity may differ
    only where the modulation sits at the threshold, which the kernel takes from a sample of the noise."""
    from pmp_reference import decode_pmp as numpy_decode

    spec = SPEC.with_(frequencies=frequencies, steps=steps)
    frames = sphere.images if spec == SPEC else simulate.render_sequence(
        small_rig, simulate.sphere_scene(), render_frames(spec), realistic(2)).images
    ours, numpy_way = decode_pmp(frames, spec, "rows"), numpy_decode(frames, spec, "rows")
    assert np.mean(ours.valid != numpy_way.valid) < 1e-3
    both = ours.valid & numpy_way.valid
    assert np.abs(ours.coord - numpy_way.coord)[both].max() < 1e-3
    assert np.array_equal(ours.index[both], numpy_way.index[both])
    assert np.isnan(ours.coord[~ours.valid]).all() and (ours.index[~ours.valid] == -1).all()
    np.testing.assert_allclose(ours.confidence, numpy_way.confidence, atol=1e-5)
    np.testing.assert_allclose(ours.brightness, numpy_way.brightness, atol=1e-5)


def test_contradicting_levels_are_rejected():
    """Frames whose middle fringes are shifted by half a period: every unwrapping is a coin toss."""
    spec = SPEC.with_(projector_size=(64, 48), frequencies=(1.0, 4.0, 16.0))
    y = np.arange(48, dtype=np.float64)[:, None] * np.ones((1, 64))
    frames = []
    for f, shift in ((1, 0.0), (4, np.pi), (16, 0.0)):
        frames += [0.4 + 0.3 * np.cos(2 * np.pi * f * y / 48 + shift - np.pi * n / 2) for n in range(4)]
    result = decode_pmp(np.stack(frames).astype(np.float32), spec, "rows")
    assert not result.valid.any()


def test_pure_noise_is_not_decoded(rng):
    frames = (0.05 + rng.normal(0, 0.01, (12, 100, 100))).astype(np.float32)
    assert decode_pmp(frames, SPEC, "rows").valid.mean() < 1e-3


# ------------------------------------------------------------------------------------ virtual rig


@pytest.mark.parametrize("frequencies, steps", [((1.0, 8.0, 64.0), 4), ((1.0, 16.0), 3), ((15.0, 16.0), 4)])
def test_noise_free_plane_recovers_rows(small_rig, frequencies, steps):
    """Hierarchical, dual-frequency and heterodyne: y_p to better than 0.05 projector px RMS without noise."""
    spec = SPEC.with_(frequencies=frequencies, steps=steps)
    seq = simulate.render_sequence(small_rig, simulate.plane_scene(), render_frames(spec), simulate.Conditions.ideal())
    result = decode_pmp(seq.images, spec, "rows")
    lit = seq.truth.lit
    assert (result.valid & lit).sum() > 0.999 * lit.sum()
    err = (result.coord - true_rows(seq.truth))[result.valid & lit]
    assert np.sqrt(np.mean(err**2)) < 0.05


@pytest.mark.parametrize("scene", ["tilted", "sphere"])
def test_no_period_jumps_in_smooth_regions(small_rig, sphere, scene):
    seq = sphere if scene == "sphere" else simulate.render_sequence(
        small_rig, simulate.tilted_plane_scene(25), render_frames(SPEC), realistic(1))
    result = decode_pmp(seq.images, SPEC, "rows")
    smooth = smooth_region(seq.truth)
    valid = result.valid & smooth
    assert valid.sum() > 0.98 * smooth.sum()
    err = np.abs(result.coord - true_rows(seq.truth))[valid]
    # a wrong order at any level costs at least a finest period (12 rows); noise and gamma stay far below half
    assert err.max() < FINEST_PERIOD / 4
    assert np.sqrt(np.mean(err**2)) < 0.3


def test_sphere_scan_accuracy(small_rig, sphere):
    """3 frequencies x 4 steps under realistic conditions, through the Scanner: the RMS 3D error of every valid point
    is well below the 4-bit composite pattern's stripe quantum, and the sphere's radius is right within 0.5 mm."""
    truth = sphere.truth
    result = Scanner(SPEC, small_rig.calibration).scan(sphere.images)
    assert (result.valid & truth.lit).sum() > 0.95 * truth.lit.sum()
    err = np.linalg.norm(result.points - truth.points, axis=-1)
    rms_all = np.sqrt(np.mean(err[result.valid & truth.surface] ** 2))
    quantum = np.median(evaluate.stripe_depth(truth, patterns.thesis_spec(PROJECTOR), small_rig.calibration)[truth.lit])
    assert rms_all < 0.1 * quantum  # measured: 6 mm (silhouette pixels mixing sphere and wall) vs 128 mm
    smooth = result.valid & smooth_region(truth)
    assert np.sqrt(np.mean(err[smooth] ** 2)) < 0.5  # measured 0.23 mm

    on_sphere = smooth & (np.abs(np.linalg.norm(truth.points - [0, 0, 800], axis=-1) - 122.555) < 1)
    centre, radius, _ = evaluate.fit_sphere(result.points[on_sphere])
    assert radius == pytest.approx(122.555, abs=0.5)  # measured 122.58 mm
    np.testing.assert_allclose(centre, [0, 0, 800], atol=0.5)
    assert result.stripe[result.valid].max() < 64 and result.stripe[~result.valid].tolist() == [-1] * (~result.valid).sum()
