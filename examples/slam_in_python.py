"""A full monocular SLAM run from Python, with a loop-detector object of your own (``slam_backend.Slam``).

The scene is a seeded 320x240 synthetic loop (``frontends.synth``: images, GT poses and GT objects, which the
``oracle`` object detector reports). The loop detector is a ``SymbioLCD2`` built here with our own
config (3 WL iterations instead of 10); any object with the ``lcd.base.LoopDetector`` methods works.
Everything else is the default system: mono-vo, the pycolmap verifier, the GTSAM backend.

Run: ``python examples/slam_in_python.py [--frames 600] [--out slam_out]``
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from frontends.datasets import open_dataset
from frontends.synth import SynthConfig, write_scene
from lcd.symbiolcd2 import SymbioLCD2, SymbioLCD2Config
from slam_backend import Slam


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--out", type=Path, help="also save the result there")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scene:
        small = {"width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}
        write_scene(SynthConfig(seed=3, frames=args.frames, **small), Path(scene), progress=False)
        dataset = open_dataset(scene)

        # -- the SLAM run: build, track every frame, finish ----------------------------------------
        detector = SymbioLCD2(SymbioLCD2Config(iterations=3), name="my-symbiolcd2")
        slam = Slam(dataset.camera, loop_detector=detector, object_detector="oracle")
        for frame in dataset:
            slam.track(frame)
        result = slam.finish()
        # ------------------------------------------------------------------------------------------

    accepted = [loop for loop in result.loops if loop.accepted]
    print(f"detector: {result.figures['detector']}")
    print(f"frames tracked: {result.figures['frames_tracked']} of {result.figures['frames']}")
    print(f"keyframes: {len(result.keyframes)}")
    print(f"loops accepted: {len(accepted)} of {len(result.loops)} verified candidates")
    print(f"corrected poses: {len(result.trajectory)}")
    if args.out is not None:
        print("wrote " + ", ".join(str(path) for path in result.save(args.out)))


if __name__ == "__main__":
    main()
