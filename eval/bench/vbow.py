"""Benchmark of the vocabulary tree and its inverted index on one core.

Figures: ``transform_ms`` (BoW vector of one image of 1500 ORB descriptors, i.e. descending the
tree and TF-IDF weighting), ``words_at_level_ms`` (coarse word ids of the same descriptors),
``add_ms`` (storing one vector in the database, amortised) and ``query_ms`` (scoring one vector
against ``--stored`` images, 2000 by default). Descriptors are real ORB descriptors of rendered
synthetic frames, so the word distribution (hence posting-list lengths) is realistic; stored
images are made distinct by shuffling descriptors between frames with a seeded generator.

Usage: ``python -m eval.bench.vbow [--vocabulary PATH] [--stored 2000] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from eval.bench.synth import pin_to_one_core
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.orb import OrbConfig, extract_orb
from frontends.synth.render import SceneRenderer
from frontends.synth.world import SynthConfig
from lcd.vbow import DEFAULT_VOCABULARY
from lcd.vocabulary import BowDatabase, Vocabulary

DESCRIPTORS_PER_IMAGE = 1500
#: Rendered frames the descriptor pool comes from.
SOURCE_FRAMES = 40


def descriptor_pool(seed: int) -> list[np.ndarray]:
    """ORB descriptors (1500 per 640x480 frame) of frames along a synthetic loop."""
    config = SynthConfig(seed=seed, frames=SOURCE_FRAMES * 10)
    scene = SceneRenderer(config)
    orb = OrbConfig(nfeatures=DESCRIPTORS_PER_IMAGE, fast_threshold=7)
    pool = []
    for index in range(0, config.frames, 10):
        gray = scene.frame(index).image
        pool.append(extract_orb(gray, orb)[1])
    return pool


def bench(vocabulary: Vocabulary, stored: int, seed: int = 0, repeats: int = 50) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    pool = descriptor_pool(seed)
    everything = np.concatenate(pool)
    query = pool[0][:DESCRIPTORS_PER_IMAGE]
    start = time.perf_counter()
    for _ in range(repeats):
        vocabulary.transform(query)
    transform = (time.perf_counter() - start) / repeats
    start = time.perf_counter()
    for _ in range(repeats):
        vocabulary.words_at_level(query, 2)
    coarse = (time.perf_counter() - start) / repeats
    # Stored images: real frames mixed with random draws from the whole pool, all distinct.
    vectors = []
    for i in range(stored):
        own = pool[i % len(pool)]
        mixed = everything[rng.integers(len(everything), size=len(own) // 3)]
        vectors.append(vocabulary.transform(np.concatenate([own[len(own) // 3 :], mixed])))
    database = BowDatabase()
    start = time.perf_counter()
    for vector in vectors:
        database.add(vector)
    add = (time.perf_counter() - start) / stored
    bow = vocabulary.transform(query)
    start = time.perf_counter()
    for _ in range(repeats):
        database.query(bow)
    query_seconds = (time.perf_counter() - start) / repeats
    return {
        "descriptors_per_image": len(query),
        "vocabulary_words": vocabulary.size,
        "stored_images": stored,
        "transform_ms": 1000 * transform,
        "words_at_level_ms": 1000 * coarse,
        "add_ms": 1000 * add,
        "query_ms": 1000 * query_seconds,
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vocabulary", type=Path, default=DEFAULT_VOCABULARY, help="vocabulary .npz")
    parser.add_argument("--stored", type=int, default=2000, help="images in the database (default: 2000)")
    parser.add_argument("--seed", type=int, default=0)
    add_json_option(parser)
    args = parser.parse_args(argv)
    how = pin_to_one_core()
    figures = bench(Vocabulary.load(args.vocabulary), args.stored, args.seed)
    print(f"bench_vbow ({how}):")
    print_figures(figures)
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
