// Small formatting helpers for the page.

export const ACTIVE_STATUSES = new Set(["queued", "running"]);

/** 75 -> "1 min 15 s"; null -> "". */
export function formatDuration(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "";
  const s = Math.round(seconds);
  if (s < 60) return `${s} s`;
  const m = Math.floor(s / 60);
  if (m < 60) return `${m} min ${s % 60} s`;
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

export function formatScans(job) {
  if (job.scans_total) return `${job.scans_done} / ${job.scans_total} scans`;
  return job.scans_done ? `${job.scans_done} scans` : "";
}

/** What a running job does now, e.g. "closing loops" ("" when not running). */
export function formatStage(job) {
  return job.status === "running" && job.stage ? job.stage : "";
}

export function formatEta(job) {
  if (job.status === "running" && job.compiling) return "compiling the engine (first run)";
  return job.status === "running" && job.eta_s !== null ? `ETA ${formatDuration(job.eta_s)}` : "";
}

export function formatTime(iso) {
  if (!iso) return "";
  const date = new Date(iso);
  return date.toLocaleString(undefined, { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" });
}

export function shortId(id) {
  return id ? id.slice(0, 8) : "";
}

/** A job's progress bar width, 0..100 [%]. */
export function progressPercent(job) {
  if (job.status === "succeeded") return 100;
  return Math.max(0, Math.min(100, 100 * (job.progress || 0)));
}

/** Create an element: el("span", {class: "pill"}, "text", child...). */
export function el(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) {
    if (value === null || value === undefined || value === false) continue;
    if (name === "class") node.className = value;
    else if (name === "dataset") Object.assign(node.dataset, value);
    else if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value === true ? "" : value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}
