"""Map products, read back with the libraries their users use: Pillow, rasterio, PyYAML, numpy (TUM).

The SlamResult is built by hand: a grid with walls at known cells, known trajectories."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from PIL import Image
from pyproj import Geod, Transformer

from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError, TileOutOfRangeError, TrajectoryFormatError
from slam_engine.model.result import MapSnapshot, OccupancyGrid, ScanStats, SlamResult, TextureMap, Trajectory
from slam_engine.products import (
    GeoOrigin,
    Georeference,
    TileScheme,
    WebMercatorScheme,
    map_image_at_zoom,
    read_trajectory,
    render_tile,
    write_occupancy_geotiff,
    write_products,
    write_ros_map,
    write_trajectory_json,
    write_trajectory_tum,
)
from slam_engine.products.files import atomic_path
from slam_engine.products.rendering import UNKNOWN_GRAY, occupancy_gray, occupancy_north_up

RES = 0.1
ORIGIN = (-2.0, -1.5)
H, W = 40, 60  # rows (y), cols (x)
WALL_CELL = (45, 20)  # (ix, iy): inside the vertical wall, world centre (2.55, 0.55)
WALL_XY = (ORIGIN[0] + (WALL_CELL[0] + 0.5) * RES, ORIGIN[1] + (WALL_CELL[1] + 0.5) * RES)
TOP_WALL_IY = 31  # a horizontal wall near the top: north up puts it in the image's upper part
FREE_CELL = (25, 15)
UNKNOWN_CELL = (2, 2)
START_LOG_ODDS = 1.0  # 3 x 3 cells around the start pose: p = 0.731 -> 73 %


def make_grid() -> OccupancyGrid:
    log_odds = np.zeros((H, W))
    log_odds[5:36, 10:48] = -5.0  # free room
    log_odds[5:36, 44:47] = 5.0  # vertical wall, 3 cells thick, x in [2.4, 2.7)
    log_odds[TOP_WALL_IY - 1:TOP_WALL_IY + 2, 10:44] = 5.0  # horizontal wall, y in [1.5, 1.8)
    ix0, iy0 = 20, 15  # cell of the start pose (0, 0)
    log_odds[iy0 - 1:iy0 + 2, ix0 - 1:ix0 + 2] = START_LOG_ODDS
    return OccupancyGrid(log_odds=log_odds, resolution_m=RES, origin_x_m=ORIGIN[0], origin_y_m=ORIGIN[1])


def make_trajectory(n: int = 21, drift: float = 0.0) -> Trajectory:
    t = 100.0 + np.arange(n) * 0.5
    x = np.linspace(0.0, 2.0, n)
    y = drift * np.linspace(0.0, 1.0, n) ** 2
    theta = np.linspace(0.0, 3.1, n) - (np.pi if drift else 0.0) * (np.arange(n) > n // 2)
    return Trajectory(t_s=t, poses=np.column_stack([x, y, theta]))


def make_result(texture: bool = True, snapshots: int = 3) -> SlamResult:
    grid = make_grid()
    traj = make_trajectory()
    stats = ScanStats(t_s=traj.t_s[::2], n_eff=np.linspace(30, 10, 11), resampled=np.arange(11) % 3 == 0,
                      match_score=np.full(11, 0.8), matched=np.arange(11) % 4 != 0, step_time_s=np.full(11, 0.01))
    tex = None
    if texture:
        colors = np.zeros((H, W, 3), dtype=np.uint8)
        colors[..., 0] = 200
        colors[..., 2] = np.arange(W, dtype=np.uint8)[None, :]
        counts = np.zeros((H, W), dtype=np.int32)
        counts[10:30, 15:40] = 3
        tex = TextureMap(colors=colors, counts=counts, resolution_m=RES, origin_x_m=ORIGIN[0], origin_y_m=ORIGIN[1])
    snaps = []
    for k in range(snapshots):
        g = make_grid()
        cols = 12 + 10 * (k + 1)
        snaps.append(MapSnapshot(scan_index=5 * k, t_s=float(traj.t_s[5 * k]),
                                 grid=OccupancyGrid(g.log_odds[:, :cols].copy(), RES, *ORIGIN),
                                 trajectory=Trajectory(traj.t_s[:5 * k + 1], traj.poses[:5 * k + 1])))
    return SlamResult(trajectory=traj, dead_reckoning=make_trajectory(drift=0.8), grid=grid, scan_stats=stats,
                      config=SlamConfig(particles=7), texture=tex, snapshots=snaps, wall_time_s=2.0,
                      peak_memory_bytes=123456, input_summary={"format": "handmade", "streams": {"scans": 21}})


def image_pixel(x_m: float, y_m: float) -> tuple[int, int]:
    """(col, row) of a map point in the north-up images of make_grid()."""
    return int((x_m - ORIGIN[0]) // RES), H - 1 - int((y_m - ORIGIN[1]) // RES)


# --- trajectory files ---------------------------------------------------------------------------

def test_trajectory_json_round_trip_keeps_poses_frame_units_and_config(tmp_path: Path) -> None:
    traj = make_trajectory()
    path = write_trajectory_json(traj, tmp_path / "t.json", frame="map", config={"particles": 7})
    document = json.loads(path.read_text())
    assert document["units"] == {"t_s": "s", "x_m": "m", "y_m": "m", "theta_rad": "rad"}
    assert document["version"] == 2 and document["frame"] == "map" and document["config"] == {"particles": 7}
    assert document["poses"][3] == {"t_s": traj.t_s[3], "x_m": traj.poses[3, 0], "y_m": traj.poses[3, 1],
                                    "theta_rad": traj.poses[3, 2]}  # the API's names
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.poses, traj.poses)
    (tmp_path / "bare.json").write_text(json.dumps(document["poses"]))
    np.testing.assert_array_equal(read_trajectory(tmp_path / "bare.json").poses, traj.poses)


def test_trajectory_json_of_version_1_still_loads(tmp_path: Path) -> None:
    """Files written before version 2 name the pose fields t, x, y, theta: old job folders still load
    (and a file mixing the two spellings pose by pose, field by field, too)."""
    traj = make_trajectory()
    old = [{"t": float(t), "x": float(p[0]), "y": float(p[1]), "theta": float(p[2])}
           for t, p in zip(traj.t_s, traj.poses, strict=True)]
    old[1] = {"t_s": old[1]["t"], "x": old[1]["x"], "y_m": old[1]["y"], "theta": old[1]["theta"]}
    path = tmp_path / "v1.json"
    path.write_text(json.dumps({"format": "lidarmap-trajectory", "version": 1, "frame": "map",
                                "units": {"t": "s", "x": "m", "y": "m", "theta": "rad"}, "config": None,
                                "poses": old}))
    back = read_trajectory(path)
    np.testing.assert_array_equal(back.t_s, traj.t_s)
    np.testing.assert_array_equal(back.poses, traj.poses)


def test_tum_file_is_plain_tum_and_reads_back_to_the_same_poses(tmp_path: Path) -> None:
    traj = make_trajectory(drift=0.5)  # headings up to 3.1 rad and wrapped negatives
    path = write_trajectory_tum(traj, tmp_path / "t.tum")
    table = np.loadtxt(path)  # what evo's TUM reader does: 8 columns, '#' comments
    assert table.shape == (len(traj), 8)
    np.testing.assert_allclose(np.linalg.norm(table[:, 4:], axis=1), 1.0, atol=1e-8)
    np.testing.assert_allclose(table[:, 3], 0.0)
    np.testing.assert_allclose(2 * np.arctan2(table[:, 6], table[:, 7]), traj.poses[:, 2], atol=1e-8)
    back = read_trajectory(path)
    np.testing.assert_allclose(back.t_s, traj.t_s, atol=1e-9)
    np.testing.assert_allclose(back.poses[:, :2], traj.poses[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (back.poses[:, 2] - traj.poses[:, 2]))), 0.0, atol=1e-8)


@pytest.mark.parametrize(("content", "fmt", "where", "expected"), [
    ("1 2 3 0 0 0 0 1\n2 2 3 0 0 0 1\n", "auto", "line 2", "TUM"),
    ("# c\n1 2 3 0 0 0 0 1\n2 a 3 0 0 0 0 1\n", "tum", "line 3", "TUM"),
    ('{"poses": [{"t_s": 1, "x_m": 2, "y_m": 3, "theta_rad": 0}, {"t_s": 2, "x_m": 1}]}', "auto", "poses[1]",
     "t_s"),
    ('{"poses": [1, 2', "json", "line 1", "JSON"),
    ('{"trajectory": []}', "auto", "", "'poses'"),
    ("2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "tum", "pose 1", "backwards"),
])
def test_bad_trajectory_files_say_where_and_which_format_was_expected(
        tmp_path: Path, content: str, fmt: str, where: str, expected: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(TrajectoryFormatError) as info:
        read_trajectory(path, format=fmt)
    message = str(info.value)
    assert str(path) in message and where in message and expected in message


def test_missing_trajectory_file_is_a_format_error_naming_the_file(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryFormatError, match="nope.tum: file not found"):
        read_trajectory(tmp_path / "nope.tum")


# --- write_products: images ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def products(tmp_path_factory) -> dict[str, Path]:
    return write_products(make_result(), tmp_path_factory.mktemp("products"))


def test_write_products_writes_every_product_and_no_temporary_files(products: dict[str, Path]) -> None:
    expected = {"trajectory.json", "trajectory.tum", "dead_reckoning.json", "dead_reckoning.tum", "occupancy.png",
                "occupancy_trajectory.png", "occupancy.tif", "map.pgm", "map.yaml", "texture.png",
                "texture.tif", "animation.gif", "run.json"}
    assert set(products) == expected
    folder = products["run.json"].parent
    assert {p.name for p in folder.iterdir()} == expected
    assert all(products[name] == folder / name for name in expected)
    dr = read_trajectory(products["dead_reckoning.json"])
    np.testing.assert_array_equal(dr.poses, make_trajectory(drift=0.8).poses)


def test_occupancy_png_free_white_occupied_black_unknown_grey_north_up(products: dict[str, Path]) -> None:
    image = np.asarray(Image.open(products["occupancy.png"]))
    assert image.shape == (H, W) and image.dtype == np.uint8
    col, row = image_pixel(*WALL_XY)
    assert (col, row) == (WALL_CELL[0], H - 1 - WALL_CELL[1])
    assert image[row, col] == 2  # p = 0.9933 -> 255 * 0.0067
    assert image[H - 1 - FREE_CELL[1], FREE_CELL[0]] == 253
    assert image[H - 1 - UNKNOWN_CELL[1], UNKNOWN_CELL[0]] == 205
    top_wall_rows = np.flatnonzero(image[:, 20] < 50)
    assert top_wall_rows.tolist() == [H - 1 - TOP_WALL_IY + d for d in (-1, 0, 1)]  # rows 7..9: upper part


def test_trajectory_overlay_draws_slam_red_and_dead_reckoning_blue(products: dict[str, Path]) -> None:
    image = np.asarray(Image.open(products["occupancy_trajectory.png"]).convert("RGB"))
    traj, dr = make_trajectory(), make_trajectory(drift=0.8)
    col, row = image_pixel(*traj.poses[15, :2])
    assert tuple(image[row, col]) == (220, 30, 30)
    col, row = image_pixel(*dr.poses[-1, :2])
    assert tuple(image[row, col]) == (30, 90, 230)


def test_rasters_written_in_bands_are_the_whole_images(tmp_path, monkeypatch) -> None:
    """The trajectories PNG and the GeoTIFF are made a band of rows at a time (memory): with bands
    that do not divide the map, the same pixels as the whole image in memory."""
    from slam_engine.products import geotiff, rendering

    grid, traj, dr = make_grid(), make_trajectory(), make_trajectory(drift=0.8)
    monkeypatch.setattr(rendering, "_BAND_ROWS", 7)
    rendering.write_occupancy_with_trajectories_png(tmp_path / "t.png", grid, traj, dr,
                                                    rendering.occupancy_rasters(grid).gray)
    expected = np.asarray(rendering.occupancy_with_trajectories(grid, traj, dr))
    assert np.array_equal(np.asarray(Image.open(tmp_path / "t.png").convert("RGB")), expected)
    monkeypatch.setattr(geotiff, "ROWS_PER_STRIP", 16)
    geotiff.write_occupancy_geotiff(grid, tmp_path / "o.tif")
    probability, known = occupancy_north_up(grid)
    with rasterio.open(tmp_path / "o.tif") as ds:
        assert np.array_equal(ds.read(1), np.where(known, probability, -1).astype(np.float32))


def test_texture_png_is_north_up_and_transparent_where_unseen(products: dict[str, Path]) -> None:
    image = np.asarray(Image.open(products["texture.png"]))
    assert image.shape == (H, W, 4)
    assert tuple(image[H - 1 - 20, 30]) == (200, 0, 30, 255)
    assert image[H - 1 - 5, 30, 3] == 0


def test_animation_has_one_frame_per_snapshot_plus_the_final_map(products: dict[str, Path]) -> None:
    gif = Image.open(products["animation.gif"])
    assert gif.n_frames == 4
    assert gif.size == (38, 31)  # the final map's known cells: columns 10..47, rows 5..35 of make_grid()
    gif.seek(0)
    first = np.asarray(gif.convert("L"))
    gif.seek(3)
    last = np.asarray(gif.convert("L"))
    col, row = image_pixel(*WALL_XY)
    col, row = col - 10, row - (H - 36)
    assert first[row, col] > 150 and last[row, col] < 50  # the wall appears only once mapped


def test_run_json_has_config_input_timings_and_per_scan_stats(products: dict[str, Path]) -> None:
    run = json.loads(products["run.json"].read_text())
    assert run["config"]["particles"] == 7
    assert run["input"] == {"format": "handmade", "streams": {"scans": 21}}
    assert run["timings"]["scans"] == 21 and run["timings"]["scans_processed"] == 11
    assert run["timings"]["scans_per_s"] == pytest.approx(10.5)
    assert run["memory"]["peak_bytes"] == 123456
    assert run["filter"]["resample_count"] == 4 and run["filter"]["match_rate"] == pytest.approx(8 / 11)
    assert len(run["scan_stats"]["n_eff"]) == 11 and run["scan_stats"]["resampled"][:4] == [True, False, False, True]
    assert run["map"]["occupied_cells"] == int(np.count_nonzero(make_grid().log_odds > math.log(0.65 / 0.35)))
    assert run["accuracy"] is None
    assert run["loop_closing"] is None  # a result without a back end's summary
    assert run["georeference"]["epsg"] is None
    assert "run.json" in run["products"] and "occupancy.tif" in run["products"]


def test_products_without_texture_or_snapshots_skip_those_files(tmp_path: Path) -> None:
    written = write_products(make_result(texture=False, snapshots=0), tmp_path)
    assert not {"texture.png", "texture.tif", "animation.gif"} & set(written)
    assert (tmp_path / "occupancy.tif").exists()


def test_atomic_write_leaves_the_old_file_and_no_temporary_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "occupancy.png"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["occupancy.png"]


# --- GeoTIFF ------------------------------------------------------------------------------------

def rio_info(path: Path) -> dict:
    """``rio info PATH`` (rasterio's command line, GDAL underneath) as a user runs it."""
    rio = Path(sys.executable).with_name("rio")
    done = subprocess.run([str(rio), "info", str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_local_geotiff_places_a_known_wall_at_its_map_coordinate(products: dict[str, Path]) -> None:
    """The local map frame has no transformation to any Earth CRS: no CRS, the transform in metres of
    the map frame, the frame named in the metadata; GDAL's tools read it (``rio info``)."""
    with rasterio.open(products["occupancy.tif"]) as ds:
        assert ds.crs is None and ds.tags()["LIDARMAP_FRAME"] == "lidarmap local map frame"
        assert ds.nodata == -1 and ds.dtypes == ("float32",) and (ds.width, ds.height) == (W, H)
        assert tuple(ds.transform)[:6] == pytest.approx((RES, 0.0, ORIGIN[0], 0.0, -RES, ORIGIN[1] + H * RES))
        band = ds.read(1)
        row, col = ds.index(*WALL_XY)
        assert (col, row) == (WALL_CELL[0], H - 1 - WALL_CELL[1])
        assert band[row, col] == pytest.approx(1 / (1 + math.exp(-5)), abs=1e-6)
        assert band[ds.index(*make_grid().cell_to_world(*UNKNOWN_CELL))] == -1
        assert ds.read_masks(1)[ds.index(*make_grid().cell_to_world(*UNKNOWN_CELL))] == 0
    info = rio_info(products["occupancy.tif"])
    assert info["crs"] is None and "lnglat" not in info and info["nodata"] == -1
    assert info["bounds"] == pytest.approx([ORIGIN[0], ORIGIN[1], ORIGIN[0] + W * RES, ORIGIN[1] + H * RES])
    assert info["transform"][:6] == pytest.approx([RES, 0.0, ORIGIN[0], 0.0, -RES, ORIGIN[1] + H * RES])
    texture = rio_info(products["texture.tif"])
    assert texture["crs"] is None and texture["count"] == 4 and texture["colorinterp"][3] == "alpha"


def test_percent_geotiff_is_int8_with_unknown_minus_one(tmp_path: Path) -> None:
    path = write_occupancy_geotiff(make_grid(), tmp_path / "o.tif", kind="percent")
    with rasterio.open(path) as ds:
        band = ds.read(1)
        assert ds.dtypes == ("int8",) and ds.nodata == -1
        assert band[ds.index(*WALL_XY)] == 99 and band[ds.index(0.05, 0.05)] == 73
        assert band[ds.index(*make_grid().cell_to_world(*FREE_CELL))] == 1
        assert band[ds.index(*make_grid().cell_to_world(*UNKNOWN_CELL))] == -1
    with pytest.raises(ConfigError, match="kind"):
        write_occupancy_geotiff(make_grid(), tmp_path / "x.tif", kind="bytes")


def expected_utm(origin: GeoOrigin, epsg: int, x_m: float, y_m: float) -> tuple[float, float]:
    """UTM of a map point (start pose at the map origin, heading 0) along the geodesic, via pyproj."""
    azimuth = origin.heading_deg - math.degrees(math.atan2(y_m, x_m))
    lon, lat, _ = Geod(ellps="WGS84").fwd(origin.longitude_deg, origin.latitude_deg, azimuth, math.hypot(x_m, y_m))
    return Transformer.from_crs(4326, epsg, always_xy=True).transform(lon, lat)


@pytest.mark.parametrize(("origin", "epsg"), [
    (GeoOrigin(48.137154, 11.576124, 30.0), 32632),  # Munich, heading 30 deg east of north
    (GeoOrigin(-33.8688, 151.2093, 200.0), 32756),  # Sydney
])
def test_utm_geotiff_has_the_zone_and_puts_start_and_wall_at_their_easting_northing(
        tmp_path: Path, origin: GeoOrigin, epsg: int) -> None:
    result = make_result(texture=True, snapshots=0)
    written = write_products(result, tmp_path, geo=origin)
    e0, n0 = Transformer.from_crs(4326, epsg, always_xy=True).transform(origin.longitude_deg, origin.latitude_deg)
    with rasterio.open(written["occupancy.tif"]) as ds:
        assert ds.crs.to_epsg() == epsg
        assert ds.transform.a == pytest.approx(RES) and ds.transform.e == pytest.approx(-RES)
        assert ds.transform.b == 0 and ds.transform.d == 0  # north up
        band = ds.read(1)
        assert band[ds.index(e0, n0)] == pytest.approx(1 / (1 + math.exp(-START_LOG_ODDS)), abs=1e-6)
        assert band[ds.index(*expected_utm(origin, epsg, *WALL_XY))] > 0.99
        assert band[ds.index(*expected_utm(origin, epsg, 1.0, 1.0))] < 0.01  # free room
        corner = ds.index(*expected_utm(origin, epsg, -5.0, -5.0), op=math.floor)
        assert not (0 <= corner[0] < ds.height and 0 <= corner[1] < ds.width) or band[corner] == -1
    with rasterio.open(written["texture.tif"]) as ds:
        assert ds.crs.to_epsg() == epsg and ds.count == 4
        assert ds.read(4)[ds.index(*expected_utm(origin, epsg, 0.5, 0.5))] == 255
    info = rio_info(written["occupancy.tif"])
    assert info["crs"] == f"EPSG:{epsg}"
    assert info["lnglat"] == pytest.approx([origin.longitude_deg, origin.latitude_deg], abs=1e-3)  # near the start
    assert rio_info(written["texture.tif"])["crs"] == f"EPSG:{epsg}"
    run = json.loads(written["run.json"].read_text())
    assert run["georeference"]["epsg"] == epsg


def test_geo_origin_outside_utm_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="latitude 85"):
        GeoOrigin(85.0, 10.0, 0.0)


# --- ROS map --------------------------------------------------------------------------------------

def ros_cell_values(image: np.ndarray, description: dict) -> np.ndarray:
    """What map_server does with the image (trinary / scale): -1 unknown, 0..100 occupancy, row 0 at y min."""
    gray = image[..., 0].astype(float) if image.ndim == 3 else image.astype(float)
    alpha = image[..., 1] if image.ndim == 3 else np.full(gray.shape, 255)
    occ = (255 - gray) / 255.0 if not description["negate"] else gray / 255.0
    occ_th, free_th = description["occupied_thresh"], description["free_thresh"]
    values = np.where(occ > occ_th, 100, np.where(occ < free_th, 0, -1))
    if description["mode"] == "scale":
        between = (occ <= occ_th) & (occ >= free_th) & (alpha == 255)
        values = np.where(between, np.rint(1 + 98 * (occ - free_th) / (occ_th - free_th)), values)
    return np.flipud(values)


def test_ros_map_yaml_origin_and_resolution_put_the_wall_where_it_belongs(products: dict[str, Path]) -> None:
    description = yaml.safe_load(products["map.yaml"].read_text())
    assert description["image"] == "map.pgm" and description["mode"] == "trinary"
    image_path = products["map.yaml"].parent / description["image"]
    assert image_path.read_bytes()[:2] == b"P5"
    image = np.asarray(Image.open(image_path))
    res, (ox, oy, yaw) = description["resolution"], description["origin"]
    assert yaw == 0.0
    col = int((WALL_XY[0] - ox) // res)
    row = image.shape[0] - 1 - int((WALL_XY[1] - oy) // res)
    assert image[row, col] == 0
    cells = ros_cell_values(image, description)  # cells[iy, ix] as map_server builds the grid
    grid = make_grid()
    p = grid.probability()
    expected = np.where(~grid.known(), -1, np.where(p > 0.65, 100, np.where(p < 0.196, 0, -1)))
    np.testing.assert_array_equal(cells, expected)
    assert cells[WALL_CELL[1], WALL_CELL[0]] == 100 and cells[FREE_CELL[1], FREE_CELL[0]] == 0


def test_ros_scale_mode_keeps_the_probability_range_and_unknown(tmp_path: Path) -> None:
    grid = make_grid()
    grid.log_odds[15, 20] = 0.4  # p = 0.599: between the thresholds, scaled
    image_path, yaml_path = write_ros_map(grid, tmp_path, mode="scale")
    description = yaml.safe_load(yaml_path.read_text())
    assert description["mode"] == "scale" and image_path.name == description["image"] == "map.png"
    image = np.asarray(Image.open(image_path))
    assert image.shape == (H, W, 2)
    cells = ros_cell_values(image, description)
    assert cells[15, 20] == round(1 + 98 * (1 / (1 + math.exp(-0.4)) - 0.196) / (0.65 - 0.196)) == 88
    assert cells[UNKNOWN_CELL[1], UNKNOWN_CELL[0]] == -1 and cells[WALL_CELL[1], WALL_CELL[0]] == 100


# --- tiles ----------------------------------------------------------------------------------------

def random_grid(h: int = 300, w: int = 700, seed: int = 3) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    return OccupancyGrid(rng.choice([-5.0, -0.4, 0.0, 0.9, 5.0], size=(h, w)), 0.05, -3.0, -7.0)


def stitch(source, z: int, scheme: TileScheme) -> np.ndarray:
    nx, ny = scheme.tile_counts(z)
    rows = [np.hstack([np.asarray(Image.open(io.BytesIO(render_tile(source, z, x, y)))) for x in range(nx)])
            for y in range(ny)]
    return np.vstack(rows)


def test_tiles_at_native_zoom_stitch_back_to_occupancy_png(tmp_path: Path) -> None:
    grid = random_grid()
    scheme = TileScheme.for_map(grid)
    assert scheme.max_zoom == 2 and scheme.tile_counts(2) == (3, 2) and scheme.tile_counts(0) == (1, 1)
    stitched = stitch(grid, 2, scheme)
    assert stitched.shape == (512, 768, 4)
    png = write_products(SlamResult(make_trajectory(), make_trajectory(), grid, make_result().scan_stats,
                                    SlamConfig()), tmp_path)["occupancy.png"]
    np.testing.assert_array_equal(stitched[:300, :700, 0], np.asarray(Image.open(png)))
    assert (stitched[:300, :700, 3] == 255).all() and (stitched[300:, :, 3] == 0).all()


@pytest.mark.parametrize("z", [0, 1])
def test_zoomed_out_tiles_stitch_to_the_map_at_that_zoom(z: int) -> None:
    grid = random_grid()
    scheme = TileScheme.for_map(grid)
    whole = map_image_at_zoom(grid, z)
    f = scheme.cells_per_pixel(z)
    assert whole.shape == (math.ceil(300 / f), math.ceil(700 / f), 4)
    stitched = stitch(grid, z, scheme)
    np.testing.assert_array_equal(stitched[:whole.shape[0], :whole.shape[1]], whole)


def test_zoom_zero_keeps_a_single_wall_cell_visible() -> None:
    log_odds = np.full((300, 700), -5.0)
    log_odds[123, 456] = 5.0
    grid = OccupancyGrid(log_odds, 0.05, 0.0, 0.0)
    tile = np.asarray(Image.open(io.BytesIO(render_tile(grid, 0, 0, 0))))
    assert tile.shape == (256, 256, 4)
    row, col = (300 - 1 - 123) // 4, 456 // 4  # 4 cells per pixel at z = 0
    assert tile[row, col, 0] == 2 and (np.delete(tile[:75, :175, 0].ravel(), row * 175 + col) == 253).all()


def test_texture_tiles_average_colours_and_leave_unseen_transparent() -> None:
    result = make_result()
    tile = np.asarray(Image.open(io.BytesIO(render_tile(result.texture, 0, 0, 0, layer="texture"))))
    assert tuple(tile[H - 1 - 20, 30]) == (200, 0, 30, 255)
    assert tile[H - 1 - 5, 30, 3] == 0 and tile[0, 100, 3] == 0


@pytest.mark.parametrize(("z", "x", "y"), [(3, 0, 0), (-1, 0, 0), (2, 3, 0), (2, 0, 2), (0, 1, 0), (1, -1, 0)])
def test_tiles_outside_the_pyramid_are_a_clear_error(z: int, x: int, y: int) -> None:
    with pytest.raises(TileOutOfRangeError, match=f"{z}"):
        render_tile(random_grid(), z, x, y)


def test_tile_layer_must_match_the_map_and_cache_returns_the_same_tile() -> None:
    grid = random_grid()
    with pytest.raises(ConfigError, match="layer 'texture'"):
        render_tile(grid, 0, 0, 0, layer="texture")
    first = render_tile(grid, 1, 1, 0, map_version=("job", 1))
    assert render_tile(grid, 1, 1, 0, map_version=("job", 1)) is first
    assert render_tile(grid, 1, 1, 0) == first


def slippy_pixel(lon: float, lat: float, z: int) -> tuple[int, int]:
    """Global pixel of a WGS 84 point in the standard XYZ (OSM) scheme."""
    n = 256 * 2**z
    return (int((lon + 180.0) / 360.0 * n),
            int((1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n))


def test_web_mercator_tiles_put_the_wall_at_its_longitude_latitude() -> None:
    origin = GeoOrigin(48.137154, 11.576124, 30.0)
    grid = make_grid()
    georef = Georeference.utm(origin, np.zeros(3))
    scheme = WebMercatorScheme.for_map(grid, georef)
    assert scheme.max_zoom == 20  # 0.1 m cells at 48 deg N: 0.0998 m pixels at z = 20
    geod = Geod(ellps="WGS84")
    for (x_m, y_m), dark in ((WALL_XY, True), ((1.0, 1.0), False)):
        azimuth = origin.heading_deg - math.degrees(math.atan2(y_m, x_m))
        lon, lat, _ = geod.fwd(origin.longitude_deg, origin.latitude_deg, azimuth, math.hypot(x_m, y_m))
        px, py = slippy_pixel(lon, lat, scheme.max_zoom)
        tile = np.asarray(Image.open(io.BytesIO(render_tile(grid, scheme.max_zoom, px // 256, py // 256,
                                                            scheme="webmercator", georef=georef))))
        assert tile[py % 256, px % 256, 3] == 255
        assert (tile[py % 256, px % 256, 0] < 50) == dark
    x0, x1, y0, y1 = scheme.tile_range(10)
    assert (x0, y0) == (x1, y1)  # the whole 6 x 4 m map in one tile at zoom 10
    assert render_tile(grid, 10, x0, y0, scheme="webmercator", georef=georef)
    with pytest.raises(TileOutOfRangeError):
        render_tile(grid, 10, x0 + 1, y0, scheme="webmercator", georef=georef)
    with pytest.raises(ConfigError, match="geo origin"):
        render_tile(grid, 0, 0, 0, scheme="webmercator")


def test_occupancy_gray_is_the_png_shading() -> None:
    probability, known = occupancy_north_up(make_grid())
    gray = occupancy_gray(probability, known)
    assert gray.min() == 2 and gray.max() == 253 and set(np.unique(gray)) == {2, 69, 205, 253}


def test_run_json_accuracy_from_relations_and_ground_truth(tmp_path: Path) -> None:
    from slam_engine.evaluation.metrics import Relations

    result = make_result(texture=False, snapshots=0)
    traj = result.trajectory
    # Ground truth says pose 0 -> pose 20 is 2.5 m straight ahead; the trajectory has it 2.0 m ahead,
    # and pose 0 -> 10 at its true 1.0 m.
    relations = Relations(t1_s=traj.t_s[[0, 0]], t2_s=traj.t_s[[10, 20]],
                          motion=np.array([[1.0, 0.0, traj.poses[10, 2]], [2.5, 0.0, traj.poses[20, 2]]]))
    shifted = Trajectory(traj.t_s, traj.poses + [1.0, 0.0, 0.0])
    written = write_products(result, tmp_path, relations=relations, ground_truth=shifted)
    accuracy = json.loads(written["run.json"].read_text())["accuracy"]
    assert accuracy["relations"]["all"]["n_relations"] == 2
    assert accuracy["relations"]["all"]["trans_mean_m"] == pytest.approx(0.25)
    assert accuracy["relations"]["all"]["rot_mean_deg"] == pytest.approx(0.0)
    assert accuracy["ate_m"] == pytest.approx(0.0, abs=1e-9)  # a pure shift vanishes after alignment


def test_animation_has_the_final_maps_framing() -> None:
    """A snapshot reaching far past the final map (the filter's own map with 30 m rays) is cut to the
    final map's known cells: every frame is framed as the final map, which fills it, and a wall both
    show is at the same pixel in both."""
    from slam_engine.products.animation import animation_frames, map_extent

    final_log_odds = np.zeros((200, 200), np.float32)
    final_log_odds[50:150, 40:160] = -2.0  # known: x in [2.0, 8.0), y in [2.5, 7.5)
    final_log_odds[100:103, 100:103] = 4.0  # a wall at x = 5.0..5.15, y = 5.0..5.15
    final = OccupancyGrid(final_log_odds, 0.05, 0.0, 0.0)
    assert map_extent(final) == pytest.approx((2.0, 2.5, 8.0, 7.5))
    big = np.full((600, 600), -2.0, np.float32)  # 30 m of rays: x, y in [-10, 20)
    big[300:303, 300:303] = 4.0  # the same wall
    snapshot = MapSnapshot(scan_index=0, t_s=0.0, grid=OccupancyGrid(big, 0.05, -10.0, -10.0),
                           trajectory=Trajectory(np.zeros(2), np.zeros((2, 3))))
    frames = list(animation_frames([snapshot], final, Trajectory(np.zeros(2), np.zeros((2, 3))), max_side_px=400))
    assert [f.size for f in frames] == [(120, 100), (120, 100)]  # 6 m x 5 m at 0.05 m: the final map's cells
    last = np.asarray(frames[1].convert("L"))
    assert (last != UNKNOWN_GRAY).all()  # the final map fills its frame
    wall = (int((5.05 - 2.0) / 0.05), int((7.5 - 5.05) / 0.05))  # (col, row)
    for frame in frames:
        assert np.asarray(frame.convert("L"))[wall[1], wall[0]] < 60
