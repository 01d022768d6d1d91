"""The control-point table shared by the Seed view (editable) and the Sequence view (read-only):
``panel.py`` (its widgets) and ``table.py`` (rows, selection, paging, centring, export)."""
