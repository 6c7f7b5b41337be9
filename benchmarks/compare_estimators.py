"""A ``relpoint compare`` table of the three landmark estimators on one log, with the time of every step.

Each step is the real command line in its own process (as a user types it), timed by wall clock and
by the CPU of the child (user + system), then the table (Markdown) and the comparison figure are
written to ``--out``:

    python benchmarks/compare_estimators.py                               # sample_logs/figure8.mcap
    python benchmarks/compare_estimators.py --log run.mcap --estimators relpoint,ekf --align se3
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def timed(command: list[str]) -> tuple[float, float]:
    """Run ``command``; its (wall, CPU) seconds. Exits with the command's output if it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    completed = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if completed.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({completed.returncode}): {completed.stderr.strip()}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--log", type=Path, default=REPO / "sample_logs" / "figure8.mcap")
    parser.add_argument("--estimators", default="relpoint,ekf,fastslam")
    parser.add_argument("--align", default="none")
    parser.add_argument("--out", type=Path, default=Path("compare-estimators"))
    args = parser.parse_args()
    relpoint = shutil.which("relpoint", path=os.path.dirname(sys.executable)) or "relpoint"
    args.out.mkdir(parents=True, exist_ok=True)
    runs, labels = [], []
    print(f"{'step':<48} {'wall s':>8} {'cpu s':>8}")
    for name in args.estimators.split(","):
        out = args.out / name
        command = [relpoint, "-q", "run", str(args.log), "--estimator", name, "-o", str(out), "--overwrite"]
        wall, cpu = timed(command)
        print(f"{'relpoint run ' + args.log.name + ' --estimator ' + name:<48} {wall:>8.1f} {cpu:>8.1f}")
        runs.append(str(out))
        labels += ["--label", name]
    table, figure = args.out / "table.md", args.out / "compare.png"
    command = [relpoint, "compare", *runs, *labels, "--reference", str(args.log), "--align", args.align,
               "-o", str(table), "--plot", str(figure), "--overwrite"]  # fmt: skip
    wall, cpu = timed(command)
    print(f"{f'relpoint compare ({len(runs)} runs, table + figure)':<48} {wall:>8.1f} {cpu:>8.1f}")
    print()
    print(table.read_text(), end="")
    print(f"\nfigure: {figure}")


if __name__ == "__main__":
    main()
