"""Errors as the browser shows them: one line, no class names, no command-line flags; a library
error (:mod:`registration.errors`) with what the analyst can do about it in the app's words."""

from __future__ import annotations

import logging
import re

from registration.errors import AerialregError

log = logging.getLogger(__name__)

# What the analyst can do about a library error (registration.errors.REMEDIES), in the app's
# words.
APP_REMEDIES = {
    "another_folder": "open the inputs in another project folder",
    "continue_or_restart": "register all frames to continue it, or start over",
    "restart": "start over: the earlier result is kept beside the new one",
    "wait": "wait for the other process to finish",
    "another_reference_frame": "choose another reference frame",
    "georeference": "open a GeoTIFF, or an image with a world file, as the base map",
    "overwrite": "allow replacing existing files",
    "resume": "register all frames again, which redoes them",
    "click": "",  # the message says to click already; the Seed view is where it is done
}


# A parenthesis or a "; give it with ..." clause that names a command-line option: advice for
# the command line, not for the browser.
_FLAG_ADVICE = re.compile(r"\s*\([^()]*(?<![\w-])--[a-z][^()]*\)|;[^;]*(?<![\w-])--[a-z][^;]*")


def without_cli_advice(text: str) -> str:
    """``text`` without the parts that tell a command-line user which option to pass."""
    return _FLAG_ADVICE.sub("", text).strip()


def browser_message(exc: BaseException) -> str:
    """One line for ``exc`` in the browser. Unusable input (``ValueError``, ``OSError``) says
    what is wrong; anything else is a bug, said as such (the traceback goes to the log).
    Command-line advice (``--force``, ``--base-crs``) is left out."""
    text = str(exc).strip()
    line = without_cli_advice(text.splitlines()[0]) if text else ""
    if isinstance(exc, AerialregError):
        remedy = APP_REMEDIES.get(exc.remedy, "")
        return f"{line}; {remedy}" if remedy else line
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    if isinstance(exc, ValueError) and line:
        return line
    log.error("unexpected error", exc_info=exc)
    return f"unexpected error ({line or 'no message'}); the server's log has the details"


# What changed, in the analyst's words, by the result.json key a resume found different.
CHANGED_SETTING = {
    "gamma": "γ",
    "seed": "the seed points",
    "reference_frame": "the reference frame",
    "config": "the registration settings (preset, transform, stages)",
    "n_frames": "the frames",
    "frame_size": "the frames",
    "base_size": "the base map",
    "base_georef": "the base map's georeference",
}


def result_started_afresh(exc, kept_as: str) -> str:
    """One line for the browser when a run could not continue the project's result
    (``registration.errors.ResumeMismatch`` or a damaged result) and started a new one, the old
    one kept as ``kept_as``."""
    key = getattr(exc, "key", None)
    if key in CHANGED_SETTING:
        what = f"{CHANGED_SETTING[key]} changed since the last result was made"
    elif getattr(exc, "difference", ""):
        what = "the input files changed since the last result was made"
    else:
        what = "the last result could not be continued (it is damaged)"
    return (
        f"{what}; it is kept as {kept_as} (Sequence view, *Earlier results*, restores it) and a "
        "new result is started"
    )
