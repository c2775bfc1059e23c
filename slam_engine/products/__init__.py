"""Map products: files written from a :class:`~slam_engine.model.result.SlamResult` (the engine itself
writes no files; this package is the one place that does) and map tiles rendered on demand.

One module per product: trajectory files, PNG renderings, GeoTIFF, ROS map, tiles, animation,
run report; :func:`write_products` writes them all.

The names below are imported when first read, so importing one small module of the package
(``slam_engine.products.files``, as the service does at start) loads neither PIL nor the writers.
"""

from typing import TYPE_CHECKING

from slam_engine._exports import lazy_exports

if TYPE_CHECKING:
    from slam_engine.products.export import accuracy_figures, georeference_for, write_products
    from slam_engine.products.georeference import GeoOrigin, Georeference, utm_epsg
    from slam_engine.products.geotiff import write_occupancy_geotiff, write_texture_geotiff
    from slam_engine.products.ros_map import write_ros_map
    from slam_engine.products.tiles import TileScheme, WebMercatorScheme, map_image_at_zoom, render_tile
    from slam_engine.products.trajectory_files import read_trajectory, write_trajectory_json, write_trajectory_tum

__all__ = [
    "GeoOrigin",
    "Georeference",
    "TileScheme",
    "WebMercatorScheme",
    "accuracy_figures",
    "georeference_for",
    "map_image_at_zoom",
    "read_trajectory",
    "render_tile",
    "utm_epsg",
    "write_occupancy_geotiff",
    "write_products",
    "write_ros_map",
    "write_texture_geotiff",
    "write_trajectory_json",
    "write_trajectory_tum",
]
__getattr__, __dir__ = lazy_exports({
    **dict.fromkeys(["accuracy_figures", "georeference_for", "write_products"], "slam_engine.products.export"),
    **dict.fromkeys(["GeoOrigin", "Georeference", "utm_epsg"], "slam_engine.products.georeference"),
    **dict.fromkeys(["write_occupancy_geotiff", "write_texture_geotiff"], "slam_engine.products.geotiff"),
    "write_ros_map": "slam_engine.products.ros_map",
    **dict.fromkeys(["TileScheme", "WebMercatorScheme", "map_image_at_zoom", "render_tile"],
                    "slam_engine.products.tiles"),
    **dict.fromkeys(["read_trajectory", "write_trajectory_json", "write_trajectory_tum"],
                    "slam_engine.products.trajectory_files"),
})
