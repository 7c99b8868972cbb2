"""``symbio vocab train``: train an ORB vocabulary tree from images, folders and datasets.

Inputs are image files, folders of images (name order; no intrinsics needed) or any dataset path
``frontends.datasets.open_dataset`` reads (TUM, KITTI, EuRoC, loop-pairs sets, videos). ``--step``
keeps every n-th image of each input: consecutive video frames are near duplicates, which would
bias the IDF. The same inputs, options and ``--seed`` give the same vocabulary.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.datasets import detect_format, open_dataset
from frontends.datasets.base import decode_image, list_images
from frontends.errors import ConfigError, DatasetError, InputFileError
from frontends.orb import OrbConfig, extract_orb
from lcd.vocabulary import Vocabulary

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}


def add_parser(subparsers: Any) -> None:
    vocab = subparsers.add_parser("vocab", help="ORB vocabulary trees").add_subparsers(
        dest="vocab_command", metavar="SUBCOMMAND", required=True
    )
    train = vocab.add_parser(
        "train",
        help="train an ORB vocabulary tree (hierarchical k-majority, TF-IDF) from images",
        description="Extract ORB features from images, folders or datasets, cluster them into a "
        "vocabulary tree of branching --k and depth --levels and save it as .npz with IDF weights "
        "from the training images. Deterministic for a given --seed.",
    )
    train.add_argument("inputs", nargs="+", type=Path, metavar="IMAGES_OR_DATASETS")
    train.add_argument("--k", type=int, default=10, help="branching factor (default: 10)")
    train.add_argument("--levels", type=int, default=5, help="tree depth (default: 5)")
    train.add_argument("--out", type=Path, required=True, help="output .npz")
    train.add_argument("--seed", type=int, default=0, help="clustering seed (default: 0)")
    train.add_argument(
        "--max-descriptors", type=int, help="cluster a seeded random sample of this many descriptors"
    )
    train.add_argument("--step", type=int, default=1, help="use every n-th image of each input (default: 1)")
    train.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one OrbConfig value (repeatable), e.g. --set nfeatures=1500",
    )
    add_json_option(train)
    train.set_defaults(handler=run_train)


def run_train(args: argparse.Namespace) -> int:
    if args.k < 2 or args.levels < 1 or args.step < 1:
        raise ConfigError("vocab train: --k must be >= 2, --levels >= 1 and --step >= 1")
    orb = load_config(OrbConfig, None, args.overrides)
    descriptors = [extract_orb(gray, orb)[1] for gray in iter_images(args.inputs, args.step)]
    if not descriptors or not any(len(d) for d in descriptors):
        raise InputFileError(args.inputs[0], "no ORB features in the inputs")
    vocabulary, stats = Vocabulary.train(
        descriptors, k=args.k, levels=args.levels, seed=args.seed, max_descriptors=args.max_descriptors
    )
    vocabulary.save(args.out)
    figures = {
        "images": stats.images,
        "descriptors": stats.descriptors,
        "words": stats.words,
        "k": args.k,
        "levels": args.levels,
        "seconds": round(stats.seconds, 3),
    }
    print(f"vocab: wrote {args.out}")
    print_figures(figures)
    write_json(args.json, figures)
    return 0


def iter_images(inputs: Sequence[Path], step: int = 1) -> Iterator[np.ndarray]:
    """Grey images of every input in order, every ``step``-th of each input (the others are not decoded)."""
    for path in inputs:
        yield from _input_images(path, step)


def _input_images(path: Path, step: int) -> Iterator[np.ndarray]:
    if not path.exists():
        raise InputFileError(path, "not found")
    if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
        yield _gray(_decode(path))
        return
    if path.is_dir() and detect_format(path) == "folder":
        # A plain image folder: the folder reader would ask for intrinsics that training does not need.
        for image_path in list_images(path)[::step]:
            yield _gray(_decode(image_path))
        return
    dataset = open_dataset(path)
    for index in range(0, len(dataset), step):
        image = dataset.read_image(index)  # None: skipped with a warning, like every reader
        if image is not None:
            yield _gray(image)


def _decode(path: Path) -> np.ndarray:
    image = decode_image(path)
    if image is None:
        raise DatasetError(path, "image does not decode")
    return image


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
