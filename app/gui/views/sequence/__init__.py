"""The Sequence view (register every frame, review them, export): ``view.py`` (state and
actions), ``panel.py`` (widgets), ``scene.py`` (the map and the frame over it), ``export.py`` and
``export_panel.py`` (the export's actions and widgets); the frames warped into the map, their
tables and residuals are ``app.gui.views.frames``, shared with the Traffic view."""
