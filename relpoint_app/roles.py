"""Which log roles stand behind each input an estimator declares (``EstimatorSpec.needs`` and ``uses``)."""

from __future__ import annotations

#: Log roles behind each input an estimator may need.
NEED_ROLES: dict[str, tuple[str, ...]] = {
    "points": ("points",),
    "depth": ("depth", "camera_info"),
    "odometry": ("odometry",),
    "fix": ("fix",),
}
