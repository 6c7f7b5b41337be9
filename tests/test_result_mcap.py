"""result.mcap shows the run in Foxglove: path, reference, observations in the world, a growing map.

Read back with mcap-ros2-support, another tool's decoder, so the schemas are checked as Foxglove and
``ros2 bag`` see them.
"""

from __future__ import annotations

import json
from collections import defaultdict
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap_ros2.reader import read_ros2_messages
from scipy.spatial import cKDTree

from formats.log import LogReader
from formats.trajectory_files import read_tum
from relpoint_cli.main import cli


def messages(path: Path) -> dict[str, list]:
    by_topic: dict[str, list] = defaultdict(list)
    for item in read_ros2_messages(str(path)):
        by_topic[item.channel.topic].append((item.schema.name, item.ros_msg))
    return by_topic


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory, small_log: Path) -> Path:
    out = tmp_path_factory.mktemp("run") / "ekf"
    result = CliRunner().invoke(cli, ["run", str(small_log), "-e", "ekf", "-o", str(out)])
    assert result.exit_code == 0, result.stderr
    return out


def test_result_mcap_carries_path_reference_observations_and_a_growing_map(run_dir: Path, small_log: Path) -> None:
    topics = messages(run_dir / "result.mcap")
    iterations = json.loads((run_dir / "run.json").read_text())["summary"]["iterations"]
    assert {name for name, _ in topics["/relpoint/path"]} == {"nav_msgs/msg/Path"}
    assert len(topics["/relpoint/pose"]) == len(topics["/tf"]) == len(topics["/relpoint/observations"]) == iterations
    paths = [msg for _, msg in topics["/relpoint/path"]]
    assert len(paths[-1].poses) == iterations and all(len(a.poses) < len(b.poses) for a, b in pairwise(paths))
    (reference,) = [msg for _, msg in topics["/relpoint/reference_path"]]
    assert len(reference.poses) == iterations and reference.header.frame_id == "world"
    maps = [msg for _, msg in topics["/relpoint/map"]]
    assert len(maps) > 10 and maps[-1].width >= maps[0].width  # the map grows over the run
    assert {f.name for f in maps[-1].fields} >= {"x", "y", "z", "rgb", "dynamic", "observations", "gt_id"}

    # The observations are moved into the world frame with the estimated pose of their stamp: at the
    # start, where the estimate is the true pose, they sit on the true landmarks.
    reader = LogReader(small_log)
    truth = next(r.value for r in reader.records(["ground_truth_landmarks"]))
    raw = [r.value for r in reader.records(["points"])]
    estimate = read_tum(run_dir / "trajectory.tum")
    for k in (0, iterations - 1):
        cloud = topics["/relpoint/observations"][k][1]
        assert cloud.header.frame_id == "world"
        xyz = np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(cloud.width, -1)[:, :3]
        T = estimate.matrices()[k]
        np.testing.assert_allclose(xyz, raw[k].points @ T[:3, :3].T + T[:3, 3], atol=1e-4)
        if k == 0:
            assert np.median(cKDTree(truth.positions).query(xyz)[0]) < 0.8  # 0.3 m noise per axis
