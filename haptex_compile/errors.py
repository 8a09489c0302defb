"""Exceptions that the command-line tools turn into one-line messages.

They live in :mod:`playback.errors` so that the light player shares them without importing
the compiler; this module re-exports them for the compiler's code.
"""
from __future__ import annotations

from playback.errors import AssetError, DeviceError, HaptexError, InputError

__all__ = ["AssetError", "DeviceError", "HaptexError", "InputError"]
