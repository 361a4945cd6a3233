"""Work on stored records that must neither hold the serve process nor run for ever: a child process with a
time limit (a re-fit with a slow method or a hostile record is stopped, not waited on).

The child is spawned (not forked: the serve process has threads), gets the function and its arguments by
pickle and sends back the result or the error; at the limit it is killed.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from typing import Any, TypeVar

from trimeter.errors import InputError, TrimeterError

T = TypeVar("T")


def run_with_time_limit(fn: Callable[..., T], args: tuple, time_limit_s: float, what: str) -> T:
    """fn(*args) in a child process; its TrimeterError raised here as it was; InputError naming `what` when it
    takes longer than `time_limit_s` (the child is killed) or fails otherwise."""
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    child = context.Process(target=_child, args=(sender, fn, args), name=f"trimeter-{what}", daemon=True)
    child.start()
    sender.close()
    try:
        if not receiver.poll(time_limit_s):
            raise InputError(f"{what} took longer than {time_limit_s:g} s and was stopped")
        ok, value = receiver.recv()
    except EOFError:
        child.join(5)
        raise InputError(f"{what} ended without an answer (its process exited with {child.exitcode})") from None
    finally:
        if child.is_alive():
            child.kill()
        child.join(5)
        receiver.close()
    if ok:
        return value
    if isinstance(value, TrimeterError):
        raise value
    raise InputError(f"{what} failed: {value}")


def _child(sender: Any, fn: Callable, args: tuple) -> None:
    try:
        result: tuple[bool, object] = (True, fn(*args))
    except TrimeterError as exc:
        result = (False, exc)
    except Exception as exc:  # e.g. scipy's QhullError from a degenerate record: one line, not a traceback
        result = (False, f"{type(exc).__name__}: {exc}")
    try:
        sender.send(result)
    except Exception as exc:  # an answer that does not pickle
        sender.send((False, f"its answer could not be sent back ({type(exc).__name__}: {exc})"))
    finally:
        sender.close()
