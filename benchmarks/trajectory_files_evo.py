"""``relpoint evaluate`` beside ``evo_ape`` / ``evo_rpe`` on the trajectory files evo reads (issue 16).

Files are built from the real TUM fr1/xyz trajectories of ``../shared/data/evo-fr1xyz`` (ground truth,
3000 poses; RGBD-SLAM estimate, 788 poses):

* ``tum-repeats-ref``: the ground truth with a copy 5 cm off after every 40th row an estimate stamp
  matches (a repeated stamp), plus comments and blank lines for relpoint (evo's reader refuses blank
  lines, so evo reads the same rows without them);
* ``tum-repeats-est``: the estimate with a copy 3 cm off after every 50th row;
* ``euroc``: the ground truth as EuRoC ``state_groundtruth_estimate0/data.csv`` (nanoseconds, w-first
  quaternion, three velocity columns) against the TUM estimate (``evo_ape euroc``);
* ``kitti-times``: both as KITTI poses with times files; evo's ``kitti`` mode has no times, so evo's
  figures are ``evo_ape tum`` on the original TUM files;
* ``kitti-index``: the evo-associated pair (788 poses each) as KITTI poses without times
  (``evo_ape kitti``, pairing by index).

Each case runs ``relpoint evaluate EST -r REF --align se3 --json`` and ``evo_ape MODE REF EST -a`` plus
``evo_rpe MODE REF EST`` (translation, and ``-r angle_deg``; delta 1 frame) with ``--save_results``,
whose full-precision statistics are printed beside relpoint's, with the largest difference.

    .venv/bin/python benchmarks/trajectory_files_evo.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from formats.trajectory_files import parse_stamp_ns, read_tum, write_kitti
from relpoint.evaluation import AlignMode, EvaluationSettings, evaluate_trajectory
from relpoint.types import Trajectory

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "evo-fr1xyz"
GT, EST = "freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt"
STATS = ("rmse", "mean", "median", "std", "min", "max")


def tool(name: str) -> str:
    """The console script ``name`` beside this interpreter (the project's venv), else on PATH."""
    beside = Path(sys.executable).parent / name
    found = str(beside) if beside.is_file() else shutil.which(name)
    if found is None:
        sys.exit(f"{name} not found beside {sys.executable} or on PATH")
    return found


def run(command: list[str]) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()}")
    return done


def rows(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


def moved(row: str, dx: float) -> str:
    fields = row.split()
    return " ".join([fields[0], repr(float(fields[1]) + dx), *fields[2:]])


def with_copies(data_rows: list[str], every: set[int], dx: float) -> list[str]:
    out = []
    for k, row in enumerate(data_rows):
        out.append(row)
        if k in every:
            out.append(moved(row, dx))
    return out


def matched_rows(gt_rows: list[str], est_rows: list[str]) -> list[int]:
    """Index of the nearest ground-truth row of each estimate row."""
    gt_t = np.array([float(r.split()[0]) for r in gt_rows])
    est_t = np.array([float(r.split()[0]) for r in est_rows])
    nearest = np.clip(np.searchsorted(gt_t, est_t), 1, len(gt_t) - 1)
    return (nearest - ((est_t - gt_t[nearest - 1]) <= (gt_t[nearest] - est_t))).tolist()


def build(directory: Path) -> dict[str, dict[str, object]]:
    """Write every case's files into ``directory``; returns, per case, relpoint's and evo's arguments."""
    gt_rows, est_rows = rows(DATA / GT), rows(DATA / EST)
    est = directory / "est.txt"
    est.write_text("\n".join(est_rows) + "\n")
    cases: dict[str, dict[str, object]] = {}

    ref_rows = with_copies(gt_rows, set(matched_rows(gt_rows, est_rows)[::40]), 0.05)
    ours, theirs = directory / "gt-repeats-relpoint.txt", directory / "gt-repeats-evo.txt"
    ours.write_text("# repeated stamps, comments and a blank line\n\n" + "\n# comment\n".join(ref_rows) + "\n")
    theirs.write_text("\n".join(ref_rows) + "\n")
    cases["tum-repeats-ref"] = {"relpoint": [est, "-r", ours], "evo": ["tum", theirs, est]}

    est_repeats = directory / "est-repeats.txt"
    est_repeats.write_text("\n".join(with_copies(est_rows, set(range(7, len(est_rows), 50)), -0.03)) + "\n")
    cases["tum-repeats-est"] = {"relpoint": [est_repeats, "-r", DATA / GT], "evo": ["tum", DATA / GT, est_repeats]}

    csv = directory / "state_groundtruth_estimate0" / "data.csv"
    csv.parent.mkdir(exist_ok=True)
    lines = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1]"]  # fmt: skip
    for row in gt_rows:
        stamp, x, y, z, qx, qy, qz, qw = row.split()
        lines.append(",".join([str(parse_stamp_ns(stamp)), x, y, z, qw, qx, qy, qz, "0.1", "-0.2", "0.3"]))
    csv.write_text("\n".join(lines) + "\n")
    cases["euroc"] = {"relpoint": [est, "-r", csv], "evo": ["euroc", csv, est]}

    kitti = {}
    for name in (GT, EST):
        poses, times = directory / f"{name}.kitti", directory / f"{name}.times"
        write_kitti(poses, read_tum(DATA / name), times)
        kitti[name] = (poses, times)
    cases["kitti-times"] = {
        "relpoint": [kitti[EST][0], "--times", kitti[EST][1], "-r", kitti[GT][0], "--reference-times", kitti[GT][1]],
        "evo": ["tum", DATA / GT, est],
    }

    gt_traj, est_traj = read_tum(DATA / GT), read_tum(DATA / EST)
    nearest = matched_rows(gt_rows, est_rows)
    # Each estimate pose and its nearest ground-truth pose, the i-th of each file.
    ref_index, est_index = directory / "ref-index.kitti", directory / "est-index.kitti"

    def subset(traj: Trajectory, index: list[int]) -> Trajectory:
        stamps = np.arange(len(index), dtype=np.int64) * 1_000_000_000
        return Trajectory(stamps, traj.positions[index], traj.quats_xyzw[index])

    write_kitti(ref_index, subset(gt_traj, nearest))
    write_kitti(est_index, subset(est_traj, list(range(len(est_rows)))))
    cases["kitti-index"] = {"relpoint": [est_index, "-r", ref_index], "evo": ["kitti", ref_index, est_index]}
    return cases


def drop_copies_ate(directory: Path, keep: str) -> float:
    """relpoint's ATE rmse (SE(3)) of ``tum-repeats-ref`` with only the first or last copy of each stamp."""
    ref_rows = rows(directory / "gt-repeats-evo.txt")
    stamps = [r.split()[0] for r in ref_rows]
    if keep == "first":
        kept = [r for i, r in enumerate(ref_rows) if i == 0 or stamps[i - 1] != stamps[i]]
    else:
        kept = [r for i, r in enumerate(ref_rows) if i + 1 == len(ref_rows) or stamps[i + 1] != stamps[i]]
    path = directory / f"gt-keep-{keep}.txt"
    path.write_text("\n".join(kept) + "\n")
    reference, estimate = read_tum(path), read_tum(directory / "est.txt")
    return evaluate_trajectory(reference, estimate, EvaluationSettings(align=AlignMode.SE3)).summary["ate_rmse"]


def evo_stats(directory: Path, name: str, command: str, args: list[object], extra: list[str]) -> dict[str, float]:
    from evo.tools import file_interface

    zip_path = directory / f"{name}-{command}-{'-'.join(extra) or 'trans'}.zip"
    zip_path.unlink(missing_ok=True)
    run([tool(command), *map(str, args), *extra, "--save_results", str(zip_path), "--no_warnings"])
    return {k: float(v) for k, v in file_interface.load_res_file(str(zip_path)).stats.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, help="Write the files here and keep them (default: a temporary dir).")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"{DATA.name} is not beside the checkout (../shared/data)")
    with tempfile.TemporaryDirectory() as scratch:
        directory = args.keep or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        worst = 0.0
        for name, case in build(directory).items():
            out = directory / f"{name}.json"
            done = run([tool("relpoint"), "evaluate", *map(str, case["relpoint"]), "--align", "se3",
                        "--json", str(out), "--overwrite"])  # fmt: skip
            summary = json.loads(out.read_text())["summary"]
            evo = {
                "ate": evo_stats(directory, name, "evo_ape", case["evo"], ["-a"]),
                "rpe_trans": evo_stats(directory, name, "evo_rpe", case["evo"], []),
                "rpe_rot_deg": evo_stats(directory, name, "evo_rpe", case["evo"], ["-r", "angle_deg"]),
            }
            print(f"\n{name}: {summary['matched_poses']:.0f} matched of {summary['reference_poses']:.0f} reference, "
                  f"{summary['estimate_poses']:.0f} estimate poses")  # fmt: skip
            for line in done.stderr.strip().splitlines():
                print(f"  stderr: {line}")
            print(f"  {'figure':<20}{'relpoint':>14}{'evo 1.38':>14}{'difference':>12}")
            for prefix, stats in evo.items():
                for stat in STATS:
                    ours, theirs = summary[f"{prefix}_{stat}"], stats[stat]
                    worst = max(worst, abs(ours - theirs))
                    print(f"  {prefix + '_' + stat:<20}{ours:14.9f}{theirs:14.9f}{ours - theirs:12.1e}")
        print(f"\nlargest difference over every figure: {worst:.1e} (required: at most 1e-6)")
        print("tum-repeats-ref if one copy of each repeated stamp were dropped instead (ATE rmse, evo's above):")
        for keep in ("first", "last"):
            print(f"  keeping the {keep} copy: {drop_copies_ate(directory, keep):.9f} m")


if __name__ == "__main__":
    main()
