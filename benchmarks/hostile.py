"""Hostile cases of the reliability contract: exit code, last stderr line, peak memory and time of each.

Every case is a real ``relpoint`` command line in its own process, with its address space capped
(``--memory-gb``) and a time limit (``--timeout``) so that a case that would exhaust the machine is
stopped and reported as such. ``--source DIR`` runs another checkout (say the code before a change,
from ``git worktree add``) on the same cases, for a before/after table.

    python benchmarks/hostile.py                      # this checkout
    python benchmarks/hostile.py --source ../before   # another one
    python benchmarks/hostile.py --only bomb,far      # cases whose name contains any of these
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mcap_ros2.writer import Writer as Ros2Writer  # noqa: E402

from formats import ros2  # noqa: E402
from relpoint.simulation import SimulationConfig  # noqa: E402
from tests.hostile_logs import far_point, one_point, time_gap, write_log  # noqa: E402

ALIAS_BOMB = "a: &a [" + ",".join(['"lol"'] * 9) + "]\n" + "".join(
    f"{b}: &{b} [" + ",".join([f"*{a}"] * 9) + "]\n" for a, b in zip("abcdefgh", "bcdefghi", strict=True)
)


def huge_cloud_log(path: Path, points: int) -> Path:
    """Two small clouds around one of ``points`` points, written with mcap-ros2-support."""
    rng = np.random.default_rng(0)
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        schema = writer.register_msgdef(ros2.POINT_CLOUD2, ros2.message_definition(ros2.POINT_CLOUD2))
        for k, n in enumerate((50, points, 50)):
            data = rng.normal(size=(n, 4)).astype(np.float32)
            stamp = (k + 1) * 100_000_000
            message = {
                "header": {"stamp": {"sec": 0, "nanosec": stamp}, "frame_id": "sensor"}, "height": 1, "width": n,
                "fields": [{"name": c, "offset": 4 * i, "datatype": 7, "count": 1} for i, c in enumerate("xyz")],
                "is_bigendian": False, "point_step": 16, "row_step": 16 * n, "data": data.tobytes(), "is_dense": True,
            }  # fmt: skip
            writer.write_message(topic="/points", schema=schema, message=message, log_time=stamp, publish_time=stamp)
        writer.finish()
    return path


def depth_log(path: Path, width: int, height: int, frames: int = 2) -> Path:
    """Depth images of one size with a matching camera_info, written with mcap-ros2-support."""
    with path.open("wb") as stream:
        writer = Ros2Writer(stream)
        image = writer.register_msgdef(ros2.IMAGE, ros2.message_definition(ros2.IMAGE))
        info = writer.register_msgdef(ros2.CAMERA_INFO, ros2.message_definition(ros2.CAMERA_INFO))
        pixels = np.full((height, width), 1500, dtype=np.uint16).tobytes()
        for k in range(frames):
            stamp = (k + 1) * 33_000_000
            header = {"stamp": {"sec": 0, "nanosec": stamp}, "frame_id": "camera"}
            f = 0.8 * width
            k_matrix = [f, 0.0, width / 2, 0.0, f, height / 2, 0.0, 0.0, 1.0]
            writer.write_message(topic="/camera/depth/camera_info", schema=info, log_time=stamp, publish_time=stamp,
                                 message={"header": header, "height": height, "width": width, "k": k_matrix,
                                          "distortion_model": "plumb_bob", "d": [], "r": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                          "p": [f, 0, width / 2, 0, 0, f, height / 2, 0, 0, 0, 1, 0]})  # fmt: skip
            writer.write_message(topic="/camera/depth/image", schema=image, log_time=stamp, publish_time=stamp,
                                 message={"header": header, "height": height, "width": width, "encoding": "16UC1",
                                          "is_bigendian": 0, "step": 2 * width, "data": pixels})  # fmt: skip
        writer.finish()
    return path


def cases(work: Path) -> list[tuple[str, list[str] | Callable[[], list[str]]]]:
    """(name, argv after ``relpoint``) of every case; files are made in ``work`` on first use."""
    sample = work / "figure8.mcap"
    shutil.copy(REPO / "sample_logs" / "figure8.mcap", sample)
    small = SimulationConfig(iterations=200, density=25, seed=3, odometry_noise=0.05)

    def user_dir() -> list[str]:
        (work / "user" / "sub").mkdir(parents=True, exist_ok=True)
        (work / "user" / "notes.txt").write_text("mine")
        (work / "user" / "sub" / "y.txt").write_text("mine")
        return ["run", str(sample), "-e", "ekf", "-o", str(work / "user")]

    def a_run() -> Path:
        out = work / "a-run"
        if not out.exists():
            subprocess.run([sys.executable, "-m", "relpoint_cli.main", "-q", "run", str(sample), "-e", "ekf", "-o",
                            str(out)], check=False, cwd=REPO, stderr=subprocess.DEVNULL)  # fmt: skip
        return out

    def file_in(name: str, content: bytes) -> Path:
        path = work / name
        path.write_bytes(content)
        return path

    def symlink() -> list[str]:
        (work / "real").mkdir(exist_ok=True)
        link = work / "link"
        if not link.is_symlink():
            link.symlink_to(work / "real")
        return ["run", str(sample), "-e", "ekf", "-o", str(link)]

    def dangling() -> list[str]:
        link = work / "dangling"
        if not link.is_symlink():
            link.symlink_to(work / "nowhere")
        return ["run", str(sample), "-e", "ekf", "-o", str(link)]

    def hostile(name: str, **kwargs: object) -> Path:
        path = work / f"{name}.mcap"
        if not path.exists():
            config = kwargs.pop("config", small)
            write_log(path, config, **kwargs)  # type: ignore[arg-type]
        return path

    bomb = lambda: file_in("bomb.yaml", ALIAS_BOMB.encode())  # noqa: E731
    out = str(work / "out")
    return [
        ("run -o a directory of user files", user_dir),
        ("run -o the log's own directory", ["run", str(sample), "-e", "ekf", "-o", str(work)]),
        ("fuse -o its own run directory", lambda: ["fuse", str(a_run()), "--log", str(sample), "-o", str(a_run())]),
        ("evaluate --json its estimate", lambda: ["evaluate", str(a_run() / "trajectory.tum"), "--reference",
                                                  str(sample), "--json", str(a_run() / "trajectory.tum")]),
        ("export a.tum -o a.tum", lambda: ["export", str(a_run() / "trajectory.tum"), "-o",
                                           str(a_run() / "trajectory.tum")]),
        ("run -o a symlink", symlink),
        ("run -o a dangling symlink", dangling),
        ("run -o / (EBUSY)", ["run", str(sample), "-e", "ekf", "-o", "/"]),
        ("run -o unwritable (/proc)", ["run", str(sample), "-e", "ekf", "-o", "/proc/relpoint-out"]),
        ("run --config alias bomb (relpoint)", lambda: ["run", str(sample), "-e", "relpoint", "-o", out,
                                                        "--config", str(bomb())]),
        ("run --config alias bomb (dense)", lambda: ["run", str(sample), "-e", "dense", "-o", out,
                                                     "--config", str(bomb())]),
        ("run --config /dev/zero", ["run", str(sample), "-e", "ekf", "-o", out, "--config", "/dev/zero"]),
        ("run --config binary.toml", lambda: ["run", str(sample), "-e", "ekf", "-o", out, "--config",
                                              str(file_in("binary.toml", bytes(range(256)) * 64))]),
        ("--param observation_sigma=1e308", ["run", str(sample), "-e", "ekf", "-o", out, "--param",
                                             "observation_sigma=1e308"]),
        ("--param ring_size=1e8", ["run", str(sample), "-e", "relpoint", "-o", out, "--param", "ring_size=1e8"]),
        ("--param particles=1e7", ["run", str(sample), "-e", "fastslam", "-o", out, "--param", "particles=1e7"]),
        ("--param variant=1.0 (fastslam)", ["run", str(sample), "-e", "fastslam", "-o", out, "--param", "variant=1.0",
                                            "--param", "particles=5"]),
        ("--param ring_size=true", ["run", str(sample), "-e", "relpoint", "-o", out, "--param", "ring_size=true"]),
        ("simulate --iterations 100000000", ["simulate", "-o", str(work / "s.mcap"), "--iterations", "100000000"]),
        ("simulate --rate 1e-300", ["simulate", "-o", str(work / "s.mcap"), "--rate", "1e-300"]),
        ("5,000,000-point cloud", lambda: ["run", str(huge_cloud_log(work / "huge.mcap", 5_000_000)), "-e", "ekf",
                                           "-o", out]),
        ("10000x10000 depth image", lambda: ["run", str(depth_log(work / "big-depth.mcap", 10_000, 10_000)), "-e",
                                             "dense", "-o", out]),
        ("1x1 depth image", lambda: ["run", str(depth_log(work / "tiny-depth.mcap", 1, 1)), "-e", "dense", "-o", out]),
        *[(f"1e30 point in every cloud ({name})", lambda name=name: ["run", str(hostile("far", spoil=far_point())),
                                                                     "-e", name, "-o", out])
          for name in ("relpoint", "ekf", "fastslam")],
        *[(f"10-year stamp gap ({name})", lambda name=name: ["run", str(hostile("gap", spoil=time_gap(100, 3.156e8),
                                                                                odometry=True)), "-e", name, "-o", out])
          for name in ("ekf", "fastslam")],
        ("100,000 one-point clouds (relpoint)", lambda: ["run", str(hostile(
            "one", config=SimulationConfig(iterations=100_000, density=25, seed=3, scenario="corridor", step=0.012),
            spoil=one_point)), "-e", "relpoint", "-o", out]),
        ("info LOG | head -c 10", ["info", str(sample)]),
    ]


def run_case(source: Path, argv: list[str], timeout: float, memory_gb: float, close_stdout: bool) -> tuple:
    """(exit code or 'killed', last stderr line, peak RSS MB, seconds) of one command line."""
    limit = int(memory_gb * 2**30)

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    env = {**os.environ, "PYTHONPATH": str(source)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    process = subprocess.Popen([sys.executable, "-m", "relpoint_cli.main", *argv], cwd=source, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=cap)  # fmt: skip
    try:
        if close_stdout:
            assert process.stdout is not None
            process.stdout.read(10)
            process.stdout.close()
            err = process.stderr.read() if process.stderr else b""
            process.wait(timeout=timeout)
        else:
            _, err = process.communicate(timeout=timeout)
        code: object = process.returncode
    except subprocess.TimeoutExpired:
        process.kill()
        _, err = process.communicate()
        code = f"killed after {timeout:.0f} s"
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    lines = [line for line in err.decode(errors="replace").splitlines() if line.strip()]
    last = lines[-1] if lines else ""
    if len(last) > 110:
        last = last[:107] + "..."
    # ru_maxrss of children is the largest so far: report it only when this case raised it.
    return code, last, (peak / 1024 if peak > before else float("nan")), seconds, len(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=REPO, help="checkout to run (default: this one)")
    parser.add_argument("--timeout", type=float, default=180.0)
    parser.add_argument("--memory-gb", type=float, default=8.0)
    parser.add_argument("--only", help="comma-separated parts of case names")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="relpoint-hostile-"))
    try:
        selected = [c for c in cases(work) if not args.only or any(p in c[0] for p in args.only.split(","))]
        # Peak memory comes from RUSAGE_CHILDREN, a running maximum, so each case runs under a fresh
        # helper interpreter that reports its own child's maximum.
        print(f"source: {args.source}  (memory cap {args.memory_gb:g} GB, timeout {args.timeout:g} s)")
        print("| case | exit | stderr lines | last stderr line | peak MB | s |")
        print("|---|---|---|---|---|---|")
        for name, argv in selected:
            # The code before the fix deletes the log's directory in one case: every case starts from the log.
            work.mkdir(exist_ok=True)
            if not (work / "figure8.mcap").exists():
                shutil.copy(REPO / "sample_logs" / "figure8.mcap", work / "figure8.mcap")
            argv = argv() if callable(argv) else argv
            code, last, peak, seconds, n_lines = isolated(args, argv, name.startswith("info"))
            print(f"| {name} | {code} | {n_lines} | {last.replace('|', '/')} | {peak:.0f} | {seconds:.1f} |", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def isolated(args: argparse.Namespace, argv: list[str], close_stdout: bool) -> tuple:
    """Run one case from a fresh helper interpreter, so the peak memory is that case's alone."""
    code = (
        f"import sys, json; sys.path.insert(0, {str(REPO)!r}); from benchmarks.hostile import run_case;"
        f"from pathlib import Path; r = run_case(Path({str(args.source)!r}), json.loads(sys.argv[1]), {args.timeout!r},"
        f" {args.memory_gb!r}, {close_stdout!r}); print(json.dumps(list(map(str, r))))"
    )
    import json

    out = subprocess.run([sys.executable, "-c", code, json.dumps(argv)], capture_output=True, text=True, check=False)
    if out.returncode != 0:
        lines = out.stderr.strip().splitlines()
        return "harness failed", lines[-1] if lines else "", float("nan"), 0.0, 0
    result = json.loads(out.stdout.strip().splitlines()[-1])
    return result[0], result[1], float(result[2]), float(result[3]), int(result[4])


if __name__ == "__main__":
    main()
