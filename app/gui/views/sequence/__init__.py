"""The Sequence view (register every frame, review them, export): ``view.py`` (state and
actions), ``frames.py`` (frames warped into the map, tables, per-frame residuals), ``panel.py``
(widgets), ``scene.py`` (the map and the frame over it), ``export.py`` and ``export_panel.py``
(the export's actions and widgets)."""
