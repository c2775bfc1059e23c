// One job's map: occupancy and texture tiles on a metric L.CRS.Simple, the SLAM and dead-reckoning
// trajectories as polylines, a colour key, a scale bar in metres and the cursor's map coordinates.

import * as L from "../vendor/leaflet/leaflet-src.esm.js";
import { getBlob, getJson } from "./api.js";
import { el } from "./format.js";

// Tile scheme, as slam_engine.products.tiles.TileScheme defines it and GET /v1/jobs/{id}/tiles/{layer}
// describes it: zoom `native_zoom` shows one tile pixel per grid cell, each zoom below halves the
// resolution, zoom 0 is the whole map in one 256 px tile; tile (x, y) counts right and down from the
// map's top-left corner. `leaflet_transformation` (a, b, c, d) on L.CRS.Simple makes LatLng = [y_m, x_m]
// in the map frame, so Leaflet distances are metres. The texture map lies on the occupancy grid's
// geometry (slam_engine.result.TextureMap), so both layers share one CRS.
export const TILE_SCHEME = Object.freeze({
  path: (jobId, layer) => `/v1/jobs/${jobId}/tiles/${layer}`,
  tileUrl: (jobId, layer) => `/v1/jobs/${jobId}/tiles/${layer}/{z}/{x}/{y}.png?v={version}`,
  zoomPastNative: 3, // zoom in this far past one pixel per cell (pixels enlarged)
  zoomOutPastWhole: 2, // and out this far past the whole map in one tile
});

const VIEW_MARGIN_M = 2; // first view: the trajectory and at least this much around it [m]
const VIEW_MARGIN_FRACTION = 0.08; // ... or this fraction of its larger side

const LAYER_NAMES = Object.freeze({
  occupancy: "Occupancy grid",
  texture: "Ground texture",
  trajectory: "Trajectory (SLAM)",
  deadReckoning: "Dead reckoning",
  savedDrives: "Saved map's drives",
  closures: "Loop closures",
  changes: "Changes since the saved map",
});
// thin and half transparent: the corridors and walls under the path stay visible
const TRAJECTORY_STYLE = { color: "#e8590c", weight: 1.5, opacity: 0.6, className: "trajectory-slam" };
const DEAD_RECKONING_STYLE = { color: "#1c7ed6", weight: 1.5, opacity: 0.55, dashArray: "6 5",
  className: "trajectory-dead-reckoning" };
// an accepted loop closure: a line between the two key frames it tied together (run.json)
const CLOSURE_STYLE = { color: "#9c36b5", weight: 1.5, opacity: 0.8, className: "loop-closure" };
// an extension's saved-map drives, under the new drive's trajectory (TRAJECTORY_STYLE)
const SAVED_DRIVES_STYLE = { color: "#2f9e44", weight: 2.5, opacity: 0.9, className: "trajectory-saved" };
// what a localised or extending drive saw changed since the saved map (changes.geojson), as changes.png
// colours it: added red, removed blue
const CHANGE_STYLES = Object.freeze({
  added: { color: "#e03131", weight: 1, opacity: 1, fillOpacity: 0.7, className: "change-added" },
  removed: { color: "#1c7ed6", weight: 1, opacity: 1, fillOpacity: 0.7, className: "change-removed" },
});
const POSE_STYLE = { radius: 5, color: "#fff", weight: 2, fillColor: "#e8590c", fillOpacity: 1,
  className: "trajectory-pose" };

function crsFor(scheme) {
  const [a, b, c, d] = scheme.leaflet_transformation;
  return L.extend({}, L.CRS.Simple, { transformation: new L.Transformation(a, b, c, d) });
}

/** The map's extent as LatLng bounds ([y_m, x_m] corners). */
function boundsOf(scheme) {
  const [left, top] = scheme.top_left_m;
  const right = left + scheme.width_cells * scheme.resolution_m;
  const bottom = top - scheme.height_cells * scheme.resolution_m;
  return L.latLngBounds([bottom, left], [top, right]);
}

/**
 * What to show first: the trajectory with room around it (the grid also holds every long beam's free
 * ray, often far beyond the walls), or the whole map when the trajectory is not known yet.
 */
function initialView(mapBounds, trajectory) {
  if (!trajectory || !trajectory.length) return mapBounds;
  const path = L.latLngBounds(trajectory);
  const margin = Math.max(VIEW_MARGIN_M, VIEW_MARGIN_FRACTION * Math.max(
    path.getNorth() - path.getSouth(), path.getEast() - path.getWest()));
  const view = L.latLngBounds([path.getSouth() - margin, path.getWest() - margin],
    [path.getNorth() + margin, path.getEast() + margin]);
  return mapBounds.intersects(view) ? view : mapBounds;
}

function sameGeometry(a, b) {
  return !!a && !!b && a.native_zoom === b.native_zoom && a.width_cells === b.width_cells
    && a.height_cells === b.height_cells && a.resolution_m === b.resolution_m
    && a.top_left_m[0] === b.top_left_m[0] && a.top_left_m[1] === b.top_left_m[1];
}

/** Tiles fetched with the API key (an <img> cannot send headers) and refreshed in place while a job runs. */
const FetchTileLayer = L.TileLayer.extend({
  createTile(coords, done) {
    const tile = document.createElement("img");
    tile.alt = "";
    tile.setAttribute("role", "presentation");
    this._fetchInto(tile, this.getTileUrl(coords), done);
    return tile;
  },

  _fetchInto(tile, url, done) {
    tile.dataset.url = url;
    getBlob(url).then((blob) => {
      const objectUrl = URL.createObjectURL(blob);
      tile.onload = () => {
        URL.revokeObjectURL(objectUrl);
        if (done) done(null, tile);
      };
      tile.onerror = () => {
        URL.revokeObjectURL(objectUrl);
        if (done) done(new Error(`tile ${url} is not an image`), tile);
      };
      tile.src = objectUrl;
    }, (error) => {
      if (done) done(error, tile);
    });
  },

  /** Fetch the visible tiles again for map ``version`` and swap each in when it arrives (no blank flash). */
  refreshTiles(version) {
    this.options.version = version;
    for (const { el, coords } of Object.values(this._tiles)) {
      if (coords.z === this._tileZoom) this._fetchInto(el, this.getTileUrl(coords), null);
    }
  },
});

/** Bottom-right readout of the cursor's map-frame coordinates [m]. */
const CursorPosition = L.Control.extend({
  options: { position: "bottomright" },
  onAdd(map) {
    const div = L.DomUtil.create("div", "cursor-position");
    div.textContent = "x —  y —";
    map.on("mousemove", (event) => {
      div.textContent = `x ${event.latlng.lng.toFixed(2)} m   y ${event.latlng.lat.toFixed(2)} m`;
    });
    map.on("mouseout", () => { div.textContent = "x —  y —"; });
    return div;
  },
});

/** Colour key: what the map's greys and the lines mean (the dead-reckoning and saved-drive lines only when
 * they are shown). */
const ColourKey = L.Control.extend({
  options: { position: "bottomright" },
  onAdd() {
    this.div = L.DomUtil.create("div", "map-key");
    this.closures = 0;
    this.changes = null;
    this.live = null;
    this.savedDrivesShown = false;
    this.setDeadReckoning(false);
    return this.div;
  },
  setSavedDrives(shown) {
    this.savedDrivesShown = shown;
    this._render();
  },
  setDeadReckoning(shown) {
    this.deadReckoningShown = shown;
    this._render();
  },
  setClosures(count) {
    this.closures = count;
    this._render();
  },
  /** A live localisation's last report (its state and confidence in the key), or null. */
  setLive(report) {
    this.live = report;
    this._render();
  },
  /** Regions added and removed since the saved map ({added, removed} counts), or null: no change map. */
  setChanges(counts) {
    this.changes = counts;
    this._render();
  },
  _render() {
    const shown = this.deadReckoningShown;
    const swatch = (colour, label) => el("div", { class: "map-key-row" },
      el("span", { class: "map-key-swatch", style: `background: ${colour}` }), label);
    const line = (style, label, className) => el("div", { class: `map-key-row ${className}` },
      el("span", { class: "map-legend-line", style: `border-top: 2px ${style.dashArray ? "dashed" : "solid"} `
        + `${style.color}` }), label);
    this.div.replaceChildren(...[
      swatch("#000", "occupied"), swatch("#fff", "free"), swatch("rgb(205, 205, 205)", "unknown"),
      line(TRAJECTORY_STYLE, LAYER_NAMES.trajectory, "key-trajectory"),
      this.savedDrivesShown ? line(SAVED_DRIVES_STYLE, LAYER_NAMES.savedDrives, "key-saved-drives") : null,
      shown ? line(DEAD_RECKONING_STYLE, LAYER_NAMES.deadReckoning, "key-dead-reckoning") : null,
      this.closures ? line(CLOSURE_STYLE, `${LAYER_NAMES.closures} (${this.closures})`, "key-closures") : null,
      this.live ? el("div", { class: "map-key-row key-live" }, `robot: ${this.live.state}`
        + (this.live.state === "found" ? ` (confidence ${this.live.confidence.toFixed(2)})` : "")
        + ` at scan ${this.live.scan}`) : null,
      ...(this.changes ? [
        el("div", { class: "map-key-row key-changes-added" }, el("span", { class: "map-key-swatch",
          style: `background: ${CHANGE_STYLES.added.color}` }), `added since the saved map (${this.changes.added})`),
        el("div", { class: "map-key-row key-changes-removed" }, el("span", { class: "map-key-swatch",
          style: `background: ${CHANGE_STYLES.removed.color}` }), `removed since (${this.changes.removed})`),
      ] : [])].filter(Boolean));
  },
});

async function posesOf(path, keep = () => true) {
  try {
    const trajectory = await getJson(path);
    return trajectory.poses.filter((pose) => keep(pose.t_s)).map((pose) => [pose.y_m, pose.x_m]);
  } catch (error) {
    if (error.status === 404 || error.status === 409) return null; // not (yet) available
    throw error;
  }
}

/** A finished job's accepted loop closures as [[y, x] anchor, [y, x] node] pairs (null: none recorded). */
async function closuresOf(jobId) {
  const run = await getJson(`/v1/jobs/${jobId}/run`).catch(() => null);
  const closures = run && run.loop_closing && run.loop_closing.closures;
  if (!closures) return null;
  return closures.filter((c) => c.accepted && c.node_xy_m && c.anchor_xy_m)
    .map((c) => [[c.anchor_xy_m[1], c.anchor_xy_m[0]], [c.node_xy_m[1], c.node_xy_m[0]]]);
}

/** A job's changed regions as {kind, rings: [[[y, x], ...], ...]} in the map frame (null: no change map). */
async function changesOf(jobId) {
  const doc = await getJson(`/v1/jobs/${jobId}/changes.geojson`).catch(() => null);
  if (!doc) return null;
  return doc.features.map((feature) => {
    // on Earth the geometry is WGS 84 and the map frame's polygon rides along in the properties
    const geometry = feature.properties.map_frame_geometry || feature.geometry;
    return { kind: feature.properties.kind, rings: geometry.coordinates.map((ring) => ring.map(([x, y]) => [y, x])) };
  });
}

function hasTexture(job) {
  return job.products.some((name) => name === "texture.png" || name === "tiles/texture");
}

export class JobMap {
  constructor(container, placeholder) {
    this.container = container;
    this.placeholder = placeholder;
    this.map = null;
    this.jobId = null;
    this.scheme = null;
    this.layers = {};
    this.hidden = new Set(); // layer names the user switched off, kept across rebuilds
    this.version = null;
    this.running = null;
    this.queued = null;
    this.onError = () => {};
    // the pane changes size when the job header grows (its summary): Leaflet must know, or the view shifts
    new ResizeObserver(() => this.map && this.map.invalidateSize({ animate: false })).observe(container);
  }

  /** Show ``job`` (null: nothing) or bring the shown job's map up to date; calls are coalesced. */
  async show(job) {
    if (!job) {
      this._clear("Select a job, or upload a drive log to make a map.");
      this.jobId = null;
      return;
    }
    if (job.id !== this.jobId) {
      this._clear("Loading the map…");
      this.jobId = job.id;
    }
    this.queued = job;
    if (this.running) return this.running;
    this.running = (async () => {
      while (this.queued) {
        const next = this.queued;
        this.queued = null;
        try {
          await this._update(next);
        } catch (error) {
          this.onError(error);
        }
      }
      this.running = null;
    })();
    return this.running;
  }

  async _update(job) {
    const version = `${job.status}-${job.scans_done}`;
    if (job.id !== this.jobId || (this.map && version === this.version)) return;
    if (job.live && job.mode === "localize" && job.map_job_id && job.status === "running") {
      return this._updateLive(job, version);
    }
    if (job.status === "succeeded" && job.products.includes("localization.png")) {
      return this._showImages(job, [
        ["localization.png", "The drive (red where its scans matched the saved map, blue where its own motion "
          + "carried it) over the saved map"],
        ...(job.products.includes("changes.png") ? [["changes.png", "What changed since the saved map: red "
          + "where the drive saw something the map held free (added), blue where it saw through something the "
          + "map held (removed)"]] : [])]);
    }
    const hasTiles = job.status === "succeeded" || job.products.includes("tiles/occupancy");
    if (!this.map) this._setPlaceholder(hasTiles ? "Loading the map…" : this._waitingText(job));
    if (!hasTiles) return;
    let scheme;
    try {
      scheme = await getJson(TILE_SCHEME.path(job.id, "occupancy"));
    } catch (error) {
      if (error.status !== 404 && error.status !== 409) throw error;
      if (!this.map) this._setPlaceholder(this._waitingText(job));
      return;
    }
    const textureScheme = hasTexture(job)
      ? await getJson(TILE_SCHEME.path(job.id, "texture")).catch(() => null) : null;
    // Trajectories while a job runs only when the service lists them among the products available now.
    const listed = (name) => job.status === "succeeded" || job.products.includes(name);
    // An extension: the saved map's drives and the new drive (its log's time span) in two colours.
    const span = job.mode === "extend" && job.input && job.input.summary && job.input.summary.time_span_s;
    const isNew = (t) => !!span && t >= span[0] && t <= span[1];
    const [trajectory, deadReckoning, savedDrives, closures, changes] = await Promise.all([
      listed("trajectory.json") ? posesOf(`/v1/jobs/${job.id}/trajectory`, (t) => !span || isNew(t)) : null,
      listed("dead_reckoning.json") ? posesOf(`/v1/jobs/${job.id}/dead-reckoning`) : null,
      span && listed("trajectory.json") ? posesOf(`/v1/jobs/${job.id}/trajectory`, (t) => !isNew(t)) : null,
      job.status === "succeeded" && job.products.includes("run.json") ? closuresOf(job.id) : null,
      job.status === "succeeded" && job.products.includes("changes.geojson") ? changesOf(job.id) : null]);
    if (job.id !== this.jobId) return; // another job was selected meanwhile
    if (!this.map || !sameGeometry(this.scheme, scheme) || !!textureScheme !== !!this.layers.texture) {
      this._build(job.id, scheme, !!textureScheme, version, trajectory);
    } else {
      this.layers.occupancy.refreshTiles(version);
      if (this.layers.texture) this.layers.texture.refreshTiles(version);
    }
    this._setPaths(trajectory, deadReckoning, savedDrives);
    this._setClosures(closures);
    this._setChanges(changes);
    this.version = version;
  }

  /** A live localisation while it runs: the saved map's tiles, the path of the scans found in it, the
   * robot where its last scan was placed, and the state in the key (GET /v1/jobs/{id}/poses, new scans). */
  async _updateLive(job, version) {
    if (!this.map || this.liveOf !== job.id) {
      const scheme = await getJson(TILE_SCHEME.path(job.map_job_id, "occupancy"));
      if (job.id !== this.jobId) return;
      this._build(job.map_job_id, scheme, false, version, null);
      this.liveOf = job.id;
      this.livePath = [];
      this.liveAfter = -1;
    }
    const answer = await getJson(`/v1/jobs/${job.id}/poses?after=${this.liveAfter}`);
    if (job.id !== this.jobId || this.liveOf !== job.id) return;
    let last = null;
    for (const report of answer.poses) {
      this.liveAfter = report.scan;
      if (report.pose && report.state === "found") this.livePath.push([report.pose[1], report.pose[0]]);
      last = report;
    }
    this._setPaths(this.livePath, null, null);
    if (last) {
      if (last.pose) this.layers.pose.setLatLng([last.pose[1], last.pose[0]]);
      this.colourKey.setLive(last);
    }
    this.version = version;
  }

  /** A job whose products are pictures, not a map (a localisation): each [product, caption] in the map pane. */
  async _showImages(job, pictures) {
    if (this.map) this._clear(null);
    const key = `${job.id}:${pictures.map(([product]) => product).join(",")}`;
    if (this.imageKey === key) return;
    const blobs = await Promise.all(pictures.map(([product]) => getBlob(`/v1/jobs/${job.id}/${product}`)));
    if (job.id !== this.jobId) return;
    this.imageKey = key;
    this.placeholder.replaceChildren(...pictures.flatMap(([product, caption], index) => [
      el("img", { src: URL.createObjectURL(blobs[index]), alt: caption, class: "product-image",
        "data-product": product }),
      el("div", { class: "muted" }, caption)]));
    this.placeholder.hidden = false;
  }

  _waitingText(job) {
    if (job.status === "queued") return "Queued: the map appears once the job runs.";
    if (job.status === "running") return "Running: the map appears after the first scans.";
    if (job.status === "failed") return "The job failed before it made a map.";
    if (job.status === "cancelled") return "The job was cancelled before it made a map.";
    return "This job has no map.";
  }

  _build(jobId, scheme, withTexture, version, trajectory) {
    const previous = this.map ? { center: this.map.getCenter(), zoom: this.map.getZoom(),
      nativeZoom: this.scheme.native_zoom } : null;
    if (this.map) this.map.remove();
    const native = scheme.native_zoom;
    const bounds = boundsOf(scheme);
    const map = L.map(this.container, {
      crs: crsFor(scheme),
      minZoom: -TILE_SCHEME.zoomOutPastWhole,
      maxZoom: native + TILE_SCHEME.zoomPastNative,
      zoomSnap: 1, // whole zooms: tiles drawn at 1:1 or a power of two, no seams between them
      attributionControl: false,
    });
    const tileOptions = {
      tileSize: scheme.tile_size, minNativeZoom: 0, maxNativeZoom: native, minZoom: map.getMinZoom(),
      maxZoom: map.getMaxZoom(), noWrap: true, bounds, version, keepBuffer: 1,
    };
    this.layers = {
      occupancy: new FetchTileLayer(TILE_SCHEME.tileUrl(jobId, "occupancy"), { ...tileOptions, className: "tiles-occupancy" }),
      texture: withTexture
        ? new FetchTileLayer(TILE_SCHEME.tileUrl(jobId, "texture"), { ...tileOptions, className: "tiles-texture" })
        : null,
      trajectory: L.polyline([], TRAJECTORY_STYLE),
      pose: L.circleMarker([0, 0], POSE_STYLE),
      deadReckoning: L.polyline([], DEAD_RECKONING_STYLE),
      savedDrives: L.polyline([], SAVED_DRIVES_STYLE),
      closures: L.layerGroup(),
      changes: L.layerGroup(),
    };
    const trajectoryGroup = L.layerGroup([this.layers.trajectory]);
    this.layers.trajectoryGroup = trajectoryGroup;
    // dead reckoning is offered once it has poses (a running job has none yet): see _setPaths
    const overlays = {
      [LAYER_NAMES.occupancy]: this.layers.occupancy,
      ...(withTexture ? { [LAYER_NAMES.texture]: this.layers.texture } : {}),
      [LAYER_NAMES.trajectory]: trajectoryGroup,
    };
    for (const [name, layer] of Object.entries(overlays)) {
      if (!this.hidden.has(name)) layer.addTo(map);
    }
    this.layerControl = L.control.layers(null, overlays, { collapsed: false, position: "topright" }).addTo(map);
    this.deadReckoningOffered = false;
    this.savedDrivesOffered = false;
    this.closuresOffered = false;
    this.changesOffered = false;
    L.control.scale({ imperial: false, metric: true, maxWidth: 160, position: "bottomleft" }).addTo(map);
    new CursorPosition().addTo(map);
    this.colourKey = new ColourKey().addTo(map);
    map.on("overlayadd", (event) => this.hidden.delete(event.name));
    map.on("overlayremove", (event) => this.hidden.add(event.name));
    // The first view may take a fractional zoom (fitted to the pane: whole zooms would leave up to half
    // of it empty; a rebuilt map keeps the view it had); the zoom buttons then step by whole zooms.
    map.options.zoomSnap = 0;
    if (previous) {
      // Same place, same metres per pixel: one native zoom step more halves the cell size on screen.
      map.setView(previous.center, previous.zoom + (native - previous.nativeZoom), { animate: false });
    } else {
      map.fitBounds(initialView(bounds, trajectory), { animate: false });
    }
    map.options.zoomSnap = 1;
    this.map = map;
    this.scheme = scheme;
    this._setPlaceholder(null);
  }

  _setPaths(trajectory, deadReckoning, savedDrives) {
    this.layers.trajectory.setLatLngs(trajectory || []);
    this.layers.savedDrives.setLatLngs(savedDrives || []);
    this.layers.deadReckoning.setLatLngs(deadReckoning || []);
    if (deadReckoning && deadReckoning.length && !this.deadReckoningOffered) {
      this.deadReckoningOffered = true;
      this.layerControl.addOverlay(this.layers.deadReckoning, LAYER_NAMES.deadReckoning);
      if (!this.hidden.has(LAYER_NAMES.deadReckoning)) this.layers.deadReckoning.addTo(this.map);
      this.colourKey.setDeadReckoning(true);
    }
    // an extension's saved-map drives: their own layer and key line, under the new drive's trajectory
    if (savedDrives && savedDrives.length && !this.savedDrivesOffered) {
      this.savedDrivesOffered = true;
      this.layerControl.addOverlay(this.layers.savedDrives, LAYER_NAMES.savedDrives);
      if (!this.hidden.has(LAYER_NAMES.savedDrives)) this.layers.savedDrives.addTo(this.map).bringToBack();
      this.colourKey.setSavedDrives(true);
    }
    const group = this.layers.trajectoryGroup;
    if (trajectory && trajectory.length) {
      this.layers.pose.setLatLng(trajectory[trajectory.length - 1]);
      if (!group.hasLayer(this.layers.pose)) group.addLayer(this.layers.pose);
    } else if (group.hasLayer(this.layers.pose)) {
      group.removeLayer(this.layers.pose);
    }
  }

  /** Accepted loop closures as lines, offered in the layer control and the key once there are any. */
  _setClosures(closures) {
    if (!closures || !closures.length || this.closuresOffered) return;
    this.closuresOffered = true;
    for (const ends of closures) this.layers.closures.addLayer(L.polyline(ends, CLOSURE_STYLE));
    this.layerControl.addOverlay(this.layers.closures, LAYER_NAMES.closures);
    if (!this.hidden.has(LAYER_NAMES.closures)) this.layers.closures.addTo(this.map);
    this.colourKey.setClosures(closures.length);
  }

  /** The changed regions as polygons over the map, offered in the layer control and the key once known. */
  _setChanges(changes) {
    if (!changes || this.changesOffered) return;
    this.changesOffered = true;
    for (const change of changes) this.layers.changes.addLayer(L.polygon(change.rings, CHANGE_STYLES[change.kind]));
    this.layerControl.addOverlay(this.layers.changes, LAYER_NAMES.changes);
    if (!this.hidden.has(LAYER_NAMES.changes)) this.layers.changes.addTo(this.map);
    const count = (kind) => changes.filter((change) => change.kind === kind).length;
    this.colourKey.setChanges({ added: count("added"), removed: count("removed") });
  }

  _clear(text) {
    this.imageKey = null;
    this.liveOf = null;
    if (this.map) this.map.remove();
    this.map = null;
    this.scheme = null;
    this.layers = {};
    this.version = null;
    this._setPlaceholder(text);
  }

  _setPlaceholder(text) {
    if (text === null && this.imageKey) return; // a product picture stays shown
    this.placeholder.hidden = !text;
    this.placeholder.textContent = text || "";
  }
}
