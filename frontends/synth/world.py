"""The synthetic scene's configuration and its world: a textured room with COCO-labelled cuboids.

World frame: x east, y north, z up, floor at z=0, room centred on the origin. Every surface is a
planar quad with its own texture, generated once from numpy Generators seeded by ``config.seed``
(never OpenCV's global RNG), so a seed fixes the whole scene.

Textures: a low-frequency colour field overlaid with random multi-scale shapes (rotated rectangles,
triangles, circles, ellipses, outlines, lines) drawn anti-aliased in dark/bright colours against
the background. Shape sizes are in metres, so the corner density seen by ORB is independent of the
texture resolution, and since every wall is one non-repeating random canvas each place of the room
looks different. Each texture is stored as an image pyramid; the renderer picks the level that
matches the on-screen texel size, which keeps distant surfaces from aliasing.

Objects: cuboids with COCO class names stand along the walls (floor and wall-mounted classes) or
on dining tables (cups, bottles, books, laptops, keyboards). Textures are seeded by class label
(``crc32``) and face shading is fixed in the object's own frame, so repeated instances of a class
look identical: the perceptual aliasing a semantic loop detector must cope with. Movable objects
("person") walk back and forth in lanes between the wall objects and the camera path; the
detector is expected to drop them.

Bays layout (``layout: bays``): a hall of ``bays`` bays in a row along x, every bay with the SAME
north-wall, south-wall, floor and ceiling textures (one texture each, repeated), so only the objects
tell the bays apart: each bay packs both long walls with floor objects, table items and wall-mounted
objects above them, drawn from its own seeded Generator. People walk across the hall near its end
walls. Seen along the ``hall`` camera path.

Ground-truth loops (``SynthConfig.loop_labels``, overridable as ``loop_labels.<field>``): frames at
least 3 s apart whose views share at least 30 % of their static surface points (rendered depth),
after the camera looked away or went 2 m away (``frontends.synth.covisibility``).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from frontends.errors import ConfigError
from frontends.synth.covisibility import CovisibilityLabelConfig
from frontends.types import CameraIntrinsics

TrajectoryKind = Literal["loop", "figure8", "out-and-back", "none", "hall"]
TRAJECTORY_KINDS: tuple[TrajectoryKind, ...] = ("loop", "figure8", "out-and-back", "none", "hall")
LayoutKind = Literal["room", "bays"]
LAYOUTS: tuple[LayoutKind, ...] = ("room", "bays")
#: The config fields of the bays layout (``scene.json`` leaves them out while they hold their defaults).
BAYS_FIELDS = ("layout", "bays", "bay_size")

#: Distance from the walls to the camera path at full path scale (m): the wall objects (<= 1.15 m
#: deep) and the person lanes (1.35 m) fit in between.
WALL_CLEARANCE = 2.2
#: Distance of the person lanes from the long walls (m).
PERSON_LANE = 1.35
#: Most bays of the bays layout, and the smallest bay (length, hall width, height; m): the hall
#: path's lanes and turns need the width, the packed wall objects the length.
MAX_BAYS = 12
MIN_BAY_SIZE = (2.5, 4.4, 2.2)
#: Distance of the bays layout's person lanes (across the hall) from its end walls (m).
HALL_PERSON_LANE = 0.7


@dataclass(frozen=True)
class SynthConfig:
    """Every knob of a synthetic scene; ``load_config(SynthConfig, yaml, ["key=value"])`` overrides."""

    seed: int = 0
    trajectory: TrajectoryKind = "loop"
    frames: int = 600
    fps: float = 30.0
    #: Timestamp of the first frame (s).
    start_time: float = 1.0
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    #: Room extent along x, y and its height (m).
    room_size: tuple[float, float, float] = (9.0, 7.0, 2.8)
    #: Place: one room, or a hall of ``bays`` bays along x with identical textures (``hall`` path).
    layout: LayoutKind = "room"
    #: Number of bays of the bays layout (each with its own objects).
    bays: int = 3
    #: One bay's length along x, the hall's width along y and its height (m).
    bay_size: tuple[float, float, float] = (3.5, 6.0, 2.8)
    #: Static objects of the room layout (the bays layout packs each bay's walls instead).
    static_objects: int = 14
    movable_objects: int = 2
    #: Target mean camera speed (m/s); met while the path scale is within its clamp range.
    speed: float = 0.7
    #: Laps of the loop and figure8 paths (the part beyond 1 revisits the start).
    laps: float = 1.4
    camera_height: float = 1.4
    camera_pitch_deg: float = -8.0
    #: Texture resolution of the walls (texels per metre); floor and ceiling use 2/3 and 1/2 of it.
    wall_texels_per_m: float = 300.0
    object_texels_per_m: float = 400.0
    #: Standard deviation of the additive Gaussian sensor noise (grey levels).
    noise_sigma: float = 2.0
    #: Standard deviation of the Gaussian optical blur (pixels); 0 disables it.
    blur_sigma: float = 0.6
    #: Relative amplitude of the slow exposure (gain) oscillation.
    exposure_amplitude: float = 0.12
    exposure_period: float = 9.0
    #: Objects with fewer visible pixels are left out of the ground truth.
    min_visible_pixels: int = 20
    #: Near clipping plane (m).
    near: float = 0.05
    loop_labels: CovisibilityLabelConfig = field(default_factory=CovisibilityLabelConfig)

    def __post_init__(self) -> None:
        sensor = min(self.noise_sigma, self.blur_sigma, self.exposure_amplitude)
        texels = min(self.wall_texels_per_m, self.object_texels_per_m)
        checks = {
            "frames must be >= 2": self.frames >= 2,
            "fps must be positive": self.fps > 0,
            "width and height must be >= 16": self.width >= 16 and self.height >= 16,
            "laps must be in (1, 3]": 1.0 < self.laps <= 3.0,
            "speed must be positive": self.speed > 0,
            "static_objects must be >= 1": self.static_objects >= 1,
            "movable_objects must be >= 0": self.movable_objects >= 0,
            "noise_sigma, blur_sigma and exposure_amplitude must be >= 0": sensor >= 0,
            "exposure_period must be positive": self.exposure_period > 0,
            "texel densities must be >= 20 per metre": texels >= 20,
            "near must be positive": self.near > 0,
            f"room_size must be >= {2 * WALL_CLEARANCE + 1} m wide and long and >= 2.2 m high": (
                min(self.room_size[:2]) >= 2 * WALL_CLEARANCE + 1 and self.room_size[2] >= 2.2
            ),
            "camera_height must be inside the room": 0.3 <= self.camera_height <= self.ceiling - 0.3,
            f"bays must be in [2, {MAX_BAYS}]": 2 <= self.bays <= MAX_BAYS,
            f"bay_size must be >= {MIN_BAY_SIZE} m (length, width, height)": all(
                size >= least for size, least in zip(self.bay_size, MIN_BAY_SIZE, strict=True)
            ),
            # One way only: ``--set`` applies one key at a time, so layout=bays must come first; the
            # other way (bays needs hall) is checked when the camera path is made.
            "trajectory hall needs layout bays (set layout first)": (
                self.trajectory != "hall" or self.layout == "bays"
            ),
        }
        failed = [message for message, ok in checks.items() if not ok]
        if failed:
            raise ConfigError(f"synth config: {'; '.join(failed)}")

    @property
    def ceiling(self) -> float:
        """Ceiling height of the place (m)."""
        return self.bay_size[2] if self.layout == "bays" else self.room_size[2]

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(
            self.fx, self.fy, self.cx, self.cy, self.width, self.height, (), source="synth config"
        )


@dataclass(frozen=True)
class ObjectClass:
    label: str
    #: Width (local x, along the wall), depth (local y) and height (m).
    size: tuple[float, float, float]
    mount: Literal["floor", "wall", "table"]
    #: Base height of wall-mounted objects (m).
    elevation: float = 0.0


FLOOR_AND_WALL_CLASSES = (
    ObjectClass("chair", (0.5, 0.5, 0.9), "floor"),
    ObjectClass("potted plant", (0.45, 0.45, 0.85), "floor"),
    ObjectClass("couch", (1.8, 0.85, 0.8), "floor"),
    ObjectClass("refrigerator", (0.7, 0.7, 1.8), "floor"),
    ObjectClass("tv", (1.0, 0.08, 0.6), "wall", 1.1),
    ObjectClass("clock", (0.32, 0.05, 0.32), "wall", 1.85),
)
TABLE = ObjectClass("dining table", (1.4, 0.8, 0.75), "floor")
TABLE_ITEMS = (
    ObjectClass("cup", (0.09, 0.09, 0.11), "table"),
    ObjectClass("bottle", (0.08, 0.08, 0.28), "table"),
    ObjectClass("book", (0.17, 0.05, 0.24), "table"),
    ObjectClass("laptop", (0.34, 0.26, 0.22), "table"),
    ObjectClass("keyboard", (0.44, 0.15, 0.03), "table"),
)
PERSON = ObjectClass("person", (0.45, 0.28, 1.7), "floor")
ITEMS_PER_TABLE = 4
#: The bays layout packs each bay wall with floor objects (drawn with these weights), table items
#: and, above them, wall-mounted ones, leaving this margin (m) at the bay ends.
BAY_FLOOR_CLASSES = (TABLE, *(c for c in FLOOR_AND_WALL_CLASSES if c.mount == "floor"))
BAY_FLOOR_WEIGHTS = (0.4, 0.2, 0.2, 0.1, 0.1)
BAY_WALL_CLASSES = tuple(c for c in FLOOR_AND_WALL_CLASSES if c.mount == "wall")
BAY_MARGIN = 0.15


@dataclass(frozen=True)
class Surface:
    """A textured planar quad: texture (0, 0) maps to corner 0, (w, 0) to 1, (w, h) to 2, (0, h) to 3."""

    #: (4, 3) corners; the outward normal is (c1 - c0) x (c3 - c0) reversed, i.e. right x up.
    corners: np.ndarray
    #: Texture pyramid (level 0 first), shading baked in.
    pyramid: tuple[np.ndarray, ...]
    texels_per_m: float


@dataclass(frozen=True)
class WorldObject:
    label: str
    #: Id in the renderer's instance buffer (1-based; 0 is the room).
    instance: int
    #: Geometric centre at t = 0 (m).
    centre: tuple[float, float, float]
    size: tuple[float, float, float]
    #: Rotation about z (rad); the local -y face (the front) faces into the room.
    yaw: float
    movable: bool = False
    #: Movable objects oscillate along their local x axis: amplitude (m), period (s), phase (rad).
    amplitude: float = 0.0
    period: float = 1.0
    phase: float = 0.0

    def centre_at(self, t: float) -> np.ndarray:
        offset = self.amplitude * math.sin(2 * math.pi * t / self.period + self.phase)
        return np.array(self.centre) + offset * np.array([math.cos(self.yaw), math.sin(self.yaw), 0.0])

    def transform_at(self, t: float) -> np.ndarray:
        """Local (base-centred) to world 4x4 transform at time ``t``."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        matrix = np.eye(4)
        matrix[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        matrix[:3, 3] = self.centre_at(t) - [0.0, 0.0, self.size[2] / 2]
        return matrix

    def corners_at(self, t: float) -> np.ndarray:
        """The 8 cuboid corners in world coordinates, (8, 3)."""
        w, d, h = self.size
        local = np.array([[x, y, z, 1.0] for x in (-w / 2, w / 2) for y in (-d / 2, d / 2) for z in (0.0, h)])
        return (local @ self.transform_at(t).T)[:, :3]


@dataclass(frozen=True)
class World:
    room_size: tuple[float, float, float]
    #: Walls, floor and ceiling in world coordinates.
    room: tuple[Surface, ...]
    objects: tuple[WorldObject, ...]
    #: Faces of each class in its local frame (base centre at the origin), shared by its instances.
    models: Mapping[str, tuple[Surface, ...]]


def quad(
    centre: np.ndarray, normal: np.ndarray, right: np.ndarray, half_w: float, half_h: float
) -> np.ndarray:
    """Corners of a rectangle seen from the side ``normal`` points to: top-left first, clockwise."""
    up = np.cross(normal, right)
    return np.array(
        [
            centre - right * half_w + up * half_h,
            centre + right * half_w + up * half_h,
            centre + right * half_w - up * half_h,
            centre - right * half_w - up * half_h,
        ]
    )


def _label_seed(seed: int, label: str) -> list[int]:
    return [seed, zlib.crc32(label.encode("utf-8"))]


def paint_texture(
    rng: np.random.Generator, width_m: float, height_m: float, texels_per_m: float, density: float = 1.0
) -> np.ndarray:
    """A non-repeating random texture of ``width_m`` x ``height_m`` metres (BGR uint8)."""
    width = max(8, round(width_m * texels_per_m))
    height = max(8, round(height_m * texels_per_m))
    cell = 0.35 * texels_per_m
    base = rng.uniform(70, 190, 3)
    grid_shape = (max(2, round(height / cell) + 1), max(2, round(width / cell) + 1))
    # Mostly brightness variation with a little colour: a plausible paint/wallpaper background.
    grid = rng.uniform(-35, 35, (*grid_shape, 1)) + rng.uniform(-12, 12, (*grid_shape, 3))
    field_ = cv2.resize((grid + base).astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
    texture = np.clip(field_, 0, 255).astype(np.uint8)
    area = width_m * height_m
    max_size = 0.8 * min(width_m, height_m)
    # (min size, max size, shapes per square metre, at least) in metres.
    for lo, hi, per_m2, least in ((0.25, 0.8, 1.0, 1), (0.06, 0.25, 14.0, 2), (0.015, 0.06, 60.0, 3)):
        count = max(least, round(area * per_m2 * density))
        sizes = rng.uniform(min(lo, max_size / 2), min(hi, max_size), count) * texels_per_m
        centres = rng.uniform(0, 1, (count, 2)) * (width, height)
        angles = rng.uniform(0, math.pi, count)
        kinds = rng.integers(0, 6, count)
        aspects = rng.uniform(0.3, 1.0, count)
        dark = rng.random(count) < 0.5
        colours = rng.integers(0, 256, (count, 3)).astype(np.float64)
        colours = np.where(dark[:, None], colours * 0.35, 255 - (255 - colours) * 0.35).round().astype(int)
        thickness = np.maximum(1, (sizes * rng.uniform(0.04, 0.12, count)).round().astype(int))
        for k in range(count):
            _draw_shape(
                texture, int(kinds[k]), centres[k], sizes[k], aspects[k], angles[k], colours[k], thickness[k]
            )
    return texture


def _draw_shape(
    image: np.ndarray,
    kind: int,
    centre: np.ndarray,
    size: float,
    aspect: float,
    angle: float,
    colour: np.ndarray,
    thickness: int,
) -> None:
    colour_t = (int(colour[0]), int(colour[1]), int(colour[2]))
    c, s = math.cos(angle), math.sin(angle)
    axis_u, axis_v = np.array([c, s]) * size / 2, np.array([-s, c]) * size * aspect / 2
    if kind in (0, 4):  # rotated rectangle, filled or outlined
        points = (
            np.array(
                [
                    centre + axis_u + axis_v,
                    centre - axis_u + axis_v,
                    centre - axis_u - axis_v,
                    centre + axis_u - axis_v,
                ]
            )
            .round()
            .astype(np.int32)
        )
        if kind == 0:
            cv2.fillConvexPoly(image, points, colour_t, cv2.LINE_AA)
        else:
            cv2.polylines(image, [points], True, colour_t, thickness, cv2.LINE_AA)
    elif kind == 1:  # triangle
        points = np.array([centre + axis_u, centre - axis_u + axis_v, centre - axis_u - 1.5 * axis_v])
        cv2.fillConvexPoly(image, points.round().astype(np.int32), colour_t, cv2.LINE_AA)
    elif kind == 2:  # disc
        cv2.circle(
            image, (round(centre[0]), round(centre[1])), max(1, round(size / 2)), colour_t, -1, cv2.LINE_AA
        )
    elif kind == 3:  # ellipse
        axes = (max(1, round(size / 2)), max(1, round(size * aspect / 2)))
        cv2.ellipse(
            image,
            (round(centre[0]), round(centre[1])),
            axes,
            math.degrees(angle),
            0,
            360,
            colour_t,
            -1,
            cv2.LINE_AA,
        )
    else:  # line
        a, b = (centre + axis_u).round().astype(int), (centre - axis_u).round().astype(int)
        cv2.line(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), colour_t, thickness, cv2.LINE_AA)


def texture_pyramid(texture: np.ndarray, shade: float) -> tuple[np.ndarray, ...]:
    """Shade a texture and build its pyramid down to ~8 texels on the short side."""
    levels = [cv2.convertScaleAbs(texture, alpha=shade)]
    while min(levels[-1].shape[:2]) >= 16:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


def build_world(config: SynthConfig) -> World:
    """The room (or hall of bays), its objects and every texture, all from ``config.seed``."""
    if config.layout == "bays":
        return _build_bays(config)
    size_x, size_y, size_z = config.room_size
    room = _room_surfaces(config)
    rng = np.random.default_rng([config.seed, 1])
    static = _place_static_objects(config, rng)
    movable = _place_people(config, rng, len(static) + 1, (size_x, size_y))
    objects = static + movable
    labels = sorted({obj.label for obj in objects})
    classes = {c.label: c for c in (*FLOOR_AND_WALL_CLASSES, TABLE, *TABLE_ITEMS, PERSON)}
    models = {label: _cuboid_faces(classes[label], config) for label in labels}
    return World((size_x, size_y, size_z), room, tuple(objects), models)


def _room_surfaces(config: SynthConfig) -> tuple[Surface, ...]:
    sx, sy, sz = config.room_size
    x, y, z = np.eye(3)
    density = config.wall_texels_per_m
    # (centre, inward normal, right, width, height, texels/m, shade, shape density)
    specs = (
        ((0, sy / 2, sz / 2), -y, x, sx, sz, density, 0.95, 1.0),
        ((sx / 2, 0, sz / 2), -x, -y, sy, sz, density, 0.85, 1.0),
        ((0, -sy / 2, sz / 2), y, -x, sx, sz, density, 0.9, 1.0),
        ((-sx / 2, 0, sz / 2), x, y, sy, sz, density, 0.8, 1.0),
        ((0, 0, 0), z, x, sx, sy, density * 2 / 3, 0.85, 0.8),
        ((0, 0, sz), -z, x, sx, sy, density / 2, 0.7, 0.4),
    )
    surfaces = []
    for index, (centre, normal, right, width, height, texels, shade, shapes) in enumerate(specs):
        rng = np.random.default_rng([config.seed, 2, index])
        texture = paint_texture(rng, width, height, texels, shapes)
        corners = quad(np.array(centre, dtype=float), normal, right, width / 2, height / 2)
        surfaces.append(Surface(corners, texture_pyramid(texture, shade), texels))
    return tuple(surfaces)


def _cuboid_faces(cls: ObjectClass, config: SynthConfig) -> tuple[Surface, ...]:
    w, d, h = cls.size
    x, y, z = np.eye(3)
    # (centre, outward normal, right, width, height, shade): shading fixed in the object frame.
    specs = (
        ((0, -d / 2, h / 2), -y, x, w, h, 0.95),
        ((w / 2, 0, h / 2), x, y, d, h, 0.85),
        ((0, d / 2, h / 2), y, -x, w, h, 0.75),
        ((-w / 2, 0, h / 2), -x, -y, d, h, 0.8),
        ((0, 0, h), z, x, w, d, 1.0),
        ((0, 0, 0), -z, x, w, d, 0.6),
    )
    faces = []
    for index, (centre, normal, right, width, height, shade) in enumerate(specs):
        rng = np.random.default_rng([*_label_seed(config.seed, cls.label), index])
        texture = paint_texture(rng, width, height, config.object_texels_per_m)
        corners = quad(np.array(centre, dtype=float), normal, right, width / 2, height / 2)
        faces.append(Surface(corners, texture_pyramid(texture, shade), config.object_texels_per_m))
    return tuple(faces)


def _place_static_objects(config: SynthConfig, rng: np.random.Generator) -> list[WorldObject]:
    n = config.static_objects
    n_tables = max(1, round(n / 7))
    n_items = min(round(0.35 * n), ITEMS_PER_TABLE * n_tables, max(0, n - n_tables - 1))
    n_rest = max(0, n - n_tables - n_items)
    # Drawn with replacement from few classes: repeated classes are the point (perceptual aliasing).
    rest = [FLOOR_AND_WALL_CLASSES[i] for i in rng.integers(0, len(FLOOR_AND_WALL_CLASSES), n_rest)]
    along_wall = [TABLE] * n_tables + rest
    sx, sy, _ = config.room_size
    corner_margin = 0.95
    # Each wall: start corner, direction along it, inward normal, length.
    walls = (
        (np.array([-sx / 2, sy / 2]), np.array([1.0, 0.0]), np.array([0.0, -1.0]), sx),
        (np.array([sx / 2, sy / 2]), np.array([0.0, -1.0]), np.array([-1.0, 0.0]), sy),
        (np.array([sx / 2, -sy / 2]), np.array([-1.0, 0.0]), np.array([0.0, 1.0]), sx),
        (np.array([-sx / 2, -sy / 2]), np.array([0.0, 1.0]), np.array([1.0, 0.0]), sy),
    )
    lengths = np.array([w[3] - 2 * corner_margin for w in walls])
    taken: list[list[tuple[float, float]]] = [[] for _ in walls]
    objects: list[WorldObject] = []
    tables: list[WorldObject] = []
    for cls in along_wall:
        w, d, h = cls.size
        for _ in range(500):
            wall = int(rng.choice(len(walls), p=lengths / lengths.sum()))
            start, direction, inward, _length = walls[wall]
            half = w / 2 + 0.12
            if lengths[wall] < 2 * half:
                continue
            s = corner_margin + half + rng.uniform(0, lengths[wall] - 2 * half)
            if all(s + half <= a or s - half >= b for a, b in taken[wall]):
                break
        else:
            raise ConfigError(
                f"synth config: cannot fit {n} objects along the walls of a {sx} x {sy} m room; "
                "lower static_objects or enlarge room_size"
            )
        taken[wall].append((s - half, s + half))
        gap = 0.02 if cls.mount == "wall" else float(rng.uniform(0.03, 0.25))
        xy = start + direction * s + inward * (gap + d / 2)
        base = cls.elevation if cls.mount == "wall" else 0.0
        obj = WorldObject(
            cls.label,
            0,
            (float(xy[0]), float(xy[1]), base + h / 2),
            cls.size,
            math.atan2(inward[0], -inward[1]),
        )
        objects.append(obj)
        if cls is TABLE:
            tables.append(obj)
    items = [TABLE_ITEMS[i] for i in rng.integers(0, len(TABLE_ITEMS), n_items)]
    for k, cls in enumerate(items):
        objects.append(_on_table(tables[k % len(tables)], cls, k // len(tables), rng))
    return [_with_instance(obj, k + 1) for k, obj in enumerate(objects)]


def _on_table(table: WorldObject, cls: ObjectClass, slot: int, rng: np.random.Generator) -> WorldObject:
    """``cls`` standing in ``slot`` of ``ITEMS_PER_TABLE`` along ``table`` (no two slots overlap),
    jittered and turned a little."""
    tw, td, th = table.size
    w, d, h = cls.size
    slot_w = tw / ITEMS_PER_TABLE
    local_x = -tw / 2 + slot_w * (slot + 0.5) + rng.uniform(-1, 1) * max(0.0, (slot_w - w) / 2 - 0.01)
    local_y = rng.uniform(-1, 1) * max(0.0, (td - max(w, d)) / 2 - 0.03)
    yaw = table.yaw + float(rng.uniform(-0.25, 0.25))
    centre = table.transform_at(0.0) @ np.array([local_x, local_y, th + h / 2, 1.0])
    return WorldObject(cls.label, 0, (float(centre[0]), float(centre[1]), float(centre[2])), cls.size, yaw)


def _with_instance(obj: WorldObject, instance: int) -> WorldObject:
    return WorldObject(
        obj.label, instance, obj.centre, obj.size, obj.yaw, obj.movable, obj.amplitude, obj.period, obj.phase
    )


def _place_people(
    config: SynthConfig, rng: np.random.Generator, first_instance: int, floor: tuple[float, float]
) -> list[WorldObject]:
    sx, sy = floor
    people = []
    for k in range(config.movable_objects):
        side = 1.0 if k % 2 == 0 else -1.0
        amplitude = float(rng.uniform(0.7, 1.2))
        reach = max(0.0, sx / 2 - 1.3 - amplitude)
        x0 = float(rng.uniform(-reach, reach))
        y0 = side * (sy / 2 - PERSON_LANE)
        people.append(
            WorldObject(
                PERSON.label,
                first_instance + k,
                (x0, y0, PERSON.size[2] / 2),
                PERSON.size,
                0.0 if side > 0 else math.pi,
                movable=True,
                amplitude=amplitude,
                period=float(rng.uniform(7.0, 11.0)),
                phase=float(rng.uniform(0, 2 * math.pi)),
            )
        )
    return people


def hall_size(config: SynthConfig) -> tuple[float, float, float]:
    """Extent of the bays layout's hall along x, y and its height (m)."""
    length, width, height = config.bay_size
    return (config.bays * length, width, height)


def bay_of(config: SynthConfig, x: float) -> int:
    """Index of the bay (0 at the west end) that contains ``x``, clamped to the hall."""
    length = config.bay_size[0]
    return min(config.bays - 1, max(0, math.floor((x + config.bays * length / 2) / length)))


def _build_bays(config: SynthConfig) -> World:
    """The hall: every bay repeats the same wall, floor and ceiling textures; each has its own objects."""
    size = hall_size(config)
    room = _bay_surfaces(config)
    static: list[WorldObject] = []
    for bay in range(config.bays):
        static += _pack_bay(config, bay)
    static = [_with_instance(obj, k + 1) for k, obj in enumerate(static)]
    rng = np.random.default_rng([config.seed, 1])
    movable = _place_hall_people(config, rng, len(static) + 1)
    objects = static + movable
    labels = sorted({obj.label for obj in objects})
    classes = {c.label: c for c in (*FLOOR_AND_WALL_CLASSES, TABLE, *TABLE_ITEMS, PERSON)}
    models = {label: _cuboid_faces(classes[label], config) for label in labels}
    return World(size, room, tuple(objects), models)


def _bay_surfaces(config: SynthConfig) -> tuple[Surface, ...]:
    """Each bay's north wall, south wall, floor and ceiling (the same four textures in every bay),
    then the two end walls (one texture)."""
    length, width, height = config.bay_size
    total = config.bays * length
    x, y, z = np.eye(3)
    density = config.wall_texels_per_m
    # (texture width, height, texels/m, shape density) of the textures every bay repeats, the end walls'.
    paints = (
        (length, height, density, 1.0),
        (length, height, density, 1.0),
        (length, width, density * 2 / 3, 0.8),
        (length, width, density / 2, 0.4),
        (width, height, density, 1.0),
    )
    textures = [
        paint_texture(np.random.default_rng([config.seed, 5, index]), w, h, texels, shapes)
        for index, (w, h, texels, shapes) in enumerate(paints)
    ]
    # (texture, centre offset from the bay centre, inward normal, right, half width, half height, shade)
    bay_specs = (
        (0, (0, width / 2, height / 2), -y, x, length / 2, height / 2, 0.95),
        (1, (0, -width / 2, height / 2), y, -x, length / 2, height / 2, 0.9),
        (2, (0, 0, 0), z, x, length / 2, width / 2, 0.85),
        (3, (0, 0, height), -z, x, length / 2, width / 2, 0.7),
    )
    pyramids = {
        (index, shade): texture_pyramid(textures[index], shade)
        for index, *_, shade in (*bay_specs, (4, 0.85), (4, 0.8))
    }
    surfaces = []
    for bay in range(config.bays):
        bay_centre = np.array([-total / 2 + (bay + 0.5) * length, 0.0, 0.0])
        for index, offset, normal, right, half_w, half_h, shade in bay_specs:
            corners = quad(bay_centre + offset, normal, right, half_w, half_h)
            surfaces.append(Surface(corners, pyramids[index, shade], paints[index][2]))
    for sign, shade in ((1.0, 0.85), (-1.0, 0.8)):
        corners = quad(
            np.array([sign * total / 2, 0.0, height / 2]), -sign * x, -sign * y, width / 2, height / 2
        )
        surfaces.append(Surface(corners, pyramids[4, shade], density))
    return tuple(surfaces)


def _pack_bay(config: SynthConfig, bay: int) -> list[WorldObject]:
    """Objects along both long walls of one bay (from their own seeded Generator): floor objects side
    by side, wall-mounted ones above them (not over anything as tall), 3-4 items on each table."""
    length, width, _ = config.bay_size
    west = -config.bays * length / 2 + bay * length
    rng = np.random.default_rng([config.seed, 4, bay])
    # Each long wall of the bay: start corner, direction along it, inward normal.
    walls = (
        (np.array([west, width / 2]), np.array([1.0, 0.0]), np.array([0.0, -1.0])),
        (np.array([west + length, -width / 2]), np.array([-1.0, 0.0]), np.array([0.0, 1.0])),
    )
    end = length - BAY_MARGIN
    objects: list[WorldObject] = []
    tables: list[WorldObject] = []
    for start, direction, inward in walls:
        # Floor objects: (start, end, height) along the wall, for the wall-mounted ones to avoid.
        below: list[tuple[float, float, float]] = []
        s = BAY_MARGIN + float(rng.uniform(0.0, 0.3))
        while True:
            fits = [k for k, cls in enumerate(BAY_FLOOR_CLASSES) if s + cls.size[0] <= end]
            if not fits:
                break
            weights = np.array([BAY_FLOOR_WEIGHTS[k] for k in fits])
            cls = BAY_FLOOR_CLASSES[int(rng.choice(fits, p=weights / weights.sum()))]
            obj = _against_wall(cls, start, direction, inward, s, float(rng.uniform(0.03, 0.2)))
            objects.append(obj)
            if cls is TABLE:
                tables.append(obj)
            below.append((s, s + cls.size[0], cls.size[2]))
            s += cls.size[0] + float(rng.uniform(0.05, 0.3))
        s = BAY_MARGIN + float(rng.uniform(0.0, 0.4))
        while True:
            cls = BAY_WALL_CLASSES[int(rng.integers(len(BAY_WALL_CLASSES)))]
            if s + cls.size[0] > end:
                break
            blocked = [b for a, b, h in below if h + 0.02 > cls.elevation and a < s + cls.size[0] and s < b]
            if blocked:
                s = max(blocked) + 0.05
                continue
            objects.append(_against_wall(cls, start, direction, inward, s, 0.02))
            s += cls.size[0] + float(rng.uniform(0.15, 0.5))
    for table in tables:
        for slot in range(int(rng.integers(3, ITEMS_PER_TABLE + 1))):
            cls = TABLE_ITEMS[int(rng.integers(len(TABLE_ITEMS)))]
            objects.append(_on_table(table, cls, slot, rng))
    return objects


def _against_wall(
    cls: ObjectClass, start: np.ndarray, direction: np.ndarray, inward: np.ndarray, s: float, gap: float
) -> WorldObject:
    """``cls`` from ``s`` to ``s + width`` along a wall, ``gap`` in front of it, its front facing inward."""
    w, d, h = cls.size
    xy = start + direction * (s + w / 2) + inward * (gap + d / 2)
    base = cls.elevation if cls.mount == "wall" else 0.0
    return WorldObject(
        cls.label, 0, (float(xy[0]), float(xy[1]), base + h / 2), cls.size, math.atan2(inward[0], -inward[1])
    )


def _place_hall_people(
    config: SynthConfig, rng: np.random.Generator, first_instance: int
) -> list[WorldObject]:
    """People walking across the hall near its end walls, in turn east and west: the camera's lanes run
    along the hall, and people walking alongside them filled the view for seconds at a time, moving
    with the camera (the monocular frontend then lost its scale)."""
    total, width, _ = hall_size(config)
    people = []
    for k in range(config.movable_objects):
        side = 1.0 if k % 2 == 0 else -1.0
        x0 = side * (total / 2 - HALL_PERSON_LANE - min(0.4, 0.2 * (k // 2)))
        amplitude = float(rng.uniform(0.6, 1.0)) * (width / 2 - PERSON_LANE)
        people.append(
            WorldObject(
                PERSON.label,
                first_instance + k,
                (x0, 0.0, PERSON.size[2] / 2),
                PERSON.size,
                math.pi / 2 if side > 0 else -math.pi / 2,
                movable=True,
                amplitude=amplitude,
                period=float(rng.uniform(7.0, 11.0)),
                phase=float(rng.uniform(0, 2 * math.pi)),
            )
        )
    return people
