"""Wall-time speed-up of ``relpoint batch --jobs 2`` over ``--jobs 1`` for an 8-job plan (issue 9).

Simulates two figure-eight logs once (not timed), then runs the same plan of 8 jobs
(2 logs x ekf, fastslam x a 2-value grid; each job runs, writes its directory and evaluates) as
``relpoint batch PLAN --jobs N`` in a fresh process, alternating N = 1 and 2, each into a fresh
results root. Prints every time, the medians and their ratio, and the load average: on a busy shared
machine the wall-time ratio falls short of the core count, so it also prints the jobs' CPU seconds
divided by the batch's wall time ("cores used"), and, as a yardstick of what the machine allows right
now, the speed-up of a pure-Python CPU burn on process pools of 1 and 2 workers.

Usage::

    python benchmarks/batch.py [--iterations 200] [--density 25] [--repeats 2] [--dask]

Before timing, relpoint's own packages are byte-compiled in place (``compileall``), as pip does when
it installs a package: an editable checkout run with ``PYTHONDONTWRITEBYTECODE=1`` (or ``python -B``,
as multiprocessing starts its fork server) otherwise compiles its sources again in every process,
about 0.1 s on the way to the first job. ``--no-compile`` measures the checkout as it is.

With ``--dask`` the same plan runs on a Dask ``LocalCluster`` of one and of two worker processes
(each started before its timed run and closed after it, preloading :mod:`relpoint_app.worker_warmup`
as ``dask worker --preload relpoint_app.worker_warmup`` does) through ``relpoint batch --scheduler``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

PLAN = """\
logs = ["logs/*.mcap"]

[estimators.ekf.grid]
observation_sigma = [0.3, 0.5]

[estimators.fastslam]
particles = {particles}
[estimators.fastslam.grid]
seed = [0, 1]

[evaluation]
align = "se3"
"""


def run_batch(plan: Path, jobs: int, results: Path, scheduler: str | None = None) -> tuple[float, float, float]:
    """Wall seconds of one ``relpoint batch`` process, the CPU seconds its jobs report and the sum of their
    wall seconds; with ``scheduler`` the jobs go to that Dask cluster instead of a local pool of ``jobs``
    workers."""
    where = ["--scheduler", scheduler] if scheduler is not None else ["--jobs", str(jobs)]
    command = [sys.executable, "-m", "relpoint_cli.main", "-q", "batch", str(plan), *where,
               "--results", str(results)]  # fmt: skip
    start = time.perf_counter()
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if completed.returncode != 0:
        raise SystemExit(f"batch --jobs {jobs} failed ({completed.returncode}):\n{completed.stdout}{completed.stderr}")
    rows = json.loads((results / "results.json").read_text())["jobs"]
    return seconds, sum(row["cpu_seconds"] for row in rows), sum(row["wall_seconds"] for row in rows)


@contextlib.contextmanager
def _cluster(workers: int) -> Iterator[str | None]:
    """The address of a Dask ``LocalCluster`` of ``workers`` processes, one thread each, started before
    the timed run (as a cluster would be) with the warm-up preloaded, and closed after it, so that no
    other cluster's scheduler and workers share the cores meanwhile; None (the local pool) for 0."""
    if not workers:
        yield None
        return
    from distributed import LocalCluster

    from relpoint_app.batch_start import WARMUP_MODULE

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, preload=[WARMUP_MODULE]) as cluster:  # fmt: skip
        yield cluster.scheduler_address


def _burn(n: int) -> float:
    start = time.process_time()
    total = 0
    for i in range(n):
        total += i * i
    return time.process_time() - start


def burn_speedup(n: int = 10_000_000, tasks: int = 4) -> float:
    """Wall-time ratio of ``tasks`` CPU-bound tasks on 1 worker over 2 workers (2.0 on two idle cores)."""
    walls = []
    for workers in (1, 2):
        start = time.perf_counter()
        with concurrent.futures.ProcessPoolExecutor(workers) as pool:
            list(pool.map(_burn, [n] * tasks))
        walls.append(time.perf_counter() - start)
    return walls[0] / walls[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=200, help="iterations per simulated log")
    parser.add_argument("--density", type=float, default=25.0)
    parser.add_argument("--particles", type=int, default=20, help="FastSLAM particles")
    parser.add_argument("--repeats", type=int, default=2, help="timed runs per --jobs value")
    parser.add_argument(
        "--dask", action="store_true", help="run the plan on a Dask LocalCluster of 1 and of 2 workers instead"
    )
    parser.add_argument(
        "--no-compile", action="store_true", help="do not byte-compile relpoint's packages before timing"
    )
    args = parser.parse_args(argv)
    if not args.no_compile:
        import compileall

        root = Path(__file__).resolve().parents[1]
        for package in ("relpoint", "relpoint_app", "relpoint_cli", "formats"):
            compileall.compile_dir(root / package, quiet=1)
        print("bytecode: relpoint's packages byte-compiled in place before timing, as an installed package is")

    from relpoint.simulation import SimulationConfig, simulate
    from relpoint_app.simulation import write_simulation

    with tempfile.TemporaryDirectory(prefix="relpoint-batch-bench-") as tmp:
        root = Path(tmp)
        for seed in (1, 2):
            config = SimulationConfig(iterations=args.iterations, density=args.density, seed=seed)
            write_simulation(simulate(config), root / "logs" / f"fig8-{seed}.mcap")
        plan = root / "plan.toml"
        plan.write_text(PLAN.format(particles=args.particles))
        print(f"plan: 2 logs x {args.iterations} iterations (density {args.density:g}) x ekf, fastslam "
              f"({args.particles} particles) x 2 grid values = 8 jobs; {os.cpu_count()} cores")  # fmt: skip
        times: dict[int, list[float]] = {1: [], 2: []}
        outside: list[float] = []  # --jobs 1: the batch's wall time outside its jobs (start-up, wind-down)
        job_walls: list[float] = []
        for repeat in range(args.repeats):
            for jobs in (1, 2):
                with _cluster(jobs if args.dask else 0) as scheduler:
                    seconds, cpu, walls = run_batch(plan, jobs, root / f"results-{jobs}-{repeat}", scheduler)
                times[jobs].append(seconds)
                if jobs == 1:
                    outside.append(seconds - walls)
                    job_walls.append(walls)
                print(
                    f"  {'Dask workers' if args.dask else '--jobs'} {jobs}: {seconds:7.2f} s wall, jobs' CPU {cpu:6.2f} s, cores used {cpu / seconds:.2f}"
                    f"   (load average {os.getloadavg()[0]:.1f})"
                )
        one, two = statistics.median(times[1]), statistics.median(times[2])
        label = "Dask workers" if args.dask else "--jobs"
        print(f"median wall time {label} 1: {one:.2f} s, {label} 2: {two:.2f} s, speed-up {one / two:.2f}x")
        serial, work = statistics.median(outside), statistics.median(job_walls)
        print(f"  with 1 worker: {work:.2f} s in jobs, {serial:.2f} s outside them (start-up, plan, wind-down); "
              f"the jobs alone run {work / max(two - serial, 1e-9):.2f}x faster on 2 workers, and with this start-up "
              f"the most 2 workers can give is {(serial + work) / (serial + work / 2):.2f}x")  # fmt: skip
        print(f"yardstick: a pure-Python CPU burn runs {burn_speedup():.2f}x faster on 2 workers than on 1 just now")
    return 0


if __name__ == "__main__":
    sys.exit(main())
