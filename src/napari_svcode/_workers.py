"""Worker threads whose failure is one notice.

napari 0.9's task-status handler of an *erring* worker raises a ``TypeError`` of its own,
which shows a second notice with a traceback beside ours. The work therefore never raises
out of a worker here: :func:`returning_failure` and :func:`yielding_failure` hand the
exception back as a :class:`Failed` value, and the widget turns it into one notice.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any

from napari.qt.threading import FunctionWorker, thread_worker

from ._errors import notify_error

__all__ = ["Failed", "function_worker", "returning_failure", "yielding_failure"]


@dataclass(frozen=True)
class Failed:
    """The exception a worker's work raised (with its traceback, for the log)."""

    error: Exception


def returning_failure(work: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``work(*args, **kwargs)``, or :class:`Failed` with the exception it raised.

    Examples
    --------
    >>> returning_failure(divmod, 7, 2)
    (3, 1)
    >>> type(returning_failure(divmod, 7, 0).error).__name__
    'ZeroDivisionError'
    """
    try:
        return work(*args, **kwargs)
    except Exception as err:  # noqa: BLE001 - the thread boundary: shown as one notice
        return Failed(err)


def yielding_failure(
    work: Callable[..., Generator[Any, Any, Any]], *args: Any, **kwargs: Any
) -> Generator[Any, Any, Any]:
    """What ``work(*args, **kwargs)`` yields; if it raises, :class:`Failed` as the last item.

    Closing the generator (a cancel) still stops the work at its current yield.

    Examples
    --------
    >>> def count(n):
    ...     yield from range(n)
    ...     raise RuntimeError("out of range")
    >>> [getattr(item, "error", item) for item in yielding_failure(count, 2)]
    [0, 1, RuntimeError('out of range')]
    """
    try:
        return (yield from work(*args, **kwargs))
    except Exception as err:  # noqa: BLE001 - the thread boundary: shown as one notice
        yield Failed(err)
        return None


def function_worker(
    work: Callable[[], Any], on_result: Callable[[Any], None], fix: str
) -> FunctionWorker:
    """An unstarted worker running ``work()``: ``on_result(value)`` when it returns, one
    error notice (the exception, then ``fix``) when it raises."""

    def deliver(result: Any) -> None:
        if isinstance(result, Failed):
            notify_error(result.error, fix)
        else:
            on_result(result)

    worker = thread_worker(returning_failure, start_thread=False)(work)
    worker.returned.connect(deliver)
    return worker
