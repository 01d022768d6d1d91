"""The app's views, one per step of the analyst's work (Calibrate, Seed, Sequence, Evaluate).

Each module holds three classes: a *panel* (the view's widgets in its folder of the control
panel: builds them, shows text and tables, reports nothing but callbacks), a *scene* (the view's
drawing under its scene node: image planes and overlays, given plain arrays), and the *view*
itself (reads and changes :class:`app.gui.state.AppState`, calls ``registration`` through the app's
worker and job runner, and tells the panel and the scene what to show).
"""
