"""Kill/resume benchmark on the demo run: ``kill -9`` at seeded random points, then ``--resume``.

Renders the demo scene (``symbio demo``'s seeded 600-frame loop), runs the demo's pipeline
(``symbio run`` with the oracle object detector at the demo's miss rate) once uninterrupted without
checkpoints (the reference) and once with ``--checkpoint-every N`` (its outputs must equal the
reference's; its metrics give the checkpoint size and ms per save), then ``--kills`` times: starts the
checkpointed run, kills it with SIGKILL at a seeded random point (after a random checkpoint, plus a
random fraction of a checkpoint interval: see ``kill_and_resume``), resumes it and compares
trajectory_tum.txt, trajectory_odometry_tum.txt, keyframes_tum.txt and loops.csv byte for byte with
the reference.

  python -m eval.bench.resume --out bench_resume_out --kills 5 --seed 0 --every 50 --json resume.json

Exit status 1 unless every round was killed and its resumed outputs equal the reference's.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from eval.checkpoint import HEADER_FILE
from eval.demo import DEMO_FRAMES, ORACLE_MISS_RATE
from eval.run import KEYFRAMES_FILE, LOOPS_FILE, METRICS_FILE, ODOMETRY_FILE, TRAJECTORY_FILE
from frontends.cli_common import write_json
from frontends.config import load_config
from frontends.synth.world import SynthConfig
from frontends.synth.writer import write_scene

COMPARED = (TRAJECTORY_FILE, ODOMETRY_FILE, KEYFRAMES_FILE, LOOPS_FILE)


def run_command(scene: Path, out: Path, every: int | None) -> list[str]:
    """The demo's pipeline on ``scene`` as a ``symbio run`` command line."""
    command = [sys.executable, "-m", "eval.cli", "run", str(scene), "--object-detector", "oracle"]
    command += ["--set", f"object_detector.miss_rate={ORACLE_MISS_RATE}", "--no-progress", "--out", str(out)]
    return command + (["--checkpoint-every", str(every)] if every is not None else [])


def timed_run(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def identical(a: Path, b: Path) -> bool:
    return all((a / name).read_bytes() == (b / name).read_bytes() for name in COMPARED)


def header_frames(out: Path) -> int:
    """Frames of the checkpoint in ``out`` (0 without one; a header being replaced reads as 0)."""
    try:
        return int(json.loads((out / HEADER_FILE).read_text())["frames"])
    except (OSError, ValueError, KeyError):
        return 0


def kill_and_resume(
    scene: Path, out: Path, every: int, frames: int, reference: Path, rng: np.random.Generator
) -> dict[str, Any]:
    """One checkpointed run killed at a random point, resumed, and compared with ``reference``.

    The point: once the checkpoint after a random multiple of ``every`` frames (below the last)
    exists, plus a random fraction of the mean time per checkpoint interval so far; the kill lands
    anywhere between two checkpoints (also during a save) whatever the machine's load."""
    target = every * int(rng.integers(1, max(frames // every, 2)))
    fraction = float(rng.uniform(0.0, 1.0))
    command = run_command(scene, out, every)
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    start = time.perf_counter()
    while process.poll() is None and header_frames(out) < target:
        time.sleep(0.02)
    time.sleep(fraction * (time.perf_counter() - start) / (target // every))
    killed = process.poll() is None
    if killed:
        process.send_signal(signal.SIGKILL)
    process.wait()
    resume_start = time.perf_counter()
    resumed = subprocess.run(
        [sys.executable, "-m", "eval.cli", "run", "--resume", str(out), "--no-progress"],
        capture_output=True,
        text=True,
    )
    if resumed.returncode != 0:
        print(resumed.stderr[-2000:], file=sys.stderr)
    found = re.search(r"resuming .* after (\d+) frames", resumed.stdout)
    return {
        "killed": killed,
        "kill_after_checkpoint": target,
        "kill_fraction_of_interval": round(fraction, 3),
        "resumed_from_frame": int(found.group(1)) if found else None,
        "resume_seconds": round(time.perf_counter() - resume_start, 1),
        "identical": resumed.returncode == 0 and identical(out, reference),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("bench_resume_out"), help="work folder")
    parser.add_argument("--kills", type=int, default=5, help="kill/resume rounds (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill delays (default 0)")
    parser.add_argument("--every", type=int, default=50, help="--checkpoint-every (default 50)")
    parser.add_argument(
        "--frames", type=int, default=DEMO_FRAMES, help=f"scene frames (default {DEMO_FRAMES})"
    )
    parser.add_argument("--json", type=Path, help="write the figures as JSON")
    args = parser.parse_args(argv)
    scene = args.out / "scene"
    config = load_config(SynthConfig, None, ["seed=0", f"frames={args.frames}", "trajectory=loop"])
    write_scene(config, scene, progress=False)
    reference = args.out / "reference"
    seconds = timed_run(run_command(scene, reference, None))
    checkpointed = args.out / "checkpointed"
    checkpointed_seconds = timed_run(run_command(scene, checkpointed, args.every))
    metrics = json.loads((checkpointed / METRICS_FILE).read_text())
    reference_metrics = json.loads((reference / METRICS_FILE).read_text())
    save_seconds = metrics["checkpoints"] * metrics["ms_per_checkpoint"] / 1e3
    pipeline_seconds = metrics["frames"] / metrics["fps"]
    rng = np.random.default_rng(args.seed)
    rounds = [
        kill_and_resume(scene, args.out / f"kill_{i}", args.every, metrics["frames"], reference, rng)
        for i in range(args.kills)
    ]
    figures = {
        "frames": metrics["frames"],
        "loops_accepted": reference_metrics["loops_accepted"],
        "checkpoint_every": args.every,
        "run_seconds": round(seconds, 1),
        "checkpointed_run_seconds": round(checkpointed_seconds, 1),
        "checkpointed_outputs_identical": identical(checkpointed, reference),
        "checkpoints": metrics["checkpoints"],
        "ms_per_checkpoint": metrics["ms_per_checkpoint"],
        "checkpoint_mb_last": metrics["checkpoint_bytes"] / 1e6,
        "checkpoint_overhead_percent": 100 * save_seconds / pipeline_seconds,
        "kills": sum(r["killed"] for r in rounds),
        "kills_identical": sum(r["killed"] and r["identical"] for r in rounds),
    }
    for key, value in figures.items():
        print(f"{key:32s} {value}")
    print("| round | killed after checkpoint | + fraction of an interval | resumed from | resume s | same |")
    print("|---|---|---|---|---|---|")
    for i, r in enumerate(rounds):
        after = r["kill_after_checkpoint"] if r["killed"] else "not killed"
        print(
            f"| {i} | {after} | {r['kill_fraction_of_interval']} | {r['resumed_from_frame']} | "
            f"{r['resume_seconds']} | {r['identical']} |"
        )
    write_json(
        args.json, {**figures, **{f"round_{i}_{k}": v for i, r in enumerate(rounds) for k, v in r.items()}}
    )
    good = figures["checkpointed_outputs_identical"] and figures["kills_identical"] == len(rounds)
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())
