"""RGB-D box filter with grid cells and occlusion flags (the RGB-D occlusion paper, SPEC C2).

Usage::

    config = RGBDConfig(variant="grid-occlusion", n_particles=300)
    filt = build_rgbd_filter(config)
    params = default_rgbd_params(config)
    background = median_background(colour_frames, depth_frames)   # cpf_jax.kernels.background
    state = filt.init(params, key, frame, box_xywh, background)
    state, info = filt.step(params, key, state, frame)
    # or a whole sequence as one lax.scan:
    states, infos = track(filt, params, key, frames, box_xywh, background)

Variants (``config.variant``; the four rows of the paper's Tables 1-2)
-------------------------------------------------------------------------
``"rgb"``             the colour layer (``cpf_jax.colour``), wrapped unchanged: the
                      RGB-only baseline (the paper's is an adaptive colour filter).
``"rgbd"``            one cell (the whole box): foreground-ratio Beta x colour x depth.
``"grid"``            ``k x k`` cells (``config.grid``, 2 in the paper), no flags.
``"grid-occlusion"``  ``k x k`` cells, each with a binary occlusion flag per particle.

Observation model (paper 2.3-2.4), per cell ``i`` of a particle's box
--------------------------------------------------------------------
Pixels are foreground against a static background model
(``kernels.background.foreground_mask``). For a visible cell (``z_i = 0``)::

    log p_i = beta_weight * log Beta(r_i; a_i, b_i)              (eq. 2)
              - d_i^2 / (2 sigma_rgb^2)                          (eq. 4-5)
              - (m_i - mu_i)^2 / (2 s_i^2)                       (2.4)

``r_i`` is the cell's foreground ratio; ``d_i`` the Bhattacharyya distance of the
H-S(V) histogram of its *foreground* pixels (the paper's "preprocessed foreground
RGB image") to the template ``q_i``; ``m_i`` the median depth of its foreground
pixels with depth, ``mu_i`` the depth template and ``s_i = sigma_depth +
sigma_depth_rel * mu_i`` (depth noise and body thickness grow with distance).
Every count is exact (``histogram.rect_reduce`` over ``[N, C, 4]`` cell
rects); the median comes from a 64-bin log-depth histogram
(``kernels.cells.histogram_quantile``, error below one bin, 5 %). The paper's
exponent in eq. 4 is garbled; we read it as the thesis's Gaussian in ``d``.
Each term has a floor (``beta_floor``, ``colour_floor``, ``depth_floor``): one
implausible statistic costs a bounded amount. The Beta shapes are fitted on synthetic
walkers, whose silhouettes fill about a third of their box; real people seen from
the front or from above fill 60-90 % (the IST recording), where the unfloored per-cell
Beta falls to about -29 for a full cell. ``beta_floor = -10`` (the Beta at a ratio of
about 0.93) caps that; -6 also helped real people but cost the toy full-occlusion test
of ``tests/test_rgbd.py`` its MOTA margin (occluder-filled cells must still look unlike
a visible target).

Foreground fill (``fill_adapted``): the floor bounds the cost of a full cell, but the
fitted means still prefer a box with a third of it foreground, and on a real person that
is a box about twice his width. On the IST recording the tracked box kept the initial
head-and-shoulders box's width (150-180 px) while the man, walking away, became 40-120
px wide; its cells took in the people beside him, and when he turned behind another man
the filter went on with a third man at his old depth. So ``init`` measures the share of
foreground in the initial box (a ground-truth box, as the colour template's), and every
Beta mean of the cells, the whole box and the inner border strips is moved by the same
logit shift (``beta_fill_shift``: the gap ``logit(fill) - logit(mean of the whole-box
Beta)`` less a dead zone, times ``fill_adapt``), each keeping its concentration
``a + b`` (the outer strips stay as fitted: nothing of a person lies outside his tight
box). One frame's fill is a noisy measure of a walker's (the synthetic walkers' first
frames fill 0.36-0.56 of their boxes, their whole walks 0.30-0.53; the IST man's first box
0.88, his unoccluded frames 0.69), so a fill within
``fill_deadzone`` logits (1.5 standard deviations of the whole-box Beta's logit) of the
fitted mean moves nothing and one beyond it moves the means by the excess: on IST the
whole-box mean goes from 0.31 to 0.73. IST AUC over 16 filter keys
(``occlusion_tables.py``, 2026-11-26), without -> with the shift: grid-occlusion about
33 -> 39.7 (keys 37.1-43.8), grid 24.0 -> 35.4, rgbd 15.8 -> 36.8 (the first figures
are over 4 keys; over 16, with the parameters passed to one jitted runner, grid-occlusion
scored 33.0 without the shift). Without the dead zone grid-occlusion scored 43.7 (keys
26.7-67.0), but on the synthetic training scenes (seeds 100-103 x 3 keys, occlusion MOTA)
occlusion_box fell from 87.3 to 79.4 (three runs below 61) while occlusion_person rose from
85.8 to 92.4. With it no scene of ``occlusion_tables.py`` is shifted except
occlusion_return seed 0 (0.03 logit), and an unshifted filter keeps its Beta shapes bit
for bit: the other synthetic rows moved only by the recompiled program's floating-point
noise (occlusion grid-occlusion MOTA 95.9 -> 96.0, worst run 91.2 both times).

For an occluded cell (``z_i = 1``) eq. 1 gives a constant. We keep that constant
(``log_occluded``) and add the depth-ordering rule the paper states in words
("depth decides who occludes whom")::

    log p_i = log_occluded + log(eps + (1 - eps) * e_i)

``e_i`` is the share of the cell covered by foreground **nearer** than the
template depth by more than ``max(occluder_margin, occluder_margin_rel * mu_i)``
(the ratio ``r_i`` times the nearer fraction of its depth histogram;
``occluder_unknown`` when the cell has too few depth samples). A cell in
front of which nothing nearer stands cannot be occluded (``eps`` is small):
without this rule a particle drifting onto empty background could call all its
cells occluded and score as well as the true, hidden target.

Occlusion flags (paper 2.5, eq. 6)
----------------------------------
Each particle carries ``C = k^2`` flags as a bit mask (``int32``, bit ``i`` =
cell ``i``). Transitions: a full ``2^C x 2^C`` matrix ``T`` (``flag_transition
= "full"``, used up to ``max_full_cells`` cells; default ``T`` is the Kronecker
product of the per-cell chains, or ``params.transition`` if given) or the
factorised per-cell chains ``P(0->1) = p_occlude``, ``P(1->0) = p_reveal``
(``"factorised"``, any ``C``). **Inference**: instead of drawing the new flags
blindly from ``T`` and weighting, each particle draws them from the locally
optimal proposal ``p(z_t | z_{t-1}, B_t, y_t) ∝ T[z_{t-1}, z_t] p(y_t | B_t,
z_t)`` and is weighted by ``sum_z T[z_{t-1}, z] p(y_t | B_t, z)``: the same
model as eq. 6, with the Monte Carlo noise of the flags integrated out (2^C
terms per particle for the full matrix, 2 per cell for the factorised form).

Body colour (``body_term``; not in the paper)
-------------------------------------------
The cells' colour templates describe the first box's layout: on the IST recording that
is a man's head and shoulders at 1 m, which says little about his whole body at 4 m, so
the cell colour terms could not tell him from a neighbour at his depth. One more term
scores identity without layout: the foreground colour histogram of the cells visible in
a flag state, pooled, against a whole-body template ``h_B``::

    log p_B(s) = max(-(d_B(s)^2 - body_ref^2) / (2 sigma_body^2), body_floor)

(0 when fewer than ``body_min_pixels`` visible foreground pixels are left, so a fully
occluded state is neither rewarded nor punished; ``body_ref`` is a typical distance of
the target, which scores 0). It joins the other multi-cell terms, per flag state, inside
the exact flag marginalisation; the pooling happens inside the histogram reduction, so
the ``[N, C, B]`` counts never exist at once. ``h_B`` starts as the initial box's
foreground histogram, is a running mean of the reported boxes of the unoccluded frames
among the first ``body_warmup`` steps (the first box may show part of the person), then
forgets at ``body_rate``; frames with any cell voted (posterior above 0.1) or lost do not
teach it. A warm-up counted in learnt frames instead (10) let the IST man's template
learn from boxes that took in the striped-sweater man beside him (frames 66-68).

Voting, search and template update (paper 3.1-3.2, eq. 7-8)
----------------------------------------------------------
The vote ``v_i`` is the posterior expectation of flag ``i`` over particles
(weights x per-particle flag posteriors). Cells with ``v_i > vote_threshold``
are voted occluded. While more than half of the cells are voted occluded, the
position noise grows by ``spread_rate`` per frame (up to ``spread_max`` times):
the particles search a wider area. Templates are updated with the forgetting
factor ``lambda = 1 - template_rate`` (colour) / ``1 - depth_rate`` (depth),
eq. 7, only in cells voted not occluded; occluded cells keep theirs (eq. 8).

Motion model
------------
The colour layer's (``config.model``, ``config.hierarchical``; ``cpf_jax.dynamics``) with
calmer box sizes (``RGBD_TAU``) and one change: the size velocities ``(vw, vh)`` keep
only ``size_velocity_decay`` of themselves per frame (0.9; 1 is the plain AR model, in
which they random-walk). A person's box narrows and widens with his gait and as he
turns; with a random-walk velocity, a cloud that had collapsed (ESS 2-8 of 150) while
his silhouette narrowed kept shrinking by its inherited 3 px/frame after it widened
again, and no particle was left wide enough to find him (synthetic occlusion_person,
scene seed 0, filter key 1: MOTA 50.0 without the decay, 96.0 with it).

Data-driven proposal (``"rgbd"`` and the grid variants; ``detector_fraction``)
-----------------------------------------------------------------------------
A person near the camera moves half a box or more per frame, far beyond the motion
noise, and his box can change size by a fifth per frame (he walks towards or away from
the camera, or more of him comes into view). The transition model therefore has a fast
component, ``p(b_t | x_{t-1}) = (1 - fast_fraction) p_motion + fast_fraction N(c_t;
mean, (fast_sigma h)^2) LN(w_t, h_t; predicted size, fast_scale^2)`` on the box ``b_t =
(c_t, w_t, h_t)``, and the boxes are drawn from a mixture proposal (as the boosted
particle filter, Okuma et al. 2004): with probability ``detector_fraction`` from a
"detector" -- a coarse map (``detector_stride``) of boxes of a grid of sizes around the
estimate's (``detector_scales``, ``detector_scale_step``) scored by their *tightness*
around foreground at the target's depth (share inside x share missing from a ring
around the box; ``detector_log_map``), near the prediction -- otherwise from the motion
model. Velocities come from the motion model either way, so each particle's weight gets
the exact ratio ``p(b_t | x_{t-1}) / ((1 - a) p_motion + a q_det)`` of the box densities
(``motion_position_log_density``, ``motion_size_log_density``,
``detector_log_density``). The detector is used (``a > 0``) only when the box at the
predicted centre is less than ``detector_need`` as tight as the best one near it, and
neither it nor the fast component while the target is voted occluded (the spreading and
the recovery search take over then). Fixed-size motion models: centres only.

The fast component's spread (and the detector's search radius) is ``fast_sigma`` times
``min(h, reach / z)``: the box height, capped by the height the initial box would have
at the target's current depth ``z`` (``reach`` = initial height x initial depth, px mm).
A box's pixel height is no measure of metric scale when the target comes into view cut
off: the IST recording starts with the head and shoulders of a man 1 m from the camera
(box 144 px high), who then walks 3-4 m away while more of his body shows (box 200-300
px). Uncapped, the half-a-box jump allowed at 1 m stayed allowed at 4 m, where it reached
another man at his depth 160 px away (frame 68; IST grid-occlusion AUC 30.3 -> 33.8 over
4 filter keys with the cap). For a whole-body initial box ``reach / z`` follows ``h``
and the cap changes nothing. The cap trusts the depth templates, so it is on only for
``"grid-occlusion"`` (``config.fast_depth_cap``), whose templates learn only in cells
voted visible: on IST the cap cost ``"grid"`` 10 AUC points (28.8 -> 18.7, 4 keys).

Reported box (``info.report``, what metrics score). ``"rgbd"`` / ``"grid"``:
the estimate (weighted mean). ``"grid-occlusion"``: the union of the cells
voted visible (``report="cells"``, the ground truth is the tight box of the
*visible* person), or the whole estimate (``report="box"``); when every cell is
voted occluded the filter reports no box (``info.lost``), which is what
CLEAR-MOT's false-positive count asks of a tracker whose target is hidden.
With ``report="pixels"`` (default) the reported box is the tight box of the
target's pixels (foreground within the target gate of the depth template) in and
around the estimate; ``"grid-occlusion"`` also reports no box when those pixels
cover less than ``min_coverage`` of the estimate (the target is hidden, whatever
the votes say). Only the main run of columns (rows) counts: the one holding the most
target pixels, its lines at most ``report_gap`` times the estimate's width (height)
apart. On IST, stray foreground at the target's depth among the desks stretched the
tight box to twice the person's width; with the main run, grid-occlusion AUC over 8
keys went from 31.4 to 33.8 (the table's 4 keys: 34.2 to 37.3). The cost: a person split
by an occluder wider than the gap is reported by his larger part (synthetic
``occlusion_return``, "rgbd" MOTA 93.3 to 82.7); letting lines across a nearer occluder
bridge the gap lost 6 points on IST, whose occluders stand beside the target.

Depth templates move: the target's depth velocity ``v`` (mm per frame) is tracked by an
alpha-beta filter. Each step first predicts every known template by ``v``; after the
update (gain ``depth_rate``) ``v`` is corrected by ``depth_velocity_rate`` times the mean
innovation (median - prediction) of the updated cells, and fades by
``depth_velocity_fade`` (0.3) per frame in frames where no cell is updated (a walking
person keeps walking for a few hidden frames, but may stop or turn round: with 0.05 the
templates of the synthetic ``occlusion_return`` walker ran on more than 1 m past him
while he turned behind the occluder). The cell medians
that update the templates count only pixels not nearer than the predicted target depth
by more than the occluder margin (depth decides: an occluder covering half a cell must
not become its template), unless nothing is seen at the templates' depth while they are
stale (below). Without the velocity, a target walking away at 150-250 mm per
frame (the IST recording, frames 52-62) leaves its templates and the target-depth gates
behind.

Depth templates age: ``depth_age`` counts the frames since a cell's template was
last updated; the target may have moved ``depth_speed`` mm per frame since, so the
depth Gaussian and the occluder margin widen by ``min(depth_speed * age,
max_drift)``, and the target gate of the recovery draw and of the pixel report
widens by ``depth_speed`` per frame hidden or stale (up to ``search_drift_max``;
``search_drift``). Cells that are not updated follow the mean depth change of the
updated ones.

Stale templates are re-learnt. Staleness counts as well as hidden frames: on
``occlusion_box`` a walker turned towards the camera behind the box and reappeared 1.2
m nearer than his templates (which had run on away from him); found by colour in one
frame, the hidden count reset, the gate shrank back and he was "hidden" again for the
rest of the sequence while the estimate sat on him (IoU 0.6-0.9 scored as misses). So
the gate stays wide until the templates learn, and when no target pixel lies at the
templates' own depth (``held < min_coverage`` in ``target_extent``) the occluder cut and
the jump test widen by the same drift, so that they can learn the nearer target.
grid-occlusion MOTA on occlusion_box, seeds 0-1 x 4 keys: 79.0 -> 95.0 (with the fade
of 0.3). After a long full occlusion the drift is wide enough to take in the occluder
itself (1 m nearer than the target after 20 hidden frames on the toy of
``test_grid_occlusion_tracks_through_a_long_full_occlusion``): so the step remembers the
occluder's depth (``occluder_depth``, the mean median of the estimate's cells nearer than
the templates by more than the occluder margin) and pixels within
``max(recovery_gate, recovery_gate_rel * z)`` of it are never the target's by drift alone
(``target_like``).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import digamma, polygamma

from cpf_jax.colour import (
    COLOUR_BINS,
    ColourConfig,
    ColourParams,
    aspect_log_prior,
    bin_index,
    build_colour_filter,
    default_colour_params,
    n_bins_of,
)
from cpf_jax.dynamics import (
    DEFAULT_TAU,
    MODELS,
    MOTION_CONSTRAINTS,
    MotionParams,
    default_motion_params,
    guide_frame,
    propagate,
)
from cpf_jax.kernels import boxes as box_ops
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels.background import Background, foreground_mask, update_background
from cpf_jax.kernels.cells import (
    beta_log_density,
    border_strips,
    coarse_counts,
    depth_bin_index,
    grid_cells,
    histogram_fraction_below,
    histogram_quantile,
    map_cell_of,
    side_cells,
    strip_counts,
    strip_table,
    window_sums,
)
from cpf_jax.kernels.histogram import (
    bhattacharyya,
    box_histograms,
    rect_reduce,
    suggest_window,
    uses_window,
)
from cpf_jax.types import (
    Filter,
    Frame,
    check_frame,
    memoised_build,
    scan_filter,
    usable_box,
)

__all__ = [
    "VARIANTS",
    "RGBDConfig",
    "RGBDParams",
    "RGBDState",
    "RGBDInfo",
    "PARAM_CONSTRAINTS",
    "DEFAULT_BETA",
    "build_rgbd_filter",
    "cell_terms",
    "CellTerms",
    "default_rgbd_params",
    "flag_bits",
    "kronecker_transition",
    "fit_beta",
    "cell_foreground_ratios",
    "initial_fill",
    "beta_fill_shift",
    "fill_adapted",
    "track",
    "track_boxes",
]

VARIANTS = ("rgb", "rgbd", "grid", "grid-occlusion")
REPORTS = ("pixels", "cells", "box")
TRANSITIONS = ("auto", "full", "factorised")

# Beta shapes (a, b) of the per-cell foreground ratio, fitted by
# ``experiments/occlusion_tables.py --fit-only`` (maximum likelihood) on the tight
# ground-truth boxes of unoccluded frames of synthetic training scenes
# (walk_across_medium, walk_towards, turn; seeds 100-103, never scored).
# Keyed by grid size k; cells row-major. Other k fall back to BETA_FALLBACK.
DEFAULT_BETA: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = {
    1: ((3.52,), (7.89,)),
    2: ((1.09, 0.93, 2.42, 2.44), (2.29, 2.03, 5.88, 5.89)),
}
BETA_FALLBACK = (2.0, 4.0)
# The initial box's foreground fill is clipped to [FILL_CLIP, 1 - FILL_CLIP] before the
# Beta means are moved towards it (``beta_fill_shift``).
FILL_CLIP = 0.05
# Motion noise of the RGB-D variants (dynamics layout, for a 200 px box): positions as
# the colour layer's DEFAULT_TAU, box size 4x calmer. The reported box comes from the
# target's pixels, so the tracked box need not follow the gait's +-40 % width changes;
# a calm size also keeps a partly hidden target's box from shrinking onto its
# visible part.
RGBD_TAU = (DEFAULT_TAU[0], DEFAULT_TAU[1], DEFAULT_TAU[2], DEFAULT_TAU[3], 1.5, 1.5, 0.2, 0.2)
# Border strips (config.border = 0.1): inner top, bottom, left, right; outer t, b, l, r.
# Inner strips: MLE fits as DEFAULT_BETA. Outer strips: every training ratio is 0 (a
# tight box has no person pixel outside), where a Beta fit degenerates to a spike;
# Beta(1, 30) is set by hand instead: log-density ~ -29 r, about -3 at r = 0.1.
DEFAULT_BORDER_BETA: tuple[tuple[float, ...], tuple[float, ...]] = (
    (4.85, 4.62, 1.34, 1.29, 1.0, 1.0, 1.0, 1.0),
    (14.24, 13.26, 15.88, 14.06, 30.0, 30.0, 30.0, 30.0),
)


@dataclasses.dataclass(frozen=True)
class RGBDConfig:
    """Static, hashable settings of the RGB-D box filter (changing one recompiles)."""

    variant: str = "grid-occlusion"
    n_particles: int = 300
    grid: int = 2  # k of the grid variants ("rgbd" always uses one cell)
    bins: tuple[int, ...] = COLOUR_BINS  # colour bins, as in ColourConfig
    depth_bins: int = 64  # log-spaced depth bins for the per-cell median
    depth_range: tuple[float, float] = (400.0, 10000.0)  # mm
    model: str = "ar1"
    hierarchical: bool = True
    resampler: str = "systematic"
    ess_threshold: float = 1.0
    min_size: float = 8.0
    init_spread: float = 0.0
    window: tuple[int, int] | None = None
    tau_height: float | None = 200.0
    aspect_prior: bool = True
    template_update: bool = True
    background_update: bool = False  # running background update on background pixels
    flag_transition: str = "auto"
    max_full_cells: int = 6  # "auto": the full 2^C matrix up to this many cells
    report: str = "pixels"
    min_depth_count: int = 8  # fewer foreground depth samples: the depth terms are skipped
    # Share of particles re-drawn, while the target is voted occluded, around random
    # foreground pixels at the target's depth (data-driven search; 0: spreading only).
    recovery_fraction: float = 0.2
    recovery_stride: int = 4  # the pixel search runs on a grid of this stride
    # Data-driven proposal (module docstring): share of the particles whose position is
    # drawn around boxes full of foreground at the target's depth (0: motion prior only),
    # on a map of this stride (pixels).
    detector_fraction: float = 0.2
    detector_stride: int = 8
    # The detector also proposes box sizes: the estimate's width x exp(i * step_w) and
    # height x exp(j * step_h), |i| <= scales[0], |j| <= scales[1] (a geometric grid whose
    # cells tile log-size; 0, 0: the estimate's size only, jittered within one step).
    detector_scales: tuple[int, int] = (2, 3)
    detector_scale_step: tuple[float, float] = (0.15, 0.12)
    colour: ColourConfig | None = None  # the "rgb" variant's colour filter (None: default)
    # Background pixels count as one extra colour bin: the histogram of the paper's
    # "preprocessed foreground RGB image" (background blacked out), so the colour term
    # also sees how much of a cell is foreground. False: foreground pixels only.
    background_bin: bool = True
    # Grid variants: also score the foreground ratio of the whole box (pooled over the
    # cells voted visible, for every flag state of the full transition form) with the
    # one-cell Beta fit. Per-cell ratios alone do not pin the scale (see docstring).
    box_term: bool = True
    # Border strips (thickness as a fraction of the box size; 0: off): inside each edge
    # of a tight box there is foreground, just outside there is none at the target's
    # depth. Their ratios have fitted Betas too; they pin the box's scale (see docstring).
    border: float = 0.1
    # Whole-body colour term ("Body colour" in the module docstring): the foreground
    # colour histogram of the visible cells pooled, against one slowly learnt template of
    # the whole person (the cells' templates describe the first box's layout only).
    body_term: bool = True
    # Cap the fast-motion component's length by the initial box's height at the target's
    # depth (``fast_length``). None: on for "grid-occlusion" only, whose depth templates
    # learn only in cells voted visible; on the IST recording the cap cost "grid" (whose
    # templates drift onto occluders, so the cap follows a wrong depth) 10 AUC points.
    fast_depth_cap: bool | None = None

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.n_particles < 1:
            raise ValueError(f"n_particles must be >= 1, got {self.n_particles}")
        if self.grid < 1:
            raise ValueError(f"grid must be >= 1, got {self.grid}")
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.resampler not in rs.SCHEMES:
            raise ValueError(
                f"resampler must be one of {tuple(rs.SCHEMES)}, got {self.resampler!r}"
            )
        if self.flag_transition not in TRANSITIONS:
            raise ValueError(
                f"flag_transition must be one of {TRANSITIONS}, got {self.flag_transition!r}"
            )
        if self.report not in REPORTS:
            raise ValueError(f"report must be one of {REPORTS}, got {self.report!r}")
        if self.flag_transition == "full" and self.n_cells > 16:
            raise ValueError(
                f"a full 2^C transition matrix needs C <= 16 cells, got {self.n_cells}"
            )
        if not 0.0 <= self.detector_fraction < 1.0:
            raise ValueError(f"detector_fraction must be in [0, 1), got {self.detector_fraction}")
        if self.detector_stride < 1:
            raise ValueError(f"detector_stride must be >= 1, got {self.detector_stride}")
        if min(self.detector_scales) < 0 or min(self.detector_scale_step) <= 0:
            raise ValueError(
                "detector_scales must be >= 0 and detector_scale_step > 0, got "
                f"{self.detector_scales}, {self.detector_scale_step}"
            )
        if self.n_cells > 30:
            raise ValueError(f"at most 30 cells (flags are int32 bit masks), got {self.n_cells}")
        lo, hi = self.depth_range
        if not 0 < lo < hi:
            raise ValueError(f"depth_range must be 0 < near < far, got {self.depth_range}")

    @property
    def k(self) -> int:
        """Cells per side: 1 for "rgb"/"rgbd", ``grid`` for the grid variants."""
        return self.grid if self.variant in ("grid", "grid-occlusion") else 1

    @property
    def n_cells(self) -> int:
        return self.k * self.k

    @property
    def occlusion(self) -> bool:
        return self.variant == "grid-occlusion"

    @property
    def depth_cap(self) -> bool:
        """Whether the fast-motion length is capped by depth (``fast_depth_cap``)."""
        return self.occlusion if self.fast_depth_cap is None else self.fast_depth_cap

    @property
    def full_transition(self) -> bool:
        if self.flag_transition == "auto":
            return self.n_cells <= self.max_full_cells
        return self.flag_transition == "full"

    @property
    def n_bins(self) -> int:
        """Length of a cell's colour histogram (with the background bin)."""
        return n_bins_of(self.bins) + (1 if self.background_bin else 0)

    @property
    def n_fg_bins(self) -> int:
        """The colour bins of foreground pixels (``n_bins`` without the background bin)."""
        return n_bins_of(self.bins)

    @property
    def colour_config(self) -> ColourConfig:
        base = self.colour or ColourConfig(
            n_particles=self.n_particles, model=self.model, hierarchical=self.hierarchical
        )
        return dataclasses.replace(base, window=self.window) if self.window else base

    def with_window(
        self, box_wh: tuple[float, float], frame_hw: tuple[int, int], growth: float = 1.5
    ) -> RGBDConfig:
        """This config with a histogram window for a box of ``box_wh`` (as ColourConfig's)."""
        cc = self.colour_config.with_window(box_wh, frame_hw, growth)
        w, h = (float(v) * growth for v in box_wh)
        window = suggest_window((w, h), 10.0, (int(frame_hw[0]), int(frame_hw[1])))
        if self.variant == "rgb":
            window = cc.window
        return dataclasses.replace(self, window=window, colour=dataclasses.replace(cc))


class RGBDParams(NamedTuple):
    """Continuous parameters (a pytree; see PARAM_CONSTRAINTS)."""

    sigma_rgb: Array  # eq. 4 width on the Bhattacharyya distance
    colour_floor: Array  # lowest log-likelihood of a cell's colour term (robust)
    sigma_depth: Array  # mm, width of the median-depth Gaussian ...
    sigma_depth_rel: Array  # ... plus this fraction of the template depth
    depth_floor: Array  # lowest log-likelihood of the depth term (robust to stray pixels)
    beta_a: Array  # [C] eq. 2 shapes per cell
    beta_b: Array  # [C]
    beta_weight: Array  # weight of the Beta terms (1: the paper)
    beta_floor: Array  # lowest log-density of a cell's / the box's Beta term (robust)
    box_beta_a: Array  # Beta shapes of the whole box's (visible cells') foreground ratio
    box_beta_b: Array
    border_a: Array  # [8] Beta shapes of the border strips' ratios (inner t/b/l/r, outer t/b/l/r)
    border_b: Array  # [8]
    border_floor: Array  # lowest log-density of one border strip
    sigma_body: Array  # width of the body colour term on the Bhattacharyya distance ...
    body_ref: Array  # ... which scores 0 at this distance (and above it less than 0)
    body_floor: Array  # lowest log-likelihood of the body colour term
    body_min_pixels: Array  # fewer visible foreground pixels: the body term says nothing
    body_rate: Array  # 1 - lambda of the body template after the warm-up ...
    body_warmup: Array  # ... a running mean of the unoccluded frames among the first steps
    # Gain of the Beta means' shift towards the initial box's foreground fill (0: the
    # fitted shapes as they are; ``fill_adapted``) ...
    fill_adapt: Array
    # ... beyond this many logits from the fitted mean (one frame's fill varies with the gait)
    fill_deadzone: Array
    log_occluded: Array  # eq. 1's constant, log
    occluder_margin: Array  # mm: nearer than the template by more than this ...
    occluder_margin_rel: Array  # ... or this fraction of it counts as an occluder
    occluder_eps: Array  # floor of the occluder evidence (log eps: "nothing in front")
    occluder_unknown: Array  # occluder evidence of a cell with too few depth samples
    p_occlude: Array  # per-cell P(visible -> occluded) per frame
    p_reveal: Array  # per-cell P(occluded -> visible) per frame
    transition: Array | None  # optional full [2^C, 2^C] row-stochastic matrix (None: Kronecker)
    vote_threshold: Array  # a cell is voted occluded when its vote exceeds this
    template_rate: Array  # 1 - lambda of eq. 7 for colour templates
    template_gate: Array  # colour templates learn only from cells closer than this
    depth_rate: Array  # 1 - lambda of eq. 7 for depth templates
    depth_velocity_rate: Array  # gain of the depth-velocity update (0: templates do not move)
    depth_velocity_fade: Array  # share of the velocity lost per frame without depth update
    depth_speed: Array  # mm per frame a template's target may move while not updated
    spread_rate: Array  # extra position noise per occluded frame (x tau)
    spread_max: Array  # cap of the position-noise multiplier
    recovery_gate: Array  # re-draw around foreground pixels within this many mm ...
    recovery_gate_rel: Array  # ... or this fraction of the target's depth
    report_margin: Array  # report="pixels": search the estimate grown by this per side
    report_min_pixels: Array  # ... ignoring columns / rows with fewer target pixels
    report_gap: Array  # ... and those further than this share of the box from the main run
    min_coverage: Array  # grid-occlusion: fewer target pixels (share of the box): hidden
    max_drift: Array  # mm, cap of depth_speed * age
    search_drift_max: Array  # mm, cap of the widening of the target gate while hidden
    fast_fraction: Array  # motion model: share of the fast-motion component ...
    fast_sigma: Array  # ... a Gaussian of this sd (fraction of the box height) around the mean
    fast_scale: Array  # ... and log-normal sizes of this log-sd around the predicted size
    detector_ring: Array  # detector: ring around a box (fraction of its size) that should be empty
    detector_min_ratio: Array  # detector: least share of target-depth foreground in a box,
    # relative to the best box near the prediction ...
    detector_floor: Array  # ... and absolute
    detector_need: Array  # detector draws only when the prediction's share is below this x best
    detector_power: Array  # detector: proposal density ~ ratio ** power x locality
    aspect_mean: Array  # log-normal prior on width / height (config.aspect_prior)
    aspect_sigma: Array
    tau: Array  # [8] motion noise (dynamics)
    # Share of the size velocities kept per frame (1: the plain AR model's random walk)
    size_velocity_decay: Array
    motion: MotionParams
    fg_depth_abs: Array  # foreground threshold, mm
    fg_depth_rel: Array  # foreground threshold, fraction of the background depth
    fg_colour: Array  # foreground threshold where depth is missing (uint8 levels)
    background_rate: Array  # running background update rate (config.background_update)
    colour: ColourParams  # the "rgb" variant's parameters


PARAM_CONSTRAINTS = RGBDParams(
    sigma_rgb="softplus",
    colour_floor="identity",
    sigma_depth="softplus",
    sigma_depth_rel="softplus",
    depth_floor="identity",
    beta_a="softplus",
    beta_b="softplus",
    beta_weight="softplus",
    beta_floor="identity",
    box_beta_a="softplus",
    box_beta_b="softplus",
    border_a="softplus",
    border_b="softplus",
    border_floor="identity",
    sigma_body="softplus",
    body_ref="softplus",
    body_floor="identity",
    body_min_pixels="softplus",
    body_rate="sigmoid",
    body_warmup="softplus",
    fill_adapt="softplus",
    fill_deadzone="softplus",
    log_occluded="identity",
    occluder_margin="softplus",
    occluder_margin_rel="softplus",
    occluder_eps="sigmoid",
    occluder_unknown="sigmoid",
    p_occlude="sigmoid",
    p_reveal="sigmoid",
    transition=None,
    vote_threshold="sigmoid",
    template_rate="sigmoid",
    template_gate="sigmoid",
    depth_rate="sigmoid",
    depth_velocity_rate="sigmoid",
    depth_velocity_fade="sigmoid",
    depth_speed="softplus",
    spread_rate="softplus",
    spread_max="softplus",
    recovery_gate="softplus",
    recovery_gate_rel="softplus",
    report_margin="softplus",
    report_min_pixels="softplus",
    report_gap="softplus",
    min_coverage="sigmoid",
    max_drift="softplus",
    search_drift_max="softplus",
    fast_fraction="sigmoid",
    fast_sigma="softplus",
    fast_scale="softplus",
    detector_ring="softplus",
    detector_min_ratio="sigmoid",
    detector_floor="sigmoid",
    detector_need="sigmoid",
    detector_power="softplus",
    aspect_mean="softplus",
    aspect_sigma="softplus",
    tau="softplus",
    size_velocity_decay="sigmoid",
    motion=MOTION_CONSTRAINTS,
    fg_depth_abs="softplus",
    fg_depth_rel="softplus",
    fg_colour="softplus",
    background_rate="sigmoid",
    colour=None,  # see cpf_jax.colour.PARAM_CONSTRAINTS
)


def default_rgbd_params(config: RGBDConfig | None = None) -> RGBDParams:
    """Hand-set defaults (and the fitted Beta shapes of ``DEFAULT_BETA`` for the grid size)."""
    config = config or RGBDConfig()
    f = jnp.float32
    c = config.n_cells
    if config.k in DEFAULT_BETA and len(DEFAULT_BETA[config.k][0]) == c:
        a, b = DEFAULT_BETA[config.k]
    else:
        a, b = (BETA_FALLBACK[0],) * c, (BETA_FALLBACK[1],) * c
    return RGBDParams(
        # A view change of the same person (front / back, blur) moves a cell's histogram
        # by d ~ 0.3; with 0.08 that alone costs 7 nats and most cells sat on the colour
        # floor, so the colour term was a step (and beat eq. 1's occluded constant by
        # chance). 0.2 makes d ~ 0.3 cost about 1 nat; synthetic occlusion MOTA holds.
        sigma_rgb=f(0.2),
        colour_floor=f(-12.0),
        sigma_depth=f(100.0),
        sigma_depth_rel=f(0.05),
        depth_floor=f(-8.0),
        beta_a=jnp.asarray(a, jnp.float32),
        beta_b=jnp.asarray(b, jnp.float32),
        beta_weight=f(1.0),
        beta_floor=f(-10.0),
        box_beta_a=f(DEFAULT_BETA[1][0][0]),
        box_beta_b=f(DEFAULT_BETA[1][1][0]),
        border_a=jnp.asarray(DEFAULT_BORDER_BETA[0], jnp.float32),
        border_b=jnp.asarray(DEFAULT_BORDER_BETA[1], jnp.float32),
        border_floor=f(-6.0),
        sigma_body=f(0.2),
        body_ref=f(0.4),
        body_floor=f(-6.0),
        body_min_pixels=f(30.0),
        body_rate=f(0.02),
        body_warmup=f(5.0),
        fill_adapt=f(1.0),
        # 1.5 standard deviations of the logit of the whole-box Beta (3.52, 7.89): the
        # first frames of the synthetic walkers fill 0.36-0.56 of their boxes (their whole
        # walks 0.30-0.53, the fitted mean 0.31) and move nothing. A background model that
        # holds the standing walker (a median over walk_towards' own frames) sees 0.06-0.12
        # and moves the means down by up to 1 logit.
        fill_deadzone=f(1.0),
        log_occluded=f(-10.0),
        occluder_margin=f(400.0),
        occluder_margin_rel=f(0.12),
        occluder_eps=f(1e-4),
        occluder_unknown=f(0.3),
        p_occlude=f(0.1),
        p_reveal=f(0.1),
        transition=None,
        vote_threshold=f(0.5),
        template_rate=f(0.02),
        template_gate=f(0.4),
        depth_rate=f(0.5),
        depth_velocity_rate=f(0.2),
        # A hidden person may stop or turn round: with 0.05 the templates keep walking
        # away for 20 hidden frames (occlusion_return). Training seeds 100-103, MOTA
        # occlusion / occlusion_return: 0.05 78.9 / 52.2, 0.2 87.1 / 76.8,
        # 0.3 86.8 / 81.3, 0.5 85.0 / 81.8 (one key per seed). 0.05 stayed for a while
        # because 0.3 lost evaluation seed 0 of occlusion_person with one key; over 4
        # keys per seed it does not (all 8 occlusion_person runs MOTA >= 96), and with
        # the stale-template gate (search_drift) grid-occlusion MOTA on occlusion_box +
        # occlusion_person (seeds 0-1 x 4 keys) is 0.05 93.3 / 0.3 96.0 (95.0 / 96.9
        # per scene), IST AUC 26.8 / 33.7 (4 keys).
        depth_velocity_fade=f(0.3),
        depth_speed=f(60.0),
        spread_rate=f(0.15),
        spread_max=f(3.0),
        recovery_gate=f(300.0),
        recovery_gate_rel=f(0.1),
        report_margin=f(0.25),
        report_min_pixels=f(2.0),
        report_gap=f(0.3),
        min_coverage=f(0.02),
        max_drift=f(500.0),
        search_drift_max=f(900.0),
        fast_fraction=f(0.05),
        fast_sigma=f(0.5),
        fast_scale=f(0.2),
        detector_ring=f(0.15),
        detector_min_ratio=f(0.6),
        detector_floor=f(0.1),
        detector_need=f(0.9),
        detector_power=f(4.0),
        aspect_mean=f(0.41),
        aspect_sigma=f(0.3),
        tau=jnp.asarray(RGBD_TAU, jnp.float32),
        size_velocity_decay=f(0.9),
        motion=default_motion_params(),
        fg_depth_abs=f(150.0),
        fg_depth_rel=f(0.05),
        fg_colour=f(40.0),
        background_rate=f(0.02),
        colour=default_colour_params(),
    )


class RGBDState(NamedTuple):
    particles: Array  # [N, 8] (cx, cy, vx, vy, w, h, vw, vh)
    previous: Array  # [N, 8]
    log_weights: Array  # [N] normalised
    flags: Array  # [N] int32 bit masks (bit i = cell i occluded)
    colour_template: Array  # [C, B] normalised histograms of the cells' foreground
    depth_template: Array  # [C] mm, 0 = unknown
    depth_age: Array  # [C] frames since each depth template was last updated
    depth_velocity: Array  # mm per frame, the target's estimated motion in depth
    vote: Array  # [C] occlusion votes of the last frame
    occluded_frames: Array  # int32, consecutive frames with the target voted occluded
    visible_size: Array  # [2] (w, h) of the last estimate with no cell voted occluded
    estimate: Array  # [4] xywh
    background: Background
    # px * mm: the initial box's height times its depth (0: unknown). reach / depth is
    # the height in pixels the initial view of the target has at that depth.
    reach: Array
    # mm: median depth of the last occluder seen in front of the target (0: none yet).
    # Pixels at its depth are not the target, however wide the stale-template gate.
    occluder_depth: Array
    # Logit shift of the Beta means towards the initial box's foreground fill
    # (``fill_adapted``; 0 without a background model).
    fill_shift: Array
    # [B - 1] normalised foreground colour histogram of the whole target (``body_term``),
    # the unoccluded frames it has learnt from and the steps since ``init``.
    body_template: Array
    body_frames: Array
    body_steps: Array


class RGBDInfo(NamedTuple):
    estimate: Array  # [4] xywh, weighted mean of the particles (the whole-body box)
    report: Array  # [4] xywh, the box to score (see the module docstring)
    lost: Array  # bool: no box is reported this frame
    ess: Array
    log_likelihood: Array  # log mean likelihood of the propagated particles
    vote: Array  # [C] posterior probability that each cell is occluded
    target_occluded: Array  # bool: more than half of the cells voted occluded
    resampled: Array
    weights_invalid: Array
    # bool: the particles' histograms came from the static window (config.window);
    # False when there is none or the exact whole-frame fallback ran (slower).
    windowed: Array


# ----------------------------------------------------------------------------- flags


def _flag_bits_np(n_cells: int) -> np.ndarray:
    s = np.arange(1 << n_cells)[:, None]
    return ((s >> np.arange(n_cells)[None]) & 1).astype(np.float32)


def flag_bits(n_cells: int) -> Array:
    """``[2^C, C] float32``: bit ``i`` of every flag state (state index = bit mask)."""
    return jnp.asarray(_flag_bits_np(n_cells))


def kronecker_transition(p_occlude: Array, p_reveal: Array, n_cells: int) -> Array:
    """Full ``[2^C, 2^C]`` matrix of independent per-cell chains (rows: from, columns: to).

    ``p_occlude`` / ``p_reveal`` are scalars or ``[C]``; ``T[s, z] = prod_i
    P(z_i | s_i)``: the factorised model written as the paper's full matrix.
    """
    bits = flag_bits(n_cells)  # [S, C]
    po = jnp.broadcast_to(jnp.asarray(p_occlude, jnp.float32), (n_cells,))
    pr = jnp.broadcast_to(jnp.asarray(p_reveal, jnp.float32), (n_cells,))
    s = bits[:, None, :]
    z = bits[None, :, :]
    p1 = jnp.where(s > 0, 1.0 - pr, po)  # P(z_i = 1 | s_i)
    return jnp.prod(jnp.where(z > 0, p1, 1.0 - p1), axis=-1)


def _log_clip(p: Array) -> Array:
    # log with log(0) = -inf (an impossible transition), and no NaN gradient at 0.
    pos = p > 0
    return jnp.where(pos, jnp.log(jnp.where(pos, jnp.minimum(p, 1.0), 1.0)), -jnp.inf)


def _flag_posterior(
    config: RGBDConfig,
    params: RGBDParams,
    key: Array,
    prev: Array,
    l_vis: Array,
    l_occ: Array,
    l_box: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Marginal log-likelihood ``[N]``, new flags ``[N] int32``, per-cell ``P(z_i=1) [N, C]``.

    ``l_box [N, 2^C]`` (full form only): an extra log-likelihood per flag state.
    """
    n, c = l_vis.shape
    if config.full_transition:
        bits = flag_bits(c)  # [S, C]
        if params.transition is None:
            trans = kronecker_transition(params.p_occlude, params.p_reveal, c)
        else:
            trans = jnp.asarray(params.transition, jnp.float32)
        log_t = _log_clip(trans)[prev]  # [N, S]
        joint = log_t + jnp.sum(l_vis, -1, keepdims=True) + (l_occ - l_vis) @ bits.T
        if l_box is not None:
            joint = joint + l_box
        log_lik = jax.nn.logsumexp(joint, axis=-1)
        post = jnp.exp(joint - log_lik[:, None])  # [N, S]
        new = jax.random.categorical(key, joint, axis=-1).astype(jnp.int32)
        p_cell = post @ bits
        return log_lik, new, p_cell
    prev_bits = ((prev[:, None] >> jnp.arange(c)) & 1).astype(bool)  # [N, C]
    po = jnp.broadcast_to(jnp.asarray(params.p_occlude, jnp.float32), (c,))
    pr = jnp.broadcast_to(jnp.asarray(params.p_reveal, jnp.float32), (c,))
    p1 = jnp.where(prev_bits, 1.0 - pr, po)
    a0 = _log_clip(1.0 - p1) + l_vis
    a1 = _log_clip(p1) + l_occ
    lse = jnp.logaddexp(a0, a1)
    p_cell = jnp.exp(a1 - lse)
    draw = jax.random.uniform(key, (n, c)) < p_cell
    new = jnp.sum(draw.astype(jnp.int32) << jnp.arange(c), axis=-1).astype(jnp.int32)
    return jnp.sum(lse, axis=-1), new, p_cell


# ----------------------------------------------------------------------------- pieces


def _to_xywh(particles: Array) -> Array:
    return box_ops.cxcywh_to_xywh(particles[..., jnp.array([0, 1, 4, 5])])


def _normalise(h: Array) -> Array:
    return h / jnp.maximum(jnp.sum(h, axis=-1, keepdims=True), 1.0)


def _clipped_area(rects: Array, width: int, height: int) -> Array:
    r = box_ops.clip_rect(rects, width, height)
    return ((r[..., 2] - r[..., 0]) * (r[..., 3] - r[..., 1])).astype(jnp.float32)


def _no_background(frame: Frame) -> Background:
    # Without a background model every pixel is foreground (colour differs from -1000).
    h, w = frame.colour.shape[:2]
    return Background(jnp.full((h, w, 3), -1000.0, jnp.float32), jnp.zeros((h, w), jnp.float32))


class _Observation(NamedTuple):
    colour_bins: Array  # [H, W] int32; background: the extra bin (or -1)
    depth_bins: Array  # [H, W] int32, -1 off the foreground or without depth
    foreground: Array  # [H, W] bool


def _observe(config: RGBDConfig, params: RGBDParams, frame: Frame, bg: Background) -> _Observation:
    fg = foreground_mask(
        frame.colour,
        frame.depth,
        bg,
        depth_abs=params.fg_depth_abs,
        depth_rel=params.fg_depth_rel,
        colour_threshold=params.fg_colour,
    )
    off = n_bins_of(config.bins) if config.background_bin else -1
    cbins = jnp.where(fg, bin_index(frame.colour, config.bins), off)
    dbins = depth_bin_index(frame.depth, fg, config.depth_bins, *config.depth_range)
    return _Observation(cbins, dbins, fg)


def _cell_templates(
    config: RGBDConfig, obs: _Observation, box_xywh: Array
) -> tuple[Array, Array, Array]:
    """Colour histograms ``[C, B]`` (normalised), median depths ``[C]`` and depth counts ``[C]``."""
    rects = box_ops.xywh_to_rect(grid_cells(box_xywh, config.k))
    hist = box_histograms(obs.colour_bins, rects, config.n_bins)
    dh = box_histograms(obs.depth_bins, rects, config.depth_bins)
    med, total = histogram_quantile(dh, config.depth_bins, *config.depth_range)
    return _normalise(hist), med, total


class CellTerms(NamedTuple):
    """Per-cell pieces of the likelihood for ``N`` boxes (all ``[N, C]``)."""

    l_vis: Array  # log-likelihood if visible: beta + colour + depth
    l_occ: Array  # log-likelihood if occluded (eq. 1 constant + depth ordering)
    l_beta: Array
    l_colour: Array
    l_depth: Array
    ratio: Array  # foreground ratio
    distance: Array  # Bhattacharyya distance to the colour template
    median_depth: Array  # mm (0: no foreground depth)
    occluder: Array  # occluder evidence e_i
    fg_count: Array
    area: Array  # pixels of the cell inside the frame
    l_border: Array  # [N, 8] Beta log-densities of the border strips (inner t/b/l/r, outer)
    border_ratio: Array  # [N, 8] their ratios
    # [N, S] body colour term per flag state (``body_states``; zeros without a template)
    l_body: Array
    # bool []: every rect was counted in the static window (False: no window, or
    # the exact whole-frame fallback ran).
    windowed: Array


def cell_terms(
    config: RGBDConfig,
    params: RGBDParams,
    colour_template: Array,
    depth_template: Array,
    obs: _Observation,
    boxes_xywh: Array,
    depth_age: Array | None = None,
    body_template: Array | None = None,
) -> CellTerms:
    """The per-cell likelihood terms of ``boxes_xywh [N, 4]`` (module docstring).

    ``depth_age [C]``: frames since each depth template was last updated; the
    target may have moved ``depth_speed`` mm per frame since, which widens the
    depth Gaussian and the occluder margin (None: fresh templates).
    ``body_template [B - 1]``: the whole-body colour template; ``l_body [N, S]`` scores
    the foreground of the cells visible in each flag state of ``body_states`` (None:
    zeros).
    """
    height, width = obs.foreground.shape
    nz, zlo, zhi = config.depth_bins, *config.depth_range
    rects = box_ops.xywh_to_rect(grid_cells(boxes_xywh, config.k))  # [N, C, 4]
    sqrt_q = jnp.sqrt(colour_template)  # [C, B]
    mu = depth_template  # [C]
    drift = (
        0.0 if depth_age is None else jnp.minimum(params.depth_speed * depth_age, params.max_drift)
    )
    margin = occluder_margin(params, mu) + drift
    near_thr = mu - margin
    area = _clipped_area(rects, width, height)

    vis_states = body_states(config)  # [S, C]
    n_states = vis_states.shape[0]

    def colour_stats(counts: Array) -> Array:  # [m, C, B] -> [m, C, 3 (+ S)]
        total = jnp.sum(counts, axis=-1)
        bc = jnp.sum(jnp.sqrt(counts) * sqrt_q, axis=-1) * jax.lax.rsqrt(jnp.maximum(total, 1.0))
        d2 = jnp.where(total > 0, jnp.clip(1.0 - bc, 0.0, 1.0), 1.0)
        out = jnp.stack([total, d2, counts[..., -1]], axis=-1)
        if body_template is None:
            return out
        # Pooled inside the reduction, so the [N, C, B] counts never exist at once.
        l_body = body_log_likelihood(params, body_template, counts, vis_states, config)
        return jnp.concatenate(
            [out, jnp.broadcast_to(l_body[:, None, :], (*out.shape[:2], n_states))], axis=-1
        )

    def depth_stats(counts: Array) -> Array:  # [m, C, Z] -> [m, C, 3]
        med, total = histogram_quantile(counts, nz, zlo, zhi)
        near = histogram_fraction_below(counts, near_thr, nz, zlo, zhi)
        return jnp.stack([med, total, near], axis=-1)

    cs = rect_reduce(
        obs.colour_bins, rects, colour_stats, n_bins=config.n_bins, window=config.window
    )
    ds = rect_reduce(obs.depth_bins, rects, depth_stats, n_bins=nz, window=config.window)
    if config.border > 0:
        # The strips need two counts each, not histograms: the foreground (inner strips)
        # and the foreground at the target's depth or farther (outer strips: a nearer
        # occluder beside the box is not the target), from one summed-area table. Counted
        # with the cells' histograms instead, they were 12 rects a particle, not 4, and
        # half the step's time (experiments/bench_rgbd.py).
        have = mu > 0
        mu_box = jnp.sum(jnp.where(have, mu, 0.0)) / jnp.maximum(jnp.sum(have), 1)
        margin_box = jnp.sum(jnp.where(have, margin, 0.0)) / jnp.maximum(jnp.sum(have), 1)
        n_fg = config.n_fg_bins
        table, frac = strip_table(
            obs.colour_bins, n_fg, obs.depth_bins, mu_box - margin_box, nz, zlo, zhi
        )
        strips = box_ops.xywh_to_rect(border_strips(boxes_xywh, config.border))  # [N, 8, 4]
        fg_strip, far_strip = strip_counts(table, frac, strips)
        area_strip = _clipped_area(strips, width, height)
        counted = jnp.concatenate([fg_strip[:, :4], far_strip[:, 4:]], axis=-1)
        strip_ratio = jnp.where(area_strip > 0, counted / jnp.maximum(area_strip, 1.0), 0.0)
        l_border = params.beta_weight * beta_log_density(
            strip_ratio, params.border_a, params.border_b
        )
        # A strip that lies wholly outside the frame says nothing; a floor keeps one
        # bad strip from outweighing everything else (robust, like the other terms).
        l_border = jnp.where(area_strip > 0, jnp.maximum(l_border, params.border_floor), 0.0)
    else:
        strip_ratio = jnp.zeros((boxes_xywh.shape[0], 8), jnp.float32)
        l_border = jnp.zeros_like(strip_ratio)
    fg_count = cs[..., 0] - (cs[..., 2] if config.background_bin else 0.0)
    ratio = jnp.where(area > 0, fg_count / jnp.maximum(area, 1.0), 0.0)
    d2 = cs[..., 1]
    l_body = (
        jnp.zeros((boxes_xywh.shape[0], n_states), jnp.float32)
        if body_template is None
        else cs[:, 0, 3:]
    )
    med, n_depth, near = ds[..., 0], ds[..., 1], ds[..., 2]

    l_beta = jnp.maximum(
        params.beta_weight * beta_log_density(ratio, params.beta_a, params.beta_b),
        params.beta_floor,
    )
    l_col = jnp.maximum(-d2 / (2.0 * params.sigma_rgb**2), params.colour_floor)
    has_depth = (n_depth >= config.min_depth_count) & (mu > 0)
    sd = jnp.sqrt((params.sigma_depth + params.sigma_depth_rel * mu) ** 2 + drift**2)
    l_dep = jnp.where(
        has_depth, jnp.maximum(-0.5 * ((med - mu) / sd) ** 2, params.depth_floor), 0.0
    )
    evidence = jnp.where(has_depth, near, params.occluder_unknown) * ratio
    eps = params.occluder_eps
    l_occ = params.log_occluded + jnp.log(eps + (1.0 - eps) * evidence)
    return CellTerms(
        l_vis=l_beta + l_col + l_dep,
        l_occ=l_occ,
        l_beta=l_beta,
        l_colour=l_col,
        l_depth=l_dep,
        ratio=ratio,
        distance=jnp.sqrt(d2),
        median_depth=jnp.where(n_depth > 0, med, 0.0),
        occluder=evidence,
        fg_count=fg_count,
        area=area,
        l_border=l_border,
        border_ratio=strip_ratio,
        l_body=l_body,
        windowed=uses_window((height, width), rects, config.window),
    )


def body_states(config: RGBDConfig) -> np.ndarray:
    """``[S, C]`` visibility (1: visible; static) of the cells in each state the body term
    scores: every flag state of the full transition form (state ``s`` has cell ``i``
    occluded when bit ``i`` of ``s`` is set, as ``flag_bits``), else one state with every
    cell visible."""
    if config.occlusion and config.full_transition:
        return 1.0 - _flag_bits_np(config.n_cells)
    return np.ones((1, config.n_cells), np.float32)


def body_log_likelihood(
    params: RGBDParams, template: Array, counts: Array, vis: np.ndarray, config: RGBDConfig
) -> Array:
    """Body colour term ``[m, S]`` of cell colour counts ``[m, C, B]`` (module docstring).

    For each state ``s`` of ``vis [S, C]`` (static 0/1) the foreground counts of its
    visible cells are pooled and compared with ``template [B - 1]`` (normalised):
    ``max(-(d^2 - body_ref^2) / (2 sigma_body^2), body_floor)``; a state with fewer than
    ``body_min_pixels`` visible foreground pixels scores 0.
    """
    n_fg = config.n_fg_bins
    fg = counts[..., :n_fg]  # [m, C, F]
    # The double where keeps gradients (tuning through the template's learning) finite.
    sqrt_t = jnp.where(template > 0, jnp.sqrt(jnp.where(template > 0, template, 1.0)), 0.0)
    vis = np.asarray(vis)
    if len(vis) <= 64:
        # One fused sum per state over its visible cells, unrolled: 3x faster on a CPU
        # than one einsum over every state (20 against 61 ms for 10,000 boxes of 2 x 2
        # cells), which lays out an [m, S, F] tensor first.
        bcs, totals = [], []
        for row in vis:
            cells = [fg[:, i] for i in np.flatnonzero(row)]
            pooled = sum(cells[1:], cells[0]) if cells else jnp.zeros_like(fg[:, 0])
            totals.append(jnp.sum(pooled, axis=-1))
            bcs.append(jnp.sum(jnp.sqrt(pooled) * sqrt_t, axis=-1))
        total, bc = jnp.stack(totals, axis=-1), jnp.stack(bcs, axis=-1)  # [m, S]
    else:  # a full transition over many cells: not unrolled
        pooled = jnp.einsum("sc,mcf->msf", vis, fg)
        total = jnp.sum(pooled, axis=-1)
        bc = jnp.sum(jnp.sqrt(pooled) * sqrt_t, axis=-1)
    bc = bc * jax.lax.rsqrt(jnp.maximum(total, 1.0))
    d2 = jnp.clip(1.0 - bc, 0.0, 1.0)
    l_body = jnp.maximum(
        -(d2 - params.body_ref**2) / (2.0 * params.sigma_body**2), params.body_floor
    )
    return jnp.where(total >= params.body_min_pixels, l_body, 0.0)


def body_histogram(config: RGBDConfig, obs: _Observation, box_xywh: Array) -> tuple[Array, Array]:
    """Normalised foreground colour histogram ``[B - 1]`` of one box and its pixel count."""
    rect = box_ops.xywh_to_rect(box_xywh)[None]
    hist = box_histograms(obs.colour_bins, rect, config.n_bins)[0]
    n_fg = config.n_fg_bins
    fg = hist[:n_fg]
    total = jnp.sum(fg)
    return fg / jnp.maximum(total, 1.0), total


def box_log_density(params: RGBDParams, fg_sum: Array, area_sum: Array) -> Array:
    """Whole-box Beta term of a pooled foreground count / area (0 for an empty area)."""
    ratio = jnp.where(area_sum > 0, fg_sum / jnp.maximum(area_sum, 1.0), 0.0)
    lp = beta_log_density(ratio, params.box_beta_a, params.box_beta_b)
    return jnp.where(area_sum > 0, jnp.maximum(params.beta_weight * lp, params.beta_floor), 0.0)


def initial_fill(foreground: Array, box_xywh: Array) -> Array:
    """Share of foreground pixels in ``box_xywh`` (clipped to the frame; 0 for an empty box):
    the one-cell ``cell_foreground_ratios`` of one frame."""
    box = jnp.asarray(box_xywh, jnp.float32)
    return cell_foreground_ratios(foreground[None], box[None], 1)[0, 0]


def beta_fill_shift(params: RGBDParams, fill: Array) -> Array:
    """Logit shift of the Beta means towards an initial box's foreground ``fill``.

    ``fill_adapt * sign(g) * max(|g| - fill_deadzone, 0)`` with ``g = logit(fill) -
    logit(m)``, ``m`` the whole-box Beta's mean: a fill the fitted Beta explains (within
    the dead zone) moves nothing, and one beyond it moves the means by the excess.
    ``fill`` is clipped to ``[FILL_CLIP, 1 - FILL_CLIP]``; 0 when ``fill`` is 0 (no
    foreground in the initial box: nothing to learn from).
    """
    prior = params.box_beta_a / (params.box_beta_a + params.box_beta_b)
    f = jnp.clip(fill, FILL_CLIP, 1.0 - FILL_CLIP)
    gap = jax.scipy.special.logit(f) - jax.scipy.special.logit(prior)
    excess = jnp.sign(gap) * jnp.maximum(jnp.abs(gap) - params.fill_deadzone, 0.0)
    return jnp.where(fill > 0, params.fill_adapt * excess, 0.0)


def fill_adapted(params: RGBDParams, shift: Array) -> RGBDParams:
    """``params`` with the cells', the whole box's and the inner border strips' Beta means
    moved by ``shift`` in logit space, each Beta's concentration ``a + b`` kept.

    The shapes were fitted on synthetic walkers, whose limbs fill about a third of their
    tight box; a real person seen from the front, the back or above fills 60-90 % (the
    IST recording: 0.69 over its unoccluded frames), and with the fitted means a box
    twice the person's width scored best there. The initial box is a ground-truth box,
    so its fill says which the target is (module docstring, "Foreground fill").
    """

    def moved(a: Array, b: Array, on: Array | bool = True) -> tuple[Array, Array]:
        k = a + b
        m = jax.nn.sigmoid(jax.scipy.special.logit(a / k) + jnp.where(on, shift, 0.0))
        # No shift keeps the shapes bit for bit (the round trip through the logit does not).
        same = (shift == 0.0) | ~jnp.asarray(on)
        return jnp.where(same, a, m * k), jnp.where(same, b, (1.0 - m) * k)

    beta_a, beta_b = moved(params.beta_a, params.beta_b)
    box_a, box_b = moved(params.box_beta_a, params.box_beta_b)
    inner = jnp.arange(params.border_a.shape[-1]) < 4  # inner t/b/l/r; outer strips stay empty
    border_a, border_b = moved(params.border_a, params.border_b, inner)
    return params._replace(
        beta_a=beta_a,
        beta_b=beta_b,
        box_beta_a=box_a,
        box_beta_b=box_b,
        border_a=border_a,
        border_b=border_b,
    )


# ----------------------------------------------------------------------------- proposal


def _gauss2_log_density(d: Array, cxx: Array, cxy: Array, cyy: Array) -> Array:
    """``log N(d; 0, [[cxx, cxy], [cxy, cyy]])`` for offsets ``d [N, 2]`` (covariances ``[N]``)."""
    det = jnp.maximum(cxx * cyy - cxy * cxy, 1e-12)
    quad = (cyy * d[:, 0] ** 2 - 2.0 * cxy * d[:, 0] * d[:, 1] + cxx * d[:, 1] ** 2) / det
    return -jnp.log(2.0 * jnp.pi) - 0.5 * jnp.log(det) - 0.5 * quad


def motion_position_log_density(
    config: RGBDConfig,
    params: RGBDParams,
    ancestors: Array,
    mean_xy: Array,
    xy: Array,
    scale: Array | None,
    extra: Array | float = 0.0,
) -> Array:
    """``log p(xy | ancestor) [N]`` of the box centre drawn by ``dynamics.propagate``.

    ``mean_xy [N, 2]``: the noise-free prediction; ``scale [N]`` the noise scale
    (``tau_height``), ``extra`` the occlusion spreading (extra isotropic noise of
    ``extra * tau``). The centre noise of every model is Gaussian; with the
    hierarchical proposal (``ar1`` models) it is the mixture of the plain one and
    the guided one, stretched along the ancestor's velocity (``dynamics``).
    """
    sx = params.tau[0] * (1.0 if scale is None else scale)
    sy = params.tau[1] * (1.0 if scale is None else scale)
    sx = jnp.broadcast_to(sx, xy.shape[:1])
    sy = jnp.broadcast_to(sy, xy.shape[:1])
    e2 = jnp.asarray(extra, jnp.float32) ** 2
    d = xy - mean_xy
    zero = jnp.zeros_like(sx)
    plain = _gauss2_log_density(d, sx**2 * (1.0 + e2), zero, sy**2 * (1.0 + e2))
    if not (config.hierarchical and config.model in ("ar1", "ar1_fixed")):
        return plain
    m = params.motion
    ex, ey, stretch = guide_frame(ancestors[:, 2], ancestors[:, 3], m)
    va, vc = (sx * stretch) ** 2, (sy / stretch) ** 2  # along e, across (e_perp = (-ey, ex))
    cxx = va * ex * ex + vc * ey * ey + e2 * sx**2
    cyy = va * ey * ey + vc * ex * ex + e2 * sy**2
    cxy = (va - vc) * ex * ey
    guided = _gauss2_log_density(d, cxx, cxy, cyy)
    g = jnp.clip(m.guided_fraction, 0.0, 1.0)
    return jnp.logaddexp(_log_clip(1.0 - g) + plain, _log_clip(g) + guided)


#: Frames at which a cell's ``depth_age`` saturates. A cell with no depth template
#: counts as this stale in ``search_drift``: the widest gate, since ``depth_speed *
#: MAX_DEPTH_AGE`` (6000 mm at the defaults) exceeds ``search_drift_max`` (900 mm).
MAX_DEPTH_AGE = 100.0


def occluder_margin(params: RGBDParams, z: Array) -> Array:
    """How much nearer (mm) than depth ``z`` a pixel or cell median must be to count as
    an occluder: ``max(occluder_margin, occluder_margin_rel * z)``."""
    return jnp.maximum(params.occluder_margin, params.occluder_margin_rel * z)


def depth_tolerance(params: RGBDParams, z: Array) -> Array:
    """Depth tolerance (mm) of "a pixel at depth ``z``" for fresh templates:
    ``max(recovery_gate, recovery_gate_rel * z)``."""
    return jnp.maximum(params.recovery_gate, params.recovery_gate_rel * z)


def mean_known_depth(depth_template: Array) -> Array:
    """Mean of the known (``> 0``) entries of ``depth_template [..., C]`` (mm; 0: none)."""
    have = depth_template > 0
    total = jnp.sum(jnp.where(have, depth_template, 0.0), axis=-1)
    return total / jnp.maximum(jnp.sum(have, axis=-1), 1)


def fast_length(reach: Array, depth_template: Array, h: Array) -> Array:
    """Length (px) the fast-motion component's spread is a multiple of (module docstring).

    The box height ``h``, capped by ``reach / z``: the height the initial box has at the
    target's depth ``z`` (:func:`mean_known_depth`). No cap while ``reach`` or ``z`` is
    unknown (0). Broadcasts ``h`` against the scalar cap.
    """
    z = mean_known_depth(depth_template)
    cap = jnp.where((reach > 0) & (z > 0), reach / jnp.maximum(z, 1.0), jnp.inf)
    return jnp.minimum(h, cap)


def detector_scale_grid(config: RGBDConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(i [S], j [S]) int``: the detector's size steps (``S = (2 Jw + 1)(2 Jh + 1)``).

    Scale ``k`` is the box ``(W exp(i_k step_w), H exp(j_k step_h))`` for the reference
    size ``(W, H)`` (the estimate's); static.
    """
    jw, jh = config.detector_scales
    i, j = np.meshgrid(np.arange(-jw, jw + 1), np.arange(-jh, jh + 1), indexing="ij")
    return i.ravel(), j.ravel()


def detector_log_map(
    config: RGBDConfig,
    params: RGBDParams,
    target_pixels: Array,
    box_wh: Array,
    centre: Array,
    sigma: Array,
) -> tuple[Array, Array, Array]:
    """Log-density of the detector proposal over (size, cell) of a coarse map.

    ``target_pixels [H, W] bool``: foreground at the target's depth. For every size ``k``
    of :func:`detector_scale_grid` (around ``box_wh``) and every cell of the
    ``detector_stride`` map, a box of that size centred on the cell scores its
    *tightness* ``t = r (1 - r_ring)``: the share ``r`` of target pixels inside it, and
    the share ``r_ring`` in a ring ``detector_ring`` of its size wide around it (a box
    inside a body has a full ring; a box around a body plus background has a low
    ``r``). Shares count only the part inside the frame. The proposal is
    ``∝ t^detector_power x N(cell; centre, sigma^2) x N(log size step; 0, fast_scale^2)``
    over the pairs within ``3 sigma`` of ``centre`` with ``t >= max(detector_min_ratio *
    best t there, detector_floor)``. Returns the normalised log-probabilities ``[S * h *
    w]`` (index ``k * h * w + cell``; ``-inf`` off the support), whether the support is
    non-empty (when it is empty the log-probabilities are uniform and must not be used),
    and ``fit``: the tightness of the box of size ``box_wh`` at ``centre`` over the best
    one near it (1 when there is none).
    """
    s = config.detector_stride
    counts = coarse_counts(target_pixels, s) / float(s * s)  # [h, w] share per block
    ones = jnp.ones_like(counts)
    hh, ww = counts.shape
    si, sj = detector_scale_grid(config)
    step_w, step_h = config.detector_scale_step
    log_fw = jnp.asarray(si * step_w, jnp.float32)
    log_fh = jnp.asarray(sj * step_h, jnp.float32)
    bw = box_wh[0] * jnp.exp(log_fw)  # [S]
    bh = box_wh[1] * jnp.exp(log_fh)
    rx = jnp.round(bw / (2.0 * s)).astype(jnp.int32)
    ry = jnp.round(bh / (2.0 * s)).astype(jnp.int32)
    tx = jnp.maximum(jnp.round(params.detector_ring * bw / s), 1).astype(jnp.int32)
    ty = jnp.maximum(jnp.round(params.detector_ring * bh / s), 1).astype(jnp.int32)

    def tightness(ry, rx, ty, tx):
        inner, inner_area = window_sums(counts, ry, rx), window_sums(ones, ry, rx)
        outer, outer_area = (
            window_sums(counts, ry + ty, rx + tx),
            window_sums(ones, ry + ty, rx + tx),
        )
        r = inner / jnp.maximum(inner_area, 1.0)
        ring_area = outer_area - inner_area
        r_ring = jnp.where(ring_area > 0, (outer - inner) / jnp.maximum(ring_area, 1.0), 0.0)
        return r * (1.0 - r_ring)

    tight = jax.vmap(tightness)(ry, rx, ty, tx)  # [S, h, w]
    cx = (jnp.arange(ww, dtype=jnp.float32) + 0.5) * s
    cy = (jnp.arange(hh, dtype=jnp.float32) + 0.5) * s
    d2 = (cx[None] - centre[0]) ** 2 + (cy[:, None] - centre[1]) ** 2
    # Support: at least detector_min_ratio of the best tightness within 3 sigma of the
    # centre, and at least detector_floor in absolute terms (specks of noise are no
    # detections).
    near = d2 <= 9.0 * jnp.maximum(sigma, 1.0) ** 2
    best = jnp.max(jnp.where(near[None], tight, 0.0))
    floor = jnp.maximum(params.detector_min_ratio * best, params.detector_floor)
    ok = near[None] & (tight >= floor)
    size_prior = -0.5 * (log_fw**2 + log_fh**2) / jnp.maximum(params.fast_scale, 1e-3) ** 2
    logits = (
        params.detector_power * jnp.log(jnp.maximum(tight, 1e-6))
        - 0.5 * d2[None] / jnp.maximum(sigma, 1.0) ** 2
        + size_prior[:, None, None]
    )
    logits = jnp.where(ok, logits, -jnp.inf).reshape(-1)
    available = jnp.any(ok)
    logits = jnp.where(available, logits, 0.0)
    # How well the box of the reference size at the centre does, relative to the best.
    cell = map_cell_of(centre, s, (hh, ww))
    k0 = int(np.flatnonzero((si == 0) & (sj == 0))[0])
    at_centre = jnp.where(cell >= 0, tight[k0].reshape(-1)[jnp.maximum(cell, 0)], 0.0)
    fit = jnp.where(best > 0, at_centre / jnp.maximum(best, 1e-6), 1.0)
    return logits - jax.nn.logsumexp(logits), available, fit


def detector_draw(
    key: Array,
    config: RGBDConfig,
    log_map: Array,
    shape: tuple[int, int],
    box_wh: Array,
    n: int,
) -> Array:
    """``[n, 4]`` boxes ``(cx, cy, w, h)`` from ``log_map [S * h * w]``.

    A (size, cell) pair, then the centre uniform inside the cell and the log-size
    uniform within half a step of the pair's size (so the sizes of neighbouring steps
    tile log-size, and :func:`detector_log_density` is a plain look-up). The pairs are
    drawn by inverse CDF over the whole map: ``O(S h w + n log(S h w))`` (per-particle
    categorical draws cost ``n x S h w`` random numbers: 79 of 170 ms of an N = 1,000
    grid-occlusion step on 2 CPU cores).
    """
    s = config.detector_stride
    hh, ww = shape
    si, sj = detector_scale_grid(config)
    step_w, step_h = config.detector_scale_step
    k1, k3 = jax.random.split(key)
    mass = jnp.exp(log_map - jnp.max(log_map))  # [S * h * w], -inf -> 0
    cdf = jnp.cumsum(mass)
    v = jax.random.uniform(k1, (n,)) * cdf[-1]
    pair = jnp.searchsorted(cdf, v, side="right")
    # Float round-off can leave v at the very top: never land past the last pair with mass.
    last = jnp.max(jnp.where(mass > 0, jnp.arange(mass.shape[0]), 0))
    pair = jnp.minimum(pair, last)
    k, cell = pair // (hh * ww), pair % (hh * ww)
    u = jax.random.uniform(k3, (n, 4))
    log_w = jnp.log(box_wh[0]) + (jnp.asarray(si, jnp.float32)[k] + u[:, 2] - 0.5) * step_w
    log_h = jnp.log(box_wh[1]) + (jnp.asarray(sj, jnp.float32)[k] + u[:, 3] - 0.5) * step_h
    return jnp.stack(
        [
            ((cell % ww).astype(jnp.float32) + u[:, 0]) * s,
            ((cell // ww).astype(jnp.float32) + u[:, 1]) * s,
            jnp.exp(log_w),
            jnp.exp(log_h),
        ],
        axis=-1,
    )


def detector_log_density(
    config: RGBDConfig,
    log_map: Array,
    shape: tuple[int, int],
    box_wh: Array,
    boxes: Array,
    sizes: bool = True,
) -> Array:
    """``log q(cx, cy, w, h) [N]`` of :func:`detector_draw` for ``boxes [N, 4]`` (cxcywh;
    per pixel^4; ``-inf`` off the map or off the size grid). ``sizes=False``: the density
    of the centre alone (per pixel^2; the sizes are not drawn from the detector)."""
    s = config.detector_stride
    hh, ww = shape
    jw, jh = config.detector_scales
    step_w, step_h = config.detector_scale_step
    cell = map_cell_of(boxes[:, :2], s, shape)
    w = jnp.maximum(boxes[:, 2], 1e-6)
    h = jnp.maximum(boxes[:, 3], 1e-6)
    i = jnp.floor(jnp.log(w / box_wh[0]) / step_w + 0.5).astype(jnp.int32)
    j = jnp.floor(jnp.log(h / box_wh[1]) / step_h + 0.5).astype(jnp.int32)
    lm = log_map.reshape(-1, hh * ww)
    if not sizes:
        marginal = jax.nn.logsumexp(lm, axis=0)  # [h * w]
        lp = jnp.where(cell >= 0, marginal[jnp.maximum(cell, 0)], -jnp.inf)
        return lp - 2.0 * jnp.log(jnp.float32(s))
    on = (cell >= 0) & (jnp.abs(i) <= jw) & (jnp.abs(j) <= jh)
    k = (jnp.clip(i, -jw, jw) + jw) * (2 * jh + 1) + (jnp.clip(j, -jh, jh) + jh)
    lp = jnp.where(on, lm[k, jnp.maximum(cell, 0)], -jnp.inf)
    # Per pixel^2 of centre, and the log-uniform size: 1 / (w step_w) x 1 / (h step_h).
    return lp - 2.0 * jnp.log(jnp.float32(s)) - jnp.log(w * step_w) - jnp.log(h * step_h)


def _motion(params: RGBDParams) -> MotionParams:
    """The motion parameters this filter proposes with: ``size_hold`` is 0 whatever
    ``params`` say, since the closed-form proposal densities below assume it
    (``cpf_jax.dynamics``, "Size hold")."""
    hold = jnp.asarray(params.motion.size_hold, jnp.float32)
    return params.motion._replace(size_hold=jnp.zeros_like(hold))


def motion_size_log_density(
    config: RGBDConfig,
    params: RGBDParams,
    ancestors: Array,
    mean_wh: Array,
    wh: Array,
    scale: Array | None,
) -> Array:
    """``log p(w, h | ancestor) [N]`` of the box size drawn by ``dynamics.propagate``.

    ``mean_wh [N, 2]``: the noise-free prediction. The size noise of every model that
    changes sizes is a correlated Gaussian: height sd ``tau_h s``, width sd ``tau_w s a``
    (``a`` = the ancestor's aspect / 0.41 when ``size_correlation > 0``, else 1),
    correlation ``size_correlation`` (the guided proposal only touches the size
    velocities). Zero for the fixed-size models (their sizes are not proposed).
    """
    if config.model.endswith("_fixed"):
        return jnp.zeros(wh.shape[:1], jnp.float32)
    sc = 1.0 if scale is None else scale
    rho = jnp.clip(jnp.asarray(params.motion.size_correlation, jnp.float32), 0.0, 0.999)
    aspect = ancestors[:, 4] / jnp.maximum(ancestors[:, 5], 1e-3)
    a = jnp.where(rho > 0, aspect / 0.41, 1.0)
    sw = jnp.broadcast_to(params.tau[4] * sc * a, wh.shape[:1])
    sh = jnp.broadcast_to(params.tau[5] * sc, wh.shape[:1])
    return _gauss2_log_density(wh - mean_wh, sw * sw, rho * sw * sh, sh * sh)


# ----------------------------------------------------------------------------- the filter


def _kept_lines(counts: Array, min_pixels: Array) -> Array:
    """``counts [L]`` target pixels per column (row) -> ``[L]`` bool: the line has one and
    the line with its two neighbours hold at least ``min_pixels``."""
    window = jnp.convolve(counts, jnp.ones((3,), counts.dtype), mode="same")
    return (counts > 0) & (window >= min_pixels)


def _main_run(counts: Array, kept: Array, gap: Array) -> Array:
    """``[L]`` bool: the kept lines of the run holding the most target pixels.

    Kept lines (``kept [L]``) at most ``gap`` lines apart belong to one run; ``counts
    [L]`` weigh them. A person is one run (an arm or a leg apart by a few lines stays
    in it); stray foreground at the target's depth further off (a desk, a wall) is
    another run, and must not stretch the tight box.
    """
    idx = jnp.arange(counts.shape[0], dtype=jnp.float32)
    last = jax.lax.cummax(jnp.where(kept, idx, -jnp.inf))
    prev = jnp.concatenate([jnp.full((1,), -jnp.inf), last[:-1]])  # last kept line before
    start = kept & (idx - prev > gap)
    run = jnp.cumsum(start.astype(jnp.int32)) - 1  # run index of every line (-1: none yet)
    run = jnp.where(kept, run, counts.shape[0])  # not kept: an unused segment
    totals = jax.ops.segment_sum(counts, run, num_segments=counts.shape[0] + 1)
    return kept & (run == jnp.argmax(totals[:-1]))


@memoised_build
def build_rgbd_filter(config: RGBDConfig) -> Filter:
    """``Filter(init, step)`` of ``config.variant``.

    ``init(params, key, frame, box_xywh, background=None) -> state`` and
    ``step(params, key, state, frame) -> (state, RGBDInfo)``. ``background`` is a
    :class:`~cpf_jax.kernels.background.Background` (None: every pixel counts as
    foreground; the "rgb" variant ignores it).
    """
    if config.variant == "rgb":
        return _rgb_filter(config)
    n = config.n_particles
    k = config.k
    c = config.n_cells
    resampler = rs.SCHEMES[config.resampler]
    # Fixed-size models: the detector proposes centres only (one size, the estimate's).
    sizes = not config.model.endswith("_fixed")
    det_config = config if sizes else dataclasses.replace(config, detector_scales=(0, 0))

    def clamp(particles: Array, width: int, height: int) -> Array:
        # Boxes stay inside the frame (the ground truth is the visible part of the
        # person): cut at the edges, but never below min_size.
        m = config.min_size
        cx, cy, w, h = (particles[:, i] for i in (0, 1, 4, 5))
        x0 = jnp.clip(cx - w / 2, 0.0, width - m)
        y0 = jnp.clip(cy - h / 2, 0.0, height - m)
        x1 = jnp.clip(cx + w / 2, x0 + m, width)
        y1 = jnp.clip(cy + h / 2, y0 + m, height)
        return (
            particles.at[:, 0]
            .set((x0 + x1) / 2)
            .at[:, 1]
            .set((y0 + y1) / 2)
            .at[:, 4]
            .set(x1 - x0)
            .at[:, 5]
            .set(y1 - y0)
        )

    def init(
        params: RGBDParams,
        key: Array,
        frame: Frame,
        box_xywh: Array,
        background: Background | None = None,
    ) -> RGBDState:
        check_frame(frame, needs_depth=True)
        box, _ = usable_box(box_xywh, frame)  # an unusable box under jit: the whole frame
        height, width = frame.colour.shape[:2]
        bg = (
            _no_background(frame)
            if background is None
            else Background(
                jnp.asarray(background.colour, jnp.float32),
                jnp.asarray(background.depth, jnp.float32),
            )
        )
        obs = _observe(config, params, frame, bg)
        hist, med, _ = _cell_templates(config, obs, box)
        body_hist, body_count = body_histogram(config, obs, box)
        cc = box_ops.xywh_to_cxcywh(box)
        one = jnp.array([cc[0], cc[1], 0.0, 0.0, cc[2], cc[3], 0.0, 0.0], jnp.float32)
        particles = jnp.tile(one, (n, 1))
        if config.init_spread > 0:
            particles = particles.at[:, :2].add(jax.random.normal(key, (n, 2)) * config.init_spread)
        particles = clamp(particles, width, height)
        return RGBDState(
            particles=particles,
            previous=particles,
            log_weights=jnp.full((n,), -jnp.log(jnp.float32(n))),
            flags=jnp.zeros((n,), jnp.int32),
            colour_template=hist,
            depth_template=med,
            depth_age=jnp.zeros((c,), jnp.float32),
            depth_velocity=jnp.zeros((), jnp.float32),
            vote=jnp.zeros((c,), jnp.float32),
            occluded_frames=jnp.zeros((), jnp.int32),
            visible_size=box[2:4],
            estimate=box,
            background=bg,
            reach=box[3] * mean_known_depth(med),
            occluder_depth=jnp.zeros((), jnp.float32),
            fill_shift=(
                jnp.zeros((), jnp.float32)
                if background is None
                else beta_fill_shift(params, initial_fill(obs.foreground, box))
            ),
            body_template=body_hist,
            # An empty first box counts for nothing: the first frame learnt replaces it.
            body_frames=jnp.where(body_count > 0, 0, -1).astype(jnp.int32),
            body_steps=jnp.zeros((), jnp.int32),
        )

    def target_depth(state: RGBDState) -> Array:
        """Mean of the known cell depth templates (mm; 0 when none is known)."""
        return mean_known_depth(state.depth_template)

    def target_gate(
        params: RGBDParams, state: RGBDState, target_z: Array, drift: bool = True
    ) -> Array:
        """Depth tolerance (mm) of "a pixel of the target": wider the longer it was hidden
        or its templates stale, as it may have walked ``depth_speed`` mm per frame (up to
        ``search_drift_max``; ``drift=False``: the tolerance of fresh templates)."""
        base = depth_tolerance(params, target_z)
        return base + search_drift(params, state) if drift else base

    def target_like(
        params: RGBDParams, state: RGBDState, z: Array, target_z: Array
    ) -> tuple[Array, Array]:
        """Which depths ``z`` may be the target's: ``(like, tight)``. ``tight``: within the
        gate of fresh templates; ``like`` adds those within the stale drift that are not
        at the remembered occluder's depth (the occluder that hid the target is nearer
        than it by less than the drift after a long occlusion, and must not be taken for
        it)."""
        tight = jnp.abs(z - target_z) < target_gate(params, state, target_z, drift=False)
        wide = jnp.abs(z - target_z) < target_gate(params, state, target_z)
        return tight | (wide & ~at_occluder(params, state, z)), tight

    def at_occluder(params: RGBDParams, state: RGBDState, z: Array) -> Array:
        """Depths ``z`` within ``max(recovery_gate, recovery_gate_rel * d)`` of the
        remembered occluder depth ``d`` (all False while none is known)."""
        occ = state.occluder_depth
        gate = depth_tolerance(params, occ)
        return (occ > 0) & (jnp.abs(z - occ) < gate)

    def search_drift(params: RGBDParams, state: RGBDState) -> Array:
        """How far (mm) the target may have moved in depth since its templates last learned:
        ``depth_speed`` per frame hidden or stale, up to ``search_drift_max``. Staleness
        counts too: a target found again by colour while its templates are off keeps the
        wide gate until they learn its depth (one frame found must not shrink it)."""
        stale = jnp.min(jnp.where(state.depth_template > 0, state.depth_age, MAX_DEPTH_AGE))
        hidden_for = jnp.maximum(state.occluded_frames.astype(jnp.float32), stale)
        return jnp.minimum(params.depth_speed * hidden_for, params.search_drift_max)

    def recovery_draw(
        key: Array, params: RGBDParams, state: RGBDState, obs: _Observation, depth: Array
    ) -> tuple[Array, Array]:
        """Which particles to re-draw ``[N] bool`` and their new states ``[N, 8]``.

        While the target is voted occluded, a share ``recovery_fraction`` of the
        particles is moved onto random foreground pixels whose depth is within
        ``max(recovery_gate, recovery_gate_rel * z)`` of the target's template
        depth ``z`` (the pixel anywhere inside the box, the estimate's size, no
        velocity): the search the paper obtains by scattering, aimed at places
        where the target can reappear. Sampling is by inverse CDF over a
        ``recovery_stride`` grid of the gated mask (static shapes).
        """
        s = config.recovery_stride
        height, width = depth.shape
        hh, ww = height // s, width // s
        target_z = target_depth(state)
        z = depth.astype(jnp.float32)
        like, _ = target_like(params, state, z, target_z)
        ok = obs.foreground & (z > 0) & like
        coarse = ok[: hh * s, : ww * s].reshape(hh, s, ww, s).sum((1, 3)).reshape(-1)
        cdf = jnp.cumsum(coarse.astype(jnp.float32))
        total = cdf[-1]
        k1, k2, k3, k4 = jax.random.split(key, 4)
        u = jax.random.uniform(k1, (n,)) * total
        cell = jnp.clip(jnp.searchsorted(cdf, u, side="right"), 0, hh * ww - 1)
        jit_px = jax.random.uniform(k2, (n, 2)) * s
        px = (cell % ww).astype(jnp.float32) * s + jit_px[:, 0]
        py = (cell // ww).astype(jnp.float32) * s + jit_px[:, 1]
        size = state.visible_size
        off = (jax.random.uniform(k3, (n, 2)) - 0.5) * 0.8 * size
        zero = jnp.zeros((n,), jnp.float32)
        fresh = jnp.stack(
            [
                px + off[:, 0],
                py + off[:, 1],
                zero,
                zero,
                jnp.full((n,), size[0]),
                jnp.full((n,), size[1]),
                zero,
                zero,
            ],
            axis=-1,
        )
        searching = (state.occluded_frames > 0) & (total > 0)
        redraw = (jax.random.uniform(k4, (n,)) < config.recovery_fraction) & searching
        return redraw, fresh

    def detector_mixture(
        key: Array,
        params: RGBDParams,
        state: RGBDState,
        obs: _Observation,
        depth: Array,
        particles: Array,
        scale: Array | None,
        spread: Array,
        extra: Array,
    ) -> tuple[Array, Array]:
        """Mixture proposal of the boxes; returns the particles and ``log p - log q [N]``.

        ``particles`` were drawn from the motion model. A share ``detector_fraction``
        of them moves its box (centre and size) to a draw of the detector proposal
        (:func:`detector_log_map`: tight boxes around foreground at the target's depth,
        sizes on a grid around the estimate's, near the predicted centre), the rest
        keeps it. Each particle's proposal is ``q = (1 - a) p_motion + a q_det`` of its
        ``(cx, cy, w, h)`` given its ancestor; the model's transition is ``p = (1 - f)
        p_motion + f N(mean, (fast_sigma h)^2) LN(size; predicted size, fast_scale^2)``
        (a fast component: a person near the camera can move half a box per frame, and
        change size by a fifth, or come into view); the weight gets ``p / q`` (exact:
        both share the velocity draws). Without any detection ``a = 0``. Fixed-size
        models: the detector proposes centres only.
        """
        s = config.detector_stride
        height, width = depth.shape
        shape = (height // s, width // s)
        k_draw, k_mix = jax.random.split(key)
        zero_tau = jnp.zeros_like(params.tau)
        pred = propagate(
            k_mix,
            state.particles,
            state.previous,
            zero_tau,
            _motion(params),
            model=config.model,
            hierarchical=config.hierarchical,
            scale=scale,
        )
        mean, mean_wh = pred[:, :2], pred[:, 4:6]
        target_z = target_depth(state)
        z = depth.astype(jnp.float32)
        gate = target_gate(params, state, target_z) + params.depth_speed
        pixels = obs.foreground & (z > 0) & (jnp.abs(z - target_z) < gate) & (target_z > 0)
        w = jnp.exp(state.log_weights)
        centre = w @ mean
        reach = state.reach if config.depth_cap else jnp.zeros_like(state.reach)
        sigma = params.fast_sigma * fast_length(reach, state.depth_template, state.estimate[3])
        sigma = sigma * spread
        ref_wh = jnp.maximum(state.estimate[2:4], config.min_size)
        log_map, available, fit = detector_log_map(
            det_config, params, pixels, ref_wh, centre, sigma
        )
        det = detector_draw(k_draw, det_config, log_map, shape, ref_wh, n)
        # Draw from the detector only when the motion prior's prediction misses: a box at
        # the predicted centre holds less than detector_need of the best one's share.
        # (A choice made from the data before drawing: the weights stay exact.)
        # While the target is voted occluded the recovery search (and the spreading) take
        # over: neither the detector nor the fast-motion component is used then.
        active = state.occluded_frames == 0
        alpha = jnp.where(
            active & available & (fit < params.detector_need), config.detector_fraction, 0.0
        )
        use = jax.random.uniform(jax.random.fold_in(k_draw, 1), (n,)) < alpha
        cols = jnp.array([0, 1, 4, 5]) if sizes else jnp.array([0, 1])
        box = jnp.where(use[:, None], det[:, : len(cols)] if not sizes else det, particles[:, cols])
        particles = particles.at[:, cols].set(box)
        xy, wh = particles[:, :2], particles[:, 4:6]
        lp_motion = motion_position_log_density(
            config, params, state.particles, mean, xy, scale, extra
        )
        var_fast = (
            params.fast_sigma * fast_length(reach, state.depth_template, state.particles[:, 5])
        ) ** 2
        lp_fast = _gauss2_log_density(xy - mean, var_fast, jnp.zeros_like(var_fast), var_fast)
        if sizes:
            lp_motion = lp_motion + motion_size_log_density(
                config, params, state.particles, mean_wh, wh, scale
            )
            # Log-normal sizes around the prediction (density per pixel^2 of (w, h)).
            log_ratio = jnp.log(jnp.maximum(wh, 1e-3)) - jnp.log(jnp.maximum(mean_wh, 1e-3))
            fs = params.fast_scale
            lp_fast = lp_fast + jnp.sum(
                -0.5 * (log_ratio / fs) ** 2
                - jnp.log(fs * jnp.sqrt(2.0 * jnp.pi))
                - jnp.log(jnp.maximum(wh, 1e-3)),
                axis=-1,
            )
        f = jnp.where(active, params.fast_fraction, 0.0)
        lp_model = jnp.logaddexp(_log_clip(1.0 - f) + lp_motion, _log_clip(f) + lp_fast)
        lq_det = detector_log_density(
            det_config, log_map, shape, ref_wh, particles[:, [0, 1, 4, 5]], sizes
        )
        lq = jnp.logaddexp(_log_clip(1.0 - alpha) + lp_motion, _log_clip(alpha) + lq_det)
        return particles, lp_model - lq

    def target_extent(
        params: RGBDParams, state: RGBDState, obs: _Observation, depth: Array, est: Array
    ) -> tuple[Array, Array, Array]:
        """Tight box ``[4]`` of the target's pixels around the estimate, their coverage, and
        the coverage of those at the templates' depth (the gate without the drift).

        Target pixels: foreground within ``max(recovery_gate, recovery_gate_rel * z)``
        of the depth template ``z`` (nearer pixels belong to an occluder);
        searched in the estimate grown by
        ``report_margin`` per side. Columns / rows with fewer than
        ``report_min_pixels`` of them are ignored (isolated noise), and so are
        those outside the main run (``_main_run``, gaps of ``report_gap``). The estimate
        itself when no target pixel is found. ``coverage``: target pixels found /
        the estimate's area (about 0 when the target is hidden); ``held``: the same
        with the gate of fresh templates (the target is where its templates expect it).
        """
        height, width = depth.shape
        target_z = target_depth(state)
        z = depth.astype(jnp.float32)
        like, tight = target_like(params, state, z, target_z)
        # Pixels without depth are left out: at depth edges and on dark hair they
        # cannot be told apart from an occluder's.
        like = obs.foreground & (z > 0) & like
        m = params.report_margin
        x0 = est[0] - m * est[2]
        y0 = est[1] - m * est[3]
        x1 = est[0] + est[2] * (1 + m)
        y1 = est[1] + est[3] * (1 + m)
        cols = jnp.arange(width, dtype=jnp.float32) + 0.5
        rows = jnp.arange(height, dtype=jnp.float32) + 0.5
        inside = ((rows >= y0) & (rows < y1))[:, None] & ((cols >= x0) & (cols < x1))[None]
        t = (like & inside).astype(jnp.float32)
        held = jnp.sum(t * tight) / jnp.maximum(est[2] * est[3], 1.0)
        # A column / row counts when it and its two neighbours hold report_min_pixels
        # target pixels: isolated noise pixels drop out, a 1 px wide arm or leg (a sliver
        # at an occluder's edge, one pixel per row) stays.
        col_count, row_count = jnp.sum(t, axis=0), jnp.sum(t, axis=1)
        col_n = _kept_lines(col_count, params.report_min_pixels)
        row_n = _kept_lines(row_count, params.report_min_pixels)
        col_n = _main_run(col_count, col_n, params.report_gap * est[2])
        row_n = _main_run(row_count, row_n, params.report_gap * est[3])
        ok = jnp.any(col_n) & jnp.any(row_n)
        coverage = jnp.sum(t) / jnp.maximum(est[2] * est[3], 1.0)
        big = jnp.float32(1e9)
        bx0 = jnp.min(jnp.where(col_n, cols - 0.5, big))
        bx1 = jnp.max(jnp.where(col_n, cols + 0.5, -big))
        by0 = jnp.min(jnp.where(row_n, rows - 0.5, big))
        by1 = jnp.max(jnp.where(row_n, rows + 0.5, -big))
        return jnp.where(ok, jnp.stack([bx0, by0, bx1 - bx0, by1 - by0]), est), coverage, held

    def step(
        params: RGBDParams, key: Array, state: RGBDState, frame: Frame
    ) -> tuple[RGBDState, RGBDInfo]:
        check_frame(frame, needs_depth=True)
        height, width = frame.colour.shape[:2]
        k_prop, k_spread, k_flag, k_res, k_rec = jax.random.split(key, 5)
        k_det = jax.random.fold_in(key, 6)
        # Depth templates move with the target (alpha-beta filter, module docstring):
        # predict them one frame ahead before they are compared with anything.
        state = state._replace(
            depth_template=jnp.where(
                state.depth_template > 0,
                jnp.maximum(state.depth_template + state.depth_velocity, config.depth_range[0]),
                0.0,
            )
        )
        obs = _observe(config, params, frame, state.background)
        scale = None if config.tau_height is None else state.particles[:, 5] / config.tau_height
        particles = propagate(
            k_prop,
            state.particles,
            state.previous,
            params.tau,
            _motion(params),
            model=config.model,
            hierarchical=config.hierarchical,
            scale=scale,
            # The size velocities forget ("Motion model" in the module docstring).
            size_velocity_decay=params.size_velocity_decay,
        )
        if config.occlusion:
            # Search a wider area while the target is voted occluded (paper 2.1, Fig. 5).
            spread = jnp.minimum(
                1.0 + params.spread_rate * state.occluded_frames.astype(jnp.float32),
                params.spread_max,
            )
            extra = jnp.sqrt(jnp.maximum(spread**2 - 1.0, 0.0))
            pos_scale = params.tau[:2] * (1.0 if scale is None else scale[:, None])
            particles = particles.at[:, :2].add(
                extra * pos_scale * jax.random.normal(k_spread, (n, 2))
            )
            # A hidden target keeps its size: nothing observes it, so it must not drift.
            hidden = state.occluded_frames > 0
            keep = jnp.concatenate([state.particles[:, 4:6], jnp.zeros((n, 2))], axis=-1)
            particles = particles.at[:, 4:8].set(jnp.where(hidden, keep, particles[:, 4:8]))
        else:
            spread = jnp.float32(1.0)
            extra = jnp.float32(0.0)
        # log p(x | ancestor) - log q(x | ancestor, y) of every particle's draw.
        log_proposal = jnp.zeros((n,), jnp.float32)
        if config.detector_fraction > 0:
            particles, log_proposal = detector_mixture(
                k_det, params, state, obs, frame.depth, particles, scale, spread, extra
            )
        flags_prev = state.flags
        if config.occlusion and config.recovery_fraction > 0:
            redraw, fresh = recovery_draw(k_rec, params, state, obs, frame.depth)
            particles = jnp.where(redraw[:, None], fresh, particles)
            flags_prev = jnp.where(redraw, 0, flags_prev)
            # The recovery draw is a search heuristic, weighted by its likelihood alone.
            log_proposal = jnp.where(redraw, 0.0, log_proposal)
        particles = clamp(particles, width, height)

        boxes_xywh = _to_xywh(particles)
        # The Beta terms, moved to the initial box's foreground fill ("Foreground fill").
        bparams = fill_adapted(params, state.fill_shift)
        terms = cell_terms(
            config,
            bparams,
            state.colour_template,
            state.depth_template,
            obs,
            boxes_xywh,
            state.depth_age,
            state.body_template if config.body_term else None,
        )
        l_vis, l_occ, fg_count, area = terms.l_vis, terms.l_occ, terms.fg_count, terms.area
        box_term = config.box_term and c > 1
        side_sum = terms.l_border[:, :4] + terms.l_border[:, 4:]  # [N, 4] per side

        if config.occlusion:
            l_box = None
            if config.full_transition:
                # Terms over several cells, for every flag state: the pooled ratio of
                # the visible cells, and the border strips of the fully visible sides.
                vis = 1.0 - flag_bits(c)  # [S, C]: 1 where the cell is visible
                sides = jnp.asarray(side_cells(k), jnp.float32)  # [4, C]
                side_on = (vis @ sides.T) >= jnp.sum(sides, axis=-1)  # [S, 4]
                l_box = side_sum @ side_on.astype(jnp.float32).T + terms.l_body  # [N, S]
                if box_term:
                    l_box = l_box + box_log_density(bparams, fg_count @ vis.T, area @ vis.T)
            else:
                # Factorised flags: the multi-cell terms cannot be split per cell;
                # they are scored as if every cell were visible.
                log_extra = jnp.sum(side_sum, axis=-1) + terms.l_body[:, 0]
                if box_term:
                    log_extra = log_extra + box_log_density(
                        bparams, jnp.sum(fg_count, axis=-1), jnp.sum(area, axis=-1)
                    )
            log_lik, flags, p_cell = _flag_posterior(
                config, params, k_flag, flags_prev, l_vis, l_occ, l_box
            )
            if not config.full_transition:
                log_lik = log_lik + log_extra
        else:
            log_lik = jnp.sum(l_vis, axis=-1) + jnp.sum(side_sum, axis=-1) + terms.l_body[:, 0]
            if box_term:
                log_lik = log_lik + box_log_density(
                    bparams, jnp.sum(fg_count, axis=-1), jnp.sum(area, axis=-1)
                )
            flags = state.flags
            p_cell = jnp.zeros((n, c), jnp.float32)
        if config.aspect_prior:
            log_lik = log_lik + aspect_log_prior(particles, params.aspect_mean, params.aspect_sigma)
        log_lik = log_lik + log_proposal
        lw, invalid, ess, log_evidence = rs.reweight(state.log_weights, log_lik)
        w = jnp.exp(lw)
        est = _to_xywh(w @ particles)
        vote = w @ p_cell  # [C]
        voted = vote > params.vote_threshold
        target_occluded = jnp.mean(voted.astype(jnp.float32)) > 0.5
        extent, coverage, held = target_extent(params, state, obs, frame.depth, est)
        # Nothing at the target's depth in or around the estimate: the target is hidden
        # (or lost), whatever the cells' votes say.
        hidden = coverage < params.min_coverage
        # Remember the occluder: the mean median depth of the estimate's cells nearer
        # than the templates by more than the occluder margin (``target_like``).
        est_hist, est_med, _ = _cell_templates(config, obs, est)
        z_pred = target_depth(state)
        near_cut = z_pred - occluder_margin(params, z_pred)
        occ_cell = (z_pred > 0) & (est_med > 0) & (est_med < near_cut)
        occluder_depth = jnp.where(
            jnp.any(occ_cell),
            jnp.sum(jnp.where(occ_cell, est_med, 0.0)) / jnp.maximum(jnp.sum(occ_cell), 1),
            state.occluder_depth,
        )

        if config.report == "pixels":
            report = extent
        elif config.occlusion and config.report == "cells":
            cells = grid_cells(est, k)  # [C, 4]
            x0 = jnp.min(jnp.where(voted, jnp.inf, cells[:, 0]))
            y0 = jnp.min(jnp.where(voted, jnp.inf, cells[:, 1]))
            x1 = jnp.max(jnp.where(voted, -jnp.inf, cells[:, 0] + cells[:, 2]))
            y1 = jnp.max(jnp.where(voted, -jnp.inf, cells[:, 1] + cells[:, 3]))
            report = jnp.where(jnp.all(voted), est, jnp.stack([x0, y0, x1 - x0, y1 - y0]))
        else:
            report = est
        lost = invalid | ((jnp.all(voted) | hidden) if config.occlusion else False)
        if config.occlusion:
            target_occluded = target_occluded | hidden

        colour_template, depth_template = state.colour_template, state.depth_template
        depth_age = state.depth_age
        if config.template_update:
            # Depth decides: the templates learn only from pixels that are not nearer than
            # the predicted target depth by more than the occluder margin (an occluder
            # covering half a cell would otherwise become the cell's median).
            # Stale templates (the target was hidden and may have moved): when nothing is
            # seen at their depth, the target found nearer within the search drift (and
            # not at the occluder's depth, ``target_like``) is the target, not an
            # occluder, and they learn its depth.
            drift = search_drift(params, state)
            z_frame = frame.depth.astype(jnp.float32)
            widen = held < params.min_coverage
            cut = (z_frame < near_cut - jnp.where(widen, drift, 0.0)) | (
                widen & (z_frame < near_cut) & at_occluder(params, state, z_frame)
            )
            gated = obs._replace(
                depth_bins=jnp.where((z_pred > 0) & (z_frame > 0) & cut, -1, obs.depth_bins)
            )
            hist = est_hist
            _, med, total = _cell_templates(config, gated, est)
            ok = (~voted) & (~lost)
            # Colour: eq. 7 in the cells voted visible whose estimate still resembles the
            # template (d < template_gate): a misplaced estimate would teach the template
            # its own error. A drastic appearance change is then carried by the depth
            # and foreground terms rather than learned.
            est_d = bhattacharyya(hist, colour_template)
            rate = jnp.where(ok & (est_d < params.template_gate), params.template_rate, 0.0)
            rate = rate[:, None]
            if config.background_bin:
                # Adapt the colours only: each cell keeps its initial share of
                # background (otherwise a drifting box teaches the template to
                # expect the background it drifted onto, and keeps drifting).
                fill = 1.0 - colour_template[:, -1:]
                fg_new = _normalise(hist[:, :-1]) * fill
                hist = jnp.concatenate([fg_new, colour_template[:, -1:]], axis=-1)
            colour_template = _normalise((1.0 - rate) * colour_template + rate * hist)
            # Depth templates learn gradual changes only: a jump larger than the
            # occluder margin is an occluder, not the target (P: "depth decides").
            jump = jnp.abs(med - depth_template) < (
                occluder_margin(params, depth_template)
                + jnp.maximum(
                    jnp.minimum(params.depth_speed * state.depth_age, params.max_drift), drift
                )
            )
            d_ok = ok & (total >= config.min_depth_count) & ((depth_template <= 0) | jump)
            updated = jnp.where(
                depth_template > 0,
                (1.0 - params.depth_rate) * depth_template + params.depth_rate * med,
                med,
            )
            # The body moves in depth as a whole: cells that are not updated (occluded,
            # no depth) follow the mean change of the updated ones, so that they are not
            # stale when they reappear (a person may change lanes while half hidden).
            moved = d_ok & (depth_template > 0)
            shift = jnp.sum(jnp.where(moved, updated - depth_template, 0.0)) / jnp.maximum(
                jnp.sum(moved), 1
            )
            follow = (~d_ok) & (depth_template > 0) & jnp.any(moved)
            depth_template = jnp.where(
                d_ok, updated, jnp.where(follow, depth_template + shift, depth_template)
            )
            depth_age = jnp.where(
                d_ok | follow, 0.0, jnp.minimum(state.depth_age + 1.0, MAX_DEPTH_AGE)
            )
            # Velocity: corrected by the mean innovation (median - predicted template) of
            # the updated cells; while nothing is measured it fades (by the same gain), so
            # the templates of a hidden target do not run away.
            innovation = jnp.sum(jnp.where(moved, med - state.depth_template, 0.0)) / jnp.maximum(
                jnp.sum(moved), 1
            )
            depth_velocity = jnp.where(
                jnp.any(moved),
                state.depth_velocity + params.depth_velocity_rate * innovation,
                (1.0 - params.depth_velocity_fade) * state.depth_velocity,
            )
            depth_velocity = jnp.clip(depth_velocity, -params.max_drift, params.max_drift)
        else:
            depth_velocity = state.depth_velocity
        body_template, body_frames = state.body_template, state.body_frames
        if config.body_term:
            # The whole-body template learns from unoccluded frames only: a running mean
            # of those among the first ``body_warmup`` steps (the initial box may show a
            # part of the person), then forgetting at ``body_rate``.
            body_hist, body_count = body_histogram(config, obs, report)
            learn = (~lost) & (jnp.max(vote) < 0.1) & (body_count >= params.body_min_pixels)
            warm = state.body_steps < params.body_warmup
            n_seen = body_frames.astype(jnp.float32)
            rate = jnp.maximum(1.0 / (n_seen + 2.0), params.body_rate)
            rate = jnp.where(warm, rate, params.body_rate)
            rate = jnp.where(learn, rate, 0.0)
            mixed = (1.0 - rate) * body_template + rate * body_hist
            body_template = mixed / jnp.maximum(jnp.sum(mixed), 1e-12)
            body_frames = body_frames + learn.astype(jnp.int32)
        body_steps = jnp.minimum(state.body_steps + 1, 1 << 30)
        background = state.background
        if config.background_update:
            background = update_background(
                background, frame.colour, frame.depth, obs.foreground, params.background_rate
            )

        occluded_frames = jnp.where(target_occluded, state.occluded_frames + 1, 0)
        (particles, previous, flags), lw, resampled = rs.resample_if(
            k_res, lw, (particles, state.particles, flags), config.ess_threshold, resampler
        )
        new_state = RGBDState(
            particles=particles,
            previous=previous,
            log_weights=lw,
            flags=flags,
            colour_template=colour_template,
            depth_template=depth_template,
            depth_age=depth_age,
            depth_velocity=depth_velocity,
            vote=vote,
            occluded_frames=occluded_frames.astype(jnp.int32),
            visible_size=jnp.where((jnp.max(vote) < 0.1) & ~lost, est[2:4], state.visible_size),
            estimate=est,
            background=background,
            reach=state.reach,
            occluder_depth=occluder_depth,
            fill_shift=state.fill_shift,
            body_template=body_template,
            body_frames=body_frames,
            body_steps=body_steps,
        )
        info = RGBDInfo(
            estimate=est,
            report=report,
            lost=lost,
            ess=ess,
            log_likelihood=log_evidence,
            vote=vote,
            target_occluded=target_occluded,
            resampled=resampled,
            weights_invalid=invalid,
            windowed=terms.windowed,
        )
        return new_state, info

    return Filter(init=init, step=step)


def _rgb_filter(config: RGBDConfig) -> Filter:
    """The "rgb" variant: the colour layer unchanged, with RGBDInfo outputs."""
    inner = build_colour_filter(config.colour_config)

    def init(params: RGBDParams, key, frame, box_xywh, background=None):
        del background  # colour only
        return inner.init(params.colour, key, frame, box_xywh)

    def step(params: RGBDParams, key, state, frame):
        state, ci = inner.step(params.colour, key, state, frame)
        info = RGBDInfo(
            estimate=ci.estimate,
            report=ci.estimate,
            lost=ci.lost,
            ess=ci.ess,
            log_likelihood=ci.log_likelihood,
            vote=jnp.zeros((1,), jnp.float32),
            target_occluded=jnp.array(False),
            resampled=ci.resampled,
            weights_invalid=ci.weights_invalid,
            windowed=ci.windowed,
        )
        return state, info

    return Filter(init=init, step=step)


# ----------------------------------------------------------------------------- sequences


def track(filt: Filter, params, key: Array, frames: Frame, box_xywh: Array, background=None):
    """A whole sequence as one ``lax.scan`` (as ``cpf_jax.colour.track``, plus the background).

    ``frames``: ``Frame`` of ``[T, ...]`` arrays; init on ``frames[0]``, steps on
    ``1..T-1``. Returns ``(final_state, infos)`` with infos of length ``T - 1``.
    Works under ``jit`` and ``vmap``.
    """
    return scan_filter(filt, params, key, frames, box_xywh, background)


def track_boxes(
    filt: Filter, params, key: Array, frames: Frame, box_xywh: Array, background=None
) -> tuple[Array, Array]:
    """``([T, 4] reported boxes, [T] lost)``: the initial box, then every step's report."""
    _, infos = track(filt, params, key, frames, box_xywh, background)
    box = jnp.asarray(box_xywh, jnp.float32)[None]
    boxes = jnp.concatenate([box, infos.report], axis=0)
    lost = jnp.concatenate([jnp.zeros((1,), bool), infos.lost])
    return boxes, lost


# ----------------------------------------------------------------------------- learning


def fit_beta(
    ratios: Array, weights: Array | None = None, method: str = "moments", iters: int = 50
) -> tuple[Array, Array]:
    """Fit ``Beta(a, b)`` to samples ``ratios [..., M]`` in ``(0, 1)`` along the last axis.

    ``method="moments"``: method of moments, ``a = m k``, ``b = (1 - m) k`` with
    ``k = m (1 - m) / v - 1`` (sample mean ``m``, variance ``v``). ``"mle"``:
    maximum likelihood by Newton's method on the two score equations
    ``psi(a) - psi(a + b) = mean log r``, ``psi(b) - psi(a + b) = mean log(1 - r)``
    (Minka's fixed point in Newton form), started from the moments fit. Samples
    are clipped to ``[1e-3, 1 - 1e-3]``; ``weights [..., M]`` (optional, e.g. 0
    for occluded frames) weight them. Returns ``(a [...], b [...])``.
    """
    if method not in ("moments", "mle"):
        raise ValueError(f"method must be 'moments' or 'mle', got {method!r}")
    r = jnp.clip(jnp.asarray(ratios, jnp.float32), 1e-3, 1.0 - 1e-3)
    wgt = jnp.ones_like(r) if weights is None else jnp.asarray(weights, jnp.float32)
    tot = jnp.maximum(jnp.sum(wgt, -1), 1e-9)
    m = jnp.sum(wgt * r, -1) / tot
    v = jnp.sum(wgt * (r - m[..., None]) ** 2, -1) / tot
    kk = jnp.maximum(m * (1.0 - m) / jnp.maximum(v, 1e-9) - 1.0, 1e-3)
    a, b = m * kk, (1.0 - m) * kk
    if method == "moments":
        return a, b
    s1 = jnp.sum(wgt * jnp.log(r), -1) / tot
    s2 = jnp.sum(wgt * jnp.log1p(-r), -1) / tot
    x = jnp.stack([jnp.log(a), jnp.log(b)], -1)  # Newton in log space keeps a, b > 0

    def newton(x, _):
        a, b = jnp.exp(x[..., 0]), jnp.exp(x[..., 1])
        g1 = digamma(a) - digamma(a + b) - s1
        g2 = digamma(b) - digamma(a + b) - s2
        t_ab = polygamma(1, a + b)
        j11 = (polygamma(1, a) - t_ab) * a  # d g1 / d log a
        j12 = -t_ab * b
        j21 = -t_ab * a
        j22 = (polygamma(1, b) - t_ab) * b
        det = j11 * j22 - j12 * j21
        dx0 = (j22 * g1 - j12 * g2) / det
        dx1 = (-j21 * g1 + j11 * g2) / det
        step = jnp.clip(jnp.stack([dx0, dx1], -1), -1.0, 1.0)
        return x - step, None

    x, _ = jax.lax.scan(newton, x, None, length=iters)
    return jnp.exp(x[..., 0]), jnp.exp(x[..., 1])


def cell_foreground_ratios(foreground: Array, boxes_xywh: Array, k: int) -> Array:
    """Foreground ratio ``[T, k*k]`` of the cells of ``boxes [T, 4]`` in masks ``[T, H, W]``.

    The training statistic of eq. 2: share of foreground pixels in each cell
    of each (ground-truth) box, cells clipped to the frame (0 for an empty cell).
    """
    fg = jnp.asarray(foreground, bool)
    height, width = fg.shape[-2:]

    def one(mask, box):
        rects = box_ops.xywh_to_rect(grid_cells(box, k))
        counts = box_histograms(jnp.where(mask, 0, -1), rects, 1)[:, 0]
        area = _clipped_area(rects, width, height)
        return jnp.where(area > 0, counts / jnp.maximum(area, 1.0), 0.0)

    return jax.vmap(one)(fg, jnp.asarray(boxes_xywh, jnp.float32))
