"""Generate the bundled samples (nothing is copied from elsewhere; everything is made here).

``python samples/make_samples.py DIR`` writes into DIR:

* ``weave.png``: a photograph-like image of a plain weave, rendered with Lambertian shading
  from a known woven-like height map (light slant 40 deg, tilt 330 deg: from the upper right,
  as photos are usually lit), with sensor noise and a slow illumination gradient; 20 um/pixel;
* ``twill_height.npy``: a 2/2 twill relief in um (thread crown 30 um), 20 um per pixel;
* ``gravel.png``: scikit-image's ``data.gravel()`` (a non-periodic photograph);
* ``brick.png``: scikit-image's ``data.brick()`` (near-regular, with perspective).

Deterministic: fixed seeds, PNGs written without timestamps.
"""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np


def weave_photo(seed: int = 0) -> np.ndarray:
    from haptex_compile.shading import Light, render_lambertian
    from haptex_compile.known_surfaces import woven_like

    px = 20.0
    height = woven_like((384, 384), px, thread_spacing_um=300.0)
    image = render_lambertian(height, px, Light(slant_deg=40.0, tilt_deg=330.0), albedo=0.8)
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:384, 0:384] / 384.0
    image = image * (0.85 + 0.15 * x) + rng.normal(0.0, 0.01, image.shape)
    return np.clip(image * 255.0, 0, 255).astype(np.uint8)


def twill_height() -> np.ndarray:
    from haptex_compile.kes import weave_relief

    relief, _ = weave_relief(32.0, 28.0, "twill", pixel_size_um=20.0, min_extent_mm=6.0)
    return (30.0 * np.asarray(relief, dtype=float)).astype(np.float64)


def main(out_dir: str) -> None:
    from skimage import data

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "weave.png"), weave_photo())
    np.save(out / "twill_height.npy", twill_height())
    cv2.imwrite(str(out / "gravel.png"), data.gravel())
    cv2.imwrite(str(out / "brick.png"), data.brick())


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(Path(__file__).parent / "gen"))
