"""Device profiles (TOML) and the µm -> volts -> DAC code conversion.

A profile describes one stimulator: its USB ids, how asset contactors map to device channels,
the DAC, the calibration (µm of peak displacement per V rms, at 40 Hz and at 320 Hz, measured
with skin load) and the safety limits. The loader validates by hand (the player must not need
jsonschema); ``schemas/device.schema.json`` describes the same structure and a test checks that
both accept and reject the same documents.

Safety rules applied by :meth:`DeviceProfile.to_codes`, in this order:

1. non-finite or negative amplitudes become 0 (counted as ``nonfinite``);
2. the global gain is applied;
3. the peak displacement ``a40 + a320`` is limited to ``max_displacement_um`` and the combined
   drive ``sqrt(V40^2 + V320^2)`` to ``max_voltage_v_rms``, both by scaling the pair
   (keeping its 40/320 balance; counted as ``clamped``);
4. volts become codes ``round(V / full_scale_v_rms * (2^bits - 1))``, clipped to the code range.
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from playback.errors import InputError
from playback.text_files import read_text

DEFAULT_PROFILE_PATH = Path(__file__).resolve().parents[1] / "samples" / "devices" / "haptex24.toml"

# The default profile, identical to samples/devices/haptex24.toml (a test keeps them equal);
# kept here so the player works when the samples folder is not installed.
DEFAULT_PROFILE: dict[str, Any] = {
    "name": "HAPTEX 24-contactor array (placeholder calibration)",
    "usb": {"vendor_id": 0x1209, "product_id": 0x0001, "interface": 0, "endpoint_out": 0x01,
            "timeout_ms": 10, "retries": 2},
    "contactors": {"count": 24, "n_channels": 24, "channel": list(range(24))},
    "dac": {"bits": 12, "full_scale_v_rms": 40.0},
    "calibration": {"um_per_v_40hz": 2.5, "um_per_v_320hz": 0.5},
    "limits": {"max_voltage_v_rms": 40.0, "max_displacement_um": 100.0},
    "output": {"gain": 1.0, "ttl_ms": 50.0},
}

# Most contactors (and channels) a profile, and so a scene the player can play, may have.
MAX_CONTACTORS = 4096
# (section, key) -> (type, required, (min, max), exclusive_min)
_FIELDS: dict[tuple[str, str], tuple[type, bool, tuple[float | None, float | None], bool]] = {
    ("usb", "vendor_id"): (int, True, (0, 0xFFFF), False),
    ("usb", "product_id"): (int, True, (0, 0xFFFF), False),
    ("usb", "interface"): (int, False, (0, 255), False),
    ("usb", "endpoint_out"): (int, False, (1, 15), False),
    ("usb", "timeout_ms"): (int, False, (1, 10000), False),
    ("usb", "retries"): (int, False, (0, 10), False),
    ("contactors", "count"): (int, True, (1, MAX_CONTACTORS), False),
    ("contactors", "n_channels"): (int, False, (1, MAX_CONTACTORS), False),
    ("dac", "bits"): (int, True, (1, 16), False),
    ("dac", "full_scale_v_rms"): (float, True, (0, None), True),
    ("calibration", "um_per_v_40hz"): (float, True, (0, None), True),
    ("calibration", "um_per_v_320hz"): (float, True, (0, None), True),
    ("limits", "max_voltage_v_rms"): (float, True, (0, None), True),
    ("limits", "max_displacement_um"): (float, True, (0, None), True),
    ("output", "gain"): (float, False, (0, None), False),
    ("output", "ttl_ms"): (float, False, (1, 10000), False),
}
_SECTIONS = {"usb", "contactors", "dac", "calibration", "limits", "output"}
_REQUIRED_SECTIONS = {"usb", "contactors", "dac", "calibration", "limits"}
_DEFAULTS = {("usb", "interface"): 0, ("usb", "endpoint_out"): 1, ("usb", "timeout_ms"): 10,
             ("usb", "retries"): 2, ("output", "gain"): 1.0, ("output", "ttl_ms"): 50.0}


@dataclass(frozen=True)
class DeviceProfile:
    """A validated device profile; see the module docstring for the conversion it performs."""

    name: str
    vendor_id: int
    product_id: int
    interface: int
    endpoint_out: int
    timeout_ms: int
    retries: int
    count: int
    n_channels: int
    channel: tuple[int, ...]
    dac_bits: int
    full_scale_v_rms: float
    um_per_v_40hz: float
    um_per_v_320hz: float
    max_voltage_v_rms: float
    max_displacement_um: float
    gain: float
    ttl_ms: float

    @property
    def code_max(self) -> int:
        """Largest DAC code."""
        return (1 << self.dac_bits) - 1

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (for the record's attributes)."""
        d = asdict(self)
        d["channel"] = list(self.channel)
        return d

    def to_codes(self, a40_um: np.ndarray, a320_um: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, int, int]:
        """Amplitudes (asset contactor order, µm peak) -> DAC codes in device channel order.

        Returns
        -------
        codes40, codes320 : ndarray of uint16, shape (n_channels,)
            Unmapped channels are 0.
        n_clamped : int
            Contactors whose pair was scaled down by a limit.
        n_nonfinite : int
            Amplitudes that were NaN, infinite or negative and were set to 0.
        """
        a40 = np.array(a40_um, dtype=np.float64).reshape(-1)
        a320 = np.array(a320_um, dtype=np.float64).reshape(-1)
        if a40.shape != (self.count,) or a320.shape != (self.count,):
            raise ValueError(f"expected {self.count} amplitudes per channel, got {a40.shape} and {a320.shape}")
        bad40 = ~np.isfinite(a40) | (a40 < 0)
        bad320 = ~np.isfinite(a320) | (a320 < 0)
        n_nonfinite = int(bad40.sum() + bad320.sum())
        if n_nonfinite:
            a40[bad40] = 0.0
            a320[bad320] = 0.0
        gain = self.gain
        a40 *= gain
        a320 *= gain
        # Limits scale the pair together so the 40/320 mix (the "tactile colour") is kept.
        scale = np.ones_like(a40)
        peak = a40 + a320
        over = peak > self.max_displacement_um
        scale[over] = self.max_displacement_um / peak[over]
        v40 = a40 * scale / self.um_per_v_40hz
        v320 = a320 * scale / self.um_per_v_320hz
        v_rms = np.hypot(v40, v320)
        over_v = v_rms > self.max_voltage_v_rms
        if over_v.any():
            f = self.max_voltage_v_rms / v_rms[over_v]
            v40[over_v] *= f
            v320[over_v] *= f
        n_clamped = int((over | over_v).sum())
        k = self.code_max / self.full_scale_v_rms
        c40 = np.clip(np.rint(v40 * k), 0, self.code_max).astype(np.uint16)
        c320 = np.clip(np.rint(v320 * k), 0, self.code_max).astype(np.uint16)
        codes40 = np.zeros(self.n_channels, dtype=np.uint16)
        codes320 = np.zeros(self.n_channels, dtype=np.uint16)
        idx = np.asarray(self.channel, dtype=np.intp)
        codes40[idx] = c40
        codes320[idx] = c320
        return codes40, codes320, n_clamped, n_nonfinite

    def code_to_v_rms(self, codes: np.ndarray) -> np.ndarray:
        """DAC codes -> drive voltage (V rms), the inverse of the last step of :meth:`to_codes`."""
        return np.asarray(codes, dtype=np.float64) * (self.full_scale_v_rms / self.code_max)


def _check_value(source: str, section: str, key: str, value: Any) -> Any:
    kind, _, (lo, hi), excl = _FIELDS[(section, key)]
    where = f"[{section}] {key}"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(source, f"{where} must be a number, got {value!r}")
    if kind is int and not isinstance(value, int):
        raise InputError(source, f"{where} must be an integer, got {value!r}")
    if not math.isfinite(value):
        raise InputError(source, f"{where} must be finite")
    if lo is not None and (value <= lo if excl else value < lo):
        raise InputError(source, f"{where} must be {'>' if excl else '>='} {lo}, got {value}")
    if hi is not None and value > hi:
        raise InputError(source, f"{where} must be <= {hi}, got {value}")
    return kind(value)


def profile_from_dict(doc: dict[str, Any], source: str = "device profile") -> DeviceProfile:
    """Validate a parsed profile document (same rules as the schema, plus cross-field checks).

    Raises
    ------
    InputError
        One line naming `source` and the offending key.
    """
    if not isinstance(doc, dict):
        raise InputError(source, "profile must be a table")
    unknown = set(doc) - _SECTIONS - {"name"}
    if unknown:
        raise InputError(source, f"unknown key(s) {', '.join(sorted(unknown))}")
    name = doc.get("name", "")
    if not isinstance(name, str):
        raise InputError(source, "name must be a string")
    values: dict[tuple[str, str], Any] = {}
    for section in _SECTIONS:
        sec = doc.get(section)
        if sec is None:
            if section in _REQUIRED_SECTIONS:
                raise InputError(source, f"missing section [{section}]")
            sec = {}
        if not isinstance(sec, dict):
            raise InputError(source, f"[{section}] must be a table")
        allowed = {k for (s, k) in _FIELDS if s == section} | ({"channel"} if section == "contactors" else set())
        extra = set(sec) - allowed
        if extra:
            raise InputError(source, f"unknown key(s) in [{section}]: {', '.join(sorted(extra))}")
        for (s, key), (_, required, _, _) in _FIELDS.items():
            if s != section:
                continue
            if key in sec:
                values[(s, key)] = _check_value(source, s, key, sec[key])
            elif required:
                raise InputError(source, f"missing [{section}] {key}")
    count = values[("contactors", "count")]
    n_channels = values.get(("contactors", "n_channels"), count)
    channel = doc["contactors"].get("channel", list(range(count)))
    if (not isinstance(channel, list) or not all(isinstance(c, int) and not isinstance(c, bool) for c in channel)):
        raise InputError(source, "[contactors] channel must be a list of integers")
    if len(channel) != count:
        raise InputError(source, f"[contactors] channel has {len(channel)} entries, count is {count}")
    if len(set(channel)) != len(channel):
        raise InputError(source, "[contactors] channel lists a device channel twice")
    if channel and (min(channel) < 0 or max(channel) >= n_channels):
        raise InputError(source, f"[contactors] channel entries must be in 0..{n_channels - 1}")
    get = lambda s, k: values.get((s, k), _DEFAULTS.get((s, k)))  # noqa: E731
    return DeviceProfile(
        name=name, vendor_id=get("usb", "vendor_id"), product_id=get("usb", "product_id"),
        interface=get("usb", "interface"), endpoint_out=get("usb", "endpoint_out"),
        timeout_ms=get("usb", "timeout_ms"), retries=get("usb", "retries"),
        count=count, n_channels=n_channels, channel=tuple(channel),
        dac_bits=get("dac", "bits"), full_scale_v_rms=get("dac", "full_scale_v_rms"),
        um_per_v_40hz=get("calibration", "um_per_v_40hz"), um_per_v_320hz=get("calibration", "um_per_v_320hz"),
        max_voltage_v_rms=get("limits", "max_voltage_v_rms"),
        max_displacement_um=get("limits", "max_displacement_um"),
        gain=float(get("output", "gain")), ttl_ms=float(get("output", "ttl_ms")),
    )


def load_profile(path: str | Path | None = None) -> DeviceProfile:
    """Read a device profile TOML; ``None`` gives the built-in HAPTEX 24-contactor default."""
    if path is None:
        return profile_from_dict(DEFAULT_PROFILE, "built-in haptex24 profile")
    path = Path(path)
    text = read_text(path, "device profile")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML ({exc})") from None
    return profile_from_dict(doc, str(path))
