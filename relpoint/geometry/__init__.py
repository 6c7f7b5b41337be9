"""Rigid-body geometry over numpy arrays, in the manner of evo's ``core/lie_algebra``: every rotation,
transform and rigid fit of the project comes from here.

* :mod:`.so3`: rotations (matrices, quaternions, rotation vectors) and the filters' SO(3) calculus;
* :mod:`.se3`: poses, inverses, point transforms and body twists;
* :mod:`.fitting`: least-squares rigid fits and their RANSAC consensus.

Conventions (see ``docs/log-format.md``): a pose ``T_a_b`` is a 4x4 homogeneous matrix that maps
coordinates in frame ``b`` to frame ``a`` (``p_a = T_a_b @ p_b``); quaternions are ``(x, y, z, w)``;
metres and radians throughout. Fast variants for per-iteration loops sit beside the checked
functions and say so (:func:`~.se3.apply_transform`, :func:`~.se3.rigid_inverse`,
:func:`~.se3.transform_soa32`, :func:`~.so3.quaternion_xyzw`); the Relative Point estimator's
compiled kernels fuse their own fits into whole phases (``relative_point/_kernels.py``).
"""

from relpoint.geometry.fitting import (
    RigidFit,
    fit_rigid,
    fit_rigid_on_axes,
    fitted_parameters,
    information_basis,
    kabsch,
    kabsch_batch,
    measured_basis,
    rigid_consensus,
    summed_information,
)
from relpoint.geometry.se3 import (
    apply_transform,
    body_twist,
    check_points,
    homogeneous,
    integrate_twist,
    invert_pose,
    matrix_to_position_quat,
    pose_matrix,
    rigid_inverse,
    transform_points,
    transform_soa32,
    twist_step,
)
from relpoint.geometry.so3 import (
    FloatArray,
    quat_to_matrix,
    quaternion_xyzw,
    skew,
    smallest_rotation,
    so3_exp,
    so3_right_jacobian,
)

__all__ = [
    "FloatArray", "RigidFit", "apply_transform", "body_twist", "check_points", "fit_rigid",
    "fit_rigid_on_axes", "fitted_parameters", "homogeneous", "information_basis", "integrate_twist",
    "invert_pose", "kabsch", "kabsch_batch", "matrix_to_position_quat", "measured_basis", "pose_matrix", "quat_to_matrix",
    "quaternion_xyzw", "rigid_consensus", "rigid_inverse", "skew", "smallest_rotation", "so3_exp",
    "so3_right_jacobian", "summed_information", "transform_points", "transform_soa32", "twist_step",
]  # fmt: skip
