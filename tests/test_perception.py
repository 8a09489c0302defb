"""Perceptual core (issue 3): thresholds, two-colour decomposition, reference analysis.

Expected numbers come from the model itself (threshold slopes, the 2 x 2 system, the line
spectrum of a sinusoidal surface), never from earlier runs.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from haptex_compile.colours import Band, TwoColourModel
from haptex_compile.errors import InputError
from haptex_compile.fractal import brownian_surface
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.io_thresholds import read_thresholds_csv
from haptex_compile.literal import literal_frame_amplitudes, literal_matrix
from haptex_compile.render import point_intensities, render_frames, straight_path
from haptex_compile.surface import Surface, periodic_surface_from_tile
from haptex_compile.thresholds import ThresholdCurves, idealised_thresholds

CURVES = idealised_thresholds()
SPEED = 80.0  # mm/s, the paper's passive test speed
HYP = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def tone_surface(freq_hz: float, amplitude_um: float, speed_mm_s: float = SPEED, min_len_mm: float = 4.0,
                 target_px_um: float = 10.0) -> Surface:
    """Periodic sinusoid along u whose temporal frequency at `speed_mm_s` along +u is `freq_hz`.

    The tile holds a whole number of wavelengths and pixels, so it repeats seamlessly.
    """
    lam_mm = speed_mm_s / freq_hz
    n_per = max(1, int(np.ceil(min_len_mm / lam_mm)))
    length_mm = n_per * lam_mm
    nx = int(round(length_mm * 1000.0 / target_px_um))
    px_um = length_mm * 1000.0 / nx
    u = np.arange(nx) * px_um / 1000.0
    return periodic_surface_from_tile(np.tile(amplitude_um * np.sin(2 * np.pi * u / lam_mm), (8, 1)), px_um)


def reference_tone(model: TwoColourModel, freq_hz: float, amplitude_um: float, footprint_mm: float,
                   speed_mm_s: float = SPEED) -> tuple[float, float]:
    surf = tone_surface(freq_hz, amplitude_um, speed_mm_s)
    return point_intensities(surf, model, AnalysisSettings(footprint_sigma_mm=footprint_mm),
                             straight_path(0.37, 0.04, speed_mm_s, 0.0), 0.0)


def pair_intensities(model: TwoColourModel, a40: float, a320: float) -> np.ndarray:
    """Channel intensities of a (a40, a320) pair by the model's own rule I_c^n = sum_k (a_k W_c(f_k))^n."""
    n = model.summation_exponent
    w = np.stack(model.weights(np.asarray(model.base_frequencies_hz)))  # [channel, colour]
    return ((np.array([a40, a320]) * w) ** n).sum(axis=1) ** (1.0 / n)


# ---------------------------------------------------------------------------------------------
# Threshold curves


def test_pacinian_best_frequency_is_between_200_and_320_hz():
    assert 200.0 <= CURVES.best_frequency_p_hz() <= 320.0


def test_channel_ordering_and_equal_intensity_ratio():
    assert CURVES.np_(40.0) < CURVES.p(40.0)
    assert CURVES.p(320.0) < CURVES.np_(320.0)
    ratio = float(CURVES.np_(40.0) / CURVES.p(320.0))
    assert 10.0 <= ratio <= 30.0
    # Straight-line construction (DOMAIN): +8 dB and -20 + 10 log2(320/250) dB re 1 µm, i.e.
    # 24.4 dB apart = 16.7; the rounded corner at 40 Hz may add under 1 dB.
    nominal_db = 8.0 - (-20.0 + 10.0 * np.log2(320.0 / 250.0))
    assert abs(20 * np.log10(ratio) - nominal_db) < 1.0


@pytest.mark.parametrize(
    "curve, f_lo, f_hi, db_per_octave",
    [("p", 30.0, 120.0, -12.0), ("p", 400.0, 900.0, 10.0), ("np", 100.0, 800.0, 6.0), ("np", 2.0, 20.0, 0.0)],
)
def test_threshold_slopes_away_from_corners(curve, f_lo, f_hi, db_per_octave):
    fn = CURVES.p if curve == "p" else CURVES.np_
    slope = 20 * np.log10(fn(f_hi) / fn(f_lo)) / np.log2(f_hi / f_lo)
    assert slope == pytest.approx(db_per_octave, abs=0.05)


def test_threshold_extrapolation_is_monotone_and_never_nan():
    low = np.array([1e-6, 1e-3, 0.1, 0.5, 1.0])
    high = np.array([1000.0, 2000.0, 1e4, 1e5, 1e8])
    for fn in (CURVES.p, CURVES.np_):
        for f in (low, high):
            assert np.all(np.isfinite(fn(f))) and np.all(fn(f) > 0)
    # P keeps rising towards 0 Hz (12 dB/oct), NP stays flat; both keep rising above 1 kHz.
    assert np.all(np.diff(CURVES.p(low)) < 0)
    assert np.allclose(CURVES.np_(low), CURVES.np_(1.0))
    assert np.all(np.diff(CURVES.p(high)) > 0) and np.all(np.diff(CURVES.np_(high)) > 0)
    for bad in (0.0, -5.0, -1e9):
        assert np.isinf(CURVES.p(bad)) and np.isinf(CURVES.np_(bad))
    # The model's weights are 0 where the threshold is infinite and finite everywhere else.
    model = TwoColourModel()
    f = np.array([-100.0, 0.0, 1e-3, 1.0, 1e5, 1e300, np.inf])
    for w in model.weights(f):
        assert np.all(np.isfinite(w)) and np.all(w >= 0)
        assert w[0] == 0.0 and w[1] == 0.0 and w[4] == 0.0


def test_threshold_csv_round_trip(tmp_path):
    path = tmp_path / "array.csv"
    rows = "\n".join(f"{float(f)!r},{float(p)!r},{float(q)!r}"
                     for f, p, q in zip(CURVES.frequency_hz, CURVES.p_um, CURVES.np_um))
    path.write_text("# my array\nfrequency_hz,threshold_p_um,threshold_np_um\n" + rows + "\n", encoding="utf-8")
    back = read_thresholds_csv(path)
    assert np.array_equal(back.frequency_hz, CURVES.frequency_hz)
    f = np.geomspace(0.5, 2000, 200)
    assert np.allclose(back.p(f), CURVES.p(f), rtol=1e-12) and np.allclose(back.np_(f), CURVES.np_(f), rtol=1e-12)
    assert "array.csv" in back.provenance


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("", "empty"),
        ("freq,p,np\n10,1,1\n20,1,1\n", "header"),
        ("frequency_hz,threshold_p_um,threshold_np_um\n10,1,abc\n20,1,1\n", "non-numeric"),
        ("frequency_hz,threshold_p_um,threshold_np_um\n10,1\n20,1,1\n", ""),
        ("frequency_hz,threshold_p_um,threshold_np_um\n20,1,1\n10,1,1\n", "increasing"),
        ("frequency_hz,threshold_p_um,threshold_np_um\n10,-1,1\n20,1,1\n", "positive"),
        ("frequency_hz,threshold_p_um,threshold_np_um\n10,1,nan\n20,1,1\n", "finite"),
        ("frequency_hz,threshold_p_um,threshold_np_um\n10,1,1\n", "two frequencies"),
    ],
)
def test_bad_threshold_csv_names_the_file(tmp_path, text, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as err:
        read_thresholds_csv(path)
    msg = str(err.value)
    assert "bad.csv" in msg and "\n" not in msg and fragment in msg


def test_unreadable_threshold_csv(tmp_path):
    with pytest.raises(InputError, match="missing.csv"):
        read_thresholds_csv(tmp_path / "missing.csv")
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00\x81garbage")
    with pytest.raises(InputError, match="binary.csv"):
        read_thresholds_csv(binary)


def test_curves_with_swapped_channels_are_refused():
    swapped = ThresholdCurves(CURVES.frequency_hz, CURVES.np_um, CURVES.p_um, "swapped")
    with pytest.raises(ValueError, match="T_np"):
        TwoColourModel(thresholds=swapped)


# ---------------------------------------------------------------------------------------------
# Two-colour decomposition: pure and intermediate tones through the reference analysis


def test_condition_number():
    cond = TwoColourModel(summation_exponent=1.0).condition_number()
    assert 10.0 <= cond <= 25.0
    # The literal paper matrix (raw thresholds, no band) is the same system at 40 and 320 Hz.
    assert np.linalg.cond(literal_matrix(CURVES)) == pytest.approx(cond, rel=1e-3)
    # With u = a^n the matrix entries are raised to n: conditioning gets worse, not singular.
    assert TwoColourModel(summation_exponent=1.23).condition_number() > cond


@pytest.mark.parametrize("n", [1.0, 1.23])
@pytest.mark.parametrize("footprint_mm", [0.0, 0.25])
@pytest.mark.parametrize("freq_hz", [40.0, 320.0])
def test_pure_tones_come_back_as_themselves(freq_hz, footprint_mm, n):
    model = TwoColourModel(summation_exponent=n)
    amp = 7.0
    d = model.decompose(*reference_tone(model, freq_hz, amp, footprint_mm))
    want = (amp, 0.0) if freq_hz == 40.0 else (0.0, amp)
    assert abs(float(d.a40) - want[0]) < 0.02 * amp
    assert abs(float(d.a320) - want[1]) < 0.02 * amp
    assert float(d.out_of_gamut) < 1e-3


@pytest.mark.parametrize("normalisation", ["peak", "sum"])
def test_literal_method_misses_the_40_hz_tone(normalisation):
    """One period in a 25 ms Blackman window leaks over 0-160 Hz: the paper's method is off by > 2 %."""
    rate, amp = 5120.0, 7.0
    t = np.arange(128) / rate
    phases = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    a40, a320 = literal_frame_amplitudes(amp * np.sin(2 * np.pi * 40.0 * t + phases[:, None]), rate, CURVES,
                                         normalisation=normalisation)
    err = np.maximum(np.abs(a40 - amp), a320) / amp
    assert np.all(err > 0.02)
    # Same tone through our analysis: within 2 % (shown in test_pure_tones_come_back_as_themselves).


def test_literal_method_recovers_an_on_bin_tone_far_from_dc_when_sum_normalised():
    """Check of the literal implementation itself: at 480 Hz (bin 12) the Blackman main lobe
    (bins 11-13, relative 0.595, 1, 0.595 with 0.095 further out) sums to 1/0.42 of the peak."""
    rate, amp = 5120.0, 3.0
    t = np.arange(128) / rate
    sig = amp * np.sin(2 * np.pi * 480.0 * t + 0.3)
    ideal = np.linalg.solve(literal_matrix(CURVES), amp / np.array([CURVES.p(480.0), CURVES.np_(480.0)]))
    a_sum = np.array(literal_frame_amplitudes(sig, rate, CURVES, normalisation="sum"))
    a_peak = np.array(literal_frame_amplitudes(sig, rate, CURVES))
    assert np.allclose(a_sum, ideal, rtol=0.03)
    assert np.allclose(a_peak, ideal / 0.42, rtol=0.03)


@pytest.mark.parametrize("n", [1.0, 1.23])
@pytest.mark.parametrize("freq_hz", [80.0, 160.0, 250.0])
def test_intermediate_tones_keep_their_channel_intensities(freq_hz, n):
    model = TwoColourModel(summation_exponent=n)
    amp = 4.0
    ip, inp = reference_tone(model, freq_hz, amp, 0.25)
    tone = np.array(model.tone_intensities(freq_hz, amp), dtype=float)
    assert np.allclose([ip, inp], tone, rtol=0.01)  # the analysis measures the tone's intensities
    d = model.decompose(ip, inp)
    # In gamut iff the 2 x 2 solution for the tone's intensities is non-negative.
    u = np.linalg.solve(model.matrix(), tone**n)
    if np.all(u >= 0):
        assert float(d.out_of_gamut) == 0.0
        assert np.allclose(pair_intensities(model, float(d.a40), float(d.a320)), tone, rtol=0.03)
    else:  # 250 Hz: just outside the gamut (DOMAIN); the nearest pair is a pure 320 Hz sine
        assert 0.0 < float(d.out_of_gamut) < 0.2
        assert float(d.a40) == 0.0 and float(d.a320) > 0.0


@pytest.mark.parametrize("n", [1.0, 1.23])
def test_20_hz_tone_is_out_of_gamut_and_mapped_to_a_playable_pair(n):
    model = TwoColourModel(summation_exponent=n)
    d = model.decompose(*reference_tone(model, 20.0, 10.0, 0.25))
    a40, a320, gam = float(d.a40), float(d.a320), float(d.out_of_gamut)
    assert np.isfinite([a40, a320, gam]).all()
    assert a40 > 0.0 and a320 == 0.0  # below 40 Hz the solution needs a negative 320 Hz part
    assert gam > 0.0
    # The reported measure is the RMS relative residual of the channel intensities (raised to n).
    tone = np.array(model.tone_intensities(20.0, 10.0)) ** n
    resid = pair_intensities(model, a40, a320) ** n / tone - 1.0
    assert gam == pytest.approx(np.sqrt(np.mean(resid**2)), rel=0.02)


# ---------------------------------------------------------------------------------------------
# DC, slow trends, speed 0, very high speed


@pytest.fixture(scope="module")
def texture():
    h = brownian_surface((128, 128), 0.5, pixel_size_um=20.0, rms_um=5.0, seed=11, periodic=True)
    return h


def test_constant_offset_carries_no_vibration(texture):
    model = TwoColourModel()
    s = AnalysisSettings()
    path = straight_path(1.1, 0.7, SPEED, 33.0)
    ref = np.array(point_intensities(periodic_surface_from_tile(texture, 20.0), model, s, path, 0.0))
    flat = np.array(point_intensities(periodic_surface_from_tile(np.full((64, 64), 1000.0), 20.0), model, s, path, 0.0))
    assert np.all(flat < 1e-6 * ref)
    shifted = np.array(point_intensities(periodic_surface_from_tile(texture + 1000.0, 20.0), model, s, path, 0.0))
    assert np.allclose(shifted, ref, rtol=1e-6)


def test_tilted_plane_carries_no_vibration(texture):
    model = TwoColourModel()
    s = AnalysisSettings()
    ref = np.array(point_intensities(periodic_surface_from_tile(texture, 20.0), model, s,
                                     straight_path(1.1, 0.7, SPEED, 33.0), 0.0))
    v, u = np.mgrid[0:400, 0:400] * 0.1  # 40 x 40 mm at 100 µm: the analysis stretch stays inside
    plane = Surface(1000.0 + 30.0 * u - 20.0 * v, 100.0)
    got = np.array(point_intensities(plane, model, s, straight_path(20.0, 20.0, SPEED, 30.0), 0.0))
    # A plane sloping by hundreds of µm over the stretch: at most 1e-4 of a 5 µm texture's
    # intensity (rounding of the removed trend), i.e. nothing felt.
    assert np.all(got < 1e-4 * ref)


def test_speed_zero_gives_exactly_zero(texture):
    model = TwoColourModel()
    surf = periodic_surface_from_tile(texture, 20.0)
    assert point_intensities(surf, model, AnalysisSettings(), lambda t: (np.full_like(t, 1.0), np.full_like(t, 2.0)), 0.0) == (0.0, 0.0)
    frames = render_frames(surf, model, AnalysisSettings(), np.array([[0.0, 0.0], [2.0, 0.0]]), np.array([0.0, 0.025]),
                           lambda t: (np.full_like(t, 1.0), np.full_like(t, 1.0), np.full_like(t, 15.0)))
    for a in (frames.a40, frames.a320, frames.out_of_gamut):
        assert np.array_equal(a, np.zeros((2, 2)))


def test_very_high_speed_is_finite_and_does_not_alias():
    model = TwoColourModel()
    s = AnalysisSettings()
    # A 10 µm map swept at 2000 mm/s: finite, non-negative amplitudes.
    h = brownian_surface((128, 128), 0.5, pixel_size_um=10.0, rms_um=5.0, seed=2, periodic=True)
    ip, inp = point_intensities(periodic_surface_from_tile(h, 10.0), model, s, straight_path(0.3, 0.4, 2000.0, 20.0), 0.0)
    d = model.decompose(ip, inp)
    assert np.isfinite([ip, inp, d.a40, d.a320]).all() and ip > 0 and inp > 0
    # A sinusoid of 0.4 mm wavelength (40 px, well resolved) at 2000 mm/s is a 5 kHz tone: far
    # above the band (stop 800 Hz), so ~nothing; at 128 mm/s the same surface is a 320 Hz tone.
    amp = 5.0
    surf = tone_surface(5000.0, amp, speed_mm_s=2000.0)
    fast = np.array(point_intensities(surf, model, s, straight_path(0.3, 0.02, 2000.0, 0.0), 0.0))
    slow = np.array(point_intensities(surf, model, s, straight_path(0.3, 0.02, 128.0, 0.0), 0.0))
    assert slow == pytest.approx(model.tone_intensities(320.0, amp), rel=0.01)
    assert np.all(fast < 1e-6 * slow)


def test_detail_finer_than_the_map_resolves_is_not_felt():
    """A 2.5-pixel period (0.8 of the map's Nyquist frequency) is not resolved: at 8 mm/s it would be
    a 320 Hz tone, but the surface does not contain it, so it must not reach the Pacinian band."""
    model = TwoColourModel()
    px = 10.0
    u = np.arange(400) * px / 1000.0
    fine = periodic_surface_from_tile(np.tile(5.0 * np.sin(2 * np.pi * u / 0.025), (8, 1)), px)
    ip, inp = point_intensities(fine, model, AnalysisSettings(), straight_path(0.3, 0.02, 8.0, 0.0), 0.0)
    tone = model.tone_intensities(320.0, 5.0)
    assert ip < 1e-3 * tone[0] and inp < 1e-3 * tone[1]


# ---------------------------------------------------------------------------------------------
# Property tests (hypothesis)

finite_amps = st.floats(min_value=0.0, max_value=1e4, allow_nan=False)


@HYP
@given(freqs=st.lists(st.floats(min_value=-100.0, max_value=1e5, allow_nan=False), min_size=1, max_size=20),
       data=st.data(), n=st.sampled_from([1.0, 1.23, 2.0]))
def test_random_spectra_give_finite_non_negative_amplitudes(freqs, data, n):
    amps = data.draw(st.lists(finite_amps, min_size=len(freqs), max_size=len(freqs)))
    d = TwoColourModel(summation_exponent=n).decompose_spectrum(np.array(freqs), np.array(amps))
    for a in (d.a40, d.a320, d.out_of_gamut):
        assert np.isfinite(a) and a >= 0


# Intensities in threshold units: 0, or from 1e-100 (below about 1e-200 the summation's powers
# reach subnormal floats and lose their relative precision: 0 and 3.9e-229 at c = 2 were off
# by 4e-8).
intensity = st.one_of(st.just(0.0), st.floats(min_value=1e-100, max_value=1e6))


@HYP
@given(ip=intensity, inp=intensity, c=st.floats(min_value=1e-3, max_value=1e3), n=st.sampled_from([1.0, 1.23]))
def test_decomposition_is_homogeneous_of_degree_one(ip, inp, c, n):
    model = TwoColourModel(summation_exponent=n)
    d1 = model.decompose(ip, inp)
    dc = model.decompose(c * ip, c * inp)
    scale = max(float(d1.a40), float(d1.a320), 1e-300)
    assert abs(float(dc.a40) - c * float(d1.a40)) <= 1e-9 * c * scale
    assert abs(float(dc.a320) - c * float(d1.a320)) <= 1e-9 * c * scale
    assert float(dc.out_of_gamut) == pytest.approx(float(d1.out_of_gamut), abs=1e-9)


intensity_or_junk = st.one_of(st.floats(min_value=-1e12, max_value=1e12),
                              st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 5e-324]))


@HYP
@given(ip=intensity_or_junk, inp=intensity_or_junk)
def test_decomposition_never_returns_nan(ip, inp):
    d = TwoColourModel().decompose(ip, inp)
    assert np.isfinite([d.a40, d.a320, d.out_of_gamut]).all() and d.a40 >= 0 and d.a320 >= 0


@st.composite
def threshold_curves(draw):
    best = draw(st.floats(min_value=150.0, max_value=350.0))
    floor_db = draw(st.floats(min_value=-30.0, max_value=-10.0))
    down = draw(st.floats(min_value=6.0, max_value=15.0))
    up = draw(st.floats(min_value=4.0, max_value=14.0))
    flat_db = draw(st.floats(min_value=0.0, max_value=15.0))
    knee = draw(st.floats(min_value=25.0, max_value=80.0))
    rise = draw(st.floats(min_value=3.0, max_value=9.0))
    f = np.geomspace(1.0, 1000.0, 31)
    p_db = floor_db + np.where(f < best, -down, up) * np.log2(f / best)
    np_db = flat_db + rise * np.maximum(np.log2(f / knee), 0.0)
    return ThresholdCurves(f, 10 ** (p_db / 20), 10 ** (np_db / 20), "hypothesis")


@HYP
@given(curves=threshold_curves(), freqs=st.lists(st.floats(min_value=0.0, max_value=2000.0), min_size=1, max_size=8),
       data=st.data(), n=st.sampled_from([1.0, 1.23]))
def test_random_thresholds_give_finite_non_negative_amplitudes(curves, freqs, data, n):
    try:
        model = TwoColourModel(thresholds=curves, summation_exponent=n)
    except ValueError:
        assume(False)
    amps = np.array(data.draw(st.lists(finite_amps, min_size=len(freqs), max_size=len(freqs))))
    d = model.decompose_spectrum(np.array(freqs), amps)
    assert np.isfinite([d.a40, d.a320, d.out_of_gamut]).all() and d.a40 >= 0 and d.a320 >= 0
    # Pure base tones come back as themselves whatever the (valid) curves (within the round-off
    # of the summation's chained powers: 1.06e-9 measured).
    for k, f0 in enumerate(model.base_frequencies_hz):
        dt = model.decompose(*model.tone_intensities(f0, 2.0))
        assert (float(dt.a40), float(dt.a320))[k] == pytest.approx(2.0, rel=1e-8)
        assert (float(dt.a40), float(dt.a320))[1 - k] == pytest.approx(0.0, abs=1e-9)


@pytest.fixture(scope="module")
def rough():
    return brownian_surface((96, 96), 0.5, pixel_size_um=20.0, rms_um=5.0, seed=5, periodic=True)


@settings(max_examples=6, deadline=None)
@given(c=st.floats(min_value=0.01, max_value=100.0), n=st.sampled_from([1.0, 1.23]))
def test_renderer_scales_with_height_amplitude(rough, c, n):
    model = TwoColourModel(summation_exponent=n)
    s = AnalysisSettings(footprint_sigma_mm=0.0)
    path = straight_path(0.5, 0.9, 60.0, 21.0)
    d1 = model.decompose(*point_intensities(periodic_surface_from_tile(rough, 20.0), model, s, path, 0.0))
    dc = model.decompose(*point_intensities(periodic_surface_from_tile(c * rough, 20.0), model, s, path, 0.0))
    assert float(dc.a40) == pytest.approx(c * float(d1.a40), rel=1e-6)
    assert float(dc.a320) == pytest.approx(c * float(d1.a320), rel=1e-6)


@settings(max_examples=6, deadline=None)
@given(speed=st.floats(min_value=10.0, max_value=250.0), eps=st.floats(min_value=1e-4, max_value=0.02))
def test_renderer_is_continuous_in_speed(rough, speed, eps):
    """log I changes with log speed at most as fast as the steepest weighting slope: W ~ f^2
    below 40 Hz (band) and T_p falls 12 dB/oct (f^2) — bound |d log I / d log s| <= 4."""
    model = TwoColourModel()
    s = AnalysisSettings(footprint_sigma_mm=0.0)
    surf = periodic_surface_from_tile(rough, 20.0)
    i1 = np.array(point_intensities(surf, model, s, straight_path(0.5, 0.9, speed, 21.0), 0.0))
    i2 = np.array(point_intensities(surf, model, s, straight_path(0.5, 0.9, speed * (1 + eps), 21.0), 0.0))
    assert np.all(np.abs(np.log(i2 / i1)) <= 4.0 * np.log1p(eps) + 1e-3)


def test_float32_and_float64_heights_agree(rough):
    model = TwoColourModel()
    s = AnalysisSettings()
    path = straight_path(0.5, 0.9, 60.0, 21.0)
    h32 = rough.astype(np.float32)
    i64 = np.array(point_intensities(periodic_surface_from_tile(h32.astype(np.float64), 20.0), model, s, path, 0.0))
    i32 = np.array(point_intensities(periodic_surface_from_tile(h32, 20.0), model, s, path, 0.0))
    assert np.allclose(i32, i64, rtol=1e-6)
    # The literal method too (float32 rounding is ~6e-8 relative).
    rate = 5120.0
    sig = np.sin(2 * np.pi * 120.0 * np.arange(128) / rate) * 3.0
    a64 = np.array(literal_frame_amplitudes(sig, rate, CURVES))
    a32 = np.array(literal_frame_amplitudes(sig.astype(np.float32), rate, CURVES))
    assert np.allclose(a32, a64, rtol=1e-5)


def test_band_weight_properties():
    band = Band()
    f = np.array([0.0, 1.0, 10.0, 100.0, 599.0, 700.0, 800.0, 5000.0])
    b = band.weight(f)
    assert b[0] == 0.0 and b[-1] == 0.0 and b[-2] == 0.0
    assert b[1] == pytest.approx(1 - np.exp(-1e-4), rel=1e-9)  # vanishes like f^4 at 0 Hz
    assert b[2] == pytest.approx(1 - np.exp(-1.0), rel=1e-9)
    assert b[5] == pytest.approx(0.5, rel=1e-9)  # raised cosine half-way from 600 to 800 Hz
    with pytest.raises(ValueError):
        Band(low_hz=700.0)


def test_intensities_invert_the_decomposition_inside_the_gamut():
    model = TwoColourModel()
    a40 = np.array([3.0, 0.0, 1.0, 12.0])
    a320 = np.array([0.0, 2.0, 0.5, 0.01])
    d = model.decompose(*model.intensities(a40, a320))
    np.testing.assert_allclose(d.a40, a40, atol=1e-9)
    np.testing.assert_allclose(d.a320, a320, atol=1e-9)
    # a pure tone at a base frequency is its amplitude times the channel weight there
    ip, inp = model.intensities(2.0, 0.0)
    wp, wnp = model.weights(40.0)
    assert ip == pytest.approx(2.0 * wp) and inp == pytest.approx(2.0 * wnp)


def test_a_footprint_passage_far_shorter_than_the_frame_is_a_point_in_the_window():
    # The window is tabulated at 1/200 of the shorter of the frame and the footprint's passage;
    # a passage of 50 ns (0.1 um at 2000 mm/s) asked for 2e8 samples. Below 1/800 of the frame
    # it is a point: the table is the bare Hann's, and the Gaussian would change the window by
    # about (sigma / T)^2 pi^2 / 4 (3.9e-6 at the limit, as measured below).
    from haptex_compile.frame_analysis import POINT_PASSAGE_FRACTION, _window_table, frame_window

    frame_ms = 25.0
    t_point, w_point = _window_table(frame_ms, 5e-8)
    t_bare, w_bare = _window_table(frame_ms, 0.0)
    assert t_point.size == t_bare.size == 401 and np.array_equal(w_point, w_bare)
    # just above the limit the Gaussian is applied, on the longest table there is (3.2e5 samples)
    sigma = 1.01 * POINT_PASSAGE_FRACTION * frame_ms / 1000.0
    t, w = _window_table(frame_ms, sigma)
    assert t.size < 2 * 800 * 200 + 1
    offsets = np.linspace(-0.02, 0.02, 81)
    change = np.abs(frame_window(offsets, frame_ms, sigma) - frame_window(offsets, frame_ms, 0.0)).max()
    assert change < 1e-5


@pytest.mark.parametrize("ratio", [801.0, 1500.0])
def test_a_footprint_passage_far_longer_than_the_frame_makes_the_window_its_gaussian(ratio):
    # A 0.25 mm footprint at 0.001 mm/s passes in 250 s, 1e4 x a 25 ms frame: the window was
    # tabulated at 1/200 of the frame over the passage (2e7 samples) and convolved directly
    # (hours; a 64 px map's compile ran past 5 minutes). Beyond 800 x the frame it is the
    # footprint's Gaussian times the Hann's area T, normalised over its truncated support as
    # the convolution's was; here against that convolution done by FFT.
    from scipy.signal import fftconvolve

    from haptex_compile.frame_analysis import FOOTPRINT_TRUNCATION, _window_table, frame_window

    frame_ms, t_frame = 25.0, 0.025
    sigma = ratio * t_frame
    step = t_frame / 200
    n = int(np.ceil((t_frame + FOOTPRINT_TRUNCATION * sigma) / step))
    t = np.arange(-n, n + 1) * step
    hann = np.where(np.abs(t) < t_frame, np.cos(np.pi * t / (2 * t_frame)) ** 2, 0.0)
    m = int(np.ceil(FOOTPRINT_TRUNCATION * sigma / step))
    g = np.exp(-0.5 * (np.arange(-m, m + 1) * step / sigma) ** 2)
    convolved = fftconvolve(hann, g / g.sum(), mode="same")
    offsets = np.linspace(-3.9 * sigma, 3.9 * sigma, 301)
    window = frame_window(offsets, frame_ms, sigma)
    assert np.abs(window - np.interp(offsets, t, convolved)).max() < 1e-5 * convolved.max()
    assert _window_table(frame_ms, sigma)[0].size < 2000


@pytest.mark.parametrize("freq, p_um, np_um", [
    ([1e-300, 1e300], [1e-30, 1e-300], [5e-324, 1e-10]),  # compiled, with NaN powers on the way
    ([1e-300, 1e300], [1000.0, 5e-324], [1e300, 1e300]),  # singular
    ([800.0, 801.0], [5e-324, 1.7e308], [2.5, 2.5]),
])
def test_absurd_threshold_tables_are_one_error_without_numpy_warnings(freq, p_um, np_um):
    # User tables of 1e-300 um (a fuzz of threshold CSVs): numpy's overflow and divide-by-zero
    # warnings reached stderr before the one-line error, and one table even compiled, with
    # "invalid value" warnings from the frame analysis. Now: one ValueError, no warning.
    import warnings

    from haptex_compile.thresholds import ThresholdCurves

    curves = ThresholdCurves(np.array(freq), np.array(p_um), np.array(np_um), "fuzz")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError):
            TwoColourModel(thresholds=curves)
