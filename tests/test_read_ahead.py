"""Frames decoded in a background thread (frontends.datasets.base.ReadAhead): same frames, same
order, the reader's errors where they happened, nothing left running."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest

from frontends.datasets.base import ReadAhead
from frontends.types import Frame


def _frames(count: int, fail_at: int | None = None) -> Iterator[Frame]:
    for i in range(count):
        if i == fail_at:
            raise OSError(f"frame {i}: disk gone")
        yield Frame(index=i, timestamp=float(i), image=np.full((2, 2), i, np.uint8))


def _readers() -> int:
    return sum(t.name == "symbio-read-ahead" for t in threading.enumerate())


def test_frames_come_out_in_order_and_the_thread_ends() -> None:
    reader = ReadAhead(_frames(50), depth=2)
    seen = [frame.index for frame in reader]
    assert seen == list(range(50))
    assert reader.finished and reader.last_index == 49
    reader.close()
    assert _readers() == 0


def test_the_readers_error_comes_out_after_the_frames_before_it() -> None:
    reader = ReadAhead(_frames(10, fail_at=6), depth=3)
    seen = []
    with pytest.raises(OSError, match="frame 6"):
        for frame in reader:
            seen.append(frame.index)
    assert seen == list(range(6))
    assert reader.finished


def test_closing_early_stops_the_reader_and_says_what_was_handed_out() -> None:
    pulled = []

    def source() -> Iterator[Frame]:
        for frame in _frames(1000):
            pulled.append(frame.index)
            yield frame

    reader = ReadAhead(source(), depth=2)
    first = [next(reader).index for _ in range(3)]
    reader.close()
    assert first == [0, 1, 2] and reader.last_index == 2 and not reader.finished
    assert len(pulled) <= 3 + 2 + 1  # handed out + queue + one in the reader's hands
    assert _readers() == 0
    with pytest.raises(StopIteration):
        next(reader)


def test_depth_must_be_positive() -> None:
    with pytest.raises(ValueError):
        ReadAhead(_frames(1), depth=0)
