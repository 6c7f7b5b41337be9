"""Simulated runs written as relpoint logs: the simulators (:mod:`relpoint.simulation`) joined to the
log writers (:mod:`formats.simulation_log`, :mod:`formats.rgbd_log`), which take core types only."""

from __future__ import annotations

import os
from collections.abc import Callable

from formats.log import Topics
from formats.rgbd_log import write_reference_cloud, write_rgbd_simulation_log
from formats.simulation_log import write_simulation_log
from relpoint.simulation import Simulation
from relpoint.simulation.rgbd import RgbdSimulation


def write_simulation(
    simulation: Simulation,
    path: str | os.PathLike[str],
    *,
    compression: str = "zstd",
    topics: Topics | None = None,
    on_step: Callable[[int], None] | None = None,
) -> dict[str, int]:
    """Write every iteration of ``simulation`` to the log ``path`` (atomically); returns message counts
    (see :func:`formats.simulation_log.write_simulation_log`). ``on_step(k)`` follows iteration ``k``."""
    return write_simulation_log(
        simulation.steps(),
        path,
        landmarks=simulation.landmarks,
        ground_truth=simulation.ground_truth,
        settings=simulation.config.log_settings(),
        compression=compression,
        topics=topics,
        on_step=on_step,
    )


def write_rgbd_simulation(
    simulation: RgbdSimulation,
    path: str | os.PathLike[str],
    *,
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> dict[str, int]:
    """Write every frame of ``simulation`` to the log ``path`` (atomically); returns message counts
    (see :func:`formats.rgbd_log.write_rgbd_simulation_log`). ``on_frame(k)`` follows frame ``k``."""
    return write_rgbd_simulation_log(
        simulation.frames(),
        path,
        poses=simulation.poses,
        settings=simulation.config.to_dict(),
        compression=compression,
        topics=topics,
        on_frame=on_frame,
    )


def write_scene_cloud(simulation: RgbdSimulation, path: str | os.PathLike[str]) -> int:
    """Write the simulated scene's reference cloud (surface samples with normals, ``world``) as a PLY
    file; returns its number of points."""
    points, normals = simulation.reference_cloud()
    return write_reference_cloud(points, normals, path)
