"""Continuous parameters of the RGB-D box filter, one ``NamedTuple`` per term, each value
declared beside its constraint and trainable flag (``cpf_jax.params``)."""

from __future__ import annotations

from typing import NamedTuple

from jax import Array

from cpf_jax.dynamics import DEFAULT_TAU, MOTION, MotionParams
from cpf_jax.likelihood import ASPECT, AspectParams
from cpf_jax.params import P, props, values
from cpf_jax.rgbd.config import RGBDConfig

__all__ = [
    "BETA_FALLBACK",
    "DEFAULT_BETA",
    "DEFAULT_BORDER_BETA",
    "RGBD_TAU",
    "ForegroundParams",
    "BetaParams",
    "BorderParams",
    "CellColourParams",
    "DepthParams",
    "BodyParams",
    "OcclusionParams",
    "TargetParams",
    "DetectorParams",
    "ReportParams",
    "RGBDParams",
    "RGBD",
    "rgbd_spec",
    "rgbd_props",
    "default_rgbd_params",
]

#: Beta shapes ``(a, b)`` of the per-cell foreground ratio (paper eq. 2), fitted by
#: maximum likelihood (``experiments/occlusion_tables.py --fit-only``) on the tight boxes
#: of unoccluded frames of the synthetic training scenes; keyed by grid size k, cells
#: row-major. Other k take ``BETA_FALLBACK``.
DEFAULT_BETA: dict[int, tuple[tuple[float, ...], tuple[float, ...]]] = {
    1: ((3.52,), (7.89,)),
    2: ((1.09, 0.93, 2.42, 2.44), (2.29, 2.03, 5.88, 5.89)),
}
BETA_FALLBACK = (2.0, 4.0)
#: Border strips (inner top, bottom, left, right; outer t, b, l, r): inner strips fitted
#: as ``DEFAULT_BETA``; every training ratio of an outer strip is 0, where a fit
#: degenerates to a spike, so they take Beta(1, 30): log-density about -29 r.
DEFAULT_BORDER_BETA: tuple[tuple[float, ...], tuple[float, ...]] = (
    (4.85, 4.62, 1.34, 1.29, 1.0, 1.0, 1.0, 1.0),
    (14.24, 13.26, 15.88, 14.06, 30.0, 30.0, 30.0, 30.0),
)
#: Motion noise for a 200 px box: the colour layer's positions, sizes 4x calmer (the
#: reported box comes from the target's pixels, so the tracked box need not follow the
#: gait's width changes, and a partly hidden target's box does not shrink onto its
#: visible part).
RGBD_TAU = (DEFAULT_TAU[0], DEFAULT_TAU[1], DEFAULT_TAU[2], DEFAULT_TAU[3], 1.5, 1.5, 0.2, 0.2)


class ForegroundParams(NamedTuple):
    """Foreground against the background model (paper 2.3)."""

    depth_abs: Array  # mm: nearer than the background by more than this is foreground ...
    depth_rel: Array  # ... or by this fraction of the background's depth
    colour: Array  # uint8 levels of colour change where depth is missing
    background_rate: Array  # running background update (``config.background_update``)


class BetaParams(NamedTuple):
    """Beta likelihood of the foreground ratio (paper eq. 2), per cell and for the box."""

    a: Array  # [C]
    b: Array  # [C]
    weight: Array  # weight of every Beta term (1: the paper)
    floor: Array  # lowest log-density of a cell's or the box's Beta term
    box_a: Array  # Beta of the whole box's (visible cells') foreground ratio
    box_b: Array
    fill_adapt: Array  # gain of the shift of every Beta mean towards the first box's fill
    fill_deadzone: Array  # ... beyond this many logits from the fitted mean


class BorderParams(NamedTuple):
    """Beta likelihood of the border strips' foreground ratios."""

    a: Array  # [8] inner t/b/l/r, outer t/b/l/r
    b: Array  # [8]
    floor: Array  # lowest log-density of one strip


class CellColourParams(NamedTuple):
    """The cells' colour term (paper eqs. 4-5) and its template (eq. 7)."""

    sigma: Array  # width on the Bhattacharyya distance
    floor: Array  # lowest log-likelihood of a cell's colour term
    rate: Array  # 1 - lambda of eq. 7
    gate: Array  # templates learn only from cells closer than this distance


class DepthParams(NamedTuple):
    """The cells' median-depth Gaussian (paper 2.4) and the moving depth templates."""

    sigma: Array  # mm, width of the Gaussian ...
    sigma_rel: Array  # ... plus this fraction of the template depth
    floor: Array  # lowest log-likelihood of a cell's depth term
    rate: Array  # 1 - lambda of eq. 7 for the depth templates
    velocity_rate: Array  # gain of the depth-velocity correction (0: templates stand still)
    velocity_fade: Array  # share of the velocity lost per frame without a depth update
    speed: Array  # mm per frame a template's target may move while not updated
    max_drift: Array  # mm, cap of speed x age


class BodyParams(NamedTuple):
    """The whole-body colour term and its template."""

    sigma: Array  # width on the Bhattacharyya distance ...
    ref: Array  # ... which scores 0 at this distance
    floor: Array  # lowest log-likelihood
    min_pixels: Array  # fewer visible foreground pixels: the term says nothing
    rate: Array  # 1 - lambda of the template after the warm-up ...
    warmup: Array  # ... a running mean of the unoccluded frames among the first steps


class OcclusionParams(NamedTuple):
    """Occluded cells (paper eq. 1), their flags' Markov chain (2.5) and the search."""

    log_occluded: Array  # eq. 1's constant, log
    margin: Array  # mm: nearer than the template by more than this ...
    margin_rel: Array  # ... or this fraction of it is an occluder
    eps: Array  # floor of the occluder evidence (log eps: "nothing in front")
    unknown: Array  # occluder evidence of a cell with too few depth samples
    p_occlude: Array  # per-cell P(visible -> occluded) per frame
    p_reveal: Array  # per-cell P(occluded -> visible) per frame
    transition: Array | None  # optional full [2^C, 2^C] row-stochastic matrix
    vote_threshold: Array  # a cell is voted occluded when its vote exceeds this
    spread_rate: Array  # extra position noise per occluded frame (x tau)
    spread_max: Array  # cap of the position-noise multiplier


class TargetParams(NamedTuple):
    """Which pixels are the target's: foreground near the depth templates."""

    gate: Array  # mm: within this of the template depth ...
    gate_rel: Array  # ... or this fraction of it
    drift_max: Array  # mm, cap of the widening of the gate while hidden or stale
    min_coverage: Array  # fewer target pixels (share of the box): the target is hidden


class DetectorParams(NamedTuple):
    """The fast-motion component of the transition and the detector proposal."""

    fast_fraction: Array  # share of the fast-motion component ...
    fast_sigma: Array  # ... a Gaussian of this sd (fraction of the box height)
    fast_scale: Array  # ... with log-normal sizes of this log-sd
    ring: Array  # ring around a detector box (fraction of its size) that should be empty
    min_ratio: Array  # least tightness, relative to the best box near the prediction ...
    floor: Array  # ... and absolute
    need: Array  # draw from the detector only when the prediction's fit is below this
    power: Array  # proposal density ~ tightness ** power x locality


class ReportParams(NamedTuple):
    """The reported box: the tight box of the target's pixels (``report="pixels"``)."""

    margin: Array  # search the estimate grown by this per side
    min_pixels: Array  # ignore columns / rows with fewer target pixels
    gap: Array  # ... and those further than this share of the box from the main run


class RGBDParams(NamedTuple):
    """Every continuous parameter of the RGB-D box filter (a pytree)."""

    motion: MotionParams
    aspect: AspectParams
    foreground: ForegroundParams
    beta: BetaParams
    border: BorderParams
    colour: CellColourParams
    depth: DepthParams
    body: BodyParams
    occlusion: OcclusionParams
    target: TargetParams
    detector: DetectorParams
    report: ReportParams


#: Defaults with their constraints (the per-cell Beta shapes for the 2 x 2 grid; see
#: ``rgbd_spec`` for other grids). Counts and thresholds that act only through
#: comparisons have no gradient and are not trainable.
RGBD = RGBDParams(
    motion=MOTION._replace(tau=P(RGBD_TAU, "softplus")),
    aspect=ASPECT,
    foreground=ForegroundParams(
        depth_abs=P(150.0, "softplus", False),
        depth_rel=P(0.05, "softplus", False),
        colour=P(40.0, "softplus", False),
        background_rate=P(0.02, "sigmoid"),
    ),
    beta=BetaParams(
        a=P(DEFAULT_BETA[2][0], "softplus"),
        b=P(DEFAULT_BETA[2][1], "softplus"),
        weight=P(1.0, "softplus"),
        # The Beta at a ratio of about 0.93: the fitted shapes come from synthetic walkers
        # that fill a third of their box, real people fill 60-90 %.
        floor=P(-10.0),
        box_a=P(DEFAULT_BETA[1][0][0], "softplus"),
        box_b=P(DEFAULT_BETA[1][1][0], "softplus"),
        fill_adapt=P(1.0, "softplus"),
        # 1.5 standard deviations of the logit of the whole-box Beta (3.52, 7.89).
        fill_deadzone=P(1.0, "softplus"),
    ),
    border=BorderParams(
        a=P(DEFAULT_BORDER_BETA[0], "softplus"),
        b=P(DEFAULT_BORDER_BETA[1], "softplus"),
        floor=P(-6.0),
    ),
    # sigma 0.2: a view change of the same person (d ~ 0.3) costs about 1 nat.
    colour=CellColourParams(
        sigma=P(0.2, "softplus"),
        floor=P(-12.0),
        rate=P(0.02, "sigmoid"),
        gate=P(0.4, "sigmoid", False),
    ),
    depth=DepthParams(
        sigma=P(100.0, "softplus"),
        sigma_rel=P(0.05, "softplus"),
        floor=P(-8.0),
        rate=P(0.5, "sigmoid"),
        velocity_rate=P(0.2, "sigmoid"),
        # A hidden person may stop or turn round: the velocity fades while unseen.
        velocity_fade=P(0.3, "sigmoid"),
        speed=P(60.0, "softplus"),
        max_drift=P(500.0, "softplus"),
    ),
    body=BodyParams(
        sigma=P(0.2, "softplus"),
        ref=P(0.4, "softplus"),
        floor=P(-6.0),
        min_pixels=P(30.0, "softplus", False),
        rate=P(0.02, "sigmoid"),
        warmup=P(5.0, "softplus", False),
    ),
    occlusion=OcclusionParams(
        log_occluded=P(-10.0),
        margin=P(400.0, "softplus"),
        margin_rel=P(0.12, "softplus"),
        eps=P(1e-4, "sigmoid"),
        unknown=P(0.3, "sigmoid"),
        p_occlude=P(0.1, "sigmoid"),
        p_reveal=P(0.1, "sigmoid"),
        transition=P(None, trainable=False),
        vote_threshold=P(0.5, "sigmoid", False),
        spread_rate=P(0.15, "softplus"),
        spread_max=P(3.0, "softplus"),
    ),
    target=TargetParams(
        gate=P(300.0, "softplus"),
        gate_rel=P(0.1, "softplus"),
        drift_max=P(900.0, "softplus"),
        min_coverage=P(0.02, "sigmoid", False),
    ),
    detector=DetectorParams(
        fast_fraction=P(0.05, "sigmoid"),
        fast_sigma=P(0.5, "softplus"),
        fast_scale=P(0.2, "softplus"),
        ring=P(0.15, "softplus"),
        min_ratio=P(0.6, "sigmoid", False),
        floor=P(0.1, "sigmoid", False),
        need=P(0.9, "sigmoid", False),
        power=P(4.0, "softplus"),
    ),
    report=ReportParams(
        margin=P(0.25, "softplus", False),
        min_pixels=P(2.0, "softplus", False),
        gap=P(0.3, "softplus", False),
    ),
)


def rgbd_spec(config: RGBDConfig | None = None) -> RGBDParams:
    """``RGBD`` with the per-cell Beta shapes of ``config``'s grid (``DEFAULT_BETA``, else
    ``BETA_FALLBACK`` for every cell)."""
    config = config or RGBDConfig()
    c = config.n_cells
    if config.k in DEFAULT_BETA and len(DEFAULT_BETA[config.k][0]) == c:
        a, b = DEFAULT_BETA[config.k]
    else:
        a, b = (BETA_FALLBACK[0],) * c, (BETA_FALLBACK[1],) * c
    beta = RGBD.beta._replace(a=P(a, "softplus"), b=P(b, "softplus"))
    return RGBD._replace(beta=beta)


def rgbd_props(config: RGBDConfig | None = None) -> RGBDParams:
    """How each RGB-D parameter is tuned (``cpf_jax.tuning``)."""
    return props(rgbd_spec(config))


def default_rgbd_params(config: RGBDConfig | None = None) -> RGBDParams:
    """The RGB-D filter's default parameters for ``config``'s grid (float32 arrays)."""
    return values(rgbd_spec(config))
