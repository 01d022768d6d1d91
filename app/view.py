"""Base class of the app's views: a GUI folder, a scene node holding image planes, click routing."""

from __future__ import annotations

from typing import TYPE_CHECKING

from app import scene2d

if TYPE_CHECKING:
    from app.server import App

GAP_PX = 80
"""Gap in pixels between side-by-side images (frame | base)."""


class View:
    """One step of the analyst's work. Subclasses set MODE and build their GUI in :meth:`build`."""

    MODE = ""

    def __init__(self, app: App) -> None:
        self.app = app
        self.state = app.state
        self.scene = app.server.scene
        self.gui = app.server.gui
        self.root_name = f"/{self.MODE.lower()}"
        self.root = self.scene.add_frame(self.root_name, show_axes=False, visible=False)
        self.image_planes: dict[str, scene2d.ImagePlane] = {}
        self.folder = self.gui.add_folder(self.MODE, visible=False)
        with self.folder:
            self.build()

    # -- to override
    def build(self) -> None:
        """Create GUI handles (inside this view's folder)."""

    def on_inputs(self) -> None:
        """Inputs changed: recreate planes for the new sizes."""

    def on_show(self) -> None:
        """The view became visible: (re)draw."""

    def on_click(self, plane: str, xy, client) -> None:
        """A click landed on ``plane`` at pixel ``xy`` (that plane's full-resolution pixels)."""

    def shutdown(self) -> None:
        """The app is stopping: end timers and threads of this view."""

    # -- shared
    def set_visible(self, visible: bool) -> None:
        self.root.visible = visible
        self.folder.visible = visible

    def planes(self) -> list[scene2d.PlaneGeometry]:
        return [p.geom for p in self.image_planes.values()]

    def clickable(self) -> dict[str, scene2d.PlaneGeometry]:
        return {name: p.geom for name, p in self.image_planes.items()}

    def make_plane(
        self, key: str, width: int, height: int, x_offset: float = 0.0
    ) -> scene2d.ImagePlane:
        """(Re)create the image plane ``key`` of ``width x height`` pixels, left edge at x_offset px."""
        old = self.image_planes.pop(key, None)
        if old is not None:
            old.clear_overlays()
            if old.handle is not None:
                old.handle.remove()
        s = scene2d.WORLD_PER_PX
        geom = scene2d.PlaneGeometry(
            width, height, position=((x_offset + width / 2.0) * s, (height / 2.0) * s, 0.0)
        )
        plane = scene2d.ImagePlane(self.scene, f"{self.root_name}/{key}", geom)
        self.image_planes[key] = plane
        return plane

    def notify(self, client, title: str, body: str, color: str = "blue") -> None:
        self.app.notify(client, title, body, color=color)
