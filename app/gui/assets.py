"""The app's static assets (top-level ``static/``) and the browser-to-Python event channel.

* ``static/camera.js``: left-drag pans, the wheel zooms to the cursor (2D images).
* ``static/app.css``: styles for the control panel (tables that scroll instead of overflowing,
  clickable rows, the step checklist).
* ``static/events.js``: ``window.aerialreg.send(kind, value)`` for clickable table rows, and
  click-to-jump on the per-frame chart.
* ``static/pointer.js``: the pixel and map coordinates under the mouse, from the images the
  app publishes with :func:`publish_planes`.

viser 1.1.1 has no public way to run a script in the client: :func:`install` queues viser's
``RunJavascriptMessage`` (the message viser itself uses to load plotly.js). The message is kept
in viser's persistent buffer, so clients that connect later run it too. The CSS is injected by a
script as a ``<style>`` element. If a viser upgrade breaks these hooks, the app still works:
orbiting comes back, tables lose their styles, and rows and chart points stop being clickable
(the widgets next to them do the same).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

ASSETS = ("camera.js", "app.css", "events.js", "pointer.js")


def static_dir() -> Path:
    """Where the assets are: ``app/static`` in an installed package (pyproject.toml maps the
    repository's ``static/`` there), else the top-level ``static/`` of a source checkout (the
    design card's place for them; also what an editable install finds)."""
    package = Path(__file__).resolve().parents[1]  # app/ (this file is app/gui/assets.py)
    for folder in (package / "static", package.parent / "static"):
        if all((folder / name).is_file() for name in ASSETS):
            return folder
    return package.parent / "static"


STATIC_DIR = static_dir()

CHANNEL_LABEL = "aerialreg events"


def read_asset(name: str) -> str:
    """The text of ``static/<name>``; FileNotFoundError naming the file when missing."""
    path = STATIC_DIR / name
    if not path.is_file():
        raise FileNotFoundError(f"app asset missing: {path}")
    return path.read_text(encoding="utf-8")


def css_loader_js(css: str) -> str:
    """A script that adds ``css`` to the page once (as ``<style id="aerialreg-css">``)."""
    return (
        "(() => { if (document.getElementById('aerialreg-css')) return;"
        " const s = document.createElement('style'); s.id = 'aerialreg-css';"
        f" s.textContent = {json.dumps(css)}; document.head.appendChild(s); }})();"
    )


def run_javascript(server, source: str) -> None:
    """Run ``source`` in every client, now and in clients that connect later (private viser
    message, see the module docstring)."""
    from viser import _messages

    server.gui._websock_interface.queue_message(_messages.RunJavascriptMessage(source=source))


def publish_planes(server, planes: list[dict]) -> None:
    """Tell every client (and later ones) which images the views hold, for the pointer
    readout (``static/pointer.js``): each ``{label, width, height, position, scale}`` and, on a
    georeferenced map, ``affine`` (pixel-corner, GDAL's order), ``unit`` and ``crs``."""
    run_javascript(server, f"window.aerialregPlanes = {json.dumps({'planes': planes})};")


def resend_value(widget) -> None:
    """Send ``widget``'s value to every client, the one whose input set it included (private
    viser message, see the module docstring). viser sends a client's change only to the other
    clients, so a value another tab set a moment earlier, still on its way to this client,
    lands in its box after the client's own input and stays there while the server holds the
    client's value (two tabs typing γ in turn ended showing different values)."""
    from viser import _messages

    impl = widget._impl
    impl.gui_api._websock_interface.queue_message(
        _messages.GuiUpdateMessage(impl.uuid, {"value": impl.value})
    )


class EventChannel:
    """Events from the app's own scripts: ``window.aerialreg.send(kind, value)`` in the browser
    becomes ``handler(value, client)`` for the handler registered under ``kind``.

    The channel is a hidden text widget; the script sets its value to a JSON object
    ``{"kind", "value", "n", "t"}`` (``n``, ``t`` make each event a change). Unknown kinds and
    malformed values are ignored (any client can send anything).
    """

    def __init__(self, gui) -> None:
        self._handlers: dict[str, Callable[[object, object], None]] = {}
        self._lock = threading.Lock()
        self.widget = gui.add_text(CHANNEL_LABEL, "", visible=False)
        self.widget.on_update(self._on_update)

    @property
    def uuid(self) -> str:
        return self.widget._impl.uuid

    def on(self, kind: str, handler: Callable[[object, object], None]) -> None:
        with self._lock:
            self._handlers[kind] = handler

    def dispatch(self, text: str, client=None) -> bool:
        """Run the handler for an event's JSON text; False when it is not a known event."""
        try:
            event = json.loads(text)
            kind, value = event["kind"], event["value"]
        except (ValueError, TypeError, KeyError):
            return False
        with self._lock:
            handler = self._handlers.get(kind) if isinstance(kind, str) else None
        if handler is None:
            return False
        try:
            handler(value, client)
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            # A page can send anything: a malformed value is refused in one log line, without
            # a traceback (it is not the app's error).
            log.warning("event %r refused: %s", kind, str(exc).splitlines()[0] if str(exc) else exc)
            return False
        return True

    def _on_update(self, event) -> None:
        self.dispatch(str(event.target.value), event.client)


def install(server, channel: EventChannel) -> list[str]:
    """Load ``static/`` into every client: camera behaviour, styles, the event channel.

    Returns the assets that could not be read (the app works without them, less comfortably:
    see the module docstring); each is logged."""
    missing = []
    scripts = {
        "camera.js": lambda text: text,
        "app.css": css_loader_js,
        "events.js": lambda text: text.replace("__CHANNEL__", channel.uuid),
        "pointer.js": lambda text: text,
    }
    for name, make in scripts.items():
        try:
            run_javascript(server, make(read_asset(name)))
        except FileNotFoundError as exc:
            log.warning("%s", exc)
            missing.append(name)
    return missing
