"""Z-buffered rendering of textured planar quads, sensor effects and per-frame ground-truth objects.

Each front-facing quad (room surfaces, cuboid faces) is clipped against the near plane in 3D
(Sutherland-Hodgman), projected and clipped to the image, and rasterised into its bounding rect with
``cv2.fillConvexPoly`` at 1/16 pixel precision. Its inverse depth is affine in the pixel
coordinates (1/z = n . K^-1 [u, v, 1] / d for the plane n . X = d in camera coordinates), so the
z-test against an inverse-depth buffer is exact per pixel. Only where the face wins is the texture
warped in (``cv2.warpPerspective`` with the texture-to-image homography, from the pyramid level whose
texel size matches the pixel size) and the colour, inverse depth and instance id written. Objects are
drawn nearest first and the room last, so occluded areas are mostly rejected before any warping.

Sensor model, applied in this order: a smooth exposure gain ``1 + A sin(2 pi t / P + phi)`` (plus a
small second harmonic) as a lookup table, Gaussian optical blur, and additive Gaussian noise. The
noise comes from a bank of images drawn once from the seeded numpy Generator; each frame uses one
of them at a random offset chosen by ``default_rng([seed, frame_index])`` (fresh noise per frame
costs more than the rendering). OpenCV's global RNG is never used, so output depends only on the
config.

Ground truth per frame: the visible pixels of each object in the instance buffer, their bounding
box, and the fraction of the object's unoccluded in-image silhouette (the union of its front faces'
polygons) they make up.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from frontends.synth.covisibility import depth_grid
from frontends.synth.trajectories import CameraPath, camera_path
from frontends.synth.world import Surface, SynthConfig, World, WorldObject, build_world

#: Fixed-point bits for cv2.fillConvexPoly (1/16 pixel).
SHIFT = 4
NOISE_BANK = 6
NOISE_PAD = 16


@dataclass(frozen=True)
class GtObject:
    """One object as seen in one frame."""

    label: str
    instance: int
    #: Bounding box of the visible pixels (x0, y0, x1, y1), x1/y1 exclusive.
    box: tuple[int, int, int, int]
    #: Visible pixels / pixels of the unoccluded silhouette inside the image.
    visible_fraction: float
    movable: bool
    pixels: int


@dataclass(frozen=True)
class RenderedFrame:
    index: int
    timestamp: float
    #: Camera-to-world pose (4x4).
    pose: np.ndarray
    image: np.ndarray
    #: Instance id per pixel (0: room).
    instances: np.ndarray
    objects: tuple[GtObject, ...]


@dataclass(frozen=True)
class _Face:
    corners: np.ndarray
    #: Outward unit normal.
    normal: np.ndarray
    surface: Surface
    instance: int


class Rasteriser:
    """Draws textured quads into colour, inverse-depth and instance buffers of one frame."""

    def __init__(self, config: SynthConfig) -> None:
        self.width, self.height = config.width, config.height
        self.fx, self.fy, self.cx, self.cy = config.fx, config.fy, config.cx, config.cy
        self.K = config.intrinsics.K
        self.near = config.near
        self.image = np.zeros((self.height, self.width, 3), np.uint8)
        self.inverse_depth = np.zeros((self.height, self.width), np.float32)
        self.instances = np.zeros((self.height, self.width), np.uint16)
        self.columns = np.arange(self.width, dtype=np.float32)
        self.rows = np.arange(self.height, dtype=np.float32)
        #: Fixed-point polygons drawn per instance this frame, for the silhouettes.
        self.polygons: dict[int, list[np.ndarray]] = {}

    def clear(self) -> None:
        self.image[:] = 0
        self.inverse_depth[:] = 0
        self.instances[:] = 0
        self.polygons = {}

    def draw(self, face: _Face, world_to_camera: np.ndarray) -> None:
        rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
        camera_points = face.corners @ rotation.T + translation
        normal = rotation @ face.normal
        # Plane n . X = d in camera coordinates; d < 0 when the camera sees the front side.
        d = float(normal @ camera_points[0])
        if d >= -1e-9:
            return
        polygon = _clip_near(camera_points, self.near)
        if len(polygon) < 3:
            return
        pixels = np.column_stack(
            [
                self.fx * polygon[:, 0] / polygon[:, 2] + self.cx,
                self.fy * polygon[:, 1] / polygon[:, 2] + self.cy,
            ]
        )
        pixels = _clip_to_image(pixels, self.width, self.height)
        if len(pixels) < 3:
            return
        x0, y0 = (max(0, math.floor(v)) for v in pixels.min(axis=0))
        x1 = min(self.width, math.ceil(pixels[:, 0].max()) + 1)
        y1 = min(self.height, math.ceil(pixels[:, 1].max()) + 1)
        if x0 >= x1 or y0 >= y1:
            return
        fixed = np.round(pixels * (1 << SHIFT)).astype(np.int32)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, fixed - np.array([x0, y0], np.int32) * (1 << SHIFT), 1, cv2.LINE_8, SHIFT)
        if face.instance:
            self.polygons.setdefault(face.instance, []).append(fixed)
        a = normal[0] / (self.fx * d)
        b = normal[1] / (self.fy * d)
        c = (normal[2] - normal[0] * self.cx / self.fx - normal[1] * self.cy / self.fy) / d
        row_part = np.float32(b) * self.rows[y0:y1] + np.float32(c)
        inverse_depth = row_part[:, None] + np.float32(a) * self.columns[None, x0:x1]
        depth_view = self.inverse_depth[y0:y1, x0:x1]
        win = mask.view(bool) & (inverse_depth > depth_view)
        bx, by, bw, bh = cv2.boundingRect(win.view(np.uint8))
        if bw == 0:
            return
        win = win[by : by + bh, bx : bx + bw]
        np.copyto(
            depth_view[by : by + bh, bx : bx + bw], inverse_depth[by : by + bh, bx : bx + bw], where=win
        )
        self.instances[y0 + by : y0 + by + bh, x0 + bx : x0 + bx + bw][win] = face.instance
        texture, homography = self._texture_homography(face, camera_points, x0 + bx, y0 + by, bw, bh)
        warped = cv2.warpPerspective(
            texture, homography, (bw, bh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        np.copyto(self.image[y0 + by : y0 + by + bh, x0 + bx : x0 + bx + bw], warped, where=win[:, :, None])

    def _texture_homography(
        self, face: _Face, camera_points: np.ndarray, left: int, top: int, width: int, height: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pyramid level matching the pixel size at the rect's centre and its homography into the rect."""
        surface = face.surface
        base_h, base_w = surface.pyramid[0].shape[:2]
        origin = camera_points[0]
        columns = np.column_stack(
            [(camera_points[1] - origin) / base_w, (camera_points[3] - origin) / base_h, origin]
        )
        to_image = self.K @ columns
        # Texels per pixel at the rect centre: sqrt |det| of the image-to-texture Jacobian.
        inverse = np.linalg.inv(to_image)
        q = inverse @ np.array([left + width / 2, top + height / 2, 1.0])
        jacobian = (inverse[:2, :2] * q[2] - np.outer(q[:2], inverse[2, :2])) / (q[2] * q[2])
        texels = math.sqrt(abs(float(np.linalg.det(jacobian))))
        level = min(len(surface.pyramid) - 1, max(0, math.floor(math.log2(max(texels, 1e-9)) + 0.5)))
        scale = float(1 << level)
        to_rect = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
        return surface.pyramid[level], to_rect @ to_image @ np.diag([scale, scale, 1.0])

    def silhouette_pixels(self, instance: int) -> int:
        """Pixels of the union of the polygons drawn for ``instance`` (its unoccluded in-image silhouette)."""
        polygons = self.polygons[instance]
        stacked = np.concatenate(polygons)
        low = np.maximum(stacked.min(axis=0) >> SHIFT, 0)
        high = np.minimum((stacked.max(axis=0) >> SHIFT) + 2, [self.width, self.height])
        mask = np.zeros((int(high[1] - low[1]), int(high[0] - low[0])), np.uint8)
        offset = (low * (1 << SHIFT)).astype(np.int32)
        for polygon in polygons:
            cv2.fillConvexPoly(mask, polygon - offset, 1, cv2.LINE_8, SHIFT)
        return int(cv2.countNonZero(mask))


def _clip_near(points: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a convex polygon (camera coordinates) to z >= near."""
    inside = points[:, 2] >= near
    if inside.all():
        return points
    out = []
    for i in range(len(points)):
        a, b = points[i], points[(i + 1) % len(points)]
        if inside[i]:
            out.append(a)
        if inside[i] != inside[(i + 1) % len(points)]:
            out.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out).reshape(-1, 3)


def _clip_to_image(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """Clip a convex polygon to a margin around the image, keeping fixed-point coordinates small."""
    low, high = -2.0, (width + 1.0, height + 1.0)
    if pixels.min() >= low and pixels[:, 0].max() <= high[0] and pixels[:, 1].max() <= high[1]:
        return pixels
    polygon = pixels
    for axis, bound, keep_greater in (
        (0, low, True),
        (0, high[0], False),
        (1, low, True),
        (1, high[1], False),
    ):
        if len(polygon) == 0:
            break
        values = polygon[:, axis] - bound
        inside = values >= 0 if keep_greater else values <= 0
        out = []
        for i in range(len(polygon)):
            j = (i + 1) % len(polygon)
            if inside[i]:
                out.append(polygon[i])
            if inside[i] != inside[j]:
                out.append(polygon[i] + values[i] / (values[i] - values[j]) * (polygon[j] - polygon[i]))
        polygon = np.array(out).reshape(-1, 2)
    return polygon


class SceneRenderer:
    """A synthetic scene: world, camera path and renderer; ``frame(i)`` renders frame ``i``."""

    def __init__(self, config: SynthConfig) -> None:
        self.config = config
        self.world: World = build_world(config)
        self.path: CameraPath = camera_path(config)
        self.rasteriser = Rasteriser(config)
        self.room_faces = tuple(_Face(s.corners, _normal(s.corners), s, 0) for s in self.world.room)
        self.static_faces = {
            obj.instance: _object_faces(self.world, obj, 0.0) for obj in self.world.objects if not obj.movable
        }
        self.movable_instances = np.array([obj.instance for obj in self.world.objects if obj.movable])
        rng = np.random.default_rng([config.seed, 3])
        noise = rng.normal(
            0.0, config.noise_sigma, (NOISE_BANK, config.height + NOISE_PAD, config.width + NOISE_PAD, 3)
        )
        noise = np.clip(np.round(noise), -255, 255)
        self.noise_positive = np.clip(noise, 0, 255).astype(np.uint8)
        self.noise_negative = np.clip(-noise, 0, 255).astype(np.uint8)
        self.exposure_phase = rng.uniform(0, 2 * math.pi, 2)

    def frame(self, index: int) -> RenderedFrame:
        t = float(self.path.timestamps[index])
        pose = self.path.poses[index]
        world_to_camera = np.linalg.inv(pose)
        raster = self.rasteriser
        raster.clear()
        centre = pose[:3, 3]
        # Front to back: objects by distance, then the room (whose faces never overlap each other).
        objects = sorted(self.world.objects, key=lambda o: float(np.linalg.norm(o.centre_at(t) - centre)))
        for obj in objects:
            faces = _object_faces(self.world, obj, t) if obj.movable else self.static_faces[obj.instance]
            for face in faces:
                raster.draw(face, world_to_camera)
        for face in self.room_faces:
            raster.draw(face, world_to_camera)
        image = self._sensor(raster.image, t, index)
        return RenderedFrame(
            index, t, pose, image, raster.instances.copy(), self._ground_truth(raster, objects)
        )

    def depth_samples(self, step: int) -> np.ndarray:
        """The last rendered frame's inverse depth on a ``step``-pixel grid (for covisibility),
        -1 where a movable object (a walking person) hides the static scene."""
        raster = self.rasteriser
        return depth_grid(raster.inverse_depth, step, raster.instances, self.movable_instances)

    def _sensor(self, image: np.ndarray, t: float, index: int) -> np.ndarray:
        config = self.config
        phase = 2 * math.pi * t / config.exposure_period
        wave = math.sin(phase + self.exposure_phase[0]) + 0.3 * math.sin(2.7 * phase + self.exposure_phase[1])
        gain = 1.0 + config.exposure_amplitude * wave / 1.3
        table = np.clip(np.round(np.arange(256) * gain), 0, 255).astype(np.uint8)
        out = cv2.LUT(image, table)
        if config.blur_sigma > 0:
            out = cv2.GaussianBlur(out, (0, 0), config.blur_sigma)
        rng = np.random.default_rng([config.seed, index])
        k = int(rng.integers(NOISE_BANK))
        dy, dx = (int(v) for v in rng.integers(0, NOISE_PAD + 1, 2))
        window = (slice(dy, dy + config.height), slice(dx, dx + config.width))
        out = cv2.add(out, self.noise_positive[k][window])
        return cv2.subtract(out, self.noise_negative[k][window])

    def _ground_truth(self, raster: Rasteriser, objects: list[WorldObject]) -> tuple[GtObject, ...]:
        found = []
        for obj in sorted(objects, key=lambda o: o.instance):
            if obj.instance not in raster.polygons:
                continue
            # Every visible pixel of an object lies inside the bounds of the polygons drawn for it.
            stacked = np.concatenate(raster.polygons[obj.instance]) >> SHIFT
            x0, y0 = np.maximum(stacked.min(axis=0) - 1, 0)
            x1, y1 = np.minimum(stacked.max(axis=0) + 2, [self.config.width, self.config.height])
            mine = raster.instances[y0:y1, x0:x1] == obj.instance
            visible = int(np.count_nonzero(mine))
            if visible < self.config.min_visible_pixels:
                continue
            silhouette = raster.silhouette_pixels(obj.instance)
            rows, columns = np.flatnonzero(mine.any(axis=1)), np.flatnonzero(mine.any(axis=0))
            box = (int(x0 + columns[0]), int(y0 + rows[0]), int(x0 + columns[-1] + 1), int(y0 + rows[-1] + 1))
            fraction = min(1.0, visible / max(silhouette, 1))
            found.append(GtObject(obj.label, obj.instance, box, fraction, obj.movable, visible))
        return tuple(found)


def _normal(corners: np.ndarray) -> np.ndarray:
    normal = np.cross(corners[1] - corners[0], corners[0] - corners[3])
    return normal / np.linalg.norm(normal)


def _object_faces(world: World, obj: WorldObject, t: float) -> tuple[_Face, ...]:
    transform = obj.transform_at(t)
    faces = []
    for surface in world.models[obj.label]:
        corners = surface.corners @ transform[:3, :3].T + transform[:3, 3]
        faces.append(_Face(corners, _normal(corners), surface, obj.instance))
    return tuple(faces)


def render_frames(config: SynthConfig) -> Iterator[tuple[np.ndarray, np.ndarray, tuple[GtObject, ...]]]:
    """(camera-to-world pose, BGR image, visible objects) for every frame, without touching the disk."""
    scene = SceneRenderer(config)
    for index in range(config.frames):
        frame = scene.frame(index)
        yield frame.pose, frame.image, frame.objects
