"""aerialreg's browser app (viser): :class:`~app.gui.server.App` and :func:`serve` in
:mod:`app.gui.server`, one folder per view in :mod:`app.gui.views`.

The app never imports the command line (:mod:`app.cli`); the command line's ``app`` subcommand
starts it through :func:`serve`. ``App`` and ``serve`` are imported on first use, so that a module
of the app (the project folder, the state) can be imported without loading viser.
"""

from __future__ import annotations

__all__ = ["App", "serve"]


def __getattr__(name: str):
    if name in __all__:
        from app.gui import server

        return getattr(server, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
