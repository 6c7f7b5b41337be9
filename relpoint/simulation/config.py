"""Settings of ``relpoint simulate``: one frozen dataclass, validated on construction."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar

from relpoint.errors import UsageError
from relpoint.settings import Settings, setting

SCENARIOS = ("figure8", "stationary", "corridor", "figure8-gaps", "spiral")
#: How moving landmarks move (see :mod:`relpoint.simulation.movers`).
MOVER_MOTIONS = ("oscillate", "line", "random-walk", "stop-and-go", "static-then-moving")
#: The latest stamp a log can hold: ROS 2 stamps count seconds in an int32.
MAX_STAMP_S = 2**31 - 1
#: Settings added after logs were first written: a log records them only when they differ from
#: their defaults, so the same older settings still give a byte-identical file.
_LATER_SETTINGS = ("mover_motion", "mover_speed", "scale")
#: The settings that are lengths of path and landmarks: :attr:`SimulationConfig.scale` multiplies them.
SCALED_LENGTHS = (
    "step", "range", "min_range", "spread_lateral", "spread_vertical", "dynamic_amplitude", "radius", "climb", "length",
)  # fmt: skip


@dataclass(frozen=True)
class SimulationConfig(Settings):
    """Everything that determines a simulated log; the same config gives a byte-identical file.

    Distances in metres, angles in degrees, times in seconds, rates in hertz.
    """

    settings_name: ClassVar[str] = "simulation"
    settings_hint: ClassVar[str] = "see `relpoint simulate --help` for the settings"

    scenario: str = setting(
        "figure8",
        choices=SCENARIOS,
        help="Path: ``figure8`` (the paper's), ``stationary`` (viewpoint fixed, paper Fig. 10), ``corridor`` (a long gently swaying run, for speed tests) or ``figure8-gaps`` (the figure eight with feature-poor stretches, placed in a survey frame that the fixes define; General Concept of 3D SLAM, Fig. 10).",
    )
    passes: int = setting(1, low=1, high=1_000, help="Figure-eight passes (the paper's long-term test runs 40).")
    step: float = setting(
        1.2, low=1e-4, high=1e3, help="Metres travelled per iteration (about 1000 iterations per 1200 m pass)."
    )
    iterations: int | None = setting(
        None, low=1, high=1_000_000, help="Total iterations; default: the whole path (``stationary``: 900)."
    )
    rate: float = setting(10.0, low=1e-3, high=1e4, help="Iterations per second (sets the stamps and velocities).")
    start_time: float = setting(
        0.0, low=0, high=MAX_STAMP_S, help="Stamp of the first iteration, seconds (the last must fit ROS's int32)."
    )
    density: float = setting(
        25.0, low=1e-3, high=1e4, help="Landmarks per 100 m of path, scattered around it (paper: 25 to 550)."
    )
    range: float = setting(70.0, low=1e-3, high=1e5, help="Far end of the viewing frustum.")
    min_range: float = setting(0.5, low=0, high=1e5, help="Near end of the viewing frustum.")
    fov_horizontal: float = setting(150.0, above=0, high=360, help="Horizontal field of view (full angle).")
    fov_vertical: float = setting(90.0, above=0, high=180, help="Vertical field of view (full angle).")
    spread_lateral: float = setting(25.0, low=0, help="Landmarks lie up to this far left/right of the path.")
    spread_vertical: float = setting(10.0, low=0, help="Landmarks lie up to this far above/below the path.")
    noise: float = setting(
        0.3, low=0, high=1e3, help="Standard deviation of the white Gaussian observation noise, per axis."
    )
    dynamic: float = setting(0.0, low=0, high=1, help="Fraction of landmarks that move (paper: up to 0.5).")
    dynamic_amplitude: float = setting(
        5.0, low=0, help="Largest excursion of a moving landmark from its centre, per axis (oscillate)."
    )
    mover_motion: str = setting(
        "oscillate",
        choices=MOVER_MOTIONS,
        help="How moving landmarks move: ``oscillate`` (about their centre, ``dynamic_amplitude``), ``line`` (constant velocity along a straight line), ``random-walk``, ``stop-and-go`` (along a line, moving half the time) or ``static-then-moving`` (still, then along a line from a random iteration on).",
    )
    mover_speed: float = setting(
        0.1, low=0, high=1e3, help="Speed of a moving landmark, metres per iteration (all motions but oscillate)."
    )
    clutter: float = setting(
        0.0, low=0, high=1e5, help="Mean number of spurious points (id -1) per iteration, uniform in the frustum."
    )
    odometry_noise: float | None = setting(
        None, low=0, help="Linear velocity noise sigma (m/s); set to write /odom (0 = perfect odometry)."
    )
    odometry_angular_noise: float | None = setting(
        None, low=0, help="Angular velocity noise sigma (rad/s); default: odometry_noise / 10."
    )
    fix_every: int = setting(
        0, low=0, high=1_000_000, help="Write an absolute position fix on /fix every this many iterations (0 = none)."
    )
    fix_noise: float = setting(1.0, low=0, high=1e4, help="Standard deviation of the fix position noise, per axis.")
    radius: float = setting(95.0, above=0, help="Figure-eight loop radius (95 m gives about 1200 m per pass).")
    climb: float = setting(25.0, low=0, help="Height of the middle crossing above the start, figure eight.")
    length: float = setting(1200.0, above=0, help="Corridor length.")
    scale: float = setting(
        1.0,
        low=1e-3,
        high=1e3,
        help="Scale of the scene: multiplies every length of path and landmarks (step, range, spreads, radius, climb, length, amplitude; density stays per 100 m scaled), not the noise or mover speed. 1 = outdoor (70 m range), 0.1 = indoor (7 m).",
    )
    seed: int = setting(0, low=0, high=2**63 - 1, help="Seed of every random draw.")

    def check(self) -> None:
        """The viewing frustum has depth."""
        if self.min_range >= self.range:
            raise UsageError(f"simulation setting min_range must be below range ({self.range}), got {self.min_range}")

    def log_settings(self) -> dict[str, Any]:
        """The settings as a log records them: later additions only where they differ from their defaults."""
        values = self.to_dict()
        defaults = {f.name: f.default for f in fields(self)}
        return {key: value for key, value in values.items() if key not in _LATER_SETTINGS or value != defaults[key]}

    def scene(self) -> SceneView:
        """These settings with :attr:`scale` folded into every length (``scale`` 1)."""
        return SceneView(self)


class SceneView:
    """A :class:`SimulationConfig` read with its ``scale`` folded into every length: what the scenario draws.

    Each setting reads through to the config; one of :data:`SCALED_LENGTHS` comes multiplied by
    ``scale``, ``density`` (landmarks per 100 m) divided by it, and ``scale`` is 1. It is no
    SimulationConfig itself: a folded length may lie beyond what a user may set (``step`` 1000 m at
    ``scale`` 10, say).
    """

    def __init__(self, config: SimulationConfig) -> None:
        self._config = config

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):  # not a setting (and never _config, unpickled or copied before it is set)
            raise AttributeError(name)
        value = getattr(self._config, name)
        if name in SCALED_LENGTHS:
            return value * self._config.scale
        if name == "density":
            return value / self._config.scale
        return 1.0 if name == "scale" else value
