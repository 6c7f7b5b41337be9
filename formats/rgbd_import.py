"""Importers of RGB-D datasets held as folders into relpoint logs (``relpoint import``).

Two layouts:

TUM RGB-D (Sturm et al. 2012)
    ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` per line, ``#`` comments), ``groundtruth.txt``
    (``timestamp tx ty tz qx qy qz qw``, camera pose in the mocap world), depth PNGs (uint16, depth x 5000,
    0 = none), colour PNGs. Each depth image is paired with the colour image nearest in time within a
    tolerance (as ``associate.py`` of the benchmark does); unpaired depth frames are written without colour.
    The camera intrinsics are not in the folder: unless given, those of the Freiburg camera (1, 2 or 3) the
    folder's name gives are used (``rgbd_dataset_freiburg3_...``), else Freiburg 1's.

7-Scenes (Shotton et al. 2013)
    ``frame-NNNNNN.depth.png`` (uint16 millimetres, 0 and 65535 = none), ``frame-NNNNNN.color.jpg``,
    ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world, ``T_world_camera``); no stamps: 30 Hz from 0 s;
    optional ``camera-intrinsics.txt`` (3x3 K), else fx = fy = 585, cx = 320, cy = 240.

The log holds ``/camera/depth/camera_info`` once, then per frame at its stamp ``/ground_truth/pose``,
``/camera/color/image`` (rgb8; resized to the depth size when it differs, as 7-Scenes colour is not
registered to depth) and ``/camera/depth/image`` (16UC1 mm), colour before depth so that a reader can
attach it to the depth frame that follows. Images are read with Pillow.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import logging
import math
import os
import re
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from formats.log import LogWriter, Topics, metadata_json
from formats.trajectory_files import format_stamp, parse_stamp_ns, text_lines
from relpoint.errors import InputError, UsageError
from relpoint.geometry import FloatArray
from relpoint.types import Intrinsics, Pose

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
#: The TUM RGB-D benchmark's published colour-camera intrinsics (its depth images are registered to the
#: colour camera) of its three Kinects, by the Freiburg number its sequences are named after.
TUM_CAMERAS = {
    1: Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3),
    2: Intrinsics(640, 480, 520.9, 521.0, 325.1, 249.7),
    3: Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6),
}
#: The camera of a TUM folder whose name does not say which one recorded it: Freiburg 1's.
TUM_DEFAULT_INTRINSICS = TUM_CAMERAS[1]
#: "freiburg3" in ``rgbd_dataset_freiburg3_long_office_household``, or "fr3" in a shortened name.
_FREIBURG_NAME = re.compile(r"(?:freiburg|(?<![a-z])fr)[_-]?([123])(?![0-9])")
SEVEN_SCENES_INTRINSICS = Intrinsics(640, 480, 585.0, 585.0, 320.0, 240.0)
SEVEN_SCENES_RATE = 30.0


@dataclass(frozen=True)
class ImportCounts:
    """Messages written by an import."""

    depth: int
    color: int
    ground_truth_pose: int
    skipped_depth: int = 0
    skipped_color: int = 0


class UnreadableImage(InputError):
    """An image file that cannot be decoded (truncated, corrupt, missing): its frame is skipped."""


class _Skips:
    """Unreadable images of an import: the first of each kind warned of by name, all counted in ``counter``."""

    def __init__(self, counter: Counter[str] | None) -> None:
        self.counter: Counter[str] = counter if counter is not None else Counter()
        self.seen: Counter[str] = Counter()

    def skip(self, kind: str, error: UnreadableImage, what: str) -> None:
        self.counter[kind] += 1
        self.seen[kind] += 1
        if self.seen[kind] == 1:
            log.warning("%s; %s (further ones are counted)", error, what)

    def summary(self, folder: Path, frames: int) -> None:
        """Warn of the counts; raise :class:`InputError` when no frame was left (``frames``: those yielded)."""
        if frames == 0 and self.seen["depth"]:
            raise InputError(f"{folder}: none of its {self.seen['depth']} depth images can be read",
                             "check that the dataset was copied whole")  # fmt: skip
        for kind, what in (("depth", "unreadable depth images: their frames were skipped"),
                           ("color", "unreadable colour images: their frames have no colour")):  # fmt: skip
            if self.seen[kind] > 1:
                log.warning("%d %s", self.seen[kind], what)


#: The last stamp a ROS 2 time holds (``builtin_interfaces/Time``: int32 seconds), ns.
_LAST_STAMP_NS = (2**31 - 1) * 1_000_000_000


def _stamp_in_range(path: Path, number: int, text: str) -> int:
    """The exact stamp (ns) of a list's seconds ``text``; InputError naming the line when it is not a number
    or lies outside what a log's stamps hold (TUM lists hold Unix seconds: milliseconds or nanoseconds
    given by mistake land centuries ahead)."""
    try:
        stamp = parse_stamp_ns(text)
    except ValueError:
        raise InputError(
            f"{path}:{number}: bad timestamp {text!r}", "each line starts with a time in seconds"
        ) from None
    if not 0 <= stamp <= _LAST_STAMP_NS:
        raise InputError(f"{path}:{number}: timestamp {text} s is outside 0 to 2^31 s (1970 to 2038), what a log "
                         "holds; TUM lists hold seconds",
                         "are the stamps milliseconds or nanoseconds? divide them to seconds")  # fmt: skip
    return stamp


def _read_list(path: Path, *, file_names: bool = False) -> list[tuple[int, list[str]]]:
    """A TUM list file: ``(stamp ns, [fields...])`` per non-comment line, the stamp exact from its decimal
    text; with ``file_names`` the one field is the rest of the line (a file name may hold spaces)."""
    if not path.is_file():
        raise InputError(f"{path}: no such file", "a TUM RGB-D folder holds rgb.txt, depth.txt and groundtruth.txt")
    rows = []
    for number, line in text_lines(path):
        if not line or line.startswith("#"):
            continue
        parts = re.split(r"[\s,]+", line, maxsplit=1) if file_names else line.replace(",", " ").split()
        if len(parts) < 2:
            raise InputError(f"{path}:{number}: cannot read {line!r}",
                             "a list line holds a time in seconds and a file name")  # fmt: skip
        rows.append((_stamp_in_range(path, number, parts[0]), [parts[1].strip()] if file_names else parts[1:]))
    return rows


def _read_groundtruth(path: Path) -> FloatArray:
    """A TUM ``groundtruth.txt``: (N, 8) ``timestamp tx ty tz qx qy qz qw`` rows. A line without eight numbers
    is an :class:`InputError` naming it; rows holding a NaN or a quaternion of zero length are left out and
    warned of (their frames have no ground truth), as 7-Scenes' invalid poses are."""
    rows = []
    invalid = 0
    first_invalid = ""
    for number, line in text_lines(path):
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        try:
            row = [float(field) for field in fields]
        except ValueError:
            row = []
        if row and math.isfinite(row[0]):
            _stamp_in_range(path, number, fields[0])
        if len(row) != 8:
            raise InputError(f"{path}:{number}: cannot read {line!r}",
                             "a ground-truth line holds eight numbers: timestamp tx ty tz qx qy qz qw")  # fmt: skip
        if not all(math.isfinite(v) for v in row) or math.hypot(*row[4:8]) < 1e-6:
            invalid += 1
            first_invalid = first_invalid or f"{path}:{number}"
            continue
        rows.append(row)
    if invalid:
        log.warning("%s holds %d invalid poses (a NaN, or a quaternion of zero length), the first at line %s; "
                    "their frames have no ground truth", path.name, invalid, first_invalid.rsplit(":", 1)[1])  # fmt: skip
    return np.array(rows, dtype=np.float64).reshape(-1, 8)


def associate_stamps(first: list[float], second: list[float], tolerance: float) -> list[int | None]:
    """For each stamp of ``first`` the index of the nearest stamp of ``second`` within ``tolerance`` (s), else None.

    Matches are one-to-one, greedily by increasing time difference (as the TUM ``associate.py``).
    """
    order = sorted(range(len(second)), key=lambda k: second[k])
    sorted_second = [second[k] for k in order]
    pairs = []
    for i, stamp in enumerate(first):
        at = bisect.bisect_left(sorted_second, stamp)
        for k in (at - 1, at):
            if 0 <= k < len(sorted_second) and abs(sorted_second[k] - stamp) <= tolerance:
                pairs.append((abs(sorted_second[k] - stamp), i, order[k]))
    # Only the two nearest stamps are candidates: the tolerance is normally far below the frame period.
    pairs.sort()
    result: list[int | None] = [None] * len(first)
    used: set[int] = set()
    for _, i, j in pairs:
        if result[i] is None and j not in used:
            result[i] = j
            used.add(j)
    return result


def _read_depth_png(path: Path, scale: float, invalid: tuple[int, ...] = ()) -> np.ndarray:
    try:
        with Image.open(path) as image:
            raw = np.asarray(image)
    except (OSError, ValueError) as error:
        raise UnreadableImage(f"{path}: cannot read the depth image ({error})") from None
    if raw.ndim != 2:
        raise InputError(f"{path}: a depth image must have one channel, got shape {raw.shape}")
    if raw.dtype.kind not in "ui" or raw.dtype.itemsize < 2:
        # An 8-bit PNG cannot hold depth at these scales: read as such, every depth is centimetres.
        raise InputError(f"{path}: the depth image is {raw.dtype} ({raw.dtype.itemsize * 8}-bit); depth PNGs are "
                         "16-bit (TUM: 5000 per metre; 7-Scenes: millimetres)",
                         "write the depth as a 16-bit PNG")  # fmt: skip
    raw = raw.astype(np.uint32)
    depth = raw.astype(np.float32) / np.float32(scale)
    bad = raw == 0
    for value in invalid:
        bad |= raw == value
    depth[bad] = 0.0
    return depth


def _read_rgb(path: Path, size: tuple[int, int]) -> np.ndarray:
    try:
        with Image.open(path) as image:
            if image.mode.startswith("I"):  # 16-bit grey ("I;16", "I"): convert("RGB") clips it to white
                grey = np.clip(np.rint(np.asarray(image, dtype=np.float64) / 257.0), 0, 255).astype(np.uint8)
                image = Image.fromarray(grey)
            image = image.convert("RGB")
            if image.size != size:
                image = image.resize(size, Image.Resampling.BILINEAR)
            return np.asarray(image, dtype=np.uint8)
    except (OSError, ValueError) as error:
        raise UnreadableImage(f"{path}: cannot read the colour image ({error})") from None


def _stamp_ns(seconds: float) -> int:
    return int(round(seconds * 1e9))


def tum_camera_number(folder: str | os.PathLike[str]) -> int | None:
    """The Freiburg camera (1, 2 or 3) a TUM RGB-D folder's name says recorded it (``rgbd_dataset_freiburg2_desk``,
    ``fr3_office``), or None. Only the folder's own name is read: the folders holding it name other things."""
    # the name as given (".." and "." made whole), then a link's target's
    for name in (Path(os.path.abspath(folder)).name, Path(folder).resolve().name):
        if match := _FREIBURG_NAME.search(name.lower()):
            return int(match.group(1))
    return None


def _pose_at(stamps: np.ndarray, positions: np.ndarray, quats: np.ndarray, stamp_ns: int, tolerance: float
             ) -> Pose | None:  # fmt: skip
    """The ground-truth pose at ``stamp_ns``: interpolated (positions linearly, orientations along the shorter
    great arc) between the samples either side of it when both lie within ``tolerance`` (s), else the
    nearest sample within ``tolerance``, else None. ``stamps`` ascending (s), ``quats`` ``(x, y, z, w)``."""
    t = stamp_ns * 1e-9
    k = int(np.searchsorted(stamps, t))
    candidates = [i for i in (k - 1, k) if 0 <= i < len(stamps) and abs(stamps[i] - t) <= tolerance]
    if not candidates:
        return None
    if len(candidates) == 2 and stamps[k] > stamps[k - 1]:
        before, after = candidates
        fraction = (t - stamps[before]) / (stamps[after] - stamps[before])
        position = positions[before] + fraction * (positions[after] - positions[before])
        quat = _slerp(quats[before], quats[after], fraction)
    else:
        nearest = min(candidates, key=lambda i: abs(stamps[i] - t))
        position, quat = positions[nearest], quats[nearest]
    return Pose(stamp_ns, tuple(float(v) for v in position), tuple(float(v) for v in quat))  # type: ignore[arg-type]


def _slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Unit quaternion ``fraction`` of the way from ``q0`` to ``q1`` along the shorter great arc."""
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    cos = float(np.dot(q0, q1))
    if cos < 0.0:
        q1, cos = -q1, -cos
    if cos > 0.9995:  # nearly equal: the chord is the arc
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = math.acos(cos)
    return (math.sin((1.0 - fraction) * angle) * q0 + math.sin(fraction * angle) * q1) / math.sin(angle)


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    """One frame of an RGB-D sequence as read from its folder.

    ``depth`` (H, W) float32 metres (0 = none) in the depth camera's optical frame; ``color`` (H, W, 3)
    uint8 resized to the depth size, or None; ``pose`` the ground-truth ``T_world_camera`` at
    ``stamp_ns``, or None.
    """

    stamp_ns: int
    depth: np.ndarray
    intrinsics: Intrinsics
    color: np.ndarray | None = None
    pose: Pose | None = None


#: ``associate.py`` outputs users keep beside (or instead of) the lists.
_ASSOCIATION_NAMES = ("associations.txt", "association.txt", "associate.txt", "assoc.txt")
#: Depth frames without colour (or ground truth) beyond this share are warned of: the tolerance is too small.
_UNPAIRED_SHARE = 0.05
#: A first frame whose median depth is nearer than this (m) is likely millimetres read as 1/5000 m.
_NEAREST_PLAUSIBLE_MEDIAN_DEPTH = 0.4


def _image_lists(folder: Path) -> tuple[list[tuple[int, list[str]]], list[tuple[int, list[str]]], str]:
    """The depth and colour lists of a TUM folder, and the name of the file the depth list came from:
    ``depth.txt`` and ``rgb.txt``, or, without ``depth.txt``, an ``associate.py`` output (``t1 file1 t2
    file2`` per line; the pair whose file lies under ``depth/`` is the depth image)."""
    if (folder / "depth.txt").is_file():
        rgb = _read_list(folder / "rgb.txt", file_names=True) if (folder / "rgb.txt").is_file() else []
        return _read_list(folder / "depth.txt", file_names=True), rgb, "depth.txt"
    association = next((folder / name for name in _ASSOCIATION_NAMES if (folder / name).is_file()), None)
    if association is None:
        raise InputError(f"{folder / 'depth.txt'}: no such file",
                         "a TUM RGB-D folder holds rgb.txt, depth.txt and groundtruth.txt (or associations.txt)")  # fmt: skip
    depth_rows, rgb_rows = [], []
    for number, line in text_lines(association):
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 4:
            raise InputError(f"{association}:{number}: holds {len(parts)} fields, not the four of associate.py's "
                             "output (time file time file)", "give depth.txt and rgb.txt instead")  # fmt: skip
        pairs = [(_stamp_in_range(association, number, parts[i]), [parts[i + 1]]) for i in (0, 2)]
        is_depth = [_under(name, "depth") for _, (name,) in pairs]
        if is_depth.count(True) != 1:
            raise InputError(f"{association}:{number}: cannot tell the depth image from the colour one",
                             "depth images lie under depth/; or give depth.txt and rgb.txt")  # fmt: skip
        depth_at = is_depth.index(True)
        depth_rows.append(pairs[depth_at])
        rgb_rows.append(pairs[1 - depth_at])
    log.warning("no depth.txt: the depth and colour images paired in %s are read", association.name)
    return depth_rows, rgb_rows, association.name


def _under(name: str, folder: str) -> bool:
    return name.replace("\\", "/").split("/")[0].lower() == folder


def _listed_file(folder: Path, name: str) -> Path:
    """The file a list names, its Windows separators read as ``/`` when the name as written is not there."""
    path = folder / name
    if "\\" in name and not path.exists():
        path = folder / name.replace("\\", "/")
    return path


def _in_time_order(rows: list[tuple[int, list[str]]], name: str) -> list[tuple[int, list[str]]]:
    """``rows`` sorted by stamp (stable), warning when the file did not list them so."""
    if all(a[0] <= b[0] for a, b in itertools.pairwise(rows)):
        return rows
    log.warning("%s is not in time order: its %d images are read in time order", name, len(rows))
    return sorted(rows, key=lambda row: row[0])


def tum_frames(
    folder: str | os.PathLike[str],
    *,
    intrinsics: Intrinsics | None = None,
    tolerance: float = 0.02,
    depth_scale: float = TUM_DEPTH_SCALE,
    skipped: Counter[str] | None = None,
) -> Iterator[RgbdFrame]:
    """The frames of a TUM RGB-D folder, one per depth image, in time order.

    Parameters
    ----------
    folder: holds ``depth.txt``, ``rgb.txt`` (optional) and ``groundtruth.txt`` (optional); without
        ``depth.txt``, an ``associate.py`` output (``associations.txt``) gives the depth and colour images.
    intrinsics: the depth camera's intrinsics (default: the folder's ``calibration.txt``, ``fx fy cx cy`` as
        ETH3D's SLAM datasets hold it, else those of the Freiburg camera the folder's name gives, else
        Freiburg 1's; see :func:`tum_camera_number`); the size is taken from the images.
    tolerance: largest stamp difference (s) when pairing depth with colour and ground truth.
    depth_scale: depth PNG units per metre (the benchmark's 5000; 1000 for millimetres).
    skipped: counts depth images skipped (``depth`` key) because their stamp repeats the previous one,
        their size differs from the first one's, or they cannot be read, and colour images that cannot
        be read (``color`` key; the frame is kept without colour).
    """
    folder = Path(folder)
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise UsageError(f"depth scale {depth_scale}", "give the depth PNGs' units per metre (TUM: 5000)")
    depth_rows, rgb_rows, depth_list = _image_lists(folder)
    if not depth_rows:
        raise InputError(f"{folder / depth_list} lists no depth image")
    depth_rows = _in_time_order(depth_rows, depth_list)
    seconds = 1e-9
    colour_match = associate_stamps([t * seconds for t, _ in depth_rows], [t * seconds for t, _ in rgb_rows],
                                    tolerance)  # fmt: skip
    truth = None
    if (folder / "groundtruth.txt").is_file():
        values = _read_groundtruth(folder / "groundtruth.txt")
        order = np.argsort(values[:, 0], kind="stable")
        truth = values[order]
    calibration = None if intrinsics else folder_calibration(folder)  # the images' own, as ETH3D's folders hold
    base = intrinsics or TUM_CAMERAS.get(tum_camera_number(folder) or 1, TUM_DEFAULT_INTRINSICS)
    camera = None
    previous = None
    repeated = resized_away = yielded = without_colour = without_truth = 0
    skips = _Skips(skipped)
    for (stamp, fields), colour_index in zip(depth_rows, colour_match, strict=True):
        if previous is not None and stamp == previous:
            if skipped is not None:
                skipped["depth"] += 1
            repeated += 1
            if repeated == 1:
                log.warning("depth frame %s repeats the stamp %s s of the one before; skipped (further ones are "
                            "counted)", fields[0], format_stamp(stamp))  # fmt: skip
            continue
        try:
            depth = _read_depth_png(_listed_file(folder, fields[0]), depth_scale)
        except UnreadableImage as error:
            skips.skip("depth", error, "frame skipped")
            continue
        h, w = depth.shape
        if camera is None:
            # given intrinsics are the user's images'; the defaults are a 640x480 camera's
            if calibration is not None:
                camera = Intrinsics(w, h, *calibration)
            else:
                camera = Intrinsics(w, h, base.fx, base.fy, base.cx, base.cy) if intrinsics else resized(base, w, h)
            _check_depth_scale(depth, depth_scale, fields[0])
        elif (w, h) != (camera.width, camera.height):
            if skipped is not None:
                skipped["depth"] += 1
            resized_away += 1
            if resized_away == 1:
                log.warning("depth image %s is %dx%d, the first one %dx%d: one camera calibration cannot hold "
                            "both; skipped (further ones are counted)", fields[0], w, h, camera.width,
                            camera.height)  # fmt: skip
            continue
        pose = None
        if truth is not None:
            pose = _pose_at(truth[:, 0], truth[:, 1:4], truth[:, 4:8], stamp, tolerance)
            without_truth += pose is None
        colour = None
        if colour_index is not None:
            colour = _colour_or_none(_listed_file(folder, rgb_rows[colour_index][1][0]), (w, h), skips)
        else:
            without_colour += bool(rgb_rows)
        previous = stamp
        yielded += 1
        yield RgbdFrame(stamp, depth, camera, colour, pose)
    skips.summary(folder, yielded)
    if repeated > 1:
        log.warning("%d depth frames repeating the stamp before them were skipped", repeated)
    if resized_away > 1:
        log.warning("%d depth images of another size than the first were skipped", resized_away)
    for count, what, source in ((without_colour, "no colour image", "rgb.txt"),
                                (without_truth, "no ground-truth pose", "groundtruth.txt")):  # fmt: skip
        if count and count > _UNPAIRED_SHARE * yielded:
            log.warning("%d of %d depth frames have %s within %g s in %s: they are written without one; a larger "
                        "--tolerance pairs stamps further apart", count, yielded, what, tolerance, source)  # fmt: skip


def _check_depth_scale(depth: np.ndarray, depth_scale: float, name: str) -> None:
    """Warn when the first depth image's median depth is nearer than a depth camera sees: its PNG likely
    holds millimetres (or another unit) rather than ``depth_scale`` per metre."""
    valid = depth[depth > 0]
    if valid.size and (median := float(np.median(valid))) < _NEAREST_PLAUSIBLE_MEDIAN_DEPTH:
        log.warning("the first depth image (%s) has a median depth of %.2f m at %g per metre, nearer than a depth "
                    "camera sees: if its PNGs hold millimetres, pass --depth-scale 1000", name, median,
                    depth_scale)  # fmt: skip


def _colour_or_none(path: Path, size: tuple[int, int], skips: _Skips) -> np.ndarray | None:
    try:
        return _read_rgb(path, size)
    except UnreadableImage as error:
        skips.skip("color", error, "its frame is written without colour")
        return None


def resized(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """``intrinsics`` of a ``intrinsics.width`` x ``intrinsics.height`` camera for its images resized to
    ``width`` x ``height`` (focal lengths and principal point scaled per axis; the same when the size is)."""
    if (width, height) == (intrinsics.width, intrinsics.height):
        return intrinsics
    sx, sy = width / intrinsics.width, height / intrinsics.height
    log.warning(
        "images of %dx%d against a %dx%d calibration: its intrinsics are scaled to the images",
        width, height, intrinsics.width, intrinsics.height,
    )  # fmt: skip
    return Intrinsics(width, height, intrinsics.fx * sx, intrinsics.fy * sy, intrinsics.cx * sx, intrinsics.cy * sy)


_SEVEN_SCENES_FRAME = re.compile(r"frame-(\d+)\.depth\.png$")


def seven_scenes_frames(
    folder: str | os.PathLike[str],
    *,
    rate: float = SEVEN_SCENES_RATE,
    first: int = 0,
    count: int | None = None,
    skipped: Counter[str] | None = None,
) -> Iterator[RgbdFrame]:
    """The frames of a 7-Scenes sequence folder (frame ``i`` stamped ``i / rate`` s).

    ``first`` and ``count`` select a range of frames (by position in the sorted frame list). ``skipped``
    counts unreadable depth images (``depth``: the frame is skipped) and colour images (``color``: the
    frame is kept without colour).
    """
    if not 0.0 < rate <= 1e6 or first < 0 or (count is not None and count < 1):
        raise UsageError(
            f"7-Scenes import: rate {rate} Hz, first {first}, count {count}",
            "the rate must be in (0, 1e6] Hz (stamps are nanoseconds), first >= 0 and count >= 1",
        )
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder")
    frames = sorted(
        (int(m.group(1)), p) for p in folder.iterdir() if (m := _SEVEN_SCENES_FRAME.search(p.name)) is not None
    )
    if not frames:
        raise InputError(f"{folder}: no frame-NNNNNN.depth.png files", "give a 7-Scenes sequence folder (seq-NN)")
    if first >= len(frames):
        raise UsageError(f"--first {first} is beyond the folder's {len(frames)} frames",
                         f"give a position from 0 to {len(frames) - 1} in the sorted frame list")  # fmt: skip
    frames = frames[first : None if count is None else first + count]
    intrinsics = SEVEN_SCENES_INTRINSICS
    if (folder / "camera-intrinsics.txt").is_file():
        K = _read_camera_matrix(folder / "camera-intrinsics.txt")
        intrinsics = Intrinsics(640, 480, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    camera = None
    invalid_poses = missing_poses = yielded = 0
    skips = _Skips(skipped)
    for number, depth_path in frames:
        stamp = _stamp_ns(number / rate)
        try:
            depth = _read_depth_png(depth_path, 1000.0, invalid=(65535,))
        except UnreadableImage as error:
            skips.skip("depth", error, "frame skipped")
            continue
        h, w = depth.shape
        if camera is None:
            camera = _calibration_for(intrinsics, w, h)
        stem = depth_path.name[: -len(".depth.png")]
        pose = None
        pose_path = folder / f"{stem}.pose.txt"
        if not pose_path.is_file():
            missing_poses += 1
            if missing_poses == 1:
                log.warning("%s is missing; no ground truth for that frame (further ones are counted)", pose_path.name)
        else:
            try:
                T = np.loadtxt(pose_path).reshape(4, 4)
            except (OSError, ValueError):  # not a 4 x 4 matrix of numbers: as invalid as a NaN pose
                T = np.full((4, 4), np.nan)
            if np.all(np.isfinite(T)) and abs(T[3, 3]) > 0:
                pose = Pose.from_matrix(stamp, T)
            else:
                invalid_poses += 1
                if invalid_poses == 1:
                    log.warning("%s holds an invalid pose; no ground truth for that frame (further ones are "
                                "counted)", pose_path.name)  # fmt: skip
        color_path = folder / f"{stem}.color.jpg"
        if not color_path.is_file():
            color_path = folder / f"{stem}.color.png"
        colour = _colour_or_none(color_path, (w, h), skips) if color_path.is_file() else None
        yielded += 1
        yield RgbdFrame(stamp, depth, camera, colour, pose)
    skips.summary(folder, yielded)
    if invalid_poses > 1:
        log.warning("%d frames hold an invalid pose and have no ground truth", invalid_poses)
    if missing_poses > 1:
        log.warning("%d frames have no pose file and no ground truth", missing_poses)


#: The calibration file TUM-layout datasets other than TUM's own keep beside the lists (ETH3D's SLAM
#: benchmark: one line ``fx fy cx cy`` of the images' pinhole camera, pixels).
TUM_CALIBRATION_FILE = "calibration.txt"


def folder_calibration(folder: str | os.PathLike[str]) -> tuple[float, float, float, float] | None:
    """``(fx, fy, cx, cy)`` (pixels, of the folder's images) from a TUM-layout folder's ``calibration.txt``,
    or None without the file; :class:`InputError` naming the file when it holds anything else or focal
    lengths that are not positive."""
    path = Path(folder) / TUM_CALIBRATION_FILE
    if not path.is_file():
        return None
    hint = f"{TUM_CALIBRATION_FILE} holds the pinhole camera as one line fx fy cx cy (pixels); or give --intrinsics"
    lines = [line for _, line in text_lines(path) if line and not line.startswith("#")]
    try:
        values = [float(v) for v in lines[0].replace(",", " ").split()] if len(lines) == 1 else []
    except ValueError:
        values = []
    if len(values) != 4:
        raise InputError(f"{path}: not one line of the four numbers fx fy cx cy", hint)
    fx, fy, cx, cy = values
    if not all(math.isfinite(v) for v in values) or fx <= 0 or fy <= 0:
        raise InputError(f"{path}: the focal lengths fx = {fx:g}, fy = {fy:g} are not positive numbers", hint)
    return fx, fy, cx, cy


def _read_camera_matrix(path: Path) -> FloatArray:
    """A 7-Scenes ``camera-intrinsics.txt``: the 3x3 camera matrix K, nine numbers; :class:`InputError`
    naming the file when it holds anything else or focal lengths that are not positive."""
    hint = "camera-intrinsics.txt holds the 3x3 camera matrix: fx 0 cx / 0 fy cy / 0 0 1"
    try:
        K = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: not a 3x3 matrix of numbers", hint) from None
    if K.size != 9:
        raise InputError(f"{path}: holds {K.size} numbers, not the nine of a 3x3 camera matrix", hint)
    K = K.reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{path}: the focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} are not positive numbers",
                         hint)  # fmt: skip
    return K


def _calibration_for(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """A 7-Scenes calibration (taken for 640x480) for ``width`` x ``height`` images. The file holds no size:
    a principal point near the middle of the images (within a tenth of their size) says the calibration
    is theirs, and it is taken as it is; else it is the dataset's 640x480 one, scaled to the images."""
    own = Intrinsics(width, height, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    if (width, height) != (intrinsics.width, intrinsics.height) and (
        abs(intrinsics.cx - (width - 1) / 2) <= width / 10 and abs(intrinsics.cy - (height - 1) / 2) <= height / 10
    ):
        return own
    return resized(intrinsics, width, height)


def write_rgbd_log(
    frames: Iterable[RgbdFrame],
    output: str | os.PathLike[str],
    *,
    metadata: dict[str, dict[str, str]],
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ImportCounts:
    """Write ``frames`` as an RGB-D relpoint log (camera info once, then pose, colour and depth per frame)."""
    topics = topics or Topics()
    depth_count = color_count = pose_count = 0
    with LogWriter(output, compression=compression, metadata=metadata) as writer:
        for index, frame in enumerate(frames):
            if depth_count == 0:
                writer.write_camera_info(frame.stamp_ns, frame.intrinsics, topics.camera_info)
            if frame.pose is not None:
                writer.write_ground_truth_pose(frame.pose, topics.ground_truth_pose)
                pose_count += 1
            if frame.color is not None:
                writer.write_color(frame.stamp_ns, frame.color, topics.color)
                color_count += 1
            writer.write_depth(frame.stamp_ns, frame.depth, topics.depth)
            depth_count += 1
            if on_frame is not None:
                on_frame(index)
    return ImportCounts(depth_count, color_count, pose_count)


def import_tum(
    folder: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    intrinsics: Intrinsics | None = None,
    tolerance: float = 0.02,
    depth_scale: float = TUM_DEPTH_SCALE,
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ImportCounts:
    """Convert a TUM RGB-D folder to a relpoint log (see :func:`tum_frames` for the parameters)."""
    skipped: Counter[str] = Counter()
    frames = tum_frames(folder, intrinsics=intrinsics, tolerance=tolerance, depth_scale=depth_scale, skipped=skipped)
    metadata = {
        "relpoint.import": metadata_json({
            "layout": "tum", "source": Path(folder).name, "tolerance": tolerance, "depth_scale": depth_scale,
            "camera": "given" if intrinsics else (
                TUM_CALIBRATION_FILE if folder_calibration(folder) else f"freiburg{tum_camera_number(folder) or 1}"
            ),
        })
    }  # fmt: skip
    counts = write_rgbd_log(
        frames, output, metadata=metadata, compression=compression, topics=topics, on_frame=on_frame
    )
    return dataclasses.replace(counts, skipped_depth=skipped["depth"], skipped_color=skipped["color"])


def import_7scenes(
    folder: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    rate: float = SEVEN_SCENES_RATE,
    first: int = 0,
    count: int | None = None,
    compression: str = "zstd",
    topics: Topics | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> ImportCounts:
    """Convert a 7-Scenes sequence folder to a relpoint log (see :func:`seven_scenes_frames`)."""
    skipped: Counter[str] = Counter()
    frames = seven_scenes_frames(folder, rate=rate, first=first, count=count, skipped=skipped)
    metadata = {"relpoint.import": metadata_json({"layout": "7scenes", "source": Path(folder).name, "rate": rate})}
    counts = write_rgbd_log(
        frames, output, metadata=metadata, compression=compression, topics=topics, on_frame=on_frame
    )
    return dataclasses.replace(counts, skipped_depth=skipped["depth"], skipped_color=skipped["color"])
