"""Static settings of the RGB-D box filter (``RGBDConfig``): changing one recompiles."""

from __future__ import annotations

import dataclasses

from cpf_jax.colour.config import COLOUR_BINS, n_bins_of
from cpf_jax.dynamics import MODELS
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels.histogram import suggest_window

__all__ = ["VARIANTS", "REPORTS", "TRANSITIONS", "RGBDConfig"]

#: The RGB-D rows of the paper's Tables 1-2 (its "RGB" row is the colour layer,
#: ``cpf_jax.colour``): one cell, a grid of cells, a grid with occlusion flags.
VARIANTS = ("rgbd", "grid", "grid-occlusion")
#: What ``info.box`` is (``cpf_jax.rgbd.report``).
REPORTS = ("pixels", "cells", "box")
TRANSITIONS = ("auto", "full", "factorised")
#: ``RGBDConfig.with_window``'s growth of the first window over the initial box.
FIRST_WINDOW_GROWTH = 1.1


@dataclasses.dataclass(frozen=True)
class RGBDConfig:
    """Static, hashable settings of the RGB-D box filter (``cpf_jax.rgbd``)."""

    variant: str = "grid-occlusion"
    n_particles: int = 300
    grid: int = 2  # k of the grid variants ("rgbd" always uses one cell)
    bins: tuple[int, ...] = COLOUR_BINS  # colour bins, as in ColourConfig
    depth_bins: int = 64  # log-spaced depth bins of the per-cell median
    depth_range: tuple[float, float] = (400.0, 10000.0)  # mm
    model: str = "ar1"
    hierarchical: bool = True
    resampler: str = "systematic"
    ess_threshold: float = 1.0
    min_size: float = 8.0
    init_spread: float = 0.0
    window: tuple[int, int] | None = None
    # A smaller window the cells' counts try before ``window`` (None: none): a table costs
    # its pixels, and one frame's cloud fits a window near the box's size while ``window``
    # must also hold the target as it grows. Counts are exact through either.
    first_window: tuple[int, int] | None = None
    tau_height: float | None = 200.0
    aspect_prior: bool = True
    template_update: bool = True  # eq. 7-8 in the cells voted visible
    background_update: bool = False  # running update of the background on its own pixels
    # Without a background model (``context.background`` None) every pixel is unseen, and
    # each frame's scene is the nearer of a plane ``behind_mm`` behind the target's depth
    # (what lies farther is neither the target nor what hides it) and the frame's own scene
    # along each row (``kernels.background.side_scene``) at these multiples of the
    # estimate's width to either side; nothing is kept from frame to frame, so a camera
    # may move. None: every pixel is foreground.
    side_scene: tuple[float, ...] | None = (0.75, 1.5)
    behind_mm: float = 500.0
    flag_transition: str = "auto"
    max_full_cells: int = 6  # "auto": the full 2^C matrix up to this many cells
    report: str = "pixels"
    min_depth_count: int = 8  # fewer foreground depth samples in a cell: no depth terms
    # Share of particles re-drawn, while the target is voted occluded, around random
    # foreground pixels at the target's depth (0: spreading only), on a grid of this stride.
    recovery_fraction: float = 0.2
    recovery_stride: int = 4
    # Data-driven proposal: share of the particles whose box is drawn around boxes full of
    # foreground at the target's depth (0: the motion prior only), on a map of this stride.
    detector_fraction: float = 0.2
    detector_stride: int = 8
    # Its box sizes: the estimate's width x exp(i step_w) and height x exp(j step_h),
    # |i| <= scales[0], |j| <= scales[1] (a geometric grid that tiles log-size).
    detector_scales: tuple[int, int] = (2, 3)
    detector_scale_step: tuple[float, float] = (0.15, 0.12)
    # Background pixels count as one extra colour bin: the histogram of the paper's
    # "preprocessed foreground RGB image", which also sees how much of a cell is
    # foreground (False: foreground pixels only).
    background_bin: bool = True
    # Grid variants: also score the foreground ratio of the whole box (pooled over the
    # cells visible in each flag state): per-cell ratios alone do not pin the scale.
    box_term: bool = True
    # Border strips, as a fraction of the box size (0: off): inside each edge of a tight
    # box there is foreground, just outside none at the target's depth.
    border: float = 0.1
    # Whole-body colour term: the visible cells' foreground colours pooled, against one
    # slowly learnt template of the whole person.
    body_term: bool = True
    # Cap the fast-motion component's length by the initial box's height at the target's
    # depth (None: on for "grid-occlusion" only, whose depth templates learn only in cells
    # voted visible).
    fast_depth_cap: bool | None = None
    # The info carries the weighed particles before resampling (``filter.WeighedCloud``): a
    # viewer colours them by weight.
    report_weights: bool = False

    def __post_init__(self) -> None:
        lo, hi = self.depth_range
        checks = (
            (self.variant in VARIANTS, f"variant must be one of {VARIANTS}, got {self.variant!r}"),
            (self.n_particles >= 1, f"n_particles must be >= 1, got {self.n_particles}"),
            (self.grid >= 1, f"grid must be >= 1, got {self.grid}"),
            (
                self.side_scene is None or (len(self.side_scene) > 0 and min(self.side_scene) > 0),
                f"side_scene must be None or positive widths, got {self.side_scene}",
            ),
            (self.model in MODELS, f"model must be one of {MODELS}, got {self.model!r}"),
            (
                self.resampler in rs.SCHEMES,
                f"resampler must be one of {tuple(rs.SCHEMES)}, got {self.resampler!r}",
            ),
            (
                self.flag_transition in TRANSITIONS,
                f"flag_transition must be one of {TRANSITIONS}, got {self.flag_transition!r}",
            ),
            (self.report in REPORTS, f"report must be one of {REPORTS}, got {self.report!r}"),
            (
                not (self.flag_transition == "full" and self.n_cells > 16),
                f"a full 2^C transition matrix needs C <= 16 cells, got {self.n_cells}",
            ),
            (
                0.0 <= self.detector_fraction < 1.0,
                f"detector_fraction must be in [0, 1), got {self.detector_fraction}",
            ),
            (
                self.detector_stride >= 1,
                f"detector_stride must be >= 1, got {self.detector_stride}",
            ),
            (
                min(self.detector_scales) >= 0 and min(self.detector_scale_step) > 0,
                "detector_scales must be >= 0 and detector_scale_step > 0, got "
                f"{self.detector_scales}, {self.detector_scale_step}",
            ),
            (
                self.n_cells <= 30,
                f"at most 30 cells (flags are int32 bit masks), got {self.n_cells}",
            ),
            (0 < lo < hi, f"depth_range must be 0 < near < far, got {self.depth_range}"),
        )
        for ok, message in checks:
            if not ok:
                raise ValueError(message)

    @property
    def k(self) -> int:
        """Cells per side: 1 for "rgbd", ``grid`` for the grid variants."""
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
    def count_windows(self) -> tuple | None:
        """The windows the cells' counts try in turn (``kernels.histogram.rect_reduce``)."""
        if self.window is None or self.first_window is None:
            return self.window
        return (self.first_window, self.window)

    @property
    def cell_window(self) -> tuple[int, int] | None:
        """The window one cell of a box is counted in by itself (``box_histograms``'s
        ``each``): the first count window over ``k`` per side, rounded up to 8 px; None
        for one cell or without a window."""
        if self.k == 1 or self.window is None:
            return None
        h, w = self.count_windows[0]
        return (-(-h // (8 * self.k)) * 8, -(-w // (8 * self.k)) * 8)

    def with_window(
        self,
        box_wh: tuple[float, float],
        frame_hw: tuple[int, int],
        growth: float = 1.5,
        first_growth: float | None = FIRST_WINDOW_GROWTH,
    ) -> RGBDConfig:
        """This config with a histogram window for a box of ``box_wh`` grown by ``growth``,
        and a first window for it grown by ``first_growth`` (None: none); both hold the
        spread of ``n_particles`` centres at 10 px (``suggest_window``)."""
        hw = (int(frame_hw[0]), int(frame_hw[1]))
        w, h = (float(v) * growth for v in box_wh)
        window = suggest_window((w, h), 10.0, hw)
        first = None
        if first_growth is not None:
            fw, fh = (float(v) * first_growth for v in box_wh)
            first = suggest_window((fw, fh), 10.0, hw, n_particles=self.n_particles)
            first = None if first[0] * first[1] >= window[0] * window[1] else first
        return dataclasses.replace(self, window=window, first_window=first)
