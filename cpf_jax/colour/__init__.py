"""Colour layer: a box particle filter on H-S(V) histograms (thesis ch. 3, SPEC C1).

::

    config = ColourConfig(n_particles=200).with_window(box[2:], frame_hw)
    filt = build_colour_filter(config)
    params = default_colour_params()
    state = filt.init(params, key, frame, box)
    state, info = filt.step(params, key, state, frame)   # info.box, info.lost, info.ess

``config.py`` holds the static settings, ``params.py`` the continuous parameters with
their constraints, ``appearance.py`` the histograms, contrast and layout model,
``templates.py`` what the filter learns, ``proposal.py`` how it moves its particles and
``filter.py`` the step that composes them.
"""

from cpf_jax.colour.appearance import (
    box_parts,
    contrast_table,
    contrast_values,
    contrast_weights,
    layout_table,
    layout_values,
    layout_vectors,
    luminance,
    mirror_layout,
    mixture_weights,
    reference_histogram,
)
from cpf_jax.colour.config import (
    COLOUR_BINS,
    CONTRASTS,
    ESTIMATORS,
    LAYOUT_FEATURES,
    UNSEEN,
    ColourConfig,
    bin_index,
    n_bins_of,
)
from cpf_jax.colour.correlation import CorrelationConfig, CorrelationParams
from cpf_jax.colour.filter import ColourInfo, ColourState, build_colour_filter
from cpf_jax.colour.params import (
    COLOUR,
    COLOUR_PROPS,
    ColourParams,
    ContrastParams,
    EstimateParams,
    HistogramParams,
    LayoutParams,
    TemplateParams,
    default_colour_params,
)

__all__ = [
    "COLOUR",
    "COLOUR_BINS",
    "COLOUR_PROPS",
    "CONTRASTS",
    "ESTIMATORS",
    "LAYOUT_FEATURES",
    "UNSEEN",
    "ColourConfig",
    "ColourInfo",
    "ColourParams",
    "ColourState",
    "ContrastParams",
    "CorrelationConfig",
    "CorrelationParams",
    "EstimateParams",
    "HistogramParams",
    "LayoutParams",
    "TemplateParams",
    "bin_index",
    "box_parts",
    "build_colour_filter",
    "contrast_table",
    "contrast_values",
    "contrast_weights",
    "default_colour_params",
    "layout_table",
    "layout_values",
    "layout_vectors",
    "luminance",
    "mirror_layout",
    "mixture_weights",
    "n_bins_of",
    "reference_histogram",
]
