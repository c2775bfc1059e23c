// "New map" panel: pick or drop a drive log, choose the main parameters, then create a session,
// upload the log into it and start a job. API errors are shown as the service words them.

import { getJson, request, sendJson, uploadFile } from "./api.js";
import { el } from "./format.js";

/** The job parameters as typed; a field that is not a number is sent as typed so the API explains. */
export function readParameters() {
  const value = (id) => {
    const text = document.getElementById(id).value.trim();
    const number = Number(text);
    return text !== "" && Number.isFinite(number) ? number : text;
  };
  return { particles: value("param-particles"), seed: value("param-seed"), resolution_m: value("param-resolution") };
}

export class NewRunPanel {
  /** ``onJobCreated(job)`` is called with the new job (JobPublic). */
  constructor(onJobCreated) {
    this.onJobCreated = onJobCreated;
    this.file = null;
    this.uploadedSession = null; // {id, file}: the log is in, only the job is left to start
    this.busy = false;
    this.dropZone = document.getElementById("drop-zone");
    this.fileInput = document.getElementById("log-file");
    this.dropText = document.getElementById("drop-text");
    this.button = document.getElementById("upload-button");
    this.status = document.getElementById("run-status");
    this.error = document.getElementById("run-error");
    this.formatSelect = document.getElementById("param-format");
    this._wire();
  }

  _wire() {
    this.fileInput.addEventListener("change", () => this.setFile(this.fileInput.files[0] || null));
    for (const name of ["dragenter", "dragover"]) {
      this.dropZone.addEventListener(name, (event) => {
        event.preventDefault();
        this.dropZone.classList.add("dragover");
      });
    }
    for (const name of ["dragleave", "drop"]) {
      this.dropZone.addEventListener(name, () => this.dropZone.classList.remove("dragover"));
    }
    this.dropZone.addEventListener("drop", (event) => {
      event.preventDefault();
      const file = event.dataTransfer && event.dataTransfer.files[0];
      if (file) this.setFile(file);
    });
    this.button.addEventListener("click", () => this.start());
  }

  /** Fill the format list from GET /v1/formats (the list stays "auto" when that fails). */
  async loadFormats() {
    try {
      const formats = await getJson("/v1/formats");
      const chosen = this.formatSelect.value;
      this.formatSelect.replaceChildren(el("option", { value: "auto" }, "auto-detect"));
      for (const format of formats.data) {
        this.formatSelect.append(el("option", { value: format.name, title: format.description }, format.name));
      }
      this.formatSelect.value = [...this.formatSelect.options].some((o) => o.value === chosen) ? chosen : "auto";
    } catch {
      // keep auto-detect only
    }
  }

  setFile(file) {
    this.file = file;
    this.uploadedSession = null;
    this.dropZone.classList.toggle("has-file", !!file);
    this.dropText.textContent = file ? `${file.name} (${(file.size / 1e6).toFixed(1)} MB)` : "Drop a drive log here";
    this._showError(null);
    this._setStatus("");
    this._refreshButton();
  }

  _refreshButton() {
    this.button.disabled = this.busy || !this.file;
    this.button.textContent = this.uploadedSession ? "Start the job" : "Upload and map";
  }

  _setStatus(text) {
    this.status.textContent = text;
  }

  _showError(error) {
    this.error.hidden = !error;
    this.error.textContent = error ? (error.message || String(error)) : "";
  }

  async start() {
    if (!this.file || this.busy) return;
    this.busy = true;
    this._refreshButton();
    this._showError(null);
    const parameters = readParameters();
    try {
      if (!this.uploadedSession) await this._upload();
      this._setStatus("Starting the job…");
      const job = await this.startJob(this.uploadedSession.id, parameters);
      this._setStatus(`Job ${job.id.slice(0, 8)} queued.`);
      this.uploadedSession = null;
      this.onJobCreated(job);
    } catch (error) {
      this._setStatus(this.uploadedSession
        ? "The log is uploaded; fix the parameters and press “Start the job”." : "");
      this._showError(error);
    } finally {
      this.busy = false;
      this._refreshButton();
    }
  }

  async _upload() {
    const file = this.file;
    this._setStatus("Creating a session…");
    const session = await sendJson("POST", "/v1/sessions", { name: file.name.slice(0, 200) || "drive log" });
    const format = this.formatSelect.value;
    const query = format && format !== "auto" ? `?format=${encodeURIComponent(format)}` : "";
    try {
      await uploadFile(`/v1/sessions/${session.id}/logs${query}`, file, (fraction) => {
        this._setStatus(fraction < 1 ? `Uploading ${file.name}: ${Math.round(100 * fraction)} %`
          : "Checking the log…");
      });
    } catch (error) {
      // A log the service refuses leaves nothing behind: drop the empty session again.
      await request(`/v1/sessions/${session.id}`, { method: "DELETE" }).catch(() => {});
      throw error;
    }
    this.uploadedSession = { id: session.id, file };
  }

  /** POST /v1/sessions/{id}/jobs with ``parameters``. */
  async startJob(sessionId, parameters) {
    return sendJson("POST", `/v1/sessions/${sessionId}/jobs`, parameters);
  }

  /** A job on an existing session with the panel's parameters; errors are shown in the panel. */
  async mapAgain(sessionId) {
    this._showError(null);
    try {
      const job = await this.startJob(sessionId, readParameters());
      this._setStatus(`Job ${job.id.slice(0, 8)} queued.`);
      this.onJobCreated(job);
    } catch (error) {
      this._showError(error);
    }
  }
}
