"""The paper's Brownian-surface experiment: felt roughness rises with fractal dimension D = 3 - H."""
from __future__ import annotations

import numpy as np

from haptex_compile.colours import TwoColourModel
from haptex_compile.fractal import brownian_surface
from haptex_compile.frame_analysis import AnalysisSettings
from haptex_compile.surface import Surface
from haptex_compile.tables import build_tables, table_grid


def test_total_intensity_and_pacinian_share_rise_with_dimension():
    model, settings = TwoColourModel(), AnalysisSettings()
    t40, t320 = float(model.thresholds.np_(40.0)), float(model.thresholds.p(320.0))
    totals, shares = [], []
    for hurst in (0.2, 0.5, 0.8):  # D = 2.8, 2.5, 2.2: decreasing D
        z = brownian_surface(128, hurst, pixel_size_um=20.0, rms_um=5.0, seed=4)
        s = Surface(z, 20.0, False)
        tab = build_tables(s, model, settings, np.array([0.0, 90.0]), np.array([80.0]), table_grid(s, 0.5))
        totals.append(float(np.mean(np.hypot(tab.intensity_p, tab.intensity_np))))
        f40, f320 = tab.a40 / t40, tab.a320 / t320
        shares.append(float(np.mean(f320 / (f40 + f320))))
    # Equal RMS height: a rougher (higher-D) surface puts more of it at short wavelengths, which
    # the Pacinian channel feels at 80 mm/s; both measures fall strictly as D falls.
    assert totals[0] > totals[1] > totals[2]
    assert shares[0] > shares[1] > shares[2]
    assert totals[0] > 2 * totals[2]
