// The viewer page: polls sessions and jobs, shows the selected job (#job=<id> in the address) on the map.

import { getApiKey, getJson, request, setApiKey } from "./api.js";
import { ACTIVE_STATUSES } from "./format.js";
import { JobHeader, renderSessions } from "./jobs.js";
import { JobMap } from "./mapview.js";
import { NewRunPanel } from "./newrun.js";

const POLL_ACTIVE_MS = 1000; // while a job is queued or running
const POLL_IDLE_MS = 5000;

const state = { sessions: [], jobs: [], selectedJobId: null, timer: null, polling: null };

const listError = document.getElementById("list-error");
const jobMap = new JobMap(document.getElementById("map"), document.getElementById("map-placeholder"));
const header = new JobHeader(cancelJob, showListError);
const newRun = new NewRunPanel((job) => {
  selectJob(job.id);
  pollSoon();
});
jobMap.onError = showListError;
window.lidarmap = { jobMap }; // for the browser console and the end-to-end tests

function showListError(error) {
  listError.hidden = !error;
  listError.textContent = error ? (error.message || String(error)) : "";
}

function selectedFromHash() {
  const match = /job=([^&]+)/.exec(window.location.hash);
  return match ? decodeURIComponent(match[1]) : null;
}

function selectJob(jobId) {
  if (jobId && window.location.hash !== `#job=${jobId}`) window.location.hash = `job=${jobId}`;
  state.selectedJobId = jobId;
  render();
}

async function cancelJob(jobId) {
  try {
    await request(`/v1/jobs/${jobId}`, { method: "DELETE" });
  } catch (error) {
    showListError(error);
  }
  pollSoon();
}

function render() {
  const jobsBySession = new Map();
  for (const job of state.jobs) {
    if (!jobsBySession.has(job.session_id)) jobsBySession.set(job.session_id, []);
    jobsBySession.get(job.session_id).push(job);
  }
  renderSessions(document.getElementById("sessions"), state.sessions, jobsBySession, state.selectedJobId, {
    onSelect: selectJob,
    onMapAgain: (sessionId) => newRun.mapAgain(sessionId),
  });
  document.getElementById("sessions-empty").hidden = state.sessions.length > 0;
  document.getElementById("sessions-count").textContent = state.sessions.length ? `(${state.sessions.length})` : "";
  const job = state.jobs.find((candidate) => candidate.id === state.selectedJobId) || null;
  header.render(job, job && state.sessions.find((session) => session.id === job.session_id));
  jobMap.show(job);
}

async function poll() {
  try {
    const [sessions, jobs] = await Promise.all([getJson("/v1/sessions?limit=200"), getJson("/v1/jobs?limit=1000")]);
    state.sessions = sessions.data;
    state.jobs = jobs.data;
    if (state.selectedJobId && !state.jobs.some((job) => job.id === state.selectedJobId)) {
      // Linked to a job outside the newest 1000: fetch it alone.
      const job = await getJson(`/v1/jobs/${encodeURIComponent(state.selectedJobId)}`).catch(() => null);
      if (job) state.jobs.push(job);
    }
    showListError(null);
  } catch (error) {
    showListError(error);
  }
  render();
}

function pollSoon(delayMs = 0) {
  clearTimeout(state.timer);
  state.timer = setTimeout(async () => {
    if (!state.polling) {
      state.polling = poll();
      await state.polling;
      state.polling = null;
    }
    const active = state.jobs.some((job) => ACTIVE_STATUSES.has(job.status));
    pollSoon(active ? POLL_ACTIVE_MS : POLL_IDLE_MS);
  }, delayMs);
}

function setUpApiKey() {
  const form = document.getElementById("api-key-form");
  const input = document.getElementById("api-key");
  const note = document.getElementById("api-key-state");
  input.value = getApiKey();
  note.textContent = input.value ? "saved" : "";
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    setApiKey(input.value.trim());
    note.textContent = input.value.trim() ? "saved" : "cleared";
    newRun.loadFormats();
    pollSoon();
  });
}

window.addEventListener("hashchange", () => {
  state.selectedJobId = selectedFromHash();
  render();
});

state.selectedJobId = selectedFromHash();
setUpApiKey();
newRun.loadFormats();
pollSoon();
