// REST client for the NePF API. Every call carries the bearer token kept in localStorage.
// The one place that knows route shapes: views call these functions, never fetch() directly.

const TOKEN_KEY = 'nepf.token';

/**
 * Base of the API routes, relative to the page: the API serves this app at "/", and relative
 * URLs keep working when a proxy mounts both under a sub-path (e.g. "/nepf/").
 */
export const API_BASE = '.';

export class ApiError extends Error {
  /**
   * @param {number} status HTTP status
   * @param {string} message human-readable summary
   * @param {any} body parsed JSON body when there was one
   */
  constructor(status, message, body) {
    super(message);
    this.status = status;
    this.body = body;
  }
}

export function getToken() {
  try {
    return localStorage.getItem(TOKEN_KEY) || '';
  } catch {
    return '';
  }
}

export function setToken(token) {
  try {
    if (token) localStorage.setItem(TOKEN_KEY, token);
    else localStorage.removeItem(TOKEN_KEY);
  } catch {
    /* private mode: keep nothing */
  }
}

function authHeaders(extra = {}) {
  const t = getToken();
  return t ? { ...extra, Authorization: `Bearer ${t}` } : { ...extra };
}

/** Turn an error body (FastAPI `detail`, our `errors` list, or text) into one line. */
export function errorSummary(body, status) {
  if (!body) return `HTTP ${status}`;
  if (typeof body === 'string') return body || `HTTP ${status}`;
  const d = body.detail ?? body.error ?? body.message;
  if (typeof d === 'string') return d;
  if (d && typeof d === 'object' && !Array.isArray(d)) {
    if (typeof d.message === 'string') return d.message;
  }
  if (Array.isArray(d) && d.length) {
    return d.map((e) => e.msg || e.message || JSON.stringify(e)).join('; ');
  }
  const errs = validationErrors(body);
  if (errs.length) return errs.map((e) => e.message).join('; ');
  return `HTTP ${status}`;
}

/**
 * Per-file validation errors from an API error body, normalised to
 * `[{code, message, file, view}]`. Accepts `{errors:[...]}`, `{detail:{errors:[...]}}`,
 * `{detail:[...]}` (FastAPI 422) and a bare list.
 */
export function validationErrors(body) {
  if (!body || typeof body !== 'object') return [];
  let list = null;
  if (Array.isArray(body)) list = body;
  else if (Array.isArray(body.errors)) list = body.errors;
  else if (body.detail && typeof body.detail === 'object') {
    if (Array.isArray(body.detail.errors)) list = body.detail.errors;
    else if (Array.isArray(body.detail)) list = body.detail;
    else if (body.detail.message) list = [body.detail];
  }
  if (!list) return [];
  return list.map((e) => {
    if (typeof e === 'string') return { code: '', message: e, file: null, view: null };
    const loc = Array.isArray(e.loc) ? e.loc.filter((p) => p !== 'body').join('.') : null;
    return {
      code: e.code || e.type || '',
      message: e.message || e.msg || JSON.stringify(e),
      file: e.file ?? loc ?? null,
      view: e.view ?? null,
    };
  });
}

async function parseBody(res) {
  const ct = res.headers.get('content-type') || '';
  if (ct.includes('json')) {
    try {
      return await res.json();
    } catch {
      return null;
    }
  }
  try {
    return await res.text();
  } catch {
    return null;
  }
}

/** fetch() with auth; JSON in and out. Throws ApiError on non-2xx. */
export async function request(method, path, { json, query, signal, raw = false } = {}) {
  let url = API_BASE + path;
  if (query) {
    const q = new URLSearchParams();
    for (const [k, v] of Object.entries(query)) if (v !== undefined && v !== null) q.set(k, v);
    const s = q.toString();
    if (s) url += (url.includes('?') ? '&' : '?') + s;
  }
  const init = { method, headers: authHeaders({ Accept: 'application/json' }), signal };
  if (json !== undefined) {
    init.headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(json);
  }
  const res = await fetch(url, init);
  if (!res.ok) {
    const body = await parseBody(res);
    if (res.status === 401) window.dispatchEvent(new CustomEvent('nepf:unauthorized'));
    throw new ApiError(res.status, errorSummary(body, res.status), body);
  }
  if (raw) return res;
  if (res.status === 204) return null;
  return parseBody(res);
}

const enc = encodeURIComponent;

/** Artifact path segments are URL-encoded one by one so "textures/orm.png" keeps its slash. */
function artifactUrl(id, path) {
  return `${API_BASE}/jobs/${enc(id)}/artifacts/${path.split('/').map(enc).join('/')}`;
}

export const api = {
  listJobs: (signal, limit = 100) => request('GET', '/jobs', { query: { limit }, signal }),
  getJob: (id, signal) => request('GET', `/jobs/${enc(id)}`, { signal }),
  metrics: (id, since, signal) => request('GET', `/jobs/${enc(id)}/metrics`, { query: { since }, signal }),
  artifacts: (id, signal) => request('GET', `/jobs/${enc(id)}/artifacts`, { signal }),
  cancel: (id) => request('POST', `/jobs/${enc(id)}/cancel`),
  remove: (id) => request('DELETE', `/jobs/${enc(id)}`),
  /** The JSON schema of a job's config with this server's limits (the upload form checks them). */
  jobConfigSchema: (signal) => request('GET', '/schemas/job-config', { signal }),
  artifactUrl,
  /** Fetch an artifact as a Response (auth header attached). */
  async artifact(id, path, signal, cache = 'default') {
    const res = await fetch(artifactUrl(id, path), { headers: authHeaders(), signal, cache });
    if (!res.ok) {
      const body = await parseBody(res);
      throw new ApiError(res.status, errorSummary(body, res.status), body);
    }
    return res;
  },
  async artifactJson(id, path, signal) {
    return (await api.artifact(id, path, signal)).json();
  },
  async artifactBlob(id, path, signal, cache = 'default') {
    return (await api.artifact(id, path, signal, cache)).blob();
  },
  /**
   * URL for the job's SSE stream. EventSource cannot send headers, so the API hands out a
   * short-lived signed ticket (POST /jobs/{id}/events/ticket) that goes in the query string;
   * the bearer token itself never appears in a URL.
   * @param {string} id
   * @param {number} since metrics cursor: the stream starts after this many records
   */
  async eventsUrl(id, since = 0) {
    const t = await request('POST', `/jobs/${enc(id)}/events/ticket`);
    const q = new URLSearchParams({ ticket: t.ticket, since: String(since) });
    return `${API_BASE}/jobs/${enc(id)}/events?${q}`;
  },
};

/**
 * Create a job: multipart upload of the dataset zip and the config JSON, through XHR so the
 * upload progress can be shown. Resolves with the created job; rejects with ApiError.
 * @param {Blob} zip
 * @param {object} config e.g. {preset, time_budget_s}
 * @param {(loaded:number,total:number)=>void} onProgress
 * @param {string} filename
 */
export function createJob(zip, config, onProgress, filename = 'dataset.zip') {
  return new Promise((resolve, reject) => {
    const form = new FormData();
    form.append('dataset', zip, filename);
    form.append('config', JSON.stringify(config));
    const xhr = new XMLHttpRequest();
    xhr.open('POST', `${API_BASE}/jobs`);
    const t = getToken();
    if (t) xhr.setRequestHeader('Authorization', `Bearer ${t}`);
    xhr.setRequestHeader('Accept', 'application/json');
    xhr.upload.onprogress = (e) => {
      if (e.lengthComputable) onProgress?.(e.loaded, e.total);
    };
    xhr.onerror = () => reject(new ApiError(0, 'Network error during upload', null));
    xhr.onabort = () => reject(new ApiError(0, 'Upload aborted', null));
    xhr.onload = () => {
      let body = null;
      try {
        body = xhr.responseText ? JSON.parse(xhr.responseText) : null;
      } catch {
        body = xhr.responseText;
      }
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else {
        if (xhr.status === 401) window.dispatchEvent(new CustomEvent('nepf:unauthorized'));
        reject(new ApiError(xhr.status, errorSummary(body, xhr.status), body));
      }
    };
    xhr.send(form);
  });
}
