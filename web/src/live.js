// Live job updates: Server-Sent Events first, polling as the fallback.
import { api } from './api.js';
import { isFinal } from './util.js';

/**
 * The fields the views use from a job record of the API (`JobPublic`, api/schemas.py): `id`,
 * `name`, `status`, `progress` {step, total, fraction, stage, eta_s, wall_s}, `created_at`,
 * `config.preset`, `error`. `raw` keeps the whole record (dataset, decisions, timestamps).
 */
export function normJob(j) {
  if (!j || typeof j !== 'object') return null;
  const p = (j.progress && typeof j.progress === 'object') ? j.progress : {};
  const num = (x) => (x !== undefined && x !== null && Number.isFinite(Number(x)) ? Number(x) : null);
  const status = String(j.status || 'unknown');
  const cfg = j.config && typeof j.config === 'object' ? j.config : {};
  return {
    raw: j,
    id: String(j.id ?? ''),
    name: j.name || '',
    status,
    fraction: status === 'succeeded' ? 1 : num(p.fraction),
    stage: p.stage ?? null,
    eta_s: num(p.eta_s),
    step: num(p.step),
    total: num(p.total),
    wall_s: num(p.wall_s),
    created: j.created_at ?? null,
    preset: cfg.preset ?? null,
    error: j.error ?? null,
  };
}

/**
 * Merge the SSE `progress` event ({status, progress, error, decisions, cancel_requested}) into
 * a normalised job (returns a new object).
 */
export function applyEvent(job, data) {
  if (!data || typeof data !== 'object') return job;
  const raw = { ...(job?.raw || {}) };
  for (const k of ['status', 'error', 'cancel_requested', 'decisions']) {
    if (data[k] !== undefined) raw[k] = data[k];
  }
  if (data.progress && typeof data.progress === 'object') raw.progress = { ...(raw.progress || {}), ...data.progress };
  return normJob(raw);
}

/** Is this SSE payload a metrics record (as written to metrics.jsonl)? */
export function isMetricRecord(d) {
  if (!d || typeof d !== 'object' || d.step === undefined) return false;
  if (d.kind === 'sync' || d.kind === 'test' || d.kind === 'train') return true;
  return Object.keys(d).some((k) => k.startsWith('loss'));
}

/**
 * Follow one job. Calls `onJob(job)` on status/progress changes, `onMetrics(records)`
 * with new metric records (each record once, in order) and `onMode(mode)` when the way it
 * follows changes ('connecting' | 'sse' | 'polling' | 'stopped').
 *
 * Protocol (api/routes/jobs.py): GET the job, then open the SSE stream
 * `/jobs/{id}/events?ticket=..&since=N` (ticket from POST /events/ticket). Events:
 * `metrics` (one metrics.jsonl record, `id` = cursor), `progress` ({status, progress, error,
 * cancel_requested, decisions}) and `end` ({status}). A dropped stream is reopened with a
 * fresh ticket from the last cursor; if the stream cannot be opened (proxy without SSE,
 * ticket refused), it polls `GET /jobs/{id}` and `/metrics?since=` every `pollMs`.
 * Returns `stop()`; `stop.state.mode` is the current mode.
 */
export function followJob(id, { onJob, onMetrics, onMode, pollMs = 2000, metrics = true } = {}) {
  let stopped = false;
  let es = null;
  let timer = null;
  let since = 0; // metrics cursor: number of records already delivered
  let job = null;
  let mode = 'connecting';
  let sseFailures = 0;
  const state = { get mode() { return mode; }, get since() { return since; } };
  const setMode = (m) => {
    if (m === mode) return;
    mode = m;
    onMode?.(m);
  };

  const emitJob = (j) => {
    if (!j || stopped) return;
    // a finished job stays finished: a late answer from before the end must not revive it
    if (job && isFinal(job.status) && !isFinal(j.status) && j.status !== 'deleted') return;
    job = j;
    onJob?.(j);
  };

  const deliver = (recs, cursorAfter) => {
    if (!recs.length || stopped) return;
    since = cursorAfter;
    onMetrics?.(recs);
  };

  async function pollMetrics() {
    if (!metrics) return;
    try {
      const res = await api.metrics(id, since);
      const recs = res?.records || [];
      deliver(recs, Number.isFinite(res?.next_since) ? res.next_since : since + recs.length);
    } catch (e) {
      if (e.status !== 404) console.warn('metrics poll failed:', e.message);
    }
  }

  async function pollJob() {
    try {
      emitJob(normJob(await api.getJob(id)));
    } catch (e) {
      if (e.status === 404) {
        emitJob({ ...(job || normJob({ id })), status: 'deleted' });
        stopAll();
      } else console.warn('job poll failed:', e.message);
    }
  }

  function startPolling() {
    if (stopped || mode === 'polling') return;
    setMode('polling');
    const tick = async () => {
      if (stopped) return;
      await Promise.all([pollJob(), pollMetrics()]);
      if (job && isFinal(job.status)) {
        await pollMetrics(); // drain what was written last
        stopAll();
        return;
      }
      if (!stopped) timer = setTimeout(tick, pollMs);
    };
    tick();
  }

  function stopAll() {
    stopped = true;
    setMode('stopped');
    if (es) es.close();
    es = null;
    clearTimeout(timer);
    timer = null;
  }

  async function openStream() {
    if (stopped || mode === 'polling') return;
    if (typeof EventSource === 'undefined') return startPolling();
    let url;
    try {
      url = await api.eventsUrl(id, metrics ? since : 1e9);
    } catch (e) {
      console.warn('no SSE ticket, polling instead:', e.message);
      return startPolling();
    }
    if (stopped || es || mode === 'polling') return; // stopped, already open, or gave up on SSE
    const src = new EventSource(url);
    es = src;
    setMode('sse');
    // events of a source that is no longer the current one (closed, replaced) are dropped
    const current = () => {
      if (src === es && !stopped) return true;
      src.close();
      return false;
    };
    src.addEventListener('open', () => {
      if (current()) sseFailures = 0;
    });
    src.addEventListener('metrics', (ev) => {
      if (!current()) return;
      let rec;
      try {
        rec = JSON.parse(ev.data);
      } catch {
        return;
      }
      const cur = Number(ev.lastEventId);
      if (metrics) deliver([rec], Number.isFinite(cur) && cur > 0 ? cur : since + 1);
    });
    src.addEventListener('progress', (ev) => {
      if (!current()) return;
      try {
        emitJob(applyEvent(job || normJob({ id }), JSON.parse(ev.data)));
      } catch {
        /* ignore a malformed event */
      }
    });
    src.addEventListener('end', async () => {
      if (!current()) return;
      // the job is final: close (EventSource would reconnect) and read the full record
      src.close();
      es = null;
      await pollJob();
      await pollMetrics();
      stopAll();
    });
    src.onerror = () => {
      if (!current()) return;
      // Tickets expire, so never let EventSource retry with the old URL: reopen with a new
      // ticket from the cursor; after repeated failures fall back to polling.
      src.close();
      es = null;
      sseFailures++;
      if (sseFailures >= 3) startPolling();
      else setTimeout(openStream, 1000 * sseFailures);
    };
  }

  (async () => {
    // Initial state: the job record and the metrics so far.
    await Promise.all([pollJob(), pollMetrics()]);
    if (stopped) return;
    if (job && isFinal(job.status)) {
      stopAll();
      return;
    }
    openStream();
  })();

  return Object.assign(stopAll, { state });
}
