"""open3d imports on a bare machine (libusb comes from the libusb-package wheel when the system lacks it)."""

from __future__ import annotations

import numpy as np

from relpoint._open3d import open3d


def test_open3d_imports_and_computes() -> None:
    o3d = open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(100, 3))))
    tree = o3d.geometry.KDTreeFlann(cloud)
    count, indices, _ = tree.search_knn_vector_3d(cloud.points[0], 1)
    assert count == 1 and indices[0] == 0
