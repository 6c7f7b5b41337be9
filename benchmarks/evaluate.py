"""Whole-process time of ``relpoint evaluate`` against ``evo_ape`` on a 20,000-pose TUM pair (issue 3, Speed).

The reference is relpoint's simulated figure eight (``relpoint.simulation``, 20 passes at 10 Hz, so
20,000 poses); the estimate is the same path with a seeded random-walk drift, position noise,
orientation noise, a rigid offset and a stamp jitter of up to 2 ms (inside the 0.01 s matching
tolerance), as a long run of an estimator would give. Both are written as TUM files, then

    relpoint evaluate EST --reference REF --align se3 --json OUT
    evo_ape tum REF EST -a

are run as subprocesses, alternately, ``--repeat`` times each (start-up, imports, file parsing and all);
the best wall and CPU (user + system) time of each, both ATE RMSE figures and the ratios are printed. relpoint also computes the RPE
and the KITTI segment errors in that time; evo_ape computes only the APE.

    .venv/bin/python benchmarks/evaluate.py [--poses 20000] [--repeat 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from formats.trajectory_files import write_tum
from relpoint.simulation import SimulationConfig, simulate
from relpoint.types import Trajectory


def make_pair(n: int, rng: np.random.Generator) -> tuple[Trajectory, Trajectory]:
    """(reference, estimate) of ``n`` poses: a simulated figure eight and a drifting, noisy, offset copy."""
    config = SimulationConfig(scenario="figure8", passes=max(1, -(-n // 1000)), iterations=n, seed=1)
    reference = simulate(config).ground_truth
    drift = np.cumsum(rng.normal(scale=2e-3, size=(n, 3)), axis=0)
    offset = Rotation.from_rotvec([0.02, -0.01, 0.3])
    positions = offset.apply(reference.positions + drift + rng.normal(scale=0.02, size=(n, 3)))
    positions += np.array([1.0, -2.0, 0.5])
    quats = (
        offset * Rotation.from_quat(reference.quats_xyzw) * Rotation.from_rotvec(rng.normal(scale=0.005, size=(n, 3)))
    )
    jitter = rng.integers(-2_000_000, 2_000_001, size=n)
    return reference, Trajectory(reference.stamps_ns + jitter, positions, quats.as_quat())


def tool(name: str) -> str:
    """The console script ``name`` beside this interpreter (the project's venv), else on PATH."""
    beside = Path(sys.executable).parent / name
    found = str(beside) if beside.is_file() else shutil.which(name)
    if found is None:
        sys.exit(f"{name} not found beside {sys.executable} or on PATH")
    return found


def timed(command: list[str]) -> tuple[float, float, str]:
    """Wall time and CPU time (user + system) of running ``command`` to completion, and its stdout.

    The CPU time is less sensitive than the wall time to other load on the machine. Exits if the command fails.
    """
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return seconds, cpu, done.stdout


def evo_rmse(stdout: str) -> float:
    match = re.search(r"^\s*rmse\s+([-+0-9.eE]+)\s*$", stdout, flags=re.MULTILINE)
    if match is None:
        sys.exit(f"no rmse in evo_ape's output:\n{stdout}")
    return float(match.group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keep", type=Path, help="Write the TUM pair here and keep it (default: a temporary dir).")
    args = parser.parse_args()

    reference, estimate = make_pair(args.poses, np.random.default_rng(args.seed))
    with tempfile.TemporaryDirectory() as scratch:
        directory = args.keep or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        ref, est, summary = directory / "reference.tum", directory / "estimate.tum", directory / "relpoint.json"
        write_tum(ref, reference)
        write_tum(est, estimate)
        relpoint_cmd = [tool("relpoint"), "evaluate", str(est), "--reference", str(ref), "--align", "se3"]
        relpoint_cmd += ["--json", str(summary)]
        evo_cmd = [tool("evo_ape"), "tum", str(ref), str(est), "-a"]
        env_note = os.environ.get("OMP_NUM_THREADS", "unset")
        print(f"{args.poses} poses, {ref.stat().st_size / 1e6:.1f} MB per TUM file; OMP_NUM_THREADS={env_note}")
        print("relpoint:", " ".join(relpoint_cmd[1:]))
        print("evo:     ", " ".join(evo_cmd[1:]))

        times: dict[str, list[float]] = {"relpoint": [], "evo_ape": []}
        cpu: dict[str, list[float]] = {"relpoint": [], "evo_ape": []}
        rmse: dict[str, float] = {}
        for _ in range(args.repeat):
            seconds, cpu_seconds, _ = timed(relpoint_cmd)
            times["relpoint"].append(seconds)
            cpu["relpoint"].append(cpu_seconds)
            rmse["relpoint"] = json.loads(summary.read_text())["summary"]["ate_rmse"]
            seconds, cpu_seconds, stdout = timed(evo_cmd)
            times["evo_ape"].append(seconds)
            cpu["evo_ape"].append(cpu_seconds)
            rmse["evo_ape"] = evo_rmse(stdout)

    best = {name: min(values) for name, values in times.items()}
    for name in ("relpoint", "evo_ape"):
        runs = ", ".join(f"{t:.2f}" for t in times[name])
        print(
            f"{name:<9} best {best[name]:6.2f} s wall  (runs {runs})  best {min(cpu[name]):5.2f} s CPU"
            f"  ATE rmse {rmse[name]:.6f} m"
        )
    agree = abs(rmse["relpoint"] - rmse["evo_ape"]) <= 1e-6 * max(1.0, abs(rmse["evo_ape"]))
    print(f"ATE rmse agree to 1e-6 (evo prints 6 decimals): {'yes' if agree else 'NO'}")
    print(f"evo_ape / relpoint wall time: {best['evo_ape'] / best['relpoint']:.2f}x (above 1: relpoint is faster)")
    print(f"evo_ape / relpoint CPU time:  {min(cpu['evo_ape']) / min(cpu['relpoint']):.2f}x")


if __name__ == "__main__":
    main()
