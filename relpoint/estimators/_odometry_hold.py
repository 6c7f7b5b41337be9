"""Odometry held between its messages: the process noise it leaves, whatever its rate.

A twist message is the velocity at its stamp (ROS); the filters hold it until the next message
(zero-order hold, *3D SLAM* eq. 5-7) and predict each interval with the twist that covers it. Two
errors make the held twist differ from the true one, and neither shrinks as messages arrive faster:

* The message's own error, of covariance ``twist.covariance``. A driver's velocity errors (slip, a
  wheel radius, its clock) last far longer than its message period, and its covariance is set per
  message whatever the rate. Taken as independent per message, ten messages between two point
  clouds would average it to a tenth of the variance and the filter would trust 100 Hz odometry ten
  times more than the same odometry at 10 Hz. So the error is one twist error held over the span of
  the last observation interval and of the message's hold: over a span ``T`` it moves the pose by
  ``e T``, however many messages share the span.
* The change of the velocity while the twist is held. A message held over several observations
  (odometry slower than the points) is extrapolated: from the first observation after its stamp
  (up to which a twist describes the motion as at the observations' rate) the velocity drifts by
  ``a tau`` with the motion model's acceleration noise ``a`` and the pose by ``a tau^2 / 2``. Held
  half a second on a vehicle, this dominates.

A message held more than :data:`STALE_INTERVALS` typical odometry intervals while observations
arrive is dropped: the filter falls back to its motion model, as without odometry, until the next
one. A gap in both streams (a paused recording) is not the odometry stopping.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator

import numpy as np

from relpoint.geometry import FloatArray
from relpoint.types import OdometryMeasurement

#: A message held longer than this many typical odometry intervals is dropped (the stream stopped).
STALE_INTERVALS = 5.0

#: Message intervals remembered for the typical one.
_HISTORY = 32


class OdometryHold:
    """The odometry message the filter holds, and the process noise of holding it over an interval."""

    def __init__(self) -> None:
        self.held: OdometryMeasurement | None = None
        self.stale = 0  # messages dropped as stale (run.json)
        self._intervals: deque[int] = deque(maxlen=_HISTORY)
        self._last_stamp_ns: int | None = None
        self._observed_ns: int | None = None
        self._overtaken_ns: int | None = None  # the first observation after the held message's stamp

    def hold(self, odometry: OdometryMeasurement) -> None:
        """Hold ``odometry`` from its stamp on (the filter has predicted to its stamp)."""
        if self._last_stamp_ns is not None and odometry.stamp_ns > self._last_stamp_ns:
            self._intervals.append(odometry.stamp_ns - self._last_stamp_ns)
        self._last_stamp_ns = odometry.stamp_ns
        self._overtaken_ns = None
        self.held = odometry

    def observed(self, stamp_ns: int) -> None:
        """Mark an observation at ``stamp_ns``: the twist error is shared from here or the message's stamp."""
        self._observed_ns = stamp_ns
        if self.held is not None and self._overtaken_ns is None and stamp_ns > self.held.stamp_ns:
            self._overtaken_ns = stamp_ns

    def expiry_ns(self) -> int | None:
        """The stamp (ns) after which the held message is stale, or None: none held, no typical interval
        yet, or no observation since its stamp (a pause of the whole log is not the odometry stopping)."""
        if self.held is None or not self._intervals or self._overtaken_ns is None:
            return None
        return self.held.stamp_ns + int(STALE_INTERVALS * float(np.median(self._intervals)))

    def drop(self) -> None:
        """Stop holding a stale message (counted)."""
        self.held = None
        self.stale += 1

    def prediction_ends(self, state_ns: int, stamp_ns: int) -> Iterator[int]:
        """The stamps (ns) a filter at ``state_ns`` predicts to, in turn, on its way to ``stamp_ns``: the
        held message's expiry first when it falls in between (the message is dropped once the filter
        has predicted to it, so the rest of the way takes the motion model), then ``stamp_ns``."""
        expiry = self.expiry_ns()
        if expiry is not None and expiry < stamp_ns:
            if expiry > state_ns:
                yield expiry
            self.drop()
        yield stamp_ns

    def twist(self) -> FloatArray:
        """The held twist (6,): (vx, vy, vz, wx, wy, wz), m/s and rad/s, sensor frame."""
        assert self.held is not None
        return np.concatenate([self.held.linear, self.held.angular])

    def noise(self, start_ns: int, end_ns: int, acceleration: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Twist covariances of holding the message over ``[start_ns, end_ns]`` (after its stamp).

        ``acceleration`` (6,): the motion model's acceleration noise per twist axis (m/s^2, rad/s^2),
        also what axes the message leaves unset take over the interval. Returns ``Q_twist`` (6, 6),
        the covariance of the message's error, which moves the pose through the interval's twist
        Jacobian ``G`` (~ ``dt I``) and is the new twist's error; and ``Q_span`` (6, 6), positive
        semi-definite, the further twist covariance that moves the pose alone: the growth of the
        shared error over the span and of the velocity's change (see the module), in units of ``G``.
        """
        held = self.held
        assert held is not None
        dt = (end_ns - start_ns) * 1e-9
        A = np.asarray(acceleration, dtype=np.float64) ** 2
        Q_twist = held.twist_covariance(A * dt**2)
        span_from = held.stamp_ns if self._observed_ns is None else min(held.stamp_ns, self._observed_ns)
        s0, s1 = max(start_ns - span_from, 0) * 1e-9, (end_ns - span_from) * 1e-9
        Q_span = Q_twist * ((s1**2 - s0**2) / dt**2 - 1.0)  # (e T)^2 grows by this, in units of dt^2
        if self._overtaken_ns is not None:
            # Up to the first observation after its stamp a twist stands for the motion as at the
            # observations' rate; held over more observations it is extrapolated, and the velocity's
            # change counts from there.
            t0 = max(start_ns - self._overtaken_ns, 0) * 1e-9
            t1 = max(end_ns - self._overtaken_ns, 0) * 1e-9
            Q_span = Q_span + np.diag(A * (t1**4 - t0**4) / (4.0 * dt**2))  # (a tau^2 / 2)^2 likewise
        return Q_twist, Q_span
