"""Deterministic synthetic multi-object loop scenes for testing the SLAM and loop-closure pipeline.

A textured room (``world``) with COCO-labelled cuboid objects, some classes repeated and identical
(perceptual aliasing), and people walking in lanes (movable objects a detector must filter), or a hall
of bays with identical textures that only their objects tell apart (``layout: bays``), seen along a
smooth camera path (``trajectories``: loop, figure8, out-and-back, none; hall for the bays) by a 640x480
pinhole camera rendered with a z-buffered polygon rasteriser with exposure drift, blur and noise
(``render``). ``writer`` stores it in the TUM RGB-D layout with ground-truth poses, per-frame object
boxes and ground-truth loop pairs. All randomness comes from numpy Generators seeded by
``SynthConfig.seed``: the same config gives byte-identical files.
"""

from frontends.synth.render import GtObject, SceneRenderer, render_frames
from frontends.synth.world import SynthConfig
from frontends.synth.writer import cached_scene, write_scene

__all__ = ["GtObject", "SceneRenderer", "SynthConfig", "cached_scene", "render_frames", "write_scene"]
