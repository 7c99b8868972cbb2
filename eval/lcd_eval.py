"""``symbio eval lcd``: loop-closure precision/recall of one detector on any dataset with GT loops.

Keyframes are every frame at least ``--keyframe-period`` seconds after the previous keyframe
(default 0.2 s: every 6th frame at 30 Hz, every frame of a loop-pairs set, whose frames are 1 s
apart). Each keyframe gets ORB features and objects, then goes to the detector; its best candidate
is scored against the ground truth as described in ``eval.lcd_metrics``. Timing is per keyframe,
split into features, objects and the detector itself.

Several detectors (``--detector a,b,c``) share one pass: every keyframe's features and objects are
computed once and fed to each, so they are compared on identical inputs (the ablation table).
A detector or object detector that raises costs only that keyframe (logged and counted in
``loop_detector_failures`` / ``object_detector_failures``), never the run.

``--verify`` also runs each query's top ``--top-k`` candidates (default 3), best first and whatever
their score, through the pipeline's own two-view verification (``slam_backend.verify.verify_two_view``:
ORB matching and pycolmap's two-view geometry with ``symbio run``'s verifier defaults, on the detectors'
features or (``--verify-features tracking``) the denser ones a ``symbio run`` keyframe carries; images
only, so not the map-point Sim(3)/PnP stages). A query's verified answer is the candidate with the most
epipolar inliers among those that pass (``--verify-answer rank``: the best-ranked one that passes).
Added figures:
``recall_at_100p_verified`` (a threshold swept over the verified answers' inlier counts),
``precision_verified`` / ``recall_verified`` at the verifier's own decision (every query with a
verified answer accepted; nothing accepted counts as precision 1.0), ``recall_at_1_verified`` (equal
to ``recall_verified``) and ``ms_verify_p50`` (median time to verify a query's candidates, over the
queries that had any). ``recall_at_1`` (raw) is the share of loop queries whose best candidate is
right. Loop-pairs sets without a calibration verify with the estimated 60 deg camera: pycolmap then
keeps the fundamental matrix where the essential one fits fewer inliers.
"""

from __future__ import annotations

import argparse
import csv
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from eval.lcd_metrics import (
    gt_references,
    has_reachable_loop,
    is_true_match,
    precision_recall_curve,
    recall_at_1,
    summarise,
    summarise_verified,
)
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.datasets import Dataset, open_dataset
from frontends.datasets.base import every_period
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError
from frontends.orb import TRACKING_ORB, OrbConfig, extract_orb
from frontends.types import CameraIntrinsics, DetectedObject, Frame, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopCandidate, LoopDetector, ObjectDetector

if TYPE_CHECKING:
    from slam_backend.verify import VerifierConfig

log = logging.getLogger(__name__)


@dataclass
class QueryRecord:
    keyframe: int
    frame: int
    match_frame: int
    score: float
    correct: bool
    has_loop: bool
    ms_features: float
    ms_objects: float
    ms_detector: float
    #: ``--verify``: the verified answer's frame (-1: no candidate passed), score, epipolar inliers
    #: and correctness; how many candidates were verified and how long that took.
    verified_match_frame: int = -1
    verified_score: float = float("-inf")
    verified_inliers: int = 0
    verified_correct: bool = False
    candidates_verified: int = 0
    ms_verify: float = 0.0


@dataclass
class LcdRun:
    records: list[QueryRecord] = field(default_factory=list)
    object_failures: int = 0
    loop_detector_failures: int = 0
    keyframes: int = 0
    #: Whether the records carry verified answers (``--verify``).
    verified: bool = False


def detect_objects(detector: ObjectDetector, frame: Frame, run: LcdRun) -> tuple[DetectedObject, ...]:
    """Objects of a frame; a failing object detector costs this keyframe its objects, not the run."""
    try:
        return tuple(detector.detect(frame.image, frame))
    except Exception as exc:  # plugin boundary: any detector error is isolated to its frame
        run.object_failures += 1
        log.warning(
            "object detector %s failed on %s: %s; keyframe kept without objects",
            detector.name,
            frame.path or f"frame {frame.index}",
            exc,
        )
        return ()


def propose_loops(
    detector: LoopDetector, keyframe: Keyframe, frame: Frame, run: LcdRun
) -> list[LoopCandidate]:
    """A failing loop detector costs this query its candidates, not the run (counted and logged)."""
    try:
        return detector.add(keyframe)
    except Exception as exc:  # plugin boundary, like object detectors
        run.loop_detector_failures += 1
        log.warning(
            "loop detector %s failed on keyframe %d (%s): %r; the query counts as unanswered",
            detector.name,
            keyframe.id,
            frame.path or f"frame {frame.index}",
            exc,
        )
        return []


@dataclass(frozen=True)
class VerifiedAnswer:
    """The chosen candidate among those that passed (None: none did), its inliers, the work it took."""

    candidate: LoopCandidate | None
    inliers: int
    #: Candidates verified.
    checked: int
    ms: float


#: ``--verify-features tracking``: the features a `symbio run` keyframe carries (the mono-vo
#: frontend's), detected at 2x below 240 px like the detectors' (`OrbConfig.upsample_below`): tracking
#: does not upsample, and without it no corridor (160x120) pair passes (docs/2026-12-06-verified-lcd.md).
VERIFICATION_ORB = replace(TRACKING_ORB, upsample_below=OrbConfig().upsample_below)

#: How a query's verified answer is chosen among its top-k candidates that pass (``--verify-answer``).
VERIFIED_ANSWERS = ("inliers", "rank")


class CandidateVerifier:
    """``--verify``: each query's top-k candidates through ``slam_backend.verify.verify_two_view``.

    ``answer="inliers"`` (default) verifies all k and answers with the one with the most epipolar
    inliers, the view that overlaps the query most (``symbio run`` sends every verified candidate to
    the backend, so this is the best constraint it gets); ``"rank"`` answers with the best-ranked
    candidate that passes and stops there. On Gardens Point (top 5, tracking features) the first
    answers right for 0.695 (vbow) / 0.690 (symbiolcd2) of the loop queries, the second for 0.640 /
    0.630: the wrong verified answers are mostly the same place 3-8 frames off
    (docs/2026-12-06-verified-lcd.md).
    Outcomes are cached by keyframe pair with their measured time, so detectors proposing the same
    pair share one verification and each is charged what it cost.
    """

    def __init__(
        self,
        camera: CameraIntrinsics,
        config: VerifierConfig,
        top_k: int,
        orb: OrbConfig | None = None,
        answer: str = "inliers",
    ) -> None:
        # pycolmap loads here, not with the module: only `eval lcd --verify` pays for it.
        from slam_backend.verify import colmap_camera

        if top_k < 1:
            raise ConfigError(f"--top-k must be >= 1, got {top_k}")
        if answer not in VERIFIED_ANSWERS:
            raise ConfigError(f"--verify-answer must be one of {', '.join(VERIFIED_ANSWERS)}, got {answer!r}")
        # The dataset's camera, even when only estimated: pycolmap's calibrated path falls back to the
        # fundamental matrix when E fits < 95 % of F's inliers. Measured on GT pairs with the 60 deg
        # estimate, it passes 70.5 % (rtabmap) / 52.0 % (gardens) vs 67.5 / 50.5 % for F/H only,
        # 0 of 200 random pairs either way: so `symbio run`'s path, unchanged.
        self.camera = colmap_camera(camera)
        self.config = config
        self.top_k = top_k
        self.rule = answer
        # None: verify with the detectors' features (the keyframe's own); else extract these
        # (``--verify-features tracking``, docs/2026-12-06-verified-lcd.md).
        self.orb = orb
        self._keyframes: list[Keyframe] = []
        self._outcomes: dict[tuple[int, int], tuple[bool, int, float]] = {}

    def features(self, keyframe: Keyframe, gray: np.ndarray) -> Keyframe:
        """``keyframe`` with the verification features of its image (no image kept)."""
        if self.orb is None:
            return replace(keyframe, image=None)
        keypoints, descriptors = extract_orb(gray, self.orb)
        return replace(keyframe, keypoints=keypoints, descriptors=descriptors, image=None)

    def remember(self, keyframe: Keyframe) -> None:
        """Keep a processed keyframe (with ``features``) as a future match."""
        self._keyframes.append(keyframe)

    def answer(self, query: Keyframe, candidates: Sequence[LoopCandidate]) -> VerifiedAnswer:
        """``query`` carries the verification features (``features``)."""
        from slam_backend.verify import verify_two_view

        spent, checked = 0.0, 0
        best: tuple[LoopCandidate, int] | None = None
        for candidate in candidates[: self.top_k]:
            key = (query.id, candidate.match)
            if key not in self._outcomes:
                start = time.perf_counter()
                outcome = verify_two_view(query, self._keyframes[candidate.match], self.camera, self.config)
                ms = 1e3 * (time.perf_counter() - start)
                self._outcomes[key] = (outcome.passed, outcome.inliers, ms)
            passed, inliers, ms = self._outcomes[key]
            spent, checked = spent + ms, checked + 1
            if passed and (best is None or inliers > best[1]):
                best = (candidate, inliers)
                if self.rule == "rank":
                    break
        if best is None:
            return VerifiedAnswer(None, 0, checked, spent)
        return VerifiedAnswer(best[0], best[1], checked, spent)


def warn_short_candidate_lists(detectors: Sequence[LoopDetector], top_k: int) -> None:
    """A detector returning fewer than ``top_k`` candidates verifies fewer: say so, and how to fix it."""
    for detector in detectors:
        most = getattr(getattr(detector, "config", None), "max_candidates", None)
        if isinstance(most, int) and most < top_k:
            log.warning(
                "%s returns at most %d candidates: --top-k %d verifies at most %d (--set max_candidates=%d)",
                detector.name,
                most,
                top_k,
                most,
                top_k,
            )


def run_lcd(
    dataset: Dataset,
    detectors: Sequence[LoopDetector],
    objects: ObjectDetector,
    orb: OrbConfig,
    keyframe_period: float,
    tolerance: int,
    progress: bool = True,
    verifier: CandidateVerifier | None = None,
) -> list[LcdRun]:
    """One run per detector; every keyframe's features and objects are computed once for all.
    With ``verifier`` the records also carry each query's verified answer."""
    pairs, _ = dataset.loop_pairs()
    if pairs is None:
        raise ConfigError(f"{dataset.root}: no ground-truth loops (no loop-pairs file and no GT poses)")
    references = gt_references(pairs)
    runs = [LcdRun(verified=verifier is not None) for _ in detectors]
    object_failures = LcdRun()
    seen_frames: list[int] = []
    names = ",".join(d.name for d in detectors)
    for frame in tqdm(
        every_period(dataset, keyframe_period), disable=not progress, unit="kf", desc=f"lcd {names}"
    ):
        tick = time.perf_counter()
        keypoints, descriptors = extract_orb(frame.gray, orb)
        tock = time.perf_counter()
        found = detect_objects(objects, frame, object_failures)
        tuck = time.perf_counter()
        pose = frame.gt_pose if frame.gt_pose is not None else np.eye(4)
        keyframe = Keyframe(
            len(seen_frames), frame.index, frame.timestamp, pose, keypoints, descriptors, found, frame.image
        )
        refs = references.get(frame.index)
        to_verify = verifier.features(keyframe, frame.gray) if verifier is not None else keyframe
        for detector, run in zip(detectors, runs, strict=True):
            start = time.perf_counter()
            candidates = propose_loops(detector, keyframe, frame, run)
            done = time.perf_counter()
            if candidates:
                best = candidates[0]
                match_frame = seen_frames[best.match]
                score, correct = float(best.score), is_true_match(match_frame, refs, tolerance)
            else:
                match_frame, score, correct = -1, float("-inf"), False
            # Which earlier keyframes the detector could have proposed: those outside its window.
            window = int(getattr(detector, "temporal_window", 0))
            eligible = seen_frames[: max(0, len(seen_frames) - window)]
            record = QueryRecord(
                keyframe.id,
                frame.index,
                match_frame,
                score,
                correct,
                has_reachable_loop(refs, eligible, tolerance),
                1e3 * (tock - tick),
                1e3 * (tuck - tock),
                1e3 * (done - start),
            )
            if verifier is not None:
                answer = verifier.answer(to_verify, candidates)
                record.candidates_verified, record.ms_verify = answer.checked, answer.ms
                if answer.candidate is not None:
                    record.verified_match_frame = seen_frames[answer.candidate.match]
                    record.verified_score = float(answer.candidate.score)
                    record.verified_inliers = answer.inliers
                    record.verified_correct = is_true_match(record.verified_match_frame, refs, tolerance)
            run.records.append(record)
            run.keyframes += 1
            run.object_failures = object_failures.object_failures
        if verifier is not None:
            verifier.remember(to_verify)
        seen_frames.append(frame.index)
    return runs


def figures_of(run: LcdRun, threshold: float) -> dict[str, Any]:
    records = run.records
    scores = np.array([r.score for r in records])
    correct = np.array([r.correct for r in records])
    has_loop = np.array([r.has_loop for r in records], dtype=bool)
    figures: dict[str, Any] = dict(summarise(scores, correct, int(has_loop.sum()), threshold))
    figures["recall_at_1"] = recall_at_1(correct, has_loop)
    if run.verified:
        figures.update(
            summarise_verified(
                np.array([r.verified_match_frame >= 0 for r in records], dtype=bool),
                np.array([r.verified_correct for r in records], dtype=bool),
                np.array([r.verified_inliers for r in records]),
                has_loop,
            )
        )
        # Over the queries that had candidates to verify (the first ones have none in the window).
        verify_ms = np.array([r.ms_verify for r in records if r.candidates_verified])
        figures["ms_verify_p50"] = float(np.percentile(verify_ms, 50)) if len(verify_ms) else float("nan")
        figures["ms_verify_p95"] = float(np.percentile(verify_ms, 95)) if len(verify_ms) else float("nan")
    total = np.array([r.ms_features + r.ms_objects + r.ms_detector for r in records])
    for name, values in (
        ("ms_per_keyframe", total),
        ("ms_features", np.array([r.ms_features for r in records])),
        ("ms_objects", np.array([r.ms_objects for r in records])),
        ("ms_detector", np.array([r.ms_detector for r in records])),
    ):
        if len(values):
            figures[f"{name}_p50"] = float(np.percentile(values, 50))
            figures[f"{name}_p95"] = float(np.percentile(values, 95))
    figures["keyframes"] = run.keyframes
    figures["object_detector_failures"] = run.object_failures
    figures["loop_detector_failures"] = run.loop_detector_failures
    return figures


#: Counters a detector may expose, reported with its figures (e.g. SymbioLCD2's keyframes with too
#: few objects for the paper's graph).
DETECTOR_COUNTERS = ("object_poor_keyframes",)


def detector_counters(detector: LoopDetector) -> dict[str, int]:
    return {name: int(getattr(detector, name)) for name in DETECTOR_COUNTERS if hasattr(detector, name)}


#: Columns ``--csv`` gains with ``--verify``.
VERIFIED_COLUMNS = (
    "verified_match_frame",
    "verified_score",
    "verified_inliers",
    "verified_correct",
    "candidates_verified",
    "ms_verify",
)


def write_queries_csv(path: Path, runs: dict[str, LcdRun]) -> None:
    verified = any(run.verified for run in runs.values())
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        header = ["detector", "keyframe", "frame", "match_frame", "score", "correct", "has_loop"]
        writer.writerow(header + list(VERIFIED_COLUMNS) if verified else header)
        for name, run in runs.items():
            for r in run.records:
                row: list[Any] = [
                    name,
                    r.keyframe,
                    r.frame,
                    r.match_frame,
                    f"{r.score:.6f}",
                    int(r.correct),
                    int(r.has_loop),
                ]
                if verified:
                    row += [
                        r.verified_match_frame,
                        f"{r.verified_score:.6f}",
                        r.verified_inliers,
                        int(r.verified_correct),
                        r.candidates_verified,
                        f"{r.ms_verify:.2f}",
                    ]
                writer.writerow(row)


def plot_pr(path: Path, runs: dict[str, LcdRun], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    for name, run in runs.items():
        scores = np.array([r.score for r in run.records])
        correct = np.array([r.correct for r in run.records])
        positives = sum(r.has_loop for r in run.records)
        _, precision, recall = precision_recall_curve(scores, correct, positives)
        ax.plot(recall, precision, drawstyle="steps-post", label=name)
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02), title=title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def default_object_detector(dataset: Dataset) -> str:
    """Synthetic scenes carry their GT objects: use the oracle there, the CNN elsewhere."""
    return "oracle" if (dataset.root / "gt_objects.jsonl").is_file() else "ssd-mobilenet"


def add_lcd_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "lcd",
        help="loop-closure precision/recall of a detector on a dataset with GT loops",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_arguments(parser)
    parser.add_argument(
        "--detector",
        default="symbiolcd2",
        help="loop detector name (see `symbio detectors`), or several comma separated: one pass over "
        "the dataset, features and objects computed once, a comparison table",
    )
    parser.add_argument(
        "--object-detector", help="object detector (default: oracle on synthetic scenes, else ssd-mobilenet)"
    )
    parser.add_argument("--tolerance", type=int, default=0, help="frames a match may be off a GT reference")
    parser.add_argument("--keyframe-period", type=float, default=0.2, help="seconds between keyframes")
    parser.add_argument("--config", type=Path, help="YAML of the loop detector's config")
    parser.add_argument(
        "--wl-backend",
        choices=("ours", "grakel"),
        help="symbiolcd2 detectors: the WL kernel implementation (grakel: the slow reference)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a loop-detector config value",
    )
    parser.add_argument(
        "--object-set",
        dest="object_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an object-detector config value",
    )
    parser.add_argument(
        "--orb-set",
        dest="orb_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an ORB config value",
    )
    parser.add_argument(
        "--verify",
        action="store_true",
        help="also verify each query's top-k candidates with the pipeline's two-view verification (ORB "
        "matches + pycolmap epipolar geometry, `symbio run`'s verifier defaults) and report the verified "
        "figures: *_verified, recall_at_100p_verified sweeping the verified answers' inlier counts",
    )
    parser.add_argument(
        "--top-k",
        type=int,
        metavar="K",
        help="--verify: candidates verified per query, best first (default 3)",
    )
    parser.add_argument(
        "--verify-answer",
        choices=VERIFIED_ANSWERS,
        help="--verify: a query's answer among its candidates that pass: the one with the most "
        "epipolar inliers (default) or the best-ranked one",
    )
    parser.add_argument(
        "--verify-features",
        choices=("detector", "tracking"),
        help="--verify: match the detectors' features (default) or the denser ones a `symbio run` "
        "keyframe carries",
    )
    parser.add_argument(
        "--verify-set",
        dest="verify_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="--verify: override a verifier config value (e.g. min_inliers=50)",
    )
    parser.add_argument("--plot", type=Path, metavar="PNG", help="save the precision/recall curve")
    parser.add_argument(
        "--csv", type=Path, help="save every query's best candidate (with --verify also its verified answer)"
    )
    parser.add_argument("--no-progress", action="store_true")
    add_json_option(parser)
    parser.set_defaults(handler=run_lcd_command)


def run_lcd_command(args: argparse.Namespace) -> int:
    from frontends.config import load_config

    if not args.verify and (
        args.top_k is not None or args.verify_overrides or args.verify_answer or args.verify_features
    ):
        raise ConfigError(
            "--top-k, --verify-answer, --verify-features and --verify-set apply only with --verify"
        )
    top_k = 3 if args.top_k is None else args.top_k
    if top_k < 1:
        raise ConfigError(f"--top-k must be >= 1, got {top_k}")
    dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    overrides = list(args.overrides)
    if args.wl_backend:
        overrides.append(f"wl_backend={args.wl_backend}")
    names = [name.strip() for name in args.detector.split(",") if name.strip()]
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"--detector {args.detector!r}: give distinct detector names, comma separated")
    detectors = [LOOP_DETECTORS.load(name)(overrides, args.config) for name in names]
    object_name = args.object_detector or default_object_detector(dataset)
    objects = OBJECT_DETECTORS.load(object_name)(args.object_overrides)
    orb = load_config(OrbConfig, None, args.orb_overrides)
    verifier = None
    if args.verify:
        from slam_backend.verify import VerifierConfig

        verifier = CandidateVerifier(
            dataset.camera,
            load_config(VerifierConfig, None, args.verify_overrides),
            top_k,
            orb=VERIFICATION_ORB if args.verify_features == "tracking" else None,
            answer=args.verify_answer or "inliers",
        )
        warn_short_candidate_lists(detectors, top_k)
    runs = run_lcd(
        dataset,
        detectors,
        objects,
        orb,
        args.keyframe_period,
        args.tolerance,
        not args.no_progress,
        verifier,
    )
    results = {
        name: {
            "detector": name,
            "object_detector": object_name,
            "tolerance": args.tolerance,
            **(
                {
                    "top_k": top_k,
                    "verify_answer": verifier.rule,
                    "verify_features": args.verify_features or "detector",
                }
                if verifier is not None
                else {}
            ),
            **figures_of(run, detector.threshold),
            **detector_counters(detector),
        }
        for name, detector, run in zip(names, detectors, runs, strict=True)
    }
    print(f"eval lcd on {dataset.root} ({dataset.format_name}, {runs[0].keyframes} keyframes)")
    if len(names) == 1:
        print_figures(results[names[0]])
        write_json(args.json, results[names[0]])
    else:
        print(comparison_table(results))
        write_json(
            args.json, {f"{name}.{k}": v for name, figures in results.items() for k, v in figures.items()}
        )
    if args.csv:
        write_queries_csv(args.csv, dict(zip(names, runs, strict=True)))
    if args.plot:
        plot_pr(args.plot, dict(zip(names, runs, strict=True)), dataset.root.name)
    return 0


COMPARED = (
    "recall_at_100p",
    "recall_at_1",
    "auc_pr",
    "precision",
    "recall",
    "ms_detector_p50",
    "loop_detector_failures",
)
#: Columns the table gains with ``--verify``.
COMPARED_VERIFIED = (
    "recall_at_100p_verified",
    "recall_at_1_verified",
    "precision_verified",
    "recall_verified",
    "ms_verify_p50",
)


def comparison_table(results: dict[str, dict[str, Any]]) -> str:
    """A markdown table of the main figures, one row per detector."""
    verified = all("recall_at_100p_verified" in figures for figures in results.values())
    columns = COMPARED + COMPARED_VERIFIED if verified else COMPARED
    lines = ["| detector | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for name, figures in results.items():
        cells = [
            f"{figures[key]:.3f}" if isinstance(figures[key], float) else str(figures[key]) for key in columns
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def add_parser(subparsers: Any) -> None:
    """``symbio detectors`` (``symbio eval lcd`` is added by ``eval.eval_cli``)."""
    detectors = subparsers.add_parser("detectors", help="list the installed loop and object detectors")
    detectors.set_defaults(handler=list_detectors)


def list_detectors(args: argparse.Namespace) -> int:
    for title, registry in (("loop detectors", LOOP_DETECTORS), ("object detectors", OBJECT_DETECTORS)):
        print(f"{title} (entry points: {registry.group}):")
        for name in registry.names():
            print(f"  {name:<22} {registry.origin(name)}")
    return 0
