"""Dense RGB-D SLAM by projective point-to-plane ICP and point-based fusion (the dense-SLAM paper, section 4).

Each depth frame is turned into a vertex/normal pyramid (section 2, :mod:`.maps`); the camera is tracked
*map-to-frame*: the map's points rendered at the previous pose are the ICP source and the new frame the
target (section 4), coarse to fine (:mod:`.icp`); the frame is then fused into the map at the tracked pose
(section 3, :mod:`.fusion`). The first frame's camera is ``world`` (identity pose).

Beyond the paper's plain least squares, ICP weights each residual by a Huber weight and by the inverse
variance of Kinect depth noise at its depth (``depth_weighting``), fusion weights each measurement by
Keller et al.'s radial confidence, and only points seen at least twice are tracked against. The depth
noise is measured from the first frames (:mod:`.noise`), and the thresholds set for a Kinect v1's are
widened where it exceeds them (``noise_model``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from relpoint.errors import EstimatorError, UsageError
from relpoint.estimators.base import DEPTH, Estimator
from relpoint.estimators.dense import _kernels
from relpoint.estimators.dense.fusion import PointMap, colors_filled
from relpoint.estimators.dense.icp import SIGMA_1M, IcpSettings, alignment_cost, depth_sigma, track
from relpoint.estimators.dense.maps import EDGE_JUMP, EdgeNoise, Level, build_pyramid
from relpoint.estimators.dense.noise import REFERENCE_DEPTH, DepthNoise, fit_noise, second_differences
from relpoint.estimators.spec import EstimatorSpec
from relpoint.geometry import FloatArray, invert_pose
from relpoint.settings import Settings, setting
from relpoint.types import DepthFrame, Intrinsics, LandmarkMap, Pose

logger = logging.getLogger(__name__)

GAP_RATIO = 1.5
"""A frame more than this many typical frame intervals after the last tracked one follows a gap (frames
missing from the log, or lost): its camera may have moved that much further, and the association gate
is widened in proportion."""

INTERVAL_HISTORY = 30
"""The typical frame interval is the median of the last this many stamp differences."""

SUSPECT_HISTORY = 10
"""A tracked frame is compared with the last this many tracked frames (their median residual and pairs)."""

SUSPECT_RMSE_RATIO = 2.5
SUSPECT_PAIRS_RATIO = 0.5
"""A frame whose ICP ended with more than ``SUSPECT_RMSE_RATIO`` times the recent median point-to-plane
residual on fewer than ``SUSPECT_PAIRS_RATIO`` times the recent median number of pairs converged
somewhere the frame does not fit: on the 7-Scenes kitchen taken every 16th frame (7-18 cm and up to 11
degrees between frames), the frames that jumped 13 and 33 cm off their true motion ended at 3.9 and 2.9
times the residual on 0.07 and 0.4 times the pairs; over every frame, every 8th and every 12th no frame
comes near both. Such frames are kept (the pose may still be right) but counted and warned."""

FAR_MEDIAN_DEPTH = 8.0
"""A first frame whose median depth lies beyond this (metres) is warned of: depth cameras (structured
light, time of flight, active stereo) see rooms, so its depth is more likely in another unit than the log
format's (TUM's 5000 per metre, a RealSense D405's 0.1 mm, read as millimetres), which would scale the
path and the map without anything else looking wrong."""

PROCESSED_PIXELS = 460_800
"""With ``downsample`` 0, frames are processed at the largest resolution of at most this many pixels
(1.5 times 640x480), halving up to twice: the time per frame and the map grow with the pixels, the
accuracy hardly (the 7-Scenes kitchen upsampled to 1280x720, 150 frames: 1.34 cm ATE at full size, 1.04 s
a frame and 4.5 million map points; at 640x360 1.35 cm, 0.31 s and 0.77 million)."""

IMPOSSIBLE_MEDIAN_DEPTH = 100.0
"""Without a ``max_depth``, a run whose first usable frame's median depth lies beyond this (metres) is refused:
no depth camera measures a scene that far, and such depth is in another unit (32FC1 holding millimetres:
the kitchen's then tracked as a camera standing still, without a word but the far-depth warning)."""

NOISE_FRAMES = 5
"""The depth noise (``noise_model``) is measured over the first this many frames of the map: their pixels'
second differences for the edge thresholds, the ICP residuals of the first this many tracked frames for the
fusion gate and the Huber threshold."""

EDGE_SIGMAS = 3.0
"""Neighbouring pixels of one surface differ by at most this many standard deviations of their difference
(``sqrt(2)`` times the pixel noise) before an edge threshold takes them for two surfaces (0.3 % of pairs of
one surface beyond it, for Gaussian noise)."""

GATE_SIGMAS = 3.0
"""The fusion gate is at least this many standard deviations of the measured frame-to-map residuals."""

HUBER_SIGMAS = 1.345
"""The Huber threshold is at least this many standard deviations of the measured frame-to-map residuals
(the usual choice: 95 % of least squares' efficiency on Gaussian noise)."""

STABLE_SHARE = 0.25
"""Finer ICP levels track against the stable map points only when they are at least this share of the
points rendered there (fewer, and they would pin the pose to a corner of the view)."""


@dataclass(frozen=True)
class DenseConfig(Settings):
    """Settings of the dense estimator. Metres, degrees, frames."""

    settings_name: ClassVar[str] = "dense"
    settings_hint: ClassVar[str] = "see `relpoint config --estimator dense` for the parameters"

    downsample: int = setting(0, choices=(0, 1, 2, 4))
    """Process the depth at 1/downsample of its resolution (1, 2 or 4; 2x2 block averaging); 0 = from the
    first frame's size: the least factor that leaves at most ``PROCESSED_PIXELS`` (640x480 and 848x480 run
    at full size, 1280x720 at 640x360, 1920x1080 at 480x270)."""
    smooth_depth: bool = True
    """Smooth the depth with an edge-preserving 3x3 mean before computing vertices and normals."""
    pyramid_levels: int = setting(3, low=1, high=5)
    """Pyramid levels for coarse-to-fine ICP (each halves the resolution)."""
    icp_iterations: tuple[int, ...] = setting((4, 5, 10), low=0)
    """ICP iterations per level, finest first (one entry per level)."""
    source_stride: int = setting(2, low=1, high=8)
    """Use every ``source_stride``-th pixel (in both directions) of the rendered map as ICP source at each
    level (1 = all; 2 quarters the cost of the finest level)."""
    icp_distance: float = setting(0.2, above=0)
    """Association gate ``|p' - q|`` of ICP, metres (section 2.1). It must cover the motion between two
    frames (the coarse levels start from the last pose): on the 7-Scenes kitchen at 3 frames a second
    (every 10th frame, 12 cm between frames) 0.1 m left ATE at 25.4 cm and 0.2 m gives 3.1 cm; at 30
    frames a second both give 2.2 cm (320x240), and the simulated room 2.5 mm."""
    max_step: float = setting(0.5, above=0)
    """Most a frame may move from the one before, metres: a larger ICP result is a divergence (a hand-held
    camera at 3 frames a second moves 12 cm, and the depth reaches 4 m), so the frame counts as lost."""
    icp_normal_angle: float = setting(30.0, above=0, high=180)
    """Association gate on the angle between map and frame normals, degrees."""
    huber_delta: float = setting(0.02, low=0)
    """Huber threshold on point-to-plane residuals, metres (0 = plain least squares as in the paper); with
    ``noise_model``, at least ``HUBER_SIGMAS`` times the residual noise measured at each pair's depth."""
    rotation_iterations: int = setting(3, low=0, high=100)
    """Before the joint ICP, turn the camera about its centre by up to this many rotation-only iterations at
    the coarsest level, and start from there when that explains the level at least as well as the last
    pose (0 = start from the last pose, as KinectFusion). A fast turn otherwise leaks into a translation
    along a blank wall: turned at 80 degrees a second in an empty simulated room, the camera slid 0.89 m
    with 3 (0.05 m RMS); the 7-Scenes kitchen's ATE is unchanged at 320x240 (2.24 cm), better on every 12th
    frame at 640x480 (3.93 -> 3.38 cm)."""
    constant_velocity: bool = False
    """Start ICP from the previous pose moved by the last frame-to-frame motion when that start explains
    the frame at the coarsest level at least as well as the previous pose does (else from the previous
    pose, as KinectFusion). Off by default: on the 7-Scenes redkitchen frames one such start (frame 58, a
    1.3 cm step) converged 2 cm off, the map was corrupted and tracking never recovered."""
    depth_weighting: bool = True
    """Weight each ICP residual by the inverse variance of the Kinect-like depth noise at its depth
    (``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` m, Nguyen et al. 2012): far, noisy points count less."""
    fusion_depth_weighting: bool = False
    """Multiply each measurement's fusion weight by ``min(1, (sigma(1 m) / sigma(z))^2)`` (the depth noise
    model of ``depth_weighting``): far measurements move fused points less."""
    map_normals: bool = False
    """Measure the point-to-plane residual along the map's (fused, smoother) normal instead of the frame's
    (the paper's ``n_q``); both are still gated by the normal-angle check."""
    convergence_rotation: float = setting(3e-4, above=0)
    """ICP stops a level when the rotation increment is below this (radians) ..."""
    convergence_translation: float = setting(3e-4, above=0)
    """... and the translation increment below this (metres)."""
    min_correspondences: int = setting(100, low=6, high=10_000_000)
    """Fewer pairs than this and the frame's tracking is rejected (the pose is predicted instead)."""
    fusion_distance: float = setting(0.01, above=0)
    """Fusion gate: largest distance between a frame point and the map point rendered at its pixel, metres,
    at zero depth ..."""
    fusion_distance_quadratic: float = setting(0.005, low=0)
    """... plus this times the squared depth (1/m): Kinect-like noise grows with depth squared. With
    ``noise_model`` both terms are widened to the pixel noise measured from the frames where it needs more."""
    fusion_normal_angle: float = setting(30.0, above=0, high=180)
    """Fusion gate on the normal angle, degrees."""
    radial_sigma: float = setting(0.6, low=0)
    """Keller et al.'s radial confidence: a measurement at normalised distance ``r`` from the image centre
    is fused with weight ``exp(-r^2 / (2 sigma^2))`` (0 = weight 1 everywhere, the paper's rule)."""
    track_min_weight: float = setting(2.0, low=0)
    """Only map points with at least this weight are ICP sources at the finer pyramid levels (0 = all),
    unless they are under a quarter of the rendered points; the coarsest level takes every rendered point."""
    max_weight: float = setting(100.0, above=0)
    """Weights stop growing here (so that the map keeps adapting)."""
    min_depth: float = setting(0.1, low=0, high=1e3)
    """Depths below this are ignored, metres."""
    max_depth: float = setting(math.inf, low=1e-3, high=math.inf)
    """Depths above this are ignored, metres (default: none). Far depth is noisy (Kinect-like noise grows
    with depth squared), but ICP weights it by that noise (``depth_weighting``) and the fusion gate grows
    with it; a fixed cap instead threw away what another camera's or a larger room's frames hold. The
    7-Scenes kitchen (depths up to 3.6 m) is the same with the earlier 4 m cap; the kitchen three times
    as large (depths 1.5-11 m, Kinect-like noise and disparity steps added) had 8.5 cm ATE with it, 4.8
    without, and a simulated room three times as large 64 cm against 1.2 cm."""
    remove_unstable: bool = True
    """Remove points still below ``stable_weight`` ``unstable_age`` frames after they were added."""
    stable_weight: float = setting(2.0, above=0)
    """Weight a point needs to count as stable."""
    unstable_age: int = setting(10, low=1, high=1_000_000)
    """Frames an unstable point may survive."""
    noise_model: bool = True
    """Measure the depth noise from the first frames (``NOISE_FRAMES``; :mod:`.noise`) and widen the
    thresholds that separate noise from structure where it exceeds what they were set for (a Kinect v1):
    the edge thresholds of smoothing and downsampling, the fusion gate and the Huber threshold. At Kinect v1
    noise nothing changes."""

    def check(self) -> None:
        """One ICP iteration count per pyramid level; a depth range that holds depths."""
        if len(self.icp_iterations) != self.pyramid_levels:
            raise UsageError(
                f"dense setting icp_iterations must hold one count per level (pyramid_levels {self.pyramid_levels}, "
                f"finest first), got {self.icp_iterations!r}"
            )
        if self.min_depth >= self.max_depth:
            raise UsageError(
                f"dense setting min_depth must be below max_depth ({self.max_depth}), got {self.min_depth}"
            )

    def icp_settings(self) -> IcpSettings:
        return IcpSettings(
            iterations=self.icp_iterations,
            distance_threshold=self.icp_distance,
            normal_cos_threshold=math.cos(math.radians(self.icp_normal_angle)),
            convergence_rotation=self.convergence_rotation,
            convergence_translation=self.convergence_translation,
            min_correspondences=self.min_correspondences,
            huber_delta=self.huber_delta,
            depth_weighting=self.depth_weighting,
            map_normals=self.map_normals,
            rotation_iterations=self.rotation_iterations,
        )


def _downsample_color(color: npt.NDArray[np.uint8], factor: int) -> npt.NDArray[np.uint8]:
    """Mean of each ``factor x factor`` block of an (H, W, 3) uint8 image, rounded (one compiled pass:
    :func:`_kernels.downsample_color`)."""
    return _kernels.downsample_color(np.ascontiguousarray(color, dtype=np.uint8), int(factor))


class DenseFusion(Estimator[DepthFrame]):
    """Dense SLAM over depth frames: map-to-frame projective ICP tracking and point-based fusion.

    :meth:`step` returns ``T_world_camera`` (camera optical frame) for each frame; the first is the
    identity. :meth:`dense_map` gives the fused points; :meth:`landmark_map` is empty (no landmarks).
    """

    name: ClassVar[str] = "dense"

    def __init__(self, config: DenseConfig | None = None, rng: np.random.Generator | None = None) -> None:
        del rng  # deterministic
        self.config = config or DenseConfig()
        self._icp = self.config.icp_settings()
        self._fusion_cos = math.cos(math.radians(self.config.fusion_normal_angle))
        self.map = PointMap()
        self._frames = 0
        self._input_points = 0
        self._T_world_camera: FloatArray | None = None
        self._motion: FloatArray | None = None  # T_previous_current of the last tracked frame
        self.predicted_frames = 0
        self.rotation_start_frames = 0
        self._icp_iterations = 0
        self._model_index: npt.NDArray[np.int64] | None = None
        self._last_stamp: int | None = None
        self._tracked_stamp: int | None = None  # stamp of the last frame fused at a tracked pose
        self._intervals: deque[int] = deque(maxlen=INTERVAL_HISTORY)
        self.gap_frames = 0
        self._checked_intrinsics: set[Intrinsics] = set()
        self._odd_principal_point: str | None = None
        self._far_depth: str | None = None
        self._auto_downsample: int | None = None
        self._widest_gate = 0.0
        self._longest_gap_ns = 0
        self.lost_frames = 0
        self.lost_reasons: Counter[str] = Counter()
        # Frames whose pairs left directions of motion unobserved (one plane in view, a corridor): the pose
        # keeps the prediction along them, so the trajectory is unreliable there.
        self.degenerate_frames = 0
        self.suspect_frames = 0
        self._recent_fits: deque[tuple[float, int]] = deque(maxlen=SUSPECT_HISTORY)  # (rmse m, pairs)
        self._unobserved: Counter[int] = Counter()
        self.removed_points = 0
        self.last_track: Any = None
        self._radial: npt.NDArray[np.float32] | None = None
        # Frames before the map could start (too few depths in range), and what their depths were.
        self.frames_before_map = 0
        self._unused_depths: list[float] = []
        # Depth noise measured from the frames (noise_model): samples of the first frames, the fitted models
        # and what they widened.
        self._pixel_samples: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]] = []
        self._residual_samples: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]] = []
        self.pixel_noise: DepthNoise | None = None
        self.residual_noise: DepthNoise | None = None
        self._edge_noise: EdgeNoise | None = None
        self._fusion_distance = self.config.fusion_distance
        self._fusion_quadratic = self.config.fusion_distance_quadratic
        self._widened: list[str] = []
        self._noise_warning: str | None = None

    @classmethod
    def compile(cls) -> None:
        """Compile or load the per-pixel loops (:mod:`relpoint.estimators.dense._kernels`); nothing to do
        when they were built ahead of time at install."""
        _kernels.prepare()

    # -- frames ------------------------------------------------------------------------------------

    def pyramid(self, frame: DepthFrame) -> list[Level]:
        """The frame's pyramid at the processing resolution (``downsample``) with the depth range applied."""
        skip = int(math.log2(self._downsample(frame.intrinsics)))
        return build_pyramid(
            frame.depth, frame.intrinsics, self.config.pyramid_levels,
            min_depth=self.config.min_depth, max_depth=self.config.max_depth, skip=skip,
            smooth=self.config.smooth_depth, edge_noise=self._edge_noise,
        )  # fmt: skip

    def _measure_pixel_noise(self, frame: DepthFrame) -> None:
        """Add the frame's second differences (input resolution, depth range applied) to the pixel noise
        samples and refit :attr:`pixel_noise`. Where it exceeds what they allow in the measured depth range,
        the edge thresholds (3 % of the depth) are widened to ``EDGE_SIGMAS`` standard deviations of a
        neighbour difference, and the fusion gate to ``GATE_SIGMAS`` standard deviations of the difference
        of two points of smoothed, downsampled frames (a 3x3 mean of independent noise divides it by 3, each
        halving by 2). Noise correlated over several pixels hardly shows in second differences, and these
        thresholds stay: neighbours then hardly differ, and a fusion gate widened to it merged bent surfaces
        (kitchen frames with stereo-like noise correlated over 4 px: ATE 6.8 -> 7.7 cm with a gate four times
        as wide)."""
        depth = frame.depth
        usable = np.isfinite(depth) & (depth >= self.config.min_depth) & (depth <= self.config.max_depth)
        self._pixel_samples.append(second_differences(np.where(usable, depth, np.float32(0.0))))
        model = fit_noise(*(np.concatenate(parts) for parts in zip(*self._pixel_samples, strict=True)))
        if model is None:
            return
        self.pixel_noise = model
        edge = model.scaled(EDGE_SIGMAS * math.sqrt(2.0))
        self._edge_noise = (edge.constant, edge.quadratic) if edge.exceeds(0.0, EDGE_JUMP, 0.0) else None
        averaged = (3.0 if self.config.smooth_depth else 1.0) * self._downsample(frame.intrinsics)
        gate = model.scaled(GATE_SIGMAS * math.sqrt(2.0) / averaged)
        self._fusion_distance = self.config.fusion_distance
        self._fusion_quadratic = self.config.fusion_distance_quadratic
        if gate.exceeds(self.config.fusion_distance, 0.0, self.config.fusion_distance_quadratic):
            self._fusion_distance = max(self.config.fusion_distance, gate.constant)
            self._fusion_quadratic = max(self.config.fusion_distance_quadratic, gate.quadratic)

    def _measure_residual_noise(self, result: Any) -> None:
        """Add a tracked frame's finest-level ICP point-to-plane residuals to the samples; after
        ``NOISE_FRAMES`` frames fit :attr:`residual_noise` and widen the Huber threshold to ``HUBER_SIGMAS``
        standard deviations of them where that exceeds ``huber_delta`` in the measured depth range; then
        report what the measured noise widened."""
        if result.pair_depths is None or result.pair_residuals is None:
            return
        self._residual_samples.append((result.pair_depths.copy(), result.pair_residuals.copy()))
        if len(self._residual_samples) < NOISE_FRAMES:
            return
        model = fit_noise(*(np.concatenate(parts) for parts in zip(*self._residual_samples, strict=True)))
        self._residual_samples = []
        if model is None:
            return
        self.residual_noise = model
        huber = model.scaled(HUBER_SIGMAS)
        if self.config.huber_delta > 0 and huber.exceeds(self.config.huber_delta, 0.0, 0.0):
            self._icp = dataclasses.replace(self._icp, huber_noise=(huber.constant, huber.quadratic))
        self._report_noise()

    def _report_noise(self) -> None:
        """Name (and warn once of) the thresholds the measured depth noise widened."""
        widened = []
        if self._edge_noise is not None:
            edge = self._edge_noise[0] + self._edge_noise[1] * REFERENCE_DEPTH**2
            widened.append(
                f"edge thresholds {edge * 100:.2g} cm at {REFERENCE_DEPTH:g} m (was {EDGE_JUMP * 100:g} % of the depth)"
            )
        if (self._fusion_distance, self._fusion_quadratic) != (
            self.config.fusion_distance, self.config.fusion_distance_quadratic
        ):  # fmt: skip
            widened.append(
                f"fusion gate {self._fusion_distance:.3g} m + {self._fusion_quadratic:.3g} z^2 "
                f"(was {self.config.fusion_distance:g} + {self.config.fusion_distance_quadratic:g} z^2)"
            )
        if self._icp.huber_noise is not None:
            constant, quadratic = self._icp.huber_noise
            widened.append(
                f"Huber threshold {max(self.config.huber_delta, constant + quadratic * REFERENCE_DEPTH**2) * 100:.2g} cm "
                f"at {REFERENCE_DEPTH:g} m, {max(self.config.huber_delta, constant + quadratic * 16) * 100:.2g} cm "
                f"at 4 m (was {self.config.huber_delta * 100:g} cm)"
            )
        self._widened = widened
        if widened and self._noise_warning is None:
            measured = []
            if self.pixel_noise is not None:
                measured.append(f"{float(self.pixel_noise.sigma(REFERENCE_DEPTH)) * 100:.2g} cm from pixel to pixel")
            if self.residual_noise is not None:
                measured.append(
                    f"{float(self.residual_noise.sigma(REFERENCE_DEPTH)) * 100:.2g} cm between frame and map"
                )
            self._noise_warning = (
                f"depth noise measured from the first frames at {REFERENCE_DEPTH:g} m: "
                + ", ".join(measured)
                + " (the settings are made for a Kinect v1: about 0.6 cm a pixel there); widened: "
                + "; ".join(widened)
                + ": expect a less accurate path and map than with a less noisy camera"
            )
            logger.warning("frame %d: %s", self._frames, self._noise_warning)

    def _downsample(self, intrinsics: Intrinsics) -> int:
        """The downsampling factor: ``downsample``, or with 0 the least of 1, 2 and 4 that leaves the first
        frame at most ``PROCESSED_PIXELS`` (kept for the log: one map, one resolution)."""
        if self.config.downsample:
            return self.config.downsample
        if self._auto_downsample is None:
            pixels = intrinsics.width * intrinsics.height
            self._auto_downsample = next((f for f in (1, 2) if pixels <= PROCESSED_PIXELS * f * f), 4)
        return self._auto_downsample

    def _source_levels(self) -> list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]]:
        """Per pyramid level, the ICP source: (3, N_l) world positions and normals of the map points rendered
        at the last pose, every ``2**level * source_stride``-th pixel.

        The coarsest level takes every rendered point: it sets the basin of convergence, and under fast
        motion the stable points (seen in earlier frames too) are a shrinking part of the last view, while
        the coarse averaging already damps the noise of points seen once. Finer levels take the stable
        points unless they are fewer than ``STABLE_SHARE`` of those rendered (a share, so that the choice
        does not depend on the image size).
        """
        assert self._model_index is not None
        out = []
        coarsest = self.config.pyramid_levels - 1
        for level in range(self.config.pyramid_levels):
            stride = 2**level * self.config.source_stride
            ids = self._model_index[::stride, ::stride].reshape(-1)
            ids = ids[ids >= 0]
            if self.config.track_min_weight > 0 and level < coarsest:
                stable = ids[self.map.weights[ids] >= self.config.track_min_weight]
                if len(stable) >= max(STABLE_SHARE * len(ids), self.config.min_correspondences):
                    ids = stable
            out.append((np.take(self.map.positions, ids, axis=1), np.take(self.map.normals, ids, axis=1)))
        return out

    def _predict(
        self, sources: list[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]], pyramid: list[Level]
    ) -> FloatArray:
        """The initial guess ``T_world_camera`` of ICP: the previous pose, or the constant-velocity prediction
        when it explains the coarsest level at least as well (fewer iterations, and no divergence: an
        under-converged motion never feeds back unchecked)."""
        assert self._T_world_camera is not None
        previous = self._T_world_camera
        if not self.config.constant_velocity or self._motion is None:
            return previous
        predicted = previous @ self._motion
        coarse = len(pyramid) - 1
        points, normals = sources[coarse]
        n_prev, cost_prev = alignment_cost(invert_pose(previous), points, normals, pyramid[coarse], self._icp)
        n_pred, cost_pred = alignment_cost(invert_pose(predicted), points, normals, pyramid[coarse], self._icp)
        # a cost is inf with too few pairs: two infinities say nothing for the prediction
        if math.isfinite(cost_pred) and n_pred >= 0.9 * n_prev and cost_pred <= cost_prev:
            self.predicted_frames += 1
            return predicted
        return previous

    def _confidence(self, level: Level) -> npt.NDArray[np.float32]:
        k = level.intrinsics
        if self._radial is None or self._radial.size != k.width * k.height:
            u = (np.arange(k.width) - k.cx) / (k.width / 2)
            v = (np.arange(k.height) - k.cy) / (k.height / 2)
            r2 = (u[None, :] ** 2 + v[:, None] ** 2) / 2  # 1 at the corners
            self._radial = np.exp(-r2 / (2 * self.config.radial_sigma**2)).astype(np.float32).reshape(-1)
        return self._radial

    def step(self, observation: DepthFrame) -> Pose:
        """Track the frame against the map, fuse it, and return ``T_world_camera`` at its stamp."""
        frame = observation
        if not isinstance(frame, DepthFrame):
            raise EstimatorError("the dense estimator takes depth frames (DepthFrame), not point observations")
        if self._last_stamp is not None and frame.stamp_ns <= self._last_stamp:
            raise EstimatorError(f"depth frame stamp {frame.stamp_ns} ns is not after the previous one")
        if frame.intrinsics not in self._checked_intrinsics:
            self._check_principal_point(frame.intrinsics)
        if self._last_stamp is not None:
            self._intervals.append(frame.stamp_ns - self._last_stamp)
        if self.config.noise_model and self.frames_before_map + NOISE_FRAMES > self._frames:
            self._measure_pixel_noise(frame)
        pyramid = self.pyramid(frame)
        level0 = pyramid[0]
        colors = frame.color
        if colors is not None and self._downsample(frame.intrinsics) > 1:
            colors = _downsample_color(colors, self._downsample(frame.intrinsics))
        self._input_points += int(level0.valid.sum())

        if self._T_world_camera is None:
            # The next frame is tracked against this one's points at every source_stride-th pixel: a map
            # started from fewer than min_correspondences of them could never track a frame, nor grow.
            stride = self.config.source_stride
            usable = int(level0.valid[::stride, ::stride].sum())
            if usable < self.config.min_correspondences:
                return self._before_map(frame, usable)
            self._check_first_depths(level0)
            T_world_camera = np.eye(4)
        else:
            sources = self._source_levels()
            prediction = self._predict(sources, pyramid)
            result = track(sources, pyramid, invert_pose(prediction), self._gap_settings(frame.stamp_ns))
            self._icp_iterations += result.iterations
            self.rotation_start_frames += result.rotation_start
            self.last_track = result
            step = invert_pose(self._T_world_camera) @ invert_pose(result.T_camera_world) if result.ok else None
            if step is not None and float(np.linalg.norm(step[:3, 3])) <= self.config.max_step:
                T_world_camera = invert_pose(result.T_camera_world)
                if result.unobserved:
                    self._degenerate(result.unobserved)
                self._check_fit(result.rmse, result.correspondences)
                if self.config.noise_model and self.residual_noise is None and self._frames < 4 * NOISE_FRAMES:
                    self._measure_residual_noise(result)
                    if self._frames == 4 * NOISE_FRAMES - 1:  # no residual model: report the pixel model's
                        self._report_noise()
            else:
                # Held, and not fused: a frame placed at a pose it was not tracked to would corrupt the map.
                self.lost_frames += 1
                if not level0.valid.any():
                    self.lost_reasons["the frame holds no depth in range"] += 1
                    reason = f"no pixel with depth {self._depth_range()}"
                elif step is not None:
                    self.lost_reasons["ICP moved the camera beyond max_step"] += 1
                    reason = f"ICP moved it {float(np.linalg.norm(step[:3, 3])):.2f} m, beyond max_step {self.config.max_step:g} m"
                elif result.correspondences < self.config.min_correspondences:
                    self.lost_reasons["too few ICP pairs: little of the frame's depth matches the map"] += 1
                    reason = f"ICP ended with {result.correspondences} pairs (min_correspondences {self.config.min_correspondences})"
                else:
                    self.lost_reasons["singular normal equations"] += 1
                    reason = "the ICP normal equations were singular"
                logger.warning("frame %d: tracking failed (%s); pose held, frame not fused", self._frames, reason)
                self._frames += 1
                self._last_stamp = frame.stamp_ns
                return Pose.from_matrix(frame.stamp_ns, self._T_world_camera)

        index_map = self.map.render(invert_pose(T_world_camera), level0)
        confidence = self._confidence(level0) if self.config.radial_sigma > 0 else None
        if self.config.fusion_depth_weighting:
            depth = level0.planes[2]
            factor = np.minimum((np.float32(SIGMA_1M) / depth_sigma(depth)) ** 2, np.float32(1.0))
            confidence = factor if confidence is None else confidence * factor
        self._model_index, _ = self.map.fuse(
            T_world_camera, level0, colors, index_map, self._fusion_distance, self._fusion_cos,
            self._frames, self.config.max_weight, self._fusion_quadratic, confidence,
        )  # fmt: skip
        if self.config.remove_unstable and self._frames % self.config.unstable_age == 0 and self._frames > 0:
            drop = self.map.unstable(self._frames, self.config.stable_weight, self.config.unstable_age)
            if drop.any():
                remap = self.map.remove(drop)
                self.removed_points += int(drop.sum())
                self._model_index = np.where(self._model_index >= 0, remap[np.maximum(self._model_index, 0)], -1)
        if self._T_world_camera is not None:
            self._motion = invert_pose(self._T_world_camera) @ T_world_camera
        self._T_world_camera = T_world_camera
        self._frames += 1
        self._last_stamp = self._tracked_stamp = frame.stamp_ns
        return Pose.from_matrix(frame.stamp_ns, T_world_camera)

    def _depth_range(self) -> str:
        """The depths used, as words: "in 0.1-4 m", or "from 0.1 m" without ``max_depth``."""
        if math.isinf(self.config.max_depth):
            return f"from {self.config.min_depth:g} m"
        return f"in {self.config.min_depth:g}-{self.config.max_depth:g} m"

    def _check_first_depths(self, level: Level) -> None:
        """Warn of a first frame whose median depth is beyond ``FAR_MEDIAN_DEPTH``: most likely depth in
        another unit than the log format's, which scales the path and the map and nothing else shows."""
        median = float(np.median(level.depth[level.valid]))
        if median > IMPOSSIBLE_MEDIAN_DEPTH and math.isinf(self.config.max_depth):
            raise EstimatorError(
                f"the first frame with depth has a median depth of {median:.0f} m, farther than any depth camera "
                "measures: its depth is most likely in another unit than the log format's (16UC1 millimetres, "
                "32FC1 metres; e.g. millimetres in a 32FC1 image); convert the unit when writing the log, or set "
                "--param max_depth to take it as it is"
            )
        if median > FAR_MEDIAN_DEPTH:
            self._far_depth = (
                f"the map's first frame has a median depth of {median:.1f} m, far for a depth camera: if its "
                "depth images hold another unit than the log format's (16UC1 millimetres, 32FC1 metres; e.g. "
                "TUM's 5000 per metre or a RealSense D405's 0.1 mm), the path and map are scaled by as much; "
                "convert the unit when writing the log"
            )
            logger.warning("frame %d: %s", self._frames, self._far_depth)

    def _check_principal_point(self, k: Intrinsics) -> None:
        """Warn (once) of a principal point on or beyond the image border: a camera's optical axis meets
        its image near the middle, so such a CameraInfo is most likely wrong (another image size, a
        cropped or binned image, fields in the wrong places) and every back-projected point with it."""
        self._checked_intrinsics.add(k)
        if 0 < k.cx < k.width - 1 and 0 < k.cy < k.height - 1:
            return
        message = (
            f"the camera_info's principal point ({k.cx:g}, {k.cy:g}) lies on or beyond the border of its "
            f"{k.width}x{k.height} image: the intrinsics are most likely wrong, and the map and path with them"
        )
        if self._odd_principal_point is None:
            logger.warning("frame %d: %s", self._frames, message)
            self._odd_principal_point = message

    def _gap_settings(self, stamp_ns: int) -> IcpSettings:
        """ICP settings for a frame at ``stamp_ns``: after a gap (more than ``GAP_RATIO`` typical intervals
        since the last tracked frame) the association gate ``icp_distance``, chosen for the motion between
        two frames, grows with the time elapsed, up to ``max_step`` (a larger motion is a divergence anyway).
        A 1 s gap in 30 fps kitchen frames was otherwise registered 12 cm short, without a warning."""
        if self._tracked_stamp is None or len(self._intervals) < 2:
            return self._icp
        typical = float(np.median(np.asarray(self._intervals, dtype=np.float64)))
        elapsed = stamp_ns - self._tracked_stamp
        if typical <= 0 or elapsed <= GAP_RATIO * typical:
            return self._icp
        gate = min(self.config.icp_distance * elapsed / typical, max(self.config.max_step, self.config.icp_distance))
        if self.gap_frames == 0:
            logger.warning(
                "frame %d: %.3g s since the last tracked frame, %.1f times the typical %.3g s: ICP's association "
                "gate widened from %g m to %.2f m for it; further such frames are counted in run.json (gap_frames)",
                self._frames, elapsed * 1e-9, elapsed / typical, typical * 1e-9, self.config.icp_distance, gate,
            )  # fmt: skip
        self.gap_frames += 1
        self._widest_gate = max(self._widest_gate, gate)
        self._longest_gap_ns = max(self._longest_gap_ns, elapsed)
        return dataclasses.replace(self._icp, distance_threshold=gate)

    def _check_fit(self, rmse: float, pairs: int) -> None:
        """Count (and warn once of) a tracked frame whose fit is far worse than the recent ones'
        (``SUSPECT_RMSE_RATIO``, ``SUSPECT_PAIRS_RATIO``); remember the fit."""
        if len(self._recent_fits) >= SUSPECT_HISTORY // 2 and math.isfinite(rmse):
            typical_rmse = float(np.median([fit[0] for fit in self._recent_fits]))
            typical_pairs = float(np.median([fit[1] for fit in self._recent_fits]))
            if rmse > SUSPECT_RMSE_RATIO * typical_rmse and pairs < SUSPECT_PAIRS_RATIO * typical_pairs:
                if self.suspect_frames == 0:
                    logger.warning(
                        "frame %d: ICP ended with %.1f times the recent residual (%.1f mm) on %.2f times the recent "
                        "pairs: the motion may have been too large to follow, and the pose may be wrong from here; "
                        "further such frames are counted in run.json (suspect_frames)",
                        self._frames, rmse / typical_rmse, rmse * 1e3, pairs / typical_pairs,
                    )  # fmt: skip
                self.suspect_frames += 1
        if math.isfinite(rmse):
            self._recent_fits.append((rmse, pairs))

    def _degenerate(self, unobserved: int) -> None:
        """Count a frame whose pairs left ``unobserved`` directions of motion unconstrained; warn once."""
        if self.degenerate_frames == 0:
            logger.warning(
                "frame %d: degenerate geometry (e.g. one plane in view): %d of 6 directions of motion hold no "
                "more information than the noise of the normals gives them, and the pose keeps ICP's start (the "
                "last pose) along them; further frames are counted in run.json (degenerate_frames)",
                self._frames, unobserved,
            )  # fmt: skip
        self.degenerate_frames += 1
        self._unobserved[unobserved] += 1

    def _before_map(self, frame: DepthFrame, usable: int) -> Pose:
        """A frame with too few depths in range to start the map (a camera's first frames are often
        empty): not fused, its pose the identity; the map starts at the first usable frame."""
        depth = frame.depth[np.isfinite(frame.depth) & (frame.depth > 0)]
        if depth.size:
            self._unused_depths.append(float(np.median(depth)))
        if self.frames_before_map == 0:
            logger.warning(
                "frame %d: %d pixels with depth %s at the ICP's source stride %d, fewer than "
                "min_correspondences %d: the map starts at the first frame that has enough", self._frames, usable,
                self._depth_range(), self.config.source_stride, self.config.min_correspondences,
            )  # fmt: skip
        self.frames_before_map += 1
        self._frames += 1
        self._last_stamp = frame.stamp_ns
        return Pose.from_matrix(frame.stamp_ns, np.eye(4))

    def finish(self, trajectory: Any) -> Any:
        """The trajectory as it is; fails (:class:`EstimatorError`, naming the depths it saw) when no frame
        could start the map."""
        if self._T_world_camera is None and self.frames_before_map:
            if self._unused_depths:
                median = float(np.median(self._unused_depths))
                seen = f"their median depth is {median:.2f} m"
                if median > self.config.max_depth:
                    seen += (f", beyond max_depth {self.config.max_depth:g} m: a depth image holds millimetres "
                             "in 16UC1 and metres in 32FC1 (REP 118); convert another unit (TUM's 5000 per metre) when writing the log, or "
                             "raise --param max_depth")  # fmt: skip
                elif median < self.config.min_depth:
                    seen += f", below min_depth {self.config.min_depth:g} m: check the depth unit, or lower --param min_depth"
            else:
                seen = "they hold no depth at all (every pixel 0 or NaN)"
            raise EstimatorError(
                f"no depth frame of {self.frames_before_map} had {self.config.min_correspondences} pixels with depth "
                f"{self._depth_range()} at the ICP's source stride "
                f"{self.config.source_stride} to start the map; {seen}"
            )
        return trajectory

    # -- outputs -----------------------------------------------------------------------------------

    def landmark_map(self) -> LandmarkMap:
        return LandmarkMap.empty()

    @property
    def map_size(self) -> int:
        return len(self.map)

    def dense_map(self) -> tuple[FloatArray, FloatArray, npt.NDArray[np.uint8], FloatArray]:
        """The fused map: positions (M, 3) metres and unit normals (M, 3) in ``world``, colours (M, 3) uint8 RGB,
        weights (M,) (measurements fused per point); float64 copies. A point that no frame with colour has
        seen takes the colour of the nearest point that one has (:func:`colors_filled`)."""
        positions = self.map.positions.T.astype(np.float64)
        return (
            positions,
            self.map.normals.T.astype(np.float64),
            colors_filled(
                positions, np.clip(np.rint(self.map.colors.T), 0, 255).astype(np.uint8), self.map.color_weights > 0
            ),
            self.map.weights.astype(np.float64),
        )

    def summary(self) -> dict[str, Any]:
        points = len(self.map)
        return {
            "frames": self._frames,
            "downsample": self.config.downsample or self._auto_downsample or 1,
            "map_points": points,
            "input_points": self._input_points,
            "compression_ratio": points / self._input_points if self._input_points else 0.0,
            "lost_frames": self.lost_frames,
            "lost_reasons": dict(self.lost_reasons),
            "degenerate_frames": self.degenerate_frames,
            "suspect_frames": self.suspect_frames,
            "gap_frames": self.gap_frames,
            "frames_before_map": self.frames_before_map,
            "predicted_frames": self.predicted_frames,
            "rotation_start_frames": self.rotation_start_frames,
            "icp_iterations_per_frame": self._icp_iterations / max(self._frames - 1, 1),
            "removed_unstable_points": self.removed_points,
            "depth_noise": {
                "pixel": None if self.pixel_noise is None else self.pixel_noise.as_dict(),
                "residual": None if self.residual_noise is None else self.residual_noise.as_dict(),
                "widened": list(self._widened),
            },
        }

    def run_warnings(self) -> list[str]:
        warnings = []
        if self.lost_reasons:
            reasons = ", ".join(f"{n} {reason}" for reason, n in self.lost_reasons.most_common())
            warnings.append(f"dense: why frames were lost: {reasons}")
        if self._odd_principal_point:
            warnings.append(f"dense: {self._odd_principal_point}")
        if self._far_depth:
            warnings.append(f"dense: {self._far_depth}")
        if self._noise_warning:
            warnings.append(f"dense: {self._noise_warning}")
        if self.gap_frames:
            warnings.append(
                f"dense: {self.gap_frames} frames came after a gap in time (up to {self._longest_gap_ns * 1e-9:.3g} s "
                f"since the last tracked frame); ICP searched up to {self._widest_gate:.2f} m for their pairs"
            )
        if self.suspect_frames:
            warnings.append(
                f"dense: {self.suspect_frames} of {self._frames} frames ended ICP with far more residual on far fewer "
                "pairs than the frames before them (the motion between frames may be too large to follow): the "
                "poses from there may be wrong; a higher frame rate, or a smaller icp_distance with max_step, helps"
            )
        if self.degenerate_frames:
            most = self._unobserved.most_common(1)[0][0]
            warnings.append(
                f"dense: {self.degenerate_frames} of {self._frames} frames saw degenerate geometry (e.g. one plane): "
                f"their depth left up to {max(self._unobserved)} of 6 directions of motion unobserved (mostly "
                f"{most}), where the pose keeps ICP's start (the last pose); the trajectory is unreliable there"
            )
        return warnings


SPEC = EstimatorSpec(
    name="dense",
    description="Dense RGB-D SLAM: map-to-frame projective point-to-plane ICP and point-based fusion",
    config_class=DenseConfig,
    estimator_class=DenseFusion,
    input_kind=DEPTH,
    uses=frozenset({"color"}),  # optional: colours of the map points
)
