"""An RGB-D scenario for the dense estimator: a furnished room rendered by ray casting along a smooth path.

The scene is a closed room (walls, floor, ceiling seen from inside) with boxes of several sizes and
orientations and spheres, so that point-to-plane ICP is constrained on every axis (plane-only rooms
let it slide). A camera (optical frame: x right, y down, z forward) moves on a smooth elliptical path
and looks outwards at the walls. Each frame is rendered with open3d's ``RaycastingScene``: one ray per
pixel through ``K^-1 [u, v, 1]`` (the same convention as the estimator's back-projection), so the hit
distance is the z-depth. Optional Kinect-like noise (Khoshelham & Elberink 2012; Nguyen et al. 2012):
axial noise ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` m, disparity quantisation (steps growing as
``z^2``), pixels missing where the surface is seen at a grazing angle, outside the sensor's range, or
at random. Colours are a per-object base colour with a checker pattern.

Everything is deterministic given the config's seed; frames are rendered on demand.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from relpoint.errors import UsageError
from relpoint.geometry import FloatArray
from relpoint.settings import Settings, setting
from relpoint.types import DepthFrame, Intrinsics, Trajectory

RESOLUTIONS = {"320x240": (320, 240), "640x480": (640, 480)}


@dataclass(frozen=True)
class RgbdConfig(Settings):
    """Settings of the simulated RGB-D room. Metres, degrees, seconds, hertz."""

    settings_name: ClassVar[str] = "rgbd"
    settings_hint: ClassVar[str] = "room settings go in a --config file (see docs/dense.md)"

    resolution: str = setting("320x240", choices=tuple(RESOLUTIONS), help="Image size: 320x240 or 640x480.")
    frames: int = setting(150, low=1, high=100_000, help="Number of frames.")
    rate: float = setting(30.0, low=1e-3, high=1e4, help="Frames per second.")
    speed: float = setting(0.25, low=0, help="Camera speed along its path, m/s.")
    turn_rate: float = setting(15.0, low=0, help="Rate at which the viewing direction sweeps round the room, deg/s.")
    noise: bool = setting(True, help="Add Kinect-like depth noise, quantisation and missing pixels.")
    grazing_angle: float = setting(
        75.0, above=0, high=90, help="With noise: pixels seen at more than this incidence angle are missing."
    )
    dropout: float = setting(0.01, low=0, below=1, help="With noise: share of pixels missing at random.")
    min_range: float = setting(0.4, low=0, help="Nearest measurable depth.")
    max_range: float = setting(5.0, above=0, help="Farthest measurable depth.")
    reference_points: int = setting(
        200_000, low=1, high=10_000_000, help="Points sampled from the scene's surfaces for map evaluation."
    )
    seed: int = setting(0, low=0, high=2**63 - 1, help="Seed of every random draw.")

    def check(self) -> None:
        """The measurable depth range holds depths."""
        if self.min_range >= self.max_range:
            raise UsageError(f"rgbd setting min_range must be below max_range ({self.max_range}), got {self.min_range}")


# -- scene ------------------------------------------------------------------------------------------------

ROOM = (6.0, 5.0, 2.8)  # x, y, z extent; the floor is z = 0, the room centred on x = y = 0


def _box(
    centre: npt.ArrayLike, size: npt.ArrayLike, yaw_deg: float = 0.0, inward: bool = False
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """Vertices (8, 3) and triangles (12, 3) of a box; ``inward`` flips the faces (a room seen from inside)."""
    sx, sy, sz = np.asarray(size, dtype=np.float64) / 2
    corners = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = corners @ R.T + np.asarray(centre, dtype=np.float64)
    # Corner index = 4 * ix + 2 * iy + iz; faces listed counter-clockwise seen from outside.
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = []
    for a, b, c_, d in quads:
        triangles += [(a, b, c_), (a, c_, d)]
    tri = np.array(triangles, dtype=np.int64)
    return vertices, (tri[:, ::-1].copy() if inward else tri)


def _sphere(
    centre: npt.ArrayLike, radius: float, rings: int = 24, segments: int = 48
) -> tuple[FloatArray, npt.NDArray[np.int64]]:
    """A UV sphere: vertices (V, 3) and outward triangles (F, 3)."""
    theta = np.linspace(0, math.pi, rings + 1)
    phi = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    vertices = vertices * radius + np.asarray(centre, dtype=np.float64)
    triangles = []
    for i in range(rings):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            triangles += [(a, c, b), (b, c, d)]
    tri = np.array(triangles, dtype=np.int64)
    # Drop the degenerate triangles at the poles.
    v = vertices[tri]
    area = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return vertices, tri[area > 1e-12]


@dataclass(frozen=True, eq=False)
class Scene:
    """A triangle-mesh scene in ``world`` (z up): vertices (V, 3) m, triangles (F, 3), object id (F,), colours (K, 3) uint8."""

    vertices: FloatArray
    triangles: npt.NDArray[np.int64]
    object_ids: npt.NDArray[np.int64]
    colors: npt.NDArray[np.uint8]

    def sample(self, n: int, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
        """``n`` points drawn uniformly over the surface area, and their unit normals, (n, 3) each."""
        a, b, c = (self.vertices[self.triangles[:, k]] for k in range(3))
        cross = np.cross(b - a, c - a)
        area = 0.5 * np.linalg.norm(cross, axis=1)
        face = rng.choice(len(area), size=n, p=area / area.sum())
        u, v = rng.random(n), rng.random(n)
        flip = u + v > 1
        u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
        points = a[face] + u[:, None] * (b[face] - a[face]) + v[:, None] * (c[face] - a[face])
        normals = cross[face] / np.linalg.norm(cross[face], axis=1, keepdims=True)
        return points, normals


def room_scene() -> Scene:
    """The furnished room: walls/floor/ceiling, eight boxes along the walls (several yaws) and four spheres."""
    lx, ly, lz = ROOM
    parts: list[tuple[FloatArray, npt.NDArray[np.int64]]] = [_box((0, 0, lz / 2), (lx, ly, lz), inward=True)]
    boxes = [
        ((2.3, 1.6, 0.4), (0.8, 0.6, 0.8), 20.0), ((2.4, -1.2, 0.25), (0.6, 1.0, 0.5), -10.0),
        ((-2.2, 1.7, 0.6), (1.0, 0.5, 1.2), 0.0), ((-2.3, -1.5, 0.35), (0.7, 0.7, 0.7), 35.0),
        ((0.5, 2.1, 0.45), (1.2, 0.5, 0.9), 5.0), ((-0.8, -2.1, 0.3), (0.9, 0.6, 0.6), -25.0),
        ((2.6, 0.2, 1.4), (0.4, 0.8, 0.3), 0.0), ((-2.6, 0.0, 1.0), (0.3, 1.2, 0.4), 0.0),
    ]  # fmt: skip
    for centre, size, yaw in boxes:
        parts.append(_box(centre, size, yaw))
    for centre, radius in (((1.6, -1.9, 0.9), 0.35), ((-1.5, 2.0, 1.6), 0.3), ((2.5, 0.9, 0.25), 0.25),
                           ((-2.4, -0.6, 1.9), 0.3)):  # fmt: skip
        parts.append(_sphere(centre, radius))
    vertices, triangles, object_ids = [], [], []
    offset = 0
    for k, (v, t) in enumerate(parts):
        vertices.append(v)
        triangles.append(t + offset)
        object_ids.append(np.full(len(t), k, dtype=np.int64))
        offset += len(v)
    rng = np.random.default_rng(12345)  # fixed palette, independent of the config's seed
    colors = rng.integers(60, 230, size=(len(parts), 3)).astype(np.uint8)
    return Scene(np.concatenate(vertices), np.concatenate(triangles), np.concatenate(object_ids), colors)


# -- camera path ------------------------------------------------------------------------------------------


def look_at(position: FloatArray, target: FloatArray, up: FloatArray | None = None) -> FloatArray:
    """``T_world_camera`` (4, 4) of an optical-frame camera at ``position`` looking at ``target`` (z up)."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, position
    return T


def camera_path(config: RgbdConfig) -> FloatArray:
    """True camera poses ``T_world_camera`` (N, 4, 4): a slow ellipse near the centre, looking outwards.

    The viewing direction sweeps round the room at ``turn_rate``; the camera moves at about ``speed``
    along an ellipse, with a gentle vertical bob and look-height change, so that motion spans all six
    degrees of freedom.
    """
    t = np.arange(config.frames) / config.rate
    sweep = np.radians(config.turn_rate) * t
    omega = config.speed / 0.8  # rad/s along an ellipse of radius ~0.8 m
    poses = []
    for k in range(config.frames):
        position = np.array(
            [0.8 * math.cos(omega * t[k]), 0.5 * math.sin(omega * t[k]), 1.3 + 0.15 * math.sin(0.7 * omega * t[k])]
        )
        heading = sweep[k]
        target = np.array([3.0 * math.cos(heading), 3.0 * math.sin(heading), 0.6 + 0.3 * math.sin(0.5 * heading + 0.3)])
        poses.append(look_at(position, target))
    return np.array(poses)


# -- rendering --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RgbdSimulation:
    """A simulated RGB-D sequence; frames are rendered on demand by :meth:`frame` / :meth:`frames`.

    Attributes
    ----------
    config: the settings.
    intrinsics: pinhole intrinsics of the depth (and registered colour) camera.
    scene: the meshes.
    poses: (N, 4, 4) true ``T_world_camera`` (world = the room, z up).
    stamps_ns: (N,) int64 frame stamps.
    """

    config: RgbdConfig
    intrinsics: Intrinsics
    scene: Scene
    poses: FloatArray
    stamps_ns: npt.NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.stamps_ns)

    @property
    def ground_truth(self) -> Trajectory:
        """True camera trajectory ``T_world_camera``."""
        return Trajectory.from_matrices(self.stamps_ns, self.poses)

    @cached_property
    def _raycaster(self) -> Any:
        from relpoint._open3d import open3d

        o3d = open3d()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(self.scene.vertices.astype(np.float32)),
            o3d.core.Tensor(self.scene.triangles.astype(np.uint32)),
        )
        return scene

    def reference_cloud(self) -> tuple[FloatArray, FloatArray]:
        """Points (M, 3) and normals (M, 3) sampled over the scene surfaces (``reference_points``), for map evaluation."""
        rng = np.random.default_rng([self.config.seed, 1])
        return self.scene.sample(self.config.reference_points, rng)

    def render(self, index: int) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint8]]:
        """Depth (H, W) float32 metres (0 = missing) and colour (H, W, 3) uint8 of frame ``index``."""
        from relpoint._open3d import open3d

        o3d = open3d()
        k = self.intrinsics
        T = self.poses[index]
        u, v = np.meshgrid(np.arange(k.width), np.arange(k.height))
        rays_cam = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u, dtype=np.float64)], axis=-1)
        directions = rays_cam @ T[:3, :3].T
        rays = np.concatenate([np.broadcast_to(T[:3, 3], directions.shape), directions], axis=-1)
        hit = self._raycaster.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        depth = hit["t_hit"].numpy().astype(np.float64)  # ray direction has unit z: t is the z-depth
        triangle = hit["primitive_ids"].numpy().astype(np.int64)
        normals = hit["primitive_normals"].numpy().astype(np.float64)
        missing = ~np.isfinite(depth)
        depth[missing] = 0.0
        triangle[missing] = 0

        # Colour: the object's base colour times a 10 cm checker pattern on the surface.
        points = T[:3, 3] + directions * depth[..., None]
        checker = (np.floor(points / 0.1).astype(np.int64).sum(axis=-1) % 2).astype(np.float64)
        base = self.scene.colors[self.scene.object_ids[triangle]].astype(np.float64)
        color = np.clip(base * (0.75 + 0.25 * checker)[..., None], 0, 255).astype(np.uint8)
        color[missing] = 0

        if self.config.noise:
            rng = np.random.default_rng([self.config.seed, 2, index])
            unit = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
            cos_incidence = np.abs((unit * normals).sum(axis=-1))
            sigma = 0.0012 + 0.0019 * (depth - 0.4) ** 2
            noisy = depth + sigma * rng.standard_normal(depth.shape)
            # Kinect v1 disparity quantisation: 1/8 pixel steps, i.e. depth steps of 2.85e-3 z^2 m.
            step = 2.85e-3
            with np.errstate(divide="ignore"):
                noisy = np.where(noisy > 0, 1.0 / (np.round((1.0 / np.maximum(noisy, 1e-6)) / step) * step), 0.0)
            drop = cos_incidence < math.cos(math.radians(self.config.grazing_angle))
            drop |= rng.random(depth.shape) < self.config.dropout
            depth = np.where(drop, 0.0, noisy)
        depth[(depth < self.config.min_range) | (depth > self.config.max_range) | missing] = 0.0
        return depth.astype(np.float32), color

    def frame(self, index: int) -> DepthFrame:
        """Frame ``index`` as a :class:`DepthFrame` with its colour image."""
        depth, color = self.render(index)
        return DepthFrame(int(self.stamps_ns[index]), depth, self.intrinsics, color)

    def frames(self) -> Iterator[DepthFrame]:
        """Every frame in order."""
        for index in range(len(self)):
            yield self.frame(index)


def simulate_rgbd(config: RgbdConfig | None = None) -> RgbdSimulation:
    """The furnished-room RGB-D sequence of ``config`` (frames rendered lazily)."""
    config = config or RgbdConfig()
    width, height = RESOLUTIONS[config.resolution]
    f = 525.0 * width / 640.0  # Kinect v1-like field of view (about 63 x 49 degrees)
    intrinsics = Intrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
    period_ns = round(1e9 / config.rate)
    stamps = np.arange(config.frames, dtype=np.int64) * period_ns
    return RgbdSimulation(config, intrinsics, room_scene(), camera_path(config), stamps)
