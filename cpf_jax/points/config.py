"""Static settings of the point filter (``PointConfig``) and the body points it knows."""

from __future__ import annotations

import dataclasses

from cpf_jax.kernels import resample as rs
from cpf_jax.types import KINECT_V2_DEPTH, Intrinsics

__all__ = [
    "AUTO_POINTS",
    "BODY_POINTS",
    "BODY_POINT_DEPTH_OFFSET_MM",
    "JOINED_ANCHORS",
    "REFERENCES",
    "VISIBILITIES",
    "WEIGHTINGS",
    "PointConfig",
]

WEIGHTINGS = ("spin", "geodesic", "combined")
VISIBILITIES = ("off", "report", "particles")
JOINED_ANCHORS = ("centre", "depth")
#: The body points tracked by default (names of ``SyntheticSequence.joint_names``).
BODY_POINTS = ("head", "left_hand", "right_hand", "left_foot", "right_foot")
#: mm from the surface under each of ``BODY_POINTS`` to the joint centre behind it
#: (``PointParams.joint_depth_offset``): half a hand's thickness for hands; rough
#: values for the head and feet.
BODY_POINT_DEPTH_OFFSET_MM = (80.0, 20.0, 20.0, 40.0, 40.0)
REFERENCES = ("head", "centroid")
#: The points ``body_extremities`` finds (``cpf-track --points auto``): "a" is the one
#: further left in the image, "b" the other (which of the person's hands is which
#: depends on the way they face).
AUTO_POINTS = ("head", "hand_a", "hand_b", "foot_a", "foot_b")


@dataclasses.dataclass(frozen=True)
class PointConfig:
    """Static, hashable settings of the point filter (``cpf_jax.points``)."""

    n_particles: int = 100
    weighting: str = "combined"  # "spin" | "geodesic" | "combined"
    window: tuple[int, int] = (256, 192)  # (rows, cols) of the depth window
    box_margin: float = 0.1  # the box is enlarged by this fraction on every side
    intrinsics: Intrinsics = KINECT_V2_DEPTH
    seg_max_dz_mm: float = 10.0  # thesis 4.1.2
    surface_max_dist_mm: float = 15.0  # thesis 4.1.4
    # Depth at which the two thresholds hold; they scale with the pixel pitch
    # (depth x window scale / f). None: fixed thresholds (times the window scale).
    threshold_depth_mm: float | None = 2000.0
    # Geodesic reference points (thesis 4.3: head or body centroid); several give a
    # vector of distances per pixel. The head: the centroid moves with the limbs, and
    # its paths to a hand switch between the shoulder and a hand-on-thigh contact.
    references: tuple[str, ...] = ("head",)
    # Edges of the graph the geodesic distances run over, in mm at ``threshold_depth_mm``
    # (None: the surface graph's, ``surface_max_dist_mm``, thesis 4.3). Looser edges bridge
    # the depth jumps that cut a side-on person's near arm off the trunk, where the
    # surface graph leaves the hand unreachable from the head.
    geodesic_max_dist_mm: float | None = None
    spin_width: int = 20  # App. G
    spin_bin_factor: float = 1.0  # bin size in mesh resolutions (App. G: 1-2)
    support_angle_deg: float = 60.0  # App. G: 60-90
    normal_smoothing: int = 2  # vertex normals summed over (2k+1)^2 pixels (0: one ring)
    # Floor removal before segmentation: drop pixels whose normal is within this
    # angle of ``up`` (camera coordinates, Y down). None: no floor removal (thesis).
    floor_max_tilt_deg: float | None = 30.0
    up: tuple[float, float, float] = (0.0, -1.0, 0.0)
    # Only components at least this far in front of the box's background (median
    # depth of the ROI border) may be the body; None: the thesis's plain largest.
    background_margin_mm: float | None = 250.0
    # None: the body is one component (thesis). A fraction f: the union of the
    # components with at least f times the largest one's pixels (use with a
    # foreground mask, which has removed the background already).
    min_component_fraction: float | None = None
    # With ``min_component_fraction``: only the sizeable components joined, through edges of
    # at most this depth step (mm at ``threshold_depth_mm``), to the one nearest the box's
    # centre; None: all of them (other people in the box stay in).
    joined_max_dz_mm: float | None = None
    # With ``joined_max_dz_mm``: which joined groups are the tracked person's. "centre", the
    # group of the pixel nearest the box's centre; "depth", every group whose mean depth lies
    # within ``anchor_max_dz_mm`` of the target's depth (``PointFrame.target_depth``, layer
    # 1's depth templates in the cascade; the box's centre lies on whoever passes in front),
    # the centre's group when no depth is given or no group is there.
    joined_anchor: str = "centre"
    anchor_max_dz_mm: float = 300.0
    # With ``joined_anchor="depth"``: a component is sizeable against the largest one at the
    # target's depth rather than the largest in the window (a target mostly hidden by
    # someone nearer shows only small pieces).
    anchor_sizeable: bool = False
    patch_radius: int = 32  # window pixels visited per spin image (see kernels.spin)
    spin_batch: int = 32  # distinct query pixels per spin-image loop step
    follow_box: bool = True
    # Temporal depth consistency: a particle whose surface depth departs from the
    # predicted depth of its point loses weight (``params.depth_sigma``).
    depth_consistency: bool = True
    # Hidden points (``points.filter.hidden_term``): "report", a per-point flag filtered
    # from the cloud's likelihoods (hidden against visible, ``hidden_evidence``), which
    # leaves the cloud as it is; "particles", a flag on every particle, so that a hidden
    # point's cloud moves on with its predicted motion instead of onto the surface in front
    # of it; "off", no flag.
    visibility: str = "report"
    # With "particles": a particle that shows again is drawn from the body pixels at the
    # point's geodesic distance from the references near its last estimate
    # (``filter.point_reacquire``).
    reacquire: bool = True
    # A prior on each point's offset in the box about its start offset
    # (``points.filter.anchor_term``): the body model's say in where a hand can be.
    anchor_prior: bool = False
    # The geodesic references follow the distances under the visible estimates
    # (``points.filter.geodesic_reference_update``) instead of staying at the first frame's.
    adapt_geodesic: bool = False
    ess_threshold: float = 1.0  # 1.0: resample every frame (SIR)
    resampler: str = "systematic"
    max_sweeps: int = 64  # geodesic relaxation sweeps (converges in 3-8)
    # PointInfo.surface carries the segmented body's 3D points (for a live display; off by
    # default: [Hw * Ww, 3] per frame would fill a long scan's outputs).
    report_surface: bool = False

    def __post_init__(self) -> None:
        if self.n_particles < 1:
            raise ValueError(f"n_particles must be >= 1, got {self.n_particles}")
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if not self.references or any(r not in REFERENCES for r in self.references):
            raise ValueError(
                f"references must be a non-empty tuple of {REFERENCES}, got {self.references!r}"
            )
        if self.visibility not in VISIBILITIES:
            raise ValueError(f"visibility must be one of {VISIBILITIES}, got {self.visibility!r}")
        if self.resampler not in rs.SCHEMES:
            raise ValueError(
                f"resampler must be one of {tuple(rs.SCHEMES)}, got {self.resampler!r}"
            )
        if self.min_component_fraction is not None and not 0 < self.min_component_fraction <= 1:
            raise ValueError("min_component_fraction must be in (0, 1] or None")
        if self.joined_max_dz_mm is not None and self.joined_max_dz_mm <= 0:
            raise ValueError(f"joined_max_dz_mm must be > 0 or None, got {self.joined_max_dz_mm}")
        if self.joined_anchor not in JOINED_ANCHORS:
            raise ValueError(
                f"joined_anchor must be one of {JOINED_ANCHORS}, got {self.joined_anchor!r}"
            )
        if self.anchor_max_dz_mm <= 0:
            raise ValueError(f"anchor_max_dz_mm must be > 0, got {self.anchor_max_dz_mm}")
        if self.geodesic_max_dist_mm is not None and self.geodesic_max_dist_mm <= 0:
            raise ValueError(
                f"geodesic_max_dist_mm must be > 0 or None, got {self.geodesic_max_dist_mm}"
            )
        if min(self.window) < 8:
            raise ValueError(f"window too small: {self.window}")

    def with_foreground(self) -> PointConfig:
        """These settings for a body limited to a foreground mask: the union of the
        sizeable components, with the looser thresholds that keep a side-on person's near
        arm and leg (apart from the trunk in depth) on it, and geodesics whose edges bridge
        the depth jump between that arm and the trunk."""
        return dataclasses.replace(
            self,
            seg_max_dz_mm=25.0,
            surface_max_dist_mm=40.0,
            min_component_fraction=0.05,
            geodesic_max_dist_mm=160.0,
        )

    @property
    def hidden_particles(self) -> bool:
        return self.visibility == "particles"

    @property
    def uses_spin(self) -> bool:
        return self.weighting in ("spin", "combined")

    @property
    def uses_geodesic(self) -> bool:
        return self.weighting in ("geodesic", "combined")
