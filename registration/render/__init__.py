"""Registered outputs as images: frames rendered into base-map pixels, the displacement field's
components (paper Fig. 5), overlays (paper Fig. 6), videos, and drawing helpers that return arrays.
"""

from registration.render.figures import field_component_images, overlay
from registration.render.frames import footprint, render_registered, render_to_base
from registration.render.video import write_registered_sequence, write_video

__all__ = [
    "field_component_images",
    "footprint",
    "overlay",
    "render_registered",
    "render_to_base",
    "write_registered_sequence",
    "write_video",
]
