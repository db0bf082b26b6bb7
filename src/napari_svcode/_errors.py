"""Error notifications that fit a toast: the cause in one short line, the fix in a second.

A message longer than its short cause follows them after a blank line, so napari's
expand arrow on the toast shows it whole; the full message (with the traceback of an
exception) also goes to the ``napari_svcode`` logger.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Sequence
from typing import Any

from napari.utils.notifications import (
    Notification,
    NotificationSeverity,
    notification_manager,
    show_error,
    show_warning,
)

__all__ = ["LOG", "dispatch", "fix_for", "notify_error", "notify_warning", "short_cause",
           "toast_text"]

LOG = logging.getLogger("napari_svcode")
MAX_CAUSE = 90

_PATH = re.compile(r"(?:[A-Za-z]:)?(?:[\\/][^\s\\/:;,'\"()]+)+[\\/]([^\s\\/:;,'\"()]+)")

#: (pattern in the full message, the fix that fits it), first match wins
_FIXES = (
    ("expects raw sensor frames", "choose the raw frame of this system, or set its system "
                                  "in Calibration"),
    ("NaN or Inf", "replace the NaN/Inf pixels (e.g. by 0) and try again"),
    ("trained for system", "choose a model trained for this system"),
    ("bundled", "choose 'model file' and pick a .safetensors model for this system"),
    ("not found", "choose a file that exists"),
    ("safetensors", "choose a .safetensors model written by svcode train"),
    ("not a MultiWienerNet", "choose the model file of the chosen method"),
    ("not a SVFourierNet", "choose the model file of the chosen method"),
    ("precision", "choose precision fp32"),
    ("device", "choose device cpu"),
    ("saturat", "lower the exposure, or check the sensor's bit depth in the system"),
)


def short_cause(problem: object) -> str:
    """The first clause of ``problem``'s message, folders stripped from paths, ≤ 90 chars."""
    text = _PATH.sub(r"\1", " ".join(str(problem).split()))
    first = re.split(r"(?<=[^\d\s])[.;] |\n| → ", text, maxsplit=1)[0].rstrip(".;: ")
    if len(first) > MAX_CAUSE:
        first = first[: MAX_CAUSE - 1].rstrip() + "…"
    return first


def fix_for(problem: object, default: str = "") -> str:
    """The remedy that fits ``problem``'s message, else ``default``."""
    text = str(problem)
    for pattern, fix in _FIXES:
        if pattern.lower() in text.lower():
            return fix
    return default


def _log(level: int, problem: object, fix: str) -> None:
    exc_info = problem if isinstance(problem, BaseException) else None
    LOG.log(level, "%s%s", problem, f"\nWhat to do: {fix}" if fix else "", exc_info=exc_info)


def toast_text(problem: object, fix: str) -> str:
    """The short cause, the fix, and the whole message when the cause cut it short.

    Examples
    --------
    >>> print(toast_text("frame 3 is blank; check the shutter", "look at frame 3"))
    frame 3 is blank
    → look at frame 3
    <BLANKLINE>
    frame 3 is blank; check the shutter
    """
    short = short_cause(problem)
    text = short + (f"\n→ {fix}" if fix else "")
    whole = " ".join(str(problem).split())
    return text if whole.rstrip(".;: ") == short else f"{text}\n\n{whole}"


def notify_error(problem: object, what_to_do: str = "") -> None:
    """Toast ``problem`` (an exception or text) as its short cause and a fitting fix.

    ``what_to_do`` is the fix used when none of the known causes matches; the full text
    goes to the ``napari_svcode`` logger.
    """
    fix = fix_for(problem, what_to_do)
    _log(logging.ERROR, problem, fix)
    show_error(toast_text(problem, fix))


#: a toast's button: its text and what it does (called with the toast)
Action = tuple[str, Callable[[Any], None]]


def notify_warning(problem: str, what_to_do: str, actions: Sequence[Action] = ()) -> None:
    """Toast a warning in two lines (cause, then what to do) and log it; ``actions``
    become buttons on the toast (the fix one click away)."""
    _log(logging.WARNING, problem, what_to_do)
    text = toast_text(problem, what_to_do)
    if actions:
        dispatch(Notification(text, NotificationSeverity.WARNING, actions=tuple(actions)))
    else:
        show_warning(text)


def dispatch(notification: Notification) -> None:
    """Show ``notification`` (napari's notification manager)."""
    notification_manager.dispatch(notification)
