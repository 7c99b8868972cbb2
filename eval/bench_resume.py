"""Kill/resume benchmark on the demo run: ``kill -9`` at seeded random points, then ``--resume``.

Renders the demo scene (``symbio demo``'s seeded 600-frame loop), runs the demo's pipeline
(``symbio run`` with the oracle object detector at the demo's miss rate) once uninterrupted without
checkpoints (the reference) and once with ``--checkpoint-every N`` (its outputs must equal the
reference's; its metrics give the checkpoint size and ms per save), then ``--kills`` times: starts the
checkpointed run, waits for its first checkpoint, kills it with SIGKILL after a seeded uniform delay
(up to 90 % of the reference's remaining run time), resumes it and compares trajectory_tum.txt,
trajectory_odometry_tum.txt, keyframes_tum.txt and loops.csv byte for byte with the reference.

  python -m eval.bench_resume --out bench_resume_out --kills 5 --seed 0 --every 50 --json resume.json

Exit status 1 if any resumed run differs from the reference.
"""

from __future__ import annotations

import argparse
import json
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


def kill_and_resume(
    scene: Path, out: Path, every: int, reference: Path, seconds: float, rng: np.random.Generator
) -> dict[str, Any]:
    """One checkpointed run killed after its first checkpoint plus a random delay, then resumed."""
    process = subprocess.Popen(
        run_command(scene, out, every), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    start = time.perf_counter()
    while not (out / HEADER_FILE).exists() and process.poll() is None:
        time.sleep(0.05)
    first = time.perf_counter() - start
    delay = float(rng.uniform(0.0, 0.9 * max(seconds - first, 0.0)))
    time.sleep(delay)
    killed = process.poll() is None
    if killed:
        process.send_signal(signal.SIGKILL)
    process.wait()
    frames = json.loads((out / HEADER_FILE).read_text())["frames"] if (out / HEADER_FILE).exists() else None
    resume_start = time.perf_counter()
    resumed = subprocess.run(
        [sys.executable, "-m", "eval.cli", "run", "--resume", str(out), "--no-progress"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    if resumed.returncode != 0:
        print(resumed.stderr[-2000:], file=sys.stderr)
    return {
        "killed": killed,
        "kill_after_s": round(first + delay, 2),
        "checkpoint_frames": frames,
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
        kill_and_resume(scene, args.out / f"kill_{i}", args.every, reference, seconds, rng)
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
        "kills": len(rounds),
        "kills_identical": sum(r["identical"] for r in rounds),
    }
    for key, value in figures.items():
        print(f"{key:32s} {value}")
    print(
        "| round | killed | after s | checkpoint frames | resume s | identical |\n|---|---|---|---|---|---|"
    )
    for i, r in enumerate(rounds):
        print(
            f"| {i} | {r['killed']} | {r['kill_after_s']} | {r['checkpoint_frames']} | {r['resume_seconds']} "
            f"| {r['identical']} |"
        )
    write_json(
        args.json, {**figures, **{f"round_{i}_{k}": v for i, r in enumerate(rounds) for k, v in r.items()}}
    )
    return 0 if figures["checkpointed_outputs_identical"] and figures["kills_identical"] == len(rounds) else 1


if __name__ == "__main__":
    sys.exit(main())
