"""How panels turn viser widget events into the typed callbacks views register.

A panel owns its viser handles; a view only calls the panel's typed properties and registers
callbacks such as ``panel.on_gamma_changed(callback)``. These helpers are the one place where an
event's raw ``target.value`` is read and converted, and where a button group's labels are mapped
to the actions they stand for, so no view ever compares label text.

Every callback gets the browser tab that caused it as its last argument (``None`` when Python
set the widget): views use it to address notifications and camera moves.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from app.gui.context import Client

T = TypeVar("T")

ClientCallback = Callable[[Client], None]


def on_change(handle, convert: Callable[[Any], T], callback: Callable[[T, Client], None]) -> None:
    """``callback(convert(value), client)`` whenever ``handle``'s value changes (in the browser,
    or assigned from Python: viser then runs it at once, in the assigning thread)."""
    handle.on_update(lambda event: callback(convert(event.target.value), event.client))


def on_press(handle, callback: ClientCallback) -> None:
    """``callback(client)`` when the button ``handle`` is pressed."""
    handle.on_click(lambda event: callback(event.client))


def on_choice(group, actions: Mapping[str, Callable[[Client], None]]) -> None:
    """A button group whose buttons each run their own action (``label -> action(client)``).

    Labels not in ``actions`` (none, unless the group's options change) do nothing."""

    def dispatch(event) -> None:
        action = actions.get(event.target.value)
        if action is not None:
            action(event.client)

    group.on_click(dispatch)


def on_any_change(handles, callback: ClientCallback) -> None:
    """``callback(client)`` when any of ``handles`` changes (display options read together)."""
    for handle in handles:
        handle.on_update(lambda event: callback(event.client))


def on_upload(button, default_name: str, callback: Callable[[str, bytes, Client], None]) -> None:
    """``callback(file name, content, client)`` when a file is uploaded with the upload button
    ``button`` (``default_name`` when the browser sends none)."""

    def uploaded(event) -> None:
        value = event.target.value
        name = str(getattr(value, "name", "") or default_name)
        callback(name, getattr(value, "content", b"") or b"", event.client)

    button.on_upload(uploaded)
