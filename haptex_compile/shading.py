"""Heights from shading: Lambertian rendering, light estimation, solvers and relief scaling.

Conventions (DOMAIN.md): image rows are +v (+y, down), columns +u (+x, right); the height axis
points towards the camera. A light of slant ``s`` and tilt ``t`` is the unit vector
``L = (sin s cos t, sin s sin t, cos s)`` in (x, y, z); a surface of slopes
``p = dh/dx, q = dh/dy`` has normal ``(-p, -q, 1) / sqrt(1 + p**2 + q**2)`` and the Lambertian
image is ``albedo * max(0, n . L)`` (attached shadows only, no cast shadows).

Heights from shading have no absolute scale (the slopes scale with the assumed slant and
albedo); :func:`scale_relief` fixes it from a stated relief.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from haptex_compile.forked_map import forked_map
from haptex_compile.shading_prior import along_light_power

__all__ = [
    "Light",
    "SfsResult",
    "render_lambertian",
    "estimate_light",
    "estimated_light_note",
    "tsai_shah",
    "shape_from_shading",
    "scale_relief",
    "normalised_height_error",
    "tilt_axis_difference_deg",
    "valid_pixels",
    "METHODS",
]

#: Pixels at or above this (saturated) or at or below DARK (black) carry no slope information.
SATURATED = 0.99
DARK = 0.01
METHODS = ("default", "accurate", "tsai-shah")
# Below this slant the linear term of the reflectance (the only one that fixes the sign of the
# slopes) is too weak: shape from shading is ill-posed and we fall back (see shape_from_shading).
MIN_SLANT_DEG = 5.0
MAX_SLANT_DEG = 89.0
# From this slant on, attached and cast shadows dominate and the solution degrades.
GRAZING_DEG = 75.0
# On a periodic tile, light within this angle of a direction across which a tile-sized wave
# runs (the tile's axes and diagonals, i.e. perpendicular to the wave vectors of 1 cycle per
# tile along x, y or both) is warned of: those waves have no slope along the light, so the
# shading sees them only at second order and the solver leaves them wrong. Measured on the
# bench surfaces at 60° (256 px, light given): plain weave tilt 0, +1, +2, +3° 0.885, 0.881,
# 0.823, 0.067; bumps at 270° 0.758, 0.450 (+1), 0.070 (+2), 0.023 (+3); Brownian at 0°
# 0.213, 0.187 (+1), 0.092 (+2), 0.040 (+3); off these directions 0.02-0.07.
ALIGNED_TILT_DEG = 3.0
# A lattice relief (a weave photo's tile) lit nearly along one of its weave directions: the
# profiles across that direction (a yarn's cross-section) have little slope along the light,
# and the shading sees them at first order only in proportion to sin(slant) |sin(angle between
# the tilt and the direction)| (see weave_visibility), which is warned of below this. Measured
# with bench/bench_photo.py (1024 px photos of 20 µm pixels, light given; plain weaves and
# smooth cells on a square and an oblique lattice, slants 15-60°, tilts 0-30° off a weave
# direction 0, 3, 8, 12, 20, 30°): 54 lights below 0.15, 25 of them with height errors above
# 0.1 from the pyramid alone (up to 0.76, plain weaves lit 3° off their yarns at 30°); 18 above
# it, errors at most 0.105. Below it the solve adds starts at full resolution
# (_fine_starts, on a small window of the lattice: _start_from_cell), which leaves 7
# above 0.1 (up to 0.74); at slant 15° every tilt is below it on a square lattice.
WEAVE_VISIBILITY_MIN = 0.15
# Joint light search (see _refine_light): reduced image side, the assumed alignment of the best
# lit normal with the light (cos 35°), and the slant bias that assumption can cause.
SEARCH_SIDE_PX = 96
# Worker processes that solve the search's candidate lights side by side, and the extra
# starts of a tile lit along its axes or a weave direction (_bare_tile_starts, _held_starts,
# _fine_starts; None: one per CPU this process may use; 1: in the calling process; see
# forked_map). The same results either way.
SEARCH_PROCESSES: int | None = None
# The final stage's image side at most (the whole image when it is smaller; see _refine_light).
FINAL_SIDE_PX = 256
# The coarse image is rescanned at the final side when it loses more than this fraction of the
# image's variance.
MAX_REDUCTION_LOSS = 0.05
# The final stage first scans the tilt this far either side of the coarse estimate.
TILT_SCAN_DEG = 30.0
TILT_SCAN_STEP_DEG = 10.0
ALIGN_COS = float(np.cos(np.deg2rad(35.0)))
CAP_BIAS_DEG = 2.0
# An estimate whose fitted albedo is within 2 % of that bound is flagged: there the misfit
# did not fix the slant (a plateau of steep lights with a large albedo fits as well).
AT_BOUND_FRACTION = 0.98
# Below that plateau, a light whose misfit is this fraction of the best at the image
# statistics' slant or less is a well (true lights on lattice reliefs: 0.03-0.21; random
# bumps and Brownian surfaces under near-frontal light, which have none: 0.8-0.9).
WELL_DEPTH = 0.3
# That plateau, where the image does not fix the slant, lies near acos(ALIGN_COS) = 35° plus
# the relief's slopes (measured 34-46°); a flagged estimate steeper than this is a steep light
# with the bound active (photo bench, lattice windows lit at 55°: 50-58°), left as it is (the
# search below it took a plain weave's window from 0.371 to 1.000).
PLATEAU_MAX_DEG = 47.5
KNEE_FACTOR = 1.25
# The tilt sweep of the light search (see _swept_tilt): steps over 180° at the first knee's
# slant, and how much lower than the statistical tilt's a free-albedo misfit must be for the
# search to be run again from there. At 10° the true light's well (about 20° wide on the
# reduced image of the lattices measured) is not stepped over.
TILT_SWEEP_STEP_DEG = 10.0
SWEEP_GAIN = 0.5
# The search from the swept tilt goes on to the final image only if its reduced-image result
# fits below this fraction of the first search's (measured: 0.05-0.09 where its light was
# then kept, 0.2-1.0 where it was not; each final stage costs 1.5-8 s).
SECOND_SEARCH_GAIN = 0.15
# Weight of the flat-on-average prior for non-periodic images (see solve_variational). With
# the spectral prior below holding a weave's long waves, the base prior need not be strong:
# measured against 1.0 (bench_shading's plain images, light given, slants 15-60°, summed
# errors of the four lights, image / crop): random bumps at 96 px 1.74 / 1.73 -> 1.49 / 1.58,
# 128 px 1.73 / 1.91 -> 1.61 / 1.70, 256 px 1.02 / 1.07 -> 0.94 / 0.86 (at 60°: 0.326 ->
# 0.298); Brownian surfaces 3.61 / 3.61 -> 3.16 / 3.29, 3.37 / 3.67 -> 2.92 / 3.38, 3.25 /
# 3.50 -> 3.20 / 3.36; the plain weave and sphere caps within 0.01. On 60 crops of 512 px
# tiles each (see LOWFREQ_PLANE_WEIGHT; both with an energy threshold of 2 to drop it), mean
# errors: random bumps 0.253 -> 0.237, plain weave 0.221 -> 0.225, sphere caps 0.328 ->
# 0.333. At 0.1 the weave's crops are worse (0.247, 10 above 0.4, against 0.225 and 7); at
# 0.03 the bumps' 256 px images too (1.09 / 0.93).
LOWFREQ_WEIGHT = 0.3
LOWFREQ_CYCLES = 1.0
# The prior is tested on the pyramid level at most LOWFREQ_CHECK_SIDE px across, and not the
# finest: solved again without it, and dropped if its result has more than
# LOWFREQ_REJECT_RATIO times the energy and the result without it an albedo at most
# LOWFREQ_REJECT_ALBEDO times its own (solve_variational's lowfreq_check_level). Measured
# (energy ratio, albedo ratio) on 96-256 px images (light given, slants 15-60°, tilts
# 30/120/200/300°) and on 210 crops of 512 px tiles (see LOWFREQ_PLANE_WEIGHT), after the
# error with and without the prior: sphere caps on flat ground 17-210 (0.89-1.07), with
# the prior 0.78-0.98, without 0.01-0.11; crops of a sphere cap without flat ground 1.25-210
# (0.88-1.03), better without the prior in all but one; textures (plain weave, random bumps,
# Brownian surfaces) 0.5-2.9, where the prior gave the better result up to 1.46 at albedo
# ratios below 1.1, up to 1.66 above (the plain weave at 60°: without the prior a steeper
# surface under albedo 1.1-1.6 x its own, error 0.95-1.0 against 0.07-0.14). On domains
# with wider margins (PLAIN_MARGIN 0.15-0.3) that weave reaches energy ratios of 2.1-3.5
# (albedo ratios 1.8-2.1, measured with weight 1), which an energy threshold alone then
# dropped. The threshold was 4 with no albedo test (and LOWFREQ_WEIGHT 1): crops of sphere
# caps with ratios of 1.9-4 came back flattened (0.97 -> 0.11 for a strip across the cap lit
# along its short side). Both changes on those 60 crops each, mean errors: sphere caps 0.354
# -> 0.328, plain weave 0.227 -> 0.225, random bumps 0.253 -> 0.237 (bench_shading's 30
# each: 0.364 -> 0.319, 0.243 -> 0.250, 0.270 -> 0.256).
LOWFREQ_CHECK_SIDE = 128
LOWFREQ_REJECT_RATIO = 1.75
LOWFREQ_REJECT_ALBEDO = 1.1
# The prior is tightened on the waves of up to SPECTRAL_PRIOR_CYCLES cycles per image side
# across the light that the image's waves along it show to have little power (a weave has
# none below its own frequency): a Gaussian prior of that power over noise of variance
# SPECTRAL_PRIOR_WEIGHT x albedo² (see shading_prior).
SPECTRAL_PRIOR_CYCLES = 6
SPECTRAL_PRIOR_WEIGHT = 3e-4
# With the prior, the slopes of the least-squares plane through the data region are held
# near 0 as well, with LOWFREQ_PLANE_WEIGHT x the prior's weight (see solve_variational's
# lowfreq_plane_weight): a tilt along the light darkens or brightens the image uniformly,
# which the albedo undoes, and the prior's few long waves on the periodic domain barely see a
# tilt whose return lies in the margin. Measured on 180 crops (90-420 px, any aspect, offset
# and tilt, slants 15-60°) of 512 px tiles, light given, against the same solver without it:
# plain weave mean error 0.221 -> 0.191, above 0.4: 8 -> 2 of 60 (worst 0.854 -> 0.775, lit
# 2° off its diagonal, where the spectral prior's 6 cycles take it: with 5, 0.076);
# random bumps 0.296 -> 0.245, worst 0.944 -> 0.468, above 0.4: 9 -> 3; sphere caps (whose
# prior is dropped) unchanged. Weights 0.3 and 1: the same within 0.01, the weave's mean
# 0.01 worse; bench_shading's plain-image table within 0.01 of the baseline. Random bumps of
# 1 Mpx at 45°: 1.82 -> 1.93 s (best of 3, same run), error 0.134 -> 0.130.
LOWFREQ_PLANE_WEIGHT = 0.1
# On the pyramid's quarter-resolution level and coarser ones, that plane is held (its weight x
# COARSE_PLANE_FACTOR; see solve_variational's lowfreq_plane_coarse). Their fits came out
# tilted along the light, and the finer levels spent their steps removing the tilt: random
# bumps of 1 Mpx lit at 45° (light given) left the 288 px level with 2.7 x the true RMS
# height, nearly all of it a plane sloping towards the light; the half-resolution level's
# first Gauss-Newton step was 0.73 px RMS, 97 % of it in waves of at most 8 cycles (a tile's
# first step there: 0.13 px, 38 %). With the plane held, that step is 0.20 px.
# Measured against 1 (light given, one run): 90 random crops (bench_shading's) mean errors
# plain weave 0.250 -> 0.235 (8 better by 0.01 or more, 2 worse), random bumps 0.2555 ->
# 0.2544, sphere caps the same; bench_shading's 32 plain images and crops within 0.006 but
# the Brownian ones (means 0.801 -> 0.789, 0.841 -> 0.847); 1 Mpx images of random bumps at
# 15° / 45° 0.334 / 0.128 -> 0.298 / 0.125 (1.83 -> 1.50 s at 45°, best of 3; the other
# three within 0.06 s), of the plain weave 0.230 / 0.091 -> 0.221 / 0.090. A factor of 1e4
# gives the same within 0.005 but the weave's crops (0.240); from the eighth-resolution
# level on, the bumps at 15° lose the gain (0.333). With the light estimated (bench_light's
# 60 crops, bench_shading's 16 plain crops) and bench_photo's coarse lattices: the same
# within 0.002 on average (bench_light, report e2b44e1: 26 of 60 estimates worse than the
# given light by more than 5 points, as before; 12 of them unflagged, against 11).
COARSE_PLANE_FACTOR = 1000.0
COARSE_PLANE_LEVEL = 2
# On an image with free edges, each line along the light has an unknown height offset (its
# strip does not close on itself as on a tile); the flat-on-average prior and the thin plate
# set them. On the finest level of an image of side N < PLAIN_FINE_PRIOR_PX, that prior's
# weight (and its plane term's) is multiplied by (N / PLAIN_FINE_PRIOR_PX)²
# (solve_variational's lowfreq_fine_factor; the coarse levels keep it whole, and the spectral
# prior is not changed). Why: against the prior, the thin plate's hold on those long waves
# grows as 1 / N² (k⁴ against k² at a given number of cycles per image), and on small images it
# sets the offsets better than the prior. Measured on random bumps as plain images (light
# given, 10 seeds, mean / worst error / seeds above 0.3, one run each against the factor 1):
# 256 px at 60° 0.287 / 0.385 / 3 -> 0.273 / 0.361 / 2, at 45° 0.227 -> 0.210, at 15° 0.244 /
# 0.322 / 1 -> 0.211 / 0.267 / 0; 128 px 0.471 / 0.411 / 0.428 -> 0.409 / 0.340 / 0.309 at 60°
# / 45° / 15°; 384 and 512 px within 0.004 (worst at 15°, 384 px 0.281 -> 0.291); 768 px (4
# seeds, factor 0.56) within 0.002 at 45-60° but 0.183 -> 0.189 at 15° (each seed 0.004-0.010
# worse, the trend of 1 Mpx below); bench_shading's 90 random crops: random bumps mean 0.250 ->
# 0.228, worst 0.541 -> 0.377, plain weave 0.240 -> 0.235, sphere caps (prior dropped) the
# same; its plain table's Brownian surface 0.839 / 0.808 / 0.820 / 0.674 -> 0.814 / 0.804 /
# 0.792 / 0.578; with the light estimated (bench_light's 60 crops) the same within 0.006 on
# average; with noise of sigma 0.01 (256 px) 0.298 / 0.243 / 0.307 -> 0.288 / 0.233 / 0.293,
# but with sigma 0.03 worse at 15° (0.646 -> 0.727: both far off). The same factor on 1 Mpx
# images (0.1 or 0.01) made them worse at 15° (seeds 2, 5: 0.189 / 0.234 -> 0.225-0.241 /
# 0.285-0.301), hence full weight from PLAIN_FINE_PRIOR_PX up.
PLAIN_FINE_PRIOR_PX = 1024
# A plain image's periodic domain halves to sizes with fast FFTs down to about this size.
FAST_HALF_PX = 128
# The margin around a plain image, as a fraction of its longer side (at least 8 px).
PLAIN_MARGIN = 0.08
# Black and saturated pixels enter the solve as one-sided bounds (see solve_variational).
CENSORED = True
# The light search solves each candidate light on a periodic domain; on a plain image the
# domain's seam joins edges that do not match, and the misfit there depends on the light.
# So a plain image's misfit leaves out a band of this fraction of each side (the solve still
# fits it). Measured on bench_shading's 16 plain crops (224 px; four surfaces at slants
# 15-60°, light estimated): summed height error 5.72 -> 5.15 / 5.18 / 5.16 with bands of
# 0.05 / 0.1 / 0.15, at no cost; at 0.15 random bumps lit at 30° and 45° 0.300 / 0.417 ->
# 0.215 / 0.206 (light given: 0.208 / 0.199), the plain weave at 45° and 60° 0.258 / 0.283
# -> 0.113 / 0.161 (given 0.099 / 0.143). On 60 random crops of 512 px tiles (90-420 px, the
# sphere cap, the plain weave, random bumps; 20 each), mean error for bands 0 / 0.05 / 0.15 /
# 0.25: sphere 0.485 / 0.481 / 0.469 / 0.457, weave 0.295 / 0.284 / 0.265 / 0.352, bumps
# 0.324 / 0.301 / 0.280 / 0.292 (light given: 0.342, 0.215, 0.219).
PLAIN_MISFIT_BAND = 0.15
# Every surface has an extremum, where its slope is 0 and its shading albedo x cos(slant):
# the albedo is at most the brightest pixels' level (the 99.9th percentile of the valid
# ones) over cos(slant), times ALBEDO_SLACK for that percentile. The solve's albedo is
# bounded there unless pixels are saturated (their level is then unknown). Without it, a
# plain weave lit at 60° on some periodic domains (320-352 px for a 256 px image) ran away to
# a steep surface under 3 x the true albedo: normalised error 1.0; bounded, 0.07-0.08.
ALBEDO_SLACK = 1.1
# Settings of solve_variational for method "default" (its own defaults are the light search's,
# whose misfit thresholds were measured with them). The half-resolution level converges (up
# to 8 Gauss-Newton steps of 20 conjugate-gradient iterations) with the albedo eliminated by
# variable projection, so the finest level starts from the right shape and albedo: otherwise
# the albedo, 0.3 % below the brightest pixels' bound there, is raised to it and the finest
# level's 3 steps do not recover (the sphere cap at 30°: 8 x the true surface's energy, a320
# +30 %). The projection is left out where sub-pixel roughness darkens that level's image
# (sub-pixel variance ratio above 0.1: the Brownian surfaces' 0.25-0.3, against 0.001-0.04
# for the sphere cap, the plain weave and the bumps), and on the other levels: both were
# measured worse on the Brownian surfaces, the latter on the plain weave too. Every level
# stops once a full step gains little (below), which pays for the rest. The
# albedo's lower bound is lowered by the 99.9th percentile's share of the image noise (3.09
# sigma), so that noise does not raise it (see solve_variational's bound_noise_sigmas).
# The finest level's steps take 9 CG iterations, not 6: its fine detail (woven cells of
# 16 px) converges in CG, not in more steps (12 plain weaves, 256 px tiles, noise-free, as a
# photo's tile averaged over many cells: mean error 0.143 -> 0.115; the bench's plain weave
# 0.038 -> 0.030 and bumps 0.078 -> 0.066; with noise of sigma 0.01 unchanged), for
# 15-17 % more time at 1 Mpx (bumps, Brownian; one run, with the fused matvec).
# Coarse pixels partly in shadow or saturated carry no intensity (see solve_variational's
# censored_data). Each Gauss-Newton step joins the level's previous two (the minimum of the
# model over their span, see solve_variational's subspace_steps), and a level stops once a
# full step gains less than 0.03 % (not 0.1 %): with both, the sphere cap at 60° (light
# given) a320 +30 % -> +16 %, height error 0.021 -> 0.016 (estimated light: +23 % -> +11 %);
# Brownian at 30° 0.044 -> 0.036, at 75° 0.199 -> 0.172; the other bench cases within 0.002.
# Images lit at low slant (up to LOW_SLANT_MAX_DEG) with smooth shading: the thin plate's
# weight grows by LOW_SLANT_LAM_GROWTH per level beyond the half-resolution one, not 8
# (solve_variational's smooth_lam_growth; smooth: that level's sub-pixel variance ratio at
# most 0.1, which leaves out the Brownian surfaces' 0.26-0.32). At 15°, starting from the
# heavily smoothed coarse levels, the half-resolution level settled in another minimum than
# the truth's (measured by level: seed 2 went 0.707 -> 0.415 there, seed 1 0.669 -> 0.095),
# and the finest level kept it: random bumps (the bench's generator,
# 10 seeds, 256 px tiles, light given) 0.042-0.381, mean 0.169, where the minimum near the
# truth has error 0.007 and 1/2.7 of the energy the default reached (seed 2; seed 9 1/2.0;
# the accurate solver 1/2.4 and 1/1.9). With 2: 15° mean 0.067, worst 0.205. Measured in one
# run with the growth at 2 for every slant: the same errors at 30-60° (10 seeds: means 0.052 /
# 0.045 / 0.042 -> 0.052 / 0.045 / 0.043), the bench's tiles, noisy images, steep lights and
# lattices within 0.006, but the sphere cap's worst a320 error (slants 15-60°) went +20 % ->
# +28 % (below threshold) and its error at 60° 0.016 -> 0.018, hence the slant limit; 1 Mpx
# bumps at 45° 1.01 -> 1.02 s. In the full bench only its random bumps at 15° moved (0.051 ->
# 0.050). Fewer pyramid levels or the fine starts do not help (0.38-0.82). A growth of 4 on
# every level: 15° worst 0.187, but the Brownian tiles 0.17-0.04 -> 0.23-0.06 without the
# ratio test, and 1 Mpx 1.01 -> 1.14 s (one more step at half resolution).
# The same holds for plain images and for the accurate method (same harness, one run each,
# against the growth of 8 there). Accurate tiles: 15° mean 0.162 -> 0.014, worst 0.381 ->
# 0.059; the bench's tiles, noisy images, steep lights, lattices and 7 Brownian seeds at 15°
# unchanged. Plain images of the same 10 seeds at 15° (256 px): mean 0.274 -> 0.243, worst
# 0.339 -> 0.314; 1 Mpx random bumps at 15° (seeds 5, 2) 0.298 / 0.324 -> 0.244 / 0.191,
# the plain weave 0.221 -> 0.152, at 10° bumps 0.72 -> 0.58, weave 0.282 -> 0.145, sphere
# caps within 0.001, 0-8 % more time (one run, 1.8-2.2 s); bench_shading's
# plain images and random crops within 0.005 on average (bumps 0.254 -> 0.249, weave 0.235 ->
# 0.239); light estimated on bench_light's 60 crops, 5 better by 0.03-0.09, none worse.
LOW_SLANT_LAM_GROWTH = 2.0
LOW_SLANT_MAX_DEG = 20.0
# At those slants the default's half-resolution level takes 12 CG iterations a step, not 20:
# its later steps creep along a shallow valley (each gains 0.03-0.2 % of the energy, all 8
# are needed), and how exactly each step is solved does not matter there (1 Mpx random bumps
# at 15°: after 20 iterations the CG's residual is still 0.2 of the right-hand side from the
# fourth step on; with 60, reaching 0.02, the same height error, 0.161 against 0.162).
# Measured with bound_start_albedo: 1 Mpx bumps at 15° 1.16 -> 0.98 s (same error, 0.158);
# random bumps of 30 seeds (256 px tiles, lights (15°, 30°), (20°, 120°), (15°, 300°)) mean
# error 0.059 / 0.042 / 0.073 -> 0.061 / 0.042 / 0.073; the bench's tiles at 15° within
# 0.001 (Brownian 0.172 -> 0.163). Not above 20°: the sphere cap at 60° needs its
# converged steps (a320 +16 % -> +20 % with 15 iterations, +25 % with 10 after 2 steps).
LOW_SLANT_MID_CG = 12
# Each level starts from an albedo within its bounds (see solve_variational's
# bound_start_albedo: the finest level's lower bound lies above the albedo it inherits).
DEFAULT_SOLVER = dict(mid_gn=8, mid_cg=20, fine_cg=9, gn_rtol=3e-4, albedo_projection=True,
                      projection_levels=(1,), projection_max_ratio=0.1, bound_noise_sigmas=3.09,
                      censored_data=False, subspace_steps=2, bound_start_albedo=True)
# Plain images: a level stops once a full step gains less than 0.1 %. Their half-resolution
# level gains 0.05-0.1 % a step for all its 8 steps (a tile's converges in 4), for no
# accuracy: bench_shading's plain-image table (light given, plain renderings and crops)
# summed 4.58 / 5.38 -> 4.61 / 5.38; random bumps of 1 Mpx 2.14-2.24 -> 1.62-1.72 s/Mpx.
# The finest level's steps take 6 CG iterations (a tile's 9 resolve its weave's cells; the
# edges of a plain image limit it first): the table 4.61 / 5.38 -> 4.59 / 5.36, bumps of
# 1 Mpx 1.94-2.14 -> 1.66-1.68 s/Mpx (error 0.146 -> 0.134), a 960 px crop of the plain weave
# the same errors (0.363, 0.123 at slants 15°, 45°).
PLAIN_SOLVER = dict(gn_rtol=1e-3, fine_cg=6)
# Method "accurate": more steps and iterations everywhere, converged solves, the albedo
# projected on every level without sub-pixel roughness (Brownian surfaces, 7 seeds x 2 tilts
# at 15°: mean a320 error -13 % -> -9 % with the ratio limit). Levels stop once a full step
# gains less than 0.01 %: same errors on the bench surfaces, 1 Mpx 2.80 -> 2.30 s. Steps
# join the previous two as in the default (sphere cap at 60°, light given: a320 +33 % -> +21 %).
ACCURATE_SOLVER = dict(coarse_gn=30, mid_gn=8, fine_gn=6, coarse_cg=20, fine_cg=20, tol=0.01,
                       albedo_projection=True, projection_max_ratio=0.1, gn_rtol=1e-4,
                       bound_noise_sigmas=3.09, censored_data=False, subspace_steps=2)
TERMINATOR_FRACTION = 0.25
OVEREXPOSED_RING = 0.9


@dataclass(frozen=True)
class Light:
    """A distant point light.

    Attributes
    ----------
    slant_deg : float
        Angle from the camera (view) axis in degrees; 0 = light straight above.
    tilt_deg : float
        Azimuth in degrees, counter-clockwise from +u towards +v: the light lies towards
        ``(cos tilt, sin tilt)`` in image (x, y) (x right, y down).
    slant_sd_deg, tilt_sd_deg : float
        Standard uncertainties in degrees (0 when given by the user).
    albedo_at_bound : bool
        Estimated lights only: the albedo fitted at this light sat at the light search's upper
        bound, so the image did not fix the slant (see :func:`estimate_light`); False when
        given by the user.
    """

    slant_deg: float
    tilt_deg: float
    slant_sd_deg: float = 0.0
    tilt_sd_deg: float = 0.0
    albedo_at_bound: bool = False

    def __post_init__(self) -> None:
        for name in ("slant_deg", "tilt_deg", "slant_sd_deg", "tilt_sd_deg"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"Light.{name} must be finite, got {getattr(self, name)!r}")
        if not 0.0 <= self.slant_deg <= 90.0:
            raise ValueError(f"Light.slant_deg must be in [0, 90], got {self.slant_deg!r}")
        if self.slant_sd_deg < 0 or self.tilt_sd_deg < 0:
            raise ValueError("Light uncertainties must be >= 0")

    @property
    def vector(self) -> np.ndarray:
        """Unit vector (lx, ly, lz) in image (x, y) and towards the camera (z)."""
        s, t = np.deg2rad(self.slant_deg), np.deg2rad(self.tilt_deg)
        return np.array([np.sin(s) * np.cos(t), np.sin(s) * np.sin(t), np.cos(s)])


@dataclass(frozen=True)
class SfsResult:
    """Output of :func:`shape_from_shading`.

    Attributes
    ----------
    height : ndarray
        Relative heights in µm as implied by the light and albedo used (no physical scale:
        use :func:`scale_relief`), mean 0.
    light : Light
        The light used (given, or estimated with its uncertainty).
    albedo : float
        The albedo used (estimated).
    method : str
        The solver that produced `height` (after any fallback).
    warnings : tuple of str
        Ill-posed inputs and fallbacks, one sentence each.
    """

    height: np.ndarray
    light: Light
    albedo: float
    method: str
    warnings: tuple[str, ...]


# --------------------------------------------------------------------------------------------
# Input handling


def _as_image(image) -> tuple[np.ndarray, list[str]]:
    """Grey image as float64 in [0, 1] (NaN kept: they are masked later)."""
    warnings: list[str] = []
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"image must be a 2-D grey array, got shape {a.shape}")
    if a.shape[0] < 4 or a.shape[1] < 4:
        raise ValueError(f"image must be at least 4 x 4 pixels, got {a.shape}")
    if np.issubdtype(a.dtype, np.integer):
        img = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.floating) or a.dtype == bool:
        img = a.astype(np.float64)
    else:
        raise ValueError(f"image must be numeric, got dtype {a.dtype}")
    finite = np.isfinite(img)
    if not finite.all():
        warnings.append(f"{int((~finite).sum())} non-finite pixels ignored")
    if finite.any():
        top = float(np.max(img[finite]))
        low = float(np.min(img[finite]))
        if top > 1.0 + 1e-6 or low < -1e-6:
            # Float images outside [0, 1]: map the range to [0, 1] rather than clip the data.
            span = top - min(low, 0.0)
            img = (img - min(low, 0.0)) / (span if span > 0 else 1.0)
            warnings.append("image values outside [0, 1] were rescaled to [0, 1]")
    return img, warnings


def valid_pixels(image: np.ndarray, mask=None) -> np.ndarray:
    """Pixels that carry slope information: finite, not saturated (>= 0.99), not black (<= 0.01).

    Parameters
    ----------
    image : ndarray
        Grey image in [0, 1].
    mask : ndarray of bool, optional
        Extra pixels to use (True) or ignore (False).

    Returns
    -------
    ndarray of bool
    """
    img = np.asarray(image, dtype=float)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(img) & (img > DARK) & (img < SATURATED)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != img.shape:
            raise ValueError(f"mask shape {m.shape} differs from image shape {img.shape}")
        ok &= m
    return ok


# --------------------------------------------------------------------------------------------
# Rendering


def render_lambertian(
    height_um: np.ndarray,
    pixel_size_um: float,
    light: Light,
    albedo: float = 1.0,
    *,
    periodic: bool = False,
) -> np.ndarray:
    """Lambertian image of a height map under a distant light (orthographic camera).

    Parameters
    ----------
    height_um : ndarray
        Height map in µm (rows = +v, columns = +u).
    pixel_size_um : float
        Pixel size in µm.
    light : Light
        The light.
    albedo : float
        Albedo in [0, 1].
    periodic : bool
        The height map is a tile: central differences wrap around at the edges (otherwise
        ``np.gradient``, one-sided at the edges).

    Returns
    -------
    ndarray
        Image ``albedo * max(0, n . L)`` in [0, 1]; slopes by central differences;
        attached shadows are 0, cast shadows are not modelled.
    """
    h = np.asarray(height_um, dtype=float)
    if h.ndim != 2:
        raise ValueError(f"height_um must be 2-D, got shape {h.shape}")
    if not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise ValueError(f"pixel_size_um must be finite and positive, got {pixel_size_um!r}")
    if not 0.0 <= albedo <= 1.0:
        raise ValueError(f"albedo must be in [0, 1], got {albedo!r}")
    if periodic:
        p = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / (2.0 * pixel_size_um)
        q = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) / (2.0 * pixel_size_um)
    else:
        q, p = np.gradient(h, pixel_size_um)
    lx, ly, lz = light.vector
    shade = (lz - p * lx - q * ly) / np.sqrt(1.0 + p * p + q * q)
    return np.clip(albedo * shade, 0.0, 1.0)


def tilt_axis_difference_deg(tilt_a_deg: float, tilt_b_deg: float) -> float:
    """Angle in [0, 90] degrees between two tilts' axes: a tilt and the tilt + 180° light the
    same surface, bumps versus dents (see :func:`estimate_light`)."""
    return abs((tilt_a_deg - tilt_b_deg + 90.0) % 180.0 - 90.0)


def normalised_height_error(height: np.ndarray, height_true: np.ndarray) -> float:
    """RMS residual of the best affine fit ``h_true ~ a h + b``, over RMS(h_true - mean).

    0 is perfect; 1 means the recovered height explains nothing. NaN entries count as failure
    (the error is then 1.0 or more).
    """
    h = np.asarray(height, dtype=float).ravel()
    t = np.asarray(height_true, dtype=float).ravel()
    t = t - t.mean()
    denom = float(np.sqrt(np.mean(t * t)))
    if denom == 0:
        raise ValueError("height_true is flat: the normalised error is undefined")
    if not np.all(np.isfinite(h)):
        return float("inf")
    hc = h - h.mean()
    var = float(np.dot(hc, hc))
    a = float(np.dot(hc, t)) / var if var > 0 else 0.0
    return float(np.sqrt(np.mean((t - a * hc) ** 2)) / denom)


# --------------------------------------------------------------------------------------------
# Tsai & Shah (1994)


def tsai_shah(
    image: np.ndarray, light: Light, *, n_iter: int = 50, pixel_size_um: float = 1.0
) -> np.ndarray:
    """Shape from shading by Tsai & Shah's linear approximation (Image Vis. Comput. 12, 1994).

    A faithful port: the slopes are backward differences ``p = Z[i, j] - Z[i, j-1]``,
    ``q = Z[i, j] - Z[i-1, j]`` (0 on the first row and column), the reflectance
    ``R = (1 + p ps + q qs) / (sqrt(1 + p² + q²) sqrt(1 + ps² + qs²))`` clipped at 0, and each
    pixel takes a Newton step on ``f(Z) = E - R(p, q)`` linearised in ``Z[i, j]`` alone, damped by
    the paper's gain ``K = S df / (W + df S df)`` with ``S`` updated as ``S = (1 - K df) S``
    (``S0 = 0.01``, ``W = 1e-8``), from a flat start ``Z = 0`` (Jacobi sweep: all pixels from the
    previous iterate). Here ``(ps, qs) = -tan(slant) (cos tilt, sin tilt)`` follows this module's
    light convention. No safeguards are added: with light along the view axis ``df/dZ`` is 0 at
    the flat start and nothing moves; for many other lights it diverges (values are returned as
    they are, which may be huge, but NaN/inf are replaced by 0 so that callers can score them).

    Parameters
    ----------
    image : ndarray
        Grey image in [0, 1] (the albedo is taken as 1, as in the paper).
    light : Light
        Light direction.
    n_iter : int
        Number of iterations.
    pixel_size_um : float
        Pixel size in µm: the returned heights are ``Z * pixel_size_um``.

    Returns
    -------
    ndarray
        Relative heights in µm (the paper's Z, which increases towards the camera), mean 0.
    """
    E, _ = _as_image(image)
    E = np.where(np.isfinite(E), E, 0.0)
    if n_iter < 0:
        raise ValueError(f"n_iter must be >= 0, got {n_iter!r}")
    slant = min(light.slant_deg, MAX_SLANT_DEG)
    t = np.deg2rad(light.tilt_deg)
    ps = -np.tan(np.deg2rad(slant)) * np.cos(t)
    qs = -np.tan(np.deg2rad(slant)) * np.sin(t)
    norm_s = np.sqrt(1.0 + ps * ps + qs * qs)
    Z = np.zeros_like(E)
    S = np.full_like(E, 0.01)
    W = 1e-8
    with np.errstate(all="ignore"):
        for _ in range(n_iter):
            p = np.zeros_like(Z)
            q = np.zeros_like(Z)
            p[1:, 1:] = Z[1:, 1:] - Z[1:, :-1]
            q[1:, 1:] = Z[1:, 1:] - Z[:-1, 1:]
            pq = 1.0 + p * p + q * q
            R = np.maximum(0.0, (1.0 + p * ps + q * qs) / (np.sqrt(pq) * norm_s))
            f = E - R
            df = -((ps + qs) / (np.sqrt(pq) * norm_s) - (p + q) * (1.0 + p * ps + q * qs)
                   / (np.sqrt(pq**3) * norm_s))
            K = S * df / (W + df * S * df)
            S = (1.0 - K * df) * S
            Z = Z - K * f  # Newton: Z - f / f' when W -> 0
    Z = np.where(np.isfinite(Z), Z, 0.0)
    return (Z - Z.mean()) * pixel_size_um


# --------------------------------------------------------------------------------------------
# Light and albedo estimation


def _moment_albedo(values: np.ndarray, slant_deg: float) -> float:
    """Albedo from the mean and variance of the intensities, for a known slant.

    For a stationary surface the linear term of ``R`` averages out, so with isotropic slopes
    (``<g²> = 2 <g_l²>``) to second order ``mean = a cos s (1 - var / (a² sin² s))``: a
    quadratic in the albedo ``a``. Bounded below by the brightest pixels (``R <= 1``).
    """
    v = values[np.isfinite(values)]
    if v.size == 0:
        return 1.0
    m, var = float(v.mean()), float(v.var())
    s = np.deg2rad(np.clip(slant_deg, 1.0, 85.0))
    c = np.cos(s)
    a = (m + np.sqrt(m * m + 4 * c * c * var / np.sin(s) ** 2)) / (2 * c)
    top = float(np.percentile(v, 99.9))
    return float(max(a, top, 1e-3))


def _downsample_to(img: np.ndarray, valid: np.ndarray, side: int):
    """Area-average image and weights so that the larger side is at most `side` pixels."""
    import cv2

    rows, cols = img.shape
    f = max(rows, cols) / side
    if f <= 1:
        return img.astype(np.float32), valid.astype(np.float32)
    size = (max(int(round(cols / f)), 8), max(int(round(rows / f)), 8))
    w = valid.astype(np.float32)
    wi = cv2.resize(np.where(valid, img, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return _normalised(wi, cv2.resize(w, size, interpolation=cv2.INTER_AREA))


def _block_average(img: np.ndarray, valid: np.ndarray, side: int):
    """Average image and weights over f x f blocks, f the smallest integer that brings the
    larger side to at most `side` pixels (edges wrap to fill the last blocks).

    The light search's final image: averaging over fractional blocks (:func:`_downsample_to`)
    mixes neighbouring pixels unevenly, which is not the shading of any surface. Measured on
    a lattice relief of 16 px cells at 256 px lit at 45°: reduced to 192 px that way, its
    misfit's minimum moved 15° in tilt; averaged over 2 x 2 blocks (128 px) it stayed on the
    true light. (The coarse stage keeps :func:`_downsample_to`: with 3 x 3 blocks instead, the
    bench's plain weave lost its 60° estimate, 60° -> 66°.)
    """
    rows, cols = img.shape
    f = int(np.ceil(max(rows, cols) / side))
    if f <= 1:
        return img.astype(np.float32), valid.astype(np.float32)
    pad = ((0, (-rows) % f), (0, (-cols) % f))
    w = np.pad(valid.astype(np.float32), pad, mode="wrap")
    wi = np.pad(np.where(valid, img, 0).astype(np.float32), pad, mode="wrap")
    r, c = w.shape[0] // f, w.shape[1] // f
    blocks = lambda a: a.reshape(r, f, c, f).mean(axis=(1, 3))  # noqa: E731
    return _normalised(blocks(wi), blocks(w))


def _normalised(wi: np.ndarray, ww: np.ndarray):
    """Weighted image over weights, and the reduced pixels that are mostly valid."""
    out = np.where(ww > 1e-3, wi / np.maximum(ww, 1e-3), 0.0).astype(np.float32)
    return out, (ww > 0.5).astype(np.float32)


def _tilt_axis(img: np.ndarray, valid: np.ndarray) -> tuple[float, float, float]:
    """Axis of the light's tilt from the image-gradient second moments.

    For an isotropic surface under the linear part of the reflectance, the gradient moment
    tensor is proportional to ``1 + 2 l l^T`` (l = tilt direction): its principal axis is the
    tilt, up to 180°. Returns (axis in degrees in [0, 180), anisotropy (l1-l2)/(l1+l2), sd).
    """
    gy, gx = np.gradient(np.where(valid, img, 0.0))
    ok = ndimage.binary_erosion(valid, iterations=1, border_value=0)
    if ok.sum() < 16:
        ok = valid
    gx, gy = gx * ok, gy * ok

    def axis(sl):
        jxx = float(np.sum(gx[sl] ** 2))
        jyy = float(np.sum(gy[sl] ** 2))
        jxy = float(np.sum(gx[sl] * gy[sl]))
        ang = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
        tr = jxx + jyy
        aniso = np.hypot(jxx - jyy, 2 * jxy) / tr if tr > 0 else 0.0
        return ang, aniso

    ang, aniso = axis((slice(None), slice(None)))
    # Spread over 4 x 4 blocks: the axial (doubled-angle) circular spread, / sqrt(blocks).
    rows, cols = img.shape
    doubled = []
    for i in range(4):
        for j in range(4):
            sl = (
                slice(i * rows // 4, (i + 1) * rows // 4),
                slice(j * cols // 4, (j + 1) * cols // 4),
            )
            a, _ = axis(sl)
            doubled.append(2 * a)
    c, s = np.mean(np.cos(doubled)), np.mean(np.sin(doubled))
    r = min(max(np.hypot(c, s), 1e-9), 1.0)
    sd_block = 0.5 * np.rad2deg(np.sqrt(-2 * np.log(r)))
    sd = float(min(sd_block / 4.0 + (90.0 if aniso < 0.02 else 0.0), 90.0))
    return float(np.rad2deg(ang) % 180.0), float(aniso), sd


def _moment_slant(values: np.ndarray) -> float:
    """Slant from the intensity moments, for Gaussian isotropic slopes (small-slope expansion).

    With ``I = a (c - s g_l) / sqrt(1 + g²)`` and slopes ``N(0, sigma²)`` per component, to
    leading order ``mean = a c``, ``var = a² s² sigma²`` and third central moment
    ``mu3 = -3 a³ s² c sigma⁴``, hence ``tan² slant = -3 var² / (mean mu3)``. The shading of
    a surface is negatively skewed (slopes only darken the flat-surface value ``a c``); no skew
    means grazing light. Returns degrees in [0, 90].
    """
    v = values[np.isfinite(values)]
    m = float(v.mean())
    var = float(v.var())
    mu3 = float(np.mean((v - m) ** 3))
    if m <= 0 or var <= 0:
        return 0.0
    if mu3 >= 0:
        return 90.0
    return float(np.rad2deg(np.arctan(np.sqrt(-3.0 * var * var / (m * mu3)))))


def estimate_light(image, *, mask=None, refine: bool = True, periodic: bool = True) -> tuple[Light, float]:
    """Estimate the light direction (with its uncertainty) and the albedo from one image.

    Statistics of the shading of a stationary, isotropic random surface (in the spirit of
    Pentland 1982 and Lee & Rosenfeld 1985):

    - tilt: the principal axis of the image-gradient moment tensor, which is proportional to
      ``1 + 2 l l^T`` for such surfaces in the linear-shading regime. The sign is not
      observable (a surface lit from ``t`` looks exactly like the inverted surface lit from
      ``t + 180°``); the convention is the human one, light from the top of the image
      (``sin(tilt) <= 0``);
    - slant: from the mean, variance and (negative) skew of the intensities
      (:func:`_moment_slant`);
    - albedo: from the mean and variance at that slant (:func:`_moment_albedo`);
    - with `refine` (default), the light is then estimated jointly with the shape: the light
      whose best surface (default solver, albedo bounded by the brightest pixels) leaves the
      smallest misfit (:func:`_refine_light`), and the albedo is the one fitted there. This
      matters: the solver is very sensitive to the light (1-2° off can double its error).
      When the albedo fitted there sits at its bound (``Light.albedo_at_bound``: the misfit
      did not fix the slant) above the statistical slant and no steeper than
      ``PLATEAU_MAX_DEG``, the light is searched again below that plateau (see
      :func:`_refine_light`) and the estimate stays flagged, with an uncertainty spanning
      the plateau.

    Without `refine`, the uncertainties are the spread of the same estimators over 4 x 4
    blocks divided by 4 (sampling only), with a floor of 5° for the slant's model error;
    surfaces with strongly non-Gaussian slopes (e.g. woven yarns) bias the statistical slant
    by 10-25°.

    Parameters
    ----------
    image : ndarray
        Grey image (integers are scaled by their maximum; floats should be in [0, 1]).
    mask : ndarray of bool, optional
        Pixels to use.
    refine : bool
        Estimate the light jointly with the shape (about 40 solves on a 96-pixel image and
        40 on one of at most 256 pixels; on 2 cores 1.3-2.1 s for the 256 px bench tiles,
        with each step's candidate lights solved side by side in ``SEARCH_PROCESSES``
        worker processes, 2.4-3.6 s in one).
    periodic : bool
        Whether the image wraps (a tile). The search solves each light on a periodic domain
        either way; on a plain image (False) its misfit leaves out a band of
        ``PLAIN_MISFIT_BAND`` of each side, where that domain's seam joins edges that do not
        match.

    Returns
    -------
    (Light, float)
        The light with its uncertainty, and the albedo.
    """
    img, _ = _as_image(image)
    return _estimate_light(img, valid_pixels(img, mask), mask, refine, periodic=periodic)


def _estimate_light(img, valid, mask, refine, censored=None, periodic=True) -> tuple[Light, float]:
    """:func:`estimate_light` on a prepared image (`censored`: :func:`_censored_pixels`
    of it, when the caller has them)."""
    if valid.sum() < 16 or float(np.std(img[valid])) < 1e-4:
        # No shading: nothing to estimate. Overhead light with full uncertainty.
        top = float(np.max(img[valid])) if valid.any() else 1.0
        return Light(0.0, 0.0, 90.0, 180.0), max(top, 1e-3)
    axis, _aniso, tilt_sd = _tilt_axis(img, valid)
    tilt = axis if axis == 0 else axis + 180.0  # sin(tilt) <= 0: light from the image top
    slant = _moment_slant(img[valid])
    rows, cols = img.shape
    blocks = []
    for i in range(4):
        for j in range(4):
            sl = (
                slice(i * rows // 4, (i + 1) * rows // 4),
                slice(j * cols // 4, (j + 1) * cols // 4),
            )
            vb = img[sl][valid[sl]]
            if vb.size >= 16 and float(np.std(vb)) > 1e-4:
                blocks.append(_moment_slant(vb))
    slant_sd = float(np.std(blocks) / np.sqrt(len(blocks))) if len(blocks) > 1 else 90.0
    slant_sd = float(min(max(slant_sd, 5.0), 90.0))
    albedo, at_bound = None, False
    if refine:
        slant, tilt, slant_sd, tilt_sd, albedo, at_bound = _refine_light(
            img, valid, slant, tilt, censored if censored is not None else _censored_pixels(img, mask),
            periodic=periodic,
        )
    if albedo is None:
        albedo = _moment_albedo(img[valid], slant)
    if np.sin(np.deg2rad(tilt)) > 0:
        # The search may cross the horizontal; the flip is exact (heights negated).
        tilt += 180.0
    light = Light(float(np.clip(slant, 0.0, 90.0)), float(tilt % 360.0), slant_sd, tilt_sd, at_bound)
    return light, albedo


def estimated_light_note(light: Light, periodic: bool = True) -> str:
    """The warning that states an estimated light and its uncertainty (`periodic` False: it
    was estimated on a plain image, where the search is less sure)."""
    note = (
        f"light estimated: slant {light.slant_deg:.1f} ± {light.slant_sd_deg:.1f}°, tilt"
        f" {light.tilt_deg:.1f} ± {light.tilt_sd_deg:.1f}° (the tilt's 180° ambiguity, bumps"
        " versus dents, is resolved by assuming light from the top of the image; the ± is the"
        " width of the misfit's minimum and does not cover other minima: on low lattice reliefs"
        " lit at 15-30° the search has settled 4-23° steeper, so give --light when it is known)"
    )
    if light.slant_sd_deg > 0 and light.slant_deg <= MIN_SLANT_DEG:
        note += (
            f"; the slant is the search's lowest ({MIN_SLANT_DEG:g}°): the light may be nearer the"
            " view axis still (diffuse or coaxial light, as in inspection photos), where the shading"
            " barely fixes the slopes' signs: give --light if it is known"
        )
    if light.albedo_at_bound:
        note += (
            "; UNRELIABLE: the misfit was lowest on a plateau of lights with the albedo at its"
            " upper bound, where it does not fix the slant (near-frontal light, a low relief or"
            f" a steep light lands there); a plateau below {PLATEAU_MAX_DEG:g}° was searched"
            " again beneath (the ± spans it): on the bench such estimates were right for 5 of 7"
            " lattice reliefs lit at 5-15°, otherwise up to 18° off in slant and 70° in tilt:"
            " give --light"
        )
    if not periodic:
        note += (
            "; on a plain image (not periodic) the estimate is less sure: on 60 random crops"
            " (90-420 px) of rendered sphere caps, plain weaves and random bumps, 27 estimates left"
            " the heights more than 5 points worse than the true light's, 12 of them not flagged"
            " UNRELIABLE (the true light turned 3° in tilt does that to 34 of them): give --light"
            " when it is known"
        )
    return note


def _reduction_loss(img: np.ndarray, valid: np.ndarray, side: int, reduce=_downsample_to) -> float:
    """Fraction of the image's variance (valid pixels) lost by reducing it to `side` pixels."""
    small, w = reduce(img, valid, side)
    if small.shape == img.shape:
        return 0.0
    import cv2

    back = cv2.resize(small, img.shape[::-1], interpolation=cv2.INTER_LINEAR)
    v = img[valid]
    var = float(np.var(v))
    return float(np.mean((v - back[valid]) ** 2) / var) if var > 0 else 0.0


def _finite_or_zero(img: np.ndarray) -> np.ndarray:
    """`img` with its non-finite pixels (which carry no data) set to 0."""
    return np.where(np.isfinite(img), img, 0.0)


def _misfit_function(img, valid, censored, side_px, reduce=_downsample_to, periodic=True):
    """The light search's misfit: a function ``fit(slant_deg, tilt_deg) -> (misfit, albedo)``
    on `img` reduced to at most `side_px` pixels (cached per light).

    For each light the default solver fits a surface, with the exact reflectance on every
    level and the albedo bounded above by ``I_top / ALIGN_COS``; the misfit is the data
    energy left (thin-plate term excluded); on a plain image (`periodic` False), outside a
    band of ``PLAIN_MISFIT_BAND`` times each side along the edges. ``fit.at_bound`` is the
    albedo from which a fit counts as held at that bound (``AT_BOUND_FRACTION`` of it).
    `censored` is :func:`_censored_pixels` of the image. ``fit.prefetch(lights)`` solves the
    (slant, tilt) pairs not cached yet at once, with ``fit.map_`` (a map over them that
    :func:`_refine_light` runs in worker processes; by default, one by one), and
    ``fit.solve_light(slant, tilt)`` is one uncached solve.
    """
    from haptex_compile.shading_variational import energy, solve_variational

    # A reduced image, not a crop: a crop is not periodic, and with free edges grazing
    # lights fit as well (measured on 256 px bumps: slant 15° estimated as 38°). Averaging
    # changes the shading of rough surfaces, though (Brownian tiles of 256 px: see the
    # bench). An image small enough is not reduced: its non-finite pixels (weight 0) must not
    # reach the solver's sums.
    small, w = reduce(_finite_or_zero(img), valid, side_px)
    # Censored pixels of the reduced image: the fraction of black (saturated) pixels in
    # each reduced pixel that has too few valid ones.
    cens = {}
    if CENSORED:
        everywhere = np.ones(img.shape, bool)
        for key, full in zip(("dark", "bright"), censored):
            frac = reduce(full, everywhere, side_px)[0] * (w == 0)
            cens[key] = frac if frac.any() else None
    top = float(np.percentile(small[w > 0], 99.9))
    w_misfit = w
    if not periodic:
        w_misfit = np.zeros_like(w)
        br, bc = (int(round(PLAIN_MISFIT_BAND * n)) for n in w.shape)
        w_misfit[br:w.shape[0] - br, bc:w.shape[1] - bc] = w[br:w.shape[0] - br, bc:w.shape[1] - bc]
        if w_misfit.sum() < 0.25 * w.sum():
            w_misfit = w  # a mask that leaves little data inside the band: keep it all
    cache: dict[tuple[float, float], tuple[float, float]] = {}

    def solve_light(s, t):
        # The exact reflectance on every level: the misfits of different lights are
        # compared, and the coarse levels' damping depends on the light.
        lv = Light(s, t % 360.0).vector
        z, a = solve_variational(small, w, lv, top, albedo_max=top / ALIGN_COS, subgrid_damping=0.0, **cens)
        e = energy(small, w_misfit, lv, a, z, lam=0.0, **cens)
        # A failed solve ranks last (np.argmin would take a NaN for the minimum).
        return (e if np.isfinite(e) else np.inf, a)

    def key_of(s, t):
        s = float(np.clip(s, MIN_SLANT_DEG, 85.0))
        return (round(s, 3), round(float(t) % 360.0, 3)), s

    def fit(s, t):
        key, s = key_of(s, t)
        if key not in cache:
            cache[key] = solve_light(s, t)
        return cache[key]

    def prefetch(lights):
        # The lights not cached yet, solved at once by fit.map_ (the same solves, in the
        # same order, as fitting them one by one).
        todo: dict = {}
        for s, t in lights:
            key, s = key_of(s, t)
            if key not in cache:
                todo.setdefault(key, (s, t))
        if todo:
            cache.update(zip(todo, fit.map_(list(todo.values()))))

    fit.at_bound = AT_BOUND_FRACTION * top / ALIGN_COS
    fit.solve_light, fit.prefetch = solve_light, prefetch
    fit.map_ = lambda lights: [solve_light(s, t) for s, t in lights]
    return fit


def light_misfit(image, light: Light, *, mask=None, periodic: bool = True) -> tuple[float, bool]:
    """The misfit by which the light search ranks lights, for one light: the data energy the
    default solver leaves on the image (block-averaged to at most ``FINAL_SIDE_PX`` pixels,
    as in the search's final stage), with the albedo bounded above by ``I_top / ALIGN_COS``.
    Lower is better; compare lights on the same image only. On a plain image
    (`periodic` False) a band of ``PLAIN_MISFIT_BAND`` of each side is left out, as in the
    search.

    Comparing the estimated light with the true one tells a search that missed the true
    light's well (the true light fits better) from shading that cannot tell them apart
    (the estimate fits as well or better), unless the bound excludes the true albedo there
    (steep light on a gentle relief: no normal within ``acos(ALIGN_COS)`` of the light).

    Returns
    -------
    (float, bool)
        The misfit, and whether the fitted albedo sits at its bound (within
        ``1 - AT_BOUND_FRACTION``).
    """
    img, _ = _as_image(image)
    valid = valid_pixels(img, mask)
    fit = _misfit_function(img, valid, _censored_pixels(img, mask), FINAL_SIDE_PX, _block_average,
                           periodic=periodic)
    misfit, albedo = fit(light.slant_deg, light.tilt_deg)
    return float(misfit), bool(albedo >= fit.at_bound)


class _LightFit(NamedTuple):
    """A light search's result (see :func:`_refine_light`)."""

    slant: float
    tilt: float
    slant_sd: float
    tilt_sd: float
    albedo: float
    at_bound: bool


def _refine_light(img, valid, slant, tilt, censored, side=SEARCH_SIDE_PX, periodic=True) -> _LightFit:
    """Estimate the light jointly with the shape: the light whose best surface explains the image.

    For each candidate light the default solver fits a surface to a reduced image (at most
    `side` pixels), with the albedo bounded above by ``I_top / ALIGN_COS`` (``I_top`` = 99.9th
    percentile of the intensities): somewhere on the surface a normal lies within
    ``acos(ALIGN_COS)`` of the light, so the brightest pixels are nearly the albedo. Without
    that bound, a grazing light with a large albedo and shallow slopes explains any image
    (the misfit falls monotonically towards grazing light); with it, the data misfit has a
    sharp minimum near the true slant (measured on the bench surfaces at 128 px).

    On a plain image (`periodic` False) the misfit leaves out a band along the edges, where
    the periodic solve must join edges that do not match (see ``PLAIN_MISFIT_BAND``).

    Attached shadows and over-exposed shading (``CENSORED``): each solve takes them as
    one-sided bounds (see :func:`_censored_pixels`), so a light that would leave a shadowed
    surface facing it costs misfit. Measured at slant 60° on 256 px tiles: the sphere cap's
    estimate went from 64° to 60° (height error 0.105 -> 0.031) and the plain weave's from
    66° to 60° (0.137 -> 0.052).

    Search: on an image reduced to at most `side` pixels, the slant on a 5° grid over 5-80°
    at the statistical tilt (the knee, see below), the tilt by halving steps (±8° to 1°), the
    slant on a 1° grid. Then on the final image (the image itself up to ``FINAL_SIDE_PX``,
    else block-averaged to at most that): the 5° slant grid again if the reduced image lost
    more than ``MAX_REDUCTION_LOSS`` of the image's variance, a tilt scan
    (±``TILT_SCAN_DEG`` in ``TILT_SCAN_STEP_DEG`` steps), and a compass search over slant and
    tilt together (steps 2°, 1°, 0.5°; they are coupled). The misfit is invariant under
    ``tilt -> tilt + 180°`` with the height negated (bumps versus dents), so the tilt stays
    on the side of the statistical estimate (light from the top of the image).

    Those steps are local, and the statistical tilt assumes an isotropic surface: a lattice
    relief's own anisotropy can turn it far from the light (31° on a 16 px oblique lattice,
    59° on a plain weave of 47 px cells), where they settle on another minimum. So the tilt
    axis is also swept on the reduced image at the first knee's slant (:func:`_swept_tilt`);
    a well there is searched again from (if its reduced image fits better), and that light
    kept if it fits the final image better with the albedo free. Measured (light estimated,
    noise-free): of 40 cases of ``bench/bench_shading.py`` (its four surfaces and three
    lattices at 15-60°, near-frontal lights) one changed, the oblique 16 px lattice at 15°,
    30° (22°, 349°, flagged, height error 0.828 -> 15°, 210°, 0.057); of the 16 photos of
    ``bench/bench_photo.py``'s first and coarse-lattice tables one, a smooth relief of 47 px
    cells at 40°, 60° (46°, 200°, flagged, 0.844 -> 40°, 240°, 0.018; what users feel, mean
    a40 / a320 against the true relief's, -22 % / -32 % -> 0 % / 0 %); the six real photos
    of ``../shared/fabrics`` kept their lights. Cost: the sweep, 18 solves on the reduced
    image (0.1-0.3 s); a second search's reduced stage where the sweep finds a well (0.3-1.2
    s), and its final stage only where that stage fits below ``SECOND_SEARCH_GAIN`` of the
    first's (+2.1 s on the photo it corrected).

    Returns
    -------
    _LightFit
        (slant, tilt, slant_sd, tilt_sd, albedo, at_bound): degrees, the albedo fitted at
        the chosen light, and whether that albedo is within
        ``1 - AT_BOUND_FRACTION`` of its bound. The uncertainties are the change
        that doubles the misfit (parabola through ±1°), at least 1° for the slant, combined
        in quadrature with ``CAP_BIAS_DEG`` for the bound's possible bias (too low a slant when
        no normal comes within ``acos(ALIGN_COS)`` of the light), and at least 0.5° for the
        tilt. On the bench surfaces (noise-free) the errors are 0-5° in slant and 0-5° in
        tilt; see ``bench/bench_shading.py`` for the calibration. They are local: on smooth
        lattice reliefs (RMS slope 0.16) lit at 15-30° the search settled 4-23° too steep
        with ±2°. Measured causes: the statistical tilt is up to 36° off on lattices; the
        true light's well is narrow (±2.5° at 256 px, where it is the global minimum of the
        misfit) and the solver's few steps leave its misfit above that of a plateau of steep
        lights, each with the albedo at its bound. Near-frontal light (slant 0-5°) lands on
        the same plateau (random bumps: 36°). `at_bound` marks that plateau: on the bench's
        four surfaces and three lattices at 256 px (slants 0, 5, 10, 15, 30, 45, 60°) it
        flagged every estimate 5° or more off in slant except three: overhead light on the
        sphere cap and the plain weave (estimated 14° and 16°) and one lattice at 15°
        (estimated 20°); and, of the good estimates, two at 60°, where the bound is active
        anyway.

        When the plateau lies above the statistical slant `slant` and no steeper than
        ``PLATEAU_MAX_DEG`` (a steeper one is a steep light with the bound active), the
        light is searched again below it (a 180° tilt scan at that slant, a slant scan, a
        compass search) and a well is taken if its misfit is at most ``WELL_DEPTH`` times
        the best at that slant, else that slant with the search's tilt; `at_bound` stays set
        and the uncertainties span the plateau. Measured at 256 px (bumps, Brownian surface,
        three lattices; 15 such cases, slants 0-30°): the lattices lit at 5-15° came out
        within 0.5° and 1° in 5 of 7 cases, with the height error of the given light (e.g.
        0.867 -> 0.042); the others were left at the statistics' slant (e.g. Brownian at 5°:
        0.960 -> 0.614, 0.603 with the light given). Cost: about 30-50 more solves, 2-4 s at
        256 px.
    """
    coarse = _misfit_function(img, valid, censored, side, periodic=periodic)
    final = _misfit_function(img, valid, censored, FINAL_SIDE_PX, _block_average, periodic=periodic)
    lossy = _reduction_loss(img, valid, side) > MAX_REDUCTION_LOSS
    # The candidate lights of each step of the search are solved side by side (forked_map).
    fits = (coarse, final)
    with forked_map(lambda k, s, t: fits[k].solve_light(s, t), SEARCH_PROCESSES) as map_:
        for k, fit in enumerate(fits):
            fit.map_ = lambda lights, k=k: map_([(k, s, t) for s, t in lights])
        knee, coarse_misfit, found = _search_light(coarse, final, lossy, float(slant), float(tilt))
        swept = _swept_tilt(coarse, knee, float(tilt))
        if swept is None:
            return found
        _, _, other = _search_light(coarse, final, lossy, float(slant), swept, beat=SECOND_SEARCH_GAIN * coarse_misfit)
        # The other search's light is kept where it fits better with the albedo free (both
        # misfits are cached: each search ended on its light's).
        if (other is not None and not other.at_bound
                and final(other.slant, other.tilt)[0] < final(found.slant, found.tilt)[0]):
            return other
        return found


def _swept_tilt(coarse, slant: float, tilt: float) -> float | None:
    """A tilt whose coarse misfit at `slant` (the first knee) is well below the statistical
    `tilt`'s, or None.

    The statistical tilt assumes an isotropic surface; a lattice relief's own anisotropy can
    turn it far from the light (measured: 59° on a plain weave of 47 px cells), beyond the
    local searches' reach. So the tilt axis is swept over 180° in ``TILT_SWEEP_STEP_DEG``
    steps at that slant, among lights whose albedo is free; the best is returned if its misfit
    is below ``SWEEP_GAIN`` times the statistical tilt's (or that one's albedo sat at the bound),
    even where it lies within the final stage's tilt scan of the search's light: that scan runs
    at the search's slant, and a well at another slant can be too narrow to show there
    (measured: a lattice relief lit at 15°, 30°, whose search ended free at 20.5°, 20°; the
    well, 10° of tilt away, fits 10 x better). The search from the swept tilt goes on to the
    final image only if it beats the first (``SECOND_SEARCH_GAIN``).
    """
    sweep = tilt + np.arange(0.0, 180.0, TILT_SWEEP_STEP_DEG)
    coarse.prefetch([(slant, t) for t in sweep])
    errs = [_free_misfit(coarse, slant, t) for t in sweep]
    best = int(np.argmin(errs))
    if not np.isfinite(errs[best]) or not errs[best] < SWEEP_GAIN * errs[0]:
        return None
    return float(sweep[best])


def _free_misfit(fit, slant: float, tilt: float) -> float:
    """The misfit `fit` gives the light, or infinity where its fitted albedo sits at the
    search's bound (``fit.at_bound``: there the misfit does not fix the light)."""
    misfit, albedo = fit(slant, tilt)
    return misfit if albedo < fit.at_bound else np.inf


def _search_light(coarse, final, reduction_lossy: bool, slant: float, tilt: float,
                  beat: float | None = None) -> tuple[float, float, _LightFit | None]:
    """One search of :func:`_refine_light` from the statistical `slant` and `tilt`, with the
    misfit functions `coarse` (reduced image) and `final`; `reduction_lossy`: the reduced image
    lost more than ``MAX_REDUCTION_LOSS`` of the variance. Returns the first knee's slant, the
    reduced image's misfit at the end of its stage, and the search's :class:`_LightFit`;
    that is None if `beat` is given and the reduced image's misfit is not below it (the
    final stage is then skipped)."""
    stat_slant = float(slant)

    def misfits(e_fn, lights, top=np.inf):
        # e_fn at each (slant, tilt), the uncached ones solved at once (fit.prefetch); `top`:
        # the highest slant e_fn solves for (above it, it returns inf unsolved)
        fit.prefetch([(a, b) for a, b in lights if a <= top])
        return [e_fn(a, b) for a, b in lights]

    def polish_tilt(e_of, s, t, step, stop):
        while step >= stop:
            cands = [t - step, t, t + step]
            errs = misfits(e_of, [(s, c) for c in cands])
            if not np.isfinite(min(errs)):
                break  # no misfit to follow (the walk would never stop)
            t_new = cands[int(np.argmin(errs))]
            if t_new == t:
                step /= 2
            t = t_new
        return t

    def best(e_of, slants, t):
        errs = misfits(e_of, [(g, t) for g in slants])
        return float(slants[int(np.argmin(errs))]), np.asarray(errs)

    # Coarse: the misfit drops steeply up to the true slant, then stays low (a plateau that
    # rises slowly) until the albedo bound bites; on the reduced image the plateau can dip
    # below the true slant's misfit, so take the knee: the lowest slant whose misfit is within
    # KNEE_FACTOR of the minimum.
    fit = coarse
    e_of = lambda s_, t_: fit(s_, t_)[0]  # noqa: E731
    grid = np.arange(5.0, 80.0 + 1e-9, 5.0)
    errs = np.asarray(misfits(e_of, [(g, tilt) for g in grid]))
    s = knee = float(grid[errs <= KNEE_FACTOR * errs.min()][0])
    t = polish_tilt(e_of, s, float(tilt), 8.0, 1.0)
    s, _ = best(e_of, np.arange(max(MIN_SLANT_DEG, s - 3.0), min(85.0, s + 6.0) + 1e-9, 1.0), t)
    coarse_misfit = e_of(s, t)
    if beat is not None and not coarse_misfit < beat:
        return knee, coarse_misfit, None
    # Final: the sharp minimum on a larger image (the reduced image blurs it; 1° of slant can
    # cost several points of height error). Images with much detail below the reduced
    # pixel (fractal surfaces) are not the shading of any surface once averaged: their
    # reduced misfit has its knee at too high a slant (Brownian H = 0.7, 256 px, slant 15°:
    # 40° at 96 px, 15° at full resolution). For them the final image is larger and the
    # slant grid is scanned again on it.
    # Final image: the largest affordable. Block-averaging to the smallest image that keeps
    # 95 % of the variance (128 px for most 256 px tiles) misled the search: the misfits that
    # pick the light are far below that 5 % (measured at slants 15-60° on the bench's 256 px
    # tiles: sphere cap worst gap to the given light +0.031 -> +0.006, plain weave
    # +0.018 -> +0.008, a 32 px oblique lattice at 30° 0.294 -> 0.204; 1-1.5 s more).
    fit = final
    e_of = lambda s_, t_: fit(s_, t_)[0]  # noqa: E731
    if reduction_lossy:
        # Averaging biases the slant upwards (it darkens rough shading): scan up to just above
        # the coarse estimate.
        low = grid[grid <= s + 5.0]
        errs = np.asarray(misfits(e_of, [(g, t) for g in low]))
        s = float(low[errs <= KNEE_FACTOR * errs.min()][0])
    # The misfit is narrow in tilt (a few degrees) and the reduced image can settle on a side
    # lobe: scan the tilt around the estimate (measured on a painted plain-weave window lit at
    # 45°: the coarse stage stopped 13° off, with 3.5 times the misfit of the true tilt's).
    tilts = t + np.arange(-TILT_SCAN_DEG, TILT_SCAN_DEG + 1e-9, TILT_SCAN_STEP_DEG)
    t = float(tilts[int(np.argmin(misfits(e_of, [(s, c) for c in tilts])))])
    # Slant and tilt are coupled: a compass search over both (8 neighbours), halving steps
    # (from 2°: starting at 1° left the plain weave at 30° stuck 2° and 4° off).
    def compass(e_fn, s, t, top=np.inf):
        step = 2.0
        while step >= 0.5:
            cands = [(s + i * step, t + j * step) for i in (-1, 0, 1) for j in (-1, 0, 1)]
            cands = [(a, b) for a, b in cands if MIN_SLANT_DEG <= a <= 85.0]
            errs = misfits(e_fn, cands, top)
            if not np.isfinite(min(errs)):
                break  # as in polish_tilt
            s_new, t_new = cands[int(np.argmin(errs))]
            if (s_new, t_new) == (s, t):
                step /= 2
            s, t = s_new, t_new
        return s, t

    s, t = compass(e_of, s, t)
    bound = fit.at_bound  # a fitted albedo this high is at the bound
    plateau = None
    if fit(s, t)[1] >= bound and stat_slant < s <= PLATEAU_MAX_DEG:
        # On the plateau of steep lights with the albedo at its bound, where the misfit does
        # not fix the slant. Below it the true light's well is deep and narrow (lattice
        # reliefs lit at 15°: misfit 1e-3 against 4e-2 10° of tilt away), but the search's
        # tilt may be far from it (the statistical tilt is up to 36° off on lattices). So,
        # among lights whose albedo is free and no steeper than the image statistics' slant
        # + 5° (the plateau's edge fits better still): scan the tilt over 180° at that slant
        # (the misfit repeats with the height negated), then the slant, then the compass
        # search. A light whose misfit is at most WELL_DEPTH times the best at the statistics'
        # slant (a well) is taken; else that slant, with the search's tilt.
        plateau = (s, t)
        top_slant = stat_slant + 5.0

        def free(a, b):
            return _free_misfit(fit, a, b) if a <= top_slant else np.inf

        tilts = t + np.arange(0.0, 180.0, TILT_SCAN_STEP_DEG)
        errs = misfits(free, [(stat_slant, c) for c in tilts], top_slant)
        e_stat = float(min(errs))
        s = stat_slant
        if np.isfinite(e_stat):
            t_low = float(tilts[int(np.argmin(errs))])
            slants = np.arange(MIN_SLANT_DEG, top_slant + 1e-9, 1.0)
            errs_s = misfits(free, [(c, t_low) for c in slants], top_slant)
            s_w, t_w = compass(free, float(slants[int(np.argmin(errs_s))]), t_low, top_slant)
            if free(s_w, t_w) <= WELL_DEPTH * e_stat:
                s, t = s_w, t_w
    # Uncertainty: the change that doubles the misfit (parabola through ±1°), at least 1°
    # (slant; in quadrature with the albedo bound's possible bias) and 0.5° (tilt).
    e0, e_s_minus, e_s_plus, e_t_minus, e_t_plus = misfits(
        e_of, [(s, t), (s - 1, t), (s + 1, t), (s, t - 1), (s, t + 1)])

    def half_width(e_minus, e_plus):
        curv = 0.5 * (e_minus + e_plus - 2.0 * e0)
        return float(np.sqrt(e0 / curv)) if curv > 0 and e0 > 0 else 90.0

    slant_sd = float(np.hypot(max(half_width(e_s_minus, e_s_plus), 1.0), CAP_BIAS_DEG))
    tilt_sd = max(half_width(e_t_minus, e_t_plus), 0.5)
    albedo = fit(s, t)[1]
    at_bound = albedo >= bound
    if plateau is not None:
        # The plateau fits as well: the ± spans it. Still flagged.
        at_bound = True
        slant_sd = max(slant_sd, plateau[0] - s)
        tilt_sd = max(tilt_sd, tilt_axis_difference_deg(plateau[1], t))
    return knee, coarse_misfit, _LightFit(s, t % 360.0, min(slant_sd, 90.0), min(tilt_sd, 90.0), albedo, bool(at_bound))


# --------------------------------------------------------------------------------------------
# The driver


def _censored_pixels(img: np.ndarray, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """Attached shadows and over-exposed shading, as float32 weights of one-sided bounds.

    A black (``<= DARK``) region is an attached shadow, where the surface faces away from the
    light, only if a terminator bounds it: the shading falls to zero continuously, so the lit
    pixels around it are dim (median at most ``TERMINATOR_FRACTION`` of the brightest). Stains
    and cast shadows have sharp edges and stay plain missing data. Likewise a saturated
    (``>= SATURATED``) region counts as over-exposed shading only if the shading rises to it
    continuously (the pixels around it at least ``OVEREXPOSED_RING``), not a specular highlight.
    """
    finite = np.isfinite(img)
    with np.errstate(invalid="ignore"):
        dark = finite & (img <= DARK)
        bright = finite & (img >= SATURATED)
    if mask is not None:
        m = np.asarray(mask, bool)
        dark &= m
        bright &= m
    lit = valid_pixels(img, mask)
    top = float(np.percentile(img[lit], 99.9)) if lit.any() else 1.0

    def bounded(region, keep):
        if not region.any():
            return region
        labels, n = ndimage.label(region, structure=np.ones((3, 3)))
        ring = lit & ~region & ndimage.binary_dilation(region, structure=np.ones((3, 3)))
        ring_labels = np.where(ring, ndimage.maximum_filter(labels, size=3), 0)
        index = np.arange(1, n + 1)
        med = np.asarray(ndimage.median(img, ring_labels, index), dtype=float)
        ok = np.zeros(n + 1, bool)
        ok[1:] = np.isfinite(med) & keep(med)
        return ok[labels]

    dark = bounded(dark, lambda med: med <= TERMINATOR_FRACTION * top)
    bright = bounded(bright, lambda med: med >= OVEREXPOSED_RING)
    return dark.astype(np.float32), bright.astype(np.float32)


def _embed(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`a` in the top-left corner of a zero array of `shape`."""
    out = np.zeros(shape, a.dtype)
    out[: a.shape[0], : a.shape[1]] = a
    return out


def _solve_domain(img: np.ndarray, valid: np.ndarray, censored, periodic: bool,
                  light: Light | None = None, albedo: float = 0.0):
    """The periodic domain the variational solver works on.

    A tile is its own domain. A plain image is embedded in a larger periodic domain whose
    margin carries no data (its edges are free), with the flat-on-average prior, tightened
    where the image's waves along `light` (with `albedo`) show no long-wave power
    (:mod:`haptex_compile.shading_prior`). `censored` is :func:`_censored_pixels` of the image.
    With `light` and no saturated pixel, the albedo is bounded above (``ALBEDO_SLACK``).

    Returns
    -------
    (image, weight, kwargs)
        Domain image (invalid pixels set to the mean), boolean data weights, and the keyword
        arguments of :func:`~haptex_compile.shading_variational.solve_variational` that
        describe the domain (data region, prior, censored pixels, albedo bound).
    """
    rows, cols = img.shape
    dark, bright = censored
    fill = float(np.mean(img[valid]))
    kwargs: dict = {}
    if periodic:
        dom_img, dom_w = img, valid
    else:
        pad = max(8, int(PLAIN_MARGIN * max(rows, cols)))
        # Sizes that halve to fast FFT sizes (factors 2, 3 and 5 only) down to about
        # FAST_HALF_PX: 1024 px would get 1125, which halves to 562 = 2 x 281 (a prime) and
        # that level's steps took 3 x as long. Smaller levels cost little either way, and
        # a wider margin than needed loosens the solve (a 128 px sphere cap: 0.025 -> 0.109;
        # bench_shading's plain images with PLAIN_MARGIN 0.15: sphere caps 0.01-0.08 ->
        # 0.02-0.14, crops of the plain weave 0.09-0.28 -> 0.06-0.18; the thin plate's weight
        # in the margin at 0.1 x: sphere caps up to 0.28). The margin's thin plate joins
        # opposite edges, which holds a scene's level ground and bends a texture's edges;
        # the final data misfit picks the better margin in 21 of 24 cases, at twice the time.
        shape = []
        for n in (rows + pad, cols + pad):
            unit = 2 ** max(0, int(np.log2(n / FAST_HALF_PX)))
            shape.append(unit * sfft.next_fast_len(-(-n // unit), real=True))
        shape = tuple(shape)
        dom_img = _embed(img, shape)
        dom_w = _embed(valid, shape)
        dark, bright = (_embed(a, shape) for a in (dark, bright))
        # Not the finest level: its few steps leave textures' ratios at up to 9 (bumps, 128 px).
        check_level = max(1, int(np.ceil(np.log2(max(rows, cols) / LOWFREQ_CHECK_SIDE))))
        kwargs.update(
            data_shape=(rows, cols), lowfreq_weight=LOWFREQ_WEIGHT, lowfreq_cycles=LOWFREQ_CYCLES,
            lowfreq_check_level=check_level, lowfreq_reject_ratio=LOWFREQ_REJECT_RATIO,
            lowfreq_reject_albedo=LOWFREQ_REJECT_ALBEDO,
            lowfreq_plane_weight=LOWFREQ_PLANE_WEIGHT, lowfreq_plane_coarse=COARSE_PLANE_FACTOR,
            lowfreq_plane_coarse_level=COARSE_PLANE_LEVEL,
            lowfreq_fine_factor=min(1.0, max(rows, cols) / PLAIN_FINE_PRIOR_PX) ** 2,
        )
        if light is not None and light.slant_deg >= MIN_SLANT_DEG:
            power = along_light_power(np.where(valid, img, fill), light.vector, albedo,
                                      max_cycles=SPECTRAL_PRIOR_CYCLES)
            if power is not None:
                kwargs.update(lowfreq_power=power, lowfreq_power_weight=SPECTRAL_PRIOR_WEIGHT)
    if CENSORED:
        kwargs.update(dark=dark, bright=bright)
    if light is not None and valid.any() and not np.any(img[np.isfinite(img)] >= SATURATED):
        top = float(np.percentile(img[valid], 99.9))
        kwargs.update(albedo_max=ALBEDO_SLACK * top / float(light.vector[2]))
    return np.where(dom_w, dom_img, fill), dom_w, kwargs


def _brightness_start(
    img: np.ndarray, valid: np.ndarray, albedo: float, cos_s: float
) -> np.ndarray:
    """Starting height for near-overhead light: bright = high (convex surfaces), with the slope
    magnitude that the intensities imply (``|g|² = (albedo cos s / I)² - 1``); pixel units."""
    fill = np.where(valid, img, np.mean(img[valid]) if valid.any() else 0.5)
    z = ndimage.gaussian_filter(fill, 2.0, mode="wrap")
    z -= z.mean()
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = (albedo * cos_s / np.maximum(img, 1e-3)) ** 2 - 1.0
    target = float(np.sqrt(np.mean(np.clip(g2[valid], 0.0, 4.0)))) if valid.any() else 0.0
    gy, gx = np.gradient(z)
    cur = float(np.sqrt(np.mean(gx * gx + gy * gy)))
    return z * (target / cur) if cur > 0 else z


def shape_from_shading(
    image,
    *,
    pixel_size_um: float,
    light: Light | None = None,
    method: str = "default",
    periodic: bool = False,
    mask=None,
    weave_basis_px=None,
) -> SfsResult:
    """Relative heights from one Lambertian image.

    Parameters
    ----------
    image : ndarray
        Grey image (integers are scaled by their maximum; floats should be in [0, 1]).
    pixel_size_um : float
        Pixel size in µm.
    light : Light, optional
        The light; estimated with :func:`estimate_light` when omitted.
    method : str
        ``"default"``: Gauss-Newton on the exact Lambertian energy with a small thin-plate
        term, coarse to fine, FFT-preconditioned conjugate gradients, albedo fitted by least
        squares and bounded below by the brightest pixels (see
        :mod:`haptex_compile.shading_variational`; settings ``DEFAULT_SOLVER``, for plain
        images with ``PLAIN_SOLVER``'s);
        ``"accurate"``: the same with more iterations on every level
        (``ACCURATE_SOLVER``), about 3 x slower (measured on the bench surfaces, light
        given, slants 15-60°: worst normalised height error of random bumps 0.02 instead of
        0.08, of the sphere cap at 15-45° 0.002 instead of 0.006, the others about the same;
        see ``bench/bench_shading.py``); ``"tsai-shah"``: :func:`tsai_shah`, for
        comparison. Light straight above (slant < 5°) makes the slopes' signs unobservable:
        the default then starts from a bright-is-high guess (warned, method suffixed).
    periodic : bool
        The image is a tile: the height wraps seamlessly (all operators are periodic).
        Otherwise the image is embedded in a larger periodic domain whose margin carries no
        data, so its edges are free, and a weak prior that the fabric lies flat on average
        (no slope across the light at wavelengths longer than the image) removes the ramps
        that shading cannot see; it is tightened on the longest waves across the light where
        the image's waves along the light show little power (a weave: see
        :mod:`haptex_compile.shading_prior`). Periodic tiles are much better posed: a strip
        along the light closes on itself, so its height offset is fixed (measured on 256 px
        random bumps at 45°: 0.07 periodic, 0.24 as a plain image). On a plain image those
        offsets are left to the thin plate and the prior, and the energy's own minimum is off:
        random bumps at 60°, 10 seeds, the minimum nearest the true surface has normalised
        errors 0.25-0.32 (the default 0.23-0.36; ``bench/bench_shading.py``).
    mask : ndarray of bool, optional
        Pixels to use; saturated (>= 0.99), black (<= 0.01) and non-finite pixels are always
        excluded and filled by the smoothness term.
    weave_basis_px : array_like, optional
        The lattice of the image's relief (columns t1, t2 in pixels, a reduced basis), when
        known (a weave photo's tile or image). Light nearly along one of its weave directions
        (:func:`weave_visibility` below ``WEAVE_VISIBILITY_MIN``) is warned of and, on a
        periodic tile, solved from more starts (see :func:`_start_from_cell`). Without it,
        light along a tile's axes and diagonals is (see :func:`_bare_tile_starts`); with it,
        only when the light is also near a weave direction (a weave's window is cut to repeat
        the lattice, and its own axes mean nothing).

    Returns
    -------
    SfsResult
        Heights in µm as implied by the light and albedo (mean 0), the light and albedo used,
        the method and warnings.
    """
    from haptex_compile.shading_variational import solve_variational

    if not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise ValueError(f"pixel_size_um must be finite and positive, got {pixel_size_um!r}")
    if method not in METHODS:
        raise ValueError(f"unknown shape-from-shading method {method!r} (use one of {METHODS})")
    img, warnings = _as_image(image)
    valid = valid_pixels(img, mask)
    n_bad = int(img.size - valid.sum())
    if n_bad:
        warnings.append(
            f"{n_bad} saturated, black, non-finite or masked pixels carry no slope information:"
            " attached shadows and over-exposed shading enter as bounds, the rest is filled by"
            " smoothness"
        )
    flat = np.zeros(img.shape)
    if valid.sum() < max(16, 0.01 * img.size) or float(np.std(img[valid])) < 1e-4:
        warnings.append("image has no usable shading (flat or almost all masked): height is flat")
        used = light if light is not None else Light(0.0, 0.0, 90.0, 180.0)
        top = float(np.max(img[valid])) if valid.any() else 1.0
        return SfsResult(flat, used, top, method, tuple(warnings))
    censored = _censored_pixels(img, mask)
    if light is None:
        light, albedo = _estimate_light(img, valid, mask, True, censored, periodic=periodic)
        warnings.append(estimated_light_note(light, periodic))
    else:
        albedo = _moment_albedo(img[valid], light.slant_deg)

    if method == "tsai-shah":
        if light.slant_deg < MIN_SLANT_DEG:
            warnings.append(
                "light along the view axis: Tsai-Shah's df/dZ vanishes at the flat start and the"
                " height stays flat"
            )
        h = tsai_shah(_finite_or_zero(img), light, pixel_size_um=pixel_size_um)
        return SfsResult(h, light, 1.0, method, tuple(warnings))

    used_method = method
    z0 = None
    if light.slant_deg < MIN_SLANT_DEG:
        # Only |slope| is observable (an eikonal problem without sign): start from a convex
        # guess so that Gauss-Newton has a non-zero Jacobian.
        cos_s = np.cos(np.deg2rad(light.slant_deg))
        albedo = max(float(np.percentile(img[valid], 99.5)) / cos_s, 1e-3)
        warnings.append(
            f"light along the view axis (slant {light.slant_deg:.1f}° < {MIN_SLANT_DEG}°): the"
            " slopes' signs are not observable; fell back to a bright-is-high start (convex"
            " surfaces)"
        )
        used_method = f"{method}+brightness-start"
    along_weave = None
    if weave_basis_px is not None and light.slant_deg >= MIN_SLANT_DEG:
        visibility, weave_tilt = weave_visibility(light, weave_basis_px)
        if visibility < WEAVE_VISIBILITY_MIN:
            # The more starts run on a tile only (a small periodic window of its lattice).
            along_weave = (visibility, weave_tilt) if periodic else None
            if np.sin(np.deg2rad(light.slant_deg)) < WEAVE_VISIBILITY_MIN:
                # Every direction is below the threshold: the cause is the slant, not the tilt.
                where = (f"light (slant {light.slant_deg:.1f}°, tilt {light.tilt_deg:.1f}°) nearly overhead:"
                         f" sin(slant) x sin(angle to any weave direction) is below {WEAVE_VISIBILITY_MIN:g}"
                         f" (at the direction at tilt {round(weave_tilt, 1) % 180.0:.1f}°: {visibility:.3f})")
            else:
                where = (f"light (slant {light.slant_deg:.1f}°, tilt {light.tilt_deg:.1f}°) nearly along the weave"
                         f" direction at tilt {round(weave_tilt, 1) % 180.0:.1f}°: sin(slant) x sin(angle between"
                         f" them) = {visibility:.3f} < {WEAVE_VISIBILITY_MIN:g}")
            if periodic:
                remedy = ("solved from 2-3 more starts at full resolution (on a small"
                          " periodic window of the lattice, the best polished on the tile), the lowest energy kept, and"
                          " they may still come back wrong (bench: of 54 such lights on plain weaves and"
                          " smooth cells, 7 gave height errors above 0.1, up to 0.74, against 25 from the pyramid alone)")
            else:
                remedy = ("the image is not a periodic tile, so it is solved from the pyramid alone, and they may"
                          " come back wrong (bench/bench_photo.py's coarse plain weave lit 7° off t1 - t2 at slant 30°:"
                          " height error 0.23, against 0.01-0.05 for its other lights)")
            warnings.append(
                f"{where}, so the profiles across that direction (the yarns' cross-sections) barely shade;"
                f" {remedy}; light the fabric so that this product is at least"
                f" {WEAVE_VISIBILITY_MIN:g} for every weave direction (e.g. slant 45°, 15-30° off the yarns)"
            )
    # A weave's window: its axes and diagonals matter only where they run along a weave
    # direction (warned above; the held starts still run); elsewhere the waves across them are
    # not the weave's (bench/bench_photo.py's plain weave lit 30° off t1, along the 975 x 787 px
    # window's diagonal: the same height error, 7.0 s -> 1.6 s).
    aligned = None
    if periodic and (weave_basis_px is None or along_weave is not None):
        aligned = _tile_aligned_tilt(light.tilt_deg, img.shape)
    if weave_basis_px is None and aligned is not None and light.slant_deg >= MIN_SLANT_DEG:
        warnings.append(
            f"light tilt {light.tilt_deg:.1f}° within {ALIGNED_TILT_DEG:g}° of the periodic"
            f" tile's {aligned[0]} ({aligned[1]:.1f}°): the tile-sized waves across the light have"
            " no slope along it and the shading barely fixes them (solved from 2 starts of the"
            " pyramid and 1 at full resolution, the lowest energy kept); the heights may be far"
            " off (bench: normalised errors up to 0.47, a sphere cap along the diagonal at 60°);"
            f" light the fabric at least {ALIGNED_TILT_DEG:g}° away from its weave's axes and"
            " diagonals"
        )
    if light.slant_deg >= GRAZING_DEG:
        warnings.append(
            f"grazing light (slant {light.slant_deg:.1f}° >= {GRAZING_DEG:g}°): shadowed pixels"
            " carry no information and cast shadows are not modelled; expect large errors"
        )
    rows, cols = img.shape
    dom_img, dom_w, domain_kwargs = _solve_domain(img, valid, censored, periodic, light, albedo)
    if z0 is None and light.slant_deg < MIN_SLANT_DEG:
        z0 = _brightness_start(dom_img, dom_w, albedo, np.cos(np.deg2rad(light.slant_deg)))
    kwargs = {}
    if z0 is not None:
        # Do not coarsen the start away (from a flat height, overhead light has no Jacobian),
        # and take few steps: the problem has no unique answer, the start is the prior.
        kwargs.update(min_size=24, coarse_gn=6, mid_gn=3, fine_gn=2, coarse_cg=30, fine_cg=10)
    if method == "accurate":
        kwargs.update(ACCURATE_SOLVER)
    elif z0 is None:
        kwargs.update(DEFAULT_SOLVER if periodic else {**DEFAULT_SOLVER, **PLAIN_SOLVER})
    if z0 is None and light.slant_deg <= LOW_SLANT_MAX_DEG:
        kwargs.update(smooth_lam_growth=LOW_SLANT_LAM_GROWTH)
        if method != "accurate":
            kwargs.update(mid_cg=LOW_SLANT_MID_CG)
    kwargs.update(domain_kwargs)
    albedo_start = albedo
    weight = dom_w.astype(np.float32)
    z, albedo = solve_variational(dom_img, weight, light.vector, albedo, z0=z0, **kwargs)
    if (aligned is not None or along_weave is not None) and z0 is None:
        starts = [(z, albedo)]
        if along_weave is None:
            # A bare tile (no lattice given) lit along its axis or diagonal.
            starts += _bare_tile_starts(dom_img, weight, light, albedo_start, kwargs, domain_kwargs)
        else:
            if aligned is not None:
                starts += _held_starts(dom_img, weight, light, albedo_start, kwargs)
            # The raw intensities (shadows and highlights included; unknown pixels NaN) for
            # the small window's tile: the domain image has its invalid pixels filled.
            known = np.isfinite(img) if mask is None else np.isfinite(img) & np.asarray(mask, bool)
            from_cell = _start_from_cell(dom_img, weight, light, albedo_start, domain_kwargs,
                                         weave_basis_px, np.where(known, img, np.nan))
            starts += from_cell or _fine_starts(dom_img, weight, light, albedo_start, domain_kwargs)
        z, albedo = _lowest_energy(dom_img, weight, light, domain_kwargs, starts, weave_basis_px)
    z = z[:rows, :cols].astype(np.float64)
    gy, gx = np.gradient(z)
    if not np.all(np.isfinite(z)) or float(np.max(np.hypot(gx, gy))) > 50.0:
        warnings.append(
            "the solver ran away (non-finite or slopes > 50); fell back to a flat height"
        )
        z = np.zeros_like(z)
        used_method = f"{used_method}+flat-fallback"
    height = (z - z.mean()) * pixel_size_um
    return SfsResult(height, light, float(albedo), used_method, tuple(warnings))


# Light nearly along a weave direction and along its window's axis or diagonal: the solve is
# repeated with the waves that have no slope along the light held on the coarse levels (from
# these pyramid levels on), and the result of lowest energy is kept (see _held_starts).
HELD_START_LEVELS = (2, 1)
# A tile with no lattice given holds them from this level only (see _bare_tile_starts).
BARE_TILE_HELD_LEVEL = 2


def _lowest_energy(img, weight, light: Light, domain_kwargs: dict, starts: list, basis_px=None):
    """Of the solves `starts`, (z, albedo) pairs on the domain, the one of lowest energy (the
    same energy for all: the finest level's; the first of equals).

    With `basis_px` (a weave's lattice, on which the domain is periodic), when a solve does
    not repeat cell by cell (its RMS departure from its cell average above
    ``CELL_REPEAT_MAX`` of its RMS), the solves are scored by the energies of their cell
    averages (:func:`_cell_average`), painted back over the domain: the heights a weave's
    surface keeps (``photo.photo_surface`` averages them over the lattice). On the real
    photos in ``../shared/fabrics`` lit near a weave direction or overhead (as estimated) the
    solves depart by 32-100 % and their averages' energies are 3-34 x their own, in another
    order. Solves that repeat (the bench's synthetic weaves: 1-5 %) keep their own energies:
    the average's interpolation doubles them there, and ranked by it the bench's
    weave-direction table lost (plain weave on the oblique lattice at 45°, 8° off t1: 0.081
    -> 0.147).
    """
    from haptex_compile.shading_variational import energy

    censored = {k: domain_kwargs[k] for k in ("dark", "bright") if k in domain_kwargs}
    finite = [bool(np.all(np.isfinite(z))) for z, _ in starts]  # a non-finite solve comes last
    scored = [z for z, _ in starts]
    if basis_px is not None:
        averages = [_cell_average(z, basis_px).synthetic if ok else z for (z, _), ok in zip(starts, finite)]
        if any(ok and np.std(z - a) > CELL_REPEAT_MAX * np.std(z) for z, a, ok in zip(scored, averages, finite)):
            scored = averages
    energies = [energy(img, weight, light.vector, a, z, **censored) if ok else np.inf
                for z, (_, a), ok in zip(scored, starts, finite)]
    return starts[int(np.argmin(np.nan_to_num(energies, nan=np.inf)))]


def _cell_average(z: np.ndarray, basis_px):
    """The mean of periodic `z` over the cells of its lattice (columns t1, t2 in pixels; `z` is
    periodic on it): a ``tiles.TileAverage`` whose ``synthetic`` is painted over `z`'s shape."""
    from haptex_compile.lattice import Lattice
    from haptex_compile.tiles import average_tile

    b = np.asarray(basis_px, dtype=float)
    return average_tile(z, Lattice(True, b[:, 0], b[:, 1], 1.0, "the domain's lattice"),
                        combine="mean", samples_per_px=2.0, flatten_sigma_px=None)


def _held_starts(img, weight, light: Light, albedo0: float, kwargs: dict) -> list:
    """The solves (z, albedo) holding the waves with no slope along the light from each of
    ``HELD_START_LEVELS`` on (`kwargs`: the main solve's settings).

    A coarse level's averaged image sets those waves wrong, and the finest level cannot undo
    them. Measured at 256 px, light given along the axes and diagonals, slants 30-60°: plain
    weave at worst 0.885 -> 0.063, random bumps 0.758 -> 0.311 (60°, along y), 0.233 -> 0.096
    (30°, along x); the sphere cap along the diagonal at 60° stays at 0.470 (no start finds
    its minimum), Brownian surfaces within 0.02 except one at 0.053 -> 0.076.
    """
    return _side_by_side(*(functools.partial(_held_start, img, weight, light, albedo0, kwargs, level)
                           for level in HELD_START_LEVELS))


def _held_start(img, weight, light: Light, albedo0: float, kwargs: dict, level: int):
    """The pyramid solve (z, albedo) with `kwargs` (the main solve's settings), holding the
    waves with no slope along the light from pyramid level `level` on."""
    from haptex_compile.shading_variational import solve_variational

    return solve_variational(img, weight, light.vector, albedo0, hold_from_level=level, **kwargs)


def _side_by_side(*calls) -> list:
    """The results of the independent zero-argument `calls`, in order, run side by side in
    forked workers (``SEARCH_PROCESSES``; the same results in one process)."""
    with forked_map(lambda k: calls[k](), SEARCH_PROCESSES) as map_:
        return map_([(k,) for k in range(len(calls))])


# Full-resolution starts for light along a tile's axis or diagonal or nearly along a weave
# direction (see _fine_starts): Gauss-Newton steps and CG iterations of each solve,
# the relative gain at which it stops, and the thin-plate weights of the continuation start.
FINE_START_GN = 30
FINE_START_CG = 20
FINE_START_RTOL = 1e-5
FINE_START_LAMS = (1e-3, 1e-4)


def _fine_starts(img, weight, light: Light, albedo0: float, domain_kwargs: dict) -> list:
    """Two or three solves (z, albedo) at full resolution only, from flat starts; the caller
    keeps the one of lowest energy (:func:`_lowest_energy`).

    A coarse level of a lattice relief lit nearly along a weave direction under-resolves the
    yarns, and its averaged image sets their cross-sections (the waves the light barely sees)
    wrong; the finer levels keep that. From a flat start at full resolution the shading's
    coupling with the well-seen waves sets them (plain weave, 16 px cells, lit 3° off its
    yarns at 45°: 0.649 from the pyramid, 0.024 from the flat start, which is the truth's
    energy). The starts: flat (``FINE_START_GN`` steps); that result with the waves that have
    no slope at all along the light (light along the domain's axes or diagonals) negated,
    since the shading sees them only at second order, where a ridge and a groove look alike;
    and flat with the thin-plate weight stepped down through ``FINE_START_LAMS`` (smooth
    shapes first). Measured (plain weaves and smooth cells in 208 px periodic windows of a
    square and an oblique lattice, slants 30-60°, 0-12° off a weave direction, light given):
    summed height errors 8.6 -> 3.1 and 9.6 -> 5.9; at 1° off, where no start finds the
    truth's basin, the energy can pick worse (0.475 -> 0.990 once). On bench/bench_photo.py's
    photos (54 lights below ``WEAVE_VISIBILITY_MIN``): errors above 0.1 in 25 cases -> 7.
    Bench tiles lit along their axes and diagonals (slants 30-60°): summed 3.58 -> 1.74,
    random bumps along the axes at 60° 0.474 -> 0.123 and 0.524 -> 0.075; none worse by more
    than 0.03. Cost: up to 2 x ``FINE_START_GN`` steps at full resolution (3 x when the light
    runs along the domain's axes or diagonals): on a plain weave tile of 1024 px lit 3° off
    its yarns, 12-13 s instead of 0.6 s. A weave's tile runs them on a small window of its
    lattice instead (:func:`_start_from_cell`). The two chains (flat, then its unseen waves
    negated; the continuation) run side by side in worker processes, as do
    :func:`_held_starts`' two solves (``SEARCH_PROCESSES``; the same heights): measured on 2
    cores, bench tiles of 256 px lit along their axes and diagonals (three surfaces, three
    lights, and a lattice along a weave direction) 12.5 -> 8.7 s in all, random bumps of
    512 px and 1024 px lit along x 5.7 -> 4.1 s and 17.1 -> 15.8 s. A tile with no lattice
    given now runs the continuation only (:func:`_bare_tile_starts`).
    """
    def flat_and_negated():
        zf, af = _full_resolution_solve(img, weight, light, albedo0, domain_kwargs)
        invisible = _unseen_waves(zf, light)
        return [(zf, af)] + ([] if invisible is None else
                             [_full_resolution_solve(img, weight, light, af, domain_kwargs, zf - 2.0 * invisible)])

    # The two chains are independent: side by side.
    first, second = _side_by_side(flat_and_negated,
                                  lambda: [_continuation_start(img, weight, light, albedo0, domain_kwargs)])
    return first + second


def _full_resolution_solve(img, weight, light: Light, albedo0: float, domain_kwargs: dict, z_start=None,
                           steps: int = FINE_START_GN, **thin_plate):
    """One solve of the full-resolution starts (see :func:`_fine_starts`): `steps`
    Gauss-Newton steps on the domain only, from `z_start` (flat by default)."""
    from haptex_compile.shading_variational import solve_variational

    return solve_variational(img, weight, light.vector, albedo0, z0=z_start, max_levels=1, fine_gn=steps,
                             fine_cg=FINE_START_CG, gn_rtol=FINE_START_RTOL, **thin_plate, **domain_kwargs)


def _continuation_start(img, weight, light: Light, albedo0: float, domain_kwargs: dict):
    """The continuation of :func:`_fine_starts`: from flat at full resolution, with the thin
    plate's weight stepped down through ``FINE_START_LAMS`` (smooth shapes first); (z, albedo)."""
    zc, ac = None, albedo0
    for lam in FINE_START_LAMS:
        zc, ac = _full_resolution_solve(img, weight, light, ac, domain_kwargs, zc,
                                        FINE_START_GN // len(FINE_START_LAMS), lam=lam)
    return zc, ac


def _bare_tile_starts(img, weight, light: Light, albedo0: float, kwargs: dict, domain_kwargs: dict) -> list:
    """The starts of a tile with no lattice given, lit along its axis or diagonal: the pyramid
    with the waves that have no slope along the light held from level ``BARE_TILE_HELD_LEVEL``
    on (`kwargs`: the main solve's settings), and the continuation at full resolution
    (:func:`_continuation_start`), side by side; the caller keeps the lowest energy.

    Of the starts a weave's tile runs (:func:`_held_starts`, :func:`_fine_starts`), these
    two are the ones that were kept: measured at 256, 512 and 1024 px (the bench's four
    surfaces and random bumps of seeds 5 and 9, only 5 at 1024 px; slants 30°, 45° and 60°, light
    along x and along the diagonal: 36, 36 and 30 cases), the lowest energy was the
    continuation's in 24, 22 and 12 cases, the plain pyramid's in 7, 10 and 11, the start held
    from level 2 in 3, 4 and 6, and the flat start or its negation in 2, 0 and 1 (the plain
    weave along the diagonal at 45° and 60° at 256 px, the bumps of seed 5 along x at 60° at
    1024 px, where the continuation came within 0.1 % of their energy, with height errors
    0.005 -> 0.006, 0.009 -> 0.009 and 0.068 -> 0.062); the start held from level 1, in none.
    Measured without the other three on the bench's four surfaces (24 lights along x and the
    diagonal at 256 px, 12 at 512 and 1024 px): the same errors (to 0.001) but for the plain
    weave along the diagonal at 45° (256 px: 0.005 -> 0.006), and a solve takes 0.47 s
    instead of 0.94 s at 256 px, 1.8 s instead of 4.0 s at 512 px and 6.1 s instead of 15.9 s
    at 1024 px (means, one run each).
    """
    return _side_by_side(lambda: _held_start(img, weight, light, albedo0, kwargs, BARE_TILE_HELD_LEVEL),
                         lambda: _continuation_start(img, weight, light, albedo0, domain_kwargs))


# The full-resolution starts of a weave's tile run on a small periodic window of its lattice
# (tiles.small_periodic_window, as for the light search), and the best is averaged over the
# cell, painted over the domain and polished there with FINE_POLISH_GN steps (see
# _start_from_cell). A solve departing from its cell average by more than CELL_REPEAT_MAX of
# its RMS does not repeat cell by cell (see _lowest_energy).
FINE_POLISH_GN = 3
CELL_REPEAT_MAX = 0.2


def _start_from_cell(img, weight, light: Light, albedo0: float, domain_kwargs: dict,
                     basis_px, raw: np.ndarray) -> list | None:
    """:func:`_fine_starts` for a domain that repeats a weave's lattice (`basis_px`, columns
    t1, t2 in pixels; the domain is exactly periodic on it), run on a small periodic window of
    the lattice's averaged tile (a weave's solution repeats in every cell): the one of lowest
    energy there is averaged over the cell, painted over the domain and polished with
    ``FINE_POLISH_GN`` Gauss-Newton steps; returned as a list of one.

    None (the caller runs the starts on the domain itself) when no window of at most a
    quarter of the domain strains the lattice by ``tiles.SMALL_WINDOW_STRAIN`` or less.
    Where the window's solution does not repeat in every cell (the real ``plain-2000px.jpg``,
    light estimated 10° off a weave direction at slant 30°: it departs from its cell average
    by 85 %; the bench's synthetic weaves by 0-5 %), its average, polished, has a higher
    energy than the starts run on the domain; but those do not repeat either, and it is their
    cell averages that the surface keeps, whose energies are higher still: the solves are
    then compared by their averages (see :func:`_lowest_energy`), and the starts need not
    run on the domain. Measured on the three real photos whose window's solution does not
    repeat (``photo_surface``, light estimated), the energy of the kept heights' cell
    average against the starts run on the domain: ``plain-2000px.jpg`` 829 -> 358 (15.9 s
    -> 5.2 s), ``plain-defect-e2r10.jpg`` 411 -> 210 (6.8 s -> 2.4 s), ``plain-slub-a10.bmp``
    600 -> 322 (4.7 s -> 2.9 s).

    `raw` is the image with its unknown pixels NaN: the window is painted from the raw
    intensities, attached shadows included (from the domain image, whose invalid pixels hold
    the mean, a plain weave lit at 60°, 3° off its yarns, came back at 0.76 instead of 0.04).

    Measured: plain weave tile of 1024 px (16 px cells, 64 px window) lit 3° off its yarns
    at 45°: 1.44 s instead of 13.6 s for the same height error (0.024);
    bench/bench_photo.py's plain weave lit 7° off t1 + t2 (a 975 x 787 px window): the
    pipeline 3.1 s instead of 13.6 s (0.024 against 0.023). The bench's 54 warned lights:
    summed errors 3.87 -> 3.83, the same 7 above 0.1; the one worse by more than 0.01 is the
    oblique lattice's plain weave exactly along t1 at 45° (0.225 -> 0.263, 0.087 from the
    pyramid alone). Polishing every start (not only the best) or with 6 steps: 3.87 either
    way, slower.
    """
    from haptex_compile.shading_variational import solve_variational
    from haptex_compile.tiles import paint_tile, small_periodic_window

    basis = np.asarray(basis_px, dtype=float)
    small = small_periodic_window(basis)
    if small is None or small[1][0] * small[1][1] > img.size / 4:
        return None

    b_small, shape_small = small
    small_img = np.clip(paint_tile(_cell_average(raw, basis).tile, b_small, shape_small), 0.0, None)
    small_weight = valid_pixels(small_img).astype(np.float32)
    small_kwargs = dict(zip(("dark", "bright"), _censored_pixels(small_img))) if CENSORED else {}
    z, a = _lowest_energy(small_img, small_weight, light, small_kwargs,
                          _fine_starts(small_img, small_weight, light, albedo0, small_kwargs))
    z0 = paint_tile(_cell_average(z, b_small).tile, basis, img.shape)
    return [solve_variational(img, weight, light.vector, a, z0=z0, max_levels=1, fine_gn=FINE_POLISH_GN,
                              fine_cg=FINE_START_CG, gn_rtol=FINE_START_RTOL, **domain_kwargs)]


def _unseen_waves(z: np.ndarray, light: Light) -> np.ndarray | None:
    """The part of periodic `z` made of waves with no slope along the light's tilt (wave
    vector perpendicular to it: the light runs along the domain's axes or diagonals), or None
    when there are none."""
    rows, cols = z.shape
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.rfftfreq(cols)[None, :]
    t = np.deg2rad(light.tilt_deg)
    unseen = np.abs(kx * np.cos(t) + ky * np.sin(t)) <= 1e-6 * np.hypot(kx, ky)
    unseen[0, 0] = False
    if not unseen.any():
        return None
    spec = sfft.rfft2(z.astype(np.float64))
    return sfft.irfft2(np.where(unseen, spec, 0.0), s=z.shape).astype(z.dtype)


def _tile_aligned_tilt(tilt_deg: float, shape: tuple[int, int]) -> tuple[str, float] | None:
    """The periodic tile's axis or diagonal within ``ALIGNED_TILT_DEG`` of the light's tilt,
    as (name, its tilt in degrees), or None.

    Those directions are perpendicular to the wave vectors of one cycle per tile along x
    (``(1/cols, 0)``), y, or both (``(1/cols, ±1/rows)``): a wave with such a vector has no
    slope along the light. For a square tile they are the axes and the diagonals.
    """
    rows, cols = shape
    directions = {
        "x axis": 0.0,
        "y axis": 90.0,
        "diagonal": float(np.degrees(np.arctan2(rows, cols))),  # across the (1, -1) wave
        "anti-diagonal": float(np.degrees(np.arctan2(rows, -cols))),  # across the (1, 1) wave
    }
    for name, direction in directions.items():
        if tilt_axis_difference_deg(tilt_deg, direction) < ALIGNED_TILT_DEG:
            return name, direction % 180.0
    return None


def weave_visibility(light: Light, basis_px) -> tuple[float, float]:
    """How directly `light` sees the profiles across a lattice relief's weave directions.

    The weave directions are the lattice's shortest vectors t1, t2 (the columns of
    `basis_px`, a reduced basis as :func:`haptex_compile.lattice.find_lattice` returns) and
    t1 ± t2 (a plain weave's yarns run along its reduced vectors or along their sum and
    difference, depending on which repeat the lattice found). A wave across direction d has
    no slope along d, and the first-order (linear) shading term sees its slope in proportion
    to ``sin(slant) |sin(angle between the tilt and d)|``; lit along d it is seen only at
    second order, where a ridge and a groove look alike (see ``WEAVE_VISIBILITY_MIN``).

    Returns
    -------
    (float, float)
        The smallest of those visibilities over the four directions (0 to 1), and the tilt in
        degrees (in [0, 180)) of the direction that has it.
    """
    basis = np.asarray(basis_px, float)
    t1, t2 = basis[:, 0], basis[:, 1]
    sin_slant = float(np.sin(np.deg2rad(light.slant_deg)))
    best = (np.inf, 0.0)
    for d in (t1, t2, t1 + t2, t1 - t2):
        direction = float(np.degrees(np.arctan2(d[1], d[0]))) % 180.0
        off = tilt_axis_difference_deg(light.tilt_deg, direction)
        best = min(best, (sin_slant * float(np.sin(np.deg2rad(off))), direction))
    return best


# --------------------------------------------------------------------------------------------
# Physical scale


def scale_relief(height, relief_um: float, kind: str = "rms") -> np.ndarray:
    """Give a relative height map its physical relief.

    Parameters
    ----------
    height : ndarray
        Relative heights (any unit; only the shape counts).
    relief_um : float
        The relief in µm, as `kind` says.
    kind : str
        ``"rms"`` (default): RMS height about the mean; ``"pv"``: peak-to-valley height;
        ``"mad"``: mean absolute deviation about the mean, which is how Kawabata's SMD is
        defined (along a line; for Gaussian heights RMS = 1.25 x MAD).

    Returns
    -------
    ndarray
        Height in µm, mean 0, with the requested relief. A flat input stays flat (zeros).
    """
    if kind not in ("rms", "pv", "mad"):
        raise ValueError(f"relief kind must be 'rms', 'pv' or 'mad', got {kind!r}")
    if not np.isfinite(relief_um) or relief_um < 0:
        raise ValueError(f"relief_um must be finite and >= 0, got {relief_um!r}")
    h = np.asarray(height, dtype=float)
    if not np.all(np.isfinite(h)):
        raise ValueError("height contains NaN or infinite values")
    h = h - h.mean()
    if kind == "rms":
        size = float(np.sqrt(np.mean(h * h)))
    elif kind == "pv":
        size = float(h.max() - h.min())
    else:
        size = float(np.mean(np.abs(h)))
    if size <= 0:
        return np.zeros_like(h)
    return h * (relief_um / size)
