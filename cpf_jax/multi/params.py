"""Continuous parameters of the multi-person tracker: every slot's RGB-D filter parameters
and the track management's, each value declared beside its constraint (``cpf_jax.params``).

Counts are in frames; the tracker's thresholds act through comparisons and are not
trainable."""

from __future__ import annotations

from typing import NamedTuple

from jax import Array

from cpf_jax.multi.config import MultiConfig
from cpf_jax.params import P, props, values
from cpf_jax.rgbd.params import RGBDParams, rgbd_spec

__all__ = [
    "ClaimParams",
    "LifeParams",
    "ReidParams",
    "MultiParams",
    "TRACK_SPEC",
    "multi_spec",
    "multi_props",
    "default_multi_params",
]


class ClaimParams(NamedTuple):
    """Which pixels a target claims (``claim.py``) and when two targets are one."""

    margin: Array  # its predicted box grown by this share per side
    fake_margins: Array  # claimed pixels are an occluder this many occluder margins nearer
    duplicate_overlap: Array  # boxes at one depth sharing this share of columns are one person
    reanchor_growth: Array  # a target grows onto the rest of its person when this much larger
    reanchor_margin: Array  # ... a blob within its box grown by this share per side ...
    reanchor_aspect: Array  # ... at least this wide / tall (narrower: a limb, a sliver)


class LifeParams(NamedTuple):
    """Births, confirmation, loss and death (``tracks.py``)."""

    birth_confidence: Array  # least detector confidence (``detect.person_confidence``)
    birth_aspect: Array  # least width / height of a new person's box (narrower: a limb)
    confirm: Array  # found frames in a row that confirm a tentative target
    tentative_misses: Array  # missed frames in a row that drop a tentative target
    lost_after: Array  # missed frames in a row after which a confirmed target is lost
    forget_after: Array  # missed frames in a row after which a lost target dies
    verify_after: Array  # missed frames after which a target found again must look like it
    min_evidence: Array  # least share of its estimate its own unclaimed pixels fill (found)
    hidden_share: Array  # ... or of the rest of its claim box, when nearer targets claim this
    behind_appearance: Array  # ... and what shows is this close to its body colours


class ReidParams(NamedTuple):
    """Re-identification of a newly confirmed target as a lost or hidden one (``reid.py``)."""

    appearance: Array  # most Bhattacharyya distance of the body colours
    depth: Array  # mm: most depth difference ...
    depth_speed: Array  # ... widened by this per missed frame
    reach: Array  # most centre distance (box heights) ...
    reach_speed: Array  # ... widened by this per missed frame
    weight_depth: Array  # cost of one depth gate, against a distance of 1 in appearance
    weight_reach: Array  # cost of one reach


class MultiParams(NamedTuple):
    """Every continuous parameter of the multi-person tracker (a pytree)."""

    rgbd: RGBDParams
    claim: ClaimParams
    life: LifeParams
    reid: ReidParams


#: The track management's defaults (``multi_spec`` adds the RGB-D filter's).
TRACK_SPEC = (
    ClaimParams(
        margin=P(0.2, "softplus", False),
        fake_margins=P(2.0, "softplus", False),
        duplicate_overlap=P(0.5, "sigmoid", False),
        reanchor_growth=P(1.3, "softplus", False),
        reanchor_margin=P(0.2, "softplus", False),
        reanchor_aspect=P(0.2, "softplus", False),
    ),
    LifeParams(
        birth_confidence=P(0.3, "sigmoid", False),
        birth_aspect=P(0.2, "softplus", False),
        confirm=P(3.0, "softplus", False),
        tentative_misses=P(2.0, "softplus", False),
        lost_after=P(15.0, "softplus", False),
        forget_after=P(100.0, "softplus", False),
        verify_after=P(5.0, "softplus", False),
        min_evidence=P(0.05, "sigmoid", False),
        hidden_share=P(2.0, "softplus", False),
        behind_appearance=P(1.0, "softplus", False),
    ),
    ReidParams(
        appearance=P(0.5, "sigmoid", False),
        depth=P(600.0, "softplus", False),
        depth_speed=P(40.0, "softplus", False),
        reach=P(1.0, "softplus", False),
        reach_speed=P(0.1, "softplus", False),
        weight_depth=P(0.3, "softplus", False),
        weight_reach=P(0.3, "softplus", False),
    ),
)


def multi_spec(config: MultiConfig | None = None) -> MultiParams:
    """The ``P`` tree of the tracker's parameters for ``config``'s RGB-D grid."""
    config = config or MultiConfig()
    return MultiParams(rgbd_spec(config.rgbd), *TRACK_SPEC)


def multi_props(config: MultiConfig | None = None) -> MultiParams:
    """How each of the tracker's parameters is tuned (``cpf_jax.tuning``)."""
    return props(multi_spec(config))


def default_multi_params(config: MultiConfig | None = None) -> MultiParams:
    """The tracker's default parameters (float32 arrays)."""
    return values(multi_spec(config))
