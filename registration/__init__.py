"""aerialreg's registration library (Loveland & Rosten, "Acquisition and registration of aerial
video imagery of urban traffic").

Pure library: no GUI, no printing. Conventions (fixed, see ``conventions.md`` of the project):

* A point is ``(x, y)`` = (column, row) as float; arrays of points have shape ``(N, 2)``.
* Pixel centres sit at integer coordinates, ``(0, 0)`` is the centre of the top-left pixel.
  Rescaling by ``s`` uses ``x_s = (x + 0.5) * s - 0.5`` (:func:`registration.coords.rescale`).
* Transforms are named target-first: ``base_from_frame`` maps frame pixels to base pixels.
* raw frame = as recorded (lens-distorted); corrected frame = after the Harris correction;
  base = the orthorectified base map, in whose pixels registered output lives.

Packages, by the paper's stages and the layers beneath them (each names its part of the paper
and its public API in its ``__init__``; lower layers never import higher ones):

* ``io``: files in and out (images and their limits, frame sources, the atomic writer);
* ``geometry``: the model protocol, projective and polyprojective (eq. 5), RANSAC, REQCON, the
  displacement field and ``warp``, the one remap primitive;
* ``matching``: SIFT, gridded SIFT, template grids by NCC, dense DIS flow;
* ``lens`` (section 3): the Harris model, the camera, γ from straight lines and from motion;
* ``render``: frames in base pixels, the field's components (Fig. 5), overlays (Fig. 6), videos;
* ``global_registration`` (section 4) and ``local`` (section 5): the paper's two stages;
* ``gis``: base maps and their georeference, GIS exports;
* ``synth``: the helicopter simulator with exact truth;
* ``run`` (Fig. 3): presets, the whole sequence, re-anchoring, Dask, the result folder;
* ``evaluation`` (section 6): Table 2, errors against the truth, consistency from the images.

``coords`` (point arrays) and ``mapping`` (the interface a result and the truth share) sit
beside them.
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
