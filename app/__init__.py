"""aerialreg's front ends: the ``aerialreg`` command line (:mod:`app.cli`) and the viser browser
app (:mod:`app.gui`), apart: the browser app never imports the command line, whose ``app``
subcommand starts it. :mod:`app.progress` (progress bar, sizes) serves both. Thin: everything
computed comes from :mod:`registration`."""
