"""trimeter.web.isolated: work in a child process with a time limit."""

from __future__ import annotations

import time

import pytest

from trimeter.errors import InputError, MapFileError
from trimeter.web.isolated import run_with_time_limit


def test_the_answer_and_the_errors_come_back():
    assert run_with_time_limit(divmod, (7, 2), 60, "a division") == (3, 1)
    with pytest.raises(InputError, match="a division failed: ZeroDivisionError"):
        run_with_time_limit(divmod, (1, 0), 60, "a division")
    with pytest.raises(MapFileError, match="bad map"):
        run_with_time_limit(_raise_map_error, (), 60, "a load")


def test_work_past_its_limit_is_stopped():
    started = time.monotonic()
    with pytest.raises(InputError, match="a nap took longer than 0.5 s and was stopped"):
        run_with_time_limit(time.sleep, (60,), 0.5, "a nap")
    assert time.monotonic() - started < 15


def _raise_map_error() -> None:
    raise MapFileError("bad map")
