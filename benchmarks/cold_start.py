"""First-run cost of a fresh install: cold against warm ``relpoint run``, start-up times, install size.

A *cold* run has an empty numba cache (``NUMBA_CACHE_DIR`` pointing at a new directory), as on a
fresh install or in a fresh CI container; a *warm* run repeats it with that cache filled. Each
command runs as a child process; its CPU time (user + sys, from ``wait4``) is what to compare,
since on a shared machine wall time mostly measures the neighbours. Both kernel modes are
measured: the kernels compiled ahead of time at install (the default) and ``RELPOINT_KERNELS=jit``
(compiled by numba on first call, the fallback when no compiler was at hand at install).

Usage: python benchmarks/cold_start.py [--log sample_logs/figure8.mcap] [--estimator relpoint] [--repeat 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def relpoint_command() -> list[str]:
    """The installed ``relpoint`` entry point beside this interpreter (or the same via ``-c``)."""
    script = Path(sysconfig.get_path("scripts")) / "relpoint"
    return [str(script)] if script.exists() else [sys.executable, "-c", "from relpoint_cli.main import main; main()"]


def measure(arguments: list[str], environment: dict[str, str]) -> tuple[float, float]:
    """(CPU seconds user + sys, wall seconds) of one child process; raises if it fails."""
    start = time.perf_counter()
    child = subprocess.Popen(arguments, env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"cold_start: {' '.join(arguments)} failed: {child.stderr.read().decode()[-500:]}")
    child.stderr.close()
    return usage.ru_utime + usage.ru_stime, wall


def directory_bytes(path: Path) -> int:
    """Bytes of the regular files under ``path`` (symbolic links not followed)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file() and not f.is_symlink())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", type=Path, default=ROOT / "sample_logs" / "figure8.mcap")
    parser.add_argument("--estimator", default="relpoint", help="the estimator of the runs (relpoint, fastslam, ...)")
    parser.add_argument("--repeat", type=int, default=2, help="warm runs and start-ups (the least CPU is kept)")
    args = parser.parse_args()
    relpoint = relpoint_command()
    print(f"{'command':52s} {'CPU s':>7s} {'wall s':>7s}")
    with tempfile.TemporaryDirectory(prefix="relpoint-cold-start-") as scratch:
        for mode in ("aot", "jit"):
            environment = dict(os.environ, NUMBA_CACHE_DIR=str(Path(scratch) / f"numba-cache-{mode}"))
            if mode == "jit":
                environment["RELPOINT_KERNELS"] = "jit"
            else:
                environment.pop("RELPOINT_KERNELS", None)
            run = [*relpoint, "run", str(args.log), "--estimator", args.estimator, "--overwrite", "-o"]
            cold = measure([*run, str(Path(scratch) / f"cold-{mode}")], environment)
            warm = min(measure([*run, str(Path(scratch) / f"warm-{mode}")], environment) for _ in range(args.repeat))
            print(f"{'run ' + args.log.name + ', kernels ' + mode + ', cold (empty cache)':52s} {cold[0]:7.2f} {cold[1]:7.2f}")
            print(f"{'run ' + args.log.name + ', kernels ' + mode + ', warm':52s} {warm[0]:7.2f} {warm[1]:7.2f}")
            print(f"{'  cold minus warm':52s} {cold[0] - warm[0]:7.2f} {cold[1] - warm[1]:7.2f}")
        environment = dict(os.environ, NUMBA_CACHE_DIR=str(Path(scratch) / "numba-cache-aot"))
        for label, arguments in (("relpoint --help", ["--help"]), ("relpoint info " + args.log.name, ["info", str(args.log)])):
            cpu, wall = min(measure([*relpoint, *arguments], environment) for _ in range(args.repeat))
            print(f"{label:52s} {cpu:7.2f} {wall:7.2f}")
    prefix = Path(sys.prefix)
    packages = Path(sysconfig.get_path("purelib"))
    sizes = sorted(((directory_bytes(p), p.name) for p in packages.iterdir() if p.is_dir()), reverse=True)
    print(f"install size: {directory_bytes(prefix) / 1e6:.0f} MB in {prefix}")
    print("largest packages: " + ", ".join(f"{name} {size / 1e6:.0f} MB" for size, name in sizes[:6]))


if __name__ == "__main__":
    main()
