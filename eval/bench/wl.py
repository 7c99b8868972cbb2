"""Benchmark of the incremental WL kernel (``lcd.wl.WLKernel``) against grakel.

Graphs: ``--frames`` distinct frames of a synthetic loop scene (``frontends.synth.render_frames``),
built as the ``symbiolcd2`` detector builds them: ORB with ``OrbConfig()``, the scene's ground-truth
objects through the detector's object filter, word ids of the shipped vocabulary at
``--word-level`` and ``build_graph`` with the detector's ``GraphConfig`` (defaults: the detector's).
The frames are reused cyclically to reach ``--keyframes`` keyframes, so every keyframe after the
first ``--frames`` has identical earlier copies (the kernel's worst case: they match at every
iteration).

Figures (one run, so ratios compare like with like):
- ``max_abs_diff_vs_grakel``: our normalised kernel rows vs grakel's kernel matrix on ``--check``
  keyframes (taken across a cycle boundary, so duplicates are included).
- ``ms_add_query_p50`` / ``_p95``: ``add_and_query`` with ``--keyframes`` stored, over the last 100 calls.
- ``speedup_vs_grakel_transform``: grakel fitted on ``grakel_n - 1`` keyframes, time to ``transform``
  one new keyframe, over our ``add_and_query`` time at the same store size; ``speedup_vs_grakel_refit``:
  grakel ``fit_transform`` on all ``grakel_n`` keyframes (what a refitting backend pays per keyframe)
  over ours. grakel is measured at ``grakel_n`` (``--grakel-keyframes``) because at thousands of
  keyframes one fit takes minutes.
- ``ms_add_query_h<h>``: p50 of the last 100 ``add_and_query`` calls at ``--table-keyframes`` stored.

Usage: ``python -m eval.bench.wl --keyframes 2000 [--iterations 10] --json OUT``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import cv2
import numpy as np

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.orb import OrbConfig, extract_orb
from frontends.synth import SynthConfig, render_frames
from frontends.types import DetectedObject
from lcd.graph import LabelledGraph, build_graph
from lcd.objects.filtering import filter_objects
from lcd.symbiolcd2 import SymbioLCD2Config
from lcd.vbow import DEFAULT_VOCABULARY
from lcd.vocabulary import Vocabulary
from lcd.wl import WLKernel, grakel_kernel_matrix, to_grakel

TABLE_ITERATIONS = (1, 2, 3, 5, 10, 20, 50)


def synthetic_graphs(frames: int, seed: int, word_level: int) -> list[LabelledGraph]:
    """One keyframe graph per rendered frame, built exactly as ``SymbioLCD2.graph_of`` builds it."""
    vocabulary = Vocabulary.load(DEFAULT_VOCABULARY)
    config = SymbioLCD2Config()
    graphs = []
    for _, image, objects in render_frames(SynthConfig(frames=frames, seed=seed)):
        keypoints, descriptors = extract_orb(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), OrbConfig())
        detections = [DetectedObject(o.label, 1.0, o.box) for o in objects]
        kept = filter_objects(detections, (image.shape[1], image.shape[0]), config.objects)
        words = vocabulary.words_at_level(descriptors, word_level)
        graphs.append(build_graph(keypoints, words, kept, config.graph))
    return graphs


def timed_run(graphs: Sequence[LabelledGraph], iterations: int, count: int, last: int = 100) -> np.ndarray:
    """Milliseconds of each of the last ``last`` of ``count`` cyclic ``add_and_query`` calls."""
    kernel = WLKernel(iterations)
    times = []
    for index in range(count):
        start = time.perf_counter()
        kernel.add_and_query(graphs[index % len(graphs)])
        times.append(time.perf_counter() - start)
    return 1000.0 * np.array(times[-last:])


def max_diff_vs_grakel(graphs: Sequence[LabelledGraph], iterations: int) -> float:
    reference = grakel_kernel_matrix(graphs, iterations)
    kernel = WLKernel(iterations)
    worst = 0.0
    for row, graph in enumerate(graphs):
        scores = kernel.add_and_query(graph)
        if row:
            worst = max(worst, float(np.abs(scores - reference[row, :row]).max()))
    return worst


def grakel_times(graphs: Sequence[LabelledGraph], iterations: int) -> tuple[float, float]:
    """(ms to transform one new graph after fitting the others, ms to fit_transform all of them)."""
    from grakel.kernels import VertexHistogram, WeisfeilerLehman

    def make() -> WeisfeilerLehman:
        return WeisfeilerLehman(n_iter=iterations, base_graph_kernel=VertexHistogram, normalize=True)

    inputs = [to_grakel(g) for g in graphs]
    kernel = make()
    kernel.fit(inputs[:-1])
    start = time.perf_counter()
    kernel.transform(inputs[-1:])
    transform = time.perf_counter() - start
    start = time.perf_counter()
    make().fit_transform(inputs)
    refit = time.perf_counter() - start
    return 1000.0 * transform, 1000.0 * refit


def bench(args: argparse.Namespace) -> dict[str, object]:
    start = time.perf_counter()
    graphs = synthetic_graphs(args.frames, args.seed, args.word_level)
    sizes = np.array([g.num_nodes for g in graphs])
    figures: dict[str, object] = {
        "keyframes": args.keyframes,
        "iterations": args.iterations,
        "distinct_frames": len(graphs),
        "word_level": args.word_level,
        "nodes_p50": float(np.median(sizes)),
        "nodes_max": int(sizes.max()),
        "seconds_graphs": time.perf_counter() - start,
    }
    # A window across the cycle boundary: the second half repeats frames of the first cycle.
    first = max(0, len(graphs) - args.check // 2)
    check = [graphs[i % len(graphs)] for i in range(first, first + args.check)]
    figures["max_abs_diff_vs_grakel"] = max_diff_vs_grakel(check, args.iterations)
    figures["check_keyframes"] = len(check)

    ours = timed_run(graphs, args.iterations, args.keyframes)
    figures["ms_add_query_p50"] = float(np.median(ours))
    figures["ms_add_query_p95"] = float(np.percentile(ours, 95))

    n = min(args.grakel_keyframes, args.keyframes)
    subset = [graphs[i % len(graphs)] for i in range(n)]
    transform_ms, refit_ms = grakel_times(subset, args.iterations)
    ours_small = float(np.median(timed_run(graphs, args.iterations, n, last=min(n, 20))))
    figures.update(
        grakel_n=n,
        ms_ours_at_grakel_n=ours_small,
        ms_grakel_transform=transform_ms,
        ms_grakel_refit=refit_ms,
        speedup_vs_grakel_transform=transform_ms / ours_small,
        speedup_vs_grakel_refit=refit_ms / ours_small,
    )
    table_n = min(args.table_keyframes, args.keyframes)
    figures["table_keyframes"] = table_n
    for h in TABLE_ITERATIONS:
        figures[f"ms_add_query_h{h}"] = float(np.median(timed_run(graphs, h, table_n)))
    figures["seconds_total"] = time.perf_counter() - start
    return figures


def markdown(figures: dict[str, object]) -> str:
    lines = [
        f"| h | ms per add_and_query ({figures['table_keyframes']} stored) |",
        "|---:|---:|",
        *(f"| {h} | {figures[f'ms_add_query_h{h}']:.2f} |" for h in TABLE_ITERATIONS),
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=2000)
    parser.add_argument(
        "--iterations", type=int, default=SymbioLCD2Config().iterations, help="WL iterations h (paper: 50)"
    )
    parser.add_argument("--frames", type=int, default=300, help="distinct rendered frames, reused cyclically")
    parser.add_argument("--check", type=int, default=100, help="keyframes compared with grakel")
    parser.add_argument("--grakel-keyframes", type=int, default=100, help="store size of the grakel timing")
    parser.add_argument("--table-keyframes", type=int, default=2000, help="store size of the h table")
    parser.add_argument(
        "--word-level",
        type=int,
        default=SymbioLCD2Config().word_level,
        help="vocabulary level of the word ids",
    )
    parser.add_argument("--seed", type=int, default=0)
    add_json_option(parser)
    args = parser.parse_args(argv)
    figures = bench(args)
    print_figures(figures)
    print(markdown(figures))
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
