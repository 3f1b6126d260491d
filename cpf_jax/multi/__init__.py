"""Several people at once (SPEC C9): one RGB-D box filter per slot, depth-ordered mutual
occlusion, exclusion, births from the person detector, deaths, identities through
crossings and re-entry.

::

    config = MultiConfig().with_window((80, 200), (424, 512))
    filt = build_multi_filter(config)
    params = default_multi_params(config)
    state, infos = track_people(filt, params, key, frames, Context(background=bg))
    rows = people_rows(infos)   # (frame, id, x, y, w, h, conf), MOTChallenge's columns

``config.py`` holds the static settings and ``params.py`` the continuous ones; ``claim.py``
decides who owns each pixel and what each slot's filter sees, ``births.py`` finds new
people, ``tracks.py`` and ``reid.py`` keep the targets' lives and identities, and
``filter.py`` composes them into the step.
"""

from cpf_jax.multi.config import (
    ACTIVE,
    FREE,
    LOST,
    SLOT_LOOPS,
    STATUS_NAMES,
    TENTATIVE,
    MultiConfig,
)
from cpf_jax.multi.filter import (
    MultiInfo,
    MultiState,
    build_multi_filter,
    people_rows,
    track_people,
)
from cpf_jax.multi.params import (
    MultiParams,
    default_multi_params,
    multi_props,
    multi_spec,
)
from cpf_jax.multi.tracks import Events, Tracks

__all__ = [
    "ACTIVE",
    "FREE",
    "LOST",
    "SLOT_LOOPS",
    "STATUS_NAMES",
    "TENTATIVE",
    "Events",
    "MultiConfig",
    "MultiInfo",
    "MultiParams",
    "MultiState",
    "Tracks",
    "build_multi_filter",
    "default_multi_params",
    "multi_props",
    "multi_spec",
    "people_rows",
    "track_people",
]
