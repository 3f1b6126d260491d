"""RGB-D box filter with grid cells and occlusion flags (the RGB-D occlusion paper, SPEC C2).

::

    config = RGBDConfig(variant="grid-occlusion").with_window(box[2:], frame_hw)
    filt = build_rgbd_filter(config)
    params = default_rgbd_params(config)
    state = filt.init(params, key, frame, box, Context(background=median_background(c, d)))
    state, info = filt.step(params, key, state, frame)   # info.box, info.lost, info.vote

``config.py`` holds the static settings and ``params.py`` the continuous parameters with
their constraints; ``observe.py`` reads a frame, ``cells.py`` scores cells (paper eqs.
1-5), ``flags.py`` marginalises the occlusion flags (2.5), ``proposal.py`` moves the
particles, ``depth.py`` and ``templates.py`` hold what the filter learns (eqs. 7-8),
``report.py`` the box it reports, ``beta.py`` the foreground-ratio model, and
``filter.py`` the step that composes them.
"""

from cpf_jax.rgbd.beta import (
    beta_fill_shift,
    cell_foreground_ratios,
    fill_adapted,
    fit_beta,
    initial_fill,
)
from cpf_jax.rgbd.cells import CellTerms, cell_terms
from cpf_jax.rgbd.config import REPORTS, TRANSITIONS, VARIANTS, RGBDConfig
from cpf_jax.rgbd.filter import OcclusionTrack, RGBDInfo, RGBDState, build_rgbd_filter
from cpf_jax.rgbd.flags import flag_bits, kronecker_transition
from cpf_jax.rgbd.params import (
    DEFAULT_BETA,
    RGBD,
    RGBDParams,
    default_rgbd_params,
    rgbd_props,
    rgbd_spec,
)

__all__ = [
    "DEFAULT_BETA",
    "REPORTS",
    "RGBD",
    "TRANSITIONS",
    "VARIANTS",
    "CellTerms",
    "OcclusionTrack",
    "RGBDConfig",
    "RGBDInfo",
    "RGBDParams",
    "RGBDState",
    "beta_fill_shift",
    "build_rgbd_filter",
    "cell_foreground_ratios",
    "cell_terms",
    "default_rgbd_params",
    "fill_adapted",
    "fit_beta",
    "flag_bits",
    "initial_fill",
    "kronecker_transition",
    "rgbd_props",
    "rgbd_spec",
]
