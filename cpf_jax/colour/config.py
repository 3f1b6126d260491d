"""Static settings of the colour layer (``ColourConfig``): changing one recompiles."""

from __future__ import annotations

import dataclasses

from cpf_jax.colour.camera import DOWNSCALE as CAMERA_DOWNSCALE
from cpf_jax.colour.correlation import CorrelationConfig
from cpf_jax.dynamics import DEFAULT_TAU, MODELS, RNGS
from cpf_jax.kernels import resample as rs
from cpf_jax.kernels.color import hsv_bin_index
from cpf_jax.kernels.histogram import DEFAULT_BINS, DEFAULT_CHUNK, suggest_window

__all__ = [
    "COLOUR_BINS",
    "CONTRASTS",
    "ESTIMATORS",
    "LAYOUT_FEATURES",
    "UNSEEN",
    "ColourConfig",
    "bin_index",
    "n_bins_of",
]

ESTIMATORS = ("mean", "map", "robust")
CONTRASTS = ("mixture", "linear")
#: What the linear contrast weights make of a colour seen neither in the initial box nor
#: in its ring (``ColourConfig.unseen``).
UNSEEN = ("background", "neutral")
#: Features of the layout term (``ColourConfig.layout_feature``).
LAYOUT_FEATURES = ("luminance", "gradient")

#: 8 x 8 H-S bins for chromatic pixels and 8 value bins for achromatic (dark, grey,
#: white) pixels, whose hue is noise (``kernels.color.hsv_bin_index``); ``(8, 8)`` is the
#: thesis's pure H-S histogram.
COLOUR_BINS = (*DEFAULT_BINS, 8)


def n_bins_of(bins: tuple[int, ...]) -> int:
    """Histogram length of a ``(h, s)`` or ``(h, s, v)`` bin spec."""
    return bins[0] * bins[1] + (bins[2] if len(bins) > 2 else 0)


def bin_index(colour, bins: tuple[int, ...]):
    """``[H, W] int32`` bin of every pixel of ``[H, W, 3] uint8`` RGB for a bin spec."""
    return hsv_bin_index(colour, bins[0], bins[1], bins[2] if len(bins) > 2 else 0)


@dataclasses.dataclass(frozen=True)
class ColourConfig:
    """Static, hashable settings of the colour layer (``cpf_jax.colour``)."""

    n_particles: int = 100
    # (hue, saturation) bins, or (hue, saturation, value) with value bins for the
    # achromatic pixels (Perez et al. 2002).
    bins: tuple[int, ...] = COLOUR_BINS
    # One of cpf_jax.dynamics.MODELS. The random walk (thesis eq. 3.33): a velocity
    # carries the box past a walker who stops or turns round.
    model: str = "random_walk"
    # Motion-guided sampling (thesis 2.2, 3.4): the ar1 models stretch their noise along
    # each particle's velocity; under the random walk a share of the particles moves by
    # the estimate's smoothed velocity.
    hierarchical: bool = True
    # Smoothing of that velocity: each frame it moves this far towards the estimate's
    # last displacement (1: the last displacement alone).
    velocity_rate: float = 0.5
    estimator: str = "mean"  # "mean" | "map" | "robust" (thesis 3.10 and 3.1)
    resampler: str = "systematic"  # key of cpf_jax.kernels.resample.SCHEMES
    ess_threshold: float = 1.0  # resample when ESS < threshold * N (1: every frame, SIR)
    # Slow update of the reference histograms from the estimate's (params.template).
    template_update: bool = True
    recovery_fraction: float = 0.1  # share of particles re-drawn while the target is lost
    # The target also counts as lost when the estimate's height falls below this share of
    # the initial box's (a cloud collapsed onto a small patch of similar colour; 0: off).
    collapse_ratio: float = 0.25
    min_size: float = 8.0  # px, smallest box side a particle may take
    init_spread: float = 0.0  # px, std of the initial cloud around the initial box
    # Static (h, w) window of the fast exact histogram path (None: whole-frame tables,
    # slower). ``with_window`` picks one from the initial box.
    window: tuple[int, int] | None = None
    # With a window: place it on the cloud's mean centre and keep the particle centres
    # inside it, so that every step takes the fast path (boxes larger than the window and
    # a lost target's frame-wide search fall back to the exact whole-frame path).
    contain: bool = True
    # Surround ring of the contrast weights: the initial box grown by this fraction of its
    # size on every side.
    surround_margin: float = 0.5
    # Horizontal stripes with one histogram each (a multi-part colour model, Perez et al.
    # 2002): they tell shirt-over-trousers from trousers-over-shirt; 1 is the thesis's.
    parts: int = 2
    # Centre-surround ring scored against each particle's box, as a fraction of the box
    # size per side (0: no ring).
    ring_margin: float = 0.3
    # tau holds for a box of this height (px); each particle's noise scales with its
    # height (None: tau in pixels, as in the thesis).
    tau_height: float | None = 200.0
    aspect_prior: bool = True  # log-normal prior on width / height (params.aspect)
    # Per-bin weights of the centre-surround term: "linear" (``contrast_weights``),
    # "mixture" (``mixture_weights``), or None: no such term (the thesis's likelihood).
    contrast: str | None = "linear"
    # Linear weights of colours seen neither in the initial box nor in its ring:
    # "neutral" (weight 0) or "background" (weight ``-threshold``).
    unseen: str = "neutral"
    # Layout term: the box cut into (rows, cols) cells, the normalised cross-correlation
    # of their mean feature with the initial box's (None: off). Histograms are blind to
    # where colours sit inside the box; this small template pins its vertical extent.
    layout: tuple[int, int] | None = (7, 3)
    # The layout cells' feature: "luminance" (cell means of brightness) or "gradient"
    # (gradient energy in four orientations, a small HOG-like shape template).
    layout_feature: str = "luminance"
    # Score a box by the better of the layout template and its mirror image: a person who
    # turns round is the mirror image of his first side view.
    layout_mirror: bool = False
    # Discriminative term: a correlation filter learnt online on the target against its
    # surround, one dense response map per frame that every particle reads (None: off).
    correlation: CorrelationConfig | None = None
    # Camera motion: the image's shift since the last frame (phase correlation of grey
    # frames downscaled by this factor) moves the cloud before the motion model (None: off).
    camera_motion: int | None = CAMERA_DOWNSCALE
    # Below this phase-correlation peak no single shift explains the frames: none is applied.
    camera_min_peak: float = 0.12
    rng: str = "hash"  # generator of the motion noise (cpf_jax.dynamics.RNGS)
    # Boxes per sequential block of the histogram gathers (None: all at once); the
    # default suits a CPU's 2 MB L2 cache, a GPU wants None or a large value.
    chunk: int | None = DEFAULT_CHUNK
    # The info carries the weighed particles before resampling (``filter.WeighedCloud``): a
    # viewer colours them by weight.
    report_weights: bool = False

    def __post_init__(self) -> None:
        checks = (
            (self.n_particles >= 1, f"n_particles must be >= 1, got {self.n_particles}"),
            (self.model in MODELS, f"model must be one of {MODELS}, got {self.model!r}"),
            (
                self.estimator in ESTIMATORS,
                f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}",
            ),
            (
                self.resampler in rs.SCHEMES,
                f"resampler must be one of {tuple(rs.SCHEMES)}, got {self.resampler!r}",
            ),
            (self.parts >= 1, f"parts must be >= 1, got {self.parts}"),
            (
                len(self.bins) in (2, 3) and min(self.bins[:2]) >= 1 and min(self.bins) >= 0,
                f"bins must be positive, got {self.bins}",
            ),
            (
                self.chunk is None or self.chunk >= 1,
                f"chunk must be None or >= 1, got {self.chunk}",
            ),
            (self.rng in RNGS, f"rng must be one of {RNGS}, got {self.rng!r}"),
            (
                self.camera_motion is None or self.camera_motion >= 1,
                f"camera_motion must be None or a downscale factor >= 1, got {self.camera_motion}",
            ),
            (
                0.0 <= self.collapse_ratio < 1.0,
                f"collapse_ratio must be in [0, 1), got {self.collapse_ratio}",
            ),
            (
                self.contrast is None or self.contrast in CONTRASTS,
                f"contrast must be None or one of {CONTRASTS}, got {self.contrast!r}",
            ),
            (self.unseen in UNSEEN, f"unseen must be one of {UNSEEN}, got {self.unseen!r}"),
            (
                self.layout is None or (len(self.layout) == 2 and min(self.layout) >= 1),
                f"layout must be None or (rows, cols) >= 1, got {self.layout}",
            ),
            (
                self.layout_feature in LAYOUT_FEATURES,
                f"layout_feature must be one of {LAYOUT_FEATURES}, got {self.layout_feature!r}",
            ),
        )
        for ok, message in checks:
            if not ok:
                raise ValueError(message)

    @property
    def n_bins(self) -> int:
        return n_bins_of(self.bins)

    def histogram_only(self) -> ColourConfig:
        """This config without the layout term and the template update, unseen colours
        counted as background: histograms, centre-surround contrast and aspect prior."""
        return dataclasses.replace(self, layout=None, template_update=False, unseen="background")

    def with_window(
        self,
        box_wh: tuple[float, float],
        frame_hw: tuple[int, int],
        growth: float = 1.1,
        spread: float | None = None,
        n_std: float | None = None,
    ) -> ColourConfig:
        """This config with a histogram window sized for a box of ``box_wh`` in a frame.

        The window covers the box grown by ``growth`` (and the kernel's 10 % size margin)
        plus ``n_std`` standard deviations ``spread`` of the particle centres: by default
        the position noise ``DEFAULT_TAU[0]`` at the box's height and 6 standard
        deviations when ``contain`` keeps the centres inside it, else the expected range
        of N normal samples. Larger boxes and a lost target's search stay exact through
        the kernel's whole-frame fallback, only slower.
        """
        w, h = (float(v) * growth for v in box_wh)
        if spread is None:
            spread = DEFAULT_TAU[0] * (1.0 if self.tau_height is None else h / self.tau_height)
        if n_std is None and self.contain:
            n_std = 6.0
        window = suggest_window(
            (w, h),
            spread,
            (int(frame_hw[0]), int(frame_hw[1])),
            n_particles=self.n_particles,
            n_std=n_std,
        )
        return dataclasses.replace(self, window=window)
