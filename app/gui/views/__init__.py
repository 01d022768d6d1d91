"""The app's views, one folder per step of the analyst's work (``calibrate``, ``seed``,
``sequence``, ``evaluate``, ``traffic``).

Each folder holds a *panel* (``panel.py``: the view's widgets in its folder of the control panel;
it owns the viser handles, offers typed properties and registers typed callbacks, and shows text
and tables), a *scene* (``scene.py``: the view's drawing under its scene node, image planes and
overlays given plain arrays), and the *view* itself (``view.py``: reads and changes
:class:`app.gui.state.AppState`, calls ``registration`` through the app's worker and job runner,
and tells the panel and the scene what to show). A view sees the app only as
:class:`app.gui.context.ViewContext`, and views never import each other: what they share lives in
the state.

Shared by the views: :mod:`.base` (the base classes and the playback clock), :mod:`.widgets`
(panels' event helpers), :mod:`.cptable` (the control-point table of the Seed and Sequence
views) and :mod:`.frames` (the result's frames warped into the map, for the Sequence and
Traffic views).
"""
