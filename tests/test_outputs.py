"""Output folders that are safe to trust: claimed, locked, written atomically, never through symlinks."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from eval.cli import main as symbio_main
from eval.outputs import LOCK_FILE, MANIFEST_FILE, RunFolder
from eval.run import LOOPS_FILE, METRICS_FILE, OUTPUT_FILES, REPORT_FILE, TRAJECTORY_FILE
from frontends.errors import OutputError
from frontends.safe_io import TEMP_PREFIX, atomic_write_text

REPO = Path(__file__).resolve().parent.parent


def replay(scene: Path, out: Path, *extra: str) -> int:
    """A fast ``symbio run``: the GT replayed over the first 40 frames, no loop closing."""
    argv = ["run", str(scene), "--frontend", "replay", "--set", f"trajectory={scene / 'groundtruth.txt'}"]
    return symbio_main(
        [*argv, "--no-loops", "--no-progress", "--max-frames", "40", "--out", str(out), *extra]
    )


def metrics(out: Path) -> dict[str, Any]:
    value: dict[str, Any] = json.loads((out / METRICS_FILE).read_text())
    return value


def test_a_finished_run_says_complete_and_lists_its_files(small_loop_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert replay(small_loop_scene, out) == 0
    figures = metrics(out)
    assert figures["complete"] is True and figures["interrupted"] is False
    manifest = json.loads((out / MANIFEST_FILE).read_text())
    assert set(OUTPUT_FILES) <= set(manifest["files"])
    assert not [p for p in out.iterdir() if p.name.startswith(TEMP_PREFIX)]


def test_a_folder_with_the_users_files_is_refused_unless_overwrite(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    (out / METRICS_FILE).write_text('{"mine": 1}')
    (out / "checkpoint-000010.pkl").write_bytes(b"not symbio's")
    assert replay(small_loop_scene, out) == 2
    error = capsys.readouterr().err
    assert "symbio did not write" in error and "--overwrite" in error and str(out) in error
    assert (out / METRICS_FILE).read_text() == '{"mine": 1}'  # nothing touched
    assert not (out / TRAJECTORY_FILE).exists()
    assert replay(small_loop_scene, out, "--overwrite") == 0
    assert metrics(out)["complete"] is True  # its own name is replaced ...
    assert (out / "notes.txt").read_text() == "my notes"  # ... the rest is left alone
    assert (out / "checkpoint-000010.pkl").read_bytes() == b"not symbio's"


def test_running_again_into_its_own_folder_replaces_the_earlier_run(
    small_loop_scene: Path, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    assert replay(small_loop_scene, out) == 0
    (out / "ape_over_time.png").write_bytes(b"stale plot of the earlier run")
    manifest = json.loads((out / MANIFEST_FILE).read_text())
    manifest["files"].append("ape_over_time.png")
    (out / MANIFEST_FILE).write_text(json.dumps(manifest))
    gt = small_loop_scene / "groundtruth.txt"
    (tmp_path / "no_gt").mkdir()
    for item in small_loop_scene.iterdir():
        if item.name != "groundtruth.txt":
            (tmp_path / "no_gt" / item.name).symlink_to(item)
    argv = ["run", str(tmp_path / "no_gt"), "--frontend", "replay", "--set", f"trajectory={gt}"]
    assert symbio_main([*argv, "--no-loops", "--no-progress", "--max-frames", "40", "--out", str(out)]) == 0
    assert not (out / "ape_over_time.png").exists()  # without GT the new run has no APE plot
    assert metrics(out)["ate_rmse_before"] is None


def test_a_symlink_in_out_is_replaced_not_followed(small_loop_scene: Path, tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "run"
    out.mkdir()
    (out / TRAJECTORY_FILE).symlink_to(Path("..") / "victim.txt")
    assert replay(small_loop_scene, out) == 2  # a symlink symbio did not make is the user's entry
    assert replay(small_loop_scene, out, "--overwrite") == 0
    assert victim.read_text() == "precious"
    assert not (out / TRAJECTORY_FILE).is_symlink() and (out / TRAJECTORY_FILE).stat().st_size > 0


def test_a_symlink_planted_after_the_claim_is_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    with RunFolder(tmp_path / "run", "test", names=["a.txt"]) as folder:
        (folder.root / "a.txt").symlink_to(victim)
        folder.write_text("a.txt", "output")
    assert victim.read_text() == "precious"
    assert (tmp_path / "run" / "a.txt").read_text() == "output"


def test_a_symlinked_sub_folder_is_refused(tmp_path: Path) -> None:
    (tmp_path / "elsewhere").mkdir()
    with RunFolder(tmp_path / "run", "test") as folder:
        (folder.root / "scene").symlink_to(tmp_path / "elsewhere")
        with pytest.raises(OutputError, match="symbolic link"):
            folder.folder("scene")


def test_a_manifest_cannot_make_symbio_delete_outside_the_folder(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    out = tmp_path / "run"
    out.mkdir()
    (out / MANIFEST_FILE).write_text(json.dumps({"format": "symbio-outputs", "files": ["../victim.txt"]}))
    with RunFolder(out, "test"):
        pass
    assert victim.read_text() == "precious"


def test_a_file_as_out_is_refused(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "a_file"
    target.write_text("x")
    assert replay(small_loop_scene, target) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert target.read_text() == "x"


def _read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write: chmod 555 for a user; a read-only mount for root."""
    if os.geteuid() != 0:
        folder = tmp_path / "read_only"
        folder.mkdir()
        folder.chmod(0o555)
        return folder
    for candidate in (Path("/sys/kernel"), Path("/proc/sys")):
        if candidate.is_dir() and not os.access(candidate, os.W_OK):
            return candidate
        probe = candidate / LOCK_FILE
        try:
            os.close(os.open(probe, os.O_CREAT | os.O_WRONLY, 0o644))
        except OSError:
            return candidate
        probe.unlink()
    pytest.skip("no read-only folder available to root here")


def test_a_read_only_out_gives_one_clear_error(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _read_only_folder(tmp_path)
    assert replay(small_loop_scene, folder) == 2
    error = capsys.readouterr().err
    assert error.startswith("symbio: error: ") and "cannot" in error and "Traceback" not in error
    assert replay(small_loop_scene, folder / "new") == 2
    assert "cannot create the output folder" in capsys.readouterr().err


def test_a_second_run_into_a_locked_folder_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with RunFolder(out, "first"), pytest.raises(OutputError, match="another symbio command"):
        RunFolder(out, "second").claim()
    with RunFolder(out, "third"):  # released when the first one ended
        pass


def test_a_second_process_is_refused_while_the_first_runs_and_admitted_after_kill_9(tmp_path: Path) -> None:
    out = tmp_path / "run"
    script = f"from eval.outputs import RunFolder\nimport time\nfolder = RunFolder({str(out)!r}, 'x')\n"
    script += "folder.claim()\nprint('claimed', flush=True)\ntime.sleep(60)"
    holder = subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "claimed"
        with pytest.raises(OutputError, match=rf"pid {holder.pid}"):
            RunFolder(out, "second").claim()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with RunFolder(out, "after the kill"):  # the kernel dropped the dead process's lock
        pass


def test_kill_9_while_writing_leaves_old_or_new_files_never_half(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with RunFolder(out, "first", names=["big.txt"]) as folder:
        folder.write_text("big.txt", "old\n")
    script = textwrap.dedent(
        f"""
        import os
        from eval.outputs import RunFolder
        folder = RunFolder({str(out)!r}, "second", names=["big.txt"])
        folder.claim()
        with folder.atomic("big.txt") as path:
            with open(path, "w") as handle:
                handle.write("new " * 1000)
                handle.flush()
                print("writing", flush=True)
                os.kill(os.getpid(), 9)
        """
    )
    child = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True)
    assert child.returncode == -9 and "writing" in child.stdout
    # The killed run had claimed the folder, which removed the first run's file; never a half file.
    assert not (out / "big.txt").exists()
    leftovers = [p.name for p in out.iterdir() if p.name.startswith(TEMP_PREFIX)]
    assert leftovers  # the half-written temporary file is left under a temporary name ...
    with RunFolder(out, "third", names=["big.txt"]) as folder:  # ... and cleared by the next claim
        assert not [p for p in out.iterdir() if p.name.startswith(TEMP_PREFIX)]
        folder.write_text("big.txt", "newest\n")
    assert (out / "big.txt").read_text() == "newest\n"


def test_disk_full_while_writing_outputs_is_one_clear_error_and_keeps_the_checkpoint(
    small_loop_scene: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import eval.run

    def no_space(path: Path, *_: Any) -> None:
        path.write_text("half a traject")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(eval.run, "write_poses", no_space)
    out = tmp_path / "run"
    assert replay(small_loop_scene, out, "--checkpoint-every", "10") == 2
    error = capsys.readouterr().err
    assert "No space left on device" in error and "free some space" in error and "Traceback" not in error
    assert not (out / METRICS_FILE).exists()  # no metrics.json claiming a complete run
    assert not (out / TRAJECTORY_FILE).exists()  # and no half file
    monkeypatch.undo()
    assert (out / "checkpoint.json").is_file()  # what was processed is kept: resume writes the outputs
    assert symbio_main(["run", "--resume", str(out), "--no-progress"]) == 0
    assert metrics(out)["complete"] is True and metrics(out)["frames"] == 40


def test_an_interrupted_run_says_it_is_not_complete(
    small_loop_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from slam_backend.slam import Slam

    original = Slam._track
    calls = {"n": 0}

    def interrupt_at_20(*args: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 20:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the signal handler raises here
        return original(*args)

    monkeypatch.setattr(Slam, "_track", interrupt_at_20)
    out = tmp_path / "run"
    assert replay(small_loop_scene, out) == 130
    figures = metrics(out)
    assert figures["interrupted"] is True and figures["complete"] is False
    assert figures["frames"] == 19
    assert (out / LOOPS_FILE).is_file() and (out / REPORT_FILE).is_file()


def test_atomic_write_names_the_file_on_failure(tmp_path: Path) -> None:
    (tmp_path / "folder_here").mkdir()
    with pytest.raises(OutputError, match="folder_here: is a folder"):
        atomic_write_text(tmp_path / "folder_here", "x")
    with pytest.raises(OutputError, match="missing"):
        atomic_write_text(tmp_path / "missing" / "x.txt", "x")
