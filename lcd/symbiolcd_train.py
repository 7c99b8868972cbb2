"""``symbio symbiolcd-train``: the training table of the ``symbiolcd`` Random Forest, from synthetic scenes.

Each scene (``symbio synth`` output: TUM layout, ``gt_objects.jsonl``, GT poses) is read like
``symbio eval lcd`` reads it: a keyframe every ``--keyframe-period`` seconds, ORB features, and the
``oracle`` object detector missing ``--miss-rate`` of the objects (seeded by ``--seed``). The
keyframes go through the detector's own shortlist (``lcd.symbiolcd.ShortlistBuilder``, configured
by ``--set``), so the table holds exactly the rows the detector later scores. A shortlisted pair
is a positive when it is a GT loop pair of the scene (``dataset.loop_pairs()``), a negative
otherwise.

Scenes rendered with seeds 0-99 are refused: those seeds are reserved for evaluation.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.datasets import open_dataset
from frontends.datasets.base import every_period
from frontends.errors import ConfigError, InputFileError
from frontends.orb import OrbConfig, extract_orb
from frontends.types import Keyframe
from lcd.objects.oracle import OBJECTS_FILE, OracleConfig, OracleDetector
from lcd.symbiolcd import FEATURE_NAMES, ShortlistBuilder, SymbioLCDConfig, TrainingTable, save_table
from lcd.vbow import DEFAULT_VOCABULARY
from lcd.vocabulary import Vocabulary

#: Synthetic seeds kept for evaluation; never train on them.
EVALUATION_SEEDS = range(0, 100)


def scene_rows(
    scene: Path,
    config: SymbioLCDConfig,
    vocabulary: Vocabulary,
    oracle: OracleDetector,
    orb: OrbConfig,
    keyframe_period: float,
) -> TrainingTable:
    """The shortlisted (query, candidate) pairs of one scene, labelled by its GT loop pairs."""
    dataset = open_dataset(scene)
    pairs, _ = dataset.loop_pairs()
    if pairs is None:
        raise ConfigError(f"{scene}: no ground-truth loops (no loop-pairs file and no GT poses)")
    loops = {(int(q), int(r)) for q, r in pairs.tolist()}
    builder = ShortlistBuilder(config, vocabulary)
    frame_of: list[int] = []
    features: list[np.ndarray] = []
    labels: list[np.ndarray] = []
    for frame in every_period(dataset, keyframe_period):
        keypoints, descriptors = extract_orb(frame.gray, orb)
        objects = tuple(oracle.detect(frame.image, frame))
        pose = frame.gt_pose if frame.gt_pose is not None else np.eye(4)
        keyframe = Keyframe(
            len(frame_of), frame.index, frame.timestamp, pose, keypoints, descriptors, objects, frame.image
        )
        shortlist = builder.add(keyframe)
        frame_of.append(frame.index)
        features.append(shortlist.features)
        labels.append(np.array([(frame.index, frame_of[m]) in loops for m in shortlist.matches], dtype=bool))
    return TrainingTable(
        np.concatenate(features).reshape(-1, len(FEATURE_NAMES)), np.concatenate(labels).astype(np.int64)
    )


def check_not_evaluation_scene(scene: Path) -> None:
    """Refuse synthetic scenes whose seed is reserved for evaluation (their ``scene.json`` says)."""
    description = scene / "scene.json"
    if not description.is_file():
        raise InputFileError(
            description, "not a synthetic scene (no scene.json): train on `symbio synth` output"
        )
    try:
        seed = int(json.loads(description.read_text(encoding="utf-8"))["config"]["seed"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputFileError(description, f"cannot read the scene's seed ({exc})") from None
    if seed in EVALUATION_SEEDS:
        raise ConfigError(
            f"{scene}: rendered with seed {seed}; seeds {EVALUATION_SEEDS.start}-{EVALUATION_SEEDS.stop - 1} "
            "are reserved for evaluation, train on others"
        )


def build_table(
    scenes: Sequence[Path],
    config: SymbioLCDConfig,
    miss_rate: float,
    seed: int,
    keyframe_period: float = 0.2,
    orb: OrbConfig | None = None,
) -> TrainingTable:
    vocabulary = Vocabulary.load(config.vocabulary or DEFAULT_VOCABULARY)
    oracle = OracleDetector(OracleConfig(miss_rate=miss_rate, seed=seed))
    tables = []
    for scene in scenes:
        check_not_evaluation_scene(scene)
        if not (scene / OBJECTS_FILE).is_file():
            raise InputFileError(scene / OBJECTS_FILE, "not found: the oracle needs a synthetic scene")
        tables.append(scene_rows(scene, config, vocabulary, oracle, orb or OrbConfig(), keyframe_period))
    return TrainingTable(
        np.concatenate([t.features for t in tables]), np.concatenate([t.labels for t in tables])
    )


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "symbiolcd-train",
        help="write the training table of the symbiolcd Random Forest from synthetic scenes",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("scenes", nargs="+", type=Path, metavar="SCENE", help="`symbio synth` output folders")
    parser.add_argument("--out", type=Path, required=True, help="output table (.npz)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the oracle's misses (default: 0)")
    parser.add_argument(
        "--miss-rate", type=float, default=0.3, help="share of objects the oracle misses (default: 0.3)"
    )
    parser.add_argument("--keyframe-period", type=float, default=0.2, help="seconds between keyframes")
    parser.add_argument("--config", type=Path, help="YAML of the symbiolcd config (shortlist, window, ...)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a symbiolcd config value (use the same values when detecting)",
    )
    add_json_option(parser)
    parser.set_defaults(handler=run_train)


def run_train(args: argparse.Namespace) -> int:
    config = load_config(SymbioLCDConfig, args.config, args.overrides)
    table = build_table(args.scenes, config, args.miss_rate, args.seed, args.keyframe_period)
    if len(np.unique(table.labels)) != 2:
        raise ConfigError("symbiolcd-train: the scenes gave pairs of one kind only; add scenes with loops")
    save_table(
        args.out,
        table,
        {
            "scenes": ",".join(scene.name for scene in args.scenes),
            "seed": args.seed,
            "miss_rate": args.miss_rate,
            "keyframe_period": args.keyframe_period,
        },
    )
    figures = {
        "scenes": len(args.scenes),
        "pairs": len(table.labels),
        "positives": int(table.labels.sum()),
        "negatives": int(len(table.labels) - table.labels.sum()),
        "bytes": args.out.stat().st_size,
    }
    print(f"symbiolcd-train: wrote {args.out}")
    print_figures(figures)
    write_json(args.json, figures)
    return 0
