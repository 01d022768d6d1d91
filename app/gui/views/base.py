"""Base classes of the views: scene (drawing) and view (state and actions); each view's panel
(widgets) is its own class in its folder (``panel.py``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from app.gui import scene2d
from app.gui.context import Client, ViewContext

GAP_PX = 80
"""Gap in pixels (of the right-hand image) between side-by-side images."""
PLAY_S = 0.2
"""Playback: the next frame every this many seconds (5 frames/s)."""
PLAY_SIDE_FRACTION = 0.5
"""While playing, registered frames are warped into a map preview this fraction of the
scrubbing one's side (``display_max``; Sequence and Traffic views). In Chromium with software
WebGL (`bench app`, 1280x960 frames) the browser drew 3.4-3.9 of the 5 frames/s handed to it at
the scrubbing size, 4.7-5.0 at 0.75 and all 5 at 0.5 (3 runs of 3)."""


class PlayClock:
    """A playback clock polled by a view's ticker thread: ``due(playing, now)`` says whether the
    next frame is due.

    It keeps deadlines (the next one ``period_s`` after the last, not after the moment the tick
    was polled), so polling late does not slow playback below its rate; after a stall of more
    than a period, or while not playing, it starts afresh instead of catching up."""

    def __init__(self, period_s: float = PLAY_S) -> None:
        self.period_s = period_s
        self._next: float | None = None

    def due(self, playing: bool, now: float) -> bool:
        """Whether a frame is due at ``now`` (seconds, a monotonic clock)."""
        if not playing:
            self._next = None
            return False
        if self._next is None:
            self._next = now + self.period_s  # Play shows the next frame one period later
            return False
        if now < self._next:
            return False
        self._next += self.period_s
        if self._next <= now:  # a whole period missed: no burst to catch up
            self._next = now + self.period_s
        return True


class Scene:
    """The drawing of one view: image planes under the view's scene node."""

    def __init__(self, scene, root_name: str) -> None:
        self.scene = scene
        self.root_name = root_name
        self.root = scene.add_frame(root_name, show_axes=False, visible=False)
        self.planes: dict[str, scene2d.ImagePlane] = {}

    def set_visible(self, visible: bool) -> None:
        self.root.visible = visible

    def make_plane(
        self,
        key: str,
        width: int,
        height: int,
        x_offset: float = 0.0,
        y_offset: float = 0.0,
        scale: float = scene2d.WORLD_PER_PX,
    ) -> scene2d.ImagePlane:
        """(Re)create plane ``key`` of ``width x height`` pixels drawn ``scale`` world units per
        pixel, its top-left corner at (``x_offset``, ``y_offset``) world units / WORLD_PER_PX."""
        old = self.planes.pop(key, None)
        if old is not None:
            old.remove_image()
        s0 = scene2d.WORLD_PER_PX
        geom = scene2d.PlaneGeometry(
            width,
            height,
            position=(
                x_offset * s0 + width * scale / 2.0,
                y_offset * s0 + height * scale / 2.0,
                0.0,
            ),
            scale=scale,
        )
        plane = scene2d.ImagePlane(self.scene, f"{self.root_name}/{key}", geom)
        self.planes[key] = plane
        return plane

    def geoms(self, keys=None) -> list[scene2d.PlaneGeometry]:
        return [p.geom for k, p in self.planes.items() if keys is None or k in keys]

    def set_zoom(self, world_per_screen_px: float) -> None:
        """Resize screen-sized markers and dots for the browser's zoom."""
        for plane in self.planes.values():
            plane.set_zoom(world_per_screen_px / plane.geom.scale)

    def plane_at(self, origin, direction) -> tuple[str, np.ndarray] | None:
        """The plane a click ray hits and the pixel, or None."""
        for name, plane in self.planes.items():
            xy = plane.geom.pixel_from_ray(origin, direction)
            if xy is not None and plane.geom.contains(xy):
                return name, xy
        return None


class View:
    """One step of the analyst's work. Subclasses set ``MODE`` and build panel and scene.

    A view sees the app only as a :class:`~app.gui.context.ViewContext` (``self.ctx``); it reads
    and changes ``self.state`` (under its lock), tells its panel and scene what to show, and
    posts everything slower than a frame to the worker or as a job.
    """

    MODE = ""
    CLICKABLE: tuple[str, ...] = ()

    def __init__(self, ctx: ViewContext) -> None:
        self.ctx = ctx
        self.state = ctx.state
        self.scene = self.make_scene(ctx.scene, f"/{self.MODE.lower()}")
        self.folder = ctx.gui.add_folder(self.MODE, visible=False)
        with self.folder:
            self.panel = self.make_panel(ctx.gui)
        self.connect()

    # -- to override
    def make_scene(self, scene, root_name: str) -> Scene:
        return Scene(scene, root_name)

    def make_panel(self, gui):
        raise NotImplementedError

    def connect(self) -> None:
        """Register this view's actions as the panel's callbacks."""

    def on_inputs(self) -> None:
        """Inputs changed: recreate planes for the new sizes, reset widgets."""

    def on_show(self) -> None:
        """The view became visible: (re)draw."""

    def on_state_changed(self) -> None:
        """Shared state changed elsewhere (another view, a job): refresh texts."""

    def on_click(self, plane: str, xy, client: Client) -> None:
        """A click landed on ``plane`` at pixel ``xy`` (that plane's full-resolution pixels)."""

    def shutdown(self) -> None:
        """The app is stopping: end timers and threads of this view."""

    def fit_geoms(self) -> list[scene2d.PlaneGeometry]:
        """What the camera fits when the view is shown (default: every plane)."""
        return self.scene.geoms()

    # -- shared
    def set_visible(self, visible: bool) -> None:
        self.scene.set_visible(visible)
        self.folder.visible = visible

    @property
    def visible(self) -> bool:
        with self.state.lock:
            return self.state.mode == self.MODE

    def notify(self, client: Client, title: str, body: str, color: str = "blue") -> None:
        self.ctx.notify(client, title, body, color=color)

    def submit(self, key: str, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the app's worker (latest request per key wins)."""
        self.ctx.submit(f"{self.MODE}:{key}", fn)
