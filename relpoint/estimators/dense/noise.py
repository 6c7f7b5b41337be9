"""Depth noise measured from the frames themselves: ``sigma(z) = constant + quadratic z^2`` (metres).

Depth cameras differ by an order of magnitude in noise (a Kinect v1 has about 6 mm at 2 m, an active
stereo camera with a 5 cm baseline about 3.5 cm), and the dense estimator's thresholds that separate noise
from structure (edges in the depth image, the fusion gate, the Huber threshold of ICP) were set for a
Kinect v1. Two measurements, each robust (median absolute deviations per depth bin) and fitted to the
usual shape of depth noise (a floor plus a term growing with depth squared, as disparity noise does):

- :func:`second_differences` of the raw depth image, the noise of one pixel against its neighbours (what an
  edge threshold sees; noise correlated over several pixels, as stereo matching windows make it, hardly
  shows there, and neighbours then hardly differ either);
- ICP's point-to-plane residuals between a frame and the map (what the fusion gate and the Huber threshold
  see: correlated noise shows in full).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]

MAD_TO_SIGMA = 1.4826
"""Median absolute deviation to standard deviation for Gaussian noise."""

BIN_WIDTH = 0.25
"""Depth bins of the fit, metres."""

MIN_BIN_SAMPLES = 400
"""A depth bin with fewer samples than this is left out of the fit."""

REFERENCE_DEPTH = 2.0
"""Depth at which a noise model is quoted (warnings, run.json), metres."""


@dataclass(frozen=True)
class DepthNoise:
    """Depth noise ``sigma(z) = constant + quadratic z^2`` metres, measured over depths ``near``-``far`` metres."""

    constant: float
    quadratic: float
    near: float
    far: float

    def sigma(self, z: float | F32) -> float | F32:
        """Standard deviation (metres) at depth ``z`` (metres)."""
        return self.constant + self.quadratic * z * z

    def scaled(self, factor: float) -> DepthNoise:
        """The same model times ``factor``."""
        return DepthNoise(self.constant * factor, self.quadratic * factor, self.near, self.far)

    def exceeds(self, constant: float, linear: float, quadratic: float) -> bool:
        """Whether ``sigma(z)`` exceeds ``constant + linear z + quadratic z^2`` at some depth of the measured
        range (a threshold set without the measurement covers the noise there)."""
        z = np.linspace(self.near, self.far, 64)
        return bool(np.any(self.sigma(z) > constant + linear * z + quadratic * z * z))

    def as_dict(self) -> dict[str, float]:
        return {
            "constant_m": self.constant,
            "quadratic_per_m": self.quadratic,
            "sigma_at_2m_m": float(self.sigma(REFERENCE_DEPTH)),
            "depths_m": [self.near, self.far],
        }


def second_differences(depth: F32, stride: int = 2) -> tuple[F32, F32]:
    """Depths and noise samples of a depth image (H, W) metres (0 = none): at every ``stride``-th pixel of
    every ``stride``-th row (and column) with depth on both sides along the row (column), the second
    difference ``(d_left - 2 d + d_right) / sqrt(6)``, which has the pixel noise's standard deviation for
    independent noise on a locally planar surface (a plane's depth is nearly linear over three pixels).
    Depth edges give outliers, which the fit's medians ignore."""
    d = np.asarray(depth, dtype=np.float32)
    depths, samples = [], []
    for left, mid, right in (
        (d[::stride, 0:-2:stride], d[::stride, 1:-1:stride], d[::stride, 2::stride]),  # along rows
        (d[0:-2:stride, ::stride], d[1:-1:stride, ::stride], d[2::stride, ::stride]),  # along columns
    ):
        ok = (left > 0) & (mid > 0) & (right > 0)
        depths.append(mid[ok])
        samples.append((left[ok] - 2 * mid[ok] + right[ok]) * np.float32(1 / math.sqrt(6)))
    return np.concatenate(depths), np.concatenate(samples)


def fit_noise(depths: F32, samples: F32) -> DepthNoise | None:
    """``sigma(z) = constant + quadratic z^2`` fitted to noise samples (zero-mean residuals, metres) at their
    depths (metres): per ``BIN_WIDTH`` bin with at least ``MIN_BIN_SAMPLES`` samples a robust standard
    deviation (``MAD_TO_SIGMA`` times the median absolute sample), then least squares on the relative error,
    both terms non-negative. None without two usable bins (one depth says nothing of the growth)."""
    depths = np.asarray(depths, dtype=np.float32)
    samples = np.abs(np.asarray(samples, dtype=np.float32))
    keep = np.isfinite(depths) & np.isfinite(samples) & (depths > 0)
    depths, samples = depths[keep], samples[keep]
    if depths.size < 2 * MIN_BIN_SAMPLES:
        return None
    bins = np.floor(depths / np.float32(BIN_WIDTH)).astype(np.int64)
    order = np.argsort(bins, kind="stable")
    bins, depths, samples = bins[order], depths[order], samples[order]
    starts = np.flatnonzero(np.r_[True, bins[1:] != bins[:-1]])
    ends = np.r_[starts[1:], bins.size]
    z, sigma = [], []
    for start, end in zip(starts, ends, strict=True):
        if end - start < MIN_BIN_SAMPLES:
            continue
        z.append(float(np.median(depths[start:end])))
        sigma.append(MAD_TO_SIGMA * float(np.median(samples[start:end])))
    if len(z) < 2:
        return None
    z_arr, sigma_arr = np.array(z), np.array(sigma)
    if not np.all(sigma_arr > 0):
        sigma_arr = np.maximum(sigma_arr, 1e-6)
    # Relative error: each bin counts alike, whatever its noise.
    design = np.stack([np.ones_like(z_arr), z_arr**2], axis=1) / sigma_arr[:, None]
    target = np.ones_like(z_arr)
    constant, quadratic = np.linalg.lstsq(design, target, rcond=None)[0]
    if constant < 0 or quadratic < 0:
        # One term alone, whichever fits better.
        candidates = []
        for column in (0, 1):
            x = design[:, column]
            coefficient = max(float(x @ target / (x @ x)), 0.0)
            candidates.append((float(np.sum((x * coefficient - target) ** 2)), column, coefficient))
        _, column, coefficient = min(candidates)
        constant, quadratic = (coefficient, 0.0) if column == 0 else (0.0, coefficient)
    return DepthNoise(float(constant), float(quadratic), float(z_arr.min()), float(z_arr.max()))
