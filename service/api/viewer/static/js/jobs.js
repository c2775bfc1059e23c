// Sessions with their jobs (status, progress), and the selected job's header with its downloads and,
// once it succeeded, a summary of its run record (accuracy, timings, loop closures, warnings).

import { getBlob, getJson } from "./api.js";
import {
  ACTIVE_STATUSES, el, formatDuration, formatEta, formatScans, formatStage, formatTime, progressPercent, shortId,
} from "./format.js";

/** Every product the page offers for download: [label, path under /v1/jobs/{id}/, product name, file name]. */
export const DOWNLOADS = Object.freeze([
  ["occupancy.png", "occupancy.png", "occupancy.png", "occupancy.png"],
  ["occupancy + trajectories.png", "occupancy_trajectory.png", "occupancy_trajectory.png",
    "occupancy_trajectory.png"],
  ["occupancy.tif (GeoTIFF)", "occupancy.tif", "occupancy.tif", "occupancy.tif"],
  ["map.pgm", "map.pgm", "map.pgm", "map.pgm"],
  ["map.yaml", "map.yaml", "map.yaml", "map.yaml"],
  ["trajectory (TUM)", "trajectory?format=tum", "trajectory.tum", "trajectory.tum"],
  ["dead reckoning (TUM)", "dead-reckoning?format=tum", "dead_reckoning.tum", "dead_reckoning.tum"],
  ["animation.gif", "animation.gif", "animation.gif", "animation.gif"],
  ["texture.png", "texture.png", "texture.png", "texture.png"],
  ["point cloud (PLY)", "map_points.ply", "map_points.ply", "map_points.ply"],
  ["run record (JSON)", "run", "run.json", "run.json"],
  ["map bundle (to localise in, extend, merge)", "map_bundle.npz", "map_bundle.npz", "map_bundle.npz"],
  ["drives.png", "drives.png", "drives.png", "drives.png"],
  ["localization.png", "localization.png", "localization.png", "localization.png"],
  ["confidence (JSON)", "confidence.json", "confidence.json", "confidence.json"],
  ["changes.png", "changes.png", "changes.png", "changes.png"],
  ["changes (GeoJSON)", "changes.geojson", "changes.geojson", "changes.geojson"],
]);

function progressBar(job) {
  return el("div", { class: "progress" },
    el("div", { class: `progress-fill ${job.status}`, style: `width: ${progressPercent(job).toFixed(1)}%` }));
}

/** What a job does: its particles for a mapping run, else its mode and the job whose map it starts from. */
function jobKind(job) {
  if (job.source === "map") return "uploaded map";
  const mode = job.mode || "map";
  if (mode === "map") return `${job.particles ?? "?"} particles`;
  return `${mode} in job ${shortId(job.map_job_id || "")}`;
}

function jobRow(job, selected, onSelect) {
  const meta = [formatStage(job), formatScans(job), formatEta(job)].filter(Boolean).join(" · ");
  return el("li", {
    class: `job${selected ? " selected" : ""}`, dataset: { jobId: job.id, status: job.status },
    title: `job ${job.id}`, onclick: () => onSelect(job.id),
  },
  el("span", { class: `pill ${job.status}` }, job.status),
  el("span", { class: "job-label" }, `job ${shortId(job.id)} · ${jobKind(job)}`),
  el("span", { class: "job-meta" }, meta || formatTime(job.created_at)),
  progressBar(job),
  job.error ? el("span", { class: "job-error", title: job.error }, job.error) : null);
}

/** Render the sessions (newest first), each with its jobs. */
export function renderSessions(list, sessions, jobsBySession, selectedJobId, handlers) {
  list.replaceChildren(...sessions.map((session) => {
    const jobs = jobsBySession.get(session.id) || [];
    return el("li", { class: "session", dataset: { sessionId: session.id } },
      el("div", { class: "session-head" },
        el("span", { class: "session-name", title: session.name }, session.name),
        el("span", { class: "muted" }, formatTime(session.created_at)),
        session.logs > 0 || session.chunks > 0
          ? el("button", { type: "button", class: "small", title: "Start another job with the parameters above",
            onclick: () => handlers.onMapAgain(session.id) }, "Map again")
          : null),
      jobs.length
        ? el("ul", { class: "jobs" }, jobs.map((job) => jobRow(job, job.id === selectedJobId, handlers.onSelect)))
        : el("div", { class: "muted" }, session.logs ? "no jobs yet" : "no log uploaded"));
  }));
}

function productAvailable(job, productName) {
  if (job.status !== "succeeded") return job.products.includes(productName);
  // A succeeded job lists what it wrote; an empty list means the service did not say.
  return job.products.length === 0 || job.products.includes(productName);
}

/** The run record's figures as [label, text] rows; what the record does not hold is left out. */
export function runSummary(run) {
  const rows = [];
  const accuracy = run.accuracy || {};
  const relations = accuracy.relations && accuracy.relations.all;
  const parts = [];
  if (relations && Number.isFinite(relations.trans_mean_m)) {
    parts.push(`relations ${relations.trans_mean_m.toFixed(3)} ± ${relations.trans_std_m.toFixed(3)} m, `
      + `${relations.rot_mean_deg.toFixed(2)} ± ${relations.rot_std_deg.toFixed(2)} deg`);
  }
  if (Number.isFinite(accuracy.ate_m)) parts.push(`ATE ${accuracy.ate_m.toFixed(3)} m`);
  rows.push(["Accuracy", parts.length ? parts.join("; ") : "not known (no ground truth or relations given)"]);
  const timings = run.timings || {};
  if (Number.isFinite(timings.wall_time_s)) {
    const rate = Number.isFinite(timings.scans_per_s) ? `, ${timings.scans_per_s.toFixed(1)} scans/s` : "";
    rows.push(["Time", `${formatDuration(timings.wall_time_s)} for ${timings.scans ?? "?"} scans${rate}`]);
  }
  const placed = run.localization;
  if (placed) {  // a localisation's record: where the drive was found in the saved map, and how fast
    const seconds = placed.wall_time_s;
    const time = !Number.isFinite(seconds) ? ""
      : ` in ${seconds < 60 ? `${seconds.toFixed(1)} s` : formatDuration(seconds)}`;
    const confidence = Number.isFinite(placed.mean_confidence)
      ? ` (mean confidence ${placed.mean_confidence.toFixed(2)})` : "";
    rows.push(["Localisation", placed.localised
      ? `${placed.scans_tracked} of ${placed.scans} scans matched the map${confidence}${time}`
      : `refused${time}: best score ${Number(placed.best_score).toFixed(3)}`]);
    const which = placed.which_map;
    if (which && which.chosen) rows.push(["Map", `job ${which.chosen}, among ${which.maps.length} saved maps`]);
  }
  const closing = run.loop_closing || {};
  if (Number.isFinite(closing.closures_accepted)) {
    rows.push(["Loop closures", `${closing.closures_accepted} accepted of ${closing.candidates_matched ?? "?"} `
      + "candidates matched"]);
  }
  const warnings = run.warnings || [];
  rows.push(["Warnings", warnings.length ? warnings.join("\n") : "none"]);
  return rows;
}

/** Download with the API key (a plain link cannot send the header) and save under ``fileName``. */
async function download(url, fileName) {
  const blob = await getBlob(url);
  const objectUrl = URL.createObjectURL(blob);
  const link = el("a", { href: objectUrl, download: fileName });
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(objectUrl), 10000);
}

export class JobHeader {
  constructor(onCancel, onError) {
    this.root = document.getElementById("job-header");
    this.name = document.getElementById("job-name");
    this.status = document.getElementById("job-status");
    this.scans = document.getElementById("job-scans");
    this.eta = document.getElementById("job-eta");
    this.progress = document.getElementById("job-progress");
    this.error = document.getElementById("job-error");
    this.downloads = document.getElementById("job-downloads");
    this.cancel = document.getElementById("job-cancel");
    this.onError = onError;
    this.summary = document.getElementById("job-summary");
    this.cancel.addEventListener("click", () => this.job && onCancel(this.job.id));
    this.job = null;
    this.downloadsKey = null;
    this.summaryKey = null;
  }

  render(job, session) {
    this.job = job;
    this.root.hidden = !job;
    if (!job) return;
    this.name.textContent = `${session ? session.name : "session " + shortId(job.session_id)} · job ${shortId(job.id)}`;
    this.status.textContent = job.status;
    this.status.className = `pill ${job.status}`;
    this.scans.textContent = [formatStage(job), formatScans(job)].filter(Boolean).join(" · ");
    this.eta.textContent = formatEta(job);
    this.progress.style.width = `${progressPercent(job).toFixed(1)}%`;
    this.progress.className = `progress-fill ${job.status}`;
    this.error.hidden = !job.error;
    this.error.textContent = job.error || "";
    this.cancel.hidden = !ACTIVE_STATUSES.has(job.status);
    this._renderDownloads(job);
    this._renderSummary(job);
  }

  /** A succeeded job's run record, fetched once, as a small table under the downloads. */
  _renderSummary(job) {
    const key = job.status === "succeeded" && job.products.includes("run.json") ? job.id : null;
    if (key === this.summaryKey) return;
    this.summaryKey = key;
    this.summary.replaceChildren();
    this.summary.hidden = true;
    if (!key) return;
    getJson(`/v1/jobs/${job.id}/run`).then((run) => {
      if (this.summaryKey !== key) return;
      this.summary.replaceChildren(...runSummary(run).map(([label, text]) =>
        el("div", { class: "summary-row", dataset: { figure: label.toLowerCase().replace(/ /g, "-") } },
          el("span", { class: "summary-label" }, label), el("span", { class: "summary-text" }, text))));
      this.summary.hidden = false;
    }, this.onError);
  }

  _renderDownloads(job) {
    const key = `${job.id}:${job.status}:${job.products.join(",")}`;
    if (key === this.downloadsKey) return;
    this.downloadsKey = key;
    const links = DOWNLOADS.filter(([, , product]) => productAvailable(job, product)).map(([label, path, , file]) => {
      const url = `/v1/jobs/${job.id}/${path}`;
      return el("a", {
        href: url, download: file, dataset: { product: file },
        onclick: (event) => {
          event.preventDefault();
          download(url, file).catch(this.onError);
        },
      }, label);
    });
    this.downloads.replaceChildren(...(links.length ? [el("span", { class: "muted" }, "Download:"), ...links] : []));
  }
}
