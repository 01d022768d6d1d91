"""The Seed view (seed pairs, the reference frame's coarse and fine fits, match review): ``view.py``
(seeding, fits, drawing requests), ``points.py`` (the reference frame's control points and
their edits), ``panel.py`` (widgets), ``scene.py`` (frame and map side by side, the magnifier)."""
