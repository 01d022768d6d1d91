"""aerialreg's browser app (viser): :class:`~app.gui.server.App` (:mod:`app.gui.server`), started
by :func:`serve` (:mod:`app.gui.launch`), one folder per view in :mod:`app.gui.views`.

The app never imports the command line (:mod:`app.cli`); the command line's ``app`` subcommand
starts it through :func:`serve`. ``App`` and ``serve`` are imported on first use, so that a module
of the app (the project folder, the state) can be imported without loading viser.
"""

from __future__ import annotations

__all__ = ["App", "serve"]


def __getattr__(name: str):
    if name == "App":
        from app.gui.server import App

        return App
    if name == "serve":
        from app.gui.launch import serve

        return serve
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
