"""Running an estimator over a log: read its inputs, drive the estimator, write the output directory.

The application layer between the formats (bytes to core types and back) and the core estimators:
``relpoint run`` and ``relpoint batch`` call :func:`execute_run`; scripts call :func:`run`
(also ``relpoint.run``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections import Counter, deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

import relpoint
from formats.config_files import load_settings
from formats.log import ROLE_OPTIONS, ROLE_TYPES, LogReader, Record, Topics, may_serve
from formats.outputs import check_output_directory
from formats.run_output import write_run_directory
from relpoint import pipeline
from relpoint.errors import EstimatorError, InputError, UsageError
from relpoint.estimators import ESTIMATORS, EstimatorSpec
from relpoint.estimators.base import Estimator
from relpoint.types import DepthFrame, Intrinsics, TimeWindow, Trajectory
from relpoint.undistortion import Undistortion, undistortion
from relpoint_app.roles import NEED_ROLES
from relpoint_app.run_inputs import log_record

log = logging.getLogger(__name__)


def estimator_spec(name: str) -> EstimatorSpec:
    """The registered estimator ``name``; an unknown name is a :class:`UsageError` listing the known ones."""
    if name not in ESTIMATORS:
        known = ", ".join(sorted(ESTIMATORS)) or "none installed"
        raise UsageError(f"unknown estimator {name!r}", f"choose one of: {known}")
    return ESTIMATORS[name]


def build_config(
    spec: EstimatorSpec,
    config_file: Path | None,
    params: tuple[str, ...] = (),
    settings: dict[str, Any] | None = None,
) -> Any:
    """The estimator's config dataclass from defaults, a settings file, then ``settings`` by name and
    ``--param KEY=VALUE`` items."""
    values: dict[str, Any] = {}
    if config_file is not None:
        values.update(load_settings(config_file, section=spec.name))
    values.update(settings or {})
    return spec.build_config(values, params)


@dataclasses.dataclass(frozen=True)
class _HeldDepth:
    """A depth image waiting for the colour image of its stamp (and, when none came before it, its camera_info)."""

    stamp_ns: int
    depth: np.ndarray
    intrinsics: Intrinsics | None


#: Largest stamp difference (ns) between a depth image and the colour image paired with it: the
#: contract asks for equal stamps; cameras that stamp their streams apart stay within a frame or so.
COLOUR_PAIRING_NS = 20_000_000


def estimator_inputs(
    records: Iterator[Record], skipped: Counter[str] | None = None, warnings: list[str] | None = None
) -> Iterator[Any]:
    """Core-type inputs for the pipeline from decoded log records, in the records' order.

    Depth images become :class:`DepthFrame` objects with the latest camera_info's intrinsics and the
    colour image nearest in stamp within :data:`COLOUR_PAIRING_NS` (before or after the depth image in
    the log: a depth image waits until the log has passed that window); depth images without a
    camera_info before them or within that window after them, or that do not match its size, are
    skipped, counted in ``skipped`` and reported once, as are colour images of another size than their depth image. A distortion that
    cannot be taken out is warned of, and the warning appended to ``warnings`` (run.json's).
    """
    skipped = Counter() if skipped is None else skipped
    warnings = [] if warnings is None else warnings
    intrinsics: Intrinsics | None = None
    colours: deque[tuple[int, np.ndarray]] = deque(maxlen=8)
    held: deque[Any] = deque()  # depth images (_HeldDepth) waiting for their colour, and the inputs after them

    def colour_for(stamp_ns: int, shape: tuple[int, ...]) -> np.ndarray | None:
        near = [(abs(stamp - stamp_ns), rgb) for stamp, rgb in colours if abs(stamp - stamp_ns) <= COLOUR_PAIRING_NS]
        if not near:
            return None
        rgb = min(near, key=lambda pair: pair[0])[1]
        if rgb.shape[:2] != shape:
            kind = "color: images of another size than the depth image"
            if kind not in skipped:
                log.warning("not colouring the depth image at %d ns: its colour image is %dx%d, the depth %dx%d "
                            "(colour must be registered to depth); further ones are counted in run.json",
                            stamp_ns, rgb.shape[1], rgb.shape[0], shape[1], shape[0])  # fmt: skip
            skipped[kind] += 1
            return None
        return rgb

    maps: dict[Intrinsics, Undistortion | None] = {}
    counts: Counter[str] = Counter()  # colour images read, and depth images that got one

    def undistorted(frame: DepthFrame) -> DepthFrame:
        if not frame.intrinsics.distorted:
            return frame
        if frame.intrinsics not in maps:
            try:
                maps[frame.intrinsics] = undistortion(frame.intrinsics)
                log.info("the camera_info declares %s distortion: depth and colour are undistorted",
                         frame.intrinsics.distortion_model)  # fmt: skip
            except ValueError as error:
                maps[frame.intrinsics] = None
                message = (f"the camera_info's {error} is not a distortion relpoint can take out: the images are "
                           "used as if from an ideal pinhole")  # fmt: skip
                log.warning("%s", message)
                warnings.append(message)
        undo = maps[frame.intrinsics]
        if undo is None:
            return frame
        color = None if frame.color is None else undo.color(frame.color)
        return DepthFrame(frame.stamp_ns, undo.depth(frame.depth), undo.pinhole, color)

    def matching(item: _HeldDepth) -> Intrinsics | None:
        """The camera_info of a depth image: the latest one read before it, or, when there was none, one
        read within the pairing window after it (drivers publish an image before its camera_info); None,
        counted and reported once, when there is none or it describes another image size."""
        k = item.intrinsics if item.intrinsics is not None else intrinsics
        if k is not None and item.depth.shape == (k.height, k.width):
            return k
        kind = "depth: images without a matching camera_info"
        if kind not in skipped:
            if k is None:
                detail = "no camera_info before it"
            else:
                detail = f"it is {item.depth.shape[1]}x{item.depth.shape[0]}, the camera_info {k.width}x{k.height}"
            log.warning("skipping a depth image at %d ns: %s; further ones are counted in run.json",
                        item.stamp_ns, detail)  # fmt: skip
        skipped[kind] += 1
        return None

    def release(now_ns: int | None) -> Iterator[Any]:
        while held:
            item = held[0]
            if isinstance(item, _HeldDepth):
                if now_ns is not None and now_ns <= item.stamp_ns + COLOUR_PAIRING_NS:
                    return
                k = matching(item)
                if k is not None:
                    rgb = colour_for(item.stamp_ns, item.depth.shape)
                    counts["coloured"] += rgb is not None
                    yield undistorted(DepthFrame(item.stamp_ns, item.depth, k, rgb))
            else:
                yield item
            held.popleft()

    for record in records:
        yield from release(record.stamp_ns)
        if record.role in ("points", "odometry", "fix"):
            if held:
                held.append(record.value)
            else:
                yield record.value
        elif record.role == "camera_info":
            intrinsics = record.value
        elif record.role == "color":
            colours.append((record.stamp_ns, record.value))
            counts["colour images"] += 1
        elif record.role == "depth":
            held.append(_HeldDepth(record.stamp_ns, record.value, intrinsics))
    yield from release(None)
    if counts["colour images"] and not counts["coloured"]:
        message = (f"none of the log's {counts['colour images']} colour images could colour a depth image (see "
                   "skipped for why): the map's points are black")  # fmt: skip
        log.warning("%s", message)
        warnings.append(message)


def input_roles(
    reader: LogReader, spec: EstimatorSpec, *, use_odometry: bool = True, use_fixes: bool = True
) -> list[str]:
    """The log roles an estimator reads: the ones it needs (checked present) and the optional ones the log has."""
    needed = [role for need in sorted(spec.needs) for role in NEED_ROLES.get(need, (need,))]
    reader.require(*needed)
    wanted = [
        need for need in sorted(spec.uses) if (need != "odometry" or use_odometry) and (need != "fix" or use_fixes)
    ]
    optional = [role for need in wanted for role in NEED_ROLES.get(need, (need,))]
    defaults = Topics().roles()
    for role in optional:
        topic = reader.topics.roles()[role]
        if topic != defaults[role]:
            reader.require(role)  # a topic the user named must be there, of the right type
            continue
        info = reader.topic_infos.get(topic)
        if info is not None and info.count and not reader.role_present(role):
            message = (f"{topic} carries {info.typename or 'schemaless data'}, not {ROLE_TYPES[role]}: not read as "
                       f"{role.replace('_', ' ')} (name another topic with {ROLE_OPTIONS[role]})")  # fmt: skip
            log.warning("%s", message)
            reader.warnings.append(message)
        elif info is None and (others := _unused_topics_for(reader, role)):
            # A real bag's topics are named by its drivers: a colour stream on /camera/color/image_raw is
            # not read unless named, and the run would say nothing of it.
            label = "colour images" if role == "color" else role.replace("_", " ")
            message = (f"no {label} on {topic}; the log has {ROLE_TYPES[role]} on "
                       f"{', '.join(others[:3])}{' ...' if len(others) > 3 else ''}: name one with "
                       f"{ROLE_OPTIONS[role]} to use it")  # fmt: skip
            log.warning("%s", message)
            reader.warnings.append(message)
    return needed + [role for role in optional if reader.role_present(role)]


def _unused_topics_for(reader: LogReader, role: str) -> list[str]:
    """The log's topics, with messages, that may serve ``role`` (:func:`formats.log.may_serve`: for colour,
    none named as depth, an Image too) and that no role of the run reads."""
    taken = set(reader.topics.roles().values())
    return sorted(
        topic
        for topic, info in reader.topic_infos.items()
        if info.count and topic not in taken and may_serve(role, topic, info.typename)
    )


#: Roles a time window crops; the others (camera_info) describe the sensor and are always read.
CROPPED_ROLES = frozenset({"points", "odometry", "fix", "depth", "color", "ground_truth_pose"})

#: How far (ns) past the window's end a stamp may lie before the rest of the log is left unread:
#: topics are interleaved by log time, and header stamps may trail it.
CROP_READ_AHEAD_NS = 10_000_000_000


def cropped_records(records: Iterator[Record], window: TimeWindow) -> Iterator[Record]:
    """The records inside ``window``, counted from the first record's stamp (camera_info always)."""
    if window.is_open:
        yield from records
        return
    bounds: tuple[int, int] | None = None
    for record in records:
        if record.role not in CROPPED_ROLES:
            yield record
            continue
        if bounds is None:
            bounds = window.bounds_ns(record.stamp_ns)
        if record.stamp_ns > bounds[1] + CROP_READ_AHEAD_NS:
            return
        if bounds[0] <= record.stamp_ns <= bounds[1]:
            yield record


def execute_run(
    reader: LogReader,
    spec: EstimatorSpec,
    config: Any,
    output: Path,
    *,
    seed: int = 0,
    window: TimeWindow | None = None,
    extra_info: dict[str, Any] | None = None,
    **options: Any,
) -> pipeline.RunResult:
    """What ``relpoint run`` does after parsing its options: run ``spec`` over the log, write ``output``.

    ``window`` crops the log's observations, odometry and fixes (seconds from the first one read);
    the estimator runs as :func:`run_estimator` runs it, with ``options`` (``use_odometry``,
    ``use_fixes``, ``on_iteration``, ``on_finish``, ``map_every``); ``extra_info`` is added to run.json.
    """
    result, roles = run_estimator(reader, spec, config, seed=seed, window=window, **options)
    run_info = {
        "estimator": spec.name,
        "parameters": dataclasses.asdict(config),
        "seed": seed,
        "relpoint_version": relpoint.__version__,
        "input": {**log_record(reader.path, reader.layout), "roles": sorted(roles),
                  "topics": {role: reader.topics.roles()[role] for role in sorted(roles)}},
        "skipped": dict(sorted((reader.skipped + Counter(result.skipped)).items())),
        "warnings": [*reader.warnings, *result.warnings],
        **({"time_window": dataclasses.asdict(window)} if window is not None and not window.is_open else {}),
        **(extra_info or {}),
    }  # fmt: skip
    observations = (
        (record.value for record in cropped_records(reader.records(["points"]), window or TimeWindow()))
        if "points" in roles else ()
    )  # fmt: skip
    write_run_directory(output, result, run_info, observations=observations, reference=reference_path(reader))
    return result


def run_estimator(
    reader: LogReader,
    spec: EstimatorSpec,
    config: Any,
    *,
    seed: int = 0,
    use_odometry: bool = True,
    use_fixes: bool = True,
    on_iteration: Callable[[int, Any], None] | None = None,
    on_finish: Callable[[str], None] | None = None,
    map_every: int = 0,
    window: TimeWindow | None = None,
) -> tuple[pipeline.RunResult, list[str]]:
    """Build ``spec``'s estimator from ``config`` and ``seed`` and :func:`drive` it over the log's
    input roles; the result and the roles read."""
    roles = input_roles(reader, spec, use_odometry=use_odometry, use_fixes=use_fixes)
    estimator = spec.factory(config, np.random.default_rng(seed))
    result = drive(reader, estimator, roles, on_iteration=on_iteration, on_finish=on_finish, map_every=map_every,
                   window=window)  # fmt: skip
    return result, roles


def drive(
    reader: LogReader,
    estimator: Estimator,
    roles: list[str],
    *,
    on_iteration: Callable[[int, Any], None] | None = None,
    on_finish: Callable[[str], None] | None = None,
    map_every: int = 0,
    window: TimeWindow | None = None,
) -> pipeline.RunResult:
    """The one drive loop over a log: ``estimator`` run by :func:`relpoint.pipeline.run` over the
    records of ``roles``, cropped to ``window``; ``relpoint run``, ``relpoint fuse --restart``, batch
    jobs and the Python API all come here.

    BLAS runs single-threaded (numpy's and scipy's pools alike): the estimators' matrices are small, and
    on a busy machine OpenBLAS's spinning worker threads made the EKF about 20 times slower.
    """
    observations = 0

    def counted(records: Iterator[Record]) -> Iterator[Record]:
        nonlocal observations
        for record in records:
            observations += record.role in ("points", "depth")
            yield record

    records = counted(cropped_records(reader.records(roles), window or TimeWindow()))
    # scipy bundles an OpenBLAS of its own, loaded with scipy.linalg: a pool loaded after the limit is
    # set keeps its threads (the figure eight's final adjustment took 7.6 s instead of 2 s, 13 s on a
    # loaded machine, in banded solves of 900 unknowns), so it is loaded first.
    import scipy.linalg  # noqa: F401

    try:
        with threadpool_limits(limits=1, user_api="blas"):
            return pipeline.run(
                estimator_inputs(records, reader.skipped, reader.warnings), estimator, on_iteration=on_iteration, on_finish=on_finish,
                map_every=map_every, skipped_before=reader.skipped,
            )  # fmt: skip
    except (EstimatorError, InputError):
        if window is None or window.is_open or observations:
            raise
        raise _empty_window(reader, roles, window) from None


def _empty_window(reader: LogReader, roles: list[str], window: TimeWindow) -> InputError:
    """The error of a ``--t-start``/``--t-end`` window that leaves no observation, naming the log's span."""
    topics = reader.topics.roles()
    infos = [reader.topic_infos[topics[role]] for role in roles
             if role in CROPPED_ROLES and topics.get(role) in reader.topic_infos]  # fmt: skip
    firsts = [info.first_ns for info in infos if info.first_ns is not None]
    lasts = [info.last_ns for info in infos if info.last_ns is not None]
    span = (max(lasts) - min(firsts)) * 1e-9 if firsts and lasts else 0.0
    given = " ".join(f"{option} {value:g}" for option, value in (("--t-start", window.start_s),
                                                                  ("--t-end", window.end_s)) if value is not None)  # fmt: skip
    return InputError(f"{reader.path}: {given} leaves no observation; the log spans {span:.3f} s",
                      "the window counts seconds from the log's first message")  # fmt: skip


def reference_path(reader: LogReader) -> Trajectory | None:
    """The log's ground-truth path, if it has one (for result.mcap)."""
    if reader.topics.ground_truth_pose not in reader.topic_infos:
        return None
    poses = [record.value for record in reader.records(["ground_truth_pose"])]
    return Trajectory.from_poses(poses) if poses else None


def run(
    log: str | os.PathLike[str],
    estimator: str = "relpoint",
    *,
    output: str | os.PathLike[str] | None = None,
    seed: int = 0,
    config_file: str | os.PathLike[str] | None = None,
    topics: Topics | dict[str, str] | None = None,
    use_odometry: bool = True,
    use_fixes: bool = True,
    window: TimeWindow | None = None,
    overwrite: bool = False,
    **settings: Any,
) -> pipeline.RunResult:
    """Run ``estimator`` over the log at ``log`` as ``relpoint run`` does; the Python API.

    Parameters
    ----------
    log:
        An MCAP file, a rosbag2 directory or a ROS 1 bag (see LOG_FORMAT.md).
    estimator:
        A registered estimator's name (``relpoint.estimators.ESTIMATORS``).
    output:
        When given, the run directory ``relpoint run -o`` writes (trajectory, map, timing, run.json,
        result.mcap), written atomically; an earlier relpoint output there is replaced only with
        ``overwrite`` or when it is a ``run`` output, as on the command line.
    seed:
        Seed of the estimator's random draws.
    config_file:
        A TOML or YAML settings file (its ``[estimator]`` table or flat keys), under ``settings``.
    topics:
        Topic names per role (:class:`formats.log.Topics` or a dict such as ``{"points": "/landmarks"}``).
    use_odometry, use_fixes:
        Read ``/odom`` and ``/fix`` when the log has them and the estimator uses them.
    window:
        Crop the log's observations, odometry and fixes (seconds from the first one read).
    settings:
        Estimator settings by name (``relpoint config -e NAME`` lists them); unknown names and values
        out of range raise :class:`relpoint.errors.UsageError`.

    Returns
    -------
    pipeline.RunResult
        ``trajectory`` (``T_world_sensor`` per iteration, ``world`` = the first sensor frame unless
        fixes give one), ``landmarks``, per-iteration ``seconds`` (``timing_summary()``) and the
        estimator's ``summary``.

    Raises
    ------
    relpoint.errors.RelpointError
        Unusable input (``InputError``), bad settings (``UsageError``) or an estimator failure.
    """
    spec = estimator_spec(estimator)
    config = build_config(spec, None if config_file is None else Path(config_file), settings=settings)
    topic_names = topics if isinstance(topics, Topics) else Topics(**(topics or {}))
    reader = LogReader(log, topic_names)
    if output is not None:
        directory = check_output_directory(
            Path(output), command="run", inputs=[Path(log), *([Path(config_file)] if config_file else [])],
            overwrite=overwrite,
        )  # fmt: skip
        return execute_run(
            reader, spec, config, directory, seed=seed, use_odometry=use_odometry, use_fixes=use_fixes, window=window
        )
    result, _ = run_estimator(
        reader, spec, config, seed=seed, use_odometry=use_odometry, use_fixes=use_fixes, window=window
    )
    return result
