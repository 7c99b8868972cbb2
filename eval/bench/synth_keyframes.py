"""Keyframes straight from the synthetic renderer, with ground-truth map points (verifier tests).

The rasteriser's inverse-depth buffer gives each ORB keypoint its exact depth, so
``Keyframe.points3d`` is what a perfect frontend would have triangulated (up to the keypoint's
pixel rounding; keypoints on depth edges take the nearer surface's neighbour pixel).
"""

from __future__ import annotations

import cv2
import numpy as np

from frontends.orb import OrbConfig, extract_orb
from frontends.synth.render import SceneRenderer
from frontends.types import CameraIntrinsics, Keyframe


def scene_camera(renderer: SceneRenderer) -> CameraIntrinsics:
    c = renderer.config
    return CameraIntrinsics(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, width=c.width, height=c.height)


def keyframe_with_depth(
    renderer: SceneRenderer, frame_index: int, keyframe_id: int, orb: OrbConfig | None = None
) -> Keyframe:
    """Render ``frame_index`` and return it as a keyframe with GT pose and GT map points."""
    frame = renderer.frame(frame_index)
    inverse_depth = renderer.rasteriser.inverse_depth
    gray = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
    keypoints, descriptors = extract_orb(gray, orb or OrbConfig())
    c = renderer.config
    columns = np.clip(np.round(keypoints[:, 0]).astype(np.int64), 0, c.width - 1)
    rows = np.clip(np.round(keypoints[:, 1]).astype(np.int64), 0, c.height - 1)
    inverse = inverse_depth[rows, columns].astype(np.float64)
    depth = np.where(inverse > 0, 1.0 / np.maximum(inverse, 1e-12), np.nan)
    points = np.column_stack(
        [(keypoints[:, 0] - c.cx) / c.fx * depth, (keypoints[:, 1] - c.cy) / c.fy * depth, depth]
    )
    return Keyframe(
        keyframe_id, frame_index, frame.timestamp, frame.pose, keypoints, descriptors, (), frame.image, points
    )
