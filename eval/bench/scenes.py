"""The synthetic scenes every benchmark grids over, made one way: ``symbio synth`` scenes of a
trajectory kind and seed, rendered once into a folder cache (``scene_folder``) or into memory
(``scene_frames``), and the ``--trajectories`` / ``--seeds`` options that name them."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from frontends.errors import ConfigError
from frontends.synth import SynthConfig, cached_scene
from frontends.synth.render import SceneRenderer
from frontends.types import CameraIntrinsics, Frame

#: The trajectory kinds of the benchmark grid (``symbio synth --trajectory``).
TRAJECTORIES = "loop,figure8,out-and-back"


def scene_config(trajectory: str, seed: int, frames: int) -> SynthConfig:
    """The 640x480 scene of ``trajectory`` and ``seed`` with ``frames`` frames (30 fps)."""
    return SynthConfig(trajectory=trajectory, seed=seed, frames=frames)  # type: ignore[arg-type]


def scene_folder(work: Path, trajectory: str, seed: int, frames: int) -> Path:
    """The scene as a dataset folder under ``work``, rendered unless it is there already."""
    return cached_scene(scene_config(trajectory, seed, frames), work / f"{trajectory}_{seed}_{frames}")


def scene_frames(
    trajectory: str, seed: int, frames: int, rendered_frames: int | None = None
) -> tuple[CameraIntrinsics, list[Frame], list[list[tuple[int, int, int, int]]]]:
    """The scene in memory: its camera, grey frames (with GT poses) and, per frame, the boxes of the
    movable objects (walking people); only the first ``rendered_frames`` of it, if given."""
    config = scene_config(trajectory, seed, frames)
    renderer = SceneRenderer(config)
    result, movable = [], []
    for index in range(frames if rendered_frames is None else min(rendered_frames, frames)):
        rendered = renderer.frame(index)
        # Grey copies: the renderer reuses its buffers, and 600 colour frames would need 0.5 GB.
        gray = cv2.cvtColor(rendered.image, cv2.COLOR_BGR2GRAY)
        result.append(Frame(index, rendered.timestamp, gray, None, rendered.pose.copy()))
        movable.append([obj.box for obj in rendered.objects if obj.movable])
    return config.intrinsics, result, movable


def parse_seeds(text: str) -> list[int]:
    """``0,1,2`` or ``0-6`` (or a mix: ``0-2,5``)."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            first, dash, last = part.partition("-")
            seeds += list(range(int(first), int(last) + 1)) if dash else [int(first)]
    except ValueError:
        raise ConfigError(f"seeds must look like 0,1,2 or 0-6, got {text!r}") from None
    return seeds


def add_grid_options(parser: argparse.ArgumentParser, seeds: str) -> None:
    """``--trajectories`` and ``--seeds`` (default ``seeds``) of a benchmark over the scene grid."""
    parser.add_argument("--trajectories", default=TRAJECTORIES, help=f"kinds (default {TRAJECTORIES})")
    parser.add_argument("--seeds", default=seeds, help=f"scene seeds: 0,1,2 or 0-6 (default {seeds})")
