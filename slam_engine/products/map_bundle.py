"""The map bundle file (``map_bundle.npz``): a :class:`~slam_engine.model.map_bundle.MapBundle` as a
NumPy ``.npz`` archive (a zip of ``.npy`` arrays, compressed; readable with ``numpy.load`` without
pickles) with a JSON header. Layout and version history: ``docs/map-bundle.md``."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from slam_engine.errors import MapBundleError
from slam_engine.model.drive_log import MAX_ANGLE_RAD, MAX_COORDINATE_M, MAX_RANGE_M, MAX_TIME_S, first_beyond
from slam_engine.model.map_bundle import MapBundle, StoredPlaces

MAX_BEAMS = 100_000  # a scan's beams (as a streamed scan message may hold)
# (array, columns or None for all, bound, unit): the bounds of a drive log's values
BOUNDS = (("poses", slice(0, 2), MAX_COORDINATE_M, "m"), ("poses", 2, MAX_ANGLE_RAD, "rad"),
          ("trajectory", slice(0, 2), MAX_COORDINATE_M, "m"), ("trajectory", 2, MAX_ANGLE_RAD, "rad"),
          ("t_s", None, MAX_TIME_S, "s"), ("trajectory_t_s", None, MAX_TIME_S, "s"),
          ("ends_v", None, MAX_RANGE_M, "m"), ("free_from_m", None, MAX_RANGE_M, "m"),
          ("origin_v", None, MAX_RANGE_M, "m"), ("edges_T_i_from_j", slice(0, 2), MAX_COORDINATE_M, "m"),
          ("edges_T_i_from_j", 2, MAX_ANGLE_RAD, "rad"), ("edges_sigmas", None, MAX_COORDINATE_M, "m or rad"))

# an uploaded bundle's arrays, once read: its check holds them whole (a 1.6 GB array took its process to
# 1.58 GB); about 20 million rays, some 200 times the Intel lab's map
MAX_UPLOADED_BUNDLE_BYTES = 256 * 1024**2
BUNDLE_FILE = "map_bundle.npz"
BUNDLE_FORMAT = "lidarmap-map-bundle"
BUNDLE_VERSION = 2  # 2: the place index (optional arrays PLACE_ARRAYS, header "places"); 1 is still read
READ_VERSIONS = (1, 2)
ARRAYS = ("poses", "t_s", "drive", "unverified", "scan_offsets", "ends_v", "is_hit", "free_from_m", "origin_v",
          "edges_ij", "edges_T_i_from_j", "edges_sigmas", "edges_robust", "trajectory_t_s", "trajectory",
          "trajectory_drive")
PLACE_ARRAYS = ("place_centres", "place_bins")  # (P, 2) float64 [m]; (P, rings, ceil(sectors / 8)) uint8: packed bits


def write_bundle(bundle: MapBundle, path: str | Path) -> Path:
    """Write ``bundle`` to ``path`` (a file, or a folder to hold ``map_bundle.npz``); returns the file."""
    path = Path(path)
    if path.is_dir():
        path = path / BUNDLE_FILE
    header = {"format": BUNDLE_FORMAT, "version": BUNDLE_VERSION, "resolution_m": bundle.resolution_m,
              "key_frames": len(bundle), "drives": bundle.drives, "config": bundle.config, "sensors": bundle.sensors}
    arrays = {name: np.asarray(getattr(bundle, name)) for name in ARRAYS}
    if bundle.places is not None:
        bins = np.asarray(bundle.places.bins, bool)
        header["places"] = {"radius_m": bundle.places.radius_m, "spacing_m": bundle.places.spacing_m,
                            "rings": int(bins.shape[1]), "sectors": int(bins.shape[2])}
        arrays["place_centres"] = np.asarray(bundle.places.centres, np.float64)
        arrays["place_bins"] = np.packbits(bins, axis=-1)
    with path.open("wb") as f:
        # numpy's stubs type **kwds like its allow_pickle flag (bool): the arrays are what it takes
        np.savez_compressed(f, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)  # type: ignore[arg-type]
    return path


def read_bundle(path: str | Path) -> MapBundle:
    """The bundle in ``path`` (the file, or a run's output folder holding ``map_bundle.npz``).
    :class:`MapBundleError` names the file and what is wrong: missing, not a bundle, damaged, or of
    another format version."""
    path = Path(path)
    if path.is_dir():
        path = path / BUNDLE_FILE
    if not path.is_file():
        raise MapBundleError(f"{path}: no map bundle here (a mapping run writes {BUNDLE_FILE} into its output "
                             "folder)")
    try:
        with np.load(path, allow_pickle=False) as archive:
            header = json.loads(bytes(archive["header"]).decode())
            _check_header(path, header)
            missing = [name for name in ARRAYS if name not in archive.files]
            if missing:
                raise MapBundleError(f"{path}: map bundle lacks {', '.join(missing)}")
            arrays = {name: archive[name] for name in ARRAYS}
            places = _read_places(path, header, archive)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, UnicodeDecodeError) as error:
        raise MapBundleError(f"{path}: not a readable map bundle ({error})") from None
    bundle = MapBundle(**arrays, resolution_m=float(header["resolution_m"]), config=header.get("config") or {},
                       sensors=header.get("sensors") or {}, places=places)
    _check_shapes(path, bundle)
    return bundle


def check_bundle_size(path: str | Path, max_bytes: int, max_members: int = 64) -> None:
    """Refuse (:class:`MapBundleError`) a bundle file whose arrays would take more than ``max_bytes``
    once read, before any is read: the zip's member count, each member's declared size, and each array
    header's shape against that size (a lying ``.npy`` header must not make the reader allocate more
    than the file holds). For files from outside (uploads)."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
            if len(members) > max_members:
                raise MapBundleError(f"{path}: {len(members)} files in the archive; a map bundle has at most "
                                     f"{len(ARRAYS) + len(PLACE_ARRAYS) + 1}")
            total = sum(m.file_size for m in members)
            if total > max_bytes:
                largest = max(members, key=lambda m: m.file_size)
                raise MapBundleError(f"{path}: the map bundle's arrays take {total} bytes once read "
                                     f"({largest.filename} {largest.file_size}); at most {max_bytes}")
            for member in members:
                with archive.open(member) as stream:
                    version = np.lib.format.read_magic(stream)
                    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                                   else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read_header(stream)
                if dtype.hasobject:
                    raise MapBundleError(f"{path}: {member.filename} holds Python objects; a map bundle "
                                         "holds numbers only")
                if int(np.prod(shape, dtype=np.int64)) * dtype.itemsize > member.file_size:
                    raise MapBundleError(f"{path}: {member.filename} claims shape {shape}, more than its "
                                         f"{member.file_size} bytes")
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise MapBundleError(f"{path}: not a readable map bundle ({error})") from None


def _check_header(path: Path, header: object) -> None:
    if not isinstance(header, dict) or header.get("format") != BUNDLE_FORMAT:
        raise MapBundleError(f"{path}: not a lidarmap map bundle")
    version = header.get("version")
    if isinstance(version, bool) or version not in READ_VERSIONS:
        newer = isinstance(version, int) and version > BUNDLE_VERSION
        raise MapBundleError(f"{path}: map bundle format version {version}; this lidarmap reads versions "
                             f"{', '.join(map(str, READ_VERSIONS))} (written by {'a newer' if newer else 'another'} "
                             "lidarmap)")
    resolution = header.get("resolution_m")
    if isinstance(resolution, bool) or not isinstance(resolution, int | float) or not 0.001 <= resolution <= 10.0:
        raise MapBundleError(f"{path}: map bundle resolution_m {resolution!r} is not a cell size in [0.001, 10] m")
    lidar = (header.get("sensors") or {}).get("lidar") if isinstance(header.get("sensors"), dict) else None
    if lidar is not None:
        beams = lidar.get("num_beams") if isinstance(lidar, dict) else None
        if isinstance(beams, bool) or not isinstance(beams, int) or not 1 <= beams <= MAX_BEAMS:
            raise MapBundleError(f"{path}: map bundle sensors.lidar.num_beams {beams!r} is not a beam count in "
                                 f"[1, {MAX_BEAMS}]")


def _read_places(path: Path, header: dict, archive) -> StoredPlaces | None:
    """The place index a version-2 bundle keeps (None when it keeps none); its header and arrays checked."""
    meta = header.get("places")
    if meta is None:
        return None
    limits = {"radius_m": (0.1, 1000.0), "spacing_m": (0.01, 1000.0), "rings": (1, 1000), "sectors": (8, 10_000)}
    numbers: dict[str, float] = {}
    for key, (lo, hi) in limits.items():
        value = meta.get(key) if isinstance(meta, dict) else None
        if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
            raise MapBundleError(f"{path}: map bundle places.{key} {value!r} is not within [{lo}, {hi}]")
        numbers[key] = value
    missing = [name for name in PLACE_ARRAYS if name not in archive.files]
    if missing:
        raise MapBundleError(f"{path}: map bundle names places but lacks {', '.join(missing)}")
    centres, packed = archive["place_centres"], archive["place_bins"]
    rings, sectors = int(numbers["rings"]), int(numbers["sectors"])
    if (centres.ndim != 2 or centres.shape[1] != 2 or packed.dtype != np.uint8
            or packed.shape != (len(centres), rings, (sectors + 7) // 8)):
        raise MapBundleError(f"{path}: map bundle place arrays of shapes {centres.shape} and {packed.shape} do not "
                             f"hold {rings} x {sectors} bins per place")
    at = first_beyond(np.asarray(centres, np.float64), MAX_COORDINATE_M)
    if at is not None:
        raise MapBundleError(f"{path}: map bundle place_centres holds a value (flat index {at}) that is not a "
                             f"coordinate within {MAX_COORDINATE_M:g} m")
    bins = np.unpackbits(packed, axis=-1, count=sectors).astype(bool)
    return StoredPlaces(np.asarray(centres, np.float64), bins, float(numbers["radius_m"]), float(numbers["spacing_m"]))


def _check_shapes(path: Path, b: MapBundle) -> None:
    """Every array's shape agrees with the key frames' and rays' counts, and the numbers are finite."""
    k = len(b.poses)
    n = len(b.ends_v)
    expected = {"poses": (k, 3), "t_s": (k,), "drive": (k,), "unverified": (k,), "scan_offsets": (k + 1,),
                "ends_v": (n, 2), "is_hit": (n,), "free_from_m": (n,), "origin_v": (2,),
                "edges_ij": (len(b.edges_ij), 2), "edges_T_i_from_j": (len(b.edges_ij), 3),
                "edges_sigmas": (len(b.edges_ij), 3), "edges_robust": (len(b.edges_ij),),
                "trajectory_t_s": (len(b.trajectory),), "trajectory": (len(b.trajectory), 3),
                "trajectory_drive": (len(b.trajectory),)}
    for name, shape in expected.items():
        if getattr(b, name).shape != shape:
            raise MapBundleError(f"{path}: map bundle array {name} has shape {getattr(b, name).shape}, "
                                 f"expected {shape}")
    if k == 0:
        raise MapBundleError(f"{path}: map bundle holds no key frames")
    if b.scan_offsets[0] != 0 or b.scan_offsets[-1] != n or np.any(np.diff(b.scan_offsets) < 0):
        raise MapBundleError(f"{path}: map bundle scan_offsets do not index its {n} rays")
    if len(b.edges_ij) and (b.edges_ij.min() < 0 or b.edges_ij.max() >= k):
        raise MapBundleError(f"{path}: map bundle edges name key frames outside 0..{k - 1}")
    for name in ("poses", "t_s", "ends_v", "free_from_m", "trajectory", "edges_T_i_from_j", "edges_sigmas"):
        if first_beyond(getattr(b, name), np.inf) is not None:
            raise MapBundleError(f"{path}: map bundle array {name} holds values that are not finite")
    # the bounds a drive log's values keep (slam_engine.model.drive_log): beyond them the maths overflows
    for name, columns, limit, unit in BOUNDS:
        values = np.asarray(getattr(b, name))
        values = values if columns is None else values[:, columns]
        bad = first_beyond(values, limit)
        if bad is not None:
            raise MapBundleError(f"{path}: map bundle array {name} holds {values.reshape(-1)[bad]:g}, beyond "
                                 f"+-{limit:g} {unit}")
    if len(b.edges_sigmas) and b.edges_sigmas.min() <= 0:
        raise MapBundleError(f"{path}: map bundle edges_sigmas holds a standard deviation that is not positive")
