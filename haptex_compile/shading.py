"""Heights from shading: the solvers (Tsai & Shah's, and the default variational one) and
the driver that picks the domain, the light and the starts, and relief scaling.

The conventions, the light and the inputs are in :mod:`haptex_compile.shading_image`; the light
search in :mod:`haptex_compile.shading_light`; the extra starts for lights along a tile's axes
or a weave's directions in :mod:`haptex_compile.shading_starts`. The public names of all four
are importable from here.

Heights from shading have no absolute scale (the slopes scale with the assumed slant and
albedo); :func:`scale_relief` fixes it from a stated relief.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from haptex_compile import shading_image, shading_light, shading_starts
from haptex_compile.shading_image import (
    MAX_SLANT_DEG,
    MIN_SLANT_DEG,
    SATURATED,
    Light,
    _as_image,
    _censored_pixels,
    _finite_or_zero,
    normalised_height_error,
    render_lambertian,
    tilt_axis_difference_deg,
    top_level,
    valid_pixels,
)
from haptex_compile.shading_light import estimate_light, estimated_light_note, light_misfit
from haptex_compile.shading_prior import along_light_power
from haptex_compile.shading_starts import weave_visibility

__all__ = [
    "Light",
    "SfsResult",
    "render_lambertian",
    "estimate_light",
    "estimated_light_note",
    "light_misfit",
    "tsai_shah",
    "shape_from_shading",
    "scale_relief",
    "normalised_height_error",
    "tilt_axis_difference_deg",
    "valid_pixels",
    "weave_visibility",
    "METHODS",
]

METHODS = ("default", "accurate", "tsai-shah")
# From this slant on, attached and cast shadows dominate and the solution degrades.
GRAZING_DEG = 75.0
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
# The margin around a plain image, as a fraction of its longer side (at least 8 px): the
# margin's thin plate joins opposite edges smoothly. On an image whose edges are level ground
# (an object on a flat background: see LEVEL_EDGE_FRACTION) the join holds that ground level,
# and the margin is PLAIN_MARGIN; on others (a texture that fills the image) it bends the
# edges towards each other, and a wider margin, TEXTURE_MARGIN, frees them. Measured in one
# run, light given, with PLAIN_MARGIN everywhere against that choice with TEXTURE_MARGIN 0.15
# / 0.2: bench_shading's random crops, mean errors sphere domes 0.318 -> 0.258 / 0.238 (above
# 0.4: 8 -> 5 / 2), plain weave 0.235 -> 0.218 / 0.223 (5 -> 2 / 2), random bumps 0.228 ->
# 0.226 / 0.227; its plain table (256 px renderings and 224 px crops, 4 lights): the weave's
# crops 0.170 -> 0.099 / 0.099 on average (0.289 -> 0.146 at 15°), its renderings 0.033 ->
# 0.067 / 0.043 (their edges match, and the narrow margin suits them), random bumps 0.207 /
# 0.181 -> 0.197 / 0.166 (renderings / crops) at 0.15, Brownian surfaces 0.747 / 0.816 ->
# 0.694 / 0.742, the sphere cap on level ground unchanged (with 0.2 everywhere: 0.086 -> 0.245
# at 60°); 800 px crops of 1024 px tiles (6 each): the weave 0.360 -> 0.251, random bumps
# 0.179 -> 0.165, Brownian 0.821 -> 0.818, domes of a sphere cap (edges 41-58 % level
# ground) unchanged; summed error 40.80 -> 36.88 / 36.23, time +12 % / +17 % over all of
# them. 1 Mpx renderings (the four surfaces at four lights, best of 2): summed error
# 4.36 -> 4.20 (the weave at 15° 0.156 -> 0.080), time 18.2 -> 19.7 s (the domain 1152 ->
# 1200 px; with 0.2, 1280 px). Picking the margin by the data misfit of both solves (twice the
# time) did no better than 0.2 everywhere on the 122 cases at 256 px and below (28.97 against
# 28.91 summed; 0.08: 32.29).
PLAIN_MARGIN = 0.08
TEXTURE_MARGIN = 0.15
# An image's edges are level ground when at least LEVEL_EDGE_FRACTION of the valid pixels in
# a band of LEVEL_EDGE_BAND_PX along its edges, smoothed by a Gaussian of LEVEL_EDGE_BLUR_PX
# (noise of sigma 0.03: 0.24 -> 0.88 of a flat ground's band within the tolerance), lie within
# LEVEL_EDGE_TOL of their median. Measured on bench_shading's images (above): sphere caps on
# level ground 0.64-1.0 (with noise of sigma 0.01-0.03: 0.88-1.0), 800 px domes 0.41-0.58,
# textures (random crops, plain weave, random bumps, Brownian surfaces, with that noise too)
# 0.01-0.36.
LEVEL_EDGE_FRACTION = 0.4
LEVEL_EDGE_BAND_PX = 2
LEVEL_EDGE_BLUR_PX = 2.0
LEVEL_EDGE_TOL = 0.01
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
# Large images: the levels other than the finest with 256 x 256 px or more (a 1 Mpx image's
# half- and quarter-resolution levels, a 512 px image's half) take at most 8 Gauss-Newton steps
# of 12 CG iterations (solve_variational's large_level_cap; the half-resolution level took 20,
# the quarter one up to 20 steps). They only give the next level its start, and on smooth
# reliefs they crept on to their step limits: 1 Mpx sphere caps and plain weaves took 0.95-1.15
# s/Mpx, random bumps, whose timing the bench had reported, 0.6-0.8. Measured in one run
# (best of 2; the bench's four surfaces as 1 Mpx tiles at its four lights, light given):
# summed time 14.9 -> 12.9 s, slowest 1.10 -> 0.92 s/Mpx, summed height error 0.987 -> 0.995
# (the sphere cap at 30° and 60° 0.007 / 0.023 -> 0.013 / 0.028, the others within 0.003);
# 512 px tiles 3.96 -> 3.72 s, error 0.605 -> 0.610; 1 Mpx plain images of random bumps
# (seeds 5, 2) at 45° 1.04-1.09 -> 0.91-0.93 s/Mpx and at 60° 1.17-1.30 -> 1.10-1.21, errors
# within 0.005, at 15° unchanged (12 iterations already). Tiles of 256 px have no such level.
DEFAULT_SOLVER = dict(mid_gn=8, mid_cg=20, fine_cg=9, gn_rtol=3e-4, albedo_projection=True,
                      projection_levels=(1,), projection_max_ratio=0.1, bound_noise_sigmas=3.09,
                      censored_data=False, subspace_steps=2, bound_start_albedo=True,
                      large_level_cap=(256 * 256, 8, 12))
# Plain images: a level stops once a full step gains less than 0.1 %. Their half-resolution
# level gains 0.05-0.1 % a step for all its 8 steps (a tile's converges in 4), for no
# accuracy: bench_shading's plain-image table (light given, plain renderings and crops)
# summed 4.58 / 5.38 -> 4.61 / 5.38; random bumps of 1 Mpx 2.14-2.24 -> 1.62-1.72 s/Mpx.
# The finest level's steps take 6 CG iterations (a tile's 9 resolve its weave's cells; the
# edges of a plain image limit it first): the table 4.61 / 5.38 -> 4.59 / 5.36, bumps of
# 1 Mpx 1.94-2.14 -> 1.66-1.68 s/Mpx (error 0.146 -> 0.134), a 960 px crop of the plain weave
# the same errors (0.363, 0.123 at slants 15°, 45°).
# Their large levels above the finest (256 x 256 px or more: from about 440 px a side, the
# half-resolution level of the image with its margin) take 8 CG iterations a step, not 12:
# those levels took 38 % of the time, the finest 31 % (summed over plain images of 512 and
# 768 px and 800 px crops, the bench's four surfaces at its four lights). Against the tiles'
# 12 in the same run (bench_shading._plain_timing_rows, best of 2): 16 solves of 512 px
# 5.70 -> 5.20 s, of 768 px 10.10 -> 9.23 s, summed errors 4.023 -> 4.031 and 4.029 ->
# 4.027; of 1024 px 16.8 -> 15.8 s, 4.203 -> 4.184; with 800 px crops, of 48 solves none
# worse by more than 0.04 (a Brownian crop at 60°, 0.656 -> 0.693; the plain weave at most
# 0.007). Fewer steps there, fewer on the coarser levels or a looser gn_rtol trade error for
# time along one line (summed errors of those 48 from 13.125: 6 steps 13.235, 5 steps 13.302,
# gn_rtol 3e-3 as well 13.258, at most 10-20 % faster in single runs), as did 4 previous
# steps joined (subspace_steps) with 5 steps (13.158); row threads on levels from 64 x 64 px
# gained nothing.
PLAIN_SOLVER = dict(gn_rtol=1e-3, fine_cg=6, large_level_cap=(256 * 256, 8, 8))
# Method "accurate": more steps and iterations everywhere, converged solves, the albedo
# projected on every level without sub-pixel roughness (Brownian surfaces, 7 seeds x 2 tilts
# at 15°: mean a320 error -13 % -> -9 % with the ratio limit). Levels stop once a full step
# gains less than 0.01 %: same errors on the bench surfaces, 1 Mpx 2.80 -> 2.30 s. Steps
# join the previous two as in the default (sphere cap at 60°, light given: a320 +33 % -> +21 %).
ACCURATE_SOLVER = dict(coarse_gn=30, mid_gn=8, fine_gn=6, coarse_cg=20, fine_cg=20, tol=0.01,
                       albedo_projection=True, projection_max_ratio=0.1, gn_rtol=1e-4,
                       bound_noise_sigmas=3.09, censored_data=False, subspace_steps=2)


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
# The driver


def _embed(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """`a` in the top-left corner of a zero array of `shape`."""
    out = np.zeros(shape, a.dtype)
    out[: a.shape[0], : a.shape[1]] = a
    return out


def level_edge_fraction(image: np.ndarray, valid: np.ndarray | None = None) -> float:
    """The share of an image's edges that looks like level ground: of the valid pixels in a
    band ``LEVEL_EDGE_BAND_PX`` wide along its four edges, after a Gaussian blur of
    ``LEVEL_EDGE_BLUR_PX`` (invalid pixels filled with the mean), those within
    ``LEVEL_EDGE_TOL`` (intensity, image in [0, 1]) of the band's median. 0 when the band
    holds no valid pixel."""
    img = np.asarray(image, dtype=float)
    ok = np.isfinite(img) if valid is None else np.asarray(valid, bool) & np.isfinite(img)
    if not ok.any():
        return 0.0
    filled = np.where(ok, img, float(np.mean(img[ok])))
    # The blur of strips along the edges, deep enough for its kernel (gaussian_filter's
    # default truncation at 4 sigma), gives the band the whole image's blur (1 Mpx: 34 ->
    # 4 ms); the side strips give the band's rows between the top and bottom ones.
    b = LEVEL_EDGE_BAND_PX
    depth = b + int(4.0 * LEVEL_EDGE_BLUR_PX + 0.5)
    rows = slice(b, img.shape[0] - b)
    parts = [(np.s_[:depth, :], np.s_[:b, :]), (np.s_[-depth:, :], np.s_[-b:, :]),
             (np.s_[:, :depth], np.s_[rows, :b]), (np.s_[:, -depth:], np.s_[rows, -b:])]
    vals = []
    for strip, band in parts:
        smooth = ndimage.gaussian_filter(filled[strip], LEVEL_EDGE_BLUR_PX, mode="nearest")
        vals.append(smooth[band][ok[strip][band]])
    vals = np.concatenate(vals)
    if vals.size == 0:
        return 0.0
    return float(np.mean(np.abs(vals - np.median(vals)) <= LEVEL_EDGE_TOL))


def _solve_domain(img: np.ndarray, valid: np.ndarray, censored, periodic: bool,
                  light: Light | None = None, albedo: float = 0.0, top: float | None = None):
    """The periodic domain the variational solver works on.

    A tile is its own domain. A plain image is embedded in a larger periodic domain whose
    margin carries no data (its edges are free; ``PLAIN_MARGIN`` of its longer side where its
    edges are level ground by :func:`level_edge_fraction`, else ``TEXTURE_MARGIN``), with the
    flat-on-average prior, tightened where the image's waves along `light` (with `albedo`) show
    no long-wave power (:mod:`haptex_compile.shading_prior`). `censored` is
    :func:`_censored_pixels` of the image. With `light` and no saturated pixel, the albedo is
    bounded above (``ALBEDO_SLACK`` x `top` / cos(slant); `top`: :func:`top_level` of the image,
    computed when not given).

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
        level = level_edge_fraction(img, valid) >= LEVEL_EDGE_FRACTION
        pad = max(8, int((PLAIN_MARGIN if level else TEXTURE_MARGIN) * max(rows, cols)))
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
    if shading_image.CENSORED:
        kwargs.update(dark=dark, bright=bright)
    if light is not None and valid.any() and not np.any(img[np.isfinite(img)] >= SATURATED):
        if top is None:
            top = top_level(img, valid)
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
        comparison (its heights, like the others', fall back to flat where they ran away:
        see ``RUNAWAY_SLOPE``). Light straight above (slant < 5°) makes the slopes' signs unobservable:
        the default then starts from a bright-is-high guess (warned, method suffixed).
    periodic : bool
        The image is a tile: the height wraps seamlessly (all operators are periodic).
        Otherwise the image is embedded in a larger periodic domain whose margin carries no
        data, so its edges are free (the margin is wider where the edges are not level ground:
        see :func:`level_edge_fraction`), and a weak prior that the fabric lies flat on average
        (no slope across the light at wavelengths longer than the image) removes the ramps
        that shading cannot see; it is tightened on the longest waves across the light where
        the image's waves along the light show little power (a weave: see
        :mod:`haptex_compile.shading_prior`). Periodic tiles are much better posed: a strip
        along the light closes on itself, so its height offset is fixed (measured on 256 px
        random bumps at 45°: 0.07 periodic, 0.24 as a plain image). On a plain image those
        offsets are left to the thin plate and the prior, and the energy's own minimum is off:
        random bumps at 60°, 10 seeds, the minimum nearest the true surface has normalised
        errors 0.24-0.33 (the default 0.22-0.31; ``bench/bench_shading.py``).
    mask : ndarray of bool, optional
        Pixels to use; saturated (>= 0.99), black (<= 0.01) and non-finite pixels are always
        excluded and filled by the smoothness term.
    weave_basis_px : array_like, optional
        The lattice of the image's relief (columns t1, t2 in pixels, a reduced basis), when
        known (a weave photo's tile or image). Light nearly along one of its weave directions
        (:func:`weave_visibility` below ``shading_starts.WEAVE_VISIBILITY_MIN``) is warned of
        and, on a periodic tile, solved from more starts (see
        :func:`~haptex_compile.shading_starts._start_from_cell`). Without it, light along a
        tile's axes and diagonals is (see
        :func:`~haptex_compile.shading_starts._bare_tile_starts`); with it, only when the light
        is also near a weave direction (a weave's window is cut to repeat the lattice, and its
        own axes mean nothing).

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
    top = top_level(img, valid)  # the brightest pixels' level, taken once for the three users below
    censored = _censored_pixels(img, mask, top)
    if light is None:
        light, albedo = shading_light._estimate_light(img, valid, mask, True, censored, periodic=periodic)
        warnings.append(estimated_light_note(light, periodic))
    else:
        albedo = shading_light._moment_albedo(img[valid], light.slant_deg, top)

    if method == "tsai-shah":
        if light.slant_deg < MIN_SLANT_DEG:
            # At slant 0 nothing moves; just above it the paper's gain turns the small df/dZ
            # into large steps (random bumps lit at 2°: slopes up to 19 px per px).
            warnings.append(
                f"light along the view axis (slant {light.slant_deg:.1f}° < {MIN_SLANT_DEG}°): Tsai-Shah's df/dZ"
                " vanishes or nearly at the flat start, and the height stays flat or its steps run wild"
            )
        z, used_method = _runaway_guarded(tsai_shah(_finite_or_zero(img), light), method, warnings)
        return SfsResult(_in_um(z, pixel_size_um), light, 1.0, used_method, tuple(warnings))

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
        visibility_min = shading_starts.WEAVE_VISIBILITY_MIN
        if visibility < visibility_min:
            # The more starts run on a tile only (a small periodic window of its lattice).
            along_weave = (visibility, weave_tilt) if periodic else None
            if np.sin(np.deg2rad(light.slant_deg)) < visibility_min:
                # Every direction is below the threshold: the cause is the slant, not the tilt.
                where = (f"light (slant {light.slant_deg:.1f}°) nearly overhead for every weave direction"
                         f" (sin(slant) x sin(angle to it) {visibility:.3f} < {visibility_min:g})")
            else:
                where = (f"light (slant {light.slant_deg:.1f}°, tilt {light.tilt_deg:.1f}°) nearly along the weave"
                         f" direction at tilt {round(weave_tilt, 1) % 180.0:.1f}° (sin(slant) x sin(angle between"
                         f" them) {visibility:.3f} < {visibility_min:g})")
            how = ("solved from 3-4 more starts" if periodic
                   else "not a periodic tile, so solved from the pyramid alone")
            warnings.append(
                f"{where}: the yarns' cross-sections barely shade and may come back wrong ({how}); light"
                f" the fabric so that this is at least {visibility_min:g} for every weave direction"
                " (e.g. slant 45°, 15-30° off the yarns)"
            )
    # A weave's window: its axes and diagonals matter only where they run along a weave
    # direction (warned above; the held starts still run); elsewhere the waves across them are
    # not the weave's (bench/bench_photo.py's plain weave lit 30° off t1, along the 975 x 787 px
    # window's diagonal: the same height error, 7.0 s -> 1.6 s).
    aligned = None
    if periodic and (weave_basis_px is None or along_weave is not None):
        aligned = shading_starts._tile_aligned_tilt(light.tilt_deg, img.shape)
    if weave_basis_px is None and aligned is not None and light.slant_deg >= MIN_SLANT_DEG:
        warnings.append(
            f"light tilt {light.tilt_deg:.1f}° within {shading_starts.ALIGNED_TILT_DEG:g}° of the periodic"
            f" tile's {aligned[0]} ({aligned[1]:.1f}°): the tile-sized waves across the light barely"
            " shade and the heights may be far off (solved from 4 starts); light the fabric at least"
            f" {shading_starts.ALIGNED_TILT_DEG:g}° away from its weave's axes and diagonals"
        )
    if light.slant_deg >= GRAZING_DEG:
        warnings.append(
            f"grazing light (slant {light.slant_deg:.1f}° >= {GRAZING_DEG:g}°): shadowed pixels"
            " carry no information and cast shadows are not modelled; expect large errors"
        )
    rows, cols = img.shape
    dom_img, dom_w, domain_kwargs = _solve_domain(img, valid, censored, periodic, light, albedo, top)
    if z0 is None and light.slant_deg < MIN_SLANT_DEG:
        z0 = _brightness_start(dom_img, dom_w, albedo, np.cos(np.deg2rad(light.slant_deg)))
    kwargs = {**_solver_settings(method, periodic, light.slant_deg, z0 is not None), **domain_kwargs}
    albedo_start = albedo
    weight = dom_w.astype(np.float32)
    z, albedo = solve_variational(dom_img, weight, light.vector, albedo, z0=z0, **kwargs)
    if (aligned is not None or along_weave is not None) and z0 is None:
        starts = [(z, albedo)]
        if along_weave is None:
            # A bare tile (no lattice given) lit along its axis or diagonal.
            starts += shading_starts._bare_tile_starts(dom_img, weight, light, albedo_start, kwargs, domain_kwargs)
        else:
            if aligned is not None:
                starts += shading_starts._held_starts(dom_img, weight, light, albedo_start, kwargs)
            # The raw intensities (shadows and highlights included; unknown pixels NaN) for
            # the small window's tile: the domain image has its invalid pixels filled.
            known = np.isfinite(img) if mask is None else np.isfinite(img) & np.asarray(mask, bool)
            from_cell = shading_starts._start_from_cell(dom_img, weight, light, albedo_start, domain_kwargs,
                                         weave_basis_px, np.where(known, img, np.nan))
            starts += from_cell or shading_starts._fine_starts(dom_img, weight, light, albedo_start, domain_kwargs)
        z, albedo = shading_starts._lowest_energy(dom_img, weight, light, domain_kwargs, starts, weave_basis_px)
    z, used_method = _runaway_guarded(z[:rows, :cols], used_method, warnings)
    return SfsResult(_in_um(z, pixel_size_um), light, float(albedo), used_method, tuple(warnings))


def _in_um(z: np.ndarray, pixel_size_um: float) -> np.ndarray:
    """Heights `z` in pixel units as µm; a ValueError where that overflows (a pixel size near
    1e308 um), rather than infinite heights."""
    with np.errstate(over="ignore"):
        height = z * pixel_size_um
    if not np.all(np.isfinite(height)):
        raise ValueError(f"pixel size {pixel_size_um:g} um is too large: the heights in um overflow")
    return height


RUNAWAY_SLOPE = 50.0  # px per px: a fabric's slopes are below about 1; a runaway inversion's reach 1e3+


def _runaway_guarded(z: np.ndarray, method: str, warnings: list[str]) -> tuple[np.ndarray, str]:
    """Heights `z` (pixel units) as float64 with mean 0, or flat where they ran away
    (a non-finite value or a slope above ``RUNAWAY_SLOPE``), with a warning appended to
    `warnings` and the method suffixed ``+flat-fallback``: every method's last guard (Tsai-Shah's
    faithful iteration diverges on images no surface gives: 214 px per px on a 4 x 4 noise
    image lit at 1°)."""
    # The check in the solver's float32 (1 Mpx: 23 -> 7 ms against float64).
    gy, gx = np.gradient(z)
    if np.all(np.isfinite(z)) and float(np.max(np.hypot(gx, gy))) <= RUNAWAY_SLOPE:
        z = z.astype(np.float64)
        return z - z.mean(), method
    warnings.append(f"the solver ran away (non-finite or slopes > {RUNAWAY_SLOPE:g}); fell back to a flat height")
    return np.zeros(z.shape), f"{method}+flat-fallback"


def _solver_settings(method: str, periodic: bool, slant_deg: float, start_given: bool) -> dict:
    """The keyword arguments of :func:`~haptex_compile.shading_variational.solve_variational`
    that :func:`shape_from_shading` passes for `method` ("default" or "accurate"), a tile or
    a plain image, the light's slant and whether a start height is given (the domain's own
    arguments are added by the caller)."""
    kwargs: dict = {}
    if start_given:
        # Do not coarsen the start away (from a flat height, overhead light has no Jacobian),
        # and take few steps: the problem has no unique answer, the start is the prior.
        kwargs.update(min_size=24, coarse_gn=6, mid_gn=3, fine_gn=2, coarse_cg=30, fine_cg=10)
    if method == "accurate":
        kwargs.update(ACCURATE_SOLVER)
    elif not start_given:
        kwargs.update(DEFAULT_SOLVER if periodic else {**DEFAULT_SOLVER, **PLAIN_SOLVER})
    if not start_given and slant_deg <= LOW_SLANT_MAX_DEG:
        kwargs.update(smooth_lam_growth=LOW_SLANT_LAM_GROWTH)
        if method != "accurate":
            kwargs.update(mid_cg=LOW_SLANT_MID_CG)
    return kwargs

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
