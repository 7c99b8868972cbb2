"""SymbioLCD2 on two images: the loop score, its parts, and the three-tier graphs behind it.

Without arguments, two views of a synthetic room (``frontends.synth``) are rendered: a frame of the
second lap and the ground-truth revisited frame of the first lap nearest to it; their objects are
the renderer's ground truth (what the ``oracle`` object detector reports on written scenes).
With two image paths, those images are used and their objects come from an object detector
(``--object-detector``, default ``ssd-mobilenet``; ``none`` for features only); the two images
are taken to be a minute apart, so the temporal penalty is negligible.

For each image: ORB features (``frontends.orb.extract_orb``), objects, a ``Keyframe``. Both go to
``lcd.symbiolcd2.create(["temporal_window=0", "idf_power=0"])``: the default window of 10 keyframes
would hide the first keyframe from the second, and two images are no database to weigh words by
(the default idf^2 gives every label both images hold the weight ln(2/2) = 0), so this scores with
the paper's plain kernel. The second ``add`` returns the candidate "keyframe 1 revisits
keyframe 0" with score = WL kernel - temporal penalty.

Run: ``python examples/symbiolcd2_two_images.py [IMAGE_A IMAGE_B] [--object-detector NAME]``
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import cv2
import numpy as np

from frontends.gt_loops import LoopLabelConfig, label_loop_pairs
from frontends.orb import extract_orb
from frontends.synth import SceneRenderer, SynthConfig
from frontends.types import DetectedObject, Keyframe
from lcd import symbiolcd2
from lcd.base import OBJECT_DETECTORS

# A 20 s synthetic loop (1.4 laps): frames 400+ revisit the start of the first lap.
SCENE = SynthConfig(seed=1, trajectory="loop", frames=600)
QUERY_FRAME = 475
SECONDS_APART = 60.0  # assumed time between two images given on the command line
#: Revisits by camera pose (0.6 m, 30 deg): enough to pick a reference without rendering every
#: frame's depth, as ``symbio synth``'s covisibility labels do.
REVISIT = LoopLabelConfig(max_distance=0.6, max_angle_deg=30.0, min_time_gap=3.0, leave_factor=2.0)

#: One image as the detector needs it: (BGR image, objects, timestamp in s, camera-to-world pose).
View = tuple[np.ndarray, tuple[DetectedObject, ...], float, np.ndarray]


def synthetic_views() -> list[View]:
    """The nearest GT revisited frame of the first lap, then the query frame, with GT objects."""
    scene = SceneRenderer(SCENE)
    poses, times = scene.path.poses, scene.path.timestamps
    pairs = label_loop_pairs(poses, times, REVISIT)
    references = pairs[pairs[:, 0] == QUERY_FRAME, 1]
    if references.size == 0:
        raise SystemExit(f"frame {QUERY_FRAME} revisits nothing in this scene; pick another")
    distances = np.linalg.norm(poses[references, :3, 3] - poses[QUERY_FRAME, :3, 3], axis=1)
    reference = int(references[np.argmin(distances)])
    print(
        f"synthetic scene seed {SCENE.seed}: frame {QUERY_FRAME} revisits frames "
        f"{references.min()}-{references.max()}; using the nearest, {reference} "
        f"({distances.min():.2f} m away)"
    )
    views = []
    for index in (reference, QUERY_FRAME):
        frame = scene.frame(index)
        objects = tuple(
            DetectedObject(o.label, 1.0, o.box, None, o.instance, o.visible_fraction) for o in frame.objects
        )
        views.append((frame.image, objects, frame.timestamp, frame.pose))
    return views


def image_views(paths: Sequence[str], object_detector: str) -> list[View]:
    detector = OBJECT_DETECTORS.load(object_detector)()
    views = []
    for k, path in enumerate(paths):
        image = cv2.imread(path, cv2.IMREAD_COLOR)
        if image is None:
            raise SystemExit(f"{path}: not a readable image")
        views.append((image, tuple(detector.detect(image)), k * SECONDS_APART, np.eye(4)))
    return views


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("images", nargs="*", metavar="IMAGE", help="two images (default: synthetic views)")
    parser.add_argument("--object-detector", default="ssd-mobilenet", help="for images given as paths")
    args = parser.parse_args(argv)
    if len(args.images) not in (0, 2):
        parser.error("give two images, or none for the synthetic example")
    views = image_views(args.images, args.object_detector) if args.images else synthetic_views()

    detector = symbiolcd2.create(["temporal_window=0", "idf_power=0"])
    candidates = []
    for keyframe_id, (image, objects, timestamp, pose) in enumerate(views):
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        keypoints, descriptors = extract_orb(gray)
        keyframe = Keyframe(keyframe_id, keyframe_id, timestamp, pose, keypoints, descriptors, objects, image)
        candidates = detector.add(keyframe)  # the first keyframe has nothing to match: []
        assert detector.last_graph is not None
        tiers = detector.last_graph.tier_sizes()
        # Movable classes (person) and oversized or overlapping boxes are dropped by the detector's
        # object filter, so the graph may have fewer object nodes than objects listed here.
        labels = ", ".join(o.label for o in objects) or "none"
        print(f"keyframe {keyframe_id}: {len(keypoints)} ORB features, objects: {labels}")
        print(
            f"  graph: {detector.last_graph.num_nodes} nodes, {len(detector.last_graph.edges)} edges, {tiers}"
        )

    if not candidates:
        raise SystemExit("no candidate (too few ORB features in one of the images?)")
    best = candidates[0]
    verdict = "a loop" if best.score >= detector.threshold else "not a loop"
    print(f"candidate: keyframe {best.query} revisits keyframe {best.match}")
    print(f"score: {best.score:.4f} (threshold {detector.threshold}: {verdict})")
    for name, value in best.components.items():
        print(f"  {name}: {value:.4f}")
    print("score = wl - temporal (WL subtree kernel, normalised; temporal penalty of the time gap)")
    return {"score": best.score, **best.components}


if __name__ == "__main__":
    main()
