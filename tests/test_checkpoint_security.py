"""Checkpoints that cannot run code, and resume that works from anywhere (issue 41).

A checkpoint is signed with the user's key (here the test session's: ``conftest.checkpoint_key``);
a forged payload, an edited header, another user's checkpoint, a payload outside the run folder and
a lax key are refused before a byte is unpickled, and the unpickler refuses what a run's state is
not made of even when the signature is valid. A run started with a relative dataset path and
killed resumes from another directory, with DATASET repeated or with ``--dataset`` after the
folder moved, to the outputs of an uninterrupted run; a changed dataset is refused.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import re
import secrets
import shutil
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from eval import checkpoint
from eval.checkpoint import HEADER_FILE, KEY_ENV, CheckpointError, FrameImages, check_dataset, read_header
from eval.cli import main as symbio_main
from eval.run import KEYFRAMES_FILE, LOOPS_FILE, ODOMETRY_FILE, TRAJECTORY_FILE
from frontends.datasets import open_dataset
from frontends.errors import ModelError
from slam_backend.slam import SlamState

COMPARED = (TRAJECTORY_FILE, ODOMETRY_FILE, KEYFRAMES_FILE, LOOPS_FILE)
FRAMES = 40
EVERY = 10


def checkpointed_frames(out: Path) -> int:
    try:
        return int(read_header(out)["frames"])
    except CheckpointError:
        return 0


@pytest.fixture(scope="module")
def data(small_loop_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding a copy of the small loop scene (hard links: the test that moves it must not
    move the session's scene) as ``loop``."""
    folder = tmp_path_factory.mktemp("data")
    shutil.copytree(small_loop_scene, folder / "loop", copy_function=os.link)
    return folder


@pytest.fixture(scope="module")
def killed(data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A checkpointed run started in ``data`` with the relative dataset path ``loop``, killed with
    SIGKILL once its first checkpoint exists."""
    out = tmp_path_factory.mktemp("killed") / "run"
    command = [sys.executable, "-m", "eval.cli", "run", "loop", "--max-frames", str(FRAMES), "--no-progress"]
    command += ["--checkpoint-every", str(EVERY), "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    process = subprocess.Popen(
        command, cwd=data, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        deadline = time.monotonic() + 120
        while checkpointed_frames(out) < EVERY:
            assert process.poll() is None, f"the run ended (rc {process.returncode}) before a checkpoint"
            assert time.monotonic() < deadline, "no checkpoint in time"
            time.sleep(0.01)
        process.send_signal(signal.SIGKILL)
    finally:
        process.wait()
    assert process.returncode == -signal.SIGKILL and checkpointed_frames(out) < FRAMES
    return out


@pytest.fixture(scope="module")
def reference(data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "run"
    argv = ["run", str(data / "loop"), "--max-frames", str(FRAMES), "--no-progress", "--out", str(out)]
    assert symbio_main(argv) == 0
    return out


@pytest.fixture
def run(killed: Path, tmp_path: Path) -> Path:
    """A copy of the killed run's folder, for a test to resume or tamper with."""
    return Path(shutil.copytree(killed, tmp_path / "run"))


def resume(run: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    capsys.readouterr()
    code = symbio_main(["run", *extra, "--resume", str(run), "--no-progress"])
    return code, capsys.readouterr().err


def same_outputs(run: Path, reference: Path) -> bool:
    return all((run / name).read_bytes() == (reference / name).read_bytes() for name in COMPARED)


def rewrite(run: Path, header: dict[str, Any], payload: bytes | None = None, *, sign: bool) -> None:
    """Write ``header`` (and ``payload`` in place of the checkpoint's, with its size and SHA-256
    recomputed as the issue's attacker did); ``sign``: as the key's owner would."""
    path = run / str(header["payload"])
    if payload is not None:
        path.write_bytes(payload)
        header.update(bytes=len(payload), sha256=hashlib.sha256(payload).hexdigest())
    if sign:
        header["mac"] = checkpoint._mac(checkpoint.signing_key(), header, path.read_bytes())
    (run / HEADER_FILE).write_text(json.dumps(header))


class _Shell:
    """Unpickles as ``os.system(command)``: what a forged checkpoint would run."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self) -> tuple[Any, ...]:
        return os.system, (self.command,)


# --- forged and foreign checkpoints ------------------------------------------------------------


def test_a_forged_payload_is_refused_before_it_runs(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "ran"
    rewrite(run, read_header(run), pickle.dumps(_Shell(f"touch {marker}")), sign=False)
    code, error = resume(run, capsys)
    assert code == 2 and f"{run / HEADER_FILE}: the checkpoint is not signed with your key" in error
    assert not marker.exists()


def test_a_signed_forged_payload_is_still_refused_by_the_unpickler(
    run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Defence in depth: even with the key (a valid MAC), a global outside the allowlist fails."""
    marker = tmp_path / "ran"
    header = read_header(run)
    rewrite(run, header, pickle.dumps(_Shell(f"touch {marker}")), sign=True)
    code, error = resume(run, capsys)
    assert code == 2 and f"{run / header['payload']}: the checkpoint refers to posix.system," in error
    assert not marker.exists()


@pytest.mark.parametrize(
    "edit",
    [
        lambda header: header.update(next_index=header["next_index"] + 1),
        lambda header: header.update(frames=header["frames"] - 1),
        lambda header: header["dataset"].update(frames=header["dataset"]["frames"] + 1),
    ],
    ids=["next_index", "frames", "dataset"],
)
def test_an_edited_header_is_refused(
    run: Path, capsys: pytest.CaptureFixture[str], edit: Callable[[dict[str, Any]], object]
) -> None:
    header = read_header(run)
    edit(header)
    rewrite(run, header, sign=False)
    code, error = resume(run, capsys)
    assert code == 2 and f"{run / HEADER_FILE}: the checkpoint is not signed with your key" in error


def test_a_checkpoint_of_another_user_or_machine_is_refused(
    run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "nokey" / "checkpoint.key"
    monkeypatch.setenv(KEY_ENV, str(missing))
    code, error = resume(run, capsys)
    assert code == 2 and f"no checkpoint key at {missing}: this checkpoint was made by another user" in error
    assert not missing.exists()  # resuming never creates a key
    other = tmp_path / "other.key"
    other.write_bytes(secrets.token_bytes(32))
    other.chmod(0o600)
    monkeypatch.setenv(KEY_ENV, str(other))
    code, error = resume(run, capsys)
    assert code == 2 and f"the checkpoint is not signed with your key ({other})" in error


def test_an_unsigned_version_1_checkpoint_is_refused(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    header = read_header(run)
    header["version"] = 1
    del header["mac"]
    (run / HEADER_FILE).write_text(json.dumps(header))
    code, error = resume(run, capsys)
    assert code == 2 and "checkpoint version 1 was made by an older symbiolcd2 that did not sign" in error


def _outside(run: Path, header: dict[str, Any]) -> Path:
    """The payload moved out of the run folder and named by ``../`` in a re-signed header."""
    payload = run / header["payload"]
    payload.rename(run.parent / "outside.pkl")
    header["payload"] = "../outside.pkl"
    rewrite(run, header, sign=True)
    return run / HEADER_FILE


def _symlinked(run: Path, header: dict[str, Any]) -> Path:
    """The payload moved out of the run folder with a symlink to it in its place (MAC valid)."""
    payload = run / header["payload"]
    payload.rename(run.parent / "outside.pkl")
    payload.symlink_to(run.parent / "outside.pkl")
    return payload


@pytest.mark.parametrize(
    ("place", "message"),
    [
        (_outside, "payload '../outside.pkl' is not a checkpoint-NNNNNN.pkl file"),
        (_symlinked, "symbolic link"),
    ],
)
def test_a_payload_outside_the_run_folder_is_refused(
    run: Path,
    capsys: pytest.CaptureFixture[str],
    place: Callable[[Path, dict[str, Any]], Path],
    message: str,
) -> None:
    named = place(run, read_header(run))
    code, error = resume(run, capsys)
    assert code == 2 and f"{named}: " in error and message in error


def _reduced(function: Any, *args: Any) -> bytes:
    class Call:
        def __reduce__(self) -> tuple[Any, ...]:
            return function, args

    return pickle.dumps(Call())


@pytest.mark.parametrize(
    ("data", "refused"),
    [
        (lambda marker: _reduced(os.system, f"touch {marker}"), "posix.system"),
        (lambda marker: f"cos\nsystem\n(S'touch {marker}'\ntR.".encode(), "os.system"),
        (lambda marker: _reduced(eval, f"open({str(marker)!r}, 'w')"), "builtins.eval"),
        (lambda marker: _reduced(subprocess.Popen, ["touch", str(marker)]), "subprocess.Popen"),
        (
            lambda marker: b"cbuiltins\ngetattr\n(cslam_backend.slam\nSlamState\nS'__init__'\ntR.",
            "getattr(builtins.type, '__init__')",
        ),
        # What the project's modules imported, and project functions that are no reconstructors.
        (
            lambda marker: f"ceval.checkpoint\nos.system\n(S'touch {marker}'\ntR.".encode(),
            "eval.checkpoint.os.system",
        ),
        (lambda marker: b"ceval.checkpoint\nos\n.", "eval.checkpoint.os"),
        (lambda marker: _reduced(checkpoint.discard, marker.parent), "eval.checkpoint.discard"),
        (lambda marker: _reduced(getattr, SlamState(), "add"), "getattr(slam_backend.slam.SlamState, 'add')"),
    ],
)
def test_the_unpickler_admits_only_what_a_run_state_is_made_of(
    tmp_path: Path, data: Callable[[Path], bytes], refused: str
) -> None:
    marker = tmp_path / "ran"
    path = tmp_path / "checkpoint-000010.pkl"
    unpickler = checkpoint._StateUnpickler(io.BytesIO(data(marker)), None, FrameImages(), path)  # type: ignore[arg-type]
    with pytest.raises(CheckpointError) as caught:
        unpickler.load()
    assert str(caught.value).startswith(f"{path}: the checkpoint refers to {refused}, ")
    assert not marker.exists() and path.parent.is_dir()


def test_a_state_that_does_not_pickle_is_one_clear_error(data: Path, tmp_path: Path) -> None:
    """ssd-mobilenet keeps an OpenCV network, which has no pickle support: no traceback."""
    saver = checkpoint.Checkpointer(tmp_path, 1, {}, open_dataset(data / "loop"))
    state = checkpoint.RunState(cv2.dnn.Net(), None, SlamState(), 0, [])  # type: ignore[arg-type]
    with pytest.raises(
        CheckpointError, match=r"cannot pickle 'cv2.dnn.Net' object.*--checkpoint-every"
    ) as caught:
        saver.save(state)
    assert caught.value.path == str(tmp_path / "checkpoint-000000.pkl") and not list(tmp_path.iterdir())


# --- the key ----------------------------------------------------------------------------------


def test_the_key_is_created_private_once_and_a_lax_key_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(KEY_ENV)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    assert checkpoint.key_path() == tmp_path / "home" / ".config" / "symbiolcd2" / "checkpoint.key"
    monkeypatch.setenv("XDG_CONFIG_HOME", "relative")  # invalid per the XDG spec: ignored
    assert checkpoint.key_path() == tmp_path / "home" / ".config" / "symbiolcd2" / "checkpoint.key"
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    path = tmp_path / "config" / "symbiolcd2" / "checkpoint.key"
    assert checkpoint.key_path() == path and not path.exists()
    key = checkpoint.signing_key()
    assert len(key) == 32 and path.read_bytes() == key
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert checkpoint.signing_key() == key
    assert [p.name for p in path.parent.iterdir()] == ["checkpoint.key"]  # no temporary file left
    path.chmod(0o644)
    with pytest.raises(
        CheckpointError, match=rf"^{re.escape(str(path))}: .*-rw-r--r--.* chmod 600 {re.escape(str(path))}$"
    ):
        checkpoint.signing_key()
    path.chmod(0o600)
    path.write_bytes(b"short")
    with pytest.raises(CheckpointError, match="has 5 bytes, fewer than 32"):
        checkpoint.signing_key()
    path.unlink()
    path.mkdir()
    with pytest.raises(CheckpointError, match="is not a regular file"):
        checkpoint.signing_key()


def test_a_key_made_concurrently_wins(tmp_path: Path) -> None:
    """Two runs creating the key at once: the second finds the first's in place and uses it."""
    path = tmp_path / "checkpoint.key"
    first = secrets.token_bytes(32)
    path.write_bytes(first)
    path.chmod(0o600)
    assert checkpoint._create_key(path) == first and path.read_bytes() == first
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.key"]


def test_a_lax_key_is_refused_on_resume(run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = checkpoint.key_path()
    key.chmod(0o640)
    try:
        code, error = resume(run, capsys)
    finally:
        key.chmod(0o600)
    assert code == 2 and f"{key}: the checkpoint key has permissions -rw-r-----" in error


# --- resume from anywhere -------------------------------------------------------------------------


def test_resume_from_another_directory_gives_the_uninterrupted_outputs(
    run: Path, reference: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The issue's case: started with a relative dataset path, resumed elsewhere."""
    monkeypatch.chdir(tmp_path)
    assert symbio_main(["run", "--resume", str(run), "--no-progress"]) == 0
    assert same_outputs(run, reference)


@pytest.mark.parametrize("spelling", ["relative", "absolute"])
def test_resume_with_the_dataset_repeated_from_another_directory(
    run: Path, reference: Path, data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spelling: str
) -> None:
    monkeypatch.chdir(tmp_path)
    dataset = os.path.relpath(data / "loop") if spelling == "relative" else str(data / "loop")
    assert symbio_main(["run", dataset, "--resume", str(run), "--no-progress"]) == 0
    assert same_outputs(run, reference)


def test_resume_after_the_dataset_moved(
    run: Path, reference: Path, data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    moved = data / "moved"
    (data / "loop").rename(moved)
    try:
        code, error = resume(run, capsys)
        assert code == 2 and f"{data / 'loop'} is not there any more: if it moved, give --dataset" in error
        code, error = resume(run, capsys, "--dataset", str(moved))
        assert code == 0, error
    finally:
        moved.rename(data / "loop")
    assert same_outputs(run, reference)


def test_dataset_needs_resume(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["run", str(data / "loop"), "--dataset", str(data / "loop"), "--out", str(tmp_path / "out")]
    assert symbio_main(argv) == 2
    assert "--dataset NEW_PATH goes with --resume DIR" in capsys.readouterr().err


def _replace(path: Path, data: bytes) -> None:
    """New contents in a new file: the copies are hard links to the session's scene."""
    path.unlink()
    path.write_bytes(data)


def _image(copy: Path, line: int) -> Path:
    return copy / (copy / "rgb.txt").read_text().splitlines()[line].split()[1]


def _repaint(copy: Path) -> None:
    image = cv2.imread(str(_image(copy, 10)))
    image[0, 0] ^= 1
    _replace(_image(copy, 10), cv2.imencode(".png", image)[1].tobytes())


def _add(copy: Path) -> None:
    lines = (copy / "rgb.txt").read_text().splitlines(keepends=True)
    stamp, name = lines[-1].split()
    _replace(copy / "rgb.txt", "".join(lines).encode() + f"{float(stamp) + 1:.6f} rgb/extra.png\n".encode())
    shutil.copy(copy / name, copy / "rgb" / "extra.png")


def _remove(copy: Path) -> None:
    """The last frame removed: its image, its line and the GT loop pairs that name it."""
    last = len(open_dataset(copy).entries) - 1
    lines = (copy / "rgb.txt").read_text().splitlines(keepends=True)
    _image(copy, -1).unlink()
    _replace(copy / "rgb.txt", "".join(lines[:-1]).encode())
    pairs = (copy / "gt_loop_pairs.txt").read_text().splitlines(keepends=True)
    kept = [line for line in pairs if line.startswith("#") or str(last) not in line.split()]
    _replace(copy / "gt_loop_pairs.txt", "".join(kept).encode())


@pytest.mark.parametrize("change", [_repaint, _add, _remove, lambda copy: _image(copy, 20).unlink()])
def test_a_changed_dataset_is_refused(
    killed: Path, data: Path, tmp_path: Path, change: Callable[[Path], None]
) -> None:
    copy = Path(shutil.copytree(data / "loop", tmp_path / "copy", copy_function=os.link))
    header = read_header(killed)
    check_dataset(header, open_dataset(copy), killed)  # the same data elsewhere is accepted
    change(copy)
    with pytest.raises(CheckpointError, match=r"another dataset or dataset version \((frames|sha256) "):
        check_dataset(header, open_dataset(copy), killed)


def test_the_cnn_object_detectors_survive_a_checkpoint(tmp_path: Path) -> None:
    """The default object detector on real data holds an OpenCV network: it is pickled as its config
    and model digest and loaded again, giving the same boxes; a model file changed since is refused."""
    from lcd.objects.onnx import OnnxConfig, OnnxDetector
    from lcd.objects.ssd_cv2 import create as create_ssd

    image = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    image[60:180, 100:220] = (20, 40, 200)
    path = tmp_path / "p.pkl"
    ssd = create_ssd()
    payload = checkpoint.dumps_state(ssd, FrameImages())
    restored = checkpoint._StateUnpickler(io.BytesIO(payload), None, FrameImages(), path).load()  # type: ignore[arg-type]
    assert restored is not ssd and restored.detect(image) == ssd.detect(image)
    model = tmp_path / "model.onnx"
    model.write_bytes(b"not a model")
    detector = object.__new__(OnnxDetector)
    detector.config, detector.model_path = OnnxConfig(model=str(model)), model
    payload = checkpoint.dumps_state(detector, FrameImages())
    model.write_bytes(b"changed")
    with pytest.raises(ModelError, match="model file changed since the checkpoint"):
        checkpoint._StateUnpickler(io.BytesIO(payload), None, FrameImages(), path).load()  # type: ignore[arg-type]
