"""What a view may ask of the app: the one contract between the app (:mod:`app.gui.server`) and
its views (:mod:`app.gui.views`).

Views are built with a :class:`ViewContext` and type against it, never against
:class:`app.gui.server.App` (which implements it), so the views do not import the server and the
server is the only module that knows every view. Anything a view needs from the app that is not
here is a change of this contract, made on purpose.

Threads: views' callbacks run on viser's thread pool, their drawing on the app's one worker
(:meth:`ViewContext.submit`, latest request per key wins), long computations as the app's one job
(:meth:`ViewContext.run_job`). Shared state lives in :attr:`ViewContext.state`, guarded by its
lock; nothing that touches the disk or the network is called while that lock is held.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import viser

    from app.gui.assets import EventChannel
    from app.gui.inputs import Inputs
    from app.gui.project import Project
    from app.gui.scene2d import PlaneGeometry
    from app.gui.state import AppState
    from app.gui.worker import Job

Client = Any
"""A browser tab (``viser.ClientHandle``), or None for calls made from Python (tests, the
benchmark, the worker): then feedback goes to every tab."""


class ViewContext(Protocol):
    """The app as a view sees it.

    Attributes:
        state: the one mutable state (:class:`app.gui.state.AppState`) and its lock.
        shown: what each view last handed to viser, by key (tests and the benchmark read it).
        display_max: longest side in pixels of frame images sent to the browser (the base map
            is sent at up to twice that).
        max_download_bytes: files larger than this stay in the project folder, not sent.
    """

    state: AppState
    shown: dict[str, Any]
    display_max: int
    max_download_bytes: int

    @property
    def inputs(self) -> Inputs | None:
        """The opened frames and base map (None before any are open)."""
        ...

    @property
    def project(self) -> Project:
        """The project folder (it changes when other inputs open their own project)."""
        ...

    @property
    def scene(self) -> viser.SceneApi:
        """Where a view builds its scene node (its image planes and overlays)."""
        ...

    @property
    def gui(self) -> viser.GuiApi:
        """Where a view builds its panel (inside its own folder)."""
        ...

    @property
    def events(self) -> EventChannel:
        """Events from the app's scripts in the browser (clickable table rows, the chart)."""
        ...

    def atomic(self) -> AbstractContextManager:
        """Group scene and widget updates so a browser shows them at once."""
        ...

    def gui_for(self, client: Client) -> viser.GuiApi:
        """The widgets of one tab (dialogs go to the tab that asked), or of all for None."""
        ...

    def camera_position(self, client: Client) -> tuple[float, float, float]:
        """World position of a tab's camera (the initial camera for None)."""
        ...

    def submit(self, key: str, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the app's worker; a pending request with the same key is dropped."""
        ...

    def run_job(
        self, name: str, fn: Callable[[Job], None], client: Client = None, *, queue: bool = False
    ) -> bool:
        """Run ``fn(job)`` as the app's one long job (progress and Cancel in the header);
        False (and a notice) when another job runs, unless ``queue``."""
        ...

    def notify(self, client: Client, title: str, body: str, *, color: str = "blue") -> None:
        """A notification to one tab (all for None); red ones are kept as errors."""
        ...

    def record_error(self, message: str) -> None:
        """Log an error and keep it (tests and the benchmark read the last ones)."""
        ...

    def set_status(self, text: str) -> None:
        """The status line at the top of the panel (markdown)."""
        ...

    def save(self, *, soon: bool = False) -> None:
        """Write the session to project.json (``soon``: once for a burst of calls)."""
        ...

    def state_changed(self) -> None:
        """Shared state changed: refresh the header and every view's texts."""
        ...

    def focus(self, geoms: list[PlaneGeometry], client: Client = None) -> None:
        """Point one tab's camera (all for None) at ``geoms``."""
        ...

    def send_download(self, client: Client, name: str, data: bytes) -> None:
        """Send ``data`` as file ``name`` to the tab that asked (all for None)."""
        ...

    def offer_file(self, path: Path, client: Client = None, *, name: str | None = None) -> bool:
        """Send a file the app wrote into the project, unless it is over the download limit
        (then a notice says where it is); True when sent."""
        ...
