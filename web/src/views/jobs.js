// Job list: status, progress with ETA, stage, thumbnail, created time, cancel / delete.
// Live: one SSE stream per active job; the list itself is re-polled as a fallback.
import { api } from '../api.js';
import { followJob, normJob } from '../live.js';
import { h, clear, fmtDuration, fmtTime, isFinal, toast } from '../util.js';

const LIST_POLL_MS = 4000;
/** SSE streams the list keeps open at once: browsers allow ~6 HTTP/1.1 connections per
 * host, and the page still needs some for API calls. Other active rows follow the polled list. */
const MAX_LIST_STREAMS = 3;

export function progressBar(job) {
  const pct = job.fraction === null ? null : Math.round(Math.max(0, Math.min(1, job.fraction)) * 100);
  const label = pct === null ? 'Progress unknown' : `Progress ${pct}%`;
  const eta = !isFinal(job.status) && job.eta_s !== null ? ` · ETA ${fmtDuration(job.eta_s)}` : '';
  return h('div', { class: 'progress-wrap' },
    h('div', {
      class: `progress ${job.status}`, role: 'progressbar', 'aria-label': label,
      'aria-valuemin': 0, 'aria-valuemax': 100, 'aria-valuenow': pct ?? undefined,
    }, h('div', { class: 'bar', style: { width: `${pct ?? 0}%` } })),
    h('span', { class: 'small muted progress-text' },
      `${pct === null ? '—' : `${pct}%`}${job.stage ? ` · ${job.stage}` : ''}${eta}`));
}

export function statusBadge(status) {
  return h('span', { class: `badge ${status}`, dataset: { status } }, status);
}

/** Load an artifact image through the authenticated API into an <img> (blob URL). */
export function authImage(id, path, alt, cls = 'thumb') {
  const img = h('img', { class: cls, alt, loading: 'lazy', width: 96, height: 96 });
  const holder = h('div', { class: `${cls}-holder` }, img);
  img.hidden = true;
  api.artifactBlob(id, path)
    .then((b) => {
      img.src = URL.createObjectURL(b);
      img.hidden = false;
      img.onload = () => URL.revokeObjectURL(img.src);
    })
    .catch(() => holder.append(h('span', { class: 'thumb-empty', 'aria-hidden': 'true' }, '◌')));
  return holder;
}

function pickLive(j) {
  const out = {};
  for (const [k, v] of Object.entries(j)) if (v !== null && v !== undefined && k !== 'raw') out[k] = v;
  out.raw = j.raw;
  return out;
}

/** The row's thumbnail, once the job has produced it (at the end of its export). */
function loadThumb(list, entry, job) {
  if (!entry.thumbLoaded && (job.status === 'succeeded' || job.status === 'cancelled')) {
    entry.thumbLoaded = true;
    // only ask for the thumbnail when the manifest lists it (no 404s in the console)
    api.artifacts(job.id).then((res) => {
      const arts = res?.artifacts || [];
      const thumb = arts.find((a) => a.path === 'previews/thumb.png') ||
        arts.find((a) => a.kind === 'preview' && /\.png$/i.test(a.path));
      if (thumb && !list.stopped) clear(entry.thumbSlot).append(authImage(job.id, thumb.path, `Preview of ${job.name || `job ${job.id}`}`));
    }).catch(() => {});
  }
  if (!entry.thumbSlot.firstChild) {
    entry.thumbSlot.append(h('div', { class: 'thumb-holder' }, h('span', { class: 'thumb-empty', 'aria-hidden': 'true' }, '◌')));
  }
}

/** The row's Cancel and Delete buttons. */
function rowButtons(list, entry, job, active) {
  const cancelBtn = h('button', {
    type: 'button', class: 'btn small', disabled: !active, dataset: { action: 'cancel' },
    'aria-label': `Cancel job ${job.id}`,
    onclick: async () => {
      cancelBtn.disabled = true;
      try {
        await api.cancel(job.id);
        toast('Cancel requested');
        list.refresh();
      } catch (e) {
        toast(`Cancel failed: ${e.message}`, 'error');
        cancelBtn.disabled = false;
      }
    },
  }, 'Cancel');
  const delBtn = h('button', {
    type: 'button', class: 'btn small danger', dataset: { action: 'delete' }, disabled: active,
    title: active ? 'Cancel the job first' : null,
    'aria-label': `Delete job ${job.id}`,
    onclick: async () => {
      if (!confirm(`Delete job ${job.id} and its results?`)) return;
      delBtn.disabled = true;
      try {
        await api.remove(job.id);
        list.drop(job.id);
        toast('Job deleted');
        list.refresh();
      } catch (e) {
        toast(`Delete failed: ${e.message}`, 'error');
        delBtn.disabled = false;
      }
    },
  }, 'Delete');
  return [cancelBtn, delBtn];
}

function rowMain(job) {
  return h('div', { class: 'job-main' },
    h('div', { class: 'job-title' },
      h('a', { href: `#/jobs/${encodeURIComponent(job.id)}`, class: 'job-link' }, job.name || `Job ${job.id}`),
      statusBadge(job.status),
      job.preset ? h('span', { class: 'chip' }, job.preset) : null),
    progressBar(job),
    h('div', { class: 'small muted' },
      h('span', {}, 'Created '), h('time', { datetime: String(job.created || '') }, fmtTime(job.created)),
      job.status === 'failed' && job.error ? h('span', { class: 'error-inline' }, ` · ${job.error}`) : null));
}

/** The rows of the job list, refreshed every LIST_POLL_MS; active jobs follow their stream. */
class JobListView {
  constructor(listEl, empty, errEl) {
    Object.assign(this, { listEl, empty, errEl });
    this.rows = new Map(); // id -> {el, job, thumbSlot, thumbLoaded, stop}
    this.stopped = false;
    this.timer = null;
  }

  rowFor(job) {
    const el = h('article', { class: 'job-row', dataset: { jobId: job.id }, 'aria-label': `Job ${job.name || job.id}` });
    if (sessionStorage.getItem('nepf.newJob') === job.id) {
      el.classList.add('highlight');
      sessionStorage.removeItem('nepf.newJob');
    }
    const entry = { el, job: null, thumbSlot: h('div', { class: 'thumb-slot' }), thumbLoaded: false, stop: null };
    this.rows.set(job.id, entry);
    this.updateRow(entry, job);
    return entry;
  }

  updateRow(entry, job) {
    entry.job = job;
    const { el } = entry;
    el.dataset.status = job.status;
    loadThumb(this, entry, job);
    const active = !isFinal(job.status);
    const ae = document.activeElement;
    const focused = el.contains(ae) ? ae.dataset.action || (ae.classList.contains('job-link') ? 'link' : null) : null;
    clear(el).append(entry.thumbSlot, rowMain(job),
      h('div', { class: 'job-actions' },
        h('a', { class: 'btn small', href: `#/jobs/${encodeURIComponent(job.id)}` }, 'Open'),
        ...rowButtons(this, entry, job, active)));
    if (focused) el.querySelector(focused === 'link' ? '.job-link' : `[data-action="${focused}"]`)?.focus();
    this.follow(entry, active);
  }

  /** A live stream for active jobs only (at most MAX_LIST_STREAMS at once). */
  follow(entry, active) {
    const streams = [...this.rows.values()].filter((r) => r.stop).length;
    if (active && !entry.stop && streams < MAX_LIST_STREAMS) {
      entry.stop = followJob(entry.job.id, {
        metrics: false,
        onJob: (j) => {
          if (!this.stopped && this.rows.get(j.id) === entry) this.updateRow(entry, { ...entry.job, ...pickLive(j) });
        },
      });
    } else if (!active && entry.stop) {
      entry.stop();
      entry.stop = null;
    }
  }

  drop(id) {
    const entry = this.rows.get(id);
    entry?.stop?.();
    entry?.el.remove();
    this.rows.delete(id);
  }

  show(list) {
    const seen = new Set();
    list.sort((a, b) => String(b.created || '').localeCompare(String(a.created || '')));
    list.forEach((job, i) => {
      seen.add(job.id);
      let entry = this.rows.get(job.id);
      if (!entry) entry = this.rowFor(job);
      else this.updateRow(entry, job);
      if (this.listEl.children[i] !== entry.el) this.listEl.insertBefore(entry.el, this.listEl.children[i] || null);
    });
    for (const id of [...this.rows.keys()]) if (!seen.has(id)) this.drop(id);
    this.empty.hidden = list.length > 0;
    this.listEl.setAttribute('aria-busy', 'false');
    this.listEl.dataset.loaded = 'true';
  }

  async refresh() {
    try {
      const res = await api.listJobs();
      if (this.stopped) return; // the view was left while the request was in flight
      this.errEl.hidden = true;
      this.show((res?.items || []).map(normJob).filter(Boolean));
    } catch (e) {
      this.errEl.textContent = `Could not load jobs: ${e.message}`;
      this.errEl.hidden = false;
    }
    if (!this.stopped) {
      clearTimeout(this.timer);
      this.timer = setTimeout(() => this.refresh(), LIST_POLL_MS);
    }
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
    for (const r of this.rows.values()) r.stop?.();
  }
}

export function renderJobs(root) {
  const listEl = h('div', { id: 'job-list', class: 'job-list', 'aria-live': 'polite', 'aria-busy': 'true' });
  const empty = h('p', { class: 'muted', hidden: true, id: 'jobs-empty' }, 'No jobs yet. ',
    h('a', { href: '#/upload' }, 'Upload a dataset'), ' to start one.');
  const errEl = h('p', { class: 'error', role: 'alert', hidden: true });
  root.append(
    h('section', { class: 'page', 'aria-labelledby': 'jobs-title' },
      h('div', { class: 'page-head' },
        h('h1', { id: 'jobs-title' }, 'Jobs'),
        h('a', { class: 'btn primary', href: '#/upload' }, 'New job')),
      errEl, empty, listEl),
  );
  const view = new JobListView(listEl, empty, errEl);
  view.refresh();
  return () => view.stop();
}
