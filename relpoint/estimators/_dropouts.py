"""The motion over dropped observations, measured from the points rather than predicted.

A recorder that drops frames (a full disk buffer, a sensor restarting, a link lost for a few
seconds) leaves an interval of several typical ones while the sensor keeps moving. The filters'
constant-velocity prediction over it may be right on average, but its uncertainty grows as the cube
of the interval: after 3 s of the vehicle's 0.5 rad/s^2 of angular acceleration noise the heading is
uncertain by several radians and the position by metres, every landmark in view lies inside every
point's gate, and the association pairs points with the wrong landmarks (an independent simulator's
circle at 2 m/s with 3 s dropped: ATE 0.007 -> 2.4 m for the EKF, 0.009 -> 2.8 m and 140 deg for
FastSLAM, every landmark seen after the gap mapped twice).

After such an interval the observation is registered onto the last one
(:func:`relpoint.estimators._noise.register_consecutive`: ICP from the identity, from the predicted
motion, then the global search), and where its points come back onto the last observation's (the
revisit test), the registered motion takes the prediction's place, with the uncertainty of a
registration of those points: a point's noise in position, and that over the points' spread in
rotation. Where the observations share nothing (the gap was too long to see the same landmarks), or
fewer than :data:`DROPOUT_MIN_PAIRS` mutually nearest points, the prediction stands as before; and where
the prediction itself already lays the points back onto the last observation's (the revisit test on the
predicted motion), nothing is registered: the gap did not make the prediction vague. A motion fitted to
a few stereo points is no better than the prediction. Starry Night (a hand-held rig, clouds of 6-20
points, 119 intervals of more than 3 typical ones between non-empty clouds), with the defaults:
registered after each, the EKF's ATE went 0.159 -> 0.202 m; on at least 10 pairs still 0.320 m (one
registration turned the pose by 27 degrees, within the prediction's 24 degrees of doubt); on at least
10 pairs where the prediction did not hold, the EKF 0.078 m but FastSLAM over seeds 0-4 0.093 -> 0.164
m (one seed 0.43 m). With 20 pairs the log is run as before the dropout registration. The observation after it is registered onto it too: a motion measured over
the gap places the pose but not the twist, which the platform may have changed meanwhile (a drone
turning back and forth: FastSLAM placed right after the gap, lost 0.5 s later, ATE 5.5 m).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np

from relpoint.estimators._noise import GLOBAL_MIN_PAIRS, REVISIT_RATIO, register_consecutive, revisit_measure
from relpoint.types import FloatArray

#: An interval this many times the log's typical one (its median so far) follows dropped observations:
#: at least two missing. Stamps jittered by up to half an interval never reach it.
DROPOUT_INTERVALS = 3.0

#: Mutually nearest pairs a registration over a dropout needs before it takes the prediction's place
#: (twice the global search's least): fitted to Starry Night's stereo clouds of 6-20 points it was no
#: better than the prediction (below).
DROPOUT_MIN_PAIRS = 2 * GLOBAL_MIN_PAIRS

#: Intervals remembered for the typical one.
_HISTORY = 64
#: The typical interval is taken again after this many new intervals (a median costs more than the
#: rest of the bookkeeping of an observation, and a log's rate does not change from one to the next).
_REFRESH = 8


class DropoutRegistration:
    """Keeps the last observation's points and tells, after a dropout, the motion since it.

    ``motion_since_last`` returns ``(R, t, covariance)``: the last observation's sensor frame to this
    one's (``x_last = R x_now + t``) and the covariance (6, 6) of its error ``(dt, dtheta)``, in the
    last observation's frame (``dtheta`` of ``R_true = R Exp(dtheta)``), or None when the interval is a
    regular one, the prediction holds or the registration does not. ``registered``, ``unregistered``
    and ``predicted`` count the dropouts whose motion was measured, those where it could not be, and
    those the prediction held over.
    """

    def __init__(self) -> None:
        self._intervals: deque[float] = deque(maxlen=_HISTORY)
        self._points: FloatArray | None = None
        self._stamp_ns: int | None = None
        self._rng = np.random.default_rng(0)
        self.registered = 0
        self.unregistered = 0
        self.predicted = 0
        self._after_dropout = False  # the observation after a dropout is registered too
        self._typical = 0.0  # the median of the intervals (s), taken again every _REFRESH new ones
        self._since_typical = 0

    def remember(self, stamp_ns: int, points: FloatArray) -> None:
        """The observation just processed (its points in the sensor frame, m); empty ones are not kept."""
        if self._stamp_ns is not None and stamp_ns > self._stamp_ns and not self.is_dropout(stamp_ns):
            self._intervals.append((stamp_ns - self._stamp_ns) * 1e-9)
            self._since_typical += 1
            if len(self._intervals) <= _REFRESH or self._since_typical >= _REFRESH:
                self._typical, self._since_typical = _median(self._intervals), 0
        if len(points) >= 3:
            self._points, self._stamp_ns = points, stamp_ns

    def is_dropout(self, stamp_ns: int) -> bool:
        """Whether the interval from the last kept observation to ``stamp_ns`` follows dropped ones."""
        if self._stamp_ns is None or len(self._intervals) < 3:
            return False
        return (stamp_ns - self._stamp_ns) * 1e-9 > DROPOUT_INTERVALS * self._typical

    def pending(self, stamp_ns: int) -> bool:
        """Whether :meth:`motion_since_last` may measure a motion for the observation at ``stamp_ns`` (it
        follows a dropout, or the observation that did): callers skip building its prediction otherwise."""
        return self._points is not None and (self._after_dropout or self.is_dropout(stamp_ns))

    def motion_since_last(
        self, stamp_ns: int, points: FloatArray, predicted: tuple[FloatArray, FloatArray], sigma: float
    ) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """After a dropout (and for the observation that follows it), the registered motion from the last
        observation to this one's ``points`` (sensor frame, m), ICP started from ``predicted`` ``(R, t)``
        among others; ``sigma`` is a point's noise (m). None otherwise or when the registration does not
        revisit. Called in order for every observation with points, or at least for each one
        :meth:`pending` holds for."""
        if self._points is None:
            return None
        dropout, after_dropout = self.is_dropout(stamp_ns), self._after_dropout
        self._after_dropout = dropout
        if not (dropout or after_dropout):
            return None
        points = np.asarray(points, dtype=np.float64)
        points = points[np.all(np.isfinite(points), axis=1)]
        if len(points) < 3:
            return None
        last = np.asarray(self._points, dtype=np.float64)
        last = last[np.all(np.isfinite(last), axis=1)]
        if len(last) < 3:
            return None
        predicted_measure = revisit_measure(last, points, *predicted)
        if _holds(predicted_measure):  # the prediction lays the points back onto the last ones already
            self.predicted += dropout
            return None
        registered, _, revisits = register_consecutive(last, points, predicted, self._rng)
        measured = None if registered is None else revisit_measure(last, points, *registered[:2])
        if registered is None or not revisits or not _holds(measured):
            self.unregistered += dropout
            return None
        R, t, residual = registered
        spread = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
        noise = max(sigma, float(np.sqrt(np.mean(residual**2))) if len(residual) else sigma)
        covariance = np.diag(np.r_[np.full(3, noise**2), np.full(3, (noise / max(spread, noise)) ** 2)])
        self.registered += dropout
        return R, t, covariance


def _median(values: Iterable[float]) -> float:
    """The median of a few floats, as ``numpy.median`` gives it to the bit (the mean of the middle two
    of an even count), in about 2 us where numpy takes 15-40 us for 64 values held in a deque."""
    ordered = sorted(values)
    half = len(ordered) // 2
    return ordered[half] if len(ordered) % 2 else (ordered[half - 1] + ordered[half]) / 2


def _holds(measured: tuple[float, int] | None) -> bool:
    """Whether a motion's :func:`~relpoint.estimators._noise.revisit_measure` shows it laying an
    observation's points back onto the last one's: a revisit ratio under ``REVISIT_RATIO`` over at least
    :data:`DROPOUT_MIN_PAIRS` mutually nearest pairs (fewer cannot tell)."""
    return measured is not None and measured[0] < REVISIT_RATIO and measured[1] >= DROPOUT_MIN_PAIRS


def rotation_errors(predicted: FloatArray, measured: FloatArray) -> FloatArray:
    """``dtheta`` (..., 3) of ``measured = predicted Exp(dtheta)`` for rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation  # here, not at import: scipy costs start-up time

    between = np.swapaxes(predicted, -1, -2) @ measured
    return np.asarray(Rotation.from_matrix(between.reshape(-1, 3, 3)).as_rotvec()).reshape((*between.shape[:-2], 3))
