"""Relocalisation benchmark: after a blackout, is the relocalised pose right, or refused?

A frontend that relocalises to a wrong pose builds the rest of the run on it; one that refuses
starts a new map segment, which loop closing can reconnect. This blacks out ``--black`` frames
(default 20) of the synthetic scenes from each of ``--blackouts`` (frame indices) and resumes either
where the camera really is by then ("on": it has moved on and sees the map's newest points) or
``--back`` frames before the blackout began ("back": a view the map knows well), for every
(trajectory, scene seed, frontend seed). Per case it reports what the first frame posed after the
blackout is (relocalised / backfilled from a later relocalisation / new segment / none), how far a
relocalised camera centre is from the truth (the run's segment 0 before the blackout Sim(3)-aligned
to ground truth, evo's Umeyama), and that alignment's error in % of the path before the blackout: a
relocalisation can only be judged where the map was right. The summary counts relocalisations, and
among those on a right map (below ``--map-error`` %) the ones off by more than ``--wrong`` m.

Usage: ``python -m eval.bench.relocalisation [--trajectories loop,figure8,out-and-back]
[--seeds 0-1] [--frontend-seeds 0-2] [--blackouts 40,70,100] [--black 20] [--back 15] [--after 50]
[--jobs 2] [--set KEY=VALUE ...] [--json OUT]``; ``--set`` takes mono-vo keys
(``relocalisation.max_sigma_ratio=1e9`` turns the centre-spread check off).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from evo.core.geometry import umeyama_alignment

from eval.bench.frontend import track_all
from eval.bench.scenes import parse_seeds, scene_frames
from frontends.cli_common import add_json_option, add_set_option, write_json
from frontends.errors import ConfigError
from frontends.mono_vo import create
from frontends.types import CameraIntrinsics, Frame

Resume = Literal["on", "back"]
SCENE_FRAMES = 600  # the scenes of bench_odometry / bench_pipeline: the same paths


@dataclass(frozen=True)
class Blackout:
    first_black: int
    black: int
    resume: Resume
    back: int

    def sequence(self, frames: Sequence[Frame], after: int) -> list[Frame]:
        """Frames up to the blackout, ``black`` black ones, then ``after`` frames from where the
        camera resumes, renumbered to follow on (their ground truth stays theirs)."""
        resumed = self.first_black + self.black if self.resume == "on" else self.first_black - self.back
        black = [
            dataclasses.replace(frames[i], image=np.zeros_like(frames[i].image))
            for i in range(self.first_black, self.first_black + self.black)
        ]
        later = [
            dataclasses.replace(
                f, index=self.first_black + self.black + k, timestamp=(self.first_black + self.black + k) / 30
            )
            for k, f in enumerate(frames[resumed : resumed + after])
        ]
        return [*frames[: self.first_black], *black, *later]


@dataclass(frozen=True)
class Outcome:
    name: str
    #: The first frame posed after the blackout: "relocalised", "backfilled" (in the old map, tracked
    #: backwards from a later relocalisation), "new segment" or "none" (or "no map before": fewer
    #: than 3 frames posed before the blackout).
    result: str
    #: Its camera centre's distance from the truth (m), for a relocalisation.
    error_m: float | None
    #: Segment 0 before the blackout: Sim(3)-aligned ATE (RMSE) in % of its path.
    map_error_percent: float | None


def outcome(
    name: str,
    camera: CameraIntrinsics,
    sequence: Sequence[Frame],
    blackout: Blackout,
    overrides: Sequence[str],
) -> Outcome:
    results = track_all(create(camera, overrides), sequence)
    before = [
        i
        for i in range(blackout.first_black)
        if i in results and results[i].pose is not None and results[i].segment == 0
    ]
    if len(before) < 3:  # the map started too late: nothing to relocalise in
        return Outcome(name, "no map before", None, None)
    estimate = np.array([results[i].pose[:3, 3] for i in before]).T  # type: ignore[index]
    truth = np.array([sequence[i].gt_pose[:3, 3] for i in before]).T  # type: ignore[index]
    rotation, translation, scale = umeyama_alignment(estimate, truth, with_scale=True)
    aligned = scale * rotation @ estimate + translation[:, None]
    rmse = float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=0))))
    path = float(np.sum(np.linalg.norm(np.diff(truth, axis=1), axis=0)))
    posed = [
        r
        for i, r in sorted(results.items())
        if i >= blackout.first_black + blackout.black and r.pose is not None
    ]
    if not posed:
        return Outcome(name, "none", None, 100 * rmse / path)
    first = posed[0]
    if first.segment != 0:
        return Outcome(name, "new segment", None, 100 * rmse / path)
    centre = scale * rotation @ first.pose[:3, 3] + translation  # type: ignore[index]
    error = float(np.linalg.norm(centre - sequence[first.frame_index].gt_pose[:3, 3]))  # type: ignore[index]
    # Not "relocalised": refused at first, then posed backwards from a later relocalisation.
    return Outcome(
        name, "relocalised" if first.state == "relocalised" else "backfilled", error, 100 * rmse / path
    )


def _scene_outcomes(args: tuple[str, int, list[int], list[Blackout], int, tuple[str, ...]]) -> list[Outcome]:
    """Every case of one scene (rendered once)."""
    trajectory, seed, frontend_seeds, blackouts, after, overrides = args
    logging.basicConfig(level=logging.ERROR)
    needed = max(b.first_black + b.black + after for b in blackouts)
    camera, frames, _ = scene_frames(trajectory, seed, SCENE_FRAMES, rendered_frames=needed)
    outcomes = []
    for fs in frontend_seeds:
        for b in blackouts:
            name = f"{trajectory}_{seed}/seed{fs}/{b.first_black}-{b.resume}"
            outcomes.append(outcome(name, camera, b.sequence(frames, after), b, (*overrides, f"seed={fs}")))
    return outcomes


def summarise(outcomes: Sequence[Outcome], map_error_percent: float, wrong_m: float) -> dict[str, Any]:
    relocalised = [o for o in outcomes if o.result in ("relocalised", "backfilled")]
    judged = [
        o for o in relocalised if o.map_error_percent is not None and o.map_error_percent < map_error_percent
    ]
    errors = [o.error_m for o in judged if o.error_m is not None]
    return {
        "cases": len(outcomes),
        "relocalised": len(relocalised),
        "new_segment": sum(o.result == "new segment" for o in outcomes),
        "unposed": sum(o.result == "none" for o in outcomes),
        "no_map_before": sum(o.result == "no map before" for o in outcomes),
        "relocalised_on_right_maps": len(judged),
        "wrong_relocalisations": sum(e > wrong_m for e in errors),
        "median_error_m": statistics.median(errors) if errors else None,
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trajectories", default="loop,figure8,out-and-back")
    parser.add_argument("--seeds", default="0-1", help="scene seeds: 0,1 or 0-6 (default 0-1)")
    parser.add_argument("--frontend-seeds", default="0-2", help="the frontend's RANSAC seeds (default 0-2)")
    parser.add_argument("--blackouts", default="40,70,100", help="first black frame of each case")
    parser.add_argument("--black", type=int, default=20, help="black frames (default 20)")
    parser.add_argument(
        "--back", type=int, default=15, help="'back' resumes this many frames before the blackout"
    )
    parser.add_argument("--after", type=int, default=50, help="frames run after the blackout (default 50)")
    parser.add_argument(
        "--map-error", type=float, default=2.0, help="a right map: ATE below this %% of its path"
    )
    parser.add_argument("--wrong", type=float, default=0.1, help="a wrong relocalisation: off by more (m)")
    parser.add_argument("--jobs", type=int, default=2, help="parallel scenes (default 2)")
    add_set_option(parser, "override a mono-vo setting, e.g. relocalisation.max_sigma_ratio=4 (repeatable)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    try:
        seeds, frontend_seeds = parse_seeds(args.seeds), parse_seeds(args.frontend_seeds)
        firsts = parse_seeds(args.blackouts)
        create(CameraIntrinsics(500, 500, 320, 240, 640, 480), args.overrides)  # a bad --set fails here
    except ConfigError as error:
        parser.error(str(error))
    if min(firsts) - args.back < 0 or min(firsts) < 10 or args.black < 1 or args.after < 1:
        parser.error("--blackouts must start at frame 10 or later and after --back; --black, --after >= 1")
    blackouts = [Blackout(f, args.black, r, args.back) for f in firsts for r in ("on", "back")]
    tasks = [
        (t, s, frontend_seeds, blackouts, args.after, tuple(args.overrides))
        for t in args.trajectories.split(",")
        for s in seeds
    ]
    outcomes: list[Outcome] = []
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for scene in pool.map(_scene_outcomes, tasks):
            outcomes += scene
    print("\n| case | first posed after the blackout | error (m) | map before (% of path) |")
    print("|---|---|---|---|")
    for o in outcomes:
        off = "" if o.error_m is None else f"{o.error_m:.3f}"
        before = "" if o.map_error_percent is None else f"{o.map_error_percent:.2f}"
        print(f"| {o.name} | {o.result} | {off} | {before} |")
    summary = summarise(outcomes, args.map_error, args.wrong)
    median = summary["median_error_m"]
    print(
        f"\n{summary['cases']} cases: {summary['relocalised']} relocalised, {summary['new_segment']} new "
        f"segments, {summary['unposed']} unposed; of {summary['relocalised_on_right_maps']} relocalisations "
        f"on a map within {args.map_error} % of its path, {summary['wrong_relocalisations']} off by more "
        f"than {args.wrong} m (median {'-' if median is None else f'{median:.3f}'} m)"
    )
    write_json(
        args.json,
        {"overrides": " ".join(args.overrides), **summary,
         **{f"{o.name}:{key}": value for o in outcomes for key, value in
            (("result", o.result), ("error_m", o.error_m), ("map_error_percent", o.map_error_percent))}},
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
