"""Starting the browser app: check the command line's choices, make the (guarded) viser server,
start :class:`app.gui.server.App` on it, say where it listens, and serve until Ctrl-C."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable
from pathlib import Path

from app.gui import security
from app.gui.project import Project, default_project_dir
from app.gui.server import App


def bound_address(host: str, port: int) -> str:
    """What the server listens on, as printed at start: the address actually bound, and for a
    wildcard bind which URL to open on this machine."""
    if host in ("0.0.0.0", "", "::"):
        shown = "[::]" if host == "::" else "0.0.0.0"
        return (
            f"listening on all interfaces ({shown}:{port}); open http://127.0.0.1:{port} here "
            f"or http://<this machine's address>:{port} from another machine"
        )
    name = f"[{host}]" if ":" in host else host
    return f"serving http://{name}:{port}"


def serve(
    *,
    frames: str | None,
    base: str | None,
    project_dir: str | None,
    host: str = "127.0.0.1",
    port: int = 8080,
    allow_dirs: list[str] | None = None,
    max_upload_mb: float = 500.0,
    ready: Callable[[App], None] | None = None,
    block: bool = True,
) -> App:
    """Start the app; prints the URL on stderr. Blocks until Ctrl-C when ``block``."""
    for name, p in (("--frames", frames), ("--base", base)):
        if p and not any(ch in p for ch in "*?[") and not Path(p).exists():
            raise FileNotFoundError(f"{name} not found: {p}")
    if (frames is None) != (base is None):
        raise ValueError("--frames and --base go together (or give neither for the built-in demo)")
    for p in allow_dirs or []:
        if not Path(p).is_dir():
            raise FileNotFoundError(f"--allow-dir is not a folder: {p}")
    folder = Path(project_dir) if project_dir else default_project_dir(frames, base)
    project = Project(folder)
    # The current folder is not allowed implicitly: the browser may open only what was named.
    allowed = []
    for p in (frames, base):
        if p:
            allowed.append(Path(p).expanduser().resolve().parent)
    allowed += [Path(p) for p in allow_dirs or []]
    # viser prints its own banner on stdout; keep stdout for machine-readable output.
    with contextlib.redirect_stdout(sys.stderr):
        server = security.make_server(host=host, port=port, verbose=False)
    app = App(
        server,
        project,
        frames=frames,
        base=base,
        allowed_dirs=allowed,
        max_upload_mb=max_upload_mb,
        project_is_explicit=project_dir is not None,
        auto_gamma=True,
    )
    try:
        app.start()
    except BaseException:
        app.stop()
        raise
    sys.stderr.write(
        f"aerialreg app: {bound_address(host, server.get_port())}  (project {project.folder})\n"
    )
    sys.stderr.flush()
    if ready is not None:
        ready(app)
    if block:
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
        finally:
            app.stop()
    return app
