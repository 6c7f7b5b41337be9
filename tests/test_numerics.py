"""The scipy-free numerics of the filters' path agree with scipy: chi-square quantiles, log-sum-exp,
rotation conversions and nearest neighbours (scipy is the reference here only)."""

from __future__ import annotations

import math
from decimal import Decimal

import numpy as np
import pytest
from scipy import special
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from relpoint.estimators._noise import BRUTE_FORCE_PAIRS, _Nearest
from relpoint.geometry import matrix_to_position_quat, matrix_to_quat, pose_matrix, quat_to_matrix, so3_exp, so3_log
from relpoint.statistics import chi2_gate, chi2_quantile, log_sum_exp

PROBABILITIES = np.concatenate([np.geomspace(1e-6, 0.5, 60), 1.0 - np.geomspace(1e-9, 0.5, 60)])


@pytest.mark.parametrize("dof", range(1, 13))
def test_chi2_quantile_matches_scipy(dof: int) -> None:
    for p in PROBABILITIES:
        reference = 2.0 * special.gammaincinv(dof / 2, p)
        assert chi2_quantile(float(p), dof) == pytest.approx(reference, rel=1e-10, abs=0.0)


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 30, 150, 300])
def test_chi2_quantile_inverts_the_cdf(dof: int) -> None:
    for p in (1e-6, 0.01, 0.5, 0.99, 0.9999999, 1 - 1e-9):
        x = chi2_quantile(p, dof)
        if p > 0.5:
            assert special.gammaincc(dof / 2, x / 2) == pytest.approx(1.0 - p, rel=1e-9)
        else:
            assert special.gammainc(dof / 2, x / 2) == pytest.approx(p, rel=1e-9)


def test_chi2_quantile_is_the_nearest_double() -> None:
    """The quantile is the double nearest the exact one; at the estimators' defaults (3 degrees of freedom,
    whose quantiles carry into outputs as a scale and a log weight) scipy's is within two ulps of it."""
    from relpoint.statistics import _chi2_lower_tail_exact

    for dof in (1, 3, 4, 9, 30):
        for p in (1e-6, 0.001, 0.5, 0.99, 0.999, 0.9999, 0.9999999):
            x = chi2_gate(p, dof)
            reference = 2.0 * special.gammaincinv(dof / 2, p)
            assert abs(x - reference) <= (2 * math.ulp(x) if dof == 3 and p >= 0.5 else 1e-13 * x)
            below, at, above = (float(_chi2_lower_tail_exact(dof, v) - Decimal(p)) for v in
                                (math.nextafter(x, 0.0), x, math.nextafter(x, math.inf)))  # fmt: skip
            assert below < 0.0 < above or at == 0.0
            assert abs(at) <= min(-below, above)


def test_chi2_quantile_edges() -> None:
    assert chi2_quantile(0.0, 3) == 0.0
    assert chi2_quantile(1.0, 3) == math.inf
    with pytest.raises(ValueError):
        chi2_quantile(1.5, 3)
    with pytest.raises(ValueError):
        chi2_quantile(0.5, 0)


def test_log_sum_exp_matches_scipy_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    for i in range(500):
        values = rng.normal(size=int(rng.integers(1, 80))) * rng.choice([1.0, 30.0, 1e3])
        if i % 3 == 0:  # ties at the maximum
            values[rng.integers(len(values))] = values.max()
        assert log_sum_exp(values) == special.logsumexp(values)
    for values in ([-np.inf, -np.inf], [np.inf, 1.0], [1e308, 1e308], [-1e308, 0.0], [0.0]):
        assert log_sum_exp(values) == special.logsumexp(values)
    assert math.isnan(log_sum_exp([np.nan, 1.0]))


def _rotations(rng: np.random.Generator) -> np.ndarray:
    axes = rng.normal(size=(2000, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    near_half_turn = Rotation.from_rotvec(axes * (np.pi - rng.uniform(0.0, 1e-6, (2000, 1)))).as_matrix()
    near_identity = Rotation.from_rotvec(axes * rng.uniform(0.0, 1e-7, (2000, 1))).as_matrix()
    drifted = Rotation.random(2000, random_state=rng).as_matrix() + rng.normal(scale=1e-9, size=(2000, 3, 3))
    half_turns = np.array([np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])])
    return np.concatenate([Rotation.random(5000, random_state=rng).as_matrix(), near_half_turn, near_identity,
                           drifted, half_turns])  # fmt: skip


def test_matrix_to_quat_matches_scipy_bit_for_bit() -> None:
    rotations = _rotations(np.random.default_rng(1))
    np.testing.assert_array_equal(matrix_to_quat(rotations), Rotation.from_matrix(rotations).as_quat(canonical=True))
    T = np.zeros((len(rotations), 4, 4))
    T[:, :3, :3] = rotations
    _, quats = matrix_to_position_quat(T)
    np.testing.assert_array_equal(quats, Rotation.from_matrix(rotations).as_quat(canonical=True))
    assert matrix_to_position_quat(T[0])[1].shape == (4,)
    with pytest.raises(ValueError):
        matrix_to_quat(np.diag([1.0, 1.0, -1.0])[None])


def test_quat_to_matrix_matches_scipy_bit_for_bit() -> None:
    rng = np.random.default_rng(2)
    quats = rng.normal(size=(5000, 4)) * rng.choice([1e-3, 1.0, 100.0], size=(5000, 1))
    np.testing.assert_array_equal(quat_to_matrix(quats), Rotation.from_quat(quats).as_matrix())
    np.testing.assert_array_equal(pose_matrix(np.ones(3), quats[0])[:3, :3], Rotation.from_quat(quats[0]).as_matrix())
    assert quat_to_matrix(np.zeros((0, 4))).shape == (0, 3, 3)
    with pytest.raises(ValueError):
        quat_to_matrix(np.zeros(4))


def test_so3_exp_and_log_match_scipy() -> None:
    """Bit for bit on this platform; within two ulps wherever numpy's sin and cos are not the C library's."""
    rng = np.random.default_rng(3)
    for scale in (1e-9, 1e-4, 1e-3, 3e-3, 0.1, 1.0, 3.14, 10.0):
        rotvecs = rng.normal(size=(3000, 3)) * scale
        np.testing.assert_array_max_ulp(so3_exp(rotvecs), Rotation.from_rotvec(rotvecs).as_matrix(), maxulp=2)
    rotations = _rotations(rng)
    np.testing.assert_array_equal(so3_log(rotations), Rotation.from_matrix(rotations).as_rotvec())
    assert so3_exp(np.zeros((2, 5, 3))).shape == (2, 5, 3, 3)
    assert so3_log(np.zeros((0, 3, 3))).shape == (0, 3)


@pytest.mark.parametrize("size", [3, 200, 2 * int(math.sqrt(BRUTE_FORCE_PAIRS))])
def test_nearest_matches_cKDTree(size: int) -> None:
    rng = np.random.default_rng(size)
    points = rng.normal(size=(size, 3)) * 50.0
    queries = points[rng.integers(size, size=size)] + rng.normal(size=(size, 3)) * 0.3
    distance, index = _Nearest(points).query(queries)
    reference_distance, reference_index = cKDTree(points).query(queries)
    np.testing.assert_array_equal(index, reference_index)
    np.testing.assert_array_equal(distance, reference_distance)
