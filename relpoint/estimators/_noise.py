"""Observation noise estimated from the data, so that the point estimators' defaults hold at any scale.

A simulated sensor at 70 m range and a depth camera at 2 m differ in their point noise by a factor of
twenty; bounds and gates written in metres for one are wrong for the other. The noise is therefore
taken from the first iterations of the log itself, in two parts:

- **Registration residuals.** Observations are registered with a trimmed mutual-nearest-neighbour
  ICP, consecutive ones first (points move little between two iterations compared with their
  spacing), then observations half the held-back window apart, starting from the chained consecutive
  motions. The residual of a matched pair is the difference of two noisy observations of one point:
  with per-axis noise ``sigma`` it is Gaussian with ``sigma * sqrt(2)`` per axis, whose length has
  median ``1.5382 * sqrt(2) * sigma``. The wide baseline matters on real sensors, whose error largely
  repeats from one frame to the next: on Starry Night's stereo points consecutive steps give 2 mm,
  steps 15 apart 4.9 cm (the points scatter by 4.6 cm RMSE about the true landmarks). Where ICP from
  the identity does not bring a pair's points back onto ones seen before (a sensor moving about its
  landmarks' spacing between observations: a low rate, a fast platform), it starts from the step
  before, then from a global search over points matched by their neighbour distances
  (:func:`register_consecutive`). Without it, an independent simulator's 1 Hz circle measured 0.033
  m for 0.01 m of noise and 1.72 m for 0.3 m (now 0.0100 and 0.301). Registrations whose matches
  are pairs of neighbouring points (clouds that share few landmarks) are kept out
  (:func:`distinctness`, :func:`_distinct_steps`, :func:`registration_noise`).
- **A floor relative to range.** Even the wider baseline does not see an error that stays while the
  viewpoint barely changes: on the 7-Scenes keypoints the residuals give 0.3 mm-3 mm where the
  points scatter by 1.1 cm about their tracks. The estimate is therefore at least ``RANGE_FRACTION``
  of the median range of the observed points (0.5 %: 1 cm at 2 m; 0.22-0.28 m at the simulator's
  45-55 m, under what its residuals give for its 0.3 m).

The same held-back observations also tell how hard the sensor accelerates
(:func:`estimate_acceleration`): the consecutive registrations chained into a path, velocities over
``ACCELERATION_SPAN_S``, their changes, and the white acceleration noise over one interval that
explains them. A motion model's acceleration noise written in m/s^2 for a
vehicle (2 m/s^2) lets a tabletop sensor's prediction wander over several of its landmarks' spacings,
and the association with it; unset, the EKF's and FastSLAM's ``linear_acceleration_noise`` is
``ACCELERATION_MARGIN`` times what the path shows, never less than that default scaled by the noise,
and not more than the vehicle default, unless the path itself accelerates harder: then that
(:func:`derived_acceleration_noise`). On the figure eight ten times larger (noise and all) FastSLAM's
ATE divided by the scale was 27.5 in the median of five seeds with the vehicle default (0.78 on the
figure eight itself); with what the path shows, 1.96 (``benchmarks/scene_scale.py``; docs/keypoints.md).

:class:`NoiseAdaptive` wraps an estimator whose settings need the noise: it holds back the first
observations, estimates the noise from them, builds the estimator with it and replays them; the poses
it returned for the held-back iterations are replaced in :meth:`finish`.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt

from relpoint.estimators.base import Estimator
from relpoint.geometry import FloatArray, kabsch, kabsch_batch
from relpoint.settings import Settings, setting
from relpoint.types import LandmarkMap, OdometryMeasurement, PointObservation, Pose, PositionFix, Trajectory

if TYPE_CHECKING:
    from relpoint.estimators._odometry_check import OdometryCheck

#: A registration ``(R, t, residuals)``: the rotation and translation that move a point set onto another,
#: and the residual lengths (m) of its trimmed pairs (:func:`register`).
Registration = tuple[FloatArray, FloatArray, FloatArray]
#: Median length of a 3D Gaussian vector with unit per-axis deviation, times sqrt(2) (two noisy points).
_PAIR_MEDIAN = 1.5382 * math.sqrt(2.0)
log = logging.getLogger(__name__)

#: Landmarks are seen again: registered onto the observation before, a point lies far closer to its
#: own earlier sighting than to its neighbours in its own observation. Fresh samples of surfaces (a
#: lidar scan, a depth cloud) lie about as close to the earlier samples as to each other, whatever
#: their density. The median ratio of the two distances over mutually nearest pairs (see
#: :func:`revisit_ratio`), measured: the simulator's figure eight 0.06, the 7-Scenes keypoints 0.03,
#: Starry Night's stereo landmarks 0.01, the robustness matrix's scenes at most 0.11 (30 clutter points
#: a frame: 0.12); scans of a room's walls 0.49-0.61 at 100 to 3,000 points a scan. From this ratio on a run warns that the points are not landmarks.
REVISIT_RATIO = 0.3
#: Observations of at least ``MIN_POINTS`` points held back for the estimate ...
NOISE_FRAMES = 30
MIN_POINTS = 4
#: ... but never more iterations than this (a log that rarely sees four points).
MAX_HELD = 200
#: A median point range (m) or odometry speed (m/s) beyond these says the log is likely in millimetres.
UNIT_RANGE_M = 2000.0
UNIT_SPEED_M_S = 300.0
#: Noise along the line of sight beyond this many times that across it is warned of: on isotropic
#: noise the two estimates agree within 0.9-1.1; a range error 5 and 10 times the lateral one measures
#: 3.2 and 4.4-5.2 times (the trimmed registration cuts the widest residuals along the sight).
ANISOTROPY_WARNING = 2.0
#: Smallest noise relative to the median range of the points (see the module docstring).
RANGE_FRACTION = 0.005
#: The simulator's default noise (m), which the distance settings' defaults were chosen for; the
#: fallback when the first observations cannot be registered.
SIMULATOR_SIGMA = 0.3
#: The motion models' linear acceleration noise (m/s^2) where the held-back path cannot tell: a
#: vehicle's, which the EKF's and FastSLAM's defaults were chosen for.
VEHICLE_ACCELERATION = 2.0
#: The largest linear acceleration noise (m/s^2) the settings take.
MAX_ACCELERATION_NOISE = 1e4
#: The motion models' angular acceleration noise (rad/s^2) where the held-back path cannot tell, and
#: the most it takes from a calm path: a vehicle's, which the defaults were chosen for.
VEHICLE_ANGULAR_ACCELERATION = 0.5
#: The largest angular acceleration noise (rad/s^2) the settings take.
MAX_ANGULAR_ACCELERATION_NOISE = 1e3
#: The simulator's interval between observations (s), at which the vehicle defaults were chosen.
SIMULATOR_INTERVAL_S = 0.1
#: Velocities are taken over about this span (s) of the held-back path: over one iteration the
#: registrations' own error, divided by dt^2, would swamp a slow sensor's acceleration.
ACCELERATION_SPAN_S = 0.5
#: The derived acceleration noise is this many times what the path shows: the first observations may
#: be the calmest of the log, and a hand-held camera's shake is faster than the span can see. Too
#: small a noise breaks the association; too large a one lets a prediction over a long interval
#: wander over several landmarks. 5 maps the calmest of the simulator's scenes, for which the
#: vehicle default was chosen (the indoor figure eight, 0.40-0.42 m/s^2 measured), onto that default.
#: Measured: the 7-Scenes kitchen keypoints (30 Hz, 0.35 m/s^2) give the EKF 3.5-3.9 cm at 1-3
#: m/s^2, 4.0 cm at 0.5 and 5.1 cm at 0.1; a static scene seen at 2 Hz with 0.5 m between frames
#: (0.12 m/s^2) gives landmarks 0.10 m off at 0.48 m/s^2, 0.33 m at 0.6, 1.0 m at 1 and 1.6 m at 2;
#: a tabletop scene at 0.3 m range, 0.4 mm ATE at 0.01-0.3 and 14 mm at 2. A turn sharper than the
#: margin allows is what the association's collapse retry (up to 16 x the noise) is for.
ACCELERATION_MARGIN = 5.0


#: Registration pairs within this many times their median distance count; farther ones are outliers.
REGISTRATION_TRIM = 3.0


def register(
    first: FloatArray, second: FloatArray, initial: tuple[FloatArray, FloatArray] | None = None,
    iterations: int = 15, trim: float = REGISTRATION_TRIM,
) -> Registration | None:  # fmt: skip
    """Move ``second`` onto ``first`` (both (N, 3), m) by ICP over mutual nearest neighbours.

    Each round fits only the pairs within ``trim`` times the median pair distance, starting from
    ``initial`` ``(R, t)`` (default: identity). Returns ``(R, t, residuals)`` with the trimmed pairs'
    residual lengths (m), or None when fewer than three pairs hold.
    """
    from scipy.spatial import cKDTree  # here, not at import: scipy costs start-up time

    if len(first) < 3 or len(second) < 3:
        return None
    tree_first = cKDTree(first)
    R, t = initial if initial is not None else (np.eye(3), np.zeros(3))
    residual = np.empty(0)
    for _ in range(iterations):
        moved = second @ R.T + t
        matched = _trimmed_matches(tree_first, first, moved, trim)
        if matched is None:
            return None
        distance, nearest, keep = matched
        residual = distance[keep]
        R_new, t_new = kabsch(second[keep], first[nearest[keep]])
        if np.allclose(R_new, R, atol=1e-9) and np.allclose(t_new, t, atol=1e-9):
            break
        R, t = R_new, t_new
    return R, t, residual


def _trimmed_matches(
    tree_first: Any, first: FloatArray, moved: FloatArray, trim: float
) -> tuple[FloatArray, npt.NDArray[np.intp], npt.NDArray[np.bool_]] | None:
    """The mutual nearest neighbours of ``moved`` (N, 3) in ``first`` (``tree_first`` its cKDTree) within
    ``trim`` times their median distance: ``(distance, nearest, keep)`` over ``moved``'s points, or None
    when fewer than three pairs hold."""
    from scipy.spatial import cKDTree

    distance, nearest = tree_first.query(moved)
    mutual = cKDTree(moved).query(first[nearest])[1] == np.arange(len(moved))
    if mutual.sum() < 3:
        return None
    keep = mutual & (distance <= trim * np.median(distance[mutual]))
    if keep.sum() < 3:
        return None
    return distance, nearest, keep


def revisit_measure(first: FloatArray, second: FloatArray, R: FloatArray, t: FloatArray) -> tuple[float, int] | None:
    """The revisit ratio of ``second`` moved by ``(R, t)`` onto ``first`` (both (N, 3), m) and the number
    of pairs it is the median of: over the mutually nearest pairs, the pair's distance divided by the
    ``second`` point's distance to its nearest neighbour in ``second``. Well under 1 where ``second``
    sees ``first``'s points again, about 0.5 for fresh samples of one surface or a registration that
    missed; None with fewer than three such pairs."""
    from scipy.spatial import cKDTree

    if len(first) < 2 or len(second) < 2:
        return None
    moved = second @ R.T + t
    between, nearest = cKDTree(first).query(moved)
    mutual = cKDTree(moved).query(first[nearest])[1] == np.arange(len(moved))
    within = cKDTree(second).query(second, k=2)[0][:, 1]
    usable = mutual & (within > 0)
    pairs = int(usable.sum())
    if pairs < 3:
        return None
    return float(np.median(between[usable] / within[usable])), pairs


#: Points of each observation the global search (:func:`register_globally`) draws on, at most.
GLOBAL_POINTS = 400
#: Hypotheses (three matched points each) the global search scores.
GLOBAL_HYPOTHESES = 2000
#: Neighbour distances that describe a point's surroundings, whatever the sensor's pose.
GLOBAL_NEIGHBOURS = 4
#: Descriptor matches kept per point of the later observation.
GLOBAL_MATCHES = 3
#: Mutually nearest pairs a registration from the identity needs before a revisit ratio of
#: ``REVISIT_RATIO`` or more sends it to other starts. Starry Night's few stereo points (6-9 there)
#: gave 0.31 on a step that held; another start's nearby answer moved the wide-baseline
#: registrations to a noise of 0.8 cm where the points scatter by 4.6 cm.
GLOBAL_MIN_PAIRS = 10
#: Consecutive observations searched globally before the search is given up on a log where no pair
#: has brought its points back onto ones seen before (fresh samples of surfaces never do).
GLOBAL_ATTEMPTS = 3


def register_globally(first: FloatArray, second: FloatArray, rng: np.random.Generator) -> Registration | None:
    """Move ``second`` onto ``first`` (both (N, 3), m) wherever the sensor went in between: ICP
    (:func:`register`) started from the best of ``GLOBAL_HYPOTHESES`` rigid motions, each fitted to
    three points matched by their distances to their ``GLOBAL_NEIGHBOURS`` nearest neighbours (which no
    motion changes), scored by how many of ``second``'s points it brings within a quarter of the
    points' spacing of one of ``first``'s. For a sensor that moves about its landmarks' spacing or more
    between observations (a low rate, a fast platform), where ICP from the identity settles on a wrong
    match. Returns what :func:`register` returns, or None.
    """
    from scipy.spatial import cKDTree

    k = GLOBAL_NEIGHBOURS
    if len(first) <= k + 2 or len(second) <= k + 2:
        return None
    a = first if len(first) <= GLOBAL_POINTS else first[rng.choice(len(first), GLOBAL_POINTS, replace=False)]
    b = second if len(second) <= GLOBAL_POINTS else second[rng.choice(len(second), GLOBAL_POINTS, replace=False)]
    tree_a = cKDTree(a)
    describe_a = tree_a.query(a, k=k + 1)[0][:, 1:]
    describe_b = cKDTree(b).query(b, k=k + 1)[0][:, 1:]
    spacing = float(np.median(describe_a[:, 0]))
    if not spacing > 0:
        return None
    matches = min(GLOBAL_MATCHES, len(a))
    nearest = cKDTree(describe_a).query(describe_b, k=matches)[1].reshape(len(b), matches)
    source = np.repeat(np.arange(len(b)), matches)
    target = nearest.ravel()
    picks = rng.integers(0, len(source), size=(GLOBAL_HYPOTHESES, 3))
    p, q = b[source[picks]], a[target[picks]]  # (H, 3, 3): three points of b and their matches in a
    # Keep the triangles whose sides agree (a rigid motion keeps them) and that are not degenerate.
    sides_p = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    sides_q = np.linalg.norm(q - np.roll(q, 1, axis=1), axis=2)
    rigid = np.all(np.abs(sides_p - sides_q) <= 0.5 * spacing, axis=1) & np.all(sides_p > 0.5 * spacing, axis=1)
    if not rigid.any():
        return None
    p, q = p[rigid], q[rigid]
    rotations, translations = kabsch_batch(p, q)
    moved = np.einsum("hij,nj->hni", rotations, b) + translations[:, None, :]
    distance = tree_a.query(moved.reshape(-1, 3))[0].reshape(len(p), len(b))
    best = int(np.argmax(np.sum(distance <= 0.25 * spacing, axis=1)))
    return register(first, second, (rotations[best], translations[best]))


def register_consecutive(
    first: FloatArray,
    second: FloatArray,
    previous: Registration | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[Registration | None, float | None, bool]:
    """Move ``second`` onto ``first``, the observation before it (both (N, 3), m): ICP from the identity
    (:func:`register`); where that fails or does not bring the points back onto ones seen before (its
    :func:`revisit_measure` ``REVISIT_RATIO`` or more), ICP from ``previous`` (the step before, a
    sensor keeping its pace), then the global search (:func:`register_globally`, its draws from
    ``rng``): the first of these that does. Else the identity's (what :func:`register` returns, or
    None). Fewer than ``GLOBAL_MIN_PAIRS`` pairs (a few points an observation) keep the identity's.
    Returns the registration, its revisit ratio (None: too few pairs) and whether it revisits."""
    from_identity = register(first, second)
    measured = _measure(first, second, from_identity)
    if from_identity is not None and (
        measured is None or measured[0] < REVISIT_RATIO or measured[1] < GLOBAL_MIN_PAIRS
    ):
        ratio = None if measured is None else measured[0]
        return from_identity, ratio, ratio is not None and ratio < REVISIT_RATIO  # kept: it holds, or cannot tell
    if previous is not None:
        from_previous = register(first, second, (previous[0], previous[1]))
        if (ratio := _revisiting_ratio(first, second, from_previous)) is not None:
            return from_previous, ratio, True
    found = register_globally(first, second, rng or np.random.default_rng(0))
    if (ratio := _revisiting_ratio(first, second, found)) is not None:
        return found, ratio, True
    return from_identity, None if measured is None else measured[0], False


def _measure(first: FloatArray, second: FloatArray, registered: Registration | None) -> tuple[float, int] | None:
    """:func:`revisit_measure` of ``registered`` (``register(first, second)``); None if it is None."""
    return None if registered is None else revisit_measure(first, second, registered[0], registered[1])


def _revisiting_ratio(first: FloatArray, second: FloatArray, registered: Registration | None) -> float | None:
    """The revisit ratio of ``registered`` (``register(first, second)``) when it is under ``REVISIT_RATIO``."""
    measured = _measure(first, second, registered)
    return measured[0] if measured is not None and measured[0] < REVISIT_RATIO else None


def pair_residuals(first: FloatArray, second: FloatArray) -> FloatArray:
    """Residual lengths (m) of the matched pairs of two point sets after registering them (empty if none)."""
    registered = register(first, second)
    return registered[2] if registered is not None else np.empty(0)


def _unit_warning(name: str, observations: Sequence[PointObservation], odometry: Sequence[OdometryMeasurement]) -> str:
    """A warning when the first observations' median range or the odometry's median speed is far beyond
    what a sensor carried about sees and moves at (``UNIT_RANGE_M``, ``UNIT_SPEED_M_S``): the log likely
    holds millimetres where ROS messages hold metres (REP 103); else ""."""
    ranges = [np.linalg.norm(o.points, axis=1) for o in observations if len(o)]
    median_range = float(np.median(np.concatenate(ranges))) if ranges else 0.0
    speeds = [float(np.linalg.norm(m.linear)) for m in odometry]
    median_speed = float(np.median(speeds)) if speeds else 0.0
    said = []
    if median_range > UNIT_RANGE_M:
        said.append(f"the points' median range is {median_range:,.0f} m")
    if median_speed > UNIT_SPEED_M_S:
        said.append(f"the odometry's median speed is {median_speed:,.0f} m/s")
    if not said:
        return ""
    return (f"{name}: {' and '.join(said)}: are they millimetres? ROS messages hold metres (REP 103); a log "
            "written in millimetres gives a map and path a thousand times too large, and settings in metres "
            "(ranges, speeds, gates) that do not fit it; convert the log to metres")  # fmt: skip


def _pair_estimate(residual: FloatArray, min_pairs: int) -> float | None:
    """Per-axis noise from the residuals of ``n`` registered pairs: a rigid fit absorbs 6 of their ``3 n``
    degrees of freedom, so they understate it by ``sqrt((3 n - 6) / (3 n))``, which is undone."""
    n = len(residual)
    if n < max(min_pairs, 3):
        return None
    return float(np.median(residual)) / _PAIR_MEDIAN * math.sqrt(3 * n / (3 * n - 6))


@dataclass(frozen=True)
class ConsecutiveRegistrations:
    """The observations of at least three points and the registrations of each onto the one before
    (``register(previous, next)``, None where it failed): what both the noise and the acceleration
    estimates chain, registered once. ``ratios[k]``: the revisit ratio of ``steps[k]``
    (:func:`revisit_measure`; None where it could not be told); ``revisits[k]``: whether it brings
    the later observation's points back onto the earlier one's (:func:`register_consecutive`)."""

    observations: list[PointObservation]
    steps: list[Registration | None]
    ratios: list[float | None]
    revisits: list[bool]

    @classmethod
    def of(cls, observations: Sequence[PointObservation], seed: int = 0) -> ConsecutiveRegistrations:
        """Each usable observation registered onto the one before (:func:`register_consecutive`), the
        last step that revisited offered as the next one's start (a sensor keeps its pace); ``seed``
        seeds the global search's draws."""
        usable = [o for o in observations if len(o) >= 3]
        rng = np.random.default_rng(seed)
        steps: list[Registration | None] = []
        ratios: list[float | None] = []
        revisits: list[bool] = []
        for a, b in itertools.pairwise(usable):
            # Points that never come back (samples of surfaces) are searched for a few times only.
            if any(revisits) or len(revisits) < GLOBAL_ATTEMPTS:
                previous = next((s for s, r in zip(reversed(steps), reversed(revisits), strict=True) if r), None)
                step, ratio, revisited = register_consecutive(a.points, b.points, previous, rng)
            else:
                step = register(a.points, b.points)
                measured = _measure(a.points, b.points, step)
                ratio, revisited = None if measured is None else measured[0], False
            steps.append(step)
            ratios.append(ratio)
            revisits.append(revisited)
        return cls(usable, steps, ratios, revisits)

    @functools.cached_property
    def distinct(self) -> tuple[list[PointObservation], list[Registration | None]]:
        """These observations and steps without those whose steps match neighbouring points
        (:func:`_distinct_steps`), made once."""
        return _distinct_steps(self)


def registration_noise(
    observations: Sequence[PointObservation],
    min_pairs: int = 3,
    baseline: int | None = None,
    registrations: ConsecutiveRegistrations | None = None,
) -> float | None:
    """Per-axis noise (m) seen by registering observations ``baseline`` apart, or None if none could be.

    Consecutive observations are registered first (or taken from ``registrations``, made of the same
    observations); observations ``baseline`` apart (default: half the sequence) are then registered
    starting from the chained consecutive motions, so the sensor may move far between them. An
    error that repeats from one observation to the next (the same surface seen from almost the same
    place) shows only over the wider baseline; with ``baseline`` 1 only the consecutive pairs count.
    The median of the pairs' estimates is returned, over the pairs whose matches are told from pairs of
    neighbouring points (:func:`distinctness` under ``DISTINCT_RATIO``; the chain leaves out the
    observations whose steps are not, :func:`_distinct_steps`). Where no pair is, and ``baseline`` is
    not given, half the baseline, a quarter ... down to consecutive observations are tried; where none
    is at any, the median of all the pairs at the widest.
    """
    registrations = registrations or ConsecutiveRegistrations.of(observations)
    widest: list[float] | None = None
    for pairs in _narrowing_baselines(registrations, baseline):
        estimates, told = [], []
        for first, second, registered in pairs:
            if (estimate := _pair_estimate(registered[2], min_pairs)) is not None:
                estimates.append(estimate)
                measure = distinctness(first, second, registered)
                if measure is None or measure < DISTINCT_RATIO:
                    told.append(estimate)
        if told:
            return float(np.median(told))
        widest = estimates if widest is None else widest
    return float(np.median(widest)) if widest else None


def _narrowing_baselines(
    registrations: ConsecutiveRegistrations, baseline: int | None
) -> Iterator[list[tuple[FloatArray, FloatArray, Registration]]]:
    """The registrations of :func:`_baseline_registrations` at ``baseline`` and, unless it is given,
    at half that, a quarter ... down to consecutive observations: for :func:`registration_noise` to
    go on to, while no pair at the wider baseline holds matches told from neighbours."""
    observations, steps = registrations.distinct
    points = [o.points for o in observations]
    if baseline is not None:
        yield list(_chained_registrations(points, steps, baseline))
        return
    width = max(1, len(points) // 2)
    while True:
        yield list(_chained_registrations(points, steps, width))
        if width == 1:
            return
        width = max(1, width // 2)


#: A registration's matches are told from pairs of different points while their median distance is
#: under this fraction of the distance to the nearest other point on either side (:func:`distinctness`).
#: Two points that are not the same one lie, at random, as close to each other as the nearest of their
#: other neighbours allows: for points scattered uniformly in ``D`` dimensions the ratio's distribution
#: is ``x^D``, its median 0.79 in space, 0.71 on a plane, 0.5 along a line (a registration fitted to a
#: few such pairs pulls them closer). Measured on consecutive registrations of one landmark's
#: sightings: 0.00-0.19 (Starry Night's; an independent simulator's circle at 0.05 m of noise), 0.33-0.43
#: on that circle at 0.3 m; Starry Night's wide-baseline pairs 0.03-0.45; pairs of clouds that share
#: few landmarks 0.45-0.81.
DISTINCT_RATIO = 0.5


def distinctness(first: FloatArray, second: FloatArray, registered: Registration) -> float | None:
    """How far apart the matched points of ``registered`` (``register(first, second)``, both (N, 3), m)
    lie relative to their other neighbours: over the trimmed mutual pairs, the pair's distance divided
    by the smaller of the distance from ``second``'s point (moved) to the next nearest of ``first`` and
    from ``first``'s point to the next nearest of ``second`` (moved); the median. Well under
    ``DISTINCT_RATIO`` where the pairs are sightings of one point each; at or above it where they are
    pairs of neighbours (two clouds that share few of their points, a registration that missed). Taken
    on both sides, as a sparse cloud's next nearest point is far whatever its match. None when fewer
    than three pairs hold or a cloud has fewer than two points."""
    from scipy.spatial import cKDTree

    if len(first) < 2 or len(second) < 2:
        return None
    R, t, _ = registered
    moved = second @ R.T + t
    tree_first = cKDTree(first)
    matched = _trimmed_matches(tree_first, first, moved, REGISTRATION_TRIM)
    if matched is None:
        return None
    distance, nearest, keep = matched
    beside_first = tree_first.query(moved[keep], k=2)[0][:, 1]
    beside_second = cKDTree(moved).query(first[nearest[keep]], k=2)[0][:, 1]
    return float(np.median(distance[keep] / np.maximum(np.minimum(beside_first, beside_second), 1e-300)))


def _distinct_steps(
    registrations: ConsecutiveRegistrations,
) -> tuple[list[PointObservation], list[Registration | None]]:
    """The registered observations and each one's registration onto the one before
    (``register(previous, next)``, None where it failed), with the observations whose step to or from a
    neighbour is not :func:`distinctness` ``DISTINCT_RATIO`` or more left out and their neighbours
    registered onto each other (:func:`register_consecutive`), until every step is distinct: the sparser
    observation of such a step, which shares few of its points with the other, goes. Unchanged where
    every step is distinct, where the points do not come back at all (:func:`revisit_ratio`
    ``REVISIT_RATIO`` or more: fresh samples of surfaces; their steps never are), and where fewer than
    three observations would be left.

    A front-end whose clouds swing from a few points to hundreds, each a different subset of what is in
    view, gives two consecutive clouds that share few landmarks; they still register, onto neighbouring
    landmarks, and the motions chained through such steps start the wide-baseline registrations far
    off. On an independent simulator's circle (0.05 m of noise, clouds of 5-500 points) 10 of the 14
    wide-baseline pairs then matched neighbours and measured the landmarks' spacing: 0.66 m of noise."""
    observations = list(registrations.observations)
    steps = list(registrations.steps)
    ratio = revisit_ratio(registrations)
    if ratio is None or ratio >= REVISIT_RATIO:
        return observations, steps
    known = {(id(a), id(b)): step for a, b, step in zip(observations, observations[1:], steps, strict=False)}
    rng = np.random.default_rng(0)
    kept, kept_steps = observations, steps
    while True:
        mismatched = [
            k for k, step in enumerate(kept_steps)
            if step is not None and (measure := distinctness(kept[k].points, kept[k + 1].points, step)) is not None
            and measure >= DISTINCT_RATIO
        ]  # fmt: skip
        if not mismatched:
            return kept, kept_steps
        dropped = {k if len(kept[k]) < len(kept[k + 1]) else k + 1 for k in mismatched}
        remaining = [p for k, p in enumerate(kept) if k not in dropped]
        if len(remaining) < 3:
            return kept, kept_steps
        remaining_steps: list[Registration | None] = []
        for a, b in itertools.pairwise(remaining):
            if (id(a), id(b)) not in known:
                previous = next((s for s in reversed(remaining_steps) if s is not None), None)
                known[id(a), id(b)] = register_consecutive(a.points, b.points, previous, rng)[0]
            remaining_steps.append(known[id(a), id(b)])
        kept, kept_steps = remaining, remaining_steps


def _baseline_registrations(
    registrations: ConsecutiveRegistrations, baseline: int | None = None
) -> Iterator[tuple[FloatArray, FloatArray, tuple[FloatArray, FloatArray, FloatArray]]]:
    """``(first, second, (R, t, residuals))`` of the observations ``baseline`` apart (default: half the
    sequence) that register, ``second`` moved onto ``first`` from the chained consecutive motions; the
    sequence is that of :func:`_distinct_steps`, without the observations whose step matched
    neighbouring points."""
    observations, steps = registrations.distinct
    yield from _chained_registrations([o.points for o in observations], steps, baseline)


def _chained_registrations(
    usable: list[FloatArray], steps: list[Registration | None], baseline: int | None
) -> Iterator[tuple[FloatArray, FloatArray, Registration]]:
    """:func:`_baseline_registrations` of the observations' points ``usable`` and their consecutive
    registrations ``steps`` (``steps[k]`` moves ``usable[k + 1]`` onto ``usable[k]``)."""
    baseline = max(1, len(usable) // 2 if baseline is None else baseline)
    for i in range(len(usable) - baseline):
        chain = steps[i : i + baseline]
        if any(step is None for step in chain):
            continue
        R, t = np.eye(3), np.zeros(3)
        for step in chain:  # T_i<-i+k+1 = T_i<-i+k  T_i+k<-i+k+1
            assert step is not None
            R, t = R @ step[0], R @ step[1] + t
        registered = register(usable[i], usable[i + baseline], (R, t)) if baseline > 1 else chain[0]
        if registered is not None:
            yield usable[i], usable[i + baseline], registered


def noise_along_and_across(registrations: ConsecutiveRegistrations, min_pairs: int = 6) -> tuple[float, float] | None:
    """Per-axis noise (m) along the line of sight from the sensor and across it, from the residuals of
    the observations registered half the sequence apart (as :func:`registration_noise`); the medians
    over the registered pairs. None when no pair holds ``min_pairs`` matches.

    A stereo camera's or a depth sensor's range error is several times its error across the view; an
    isotropic estimate (the residual lengths' median) then understates the range error.
    """
    from scipy.spatial import cKDTree

    along, across = [], []
    for first, second, (R, t, _) in _baseline_registrations(registrations):
        moved = second @ R.T + t
        matched = _trimmed_matches(cKDTree(first), first, moved, REGISTRATION_TRIM)
        if matched is None or matched[2].sum() < min_pairs:
            continue
        _, nearest, keep = matched
        target = first[nearest[keep]]
        residual = target - moved[keep]
        sight = target / np.maximum(np.linalg.norm(target, axis=1, keepdims=True), 1e-12)
        on_sight = np.sum(residual * sight, axis=1)
        off_sight = np.linalg.norm(residual - on_sight[:, None] * sight, axis=1)
        # two noisy points: sqrt(2) per axis; |N(0, s)| has median 0.6745 s, a 2D one's length 1.1774 s
        along.append(float(np.median(np.abs(on_sight))) / (0.6745 * math.sqrt(2.0)))
        across.append(float(np.median(off_sight)) / (1.1774 * math.sqrt(2.0)))
    if not along:
        return None
    return float(np.median(along)), float(np.median(across))


def _chained_path(registrations: ConsecutiveRegistrations) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """Stamps (s), positions (m) and rotations (``R_first_k``) of the registered observations, in the
    first observation's frame, chained from their consecutive registrations; None if any pair failed
    or there are fewer than 3. The observations are those of :func:`_distinct_steps`: a step between
    clouds that share few landmarks, registered onto neighbouring ones, is off by their spacing, and
    reads as an acceleration of metres per second squared (an independent simulator's circle at 0.27
    m/s^2, clouds of 5-500 points: 6.6 m/s^2 taken, and FastSLAM's prediction, that loose, lost the
    path's shape)."""
    observations, steps = registrations.distinct
    if len(observations) < 3 or any(step is None for step in steps):
        return None
    R, t = np.eye(3), np.zeros(3)
    positions, rotations = [t], [R]
    for step in steps:
        assert step is not None
        R, t = R @ step[0], R @ step[1] + t  # T_0<-k+1 = T_0<-k  T_k<-k+1
        positions.append(t)
        rotations.append(R)
    stamps = np.array([o.stamp_ns for o in observations], dtype=np.float64) * 1e-9
    return stamps, np.array(positions), np.array(rotations)


#: The measured starting twist's standard deviation: this fraction of it, plus what three times the
#: noise over one interval (at the points' median range, for the turn rate) would hide.
STARTING_TWIST_SPREAD = 0.25
#: The measured starting twist replaces the start from rest when the first interval moves the points
#: by more than this fraction of their spacing (in the median): a prediction from rest then pairs them
#: with their neighbours. Measured: the simulator's figure eight and corridor 0.13 and 0.18, an
#: independent simulator's car, turn on the spot and drone at 10 Hz 0.19-0.36, its circle at 1 Hz 1.8.
#: Below it the start from rest is kept: the filters learn the twist from the first observations (on
#: the figure eight at 10 Hz, starting from the measured twist changed FastSLAM's ATE by chance, up or
#: down by up to 70 % a seed, the mean of eight seeds by 1 %).
STARTING_SHIFT_FRACTION = 0.5


def starting_twist(registrations: ConsecutiveRegistrations, sigma: float) -> tuple[FloatArray, FloatArray] | None:
    """The body-frame twist ``(v (m/s), w (rad/s))`` (6,) that carries the first registered observation
    onto the second (the constant-velocity models' ``p' = p + R v dt``, ``R' = R Exp(w dt)``), and its
    standard deviation (6,) for observation noise ``sigma`` (m): ``STARTING_TWIST_SPREAD`` of the
    twist's size plus ``3 sigma / dt`` (linear) and ``3 sigma / (r dt)`` (angular, ``r`` the first
    observation's median range). None unless the two register onto each other (their points revisit)
    and the motion between them moves the points by more than ``STARTING_SHIFT_FRACTION`` of their
    spacing: a start from rest suits a smaller one."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    if not registrations.revisits or not registrations.revisits[0] or registrations.steps[0] is None:
        return None
    first, second = registrations.observations[:2]
    dt = (second.stamp_ns - first.stamp_ns) * 1e-9
    reach = float(np.median(np.linalg.norm(first.points, axis=1)))
    if not (dt > 0 and reach > 0):
        return None
    R, t, _ = registrations.steps[0]
    shift = float(np.median(np.linalg.norm(second.points @ R.T + t - second.points, axis=1)))
    spacing = float(np.median(cKDTree(first.points).query(first.points, k=2)[0][:, 1]))
    if not shift > STARTING_SHIFT_FRACTION * spacing:
        return None
    linear, angular = t / dt, Rotation.from_matrix(R).as_rotvec() / dt
    spread = np.repeat(
        [STARTING_TWIST_SPREAD * np.linalg.norm(linear) + 3.0 * sigma / dt,
         STARTING_TWIST_SPREAD * np.linalg.norm(angular) + 3.0 * sigma / (reach * dt)], 3,
    )  # fmt: skip
    return np.r_[linear, angular], spread


@dataclass(frozen=True)
class PathAcceleration:
    """How hard the held-back path accelerates, two ways (:func:`estimate_acceleration`).

    ``white``: the white acceleration noise (m/s^2) over one interval that explains its velocity
    changes. ``smoothed``: its velocity change over the span, per second: the acceleration the path
    itself shows. A smooth turn of acceleration ``A`` gives ``smoothed`` ``A`` and ``white`` ``A sqrt(m)``.
    ``angular_white`` and ``angular_smoothed``: the same (rad/s^2) of its angular velocity in the
    sensor frame, which a steady turn keeps. ``interval``: the median time between observations (s).
    """

    white: float
    smoothed: float
    angular_white: float = 0.0
    angular_smoothed: float = 0.0
    interval: float = SIMULATOR_INTERVAL_S


def estimate_acceleration(
    observations: Sequence[PointObservation], registrations: ConsecutiveRegistrations | None = None
) -> PathAcceleration | None:
    """How hard the path the observations' registrations chain into accelerates.

    Velocities are differences of positions ``m`` observations apart, ``m`` spanning about
    ``ACCELERATION_SPAN_S`` (at most a third of the path); their median change between consecutive
    spans, over the span's time ``S``, is an acceleration smoothed over ``S`` (``smoothed``). Under white
    acceleration noise the velocity wanders as the square root of time, so the noise over one interval
    ``dt`` is that times ``sqrt(S / dt) = sqrt(m)`` (``white``): the motion models' ``(a dt)^2`` per
    iteration then wander the velocity as much over ``S`` as the path did. Where a span is one interval
    (below about 3 Hz) the velocities are taken in the sensor frame at each span's start, as the motion
    models hold them, else in the first observation's. The angular velocity over a
    span is the rotation between its ends, in the sensor frame at its start, over its time; its changes
    give ``angular_smoothed`` and ``angular_white`` alike. None when the path cannot be chained or is too
    short.
    """
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    path = _chained_path(registrations or ConsecutiveRegistrations.of(observations))
    if path is None:
        return None
    stamps, positions, rotations = path
    dt = float(np.median(np.diff(stamps)))
    if not dt > 0:
        return None
    m = max(1, min(len(stamps) // 3, round(ACCELERATION_SPAN_S / dt)))
    if len(stamps) < 2 * m + 1:
        return None
    span = stamps[m:] - stamps[:-m]
    between = 0.5 * (span[m:] + span[:-m])
    velocity = (positions[m:] - positions[:-m]) / span[:, None]
    if m == 1:
        # Observations farther apart than the span (below about 3 Hz): between two of them a steady turn
        # swings the velocity by what the angular velocity explains, and the motion models hold it in the
        # sensor frame. There, in the world frame, a circle seen at 1 Hz at a 0.6 m radius showed 0.04
        # m/s^2 and the EKF took five times that: its prediction spread over the landmarks' spacing. At
        # higher rates the velocities stay in the world frame, which the margin was chosen with.
        velocity = np.einsum("kji,kj->ki", rotations[:-m], velocity)  # R_k^T v: in the span's first frame
    smoothed = float(np.median(np.linalg.norm(velocity[m:] - velocity[:-m], axis=1) / between))
    turns = np.swapaxes(rotations[:-m], 1, 2) @ rotations[m:]  # R_k^T R_k+m: the span's rotation in frame k
    angular = Rotation.from_matrix(turns).as_rotvec() / span[:, None]
    angular_smoothed = float(np.median(np.linalg.norm(angular[m:] - angular[:-m], axis=1) / between))
    return PathAcceleration(
        white=smoothed * math.sqrt(m), smoothed=smoothed, angular_white=angular_smoothed * math.sqrt(m),
        angular_smoothed=angular_smoothed, interval=dt,
    )  # fmt: skip


def derived_acceleration_noise(acceleration: PathAcceleration | None, sigma: float) -> float:
    """The motion models' linear acceleration noise (m/s^2) for a log whose held-back path shows
    ``acceleration`` (None: unknown) and whose observation noise is ``sigma`` (m):
    ``ACCELERATION_MARGIN`` times its white noise, within ``VEHICLE_ACCELERATION`` scaled by the noise
    against the simulator's and ``VEHICLE_ACCELERATION`` itself; but never less than the acceleration
    the path itself shows (its ``smoothed``; at most ``MAX_ACCELERATION_NOISE``)."""
    if acceleration is None:
        return VEHICLE_ACCELERATION
    floor = VEHICLE_ACCELERATION * min(1.0, sigma / SIMULATOR_SIGMA)
    within_vehicle = min(VEHICLE_ACCELERATION, max(ACCELERATION_MARGIN * acceleration.white, floor))
    # A path turning harder than a vehicle (an aerial sensor, a scene ten times the simulator's) keeps at
    # least what it shows: capped at the vehicle's, the prediction trails it and the association breaks.
    return float(min(MAX_ACCELERATION_NOISE, max(within_vehicle, acceleration.smoothed)))


def derived_angular_acceleration_noise(acceleration: PathAcceleration | None) -> float:
    """The motion models' angular acceleration noise (rad/s^2) for a log whose held-back path shows
    ``acceleration`` (None: unknown): ``ACCELERATION_MARGIN`` times its angular white noise, within
    ``VEHICLE_ANGULAR_ACCELERATION`` and that scaled by the square of the simulator's interval over the
    log's (so that the turn the noise lets the prediction make over one interval, ``a dt^2``, is never
    less than on the simulator's scenes), but never less than the angular white noise the path itself
    shows. At 10 Hz and faster it is the vehicle's; at 1 Hz that would let the prediction turn by 29
    degrees between two observations, where a steady turn seen at 1 Hz is mapped with a tenth of it.

    The floor is the white noise, not the acceleration smoothed over ``ACCELERATION_SPAN_S``: a platform
    that pitches and rolls faster than the span (a ground vehicle on bumps, 2-5 degrees at 0.5-2 Hz)
    averages out over it. On such a path (white 1.75, smoothed 0.78 rad/s^2) the EKF's prediction at
    0.78 left the points outside their gates in 31 iterations and mapped 3,782 landmarks for the 300
    seen; at the white noise, 298."""
    if acceleration is None:
        return VEHICLE_ANGULAR_ACCELERATION
    # (stamps in ns make a 10 Hz interval 0.1 s only within rounding: the vehicle's noise holds there exactly)
    floor = VEHICLE_ANGULAR_ACCELERATION * min(1.0, (SIMULATOR_INTERVAL_S / acceleration.interval) ** 2 * (1 + 1e-6))
    within_vehicle = min(VEHICLE_ANGULAR_ACCELERATION, max(ACCELERATION_MARGIN * acceleration.angular_white, floor))
    shown = max(acceleration.angular_white, acceleration.angular_smoothed)  # (white is the larger on any path)
    return float(min(MAX_ANGULAR_ACCELERATION_NOISE, max(within_vehicle, shown)))


_MotionSettings = TypeVar("_MotionSettings", bound="MotionNoiseSettings")


@dataclass(frozen=True)
class MotionNoiseSettings(Settings):
    """The constant-velocity model's linear acceleration noise, which the EKF (its prediction) and
    FastSLAM (its proposal) share, and which ``relpoint run`` takes from the log when it is unset."""

    linear_acceleration_noise: float | None = setting(None, low=0, high=1e4)
    """Constant-velocity model: white linear acceleration noise (m/s^2). Unset (the default): ``relpoint
    run`` takes 5 times the acceleration noise that explains the path its first observations register
    into, within 2 m/s^2 (a vehicle's) and 2 m/s^2 scaled by the observation noise against 0.3 m, but
    never less than the acceleration the path itself shows
    (:func:`relpoint.estimators._noise.derived_acceleration_noise`; ``run.json`` reports them as
    ``linear_acceleration_noise``, ``acceleration_measured`` and ``acceleration_path``): 2 m/s^2 on the
    simulator's figure eight, 23 on the same ten times larger, about 1.8 on a hand-held camera at
    30 Hz, 0.6 on a slow sensor seen at 2 Hz, a few cm/s^2 on a tabletop.
    Built directly, without ``SPEC.factory``: 2 m/s^2."""

    angular_acceleration_noise: float | None = setting(None, low=0, high=1e3)
    """Constant-velocity model: white angular acceleration noise (rad/s^2). Unset (the default):
    ``relpoint run`` takes 5 times the angular acceleration noise that explains the held-back path's
    turns, within 0.5 rad/s^2 (a vehicle's) and 0.5 scaled by the square of 0.1 s over the log's
    interval, but never less than the angular acceleration the path itself shows
    (:func:`relpoint.estimators._noise.derived_angular_acceleration_noise`; ``run.json``:
    ``angular_acceleration_noise``, ``angular_acceleration_measured``): 0.5 at 10 Hz and faster, less
    on a steady turn seen at a low rate, where 0.5 rad/s^2 lets the prediction turn by tens of degrees
    between two observations. Built directly, without ``SPEC.factory``: 0.5 rad/s^2."""

    odometry_check: bool = setting(True)
    """Check the odometry against the motion the first observations register into, and where its
    twist is biased by more than the deviation its messages state, raise that axis's variance by the
    bias squared for the whole log (:mod:`relpoint.estimators._odometry_check`; ``run.json``:
    ``odometry_check``). Only ``relpoint run`` (``SPEC.factory``) checks."""

    def at_acceleration(self: _MotionSettings, acceleration: PathAcceleration | None, sigma: float) -> _MotionSettings:
        """These settings with their unset acceleration noises derived from what the held-back path
        shows (``acceleration``, None: unknown) at observation noise ``sigma`` (m)."""
        linear, angular = self.linear_acceleration_noise, self.angular_acceleration_noise
        return dataclasses.replace(
            self,
            linear_acceleration_noise=derived_acceleration_noise(acceleration, sigma) if linear is None else linear,
            angular_acceleration_noise=(
                derived_angular_acceleration_noise(acceleration) if angular is None else angular
            ),
        )

    @property
    def acceleration_noise(self) -> float:
        """``linear_acceleration_noise`` (m/s^2), or the vehicle default when it is unset."""
        return self.linear_acceleration_noise if self.linear_acceleration_noise is not None else VEHICLE_ACCELERATION

    @property
    def angular_noise(self) -> float:
        """``angular_acceleration_noise`` (rad/s^2), or the vehicle default when it is unset."""
        angular = self.angular_acceleration_noise
        return angular if angular is not None else VEHICLE_ANGULAR_ACCELERATION

    @property
    def derives_acceleration(self) -> bool:
        """Whether an acceleration noise is unset, to be derived from the log."""
        return self.linear_acceleration_noise is None or self.angular_acceleration_noise is None


def estimate_observation_noise(
    observations: Sequence[PointObservation], registrations: ConsecutiveRegistrations | None = None
) -> float | None:
    """Per-axis observation noise (m): the registration noise, at least ``RANGE_FRACTION`` of the median range.

    None when the observations hold no point at all. ``registrations``: those of ``observations``, when
    already made.
    """
    ranges = [np.linalg.norm(o.points, axis=1) for o in observations if len(o)]
    if not ranges:
        return None
    floor = RANGE_FRACTION * float(np.median(np.concatenate(ranges)))
    registered = registration_noise(observations, registrations=registrations)
    return max(floor, registered) if registered is not None else floor


def revisit_ratio(registrations: ConsecutiveRegistrations) -> float | None:
    """How close a point comes back, relative to its neighbours: for each registered pair of consecutive
    observations, the median over mutually nearest pairs of the pair's distance divided by the later
    point's distance to its nearest neighbour in its own observation; the median over the pairs of
    observations. About 0.01-0.06 for landmarks, about 0.5 for fresh samples of surfaces; None when no
    pair of observations could be registered."""
    ratios = [ratio for ratio in registrations.ratios if ratio is not None]
    return float(np.median(ratios)) if ratios else None


class NoiseAdaptive(Estimator[PointObservation]):
    """An estimator built once the observation noise is known from the first ``frames`` observations
    of at least ``MIN_POINTS`` points (or the first ``MAX_HELD`` iterations).

    ``build(sigma, acceleration)`` makes the real estimator ``name`` for noise ``sigma`` (m) and, with
    ``measure_acceleration``, the median acceleration of the held-back path (m/s^2, or None when it
    cannot be chained; :func:`estimate_acceleration`). ``fallback`` is the noise when no pair of the
    first observations can be registered (too few points); ``sigma``, when given, is the noise the
    settings already hold, and is not estimated; ``finishing`` is the real estimator's
    :attr:`~Estimator.finishing`. Odometry and fixes that
    arrive while observations are held back are replayed in their order. ``prepare`` is the real
    estimator's :meth:`~Estimator.prepare` work that needs no noise (compiling its code), run before
    the first iteration as the pipeline asks.
    """

    def __init__(
        self,
        build: Callable[[float, PathAcceleration | None], Estimator],
        fallback: float,
        name: str,
        frames: int = NOISE_FRAMES,
        prepare: Callable[[], None] | None = None,
        sigma: float | None = None,
        measure_acceleration: bool = False,
        check_odometry: bool = False,
        finishing: str = Estimator.finishing,
        reports_unlocated: bool = False,
    ) -> None:
        self._build = build
        self._known_sigma = sigma
        self._measure_acceleration = measure_acceleration
        self._check_odometry = check_odometry
        self.odometry_check: OdometryCheck | None = None
        self._prepare = prepare
        self._fallback = fallback
        self._frames = max(2, frames)
        self._held: list[tuple[str, Any]] = []
        self._held_steps = 0
        self._informative = 0
        self._inner: Estimator | None = None
        self._replayed: list[Pose] = []
        self.sigma: float | None = None
        self.estimated = False
        self.acceleration: PathAcceleration | None = None
        self.revisit: float | None = None
        self.along_and_across: tuple[float, float] | None = None
        self.initial_twist: FloatArray | None = None
        self._units = ""
        # Iterations held back and replayed at the last of them (their work is done then): the pipeline
        # spreads that iteration's time over them.
        self.replayed_steps = 0
        self.name = name  # type: ignore[misc]  # the wrapped estimator's name
        self.finishing = finishing  # type: ignore[misc]  # and what its finish() does
        self.reports_unlocated = reports_unlocated  # type: ignore[misc]  # and whether it warns of unlocated steps

    def _start(self) -> None:
        observations = [item for kind, item in self._held if kind == "step"]
        odometry = [item for kind, item in self._held if kind == "odometry"] if self._check_odometry else []
        registrations = ConsecutiveRegistrations.of(observations)  # registered once for every estimate
        if self._known_sigma is not None:
            self.sigma = self._known_sigma
        else:
            sigma = estimate_observation_noise(observations, registrations)
            self.estimated = sigma is not None
            self.sigma = sigma if sigma is not None else self._fallback
        self.revisit = revisit_ratio(registrations)
        self._units = _unit_warning(self.name, observations, [item for kind, item in self._held if kind == "odometry"])
        if self._known_sigma is None:
            self.along_and_across = noise_along_and_across(registrations)
        if self._not_landmarks():  # said now, as a run over such clouds can take long; explained at its end
            log.warning("%s: the first %d observations look like samples of surfaces, or landmarks with noise near "
                        "their spacing (revisit ratio %.2f); the run goes on, its result may be unreliable", self.name,
                        len(observations), self.revisit)  # fmt: skip
        if self._measure_acceleration:
            self.acceleration = estimate_acceleration(observations, registrations)
        if odometry:
            from relpoint.estimators._odometry_check import check_odometry  # only for logs with odometry

            self.odometry_check = check_odometry(registrations.observations, registrations.steps, odometry)
        self._inner = self._build(self.sigma, self.acceleration)
        start = starting_twist(registrations, self.sigma)
        if start is not None and self._inner.start_moving(*start):
            self.initial_twist = start[0]
        for kind, item in self._held:
            if kind == "step":
                self._replayed.append(self._inner.step(item))
            elif kind == "odometry":
                self._inner.add_odometry(self._checked(item))
            else:
                self._inner.add_fix(item)
        self._held = []

    def prepare(self) -> None:
        if self._prepare is not None:
            self._prepare()

    def step(self, observation: PointObservation) -> Pose:
        if self._inner is not None:
            return self._inner.step(observation)
        self._held.append(("step", observation))
        self._held_steps += 1
        self._informative += len(observation) >= MIN_POINTS
        if self._informative >= self._frames or self._held_steps >= MAX_HELD:
            self._start()
            self.replayed_steps = len(self._replayed)
            return self._replayed[-1]
        return Pose(observation.stamp_ns, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

    def _checked(self, odometry: OdometryMeasurement) -> OdometryMeasurement:
        return self.odometry_check.adjusted(odometry) if self.odometry_check is not None else odometry

    def add_odometry(self, odometry: OdometryMeasurement) -> None:
        if self._inner is not None:
            self._inner.add_odometry(self._checked(odometry))
        else:
            self._held.append(("odometry", odometry))

    def add_fix(self, fix: PositionFix) -> None:
        if self._inner is not None:
            self._inner.add_fix(fix)
        else:
            self._held.append(("fix", fix))

    def landmark_map(self) -> LandmarkMap:
        return self._inner.landmark_map() if self._inner is not None else LandmarkMap.empty()

    @property
    def map_size(self) -> int:
        return self._inner.map_size if self._inner is not None else 0

    @property
    def features_started(self) -> int | None:
        return self._inner.features_started if self._inner is not None else None

    def finish(self, trajectory: Trajectory) -> Trajectory:
        if self._inner is None:  # the log ended while observations were held back
            self._start()
        assert self._inner is not None
        if self._replayed:
            positions, quats = trajectory.positions.copy(), trajectory.quats_xyzw.copy()
            for k, pose in enumerate(self._replayed[: len(trajectory)]):
                positions[k], quats[k] = pose.position, pose.quat_xyzw
            trajectory = Trajectory(trajectory.stamps_ns, positions, quats)
        return self._inner.finish(trajectory)

    def summary(self) -> dict[str, Any]:
        inner = self._inner.summary() if self._inner is not None else {}
        measured: dict[str, Any] = {}
        if self._measure_acceleration:
            measured["acceleration_measured"] = self.acceleration.white if self.acceleration else None
            measured["acceleration_path"] = self.acceleration.smoothed if self.acceleration else None
            measured["angular_acceleration_measured"] = self.acceleration.angular_white if self.acceleration else None
        if self.initial_twist is not None:
            measured["initial_twist"] = [round(float(x), 9) for x in self.initial_twist]
        if self.odometry_check is not None:
            measured["odometry_check"] = self.odometry_check.summary()
        if self.revisit is not None:
            measured["revisit_ratio"] = self.revisit
        if self.along_and_across is not None:
            measured["observation_sigma_along_sight"], measured["observation_sigma_across_sight"] = (
                self.along_and_across
            )
        return {**inner, "observation_sigma": self.sigma, "observation_sigma_estimated": self.estimated, **measured}

    def _not_landmarks(self) -> bool:
        return self.revisit is not None and self.revisit >= REVISIT_RATIO

    def _not_landmarks_warning(self) -> str:
        return (
            f"{self.name}: the points come back about as far from where they were seen before as from their "
            f"neighbours (median ratio {self.revisit:.2f}; landmarks seen with noise well under their spacing: under "
            "0.1): these are fresh samples of surfaces (a lidar scan, a depth cloud), not landmarks seen again and "
            f"again, or landmarks whose noise ({self.sigma:.3g} m measured) is near their spacing. Either way an "
            "association by position pairs many of them wrongly; the map and path may be unreliable. The point "
            "estimators need point features (e.g. `relpoint import ... --points`); depth images suit the dense "
            "estimator"
        )

    def _anisotropy_warning(self) -> list[str]:
        if self.along_and_across is None or self._not_landmarks():
            return []
        along, across = self.along_and_across
        if not (along > ANISOTROPY_WARNING * across and along > self.sigma):
            return []  # isotropic, or the noise taken (the range floor) already covers the error along the sight
        return [
            f"{self.name}: the points' noise along the line of sight ({along:.3g} m) is {along / across:.1f} times "
            f"that across it ({across:.3g} m), as a stereo camera's or a depth sensor's range error is; the "
            f"estimator models it the same in every direction ({self.sigma:.3g} m), which understates it along "
            "the sight: static points may be taken for movers and the map spreads along the rays. "
            f"`--param observation_sigma={along:.2g}` models the larger (a firmer map, at times a looser path)"
        ]

    def run_warnings(self) -> list[str]:
        checked = self.odometry_check.warnings() if self.odometry_check is not None else []
        surfaces = [self._not_landmarks_warning()] if self._not_landmarks() else []
        inner = self._inner.run_warnings() if self._inner is not None else []
        units = [self._units] if self._units else []
        return units + surfaces + self._anisotropy_warning() + checked + inner

    def __getattr__(self, name: str) -> Any:
        # Anything else (diagnostics the benchmarks and tests read) comes from the built estimator.
        inner = self.__dict__.get("_inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)
