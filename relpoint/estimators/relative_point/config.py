"""Settings of the Relative Point estimator (:class:`RelativePointConfig`), each with its range, and the
ones that scale with the observation noise (:data:`NOISE_SCALED`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from relpoint.errors import UsageError
from relpoint.estimators._noise import SIMULATOR_SIGMA
from relpoint.settings import Settings, setting

#: Distance settings that scale with the observation noise: their defaults are for the simulator's
#: 0.3 m and ``relpoint run`` multiplies them by ``observation_sigma / 0.3`` (see ``observation_sigma``).
NOISE_SCALED = (
    "match_bound", "global_match_bound", "merge_bound", "trim_floor", "consensus_bound", "spread_floor",
    "adjustment_robust", "loop_search", "min_basis_spread", "collinear_tolerance",
)  # fmt: skip


@dataclass(frozen=True)
class RelativePointConfig(Settings):
    """Settings of the Relative Point estimator. Distances in metres, durations in iterations."""

    settings_name: ClassVar[str] = "relpoint"
    #: What ``relpoint config`` says about the settings that matter.
    key_settings: ClassVar[dict[str, str]] = {
        "observation_sigma": "per-axis point noise (m). Every distance bound (match_bound, global_match_bound, "
        "merge_bound, trim_floor, consensus_bound, spread_floor, adjustment_robust, loop_search, "
        "min_basis_spread, collinear_tolerance) is written for the simulator's 0.3 m and scaled by "
        "observation_sigma / 0.3. Unset, it is estimated from the first observations; 0.3 keeps the bounds as "
        "written.",
        "match_bound": "local matching: must exceed the noise plus the error of the motion prediction.",
        "min_basis_spread, collinear_tolerance": "how spread a group's basis must be: a fit's rotation error is "
        "about the noise over this distance. Too large for the scene and no group forms.",
        "dynamic_detection": "flags moving points; its thresholds are ratios to the scatter of the points in view, "
        "never below what observation_sigma explains (dynamic_noise_floor).",
        "dynamic_tail_sigmas": "which flagged points are reported dynamic: those that stand out of the bulk of the "
        "points judged with them; the others are left out of the map as unreliable (a real sensor's heavy-tailed "
        "error crosses the factors now and then). 0 reports every flagged point.",
        "loop_search, loop_ambiguity": "loop closure beyond global matching: the largest drift looked for, and how "
        "clearly one offset must lead (a repeating scene offers several).",
    }
    settings_hint: ClassVar[str] = "see `relpoint config --estimator relpoint` for the parameters"

    observation_sigma: float | None = setting(None, low=1e-6, high=1e3)
    """Per-axis noise of a point (m). The distances in ``NOISE_SCALED`` (``match_bound``,
    ``global_match_bound``, ``merge_bound``, ``trim_floor``, ``consensus_bound``, ``spread_floor``,
    ``adjustment_robust``, ``loop_search``, and the basis geometry ``min_basis_spread`` and
    ``collinear_tolerance``, which bound a fit's rotation error at about the noise over them) are given for the simulator's 0.3 m and ``relpoint run``
    scales them by ``observation_sigma / 0.3``, so one set of defaults holds from a depth camera at 2 m
    to a sensor at 70 m. Unset (the default): estimated from the first observations of the log
    (:mod:`relpoint.estimators._noise`); ``0.3`` keeps every bound as written. A
    ``RelativePointEstimator`` built directly, without ``SPEC.factory``, takes the bounds as written."""
    ring_size: int = setting(128, low=1, high=65_536)
    """Untransformed observations each point keeps (*RltPoint* circular array); bounds regrouping intervals."""
    match_window: int = setting(3, low=1, high=1_000)
    """Points seen in the last this many iterations are candidates for local matching."""
    match_bound: float = setting(2.0, above=0)
    """Point matching bound between an untransformed point and a recent observation (m)."""
    predict_motion: bool = True
    """Predict recent observations into the current frame with the last inter-iteration motion
    (from raw matched points, not current position); False matches raw observations as in the paper
    (then use a bound above the motion per iteration)."""
    match_angle: float = setting(0.03, low=0)
    """Points the first round of local matching leaves over get a second round in which a recent
    point's bound grows by this angle (rad) times its predicted range: a prediction is off by the
    motion estimate's rotation error times the range, and at low density that error keeps far points
    entering view from ever matching (0 disables; needs ``predict_motion``)."""
    global_matching: bool = True
    """Match points that fail local matching against global positions through the current position."""
    global_match_bound: float = setting(3.0, above=0)
    """Matching bound of global matching (m)."""
    loop_search: float = setting(15.0, low=0)
    """Largest drift (m) that loop closure looks for when the sensor returns to mapped points and
    global matching misses them (0 disables; see :mod:`.loops`)."""
    loop_support: int = setting(4, low=3, high=10_000)
    """Distinct young points that must agree on a loop's offset (within half ``global_match_bound``)."""
    loop_ambiguity: float = setting(0.4, low=0, high=1)
    """A loop's offset is rejected when another offset, more than two tolerances away, gathers more
    than this fraction of its support: a scene that repeats (cabinet doors, tiles, shelves) fits
    onto old points at several offsets, a drift at one (see :mod:`.loops`)."""
    loop_every: int = setting(5, low=1)
    """Look for a loop every this many iterations."""
    loop_young: int = setting(20, low=1)
    """Points first seen within this many iterations are young: possibly old points mapped again."""
    loop_gap: int = setting(50, low=1)
    """Mapped points unseen for this many iterations are old: what a loop returns to."""
    loop_max_rotation: float = setting(0.2, low=0)
    """A loop's drift is explained by heading drift growing steadily along the path up to this total
    angle (rad); beyond it, or for the part a rotation cannot explain, it is spread linearly in time."""
    final_adjustment: bool = True
    """When the log ends, solve every group pose and point position jointly by least squares
    (:mod:`.adjustment`) and fit every iteration's pose again to the adjusted map; False keeps the
    paper's incremental solution."""
    bundle_adjustment: bool = True
    """With ``final_adjustment``, then solve every iteration's pose and every static point's position
    jointly from the log's observations themselves (a bundle adjustment over the association the run
    made), starting from the adjusted map; keeps up to 50,000 observations until the log ends (about
    20 bytes each), every iteration's until a long log needs keyframes."""
    adjustment_prior: float = setting(0.005, low=0)
    """Weight (in iterations averaged) of each point's pull towards its incremental position in the
    final adjustment: it settles the directions the relative maps leave almost free."""
    adjustment_robust: float = setting(0.5, low=0)
    """Cauchy scale of the final adjustment (m; 0: plain least squares)."""
    adjustment_iterations: int = setting(10, low=1, high=1_000)
    """Largest number of Levenberg-Marquardt iterations of the final adjustment."""
    adjustment_dynamic_factor: float = setting(2.0, low=0)
    """After the final adjustment, a point in three or more groups that disagree about its position
    by more than this times the median disagreement is flagged dynamic, and the adjustment runs again
    without it: the moving points the detection missed stand out once the groups sit where the whole
    network puts them (0 disables)."""
    adjustment_members: int = setting(32, low=3, high=10_000)
    """Members per group the final adjustment solves the group poses with, those in the most groups
    first (every member still takes its position from the adjusted poses): in a dense map a point is
    in dozens of groups and the joint solution would grow with the square of that."""
    relocate_points: int = setting(32, low=3, high=10_000)
    """Observations of mapped points each iteration keeps (sensor frame, with the point) so that the
    final adjustment can locate the iteration again on the adjusted map (bounds memory: about 20 bytes
    each)."""
    creation_delay: int = setting(4, low=0)
    """A new point becomes a creation point after this many further iterations of observation."""
    max_creations_per_iteration: int = setting(2, low=1)
    """First-grouping attempts per iteration."""
    creation_every: int = setting(2, low=1)
    """Attempt first groupings every this many iterations (due points wait for the next attempt)."""
    seed_points: int = setting(3, low=3, high=10_000)
    """Previously grouped points that seed a new group with its creation point (paper: three)."""
    regroup_min_iterations: int = setting(20, low=1)
    """A point is regrouped when it leaves view after being observed for at least this many iterations."""
    regroup_after: int = setting(96, low=1)
    """A point still in view after this many iterations is regrouped before its ring forgets the start."""
    max_regroups_per_iteration: int = setting(1, low=0)
    """Regroupings per iteration."""
    min_basis_spread: float = setting(1.0, above=0)
    """Smallest distance between basis points and of the third from the line of the first two (m)."""
    collinear_tolerance: float = setting(2.0, above=0)
    """Anchor sets whose RMS distance from their best line is below this give no reliable rotation (m):
    a fit's rotation about that line is uncertain by about the noise over this distance, and the
    group carries that error into every point it places (0.3 m noise over 2 m is about 5 degrees
    per fit, before the averaging over pairs and iterations)."""
    dynamic_detection: bool = True
    """Run dynamic point detection before a group is final."""
    dynamic_min_iterations: int = setting(15, low=1)
    """Groups with a shorter calculation interval skip dynamic detection (motion not separable from noise)."""
    dynamic_gap_ratio: float = setting(0.5, above=0)
    """Gap rule: relative jump in the sorted first-round deviations that sets the threshold."""
    dynamic_window: int = setting(40, low=1, high=10_000)
    """Iterations of history the dynamic sweep compares (first groupings are too short to tell
    motion from noise, so points are judged against the persisting majority bin)."""
    dynamic_every: int = setting(5, low=1)
    """Run the dynamic sweep every this many iterations."""
    dynamic_block: int = setting(5, low=1)
    """The sweep compares distances averaged over blocks of this many iterations (1: single
    observations), which lowers the noise so that points moving a few metres over the window stand
    out (see :func:`~relpoint.estimators.relative_point.dynamics.deviation_to_references`)."""
    dynamic_references: int = setting(6, low=1, high=1_000)
    """Verified static points each point is compared with in the sweep."""
    dynamic_verify_factor: float = setting(1.5, above=0)
    """A point whose deviation against the references is at most this times theirs is verified static."""
    dynamic_moving_factor: float = setting(2.0, above=0)
    """A point whose deviation against the references exceeds this times theirs is dynamic."""
    dynamic_tail_sigmas: float = setting(3.0, low=0, high=100)
    """Which flagged points are reported as *dynamic* landmarks. Every point a dynamic test flags
    leaves the static map, the global index and every fit; it is reported dynamic only where the
    value that flagged it also stands out of the bulk of the values judged with it, by this many
    robust standard deviations above their median on a log scale (see
    :func:`~relpoint.estimators.relative_point.dynamics.tail_bound`). The other flagged points are
    left out of the map as *unreliable* (``landmarks_unreliable`` in the summary): on a real
    sensor's heavy-tailed error a static point crosses the factors now and then, and on 7-Scenes
    keypoints 42 % of the well-tracked corners' landmarks were reported moving with the factors
    alone, 8 % with this bound, at the same ATE. 0 reports every flagged point as dynamic."""
    dynamic_noise_floor: float = setting(1.0, low=0, high=100)
    """The noise level the dynamic tests scale (the references' deviation in the sweep, the binning's
    threshold) is at least this times what ``observation_sigma`` gives two static points (``sqrt(2)
    sigma``, over the square root of the block length for block means): a deviation that the noise
    alone explains never marks a point as moving. The verified references were chosen for their low
    deviation and run below it on real keypoints (0.32 cm against 0.65 cm expected at 1 cm noise),
    which flagged points of ordinary noise; on the simulator the floor and the references agree."""
    dynamic_world_factor: float = setting(2.5, low=0)
    """A point whose block-mean positions in ``world`` (mapped by the poses of their iterations)
    scatter by more than this times the typical scatter of the points in view is dynamic; it sees
    motion in every direction, where distances only see it along each reference (0 disables)."""
    dynamic_spread_factor: float = setting(2.5, above=0)
    """A point whose groups disagree about its global position by more than this times the typical
    disagreement of the points in view is dynamic."""
    dynamic_spread_verify: float = setting(0.6, above=0, high=1)
    """... and is verified static only below this fraction of that."""
    merge_bound: float = setting(1.5, low=0)
    """New points within this distance of an older, never co-observed point are merged into it (m)."""
    trim: float = setting(3.0, low=0)
    """Least-squares fits drop pairs with residual above this times the median residual, then refit."""
    trim_floor: float = setting(0.5, low=0)
    """Smallest residual trimming may reject (m)."""
    trim_rounds: int = setting(1, low=1, high=100)
    """Trimming rounds of the group fits and the current position (each refits without the outliers)."""
    consensus_bound: float = setting(1.5, low=0)
    """Group fits and the current position re-seed from the best three-point fit (deterministic
    RANSAC over the heaviest pairs) when a pair's residual exceeds this, and drop the pairs beyond
    it, so moving points in view cannot pull them (m; 0 disables)."""
    unverified_weight: float = setting(0.5, above=0, high=1)
    """Weight factor, in group fits and the current position, of points not (yet) verified static.
    (Using verified points only would be safer against moving points but, with few points in view,
    costs more accuracy through weaker geometry than it saves.)"""
    spread_floor: float = setting(0.2, above=0)
    """Anchors and current-position points are weighted by 1 / (spread^2 + this^2), where spread is
    how much the point's groups disagree about its global position (m)."""
    max_groups_per_point: int = setting(24, low=1, high=1_000)
    """Points in more groups have their lightest redundant closed group removed (bounds memory)."""
    stale_after: int = setting(10, low=1)
    """Ungrouped points unseen for this many iterations are dropped (clutter, one-off points)."""
    coast: bool = True
    """In an iteration with fewer than three usable mapped points, move the pose by the motion of
    this iteration's locally matched raw points when they give one; False holds the pose."""

    def at_noise(self, sigma: float) -> RelativePointConfig:
        """These settings with ``observation_sigma = sigma`` (m) and the ``NOISE_SCALED`` bounds scaled to it."""
        factor = sigma / SIMULATOR_SIGMA
        scaled = {name: getattr(self, name) * factor for name in NOISE_SCALED}
        return dataclasses.replace(self, observation_sigma=sigma, **scaled)

    def check(self) -> None:
        """The windows that index a point's ring of observations fit in it."""
        if self.match_window >= self.ring_size or self.creation_delay >= self.ring_size:
            raise UsageError(
                f"relpoint settings match_window ({self.match_window}) and creation_delay ({self.creation_delay}) "
                f"must be below ring_size ({self.ring_size})"
            )
        if max(self.regroup_min_iterations, self.regroup_after, self.dynamic_window) > self.ring_size:
            raise UsageError(
                f"relpoint settings regroup_min_iterations ({self.regroup_min_iterations}), regroup_after "
                f"({self.regroup_after}) and dynamic_window ({self.dynamic_window}) must not exceed ring_size "
                f"({self.ring_size})"
            )
