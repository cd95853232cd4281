// Job page: header (status, progress, error), live charts, the adaptivity decisions, and the
// results (3D asset viewer with its controls, downloads: views/job_results.js).
import { api } from '../api.js';
import { followJob } from '../live.js';
import { JobCharts } from '../charts.js';
import { HoldoutPreview } from './holdout.js';
import { h, clear, fmtDuration, fmtTime, isFinal, toast } from '../util.js';
import { progressBar, statusBadge } from './jobs.js';
import { loadResults, renderDownloads } from './job_results.js';

/** [label, value, element id?] rows of the job's facts (pure: tested in Node). */
export function metaItems(job) {
  const raw = job.raw || {};
  const items = [['Created', fmtTime(job.created)]];
  if (raw.started_at) items.push(['Started', fmtTime(raw.started_at)]);
  if (raw.finished_at) items.push(['Finished', fmtTime(raw.finished_at)]);
  if (job.step !== null && job.step !== undefined) items.push(['Step', `${job.step}${job.total ? ` / ${job.total}` : ''}`]);
  if (job.wall_s !== null && job.wall_s !== undefined) items.push(['Wall time', fmtDuration(job.wall_s)]);
  const ds = raw.dataset || {};
  if (ds.format) {
    items.push(['Dataset', `${ds.format}${ds.n_views ? `, ${ds.n_views} views` : ''}${ds.width ? `, ${ds.width}×${ds.height}` : ''}`]);
  }
  if (ds.working_width) items.push(['Trains at', `${ds.working_width}×${ds.working_height} px`, 'meta-working-size']);
  const every = raw.config?.holdout_every;
  if (typeof every === 'number') {
    items.push(['Held-out views', every
      ? `${ds.held_out_views ?? '?'} (views 0, ${every}, ${2 * every}, …), scored during training`
      : 'none: trains on all views', 'meta-held-out']);
  }
  return items;
}

/** The note under the header for a cancelled or queued job (null: none). */
export function statusNote(status) {
  if (status === 'cancelled') return 'This job was cancelled. Below are its partial results: the model as it was when training stopped.';
  if (status === 'queued') return 'Waiting for a worker.';
  return null;
}

function actionButtons(id) {
  const cancel = h('button', {
    type: 'button', class: 'btn', id: 'job-cancel', disabled: true,
    onclick: async () => {
      cancel.disabled = true;
      try {
        await api.cancel(id);
        cancel.textContent = 'Cancelling…';
        toast('Cancel requested: the job stops at its next step and keeps its partial results.');
      } catch (err) {
        toast(`Cancel failed: ${err.message}`, 'error');
        cancel.disabled = false;
      }
    },
  }, 'Cancel');
  const remove = h('button', {
    type: 'button', class: 'btn danger', id: 'job-delete', disabled: true,
    onclick: async () => {
      if (!confirm(`Delete job ${id} and its results?`)) return;
      try {
        await api.remove(id);
        toast('Job deleted');
        location.hash = '#/jobs';
      } catch (err) {
        toast(`Delete failed: ${err.message}`, 'error');
      }
    },
  }, 'Delete');
  return { cancel, remove };
}

const panel = (id, title, ...body) => h('section', { class: 'panel', 'aria-labelledby': id }, h('h2', { id }, title), ...body);

/** The page's elements, appended to `root`. */
function layout(root, id, holdout) {
  const els = {
    title: h('h1', { id: 'job-title' }, `Job ${id}`),
    status: h('div', { class: 'job-status', id: 'job-status' }),
    error: h('div', { class: 'errors-box', id: 'job-error', role: 'alert', hidden: true }),
    note: h('p', { class: 'note', id: 'job-note', hidden: true }),
    meta: h('dl', { class: 'meta small', id: 'job-meta' }),
    decisions: h('div', { id: 'decisions' }, h('p', { class: 'muted' }, 'Reported once training starts.')),
    charts: h('div', { class: 'charts', id: 'charts' }),
    viewerHost: h('div', { class: 'viewer-host', id: 'viewer' }),
    viewerMsg: h('p', { class: 'viewer-msg muted', id: 'viewer-msg' }, 'The 3D asset appears when the export has run.'),
    controls: h('div', { class: 'viewer-controls', id: 'viewer-controls', hidden: true }),
    relitStrip: h('section', { class: 'relit-strip', id: 'relit-previews', 'aria-labelledby': 'relit-title', hidden: true, dataset: { state: 'none', applied: '' } }),
    downloads: h('div', { id: 'downloads', class: 'downloads' }, h('p', { class: 'muted' }, 'Downloads appear when the export has run.')),
    ...actionButtons(id),
  };
  root.append(h('section', { class: 'page job-page', 'aria-labelledby': 'job-title' },
    h('p', { class: 'crumbs small' }, h('a', { href: '#/jobs' }, '← All jobs')),
    h('div', { class: 'page-head' }, els.title, h('div', { class: 'job-actions' }, els.cancel, els.remove)),
    els.status, els.error, els.note, els.meta,
    panel('charts-title', 'Training', els.charts, holdout.el),
    panel('decisions-title', 'What this run left out, and why', els.decisions),
    panel('asset-title', 'Recovered asset', h('div', { class: 'viewer-layout' },
      h('div', { class: 'viewer-column' }, h('div', { class: 'viewer-frame' }, els.viewerHost, els.viewerMsg), els.relitStrip),
      els.controls)),
    panel('downloads-title', 'Downloads', els.downloads)));
  els.page = root.querySelector('.job-page'); // data-status, data-live
  return els;
}

/** The core's adaptivity decisions (report.json, via the API): one row each. */
function decisionsTable(decisions) {
  const fmtValue = (v) => (v !== null && typeof v === 'object' ? JSON.stringify(v) : String(v));
  return h('table', { class: 'decisions small', id: 'decisions-table' },
    h('thead', {}, h('tr', {}, h('th', { scope: 'col' }, 'Step'), h('th', { scope: 'col' }, 'Decision'),
      h('th', { scope: 'col' }, 'Value'), h('th', { scope: 'col' }, 'Reason'))),
    h('tbody', {}, ...decisions.map((d) => h('tr', { 'data-decision': String(d.decision) },
      h('td', {}, String(d.step ?? '')), h('td', {}, String(d.decision)),
      h('td', {}, fmtValue(d.value)), h('td', {}, String(d.reason ?? ''))))));
}

/** Status, progress, facts, error box, note and buttons from the job. */
function renderHeader(els, job) {
  els.title.textContent = job.name ? `${job.name}` : `Job ${job.id}`;
  clear(els.status).append(h('div', { class: 'row' }, statusBadge(job.status),
    job.preset ? h('span', { class: 'chip' }, job.preset) : null), progressBar(job));
  els.page.dataset.status = job.status;
  clear(els.meta).append(...metaItems(job).flatMap(([k, v, mid]) => [h('dt', {}, k), h('dd', mid ? { id: mid } : {}, v)]));
  if (job.status === 'failed') {
    clear(els.error).append(h('h2', { class: 'h3' }, 'This job failed'), h('p', { id: 'job-error-message' }, job.error || 'No error message was recorded.'));
  }
  els.error.hidden = job.status !== 'failed';
  const note = statusNote(job.status);
  if (note) els.note.textContent = note;
  els.note.hidden = !note;
  const active = !isFinal(job.status);
  const cancelling = !!job.raw?.cancel_requested && active;
  els.cancel.disabled = !active || cancelling;
  els.cancel.textContent = cancelling ? 'Cancelling…' : 'Cancel';
  els.remove.disabled = active;
  els.remove.title = active ? 'Cancel the job first' : '';
}

export function renderJob(root, id) {
  const holdout = new HoldoutPreview(id); // the latest held-out picture, below the charts
  const els = layout(root, id, holdout);
  const charts = new JobCharts(els.charts);
  const records = [];
  const st = { job: null, stopped: false, viewer: null, controls: null, resultsRequested: false, decisionsKey: '' };
  const isStopped = () => st.stopped;

  function showDecisions(decisions) {
    if (!Array.isArray(decisions) || !decisions.length) return;
    const key = JSON.stringify(decisions);
    if (key === st.decisionsKey) return;
    st.decisionsKey = key;
    clear(els.decisions).append(decisionsTable(decisions));
  }

  function requestResults(job) {
    if (st.resultsRequested) return;
    if (job.status === 'succeeded' || job.status === 'cancelled') {
      st.resultsRequested = true;
      loadResults({
        id, els, records, status: job.status, isStopped,
        onViewer: (v) => { st.viewer = v; },
        onControls: (c) => { st.controls = c; },
        onChange: () => st.controls?.sync(),
      });
    } else if (job.status === 'failed') {
      // whatever the run wrote before failing (metrics, report) can still be downloaded
      st.resultsRequested = true;
      els.viewerMsg.textContent = 'No asset: the job failed before its export.';
      api.artifacts(id).then((list) => !st.stopped && renderDownloads(els.downloads, id, list?.artifacts || [], !!list?.manifest, records))
        .catch(() => {});
    }
  }

  // the page's data-live says how it follows the job: connecting | sse | polling | stopped
  els.page.dataset.live = 'connecting';
  const stop = followJob(id, {
    onMode: (mode) => {
      els.page.dataset.live = mode;
    },
    onJob: (j) => {
      if (st.stopped) return;
      st.job = { ...(st.job || {}), ...Object.fromEntries(Object.entries(j).filter(([, v]) => v !== null && v !== undefined)) };
      st.job.status = j.status;
      renderHeader(els, st.job);
      showDecisions(st.job.raw?.decisions);
      requestResults(st.job);
    },
    onMetrics: (recs) => {
      if (st.stopped) return;
      records.push(...recs);
      charts.add(recs);
      holdout.update(recs);
    },
  });

  return () => {
    st.stopped = true;
    stop();
    charts.destroy();
    holdout.dispose();
    st.viewer?.dispose();
  };
}
