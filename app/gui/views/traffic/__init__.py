"""The Traffic view (vehicles tracked on the registered video, the paper's purpose):
``view.py`` (state and actions), ``panel.py`` (widgets and the speed chart), ``scene.py`` (the
map, the tracks coloured by speed and the vehicles of the frame shown)."""
