// The lidarmap HTTP API as the page uses it: JSON requests with the optional API key, and error
// bodies turned into readable messages.

const API_KEY_STORAGE = "lidarmap.apiKey";

export function getApiKey() {
  return window.localStorage.getItem(API_KEY_STORAGE) || "";
}

export function setApiKey(key) {
  if (key) window.localStorage.setItem(API_KEY_STORAGE, key);
  else window.localStorage.removeItem(API_KEY_STORAGE);
}

/** An answer that was not 2xx, with a message for people. */
export class ApiError extends Error {
  constructor(status, message, code = null, detail = null) {
    super(message);
    this.status = status;
    this.code = code;
    this.detail = detail;
  }
}

function headers(extra = {}) {
  const key = getApiKey();
  return key ? { ...extra, "X-API-Key": key } : extra;
}

/** "body.particles" -> "particles"; ["query", "limit"] -> "limit". */
function fieldPath(loc) {
  const parts = (Array.isArray(loc) ? loc : [loc]).map(String);
  const trimmed = ["body", "query", "path", "header"].includes(parts[0]) ? parts.slice(1) : parts;
  return trimmed.join(".");
}

function detailLines(detail) {
  if (detail === null || detail === undefined || detail === "") return [];
  if (typeof detail === "string") return [detail];
  if (Array.isArray(detail)) {
    return detail.map((item) => {
      if (item && typeof item === "object" && "msg" in item) {
        const where = fieldPath(item.loc || []);
        return where ? `${where}: ${item.msg}` : String(item.msg);
      }
      return typeof item === "string" ? item : JSON.stringify(item);
    });
  }
  if (typeof detail === "object") {
    return Object.entries(detail)
      .filter(([, value]) => value !== null && value !== undefined)
      .map(([key, value]) => `${key}: ${typeof value === "string" ? value : JSON.stringify(value)}`);
  }
  return [String(detail)];
}

/**
 * A readable message from an error answer: the service's {"error": {code, message, detail}} or
 * FastAPI's {"detail": [...]} / {"detail": "..."}.
 */
export function describeError(status, body) {
  if (body && typeof body === "object" && body.error && typeof body.error === "object") {
    const { code = null, message = "", detail = null } = body.error;
    let lines = detailLines(detail);
    // Validation errors: the message repeats the first field error; list the fields instead.
    if (Array.isArray(detail) && lines.length) return new ApiError(status, lines.join("\n"), code, detail);
    lines = lines.filter((line) => !message.includes(line));
    const text = [message || `HTTP ${status}`, ...lines].join("\n");
    return new ApiError(status, text, code, detail);
  }
  if (body && typeof body === "object" && "detail" in body) {
    const lines = detailLines(body.detail);
    return new ApiError(status, lines.join("\n") || `HTTP ${status}`, null, body.detail);
  }
  if (typeof body === "string" && body.trim()) return new ApiError(status, `HTTP ${status}: ${body.trim()}`);
  return new ApiError(status, `HTTP ${status}`);
}

async function errorFrom(response) {
  const text = await response.text();
  let body = text;
  try {
    body = JSON.parse(text);
  } catch {
    // not JSON: keep the text
  }
  const error = describeError(response.status, body);
  if (response.status === 401 && !getApiKey()) error.message += "\n(set the API key at the top right)";
  return error;
}

/** fetch with the API key; throws ApiError for non-2xx answers, TypeError when unreachable. */
export async function request(path, { method = "GET", json, body, signal } = {}) {
  const init = { method, headers: headers(), signal };
  if (json !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(json);
  } else if (body !== undefined) {
    init.body = body;
  }
  const response = await fetch(path, init);
  if (!response.ok) throw await errorFrom(response);
  return response;
}

export async function getJson(path, options) {
  return (await request(path, options)).json();
}

export async function sendJson(method, path, json) {
  return (await request(path, { method, json })).json();
}

/** A file's bytes (tiles, downloads) with the API key. */
export async function getBlob(path, signal) {
  return (await request(path, { signal })).blob();
}

/** Upload ``file`` as multipart field "file"; ``onProgress(fraction)`` while it is sent. */
export function uploadFile(path, file, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", path);
    const key = getApiKey();
    if (key) xhr.setRequestHeader("X-API-Key", key);
    xhr.upload.onprogress = (event) => {
      if (event.lengthComputable && onProgress) onProgress(event.loaded / event.total);
    };
    xhr.onload = () => {
      let body = xhr.responseText;
      try {
        body = JSON.parse(xhr.responseText);
      } catch {
        // not JSON
      }
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else reject(describeError(xhr.status, body));
    };
    xhr.onerror = () => reject(new ApiError(0, "upload failed: the service could not be reached"));
    const form = new FormData();
    form.append("file", file, file.name);
    xhr.send(form);
  });
}
