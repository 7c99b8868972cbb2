"""Benchmark of the online vocabulary (``lcd.online_vocabulary``) as a sequence grows, on one core.

A camera exploring new ground is the costly case: every keyframe founds words, so the word set and
the posting lists grow all the time. The stream imitates that with real ORB descriptors of
rendered synthetic frames (``eval.bench.vbow.descriptor_pool``): landmark j is pool descriptor
``j mod P`` with a quarter of its bits flipped (distinct landmarks, realistic bit statistics);
keyframe k observes ``--descriptors`` (default 1000) descriptors: 70 % are the landmarks
``[k * step, k * step + 700)`` (``step`` = 140, so each landmark is seen in five consecutive
keyframes) and 30 % are one-off landmarks seen once (unstable corners, which the purge deletes);
each observation flips 5 % of the landmark's bits (about 13 bits). All draws come from ``--seed``.

Figures, at each of ``--keyframes`` (default 100, 1000, 3000): ``ms_online_<n>`` (median time of
``add_and_query`` over the ``--window`` keyframes up to n: search, scoring against every earlier
keyframe, adding), ``words_online_<n>`` (live words), and the same keyframes through the shipped
tree with its inverted index (``ms_tree_<n>``: ``transform`` + ``BowDatabase.query`` + ``add``);
``ratio_online_tree_<n>`` and ``ratio_online_<n>_<first>`` (growth since the first checkpoint)
are measured in this one run.

Usage: ``python -m eval.bench.online_vocab [--keyframes 100,1000,3000] [--set KEY=VALUE] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator, Sequence

import numpy as np

from eval.bench.synth import pin_to_one_core
from eval.bench.vbow import descriptor_pool
from frontends.cli_common import add_json_option, add_set_option, print_figures, write_json
from frontends.config import load_config
from frontends.errors import ConfigError
from lcd.online_vocabulary import OnlineVocabulary, OnlineVocabularyConfig
from lcd.vbow import DEFAULT_VOCABULARY
from lcd.vocabulary import BowDatabase, Vocabulary

#: Share of a keyframe's descriptors that are landmarks seen again (the rest are seen once).
STABLE_SHARE = 0.7
#: Consecutive keyframes that see one stable landmark.
SIGHTINGS = 5
#: Probability of each bit flipping: a new landmark from its pool descriptor, an observation.
LANDMARK_FLIP = 0.25
OBSERVATION_FLIP = 0.05


def stream(pool: np.ndarray, keyframes: int, descriptors: int, seed: int) -> Iterator[np.ndarray]:
    """The descriptors of each keyframe of the exploration (module docstring)."""
    rng = np.random.default_rng(seed)
    stable = round(descriptors * STABLE_SHARE)
    step = max(1, stable // SIGHTINGS)
    landmarks = np.zeros((0, pool.shape[1]), dtype=np.uint8)
    drawn = 0

    def new_landmarks(count: int) -> np.ndarray:
        nonlocal drawn
        source = pool[(drawn + np.arange(count)) % len(pool)]
        drawn += count
        return flip(source, LANDMARK_FLIP, rng)

    for k in range(keyframes):
        first = k * step
        needed = first + stable - len(landmarks)
        if needed > 0:
            landmarks = np.concatenate([landmarks, new_landmarks(needed)])
        seen = landmarks[first : first + stable]
        once = new_landmarks(descriptors - stable)
        yield flip(np.concatenate([seen, once]), OBSERVATION_FLIP, rng)


def flip(descriptors: np.ndarray, probability: float, rng: np.random.Generator) -> np.ndarray:
    bits = np.unpackbits(descriptors, axis=1)
    mask = (rng.random(bits.shape) < probability).astype(np.uint8)
    return np.packbits(bits ^ mask, axis=1)


def bench(
    checkpoints: Sequence[int], descriptors: int, window: int, config: OnlineVocabularyConfig, seed: int
) -> dict[str, float]:
    pool = np.concatenate(descriptor_pool(seed))
    online = OnlineVocabulary(config)
    tree = Vocabulary.load(DEFAULT_VOCABULARY)
    database = BowDatabase()
    last = max(checkpoints)
    online_ms: list[float] = []
    tree_ms: list[float] = []
    figures: dict[str, float] = {"descriptors_per_keyframe": descriptors}
    for k, image in enumerate(stream(pool, last, descriptors, seed), start=1):
        start = time.perf_counter()
        online.add_and_query(image)
        online_ms.append(1e3 * (time.perf_counter() - start))
        start = time.perf_counter()
        bow = tree.transform(image)
        database.query(bow)
        database.add(bow)
        tree_ms.append(1e3 * (time.perf_counter() - start))
        if k in checkpoints:
            figures[f"ms_online_{k}"] = float(np.median(online_ms[-window:]))
            figures[f"ms_tree_{k}"] = float(np.median(tree_ms[-window:]))
            figures[f"words_online_{k}"] = online.size
            figures[f"ratio_online_tree_{k}"] = figures[f"ms_online_{k}"] / figures[f"ms_tree_{k}"]
    first = min(checkpoints)
    for k in sorted(checkpoints)[1:]:
        figures[f"ratio_online_{k}_{first}"] = figures[f"ms_online_{k}"] / figures[f"ms_online_{first}"]
    return figures


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--keyframes", default="100,1000,3000", help="checkpoints, comma separated (default: 100,1000,3000)"
    )
    parser.add_argument("--descriptors", type=int, default=1000, help="descriptors per keyframe")
    parser.add_argument("--window", type=int, default=20, help="keyframes timed at each checkpoint")
    parser.add_argument("--seed", type=int, default=0)
    add_set_option(parser, "override an online vocabulary config value (e.g. tables=16)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    try:
        checkpoints = sorted({int(value) for value in args.keyframes.split(",")})
    except ValueError:
        parser.error(f"--keyframes: expected comma-separated integers, got {args.keyframes!r}")
    if checkpoints[0] < 1 or args.descriptors < 1 or args.window < 1:
        parser.error("--keyframes, --descriptors and --window must be >= 1")
    try:
        config = load_config(OnlineVocabularyConfig, None, args.overrides)
    except ConfigError as exc:
        parser.error(str(exc))
    how = pin_to_one_core()
    figures = bench(checkpoints, args.descriptors, args.window, config, args.seed)
    print(f"bench_online_vocab ({how}):")
    print_figures(figures)
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
