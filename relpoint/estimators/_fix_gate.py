"""Validating position fixes against a filter's prediction before they are fused.

A fix fused into a filter whose position it contradicts drags the whole state after it: a 1 m fix
into a filter that knows its position to centimetres, if either covariance is off, moves the pose
further than the map allows. Each fix is therefore tested like an observation (Zhang, Milios and Gu,
*General Concept of 3D SLAM*, section 4.2, the Mahalanobis gate of eq. 14-16, here on the fix's
innovation ``nu = fix - p`` with ``S = C_p + C_fix``): inside the gate it is fused as it is; outside
it is held back. A run of ``patience`` fixes in a row outside the gate cannot be the fixes' own
noise (at probability 0.999 that is one in 10^9 for three); it means the filter itself has drifted
and its covariance is too small, so from then on each fix outside the gate is fused again, until
the first fix inside. The EKF fuses it as it is: its small covariance limits each step, and the
fixes pull it back over a few of them. FastSLAM, whose particles' covariance is its own model of
the frame's drift, grows that covariance until the fix lies on the gate's edge
(:meth:`relpoint.estimators.fastslam.FastSlam.add_fix`). An earlier version inflated the fix's
covariance onto the gate's edge instead: on figure8-gaps that left FastSLAM 9-28 m off and the EKF
lost on one seed of three (84.6 m).
"""

from __future__ import annotations

from typing import Any

from relpoint.statistics import chi2_gate


class FixGate:
    """Decides how each fix enters: as given, with an inflated covariance, or not at all.

    Parameters
    ----------
    probability: chi-square probability of the gate (3 degrees of freedom); 1 (or 0) turns it off.
    patience: fixes in a row outside the gate that are held back before they are fused inflated.
    """

    def __init__(self, probability: float = 0.999, patience: int = 3) -> None:
        self.enabled = 0.0 < probability < 1.0
        self.threshold = chi2_gate(probability, 3) if self.enabled else float("inf")
        self.patience = patience
        self._outside_in_a_row = 0
        self.rejected = 0
        self.inflated = 0

    def inflation(self, d2: float) -> float | None:
        """How a fix with squared Mahalanobis distance ``d2`` enters: 1 inside the gate, None held
        back, and past the patience ``d2`` over the gate (> 1): the factor that would put it on the
        gate's edge, which says the filter has drifted (module docstring)."""
        if d2 <= self.threshold:
            self._outside_in_a_row = 0
            return 1.0
        self._outside_in_a_row += 1
        if self._outside_in_a_row <= self.patience:
            self.rejected += 1
            return None
        self.inflated += 1
        return d2 / self.threshold

    def summary(self) -> dict[str, Any]:
        """run.json figures: fixes held back and fixes fused with an inflated covariance."""
        return {"fixes_gated_out": self.rejected, "fixes_inflated": self.inflated} if self.enabled else {}
