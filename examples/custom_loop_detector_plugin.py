"""A custom loop detector, plugged in through the ``symbio.loop_detectors`` entry point.

The detector: every keyframe becomes a 32 x 24 grey thumbnail, zero-mean and normalised; a query
scores each earlier keyframe outside its temporal window by normalised cross-correlation (the dot
product of the two thumbnails, in [-1, 1]) and returns the best as ``lcd.base.LoopCandidate``s,
best first. It needs neither features nor objects: a baseline in a dozen lines.

How a package ships it. Put the detector and a factory ``create(overrides, config_path)`` in a
module, and declare the factory in the package's ``pyproject.toml``::

    [project.entry-points."symbio.loop_detectors"]
    thumbnail = "my_package.thumbnail:create"

Once the package is installed (``pip install -e .``), ``symbio detectors`` lists ``thumbnail`` and
``symbio eval lcd SCENE --detector thumbnail,symbiolcd2`` evaluates it next to the built-ins:
``lcd.base.LOOP_DETECTORS`` finds entry points with ``importlib.metadata``.

To run without installing anything, this script fakes the installation: it writes the metadata
pip would write (``<name>.dist-info/METADATA`` and ``entry_points.txt``) into a temporary folder
and puts that folder on ``sys.path``, where ``importlib.metadata`` discovers it. The entry point
names this very file as the module (``custom_loop_detector_plugin:create``), so the registry imports
it a second time, as a module, exactly as it would import an installed plugin.

Then: ``symbio detectors`` (``eval.cli.main(["detectors"])``) lists the plugin,
``LOOP_DETECTORS.load("thumbnail")`` returns its factory, and ``eval.lcd_eval.run_lcd`` evaluates
it (with ``vbow`` on the same keyframes for comparison) on a 20 s synthetic loop scene written by
``frontends.synth.write_scene``.

Run: ``python examples/custom_loop_detector_plugin.py``
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from eval.cli import main as symbio
from eval.lcd_eval import figures_of, run_lcd
from frontends.config import load_config
from frontends.datasets import open_dataset
from frontends.orb import OrbConfig
from frontends.synth import SynthConfig, write_scene
from frontends.types import Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopCandidate

PLUGIN_NAME = "thumbnail"
ENTRY_POINT = f"{Path(__file__).stem}:create"  # module:attribute, like "my_package.thumbnail:create"


# --------------------------------------------------------------------------------- the detector
@dataclass(frozen=True)
class ThumbnailConfig:
    """Overridable like every config: ``--set temporal_window=20`` or a YAML file."""

    width: int = 32
    height: int = 24
    #: The most recent keyframes never proposed as loops (the query's own neighbourhood).
    temporal_window: int = 10
    #: Normalised cross-correlation at or above which a candidate counts as a loop (revisits of the
    #: synthetic room score up to ~0.75: views 10-20 degrees apart still correlate).
    threshold: float = 0.5
    max_candidates: int = 5


class ThumbnailDetector:
    """Implements the ``lcd.base.LoopDetector`` protocol: ``name``, ``threshold``, ``add``."""

    def __init__(self, config: ThumbnailConfig = ThumbnailConfig()) -> None:
        self.config = config
        self.name = PLUGIN_NAME
        self.threshold = config.threshold
        self.temporal_window = config.temporal_window  # eval.lcd_eval reads it (reachable GT loops)
        self.ids: list[int] = []
        self.thumbnails: list[np.ndarray] = []

    def thumbnail(self, image: np.ndarray | None) -> np.ndarray:
        """Zero-mean, unit-norm grey thumbnail; all zeros for a missing or flat image."""
        size = self.config.width * self.config.height
        if image is None:
            return np.zeros(size)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        small = cv2.resize(gray, (self.config.width, self.config.height), interpolation=cv2.INTER_AREA)
        vector = small.astype(np.float64).ravel()
        vector -= vector.mean()
        norm = float(np.linalg.norm(vector))
        return vector / norm if norm > 1e-9 else np.zeros(size)

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        query = self.thumbnail(keyframe.image)
        ids = np.asarray(self.ids, dtype=np.int64)
        eligible = np.flatnonzero(keyframe.id - ids > self.config.temporal_window)
        candidates = []
        if eligible.size:
            scores = np.stack([self.thumbnails[k] for k in eligible]) @ query  # NCC of each
            order = np.argsort(-scores, kind="stable")[: self.config.max_candidates]
            candidates = [
                LoopCandidate(keyframe.id, int(ids[eligible[k]]), float(scores[k]), {"ncc": float(scores[k])})
                for k in order
            ]
        self.ids.append(keyframe.id)
        self.thumbnails.append(query)
        return candidates


def create(overrides: Sequence[str] = (), config_path: Any = None) -> ThumbnailDetector:
    """The factory the entry point names (``lcd.base.LoopDetectorFactory``)."""
    return ThumbnailDetector(load_config(ThumbnailConfig, config_path, overrides))


# --------------------------------------------------------------------------------- the plugin
@contextlib.contextmanager
def installed_plugin() -> Iterator[Path]:
    """Pretend a package declaring the entry point is installed, for the duration of the block."""
    added = []
    with tempfile.TemporaryDirectory(prefix="symbio_plugin_") as folder:
        dist_info = Path(folder) / "symbio_thumbnail_example-0.1.0.dist-info"
        dist_info.mkdir()
        (dist_info / "METADATA").write_text(
            "Metadata-Version: 2.1\nName: symbio-thumbnail-example\nVersion: 0.1.0\n", encoding="utf-8"
        )
        (dist_info / "entry_points.txt").write_text(
            f"[symbio.loop_detectors]\n{PLUGIN_NAME} = {ENTRY_POINT}\n", encoding="utf-8"
        )
        # The "installed" distribution, and the folder of its module (this file's folder, already
        # on sys.path when run as a script).
        for path in (folder, str(Path(__file__).resolve().parent)):
            if path not in sys.path:
                sys.path.append(path)
                added.append(path)
        try:
            yield Path(folder)
        finally:
            for path in added:
                sys.path.remove(path)


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    ).parse_args(argv)
    with installed_plugin(), tempfile.TemporaryDirectory(prefix="symbio_scene_") as scratch:
        # 1. `symbio detectors` now lists the plugin, with the entry point it comes from.
        listing = io.StringIO()
        with contextlib.redirect_stdout(listing):
            symbio(["detectors"])
        print("$ symbio detectors")
        print(listing.getvalue().rstrip())
        listed = any(line.split()[:1] == [PLUGIN_NAME] for line in listing.getvalue().splitlines())

        # 2. Load it by name, like `symbio eval lcd --detector thumbnail` does.
        factory = LOOP_DETECTORS.load(PLUGIN_NAME)
        detectors = [factory(["temporal_window=10"]), LOOP_DETECTORS.load("vbow")()]
        print(f"loaded {PLUGIN_NAME!r} from {LOOP_DETECTORS.origin(PLUGIN_NAME)}: {type(detectors[0])}")

        # 3. A 20 s, 320 x 240 synthetic loop scene with ground-truth loops, read back as a dataset.
        #    Rendered at 5 frames/s (the keyframe rate) instead of 30: the same camera path and
        #    keyframe poses as the 600-frame scene of the tests, in a sixth of the time.
        scene = Path(scratch) / "loop_320"
        config = SynthConfig(
            seed=3,
            trajectory="loop",
            frames=100,
            fps=5.0,
            width=320,
            height=240,
            fx=262.5,
            fy=262.5,
            cx=159.5,
            cy=119.5,
        )
        write_scene(config, scene, progress=False)
        dataset = open_dataset(scene)

        # 4. The LCD protocol of `symbio eval lcd`: a keyframe every 0.2 s, best candidate per query,
        #    correct when within 1 frame (here one keyframe, 0.2 s; `--tolerance 6` at 30 frames/s)
        #    of a GT reference of the query. Neither detector uses objects.
        runs = run_lcd(
            dataset,
            detectors,
            OBJECT_DETECTORS.load("none")(),
            OrbConfig(),
            keyframe_period=0.2,
            tolerance=1,
            progress=False,
        )
        results = {}
        for detector, run in zip(detectors, runs, strict=True):
            figures = figures_of(run, detector.threshold)
            results[detector.name] = figures
            print(
                f"{detector.name:<10} keyframes {figures['keyframes']}, queries with a loop "
                f"{figures['queries_with_loop']}: recall_at_100p {figures['recall_at_100p']:.3f}, "
                f"auc_pr {figures['auc_pr']:.3f}, precision {figures['precision']:.3f} / recall "
                f"{figures['recall']:.3f} at threshold {detector.threshold}, "
                f"{figures['ms_detector_p50']:.2f} ms per keyframe"
            )
    print(f"plugin listed by `symbio detectors`: {listed}")
    return {
        "listed": float(listed),
        "recall_at_100p": float(results[PLUGIN_NAME]["recall_at_100p"]),
        "auc_pr": float(results[PLUGIN_NAME]["auc_pr"]),
    }


if __name__ == "__main__":
    main()
