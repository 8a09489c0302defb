"""Device profiles: conversion to codes, safety limits, and agreement with the JSON schema."""
from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from playback.device import DEFAULT_PROFILE, DEFAULT_PROFILE_PATH, load_profile, profile_from_dict
from playback.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


def test_sample_profile_equals_builtin():
    assert load_profile(DEFAULT_PROFILE_PATH) == load_profile(None)
    with open(DEFAULT_PROFILE_PATH, "rb") as fh:
        assert tomllib.load(fh) == DEFAULT_PROFILE


def test_codes_follow_calibration():
    p = load_profile(None)  # 2.5 µm/V at 40 Hz, 0.5 µm/V at 320 Hz, 12 bits over 40 V rms
    a40 = np.zeros(24)
    a320 = np.zeros(24)
    a40[0], a320[0] = 25.0, 2.0  # 10 V and 4 V
    c40, c320, clamped, bad = p.to_codes(a40, a320)
    assert c40[0] == round(10.0 / 40.0 * 4095) and c320[0] == round(4.0 / 40.0 * 4095)
    assert clamped == 0 and bad == 0
    assert c40.dtype == np.uint16 and c40.shape == (24,)


def test_limits_scale_pair_and_count():
    p = load_profile(None)
    a40 = np.zeros(24)
    a320 = np.zeros(24)
    a40[1], a320[1] = 150.0, 50.0   # 200 µm peak > 100 µm: scaled by 0.5 -> 75, 25 µm -> 30 V, 50 V
    a40[2] = 1e9                    # absurd
    c40, c320, clamped, _ = p.to_codes(a40, a320)
    v40, v320 = p.code_to_v_rms(c40), p.code_to_v_rms(c320)
    # Both limits: the pair keeps its 40/320 voltage ratio 30:50 and lands on 40 V rms.
    assert np.hypot(v40[1], v320[1]) == pytest.approx(40.0, abs=0.02)
    assert v40[1] / v320[1] == pytest.approx(30.0 / 50.0, rel=2e-3)
    assert clamped == 2
    assert np.all(np.hypot(v40, v320) <= 40.0 + 0.02)
    disp = v40 * p.um_per_v_40hz + v320 * p.um_per_v_320hz
    assert np.all(disp <= 100.0 + 0.1)


def test_nonfinite_never_reaches_codes():
    p = load_profile(None)
    a40 = np.full(24, np.nan)
    a40[3] = np.inf
    a40[4] = -5.0
    a320 = np.full(24, -np.inf)
    c40, c320, _, bad = p.to_codes(a40, a320)
    assert not c40.any() and not c320.any()
    assert bad == 48


def test_channel_map():
    doc = copy.deepcopy(DEFAULT_PROFILE)
    doc["contactors"] = {"count": 3, "n_channels": 8, "channel": [7, 0, 4]}
    p = profile_from_dict(doc)
    c40, _, _, _ = p.to_codes(np.array([2.5, 5.0, 7.5]), np.zeros(3))
    code = [round(volts * 4095 / 40) for volts in (1.0, 2.0, 3.0)]
    assert list(c40) == [code[1], 0, 0, 0, code[2], 0, 0, code[0]]


def _variants():
    base = copy.deepcopy(DEFAULT_PROFILE)
    out = [("valid default", base, True)]

    def v(name, fn, ok):
        d = copy.deepcopy(base)
        fn(d)
        out.append((name, d, ok))
    v("no name", lambda d: d.pop("name"), True)
    v("no output section", lambda d: d.pop("output"), True)
    v("optional usb keys dropped", lambda d: [d["usb"].pop(k) for k in ("interface", "endpoint_out", "timeout_ms", "retries")], True)
    v("missing usb", lambda d: d.pop("usb"), False)
    v("missing vendor", lambda d: d["usb"].pop("vendor_id"), False)
    v("vendor too big", lambda d: d["usb"].__setitem__("vendor_id", 0x10000), False)
    v("vendor float", lambda d: d["usb"].__setitem__("vendor_id", 1.5), False)
    v("vendor string", lambda d: d["usb"].__setitem__("vendor_id", "0x1209"), False)
    v("bits 0", lambda d: d["dac"].__setitem__("bits", 0), False)
    v("bits 17", lambda d: d["dac"].__setitem__("bits", 17), False)
    v("zero calibration", lambda d: d["calibration"].__setitem__("um_per_v_40hz", 0.0), False)
    v("negative voltage", lambda d: d["limits"].__setitem__("max_voltage_v_rms", -40.0), False)
    v("integer voltage ok", lambda d: d["limits"].__setitem__("max_voltage_v_rms", 40), True)
    v("gain zero ok", lambda d: d["output"].__setitem__("gain", 0.0), True)
    v("negative gain", lambda d: d["output"].__setitem__("gain", -1.0), False)
    v("ttl 0", lambda d: d["output"].__setitem__("ttl_ms", 0.0), False)
    v("unknown top key", lambda d: d.__setitem__("colour", "red"), False)
    v("unknown section key", lambda d: d["dac"].__setitem__("volts", 3), False)
    v("duplicate channel", lambda d: d["contactors"].__setitem__("channel", [0] * 24), False)
    v("channel not list", lambda d: d["contactors"].__setitem__("channel", 3), False)
    v("bool as number", lambda d: d["dac"].__setitem__("bits", True), False)
    v("section not table", lambda d: d.__setitem__("limits", 5), False)
    return out


@pytest.mark.parametrize("name, doc, ok", _variants(), ids=[v[0] for v in _variants()])
def test_schema_and_loader_agree(name, doc, ok):
    schema = json.loads((ROOT / "schemas" / "device.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    schema_ok = jsonschema.Draft202012Validator(schema).is_valid(doc)
    try:
        profile_from_dict(doc)
        loader_ok = True
    except InputError:
        loader_ok = False
    assert schema_ok == ok and loader_ok == ok


def test_loader_cross_field_checks_beyond_schema():
    # The schema cannot relate channel to count; the loader must reject these.
    doc = copy.deepcopy(DEFAULT_PROFILE)
    doc["contactors"]["channel"] = list(range(23))
    with pytest.raises(InputError, match="23 entries"):
        profile_from_dict(doc)
    doc["contactors"]["channel"] = list(range(1, 25))
    with pytest.raises(InputError, match="0..23"):
        profile_from_dict(doc)


def test_bad_toml_file(tmp_path):
    p = tmp_path / "d.toml"
    p.write_text("[usb\nvendor_id = 1")
    with pytest.raises(InputError, match="not valid TOML") as info:
        load_profile(p)
    assert str(p) in str(info.value)
    with pytest.raises(InputError, match="no such device profile"):
        load_profile(tmp_path / "none.toml")
