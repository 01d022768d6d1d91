"""Errors as the browser shows them: one line, no class names, no command-line flags; a library
error (:mod:`registration.errors`) with what the analyst can do about it in the app's words."""

from __future__ import annotations

import logging

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


def browser_message(exc: BaseException) -> str:
    """One line for ``exc`` in the browser. Unusable input (``ValueError``, ``OSError``) says
    what is wrong; anything else is a bug, said as such (the traceback goes to the log)."""
    text = str(exc).strip()
    line = text.splitlines()[0] if text else ""
    if isinstance(exc, AerialregError):
        remedy = APP_REMEDIES.get(exc.remedy, "")
        return f"{line}; {remedy}" if remedy else line
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    if isinstance(exc, ValueError) and line:
        return line
    log.error("unexpected error", exc_info=exc)
    return f"unexpected error ({line or 'no message'}); the server's log has the details"
