"""The Calibrate view (Harris γ by eye, from lines along streets, or estimated): ``view.py``
(state and actions), ``panel.py`` (widgets), ``scene.py`` (the corrected frame and its lines)."""
