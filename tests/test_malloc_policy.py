"""The solver's malloc policy: freed blocks are reused, not handed back and faulted in again."""
from __future__ import annotations

import platform
import subprocess
import sys
from unittest import mock

import numpy as np
import pytest

from haptex_compile import malloc_policy, shading_variational

GLIBC = platform.libc_ver()[0] == "glibc"

# Rounds of four 1200 x 1200 float32 arrays (a 1 Mpx plain image's domain) made and freed, as
# in the solver's CG iterations; the minor page faults of 20 rounds after 2 of warm-up.
_FAULTS = """
import resource, sys
import numpy as np
from haptex_compile import malloc_policy
if sys.argv[1] == "policy":
    assert malloc_policy.keep_freed_memory()
def rounds(k):
    for _ in range(k):
        arrays = [np.ones((1200, 1200), np.float32) for _ in range(4)]
        del arrays
rounds(2)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
rounds(20)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(not GLIBC, reason="the policy sets glibc's malloc only")
def test_freed_blocks_are_reused_rather_than_faulted_in_again():
    # The 20 rounds touch 20 x 4 x 1200² x 4 bytes = 112 500 pages of 4 KiB; with the blocks
    # kept, the warm-up's pages serve them all.
    pages = 20 * 4 * 1200 * 1200 * 4 // 4096
    assert _faults("policy") < 0.01 * pages


def test_a_solve_applies_the_policy():
    img = 0.5 + 0.01 * np.random.default_rng(0).standard_normal((64, 64))
    with mock.patch.object(shading_variational, "keep_freed_memory") as keep:
        shading_variational.solve_variational(img, np.ones_like(img), np.array([0.5, 0.0, np.sqrt(0.75)]), 0.6,
                                              max_levels=1, fine_gn=1)
    keep.assert_called_once_with()


def test_disabled_policy_changes_nothing():
    with mock.patch.object(malloc_policy, "ENABLED", False), mock.patch.object(malloc_policy, "_applied", None):
        assert malloc_policy.keep_freed_memory() is False
