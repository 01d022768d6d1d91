"""aerialreg's registration library (Loveland & Rosten, "Acquisition and registration of aerial
video imagery of urban traffic").

Pure library: no GUI, no printing. Conventions (fixed, see ``conventions.md`` of the project):

* A point is ``(x, y)`` = (column, row) as float; arrays of points have shape ``(N, 2)``.
* Pixel centres sit at integer coordinates, ``(0, 0)`` is the centre of the top-left pixel.
  Rescaling by ``s`` uses ``x_s = (x + 0.5) * s - 0.5`` (:func:`registration.coords.rescale`).
* Transforms are named target-first: ``base_from_frame`` maps frame pixels to base pixels.
* raw frame = as recorded (lens-distorted); corrected frame = after the Harris correction;
  base = the orthorectified base map, in whose pixels registered output lives.

Stage modules: ``distortion`` (section 3), ``models`` and ``robust`` (geometric models, RANSAC,
REQCON), ``features`` (control points), ``global_registration`` (section 4), ``local`` (section 5),
``evaluation`` (section 6), ``synth`` (ground-truth simulator), ``result`` (result folders),
``warp`` (the one remap primitive), ``config`` (presets), ``georef`` (map coordinates of a
georeferenced base), ``export`` and ``gis_vector`` (GeoTIFF, mosaic, video, QGIS and GeoJSON /
GeoPackage files).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

__all__ = ["load"]

if TYPE_CHECKING:
    from registration.run import RegistrationResult


def load(out_dir) -> RegistrationResult:
    """Open a result folder written by ``aerialreg register`` (see :mod:`registration.run.result`)."""
    from registration.run import load_result

    return load_result(out_dir)
