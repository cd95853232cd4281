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
 * Protocol (api/routes/events.py): GET the job, then open the SSE stream
 * `/jobs/{id}/events?ticket=..&since=N` (ticket from POST /events/ticket). Events:
 * `metrics` (one metrics.jsonl record, `id` = cursor), `progress` ({status, progress, error,
 * cancel_requested, decisions}) and `end` ({status}). A dropped stream is reopened with a
 * fresh ticket from the last cursor; if the stream cannot be opened (proxy without SSE,
 * ticket refused), it polls `GET /jobs/{id}` and `/metrics?since=` every `pollMs`.
 * Returns `stop()`; `stop.state.mode` is the current mode.
 */
export function followJob(id, { onJob, onMetrics, onMode, pollMs = 2000, metrics = true } = {}) {
  const f = new JobFollower(id, { onJob, onMetrics, onMode, pollMs, metrics });
  f.start();
  const state = { get mode() { return f.mode; }, get since() { return f.since; } };
  return Object.assign(() => f.stopAll(), { state });
}

/** The state of one followed job (see followJob): the SSE stream, or polling, and the cursor. */
class JobFollower {
  constructor(id, { onJob, onMetrics, onMode, pollMs, metrics }) {
    Object.assign(this, { id, onJob, onMetrics, onMode, pollMs, metrics });
    this.stopped = false;
    this.es = null;
    this.timer = null;
    this.since = 0; // metrics cursor: number of records already delivered
    this.job = null;
    this.mode = 'connecting';
    this.sseFailures = 0;
  }

  async start() {
    // Initial state: the job record and the metrics so far.
    await Promise.all([this.pollJob(), this.pollMetrics()]);
    if (this.stopped) return;
    if (this.job && isFinal(this.job.status)) {
      this.stopAll();
      return;
    }
    this.openStream();
  }

  setMode(m) {
    if (m === this.mode) return;
    this.mode = m;
    this.onMode?.(m);
  }

  emitJob(j) {
    if (!j || this.stopped) return;
    // a finished job stays finished: a late answer from before the end must not revive it
    if (this.job && isFinal(this.job.status) && !isFinal(j.status) && j.status !== 'deleted') return;
    this.job = j;
    this.onJob?.(j);
  }

  deliver(recs, cursorAfter) {
    if (!recs.length || this.stopped) return;
    this.since = cursorAfter;
    this.onMetrics?.(recs);
  }

  async pollMetrics() {
    if (!this.metrics) return;
    try {
      const res = await api.metrics(this.id, this.since);
      const recs = res?.records || [];
      this.deliver(recs, Number.isFinite(res?.next_since) ? res.next_since : this.since + recs.length);
    } catch (e) {
      if (e.status !== 404) console.warn('metrics poll failed:', e.message);
    }
  }

  async pollJob() {
    try {
      this.emitJob(normJob(await api.getJob(this.id)));
    } catch (e) {
      if (e.status === 404) {
        this.emitJob({ ...(this.job || normJob({ id: this.id })), status: 'deleted' });
        this.stopAll();
      } else console.warn('job poll failed:', e.message);
    }
  }

  startPolling() {
    if (this.stopped || this.mode === 'polling') return;
    this.setMode('polling');
    const tick = async () => {
      if (this.stopped) return;
      await Promise.all([this.pollJob(), this.pollMetrics()]);
      if (this.job && isFinal(this.job.status)) {
        await this.pollMetrics(); // drain what was written last
        this.stopAll();
        return;
      }
      if (!this.stopped) this.timer = setTimeout(tick, this.pollMs);
    };
    tick();
  }

  stopAll() {
    this.stopped = true;
    this.setMode('stopped');
    if (this.es) this.es.close();
    this.es = null;
    clearTimeout(this.timer);
    this.timer = null;
  }

  async openStream() {
    if (this.stopped || this.mode === 'polling') return;
    if (typeof EventSource === 'undefined') return this.startPolling();
    let url;
    try {
      url = await api.eventsUrl(this.id, this.metrics ? this.since : 1e9);
    } catch (e) {
      console.warn('no SSE ticket, polling instead:', e.message);
      return this.startPolling();
    }
    if (this.stopped || this.es || this.mode === 'polling') return; // stopped, already open, or gave up on SSE
    const src = new EventSource(url);
    this.es = src;
    this.setMode('sse');
    this.listen(src);
  }

  /** The stream's handlers; events of a source that is no longer the current one are dropped. */
  listen(src) {
    const current = () => {
      if (src === this.es && !this.stopped) return true;
      src.close();
      return false;
    };
    src.addEventListener('open', () => {
      if (current()) this.sseFailures = 0;
    });
    src.addEventListener('metrics', (ev) => {
      if (current()) this.onMetricsEvent(ev);
    });
    src.addEventListener('progress', (ev) => {
      if (!current()) return;
      try {
        this.emitJob(applyEvent(this.job || normJob({ id: this.id }), JSON.parse(ev.data)));
      } catch {
        /* ignore a malformed event */
      }
    });
    src.addEventListener('end', async () => {
      if (!current()) return;
      // the job is final: close (EventSource would reconnect) and read the full record
      src.close();
      this.es = null;
      await this.pollJob();
      await this.pollMetrics();
      this.stopAll();
    });
    src.onerror = () => {
      if (!current()) return;
      // Tickets expire, so never let EventSource retry with the old URL: reopen with a new
      // ticket from the cursor; after repeated failures fall back to polling.
      src.close();
      this.es = null;
      this.sseFailures++;
      if (this.sseFailures >= 3) this.startPolling();
      else setTimeout(() => this.openStream(), 1000 * this.sseFailures);
    };
  }

  onMetricsEvent(ev) {
    let rec;
    try {
      rec = JSON.parse(ev.data);
    } catch {
      return;
    }
    const cur = Number(ev.lastEventId);
    if (this.metrics) this.deliver([rec], Number.isFinite(cur) && cur > 0 ? cur : this.since + 1);
  }
}
