"""``symbio run``: stream a dataset through the SLAM pipeline and measure it.

frontend (each frame) -> object detector, loop detector (each keyframe) -> verifier -> backend
(``slam_backend.pipeline.LoopClosing``). Components are chosen by name (``--frontend``,
``--detector``, ``--object-detector``, ``--verifier``, ``--backend``) and configured by a run YAML
(``--config``: sections ``frontend``, ``detector``, ``object_detector``, ``verifier``, ``backend``,
``loop_closing``; each may name its component with ``name:``; a YAML without any section is the
frontend's own config) and by ``--set KEY=VALUE`` (a key starting with one of those section names
goes to that component, any other key to the frontend). ``--no-loops``: odometry only.

Writes to ``--out DIR``:

* ``trajectory_tum.txt``: every posed frame, loop-closed (each frame anchored to the backend's
  estimate of its keyframe); ``trajectory_odometry_tum.txt``: the same frames, odometry only;
  ``keyframes_tum.txt``: the loop-closed keyframes. Without loop closing the first equals the second.
* ``loops.csv``: every verified candidate: query, match (keyframe ids and frames), score, verified,
  inliers, accepted (the backend's final decision), scale, reason and, with GT poses, the
  constraint's rotation and translation-direction error against them (deg).
* ``metrics.json``: ``frames``, ``frames_tracked``, ``tracking_lost``, ``frames_initialising``
  (seen while a map initialised and not posed afterwards), ``frontend_failures``,
  ``frames_skipped`` (never given to the frontend: missing or undecodable images, duplicate or
  backwards timestamps) and ``frames_skipped_<cause>`` (per ``SKIP_CAUSES``), ``keyframes``,
  ``segments``, ``fps`` (frames per second of the whole pipeline),
  ``ms_per_frame_<stage>`` (frontend, objects, loop_detector, verifier, backend), ``ate_rmse_before`` /
  ``ate_rmse_after`` (evo APE translation RMSE after Sim(3) Umeyama alignment to the GT, odometry vs
  loop-closed, over the same frames: those of segment ``ate_segment``, the one with most tracked
  frames), ``ate_rmse_after_all`` (every posed frame; segments are one graph after loop closing),
  ``rpe_rmse_before`` / ``rpe_rmse_after`` (evo RPE translation over 1 s, on the aligned
  trajectories), ``loops_proposed`` (candidates verified), ``loops_verified``, ``loops_accepted``,
  ``false_loops_accepted`` (constraints that contradict the GT poses; see ``loop_truth``),
  ``loops_outside_gt_band``, ``lcd_precision`` / ``lcd_recall`` of the accepted loops against the GT
  loop pairs (``--tolerance`` frames), ``path_length`` (GT, m), ``interrupted``, the plugin
  failures (``object_detector_failures``, ``loop_detector_failures``, ``verifier_failures``,
  ``verifier_timeouts``) and, with ``--inject``, ``faults_injected_<kind>`` (per kind). Figures
  that need GT are null without it.

Checkpoint and resume: ``--checkpoint-every N`` saves the whole run state to ``DIR/checkpoint.json``
and ``DIR/checkpoint-FFFFFF.pkl`` every N frames (atomically; see ``eval.checkpoint``); after a
crash or ``kill -9``, ``symbio run --resume DIR`` continues with the stored dataset and options and
writes the outputs an uninterrupted run writes, bit for bit, from any working directory (add
``--dataset NEW_PATH`` if the dataset moved: its content must be the same). While
``checkpoint.json`` exists the run is unfinished: a checkpointed run deletes earlier outputs in DIR
when it starts or resumes, and its checkpoint once its outputs are written.
Trust: a checkpoint is a pickle (loading one could run code), so it is signed with an HMAC keyed by
your per-user secret, ``$SYMBIO_CHECKPOINT_KEY`` or ``~/.config/symbiolcd2/checkpoint.key``
(``$XDG_CONFIG_HOME``; made on the first checkpointed run, mode 600), and only checkpoints your key
signed are loaded: an edited or forged one is refused, and resuming another user's or machine's
checkpoint needs their key. An unpickler that admits only the classes of a run's state is a second
line of defence.

A frontend that raises on a frame costs only that frame (logged with the image path, counted lost);
failing object/loop detectors and verifiers cost one keyframe or candidate (counted), a verifier
past ``loop_closing.verify_timeout_s`` its candidate (reason "timeout"). ``--inject`` injects
faults to try this (``eval.inject``; docs/what-we-test-against.md). When the run
stops early (Ctrl-C, an unreadable image with --strict), whatever was processed is written before
the error is re-raised.

Examples:
  symbio run scene --out run                                     # mono-vo + symbiolcd2 + pycolmap + gtsam
  symbio run scene --no-loops --out run_vo                       # odometry only
  symbio run scene --detector vbow --set detector.threshold=0.1 --out run_vbow
  symbio run scene --frontend replay --set trajectory=scene/groundtruth.txt --no-loops --out run_gt
  symbio run scene --inject corrupt-image:0.05,black:0.02,objects-raise --inject-seed 1 --out run_faults
  symbio run scene --checkpoint-every 50 --out run                # after a crash: symbio run --resume run
  symbio run kitti/sequences/06 --frontend replay --set trajectory=orb.txt --set format=kitti \\
      --no-loops --out run_orb
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import fields
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from eval.components import SECTIONS, Components, load_components
from eval.inject import KINDS, Injection, InjectionSpec
from frontends.base import FRONTENDS
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import config_to_dict
from frontends.datasets import Dataset, open_dataset
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError, display_path
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS
from slam_backend.plugins import BACKENDS, VERIFIERS

if TYPE_CHECKING:  # imported where they are used: checking the command line needs none of them
    from eval.outputs import RunFolder
    from slam_backend.pipeline import LoopClosing


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the SLAM pipeline over a dataset: trajectories, loops, ATE/RPE before and after",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_arguments(parser, path_optional=True)
    defaults = Components()
    parser.add_argument(
        "--frontend",
        help=f"frontend ({', '.join(FRONTENDS.names())}; default {defaults.frontend}). "
        "replay takes its poses from a file: --set trajectory=FILE [--set format=kitti]",
    )
    parser.add_argument(
        "--detector", help=f"loop detector ({', '.join(LOOP_DETECTORS.names())}; default {defaults.detector})"
    )
    parser.add_argument(
        "--object-detector",
        help=f"object detector ({', '.join(OBJECT_DETECTORS.names())}; default: oracle on synthetic "
        "scenes, ssd-mobilenet elsewhere)",
    )
    parser.add_argument("--verifier", help=f"verifier ({', '.join(VERIFIERS.names())}; default pycolmap)")
    parser.add_argument(
        "--backend", help=f"pose-graph backend ({', '.join(BACKENDS.names())}; default gtsam)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        help=f"run YAML with sections {', '.join(SECTIONS)} (each may set name:), or a frontend config",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a setting: SECTION.key=value for " + ", ".join(SECTIONS[1:]) + "; other keys "
        "(or frontend.key) go to the frontend",
    )
    parser.add_argument("--no-loops", action="store_true", help="odometry only, no loop closing")
    parser.add_argument(
        "--viewer",
        choices=["rerun"],
        help="log images, keypoints, objects, the three-tier graph, trajectories and loops to rerun: "
        "DIR/run.rrd, or a running viewer with --viewer-connect (optional extra symbiolcd2[viewer])",
    )
    parser.add_argument("--viewer-connect", metavar="URL", help="gRPC URL of a running rerun viewer")
    parser.add_argument(
        "--tolerance",
        type=int,
        default=3,
        help="frames an accepted loop may be off a GT reference (default 3)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        metavar="DIR",
        help="output folder (with --resume: DIR). A folder holding files symbio did not write is "
        "refused; a folder of an earlier run has that run's files replaced",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a --out folder that holds other files: only the files symbio run writes "
        "are replaced, the others are left alone",
    )
    parser.add_argument("--max-frames", type=int, metavar="N", help="stop after the first N frames")
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        metavar="N",
        help="save the whole run state to the output folder every N frames (atomically; deleted "
        "when the run ends) so that --resume can continue after a crash or kill",
    )
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the checkpointed run in DIR with its stored dataset and options (DATASET and "
        "options may be repeated but must match); the outputs equal an uninterrupted run's. Only "
        "checkpoints signed with your key ($SYMBIO_CHECKPOINT_KEY, default "
        "~/.config/symbiolcd2/checkpoint.key) are loaded: a checkpoint is a pickle",
    )
    parser.add_argument(
        "--dataset",
        type=Path,
        metavar="NEW_PATH",
        help="with --resume: the run's dataset moved to NEW_PATH (its content must be unchanged)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--inject",
        metavar="KIND[:RATE],...",
        help="debug: inject faults into the run, RATE = fraction of frames or plugin calls hit. Kinds: "
        f"{', '.join(KINDS)} (see eval/inject.py and docs/what-we-test-against.md)",
    )
    parser.add_argument(
        "--inject-seed", type=int, default=0, metavar="N", help="seed of the --inject choices (default 0)"
    )
    add_json_option(parser)
    parser.set_defaults(handler=lambda args: run_command(args, parser.get_default))


def describe(components: Components, closing: LoopClosing, args: argparse.Namespace) -> dict[str, Any]:
    """The run's configuration as the report shows it: component names, settings, options."""
    return {
        "dataset": display_path(args.path),
        "no_loops": args.no_loops,
        "tolerance": args.tolerance,
        "inject": args.inject,
        "inject_seed": args.inject_seed if args.inject else None,
        "components": {
            f.name: getattr(components, f.name) for f in fields(Components) if f.name != "overrides"
        },
        "overrides": components.overrides,
        "loop_closing": config_to_dict(closing.config),
    }


#: Options that do not change what a run computes: a resumed run may set them anew.
RESUME_FREE_OPTIONS = ("handler", "command", "verbose", "resume", "out", "json", "no_progress", "overwrite")
#: How the options whose name is not their destination are spelled in messages.
OPTION_NAMES = {"path": "DATASET", "fmt": "--format", "overrides": "--set"}


def resumed_options(
    args: argparse.Namespace, default: Callable[[str], Any], header: dict[str, Any]
) -> argparse.Namespace:
    """``args`` with the run options stored in the checkpoint; a conflicting option given on the
    command line is a CheckpointError (naming the header). The stored dataset path is absolute
    (``checkpoint.run_spec``), so the working directory does not matter; ``--dataset NEW_PATH``
    replaces it (``checkpoint.check_dataset`` then checks that the content is the same)."""
    from eval import checkpoint
    from eval.checkpoint import CheckpointError

    assert args.resume is not None
    path = args.resume / checkpoint.HEADER_FILE
    if args.out is not None and args.out.resolve() != args.resume.resolve():
        raise CheckpointError(path, f"--out {args.out} differs from --resume {args.resume}")
    stored = header["spec"]
    moved: Path | None = getattr(args, "dataset", None)
    options = {key: value for key, value in vars(args).items() if key != "dataset"}
    if moved is not None:
        if args.path is not None and args.path.resolve() != moved.resolve():
            raise ConfigError(f"DATASET {args.path} and --dataset {moved}: give the moved dataset once")
        options["path"] = None  # the new place, not the stored one
    given = checkpoint.run_spec(options, RESUME_FREE_OPTIONS)
    for key, value in given.items():
        if value == checkpoint.run_spec({key: default(key)}, ())[key]:
            continue  # not given on this command line
        if stored.get(key) != value:
            option = OPTION_NAMES.get(key, "--" + key.replace("_", "-"))
            hint = " (if the dataset moved, give --dataset NEW_PATH)" if key == "path" else ""
            raise CheckpointError(
                path, f"the checkpoint was made with {option} {stored.get(key)!r}, not {value!r}{hint}"
            )
    resumed = argparse.Namespace(**vars(args))
    paths = set(stored["path_options"])
    for key, value in stored.items():
        if key not in ("components", "path_options"):
            setattr(resumed, key, Path(value) if key in paths and value is not None else value)
    if moved is not None:
        resumed.path = moved
    elif resumed.path is not None and not resumed.path.exists():
        raise CheckpointError(
            path,
            f"the run's dataset {resumed.path} is not there any more: if it moved, give --dataset NEW_PATH",
        )
    resumed.dataset = None
    resumed.out = args.resume
    return resumed


def run_command(args: argparse.Namespace, default: Callable[[str], Any] = lambda key: None) -> int:
    """``symbio run``; ``default`` gives the parser's default of an option (what --resume compares)."""
    if getattr(args, "dataset", None) is not None and args.resume is None:
        raise ConfigError("--dataset NEW_PATH goes with --resume DIR (a checkpointed run's dataset moved)")
    header = None
    if args.resume is not None:
        from eval import checkpoint

        header = checkpoint.read_header(args.resume)
        checkpoint.verified_payload(header, args.resume)  # nothing of a forged header is used
        args = resumed_options(args, default, header)
    if args.path is None or args.out is None:
        raise ConfigError("symbio run: give DATASET and --out DIR (or --resume DIR)")
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames {args.max_frames}: must be at least 1")
    if args.checkpoint_every is not None and args.checkpoint_every < 1:
        raise ConfigError(f"--checkpoint-every {args.checkpoint_every}: must be at least 1")
    if args.viewer is not None and (args.checkpoint_every is not None or header is not None):
        raise ConfigError("--viewer cannot be combined with --checkpoint-every or --resume")
    names = {
        "frontend": args.frontend,
        "detector": args.detector,
        "object_detector": args.object_detector,
        "verifier": args.verifier,
        "backend": args.backend,
    }
    components = load_components(args.config, args.overrides, names)
    dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    # Only now the pipeline's libraries (gtsam, pycolmap, OpenCV's networks): a bad command line,
    # config or calibration file is refused quickly and in little memory.
    from eval import checkpoint
    from eval.run import run_folder

    spec = {
        **checkpoint.run_spec(vars(args), RESUME_FREE_OPTIONS),
        "components": checkpoint.run_spec(vars(components), ()),
        "path_options": sorted(k for k, v in vars(args).items() if isinstance(v, Path)),
    }
    if args.inject and (args.checkpoint_every is not None or header is not None):
        # The injected faults' counters and wrappers are a debugging harness, not run state.
        raise ConfigError("--inject cannot be combined with --checkpoint-every or --resume")
    injection = Injection(InjectionSpec.parse(args.inject, args.inject_seed)) if args.inject else None
    folder = run_folder(args.out, overwrite=args.overwrite, resume=header is not None)
    with folder, sigterm_as_interrupt():
        return _run_claimed(args, folder, dataset, header, components, spec, injection)


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM stops a run as Ctrl-C does: what was processed is written, ``interrupted`` set."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_claimed(
    args: argparse.Namespace,
    folder: RunFolder,
    dataset: Dataset,
    header: dict[str, Any] | None,
    components: Components,
    spec: dict[str, Any],
    injection: Injection | None,
) -> int:
    """``symbio run`` once its output folder is claimed."""
    from eval import checkpoint
    from eval.checkpoint import Checkpointer, CheckpointError
    from eval.run import OUTPUT_FILES, RRD_FILE, build_slam, run_odometry
    from eval.viewer import RerunViewer
    from slam_backend.slam import Slam

    if injection is not None:
        dataset = injection.wrap_dataset(dataset)
    checkpointer = None
    if args.checkpoint_every is not None:
        checkpointer = Checkpointer(args.out, args.checkpoint_every, spec, dataset, folder.path)
    resume = None
    if header is None:
        slam = build_slam(dataset, components, loops=not args.no_loops)
        if injection is not None:
            injection.wrap_plugins(slam.closing, dataset)
    else:
        if spec["components"] != header["spec"]["components"]:
            raise CheckpointError(
                args.out / checkpoint.HEADER_FILE,
                f"the run config ({args.config or '--set options'}) changed since the checkpoint was made",
            )
        fingerprint = checkpointer.fingerprint if checkpointer is not None else None
        checkpoint.check_dataset(header, dataset, args.out, fingerprint)
        images = checkpointer.images if checkpointer is not None else checkpoint.FrameImages()
        resume = checkpoint.load_state(header, args.out, dataset, images)
        slam = Slam.from_parts(resume.frontend, resume.closing, resume.run)
        where = display_path(args.out)
        print(f"resuming {where} after {header['frames']} frames (next frame {resume.next_index})")
    for note in dataset.notes:
        print(f"note: {note}")
    viewer = (
        RerunViewer(folder.path(RRD_FILE), args.viewer_connect, camera=dataset.camera)
        if args.viewer == "rerun"
        else None
    )
    figures = run_odometry(
        dataset,
        slam,
        folder,
        max_frames=args.max_frames,
        progress=not args.no_progress,
        tolerance=args.tolerance,
        config=describe(components, slam.closing, args),
        viewer=viewer,
        checkpointer=checkpointer,
        resume=resume,
    )
    print(f"run {slam.frontend.name} on {display_path(dataset.root)} ({dataset.format_name})")
    print_figures(figures)
    print(f"wrote {', '.join(display_path(args.out / f) for f in OUTPUT_FILES)}")
    write_json(args.json, figures)
    return 0
