"""Settings of ``relpoint simulate``: one frozen dataclass, validated on construction."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from relpoint.errors import UsageError
from relpoint.settings import Settings, require_non_negative, require_positive

SCENARIOS = ("figure8", "stationary", "corridor", "figure8-gaps", "spiral")
#: How moving landmarks move (see :mod:`relpoint.simulation.movers`).
MOVER_MOTIONS = ("oscillate", "line", "random-walk", "stop-and-go", "static-then-moving")
#: Settings added after logs were first written: a log records them only when they differ from
#: their defaults, so the same older settings still give a byte-identical file.
_LATER_SETTINGS = ("mover_motion", "mover_speed", "scale")
#: The settings that are lengths of path and landmarks: :attr:`SimulationConfig.scale` multiplies them.
SCALED_LENGTHS = (
    "step", "range", "min_range", "spread_lateral", "spread_vertical", "dynamic_amplitude", "radius", "climb", "length",
)  # fmt: skip


def setting(default: Any, help: str) -> Any:
    """A config field with its help text (shown by ``--help`` and ``relpoint config``)."""
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class SimulationConfig(Settings):
    """Everything that determines a simulated log; the same config gives a byte-identical file.

    Distances in metres, angles in degrees, times in seconds, rates in hertz.
    """

    settings_name: ClassVar[str] = "simulation"
    limits: ClassVar[dict[str, tuple[float, float]]] = {
        "passes": (1, 1_000), "iterations": (1, 1_000_000), "step": (1e-4, 1e3), "rate": (1e-3, 1e4),
        "start_time": (0.0, 4e9), "density": (1e-3, 1e4), "range": (1e-3, 1e5), "min_range": (0.0, 1e5),
        "noise": (0.0, 1e3), "clutter": (0.0, 1e5), "fix_every": (0, 1_000_000), "fix_noise": (0.0, 1e4),
        "seed": (0, 2**63 - 1), "mover_speed": (0.0, 1e3), "scale": (1e-3, 1e3),
    }  # fmt: skip

    scenario: str = setting(
        "figure8",
        "Path: ``figure8`` (the paper's), ``stationary`` (viewpoint fixed, paper Fig. 10), ``corridor`` (a long gently swaying run, for speed tests) or ``figure8-gaps`` (the figure eight with feature-poor stretches, placed in a survey frame that the fixes define; General Concept of 3D SLAM, Fig. 10).",
    )
    passes: int = setting(1, "Figure-eight passes (the paper's long-term test runs 40).")
    step: float = setting(1.2, "Metres travelled per iteration (about 1000 iterations per 1200 m pass).")
    iterations: int | None = setting(None, "Total iterations; default: the whole path (``stationary``: 900).")
    rate: float = setting(10.0, "Iterations per second (sets the stamps and velocities).")
    start_time: float = setting(0.0, "Stamp of the first iteration, seconds.")
    density: float = setting(25.0, "Landmarks per 100 m of path, scattered around it (paper: 25 to 550).")
    range: float = setting(70.0, "Far end of the viewing frustum.")
    min_range: float = setting(0.5, "Near end of the viewing frustum.")
    fov_horizontal: float = setting(150.0, "Horizontal field of view (full angle).")
    fov_vertical: float = setting(90.0, "Vertical field of view (full angle).")
    spread_lateral: float = setting(25.0, "Landmarks lie up to this far left/right of the path.")
    spread_vertical: float = setting(10.0, "Landmarks lie up to this far above/below the path.")
    noise: float = setting(0.3, "Standard deviation of the white Gaussian observation noise, per axis.")
    dynamic: float = setting(0.0, "Fraction of landmarks that move (paper: up to 0.5).")
    dynamic_amplitude: float = setting(
        5.0, "Largest excursion of a moving landmark from its centre, per axis (oscillate)."
    )
    mover_motion: str = setting(
        "oscillate",
        "How moving landmarks move: ``oscillate`` (about their centre, ``dynamic_amplitude``), ``line`` (constant velocity along a straight line), ``random-walk``, ``stop-and-go`` (along a line, moving half the time) or ``static-then-moving`` (still, then along a line from a random iteration on).",
    )
    mover_speed: float = setting(0.1, "Speed of a moving landmark, metres per iteration (all motions but oscillate).")
    clutter: float = setting(0.0, "Mean number of spurious points (id -1) per iteration, uniform in the frustum.")
    odometry_noise: float | None = setting(
        None, "Linear velocity noise sigma (m/s); set to write /odom (0 = perfect odometry)."
    )
    odometry_angular_noise: float | None = setting(
        None, "Angular velocity noise sigma (rad/s); default: odometry_noise / 10."
    )
    fix_every: int = setting(0, "Write an absolute position fix on /fix every this many iterations (0 = none).")
    fix_noise: float = setting(1.0, "Standard deviation of the fix position noise, per axis.")
    radius: float = setting(95.0, "Figure-eight loop radius (95 m gives about 1200 m per pass).")
    climb: float = setting(25.0, "Height of the middle crossing above the start, figure eight.")
    length: float = setting(1200.0, "Corridor length.")
    scale: float = setting(
        1.0,
        "Scale of the scene: multiplies every length of path and landmarks (step, range, spreads, radius, climb, length, amplitude; density stays per 100 m scaled), not the noise or mover speed. 1 = outdoor (70 m range), 0.1 = indoor (7 m).",
    )
    seed: int = setting(0, "Seed of every random draw.")

    def __post_init__(self) -> None:
        if self.scenario not in SCENARIOS:
            raise UsageError(f"unknown scenario {self.scenario!r}", f"choose one of {', '.join(SCENARIOS)}")
        if self.mover_motion not in MOVER_MOTIONS:
            raise UsageError(f"unknown mover motion {self.mover_motion!r}", f"choose one of {', '.join(MOVER_MOTIONS)}")
        positive = {
            "passes": self.passes, "step": self.step, "rate": self.rate, "density": self.density,
            "range": self.range, "fov_horizontal": self.fov_horizontal, "fov_vertical": self.fov_vertical,
            "radius": self.radius, "length": self.length, "scale": self.scale,
        }  # fmt: skip
        require_positive(positive)
        non_negative = {
            "noise": self.noise, "clutter": self.clutter, "fix_noise": self.fix_noise, "fix_every": self.fix_every,
            "dynamic_amplitude": self.dynamic_amplitude, "spread_lateral": self.spread_lateral,
            "spread_vertical": self.spread_vertical, "min_range": self.min_range, "climb": self.climb,
            "odometry_noise": 0.0 if self.odometry_noise is None else self.odometry_noise,
            "odometry_angular_noise": 0.0 if self.odometry_angular_noise is None else self.odometry_angular_noise,
            "start_time": self.start_time, "mover_speed": self.mover_speed,
        }  # fmt: skip
        require_non_negative(non_negative)
        if not 0.0 <= self.dynamic <= 1.0:
            raise UsageError(f"dynamic must be a fraction between 0 and 1, got {self.dynamic!r}")
        if self.min_range >= self.range:
            raise UsageError(f"min_range ({self.min_range}) must be below range ({self.range})")
        if self.fov_horizontal > 360 or self.fov_vertical > 180:
            raise UsageError("fov_horizontal must be at most 360 and fov_vertical at most 180 degrees")
        if self.iterations is not None and self.iterations < 1:
            raise UsageError(f"iterations must be at least 1, got {self.iterations}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise UsageError(f"seed must be a non-negative integer, got {self.seed!r}")

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
