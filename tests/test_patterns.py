"""Gray code and composite pattern generation (thesis 3.1, eq. 3.1, table 3.1, section 6.2)."""

import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sliscan import InputError, PatternSpec, patterns
from sliscan._validate import read_image


@given(st.integers(min_value=1, max_value=12), st.data())
def test_gray_encode_decode_is_identity(bits, data):
    n = np.array(data.draw(st.lists(st.integers(0, 2**bits - 1), min_size=1, max_size=50)))
    assert np.array_equal(patterns.gray_decode(patterns.gray_encode(n)), n)


@pytest.mark.parametrize("bits", range(1, 13))
def test_gray_neighbours_differ_in_one_bit_and_cover_all_codes(bits):
    codes = patterns.gray_encode(np.arange(2**bits))
    assert sorted(codes.tolist()) == list(range(2**bits))
    flips = codes[1:] ^ codes[:-1]
    assert np.all((flips & (flips - 1)) == 0) and np.all(flips > 0)


def test_table_3_1():
    table = patterns.code_bits(patterns.gray_encode(np.arange(8)), 3)
    expected = ["000", "001", "011", "010", "110", "111", "101", "100"]
    assert ["".join(map(str, row)) for row in table] == expected


def test_code_to_stripe_skips_zero_code():
    spec = PatternSpec(skip_zero_code=True)
    codes = patterns.stripe_codes(spec)
    assert 0 not in codes.tolist() and codes.size == 15
    assert np.array_equal(patterns.code_to_stripe(codes, spec), np.arange(15))
    assert patterns.code_to_stripe(np.array([0]), spec).tolist() == [-1]


def test_stripe_of_line_and_centre_round_trip():
    spec = PatternSpec()
    lines = np.arange(768)
    stripe = patterns.stripe_of_line(lines, spec)
    assert np.array_equal(stripe, lines // 48)
    centre = patterns.stripe_center(stripe, spec)
    assert np.all(np.abs(centre - lines) <= 24)  # half a 48-line stripe
    assert patterns.stripe_of_line(np.array([-1.0, 768.0, np.nan]), spec).tolist() == [-1, -1, -1]


def _row_amplitudes(row, carriers, width):
    spectrum = np.fft.rfft(row) / width * 2
    return np.abs(spectrum[np.round(np.asarray(carriers)).astype(int)])


def test_composite_rows_carry_exactly_their_bits():
    spec = patterns.thesis_spec((1024, 768))
    image = patterns.linear_pattern(spec)
    planes = patterns.bit_planes(spec)
    for line in (0, 100, 400, 767):
        amplitudes = _row_amplitudes(image[line], spec.carriers, 1024)
        # integer carriers over the full width: exact DFT bins, so amplitude = b_p * bit
        np.testing.assert_allclose(amplitudes, spec.b_p * planes[:, line], rtol=0, atol=1e-12)
        assert image[line].mean() == pytest.approx(spec.a_p, abs=1e-12)


def test_carrier_only_and_weights():
    spec = patterns.thesis_spec((1024, 768), kind="carrier_only", weights=(1.0, 0.9, 0.8, 0.7))
    amplitudes = _row_amplitudes(patterns.linear_pattern(spec)[10], spec.carriers, 1024)
    np.testing.assert_allclose(amplitudes, spec.b_p * np.array(spec.weights), rtol=0, atol=1e-12)


def test_modified_composite_adds_sine_along_phase_direction():
    spec = patterns.thesis_spec((1024, 768), kind="modified_composite", b_p=0.1, modified_amplitude=0.1)
    column_mean = patterns.linear_pattern(spec).mean(axis=1) - spec.a_p
    amplitude = np.abs(np.fft.rfft(column_mean))[15] * 2 / 768
    assert amplitude == pytest.approx(0.1, abs=1e-9)


def test_render_is_quantised_and_gamma_precorrected():
    spec = patterns.thesis_spec((256, 64), gamma=2.2)
    image = patterns.render_pattern(spec)
    assert image.dtype == np.float32 and image.min() >= 0 and image.max() <= 1
    np.testing.assert_allclose(image * 255, np.round(image * 255), atol=1e-4)
    linear = np.clip(patterns.linear_pattern(spec), 0, 1)
    # after the projector's gamma the light is linear again, to within half a grey level
    slope = 2.2 * np.maximum(image, 1 / 255) ** 1.2 / 255
    assert np.all(np.abs(image.astype(np.float64) ** 2.2 - linear) <= 0.5 * slope + 1e-6)


def test_pattern_out_of_range_raises():
    with pytest.raises(InputError, match="pattern leaves"):
        patterns.linear_pattern(PatternSpec(b_p=0.2))
    spec = patterns.phase_spec((1024, 768), a_p=0.5, b_p=0.5 / 7)  # its own range, 0.25-0.89, moved up by 0.11
    message = r"pattern leaves \[0, 1\]: a_p 0.61 and b_p 0.0714286 make it span \[0.360, 1.003\]"
    with pytest.raises(InputError, match=message):
        patterns.linear_pattern(spec.with_(a_p=spec.a_p + 0.11))
    with pytest.raises(InputError, match="drive range must satisfy"):
        patterns.stretch_drive(spec, 0.5, 0.4)


@pytest.mark.parametrize("kwargs, message", [
    (dict(bits=3), "one carrier per bit"),
    (dict(carriers=(32.0, 64.0, 64.0, 128.0)), "distinct"),
    (dict(carriers=(32.0, 64.0, 96.0, 600.0)), "carriers must lie"),
    (dict(orientation="diagonal"), "orientation"),
    (dict(kind="stripes"), "kind"),
    (dict(gamma=0.0), "gamma"),
])
def test_spec_validation(kwargs, message):
    with pytest.raises(InputError, match=message):
        PatternSpec(**kwargs)


def test_spread_carriers_are_free_of_second_order_products():
    for bits in (2, 4, 6, 8):
        carriers = np.array(patterns.spread_carriers(bits, 1024, pilot=True))
        products = np.concatenate([(carriers[:, None] + carriers[None]).ravel(),
                                   np.abs(carriers[:, None] - carriers[None]).ravel()])
        spacing = carriers[1] - carriers[0]
        distance = np.abs(products[:, None] - carriers[None]).min()
        assert distance >= spacing - 1e-9


def test_default_spec_puts_msb_on_highest_carrier_and_skips_zero_code():
    spec = patterns.default_spec((1024, 768))
    assert spec.carriers == (128.0, 96.0, 64.0, 32.0) and spec.skip_zero_code and spec.pilot is None
    low, high = patterns.pattern_range(spec)
    assert low >= 0 and high <= 1


@pytest.mark.parametrize("make", [patterns.thesis_spec, patterns.default_spec, patterns.phase_spec])
def test_pattern_range_is_the_patterns_own_and_stretch_drive_fills_a_range(make):
    """`pattern_range` is the linear image's own extremes; `stretch_drive` maps them onto the
    range asked for by one factor on every carrier (the bits' levels keep their ratios)."""
    spec = make((1024, 768))
    image = patterns.linear_pattern(spec)
    assert patterns.pattern_range(spec) == (image.min(), image.max())
    stretched = patterns.stretch_drive(spec, 0.2, 1.0)
    assert patterns.pattern_range(stretched) == pytest.approx((0.2, 1.0), abs=1e-12)
    np.testing.assert_allclose((patterns.linear_pattern(stretched) - stretched.a_p) / stretched.b_p,
                               (image - spec.a_p) / spec.b_p, atol=1e-9)


def test_save_pattern_writes_png_and_json(tmp_path):
    spec = patterns.thesis_spec((256, 192))
    image_path, json_path = patterns.save_pattern(tmp_path / "cp.png", spec)
    assert json_path == tmp_path / "cp.json"
    loaded = PatternSpec.load(json_path)
    assert loaded.image == "cp.png" and loaded.with_(image=None) == spec
    np.testing.assert_array_equal(read_image(image_path), patterns.render_pattern(spec))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cp.json", "cp.png"]


def test_spec_load_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="bad.json: not valid JSON"):
        PatternSpec.load(bad)
    bad.write_text(json.dumps({"bits": 4, "colour": "red"}))
    with pytest.raises(InputError, match=r"bad.json: unknown keys \['colour'\]"):
        PatternSpec.load(bad)
    with pytest.raises(InputError, match="no_such.json: cannot read"):
        PatternSpec.load(tmp_path / "no_such.json")


def test_columns_orientation_transposes():
    rows = patterns.thesis_spec((256, 256))
    cols = rows.with_(orientation="columns")
    np.testing.assert_array_equal(patterns.linear_pattern(cols), patterns.linear_pattern(rows).T)


@pytest.mark.parametrize("spec", [patterns.thesis_spec((1024, 768)), patterns.default_spec((1024, 768)),
                                  patterns.default_spec((1000, 700))])
def test_stripe_geometry_matches_the_projected_lines(spec):
    """Fractional lines take the stripe of the nearest whole line (15 stripes over 768 lines
    is not a whole number of lines per stripe), and each stripe's centre lies in it."""
    rows = np.arange(spec.phase_lines)
    stripe = patterns.stripe_of_line(rows, spec)
    codes = patterns.bits_to_code(patterns.bit_planes(spec))
    assert np.array_equal(patterns.code_to_stripe(codes, spec), stripe)
    assert np.array_equal(patterns.stripe_of_line(rows + 0.49, spec), stripe)
    assert np.array_equal(patterns.stripe_of_line(rows - 0.49, spec), stripe)
    centres = patterns.stripe_center(np.arange(spec.stripes), spec)
    assert np.array_equal(patterns.stripe_of_line(centres, spec), np.arange(spec.stripes))
