"""Typed settings of every 2D prior: the one source of their defaults.

Each dataclass is frozen and hashed (as JSON of its fields) into the cache key of the prior it drives, so
changing a field recomputes exactly the priors that depend on it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Literal

from worldtree.infra.errors import SettingError


@dataclass(frozen=True)
class FlowConfig:
    """Dense optical flow (OpenCV DIS) between frame pairs, forward and backward."""

    preset: Literal["ultrafast", "fast", "medium"] = "medium"
    """DIS preset; "medium" adds variational refinement and is the most accurate."""
    offsets: tuple[int, ...] = (1, 3)
    """Frame gaps k: flow is computed for every pair (t, t+k), both directions."""
    fb_alpha: float = 0.5
    """Forward-backward check: valid where |f + b(x+f)| < fb_alpha (|f| + |b(x+f)|) + fb_beta."""
    fb_beta: float = 0.5
    """Constant slack of the forward-backward check, in pixels."""
    photo_max: float | None = 0.25
    """Valid flow also needs |I_i(x) - I_j(x+f)| below this, on grey images blurred (sigma 1 px) and normalised
    to zero mean and unit std per frame; None disables the photometric check."""
    init_from_depth: bool = True
    """Start DIS from the rigid flow given by the metric depth prior and the poses (robust to wide camera
    jumps; used only when metric depth is available: classical, or imported with a scale/shift fit)."""
    import_missing: Literal["skip", "classical"] = "skip"
    """With an imported flow folder (``PriorsConfig.flow_source``), the pairs of ``offsets`` it lacks: left out
    ("skip"), or computed here by DIS ("classical"; cached as the classical flow). Folders of neighbouring
    frames only (DynamicNeRF's RAFT) have no gap of 3, whose other viewing directions the motion cues use."""

    def dis_settings(self) -> FlowConfig:
        """The settings DIS itself depends on (the cache key of classical flow): ``import_missing`` is not one."""
        return replace(self, import_missing="skip")


@dataclass(frozen=True)
class TrackConfig:
    """Long-term point tracks: pyramidal Lucas-Kanade chained frame to frame with forward-backward checks."""

    grid_step: int = 8
    """Spacing in pixels of the seed grid (also the spacing of re-seeding in uncovered areas)."""
    max_corners: int = 1500
    """Shi-Tomasi corners added to the grid at the first frame (fewer at re-seeding, see below)."""
    corner_quality: float = 0.01
    """Shi-Tomasi quality level relative to the strongest corner."""
    min_distance: int = 6
    """No new seed closer than this (pixels) to a live track."""
    win_size: int = 21
    """Lucas-Kanade window side in pixels."""
    levels: int = 3
    """Pyramid levels above the full resolution."""
    fb_max_px: float = 1.0
    """A step is kept when tracking back lands within this many pixels of the start."""
    min_eigen: float = 1e-4
    """Lucas-Kanade minimum-eigenvalue threshold (cv2 minEigThreshold): drops textureless points."""
    reseed_every: int = 4
    """Re-seed uncovered areas every this many frames (1 = every frame)."""
    max_tracks: int = 16000
    """Upper bound on the number of tracks N; seeding stops when reached."""
    bidirectional: bool = True
    """Also track re-seeded points backwards in time, so they cover frames before their seed frame."""
    min_length: int = 3
    """Tracks visible in fewer frames than this are dropped."""
    init_from_depth: bool = True
    """Start each Lucas-Kanade step from the static-scene prediction given by depth and poses (when available)."""


@dataclass(frozen=True)
class DepthConfig:
    """Multi-view plane-sweep stereo over neighbouring training frames (known poses)."""

    num_planes: int = 64
    """Fronto-parallel depth hypotheses, uniform in inverse depth between near and far."""
    num_sources: int = 4
    """Source frames per reference frame: the nearest in time with a usable baseline."""
    max_time_gap: int = 6
    """Source frames are at most this many frames away from the reference frame."""
    min_baseline_ratio: float = 0.005
    """A source is usable when its camera centre is at least this fraction of the far bound away."""
    patch: int = 7
    """Side of the square ZNCC window in pixels (odd)."""
    best_k: int = 2
    """Per hypothesis, the cost is the mean of the best_k source costs (robust to occlusion)."""
    min_conf: float = 0.5
    """Pixels whose confidence is below this are filled from confident neighbours."""
    min_texture: float = 2.0 / 255.0
    """Patch intensity standard deviation below which the match is not trusted (textureless)."""
    fill_lambda: float = 200.0
    """Smoothness weight of the edge-aware fill (cv2.ximgproc fast global smoother)."""
    fill_sigma: float = 8.0
    """Colour sensitivity of the edge-aware fill (intensity units of 0..255)."""
    fill_support: float = 0.01
    """Where the edge-aware fill's support (its smoothed confidence) is weak, it gives way to a plane fitted to
    the frame's confident inverse depth (:func:`worldtree.priors.depth.edge_aware_fill`): the two are blended
    with weights ``support`` and ``fill_support``. A region no other camera sees (a rig's end strip) then
    continues the wall beside it instead of taking the frame's mean depth. 0: the mean, the old fallback."""
    fill_imported_masks: bool = False
    """On the pixels of imported dynamic masks, replace the stereo depth by the fill from the static
    surroundings, as on the method's own masks. Off (default): they keep the plane sweep's value, at confidence
    0 either way. An imported mask covers each moving object whole, and the fill puts all of it at the depth of
    what is behind it; on eight generated scenes with their exact masks the sweep's value (matched across
    times) scored +0.24 to +0.97 dB mPSNR, the objects nearer their depth on the four measured
    (docs/base_method.md, session 49). The method's own masks start small; there the choice measured level,
    and they are filled as before."""
    near: float | None = None
    """Nearest depth hypothesis in scene units; None uses the scene's near bound."""
    far: float | None = None
    """Farthest depth hypothesis in scene units; None uses the scene's far bound."""


@dataclass(frozen=True)
class EpiConfig:
    """Epipolar error maps and dynamic (EPI) masks from flow and camera poses."""

    threshold_px: float = 1.5
    """A pixel is dynamic when its Sampson distance exceeds this (pixels at the working resolution)."""
    track_min_frames: int = 2
    """A track is dynamic when it lies on an over-threshold pixel in at least this many frames."""
    use_poses: bool = True
    """Use the fundamental matrix of the known relative pose; False estimates it from flow (LMedS)."""
    lmeds_points: int = 4000
    """Flow correspondences sampled per pair for the LMedS estimate."""
    min_baseline: float = 1e-6
    """Below this camera-centre distance (scene units) a pair is treated as a pure rotation."""
    max_pair_median_px: float = 0.75
    """A flow pair whose median error over consistent pixels exceeds this failed as a whole and is skipped."""
    min_area_frac: float = 0.002
    """Connected mask regions smaller than this fraction of the frame are dropped (flow noise, not motion)."""
    open_px: int = 1
    """Radius of the morphological opening that removes isolated mask pixels (0 = none)."""


@dataclass(frozen=True)
class MotionConfig:
    """Motion discovery: cues fused into dynamic masks with a confidence, and dynamic tracks chained through
    dense flow inside them (``worldtree.priors.motion_cues``, ``dynamic_masks``, ``dynamic_tracks``)."""

    enabled: bool = True
    """Fuse the cues into the masks and chain dynamic tracks (False: the plain EPI masks and Lucas-Kanade
    dynamic tracks, the behaviour before motion discovery)."""
    use_epipolar: bool = True
    """Use the epipolar-error cue."""
    use_rigid: bool = True
    """Use the depth-consistency cue (flow against the rigid flow of depth and poses)."""
    rigid_tol_px: float = 1.5
    """Depth-consistency tolerance in pixels, plus ``rigid_rel_depth`` times the translational parallax."""
    rigid_rel_depth: float = 0.3
    """Relative depth error tolerated by the depth-consistency cue."""
    residual_z_low: float = 4.0
    """Static-model residual cue: evidence starts at this many robust standard deviations above the median."""
    residual_z_high: float = 8.0
    """... and is full at this many."""
    residual_floor: float = 0.04
    """Residuals below this (image units, mean over channels) are never evidence of motion."""
    temporal_self_weight: float = 0.5
    """Temporal agreement: weight of a frame's own evidence against its flow-carried neighbours'."""
    threshold: float = 0.5
    """A pixel is dynamic when its fused, temporally agreed evidence exceeds this."""
    close_px: int = 1
    """Radius of the closing that joins the pieces of one object (0 = none)."""
    dilate_px: int = 0
    """The final masks grow by this radius (object borders carry mixed pixels)."""
    track_seed_step: int = 4
    """Dynamic tracks: seed spacing in pixels inside the masks."""
    track_seed_every: int = 4
    """Dynamic tracks: re-detect uncovered mask pixels every this many frames."""
    track_gaps: tuple[int, ...] = (1, 3)
    """Frame gaps used to chain a track; a larger gap bridges a failed step (a camera change)."""
    track_mask_dilate_px: int = 3
    """A chained point must stay inside the mask dilated by this radius."""
    track_fill_px: int = 2
    """Holes of the flow's validity inside the masks are filled from the valid flow within this radius."""
    track_link_px: float = 2.0
    """Two track pieces are linked when one's flow-carried end lands within this of the other's start."""
    track_link_gap: int = 3
    """Pieces ending at frame e and starting within this many frames after are joined when the start lies
    where the ended piece's motion carries it (``worldtree.priors.track_linking``; 0 = no such linking)."""
    track_link_rel: float = 0.5
    """Linking tolerance grows by this fraction of the predicted motion (position) or of the faster motion
    (velocity agreement), on top of ``track_link_px``."""
    track_link_ncc: float = 0.5
    """Linked ends must look alike: minimum NCC of their grey patches (-1 = no appearance check)."""
    track_link_patch_px: int = 3
    """Half side of the patches compared when linking (pixels)."""
    track_step_ncc: float = -1.0
    """A chained step must keep the point's look: minimum NCC of its patches before and after (-1 = no check).
    0.5 makes the demo's chained tracks about twice as accurate but fewer and shorter, and Base lost 0.2-0.3
    dB mPSNR with it on the generated scenes (docs/base_method.md, "Track life"), hence off by default."""
    track_step_min_std: float = 0.0
    """Steps whose patch has a grey standard deviation below this are kept unchecked (too little texture for
    NCC to mean anything, e.g. a smooth balloon); 0 checks every step (flat patches never agree)."""
    track_link_camera: bool = True
    """Remove the camera's share of the motion (metric depth and poses) before continuing it across a gap."""
    track_min_length: int = 3
    """Dynamic tracks visible in fewer frames are dropped."""
    object_flow: bool = True
    """Before chaining, recompute each chaining flow pair inside the dynamic masks from each mask component's
    displacement found by masked template matching (``worldtree.priors.object_flow``): DIS with its small
    coarse-to-fine search cannot follow objects moving 6-30 px per frame at 160x90. Base gained +0.23 dB
    mPSNR on the demo and +0.51 dB on the hard scene with it (one seed; docs/priors.md); tracks live about as
    long as without it."""
    object_search_px: int = 32
    """Template search radius in pixels (working size) per frame of gap, around the position the rigid flow
    (or, without metric depth, the current flow) predicts; 32 covers the generated rig's fastest objects at
    160x90 (30 px/frame)."""
    object_min_score: float = 0.4
    """A component's match is accepted when its masked zero-mean NCC reaches this. Low because the generated
    rig's objects turn and every frame changes camera: with the exact masks of the demo the true displacement
    scores 0.2-0.9 (0.6 refused 61% of the components, 0.4 refuses 14%); the mask constraint
    (``object_min_inside``) keeps the matches on the object."""
    object_min_area_px: int = 25
    """Mask components smaller than this (pixels, dilated) are not matched (too little texture to match)."""
    object_min_inside: float = 0.5
    """A match must put at least this fraction of the component's pixels inside the other frame's dilated
    mask (the object is where the masks say it is; elsewhere it would be background)."""
    max_dynamic_tracks: int = 4000
    """Upper bound on the chained dynamic tracks."""


@dataclass(frozen=True)
class FreeSpaceConfig:
    """Which pixels of an imported depth are left out of the depth losses because a static world cannot hold
    them (:func:`worldtree.priors.free_space.free_space_violations`): outside the dynamic masks, a pixel whose
    depth puts its point in front of what other frames see there is a moving object the masks missed (or a
    wrong depth), and a depth loss there pulls static Gaussians into floaters. The classical depth is a
    static-world estimate and is never checked."""

    enabled: bool = False
    """Check an imported depth before the photometric fit (false, the default: every pixel keeps its depth). Off
    because it measured no gain beside the static floater removal (``photometric.floater_every``), which is
    what removed the veil on the twin of Balloon1 (docs/base_method.md, "Depth that a static world cannot
    hold"): on three generated scenes with their exact depth it moved mPSNR by -0.20 to -0.05 dB."""
    tolerance: float = 0.25
    """A violation needs the point nearer than ``1 - tolerance`` times the depth the other frame sees (an
    imported depth's per-frame scale is a few to 25 % off; a moving object in front of the wall is far more)."""
    views: int = 8
    """Frames each frame is compared with, spread over the video."""
    share: float = 0.5
    """Fraction of the frames that see a pixel that must find it in free space."""
    window: int = 3
    """Odd side (pixels) of the minimum filter over the other frame's depth (depth edges, pose error)."""

    def __post_init__(self) -> None:
        checks = (
            ("tolerance", 0.0 < self.tolerance < 1.0, "choose a margin between 0 and 1 (exclusive)"),
            ("views", self.views >= 1, "choose at least 1 frame"),
            ("share", 0.0 < self.share <= 1.0, "choose a fraction in (0, 1]"),
            ("window", self.window >= 1 and self.window % 2 == 1, "choose an odd size >= 1"),
        )
        for name, ok, why in checks:
            if not ok:
                raise SettingError.of_field(self, name, why)


@dataclass(frozen=True)
class DepthImportConfig:
    """How imported depth maps are read and aligned."""

    kind: Literal["depth", "disparity"] = "depth"
    """What the files hold: metric/relative depth or (inverse) disparity."""
    png_scale: float = 1000.0
    """16-bit PNG values are divided by this (1000 = millimetres to metres)."""
    fit_scale_shift: bool = False
    """Fit a per-frame scale and shift to the classical depth (in the file's own space: depth or disparity)."""
    fit_shift: bool = True
    """With ``fit_scale_shift``: also fit the shift (a line ``a x + b``); false fits the scale alone (a line
    through the origin: disparity 0 at infinity, depth 0 at the camera). The static pixels a frame is fitted
    on often span a narrow range of depth (one wall) where a relative network's error is a large part of the
    spread; the least-squares slope is then flattened (regression dilution) and a moving object nearer than
    that range, an extrapolation, lands too far. Fixing the shift at 0 takes the slope from the mean ratio
    instead (docs/priors.md, "A scale without a shift")."""
    fit_global_scale: bool = True
    """Without ``fit_scale_shift``: multiply the imported depth by the one factor that makes it agree with the
    scene's cameras (``worldtree.priors.depth_scale``: two-view triangulation of the flow's static matches).
    The cameras fix the world's scale and bundle adjustment frees only relative per-frame scales, so depth in
    other units (a network's metres, a generator's world) would otherwise stay wrong. The depth then counts
    as metric: it guides the tracks and feeds the depth-consistency motion cue."""
    scale_max_residual_px: float = 1.0
    """Global-scale fit: flow matches whose triangulated point reprojects farther than this are dropped."""
    scale_min_parallax_px: float = 2.0
    """Global-scale fit: matches whose projection moves less than this many pixels per unit of log depth
    are dropped (too little baseline to measure their depth)."""
    fit_trim: float | None = 2.5
    """Robust fit: after the weighted least squares, pixels whose residual exceeds this many robust standard
    deviations (1.4826 MAD) are dropped and the fit repeated (3 rounds); None keeps the plain fit. Multi-view
    stereo has gross errors (occlusions, repeated texture) that would otherwise tilt the line."""
    fit_balance_bins: int = 0
    """Scale/shift fit: the weights are rebalanced so that each of this many equal ranges of the imported
    values weighs the same (``imported.balanced_weights``: the far wall would otherwise pin the line and leave
    the slope, which sets every nearer depth, to a few pixels); 0 or 1 (default): the confidence weights as
    they are. Off by default: the nearest range is often a moving object's pixels that its mask missed, whose
    reference is the wall behind it, and balancing multiplies their weight (docs/base_method.md)."""
    fit_exclude_dynamic: bool = True
    """Under ``merge="fill"``: once the dynamic masks are known, refit each frame without their pixels
    (dilated by ``fit_exclude_px``) before the fitted depth fills them. The first fit, made before there are
    masks, includes the moving objects, whose reference depth is the static fill behind them."""
    fit_exclude_px: int = 3
    """Dilation (px) of the dynamic masks left out of the refit."""
    merge: Literal["replace", "fill"] = "replace"
    """"replace": the imported depth is the depth prior. "fill": keep the classical depth where it is a
    measurement (confidence >= ``fill_min_conf``, outside dynamic masks) and use the fitted imported depth only
    elsewhere (moving objects, textureless areas); needs ``fit_scale_shift``. On real footage relative network
    depth (MiDaS) is less accurate than stereo on the static background but is the only measurement on moving
    objects."""
    fill_min_conf: float = 0.5
    """Classical confidence from which the classical depth is kept under ``merge="fill"``."""
    fill_conf: float = 1.0
    """Confidence given to the imported depth where it fills (network depth carries none of its own)."""
    fill_static: Literal["import", "classical"] = "import"
    """Under ``merge="fill"``: what the static pixels stereo is unconfident on end with (a strip at the rig's end
    that one camera sees, textureless areas). "import": the fitted import at ``fill_conf``. "classical": the
    import still guides the flow and the tracks before the masks are known (on the moving objects it is the
    only measurement), but the depth-consistency motion cue tests the flow against the classical depth, and
    once the masks are known every static pixel keeps the classical depth (its edge-aware fill continues the
    confident surfaces around) with its own confidence, so that the import ends on the moving pixels only.
    With the shipped MiDaS of Balloon1, extrapolated by its per-frame scale into the strips only an end camera
    sees, "import" tilted the flat wall there by 40 % and the cue marked the strips as moving (docs/priors.md,
    "What the static pixels stereo is unsure of get under fill"). ``nvls import`` suggests "classical" for
    relative disparity."""


@dataclass(frozen=True)
class PriorsConfig:
    """All prior settings plus where each prior comes from ("classical" or a path to import)."""

    flow: FlowConfig = field(default_factory=FlowConfig)
    """Settings of the classical flow (its FB and photometric checks also apply to imported flow)."""
    tracks: TrackConfig = field(default_factory=TrackConfig)
    """Settings of the classical tracks."""
    depth: DepthConfig = field(default_factory=DepthConfig)
    """Settings of the classical depth (also the reference of an imported depth's scale/shift fit)."""
    epi: EpiConfig = field(default_factory=EpiConfig)
    """Epipolar errors, EPI masks and dynamic-track labels."""
    motion: MotionConfig = field(default_factory=MotionConfig)
    """Motion discovery (cues fused into masks, dynamic tracks chained through flow)."""
    depth_import: DepthImportConfig = field(default_factory=DepthImportConfig)
    """How imported depth is read and aligned (ignored for classical depth)."""
    depth_source: str = "classical"
    """"classical" or a folder / file of depth maps to import."""
    tracks_source: str = "classical"
    """"classical" or a CoTracker-layout file (.npy/.npz/.pt) to import."""
    flow_source: str = "classical"
    """"classical" or a folder of flow files named <i>_<j>.flo / .npy."""
    masks_source: str | None = None
    """None (EPI masks from flow) or a folder of dynamic masks, one per frame, replacing the EPI masks."""
    threads: int = 0
    """Frames (depth) and frame pairs (flow) computed at once on threads (0: torch's thread count, at most the
    cores this process may use). Each item is computed whole on one thread, so the priors are the same for any
    count."""


def config_dict(cfg) -> dict:
    """Plain JSON-able dict of a settings dataclass (tuples become lists)."""
    return asdict(cfg)
