"""The base map's place on the Earth: reading base maps (GeoTIFF, images with world files), map
coordinates in the base's CRS, and GIS exports (GeoTIFF, COG, mosaic, QGIS .points, GeoJSON,
GeoPackage).
"""

from registration.gis.basemap import read_base_map, read_georeference, stretch_to_uint8
from registration.gis.export import (
    COMPRESSIONS,
    FORMATS,
    MAP_FORMATS,
    ExportOptions,
    export_result,
    planned_files,
    resolve_formats,
    write_geotiff,
    write_png_georeferenced,
)
from registration.gis.georef import (
    GeoReference,
    find_world_file,
    parse_crs,
    read_world_file,
    world_file_text,
)
from registration.gis.vector import QGIS_POINTS_HEADER, read_points_file, write_points_file

__all__ = [
    "COMPRESSIONS",
    "ExportOptions",
    "FORMATS",
    "GeoReference",
    "MAP_FORMATS",
    "QGIS_POINTS_HEADER",
    "export_result",
    "find_world_file",
    "parse_crs",
    "planned_files",
    "read_base_map",
    "read_georeference",
    "read_points_file",
    "read_world_file",
    "resolve_formats",
    "stretch_to_uint8",
    "world_file_text",
    "write_geotiff",
    "write_png_georeferenced",
    "write_points_file",
]
