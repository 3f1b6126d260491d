"""Static settings of the multi-person tracker (``MultiConfig``): changing one recompiles."""

from __future__ import annotations

import dataclasses

from cpf_jax.detect import DetectConfig
from cpf_jax.rgbd.config import RGBDConfig

__all__ = ["FREE", "TENTATIVE", "ACTIVE", "LOST", "STATUS_NAMES", "SLOT_LOOPS", "MultiConfig"]

#: A slot's status (``Tracks.status``, int32): empty; a person found by the detector and
#: not yet confirmed (no identity, not reported); a confirmed person with an identity
#: (reported in the frames he is found); a confirmed person not seen for a while, kept
#: for re-identification until he is forgotten.
FREE, TENTATIVE, ACTIVE, LOST = 0, 1, 2, 3
STATUS_NAMES = ("free", "tentative", "active", "lost")
#: How the slots' RGB-D steps run: one after another under ``lax.map`` (each slot takes its
#: own fast or exact histogram path, and free slots are skipped), or all at once under
#: ``vmap`` (one batched program, every slot stepped; a histogram window is used only when
#: every slot's cloud fits in its own, and each branch runs for every slot).
SLOT_LOOPS = ("map", "vmap")


@dataclasses.dataclass(frozen=True)
class MultiConfig:
    """Static, hashable settings of the multi-person tracker (``cpf_jax.multi``).

    ``rgbd`` is every slot's RGB-D box filter (the tracker finds people against the
    background model of ``Context.background``, so the frame's own scene behind unseen
    pixels, ``side_scene``, is off by default); ``max_targets``
    the number of slots (people tracked at once, confirmed or not, and those kept for
    re-identification); ``max_births`` how many detections a frame may start;
    ``detect`` the person detector's thresholds on the foreground no target claims;
    ``blob_evidence`` whether a target's evidence leaves out the pixels joined at another
    target's depth to that target's claimed pixels (``claim.blob_reach``).
    ``scene_width`` (pixels, a person's width) reads the scene without people in each
    frame instead of a background model (``births.frame_scene``, for a camera that moves
    or a scene never seen empty; with ``rgbd.side_scene`` set), None: ``Context.background``.
    ``device_births`` runs the person detector in JAX (``births.device_candidates``)
    instead of on the host through ``jax.pure_callback``; off, because its block-level
    connectivity joins blobs that the host keeps apart on real footage.
    """

    rgbd: RGBDConfig = RGBDConfig(side_scene=None, n_particles=200)
    max_targets: int = 6
    max_births: int = 3
    detect: DetectConfig = DetectConfig()
    slot_loop: str = "map"
    blob_evidence: bool = False
    scene_width: float | None = None
    device_births: bool = False

    def __post_init__(self) -> None:
        if self.scene_width is not None and (self.scene_width <= 0 or self.rgbd.side_scene is None):
            raise ValueError(
                f"scene_width must be None or > 0 with rgbd.side_scene set, got "
                f"{self.scene_width} and {self.rgbd.side_scene}"
            )
        if self.max_targets < 1:
            raise ValueError(f"max_targets must be >= 1, got {self.max_targets}")
        if self.max_births < 1:
            raise ValueError(f"max_births must be >= 1, got {self.max_births}")
        if self.slot_loop not in SLOT_LOOPS:
            raise ValueError(f"slot_loop must be one of {SLOT_LOOPS}, got {self.slot_loop!r}")

    def with_window(
        self, box_wh: tuple[float, float], frame_hw: tuple[int, int], growth: float = 1.5
    ) -> MultiConfig:
        """This config with the slots' histogram window sized for people of ``box_wh``."""
        return dataclasses.replace(self, rgbd=self.rgbd.with_window(box_wh, frame_hw, growth))
