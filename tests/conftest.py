"""One conftest: the ../shared fixture and the opt-in slow tests.

Tests that need the read-only shared data take the ``shared`` fixture and carry
``@pytest.mark.shared``; without the folder they skip, so ``make test`` passes on a user's machine.

Pipeline-scale tests (whole runs on long scenes, benchmarks) carry ``@pytest.mark.slow`` and are
skipped unless ``--runslow`` is given, so ``make test`` stays within a few minutes on 2 cores; each
area keeps a small end-to-end test in the default run. ``make test-slow`` runs the self-contained slow
tests and ``make test-shared`` passes ``--runslow`` too, so CI (``.ci/run``) runs every test.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


def shared_root() -> Path:
    return Path(os.environ.get("SYMBIO_SHARED", REPO_ROOT.parent / "shared")).resolve()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", help="also run tests marked slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip_slow)


@pytest.fixture(scope="session", autouse=True)
def checkpoint_key(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Checkpoints made by tests (and their subprocesses) are signed with a key of the session:
    the user's ~/.config/symbiolcd2/checkpoint.key is never created or read."""
    path = tmp_path_factory.mktemp("checkpoint_key") / "checkpoint.key"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("SYMBIO_CHECKPOINT_KEY", str(path))
        yield path


@pytest.fixture(scope="session")
def shared() -> Path:
    """The shared data folder (SYMBIO_SHARED, default ../shared); skips the test when absent."""
    root = shared_root()
    if not (root / "data").is_dir():
        pytest.skip(f"shared data not found at {root} (set SYMBIO_SHARED)")
    return root


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The output folder of ``symbio demo`` (640x480 loop, seed 0, 600 frames; ~1 min), made once.

    Its rendered scene is ``DIR/scene``. The demo's oracle objects mask the walking people, which
    keeps its odometry and loops the same from machine to machine, unlike the weak 320x240 scene.
    """
    from eval.cli import main as symbio_main

    out = tmp_path_factory.mktemp("demo") / "out"
    assert symbio_main(["demo", "--out", str(out), "--no-progress"]) == 0
    return out


@pytest.fixture(scope="session")
def small_loop_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 600-frame (20 s) 320x240 synthetic loop scene (TUM layout, GT objects and loops), made once."""
    from frontends.synth import SynthConfig, write_scene

    folder = tmp_path_factory.mktemp("synth") / "loop_320"
    config = SynthConfig(
        seed=3, trajectory="loop", frames=600, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5
    )
    write_scene(config, folder, progress=False)
    return folder
