"""``relpoint import``: RGB-D dataset folders (TUM RGB-D, 7-Scenes) to relpoint logs, and RGB-D
sequences (those folders or an RGB-D log) to point logs of tracked corners (``--points``)."""

from __future__ import annotations

import math
from pathlib import Path

import click

from formats.log import COMPRESSIONS, Topics
from relpoint.errors import InputError, UsageError
from relpoint.types import Intrinsics
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import input_path, overwrite_option, read_paths
from relpoint_cli.progress import progress_bar
from relpoint_cli.topics import topic_options, topics_from

EXAMPLES = """\b
Examples:
  relpoint import tum rgbd_dataset_freiburg1_xyz -o fr1_xyz.mcap
  relpoint import tum office_scan -o office.mcap --intrinsics 535.4,539.2,320.1,247.6
  relpoint import 7scenes redkitchen/seq-01 -o kitchen.mcap --count 400
  relpoint import 7scenes redkitchen/seq-01 -o kitchen_points.mcap --points
  relpoint import log kitchen.mcap -o kitchen_points.mcap --points --param max_corners=500
"""


def parse_intrinsics(text: str | None, width: int = 640, height: int = 480) -> Intrinsics | None:
    """``fx,fy,cx,cy`` (pixels) for a 640x480 camera."""
    if text is None:
        return None
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
        return Intrinsics(width, height, fx, fy, cx, cy)
    except ValueError:
        raise UsageError(f"--intrinsics {text!r} is not fx,fy,cx,cy in pixels") from None


def _tum_camera_note(folder: Path) -> str:
    """What the user is told of the camera a TUM import without ``--intrinsics`` assumes."""
    from formats.rgbd_import import TUM_CALIBRATION_FILE, TUM_CAMERAS, folder_calibration, tum_camera_number

    calibration = folder_calibration(folder)
    if calibration is not None:
        return (f"relpoint: the folder's {TUM_CALIBRATION_FILE} gives the intrinsics "
                f"({','.join(f'{v:g}' for v in calibration)}; --intrinsics sets others)")  # fmt: skip
    number = tum_camera_number(folder)
    if number is None:
        return ("relpoint: warning: no --intrinsics, and the folder's name does not say which TUM camera (freiburg1, "
                "2 or 3) recorded it: Freiburg 1's are used (wrong intrinsics bend every frame's points)")  # fmt: skip
    camera = TUM_CAMERAS[number]
    return (f"relpoint: the folder's name says Freiburg {number}: its camera's intrinsics are used "
            f"({camera.fx:g},{camera.fy:g},{camera.cx:g},{camera.cy:g}; --intrinsics sets others)")  # fmt: skip


#: What an import reads from a dataset folder: lists, poses, calibration and images (a log kept there is not).
_DATASET_SUFFIXES = frozenset({".txt", ".csv", ".png", ".jpg", ".jpeg"})


def _dataset_files(folder: Path) -> list[Path]:
    """The files an import may read: those of dataset kinds in ``folder`` and in its image folders (TUM keeps
    depth/ and rgb/ beside its lists). A log written into the folder is not one: it may be replaced."""
    image_folders = [path for path in folder.iterdir() if path.is_dir()]
    return [Path(path) for path in read_paths(folder, *image_folders)
            if Path(path).is_dir() or Path(path).suffix.lower() in _DATASET_SUFFIXES]  # fmt: skip


@click.command("import", epilog=EXAMPLES)
@click.argument("layout", type=click.Choice(["tum", "7scenes", "log"]))
@click.argument("source", type=input_path())
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The .mcap log to write."
)
@click.option(
    "--intrinsics",
    help="TUM: camera fx,fy,cx,cy in pixels (default: the folder's calibration.txt, as ETH3D's, else the Freiburg "
    "camera the folder is named after, else Freiburg 1).",
)
@click.option(
    "--tolerance",
    type=click.FloatRange(min=0.0, max=1e6),
    default=0.02,
    show_default=True,
    help="TUM: timestamp association tolerance, s.",
)
@click.option(
    "--depth-scale",
    type=click.FloatRange(min=0.0, min_open=True, max=1e9),
    default=5000.0,
    show_default=True,
    help="TUM: depth PNG units per metre (the benchmark's 5000; 1000 for millimetres).",
)
@click.option(
    "--rate", type=click.FloatRange(min=0.0, min_open=True, max=1e6), default=30.0, show_default=True,
    help="7-Scenes: frames per second (the stamps are nanoseconds: at most 1e6).",
)  # fmt: skip
@click.option(
    "--first", type=click.IntRange(min=0), default=0, show_default=True, help="7-Scenes: first frame to import."
)
@click.option("--count", type=click.IntRange(min=1), help="7-Scenes: number of frames (default: all).")
@click.option(
    "--points", is_flag=True,
    help="Write tracked corners as /points (with the ground truth) instead of the images: a log for relpoint, ekf "
    "and fastslam. See docs/keypoints.md.",
)  # fmt: skip
@click.option(
    "--param", "params", multiple=True, metavar="KEY=VALUE",
    help="With --points: a keypoint setting (max_corners, min_distance, forward_backward_px, depth_jump, ...); repeatable.",
)  # fmt: skip
@click.option("--compression", type=click.Choice(sorted(COMPRESSIONS)), default="zstd", show_default=True)
@topic_options
@overwrite_option
@click.pass_context
@handle_errors
def import_command(
    ctx: click.Context, layout: str, source: Path, output: Path, intrinsics: str | None, tolerance: float,
    depth_scale: float, rate: float, first: int, count: int | None, points: bool, params: tuple[str, ...],
    compression: str, overwrite: bool, **topic_params: str,
) -> None:  # fmt: skip
    """Convert an RGB-D SOURCE in LAYOUT to a relpoint log.

    LAYOUT is tum or 7scenes (SOURCE a dataset folder), or log (SOURCE an RGB-D relpoint log; needs
    --points). With --points the log holds tracked corners in the camera frame with persistent track
    ids, and the ground-truth poses; without it, depth and colour images for the dense estimator.
    The log is written atomically; an existing OUTPUT is replaced only when relpoint wrote it (or with
    --overwrite), and never when it is one of SOURCE's files.
    """
    if not math.isfinite(tolerance):
        raise UsageError(f"--tolerance must be a number of seconds, got {tolerance}", "the default is 0.02")
    from formats.outputs import check_output_file
    from formats.rgbd_import import import_7scenes, import_tum

    if layout != "log":
        if not source.is_dir():
            problem = "not a folder" if source.exists() else "no such folder"
            raise InputError(f"{source}: {problem}", f"give the {layout} dataset's folder")
        check_output_file(output, inputs=_dataset_files(source), overwrite=overwrite)
    else:
        check_output_file(output, inputs=read_paths(source), overwrite=overwrite)

    if layout == "log" and not points:
        raise UsageError("an RGB-D log is already a relpoint log", "add --points to track its corners into /points")
    if params and not points:
        raise UsageError("--param sets keypoint settings and needs --points")
    source_of = ctx.get_parameter_source
    applies = {"intrinsics": "tum", "tolerance": "tum", "depth_scale": "tum", "rate": "7scenes", "first": "7scenes",
               "count": "7scenes"}  # fmt: skip
    ignored = [name for name, only in applies.items()
               if layout != only and source_of(name) is click.core.ParameterSource.COMMANDLINE]  # fmt: skip
    if ignored:
        names = ", ".join(f"--{name.replace('_', '-')}" for name in ignored)
        raise UsageError(f"{names} {'does' if len(ignored) == 1 else 'do'} not apply to the {layout} layout",
                         "see relpoint import --help: each option names the layouts it applies to")  # fmt: skip
    if layout == "tum" and intrinsics is None and not ctx.find_root().obj.get("quiet"):
        click.echo(_tum_camera_note(source), err=True)
    if points:
        _import_points(ctx, layout, source, output, intrinsics, tolerance, depth_scale, rate, first, count, params,
                       compression, topics_from(topic_params))  # fmt: skip
        return
    folder = source
    with progress_bar(None, f"import {layout}", unit="frame") as bar:
        if layout == "tum":
            counts = import_tum(
                folder, output, intrinsics=parse_intrinsics(intrinsics), tolerance=tolerance,
                depth_scale=depth_scale, compression=compression, on_frame=lambda _: bar.update(1),
            )  # fmt: skip
        else:
            counts = import_7scenes(
                folder, output, rate=rate, first=first, count=count, compression=compression,
                on_frame=lambda _: bar.update(1),
            )  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        click.echo(
            f"wrote {output}: {counts.depth} depth frames, {counts.color} colour images, "
            f"{counts.ground_truth_pose} ground-truth poses, {counts.skipped_depth} depth images skipped"
            + (f", {counts.skipped_color} unreadable colour images left out" if counts.skipped_color else ""),
            err=True,
        )


def _import_points(
    ctx: click.Context, layout: str, source: Path, output: Path, intrinsics: str | None, tolerance: float,
    depth_scale: float, rate: float, first: int, count: int | None, params: tuple[str, ...], compression: str,
    topics: Topics,
) -> None:  # fmt: skip
    from formats.rgbd_import import seven_scenes_frames, tum_frames
    from relpoint.frontend import KeypointSettings
    from relpoint_app.keypoint_import import log_frames, write_keypoint_log

    settings = KeypointSettings.from_strings(params)
    if layout == "tum":
        frames = tum_frames(source, intrinsics=parse_intrinsics(intrinsics), tolerance=tolerance,
                            depth_scale=depth_scale)  # fmt: skip
    elif layout == "7scenes":
        frames = seven_scenes_frames(source, rate=rate, first=first, count=count)
    else:
        frames = log_frames(source, topics)
    with progress_bar(None, f"import {layout} --points", unit="frame") as bar:
        counts = write_keypoint_log(
            frames, output, settings=settings, source={"layout": layout, "source": source.name},
            compression=compression, topics=topics, on_frame=lambda _: bar.update(1),
        )  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        per_frame = counts.points / max(counts.observations, 1)
        click.echo(
            f"wrote {output}: {counts.observations} point observations from {counts.frames} frames "
            f"({per_frame:.0f} points per frame, {counts.tracks} tracks), {counts.ground_truth_pose} ground-truth "
            f"poses, {counts.frames_without_colour} frames without colour, "
            f"{counts.frames_without_points} without a point of valid depth",
            err=True,
        )
