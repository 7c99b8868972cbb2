"""Smooth camera paths through the synthetic room, sampled at the frame rate.

Camera frame: x right, y down, z forward; poses are camera-to-world. Every path keeps the camera at
about ``camera_height`` with a slight downward pitch and small smooth pitch/roll/height wobbles.

* ``loop``: ``laps`` (default 1.4) laps of an ellipse around the room centre, looking outward at the
  walls (30 deg ahead of radial). Each lap is 7 % wider, 0.1 m higher and 12 deg more yawed than the
  previous one, so the part past one lap revisits the start from a different viewpoint.
* ``figure8``: ``laps`` laps of a lemniscate of Bernoulli with the same per-lap changes; the camera
  looks ahead but turns at 0.6x the heading's rate (less rotation per frame, more sideways parallax).
  The two passes through the centre cross at 90 deg: not a loop.
* ``out-and-back``: along the north wall looking at it, 12 deg ahead of the wall normal, then back
  along the same line (0.12 m further out, 0.1 m higher) looking 12 deg ahead the other way; the
  same spot is seen again with a ~24 deg different yaw.
* ``none``: 0.75 of a loop lap: every part of the room is seen once, nothing is revisited.
* ``hall`` (the bays layout only): back and forth along the hall on two lanes 0.7 m apart (east on
  the south lane, west on the north one), looking at the north wall 18 deg ahead of its normal for
  three legs, then swinging round (174-186 deg, spread over the east turn and 1.3 m either side) to
  the south wall for three legs, and so on. The second leg revisits the first's views from the
  opposite direction (36 deg yaw apart, 0.7 m aside), the third from the same direction (0.12 m
  aside, 6 deg yawed, 0.08 m higher). The geometry is fixed; the path runs ``speed`` x duration
  metres (a leg is ~7 m for 3 bays: 900 frames at 30 fps walk the first three legs).

Speed: paths are sampled at constant speed (out-and-back slows smoothly at its turn). The path is
scaled by ``s = clamp(speed * duration / full_length, 0.5, 1)`` so the mean speed is ``config.speed``
(0.7 m/s) for mid-length sequences (about 350-700 frames for a loop at 30 fps); shorter sequences
move faster (0.8-0.9 m/s at 300 frames), longer ones slower, and the lap count never changes. Below
half size a path would not take the camera the labeller's ``leave_factor * max_distance`` away from
a place before revisiting it. With ``frames >= 300`` the camera turns < 3 deg per frame. ``none``
never comes back to a place it left, so it has no ground-truth loops at any length.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from frontends.errors import ConfigError
from frontends.synth.world import WALL_CLEARANCE, SynthConfig, hall_size

#: Smallest path scale: smaller paths would not leave a place far enough to label its revisit.
MIN_SCALE = 0.5
#: Degrees of yaw added per lap, relative growth of the path per lap, metres of height per lap.
LAP_YAW_DEG, LAP_GROWTH, LAP_RISE = 12.0, 0.07, 0.1
OPEN_LAPS = 0.75
#: The figure8 camera turns at this fraction of the heading's rate, keeping rotation < 3 deg/frame.
FIGURE8_LOOK_GAIN = 0.6
#: Distance from the lobe ends of the figure8 to the short walls at full scale (m).
FIGURE8_END_CLEARANCE = 2.0
OUT_AND_BACK_YAW_DEG = 12.0
#: Dense samples per path used for arc-length reparametrisation.
DENSE = 20000
#: Hall path: lanes at +-HALL_LANE (m) from the hall's axis (their distance stays within the labeller's
#: 1 m max_distance), turns HALL_END_CLEARANCE (m) from the end walls, the camera looking at the wall
#: HALL_AHEAD_DEG ahead of its normal, legs along one wall before swinging to the other.
HALL_LANE, HALL_END_CLEARANCE, HALL_AHEAD_DEG, HALL_LEGS_PER_WALL = 0.35, 1.9, 18.0, 3
#: Per repeated pass (same direction, same wall), cycling 0, +1, -1 times: lateral offset (m), yaw
#: (deg) and height (m).
HALL_PASS_OFFSET, HALL_PASS_YAW_DEG, HALL_PASS_RISE = 0.12, 6.0, 0.08
#: Yaw and height change smoothly over each turn plus this much (m) of the legs either side.
HALL_TRANSITION = 1.3

#: Path shape: (parameter array, scale) -> positions (M, 3), yaw, pitch, roll (rad, each (M,)).
Shape = Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class CameraPath:
    timestamps: np.ndarray
    #: (N, 4, 4) camera-to-world poses.
    poses: np.ndarray
    #: Path size relative to the largest that fits the room.
    scale: float
    length: float

    @property
    def mean_speed(self) -> float:
        return self.length / float(self.timestamps[-1] - self.timestamps[0])

    @property
    def max_rotation_deg(self) -> float:
        """Largest rotation between consecutive frames (deg)."""
        relative = np.einsum("nji,njk->nik", self.poses[:-1, :3, :3], self.poses[1:, :3, :3])
        cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
        return float(np.degrees(np.arccos(cos)).max())


def frame_timestamps(config: SynthConfig) -> np.ndarray:
    """``start_time + i / fps`` rounded to the 6 decimals the files carry."""
    return np.round(config.start_time + np.arange(config.frames) / config.fps, 6)


def camera_path(config: SynthConfig) -> CameraPath:
    timestamps = frame_timestamps(config)
    duration = float(timestamps[-1] - timestamps[0])
    sx, sy, _ = config.room_size
    rx, ry = sx / 2 - WALL_CLEARANCE, sy / 2 - WALL_CLEARANCE
    if config.trajectory == "out-and-back":
        return _out_and_back(config, timestamps, duration)
    if config.trajectory == "hall":
        return _hall(config, timestamps, duration)
    if config.layout == "bays":
        raise ConfigError(f"synth config: layout bays needs trajectory hall, not {config.trajectory}")
    shapes: dict[str, tuple[Shape, float]] = {
        "loop": (_loop_shape(config, rx, ry, config.laps), config.laps),
        "figure8": (_figure8_shape(config, sx / 2 - FIGURE8_END_CLEARANCE, config.laps), config.laps),
        "none": (_loop_shape(config, rx, ry, OPEN_LAPS), OPEN_LAPS),
    }
    shape, laps = shapes[config.trajectory]
    phi = np.linspace(0.0, 2 * math.pi * laps, DENSE)
    full_length = _arc_length(shape(phi, 1.0)[0])[-1]
    scale = float(np.clip(config.speed * duration / full_length, MIN_SCALE, 1.0))
    arc = _arc_length(shape(phi, scale)[0])
    # Constant speed: equal arc-length steps between frames.
    phi_frames = np.interp(np.linspace(0.0, arc[-1], config.frames), arc, phi)
    positions, yaw, pitch, roll = shape(phi_frames, scale)
    return CameraPath(timestamps, _poses(positions, yaw, pitch, roll), scale, float(arc[-1]))


def _arc_length(positions: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _wobble(config: SynthConfig, phi: np.ndarray, lap: np.ndarray, laps: float) -> tuple[np.ndarray, ...]:
    """Height, pitch and roll: per-lap rise plus small wobbles at frequencies that differ per lap."""
    height = config.camera_height + LAP_RISE * (lap - laps / 2) + 0.03 * np.sin(2.3 * phi + 0.4)
    pitch = np.radians(config.camera_pitch_deg + 2.0 * np.sin(1.7 * phi + 0.3))
    roll = np.radians(1.5 * np.sin(1.3 * phi + 1.1))
    return height, pitch, roll


def _loop_shape(config: SynthConfig, rx: float, ry: float, laps: float) -> Shape:
    def shape(phi: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        lap = phi / (2 * math.pi)
        growth = scale * (1 + LAP_GROWTH * (lap - laps / 2))
        height, pitch, roll = _wobble(config, phi, lap, laps)
        positions = np.stack([rx * growth * np.cos(phi), ry * growth * np.sin(phi), height], axis=1)
        yaw = phi + np.radians(30.0 - LAP_YAW_DEG * (lap - laps / 2))
        return positions, yaw, pitch, roll

    return shape


def _figure8_shape(config: SynthConfig, half_width: float, laps: float) -> Shape:
    def planar(phi: np.ndarray, scale: float) -> np.ndarray:
        # Lemniscate of Bernoulli, x = a cos / (1 + sin^2), y = a sin cos / (1 + sin^2), growing per lap.
        lap = phi / (2 * math.pi)
        a = half_width * scale * (1 + LAP_GROWTH * (lap - laps / 2))
        denominator = 1 + np.sin(phi) ** 2
        return np.stack([a * np.cos(phi) / denominator, a * np.sin(phi) * np.cos(phi) / denominator], axis=1)

    def shape(phi: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        lap = phi / (2 * math.pi)
        height, pitch, roll = _wobble(config, phi, lap, laps)
        xy = planar(phi, scale)
        tangent = planar(phi + 1e-5, scale) - planar(phi - 1e-5, scale)
        heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
        yaw = FIGURE8_LOOK_GAIN * heading + np.radians(-LAP_YAW_DEG * (lap - laps / 2))
        return np.column_stack([xy, height]), yaw, pitch, roll

    return shape


def _out_and_back(config: SynthConfig, timestamps: np.ndarray, duration: float) -> CameraPath:
    sx, sy, _ = config.room_size
    max_length = sx - 2 * (WALL_CLEARANCE - 0.2)
    scale = float(np.clip(config.speed * duration / (2 * max_length), MIN_SCALE, 1.0))
    half = scale * max_length / 2
    u = (timestamps - timestamps[0]) / duration
    # Smoothed triangle 0 -> 1 -> 0: constant speed except a smooth turn around u = 0.5.
    eps = 0.08
    along = 1 - (np.sqrt((1 - 2 * u) ** 2 + eps**2) - eps) / (math.sqrt(1 + eps**2) - eps)
    back = (1 - np.cos(math.pi * u)) / 2
    y_route = sy / 2 - WALL_CLEARANCE
    positions = np.stack(
        [
            -half + 2 * half * along,
            y_route - 0.12 * back,
            config.camera_height + 0.1 * back + 0.03 * np.sin(2 * math.pi * 1.3 * u),
        ],
        axis=1,
    )
    yaw = np.radians(90.0 - OUT_AND_BACK_YAW_DEG * (1 - 2 * back))
    pitch = np.radians(config.camera_pitch_deg + 2.0 * np.sin(2 * math.pi * 1.7 * u + 0.3))
    roll = np.radians(1.5 * np.sin(2 * math.pi * 1.3 * u + 1.1))
    length = float(_arc_length(positions)[-1])
    return CameraPath(timestamps, _poses(positions, yaw, pitch, roll), scale, length)


def hall_legs(count: int) -> list[tuple[int, int, int]]:
    """(direction: +1 east / -1 west, wall: +1 north / -1 south, pass offset factor) of the first
    ``count`` legs: east and west in turn, HALL_LEGS_PER_WALL legs along each wall, every repeat of a
    (direction, wall) pair offset by 0, +1, -1, 0, ... times the pass offsets."""
    legs: list[tuple[int, int, int]] = []
    passes: dict[tuple[int, int], int] = {}
    for i in range(count):
        direction = 1 if i % 2 == 0 else -1
        wall = 1 if (i // HALL_LEGS_PER_WALL) % 2 == 0 else -1
        seen = passes.get((direction, wall), 0)
        passes[direction, wall] = seen + 1
        legs.append((direction, wall, (0, 1, -1)[seen % 3]))
    return legs


def _hall(config: SynthConfig, timestamps: np.ndarray, duration: float) -> CameraPath:
    """Back and forth along the bays layout's hall on two lanes, counter-clockwise, looking at one wall
    (HALL_AHEAD_DEG ahead) for HALL_LEGS_PER_WALL legs, then at the other; as far as ``speed`` goes."""
    total, _, _ = hall_size(config)
    half = total / 2 - HALL_END_CLEARANCE
    leg_length = 2 * half
    length = config.speed * duration
    # Enough legs for the length (a turn is at least pi * (HALL_LANE - HALL_PASS_OFFSET) long).
    count = int(length / leg_length) + 2
    legs = hall_legs(count)
    lanes = [direction * -HALL_LANE + factor * HALL_PASS_OFFSET for direction, _, factor in legs]
    ahead = math.radians(HALL_AHEAD_DEG)
    yaws = [
        wall * math.pi / 2 - direction * wall * ahead + math.radians(factor * HALL_PASS_YAW_DEG)
        for direction, wall, factor in legs
    ]
    # The shortest yaw change from leg to leg, a half turn counter-clockwise (with the path).
    for i in range(1, count):
        change = (yaws[i] - yaws[i - 1] + math.pi) % (2 * math.pi) - math.pi
        yaws[i] = yaws[i - 1] + (math.pi if change == -math.pi else change)
    rises = [factor * HALL_PASS_RISE for _, _, factor in legs]
    pieces, turn_middles = [], []
    arc_start = 0.0
    per_leg = max(2, DENSE // count)
    for i, (direction, _, _) in enumerate(legs):
        x = np.linspace(-direction * half, direction * half, per_leg)
        pieces.append(np.column_stack([x, np.full(per_leg, lanes[i])]))
        if i + 1 < count:
            # Half circle from this lane to the next around the end: east ends bulge east, west ends west.
            radius = abs(lanes[i + 1] - lanes[i]) / 2
            centre_y = (lanes[i + 1] + lanes[i]) / 2
            theta = np.linspace(0.0, math.pi, max(64, per_leg // 4))[1:-1]
            turn_x = direction * (half + radius * np.sin(theta))
            turn_y = centre_y - direction * radius * np.cos(theta)
            pieces.append(np.column_stack([turn_x, turn_y]))
            arc_start += leg_length
            turn_middles.append(arc_start + math.pi * radius / 2)
            arc_start += math.pi * radius
    planar = np.concatenate(pieces)
    arc = _arc_length(planar)
    s = np.linspace(0.0, length, config.frames)
    xy = np.column_stack([np.interp(s, arc, planar[:, 0]), np.interp(s, arc, planar[:, 1])])
    yaw = _smooth_steps(s, yaws, turn_middles)
    phi = s / 1.8
    height = config.camera_height + _smooth_steps(s, rises, turn_middles) + 0.03 * np.sin(2.3 * phi + 0.4)
    pitch = np.radians(config.camera_pitch_deg + 2.0 * np.sin(1.7 * phi + 0.3))
    roll = np.radians(1.5 * np.sin(1.3 * phi + 1.1))
    positions = np.column_stack([xy, height])
    return CameraPath(timestamps, _poses(positions, yaw, pitch, roll), 1.0, float(_arc_length(positions)[-1]))


def _smooth_steps(s: np.ndarray, values: list[float], middles: list[float]) -> np.ndarray:
    """``values[0]`` stepping smoothly (half cosine) to each next value around each of ``middles``;
    a step spans the turn (about pi * HALL_LANE) and HALL_TRANSITION either side."""
    width = math.pi * HALL_LANE + 2 * HALL_TRANSITION
    result = np.full(len(s), values[0])
    for i, middle in enumerate(middles):
        u = np.clip((s - middle) / width + 0.5, 0.0, 1.0)
        result += (values[i + 1] - values[i]) * (1 - np.cos(math.pi * u)) / 2
    return result


def _poses(positions: np.ndarray, yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world poses: R = Rz(yaw) Ry(-pitch) Rx(roll) B, B mapping camera axes to x-forward."""
    n = len(positions)
    base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cy, sy_ = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(-pitch), np.sin(-pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    zeros, ones = np.zeros(n), np.ones(n)
    rz = np.stack([cy, -sy_, zeros, sy_, cy, zeros, zeros, zeros, ones], axis=1).reshape(n, 3, 3)
    ry = np.stack([cp, zeros, sp, zeros, ones, zeros, -sp, zeros, cp], axis=1).reshape(n, 3, 3)
    rx = np.stack([ones, zeros, zeros, zeros, cr, -sr, zeros, sr, cr], axis=1).reshape(n, 3, 3)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rz @ ry @ rx @ base
    poses[:, :3, 3] = positions
    return poses
