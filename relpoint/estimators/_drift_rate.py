"""How fast a filter's place in the fixes' frame drifts, measured on the fixes it fuses.

A particle filter's particles share their map's errors: a map turned by a fraction of a degree
carries every particle with it, so the particles' spread does not show how far the filter has drifted
from ``world`` since the last fix. FastSLAM stands for that drift with a random walk of its position,
``rate`` metres (per axis) per metre travelled, which sets how far each fix pulls the particles
(:meth:`relpoint.estimators.fastslam.FastSlam.add_fix`). Too fast a walk lets every fix pull a
centimetre-accurate filter by a share of the fix's own noise, and bends its path and map; too slow a
walk leaves a filter that has drifted where it is until the fix gate steps in.

The rate differs by orders of magnitude between logs (the map's noise, its landmarks, the path), so
it is measured rather than set. Each fused fix measures the correction its filter's path needs: the
fix minus the mean position with the jumps of the fixes fused before taken out (the path the map
made on its own). Along the path that correction is a random walk of the drift rate, seen through
each fix's noise: a local-level model. :class:`DriftRate` runs, for every rate of a logarithmic grid,
the Kalman filter of that model over the corrections, and sums the log-likelihood of its innovations;
the rate is the most likely one, once :data:`MIN_FIXES` fixes have been seen (the prior before).
Each candidate filters the corrections with its own gain, so the estimate does not feed on the rate
the filter used meanwhile: scored on the filter's own innovations instead, a rate that let the
filter follow the fixes' noise was taken as evidence of drift, and 5 m fixes ran it away to 0.3-1.0
m/m.
"""

from __future__ import annotations

import numpy as np

from relpoint.geometry import FloatArray

#: Rates tried (m of drift per axis per m travelled): 1e-4 (a map that does not drift) to 1 (a filter
#: that has lost its map).
RATES = np.geomspace(1e-4, 1.0, 33)
#: The rate before the fixes have measured one (m/m): a map turned by about 0.1 rad.
DRIFT_PRIOR = 0.1
#: Fixes whose innovations are seen before the measured rate replaces the prior.
MIN_FIXES = 3


class DriftRate:
    """The maximum-likelihood drift rate of a filter's position in ``world`` (m/m, per axis).

    prior: the rate until :data:`MIN_FIXES` fixes have been seen (m/m).
    """

    def __init__(self, prior: float) -> None:
        self._prior = float(prior)
        self._correction = np.zeros((len(RATES), 3))  # each rate's estimate of the correction (m)
        self._variance = np.zeros(len(RATES))  # its variance, per axis (m^2)
        self._log_likelihood = np.zeros(len(RATES))
        self.fixes = 0

    @property
    def rate(self) -> float:
        """The rate to use now (m/m): the most likely one, or the prior before enough fixes."""
        if self.fixes < MIN_FIXES:
            return self._prior
        return float(RATES[int(np.argmax(self._log_likelihood))])

    def start(self, variance: float) -> None:
        """Begin at a zero correction of known variance (m^2 per axis), e.g. the frame fit's at the pinning."""
        self._correction[:] = 0.0
        self._variance[:] = max(float(variance), 0.0)

    def travel(self, distance: float, added_variance: float = 0.0) -> None:
        """The filter moved ``distance`` metres; ``added_variance`` (m^2 per axis) is what it knows it added."""
        self._variance += (RATES * distance) ** 2 + max(float(added_variance), 0.0)

    def fix(self, correction: FloatArray, variances: FloatArray) -> None:
        """A fused fix: ``correction`` (3,) the fix minus the path without the fixes' jumps (m),
        ``variances`` (3,) the fix's per-axis variances (m^2). Scores every rate by the likelihood of the
        correction given its filter's prediction, then updates each filter."""
        r = np.maximum(np.asarray(variances, dtype=np.float64), 1e-12)
        innovation = np.asarray(correction, dtype=np.float64)[None, :] - self._correction  # (rates, 3)
        S = self._variance[:, None] + r[None, :]
        self._log_likelihood -= 0.5 * np.sum(innovation**2 / S + np.log(S), axis=1)
        gain = self._variance[:, None] / S
        self._correction += gain * innovation
        self._variance = np.mean(self._variance[:, None] * (1.0 - gain), axis=1)
        self.fixes += 1

    def summary(self) -> dict[str, float | int]:
        """``drift_rate`` (m/m, the rate in use) and ``drift_rate_fixes`` (the fixes it was measured on)."""
        return {"drift_rate": round(self.rate, 6), "drift_rate_fixes": self.fixes}
