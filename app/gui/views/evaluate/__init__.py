"""The Evaluate view (ground points marked in several frames, Table 2): ``view.py`` (state and
actions), ``panel.py`` (widgets and the Table 2 window), ``scene.py`` (the frame and the marks)."""
