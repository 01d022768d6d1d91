"""aerialreg's front ends: the ``aerialreg`` command line (:mod:`app.cli`) and the viser browser
app (:mod:`app.server`). Thin: everything computed comes from :mod:`registration`."""
