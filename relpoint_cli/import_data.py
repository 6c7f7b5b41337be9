"""``relpoint import``: RGB-D dataset folders (TUM RGB-D, 7-Scenes) to relpoint logs."""

from __future__ import annotations

from pathlib import Path

import click

from formats.log import COMPRESSIONS
from relpoint.errors import InputError, UsageError
from relpoint.types import Intrinsics
from relpoint_cli.errors import handle_errors
from relpoint_cli.options import overwrite_option, read_paths
from relpoint_cli.progress import progress_bar

EXAMPLES = """\b
Examples:
  relpoint import tum rgbd_dataset_freiburg1_xyz -o fr1_xyz.mcap
  relpoint import tum fr3_office -o office.mcap --intrinsics 535.4,539.2,320.1,247.6
  relpoint import 7scenes redkitchen/seq-01 -o kitchen.mcap --count 400
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


@click.command("import", epilog=EXAMPLES)
@click.argument("layout", type=click.Choice(["tum", "7scenes"]))
@click.argument("folder", type=click.Path(path_type=Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The .mcap log to write."
)
@click.option("--intrinsics", help="TUM: camera fx,fy,cx,cy in pixels (default: Freiburg 1).")
@click.option(
    "--tolerance", type=float, default=0.02, show_default=True, help="TUM: timestamp association tolerance, s."
)
@click.option("--rate", type=float, default=30.0, show_default=True, help="7-Scenes: frames per second.")
@click.option("--first", type=int, default=0, show_default=True, help="7-Scenes: first frame to import.")
@click.option("--count", type=int, help="7-Scenes: number of frames (default: all).")
@click.option("--compression", type=click.Choice(sorted(COMPRESSIONS)), default="zstd", show_default=True)
@overwrite_option
@click.pass_context
@handle_errors
def import_command(
    ctx: click.Context, layout: str, folder: Path, output: Path, intrinsics: str | None, tolerance: float,
    rate: float, first: int, count: int | None, compression: str, overwrite: bool,
) -> None:  # fmt: skip
    """Convert an RGB-D dataset FOLDER in LAYOUT (tum or 7scenes) to a relpoint log.

    The log is written atomically; an existing OUTPUT is replaced only when relpoint wrote it (or with
    --overwrite), and never when it is one of the folder's files.
    """
    from formats.outputs import check_output_file
    from formats.rgbd_import import import_7scenes, import_tum

    if not folder.is_dir():
        problem = "not a folder" if folder.exists() else "no such folder"
        raise InputError(f"{folder}: {problem}", f"give the {layout} dataset's folder")
    # The folder's files and those of its image folders (TUM keeps depth/ and rgb/ beside its lists).
    image_folders = [path for path in folder.iterdir() if path.is_dir()]
    check_output_file(output, inputs=read_paths(folder, *image_folders), overwrite=overwrite)

    with progress_bar(None, f"import {layout}", unit="frame") as bar:
        if layout == "tum":
            counts = import_tum(
                folder, output, intrinsics=parse_intrinsics(intrinsics), tolerance=tolerance,
                compression=compression, on_frame=lambda _: bar.update(1),
            )  # fmt: skip
        else:
            counts = import_7scenes(
                folder, output, rate=rate, first=first, count=count, compression=compression,
                on_frame=lambda _: bar.update(1),
            )  # fmt: skip
    if not ctx.find_root().obj.get("quiet"):
        click.echo(
            f"wrote {output}: {counts.depth} depth frames, {counts.color} colour images, "
            f"{counts.ground_truth_pose} ground-truth poses, {counts.skipped_depth} depth images skipped",
            err=True,
        )
