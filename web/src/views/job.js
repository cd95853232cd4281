// Job page: header (status, progress, error), live charts, 3D asset viewer with channels,
// light field and relighting, and downloads from the manifest.
import { api } from '../api.js';
import { followJob } from '../live.js';
import { JobCharts } from '../charts.js';
import { HoldoutPreview } from './holdout.js';
import { AssetViewer, CHANNELS, ENVIRONMENTS, COLORMAP_CSS, UP_AXES } from '../viewer3d.js';
import { h, clear, filenameFromDisposition, fmtBytes, fmtDuration, fmtTime, isFinal, metricsToCsv, slider, toast } from '../util.js';
import { progressBar, statusBadge } from './jobs.js';
import { loadRelitPreviews } from './relit.js';

/**
 * Download a Response body (blob URL + <a download>) under its Content-Disposition name (the
 * API's "<job name>-<artifact>"), else under `name`.
 */
async function saveResponse(res, name) {
  name = filenameFromDisposition(res.headers.get('content-disposition')) || name;
  const blob = await res.blob();
  const url = URL.createObjectURL(blob);
  const a = h('a', { href: url, download: name, hidden: true });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 30000);
}

function downloadGroup(kind, path) {
  const k = String(kind || '').toLowerCase();
  const p = String(path || '').toLowerCase();
  if (k.includes('glb') || p.endsWith('.glb')) return 'Asset (GLB)';
  if (k.includes('texture') || k.includes('material') || p.startsWith('textures/')) return 'Material maps';
  if (k.includes('light_field') || p.includes('light_field')) return 'Light field';
  if (k.includes('light') || p.includes('lights')) return 'Light field';
  if (k.includes('metric') || p.includes('metrics') || k.includes('report') || p.includes('report')) return 'Metrics';
  if (k.includes('mesh') || p.endsWith('.ply') || p.endsWith('.obj')) return 'Mesh';
  if (k.includes('preview') || p.startsWith('previews/')) return 'Previews';
  return 'Other';
}
const GROUP_ORDER = ['Asset (GLB)', 'Material maps', 'Light field', 'Metrics', 'Mesh', 'Previews', 'Other'];

export function renderJob(root, id) {
  let stopped = false;
  let job = null;
  let viewer = null;
  let viewerRequested = false;
  const allRecords = [];

  // ---------------------------------------------------------------- header
  const title = h('h1', { id: 'job-title' }, `Job ${id}`);
  const statusSlot = h('div', { class: 'job-status', id: 'job-status' });
  const errorBox = h('div', { class: 'errors-box', id: 'job-error', role: 'alert', hidden: true });
  const noteBox = h('p', { class: 'note', id: 'job-note', hidden: true });
  const cancelBtn = h('button', {
    type: 'button', class: 'btn', id: 'job-cancel', disabled: true,
    onclick: async () => {
      cancelBtn.disabled = true;
      try {
        await api.cancel(id);
        cancelBtn.textContent = 'Cancelling…';
        toast('Cancel requested: the job stops at its next step and keeps its partial results.');
      } catch (err) {
        toast(`Cancel failed: ${err.message}`, 'error');
        cancelBtn.disabled = false;
      }
    },
  }, 'Cancel');
  const deleteBtn = h('button', {
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
  const actions = h('div', { class: 'job-actions' }, cancelBtn, deleteBtn);
  const meta = h('dl', { class: 'meta small', id: 'job-meta' });

  // ---------------------------------------------------------------- adaptivity decisions
  const decisionsHost = h('div', { id: 'decisions' }, h('p', { class: 'muted' }, 'Reported once training starts.'));
  let decisionsKey = '';

  // ---------------------------------------------------------------- charts
  const chartsHost = h('div', { class: 'charts', id: 'charts' });
  const holdout = new HoldoutPreview(id);

  // ---------------------------------------------------------------- viewer
  const viewerHost = h('div', { class: 'viewer-host', id: 'viewer' });
  const viewerMsg = h('p', { class: 'viewer-msg muted', id: 'viewer-msg' }, 'The 3D asset appears when the export has run.');
  const controls = h('div', { class: 'viewer-controls', id: 'viewer-controls', hidden: true });
  const relitStrip = h('section', { class: 'relit-strip', id: 'relit-previews', 'aria-labelledby': 'relit-title', hidden: true, dataset: { state: 'none', applied: '' } });
  const downloads = h('div', { id: 'downloads', class: 'downloads' }, h('p', { class: 'muted' }, 'Downloads appear when the export has run.'));

  root.append(h('section', { class: 'page job-page', 'aria-labelledby': 'job-title' },
    h('p', { class: 'crumbs small' }, h('a', { href: '#/jobs' }, '← All jobs')),
    h('div', { class: 'page-head' }, title, actions),
    statusSlot, errorBox, noteBox, meta,
    h('section', { class: 'panel', 'aria-labelledby': 'charts-title' },
      h('h2', { id: 'charts-title' }, 'Training'),
      chartsHost, holdout.el),
    h('section', { class: 'panel', 'aria-labelledby': 'decisions-title' },
      h('h2', { id: 'decisions-title' }, 'What this run left out, and why'),
      decisionsHost),
    h('section', { class: 'panel', 'aria-labelledby': 'asset-title' },
      h('h2', { id: 'asset-title' }, 'Recovered asset'),
      h('div', { class: 'viewer-layout' },
        h('div', { class: 'viewer-column' }, h('div', { class: 'viewer-frame' }, viewerHost, viewerMsg), relitStrip),
        controls)),
    h('section', { class: 'panel', 'aria-labelledby': 'downloads-title' },
      h('h2', { id: 'downloads-title' }, 'Downloads'),
      downloads)));

  const page = root.querySelector('.job-page'); // data-status, data-live
  const charts = new JobCharts(chartsHost);

  // ---------------------------------------------------------------- header updates
  function renderHeader() {
    if (!job) return;
    title.textContent = job.name ? `${job.name}` : `Job ${job.id}`;
    clear(statusSlot).append(h('div', { class: 'row' }, statusBadge(job.status),
      job.preset ? h('span', { class: 'chip' }, job.preset) : null), progressBar(job));
    page.dataset.status = job.status;
    const raw = job.raw || {};
    const metaItems = [['Created', fmtTime(job.created)]];
    if (raw.started_at) metaItems.push(['Started', fmtTime(raw.started_at)]);
    if (raw.finished_at) metaItems.push(['Finished', fmtTime(raw.finished_at)]);
    if (job.step !== null) metaItems.push(['Step', `${job.step}${job.total ? ` / ${job.total}` : ''}`]);
    if (job.wall_s !== null) metaItems.push(['Wall time', fmtDuration(job.wall_s)]);
    const ds = raw.dataset || {};
    if (ds.format) {
      metaItems.push(['Dataset', `${ds.format}${ds.n_views ? `, ${ds.n_views} views` : ''}${ds.width ? `, ${ds.width}×${ds.height}` : ''}`]);
    }
    if (ds.working_width) metaItems.push(['Trains at', `${ds.working_width}×${ds.working_height} px`, 'meta-working-size']);
    const every = raw.config?.holdout_every;
    if (typeof every === 'number') {
      metaItems.push(['Held-out views', every
        ? `${ds.held_out_views ?? '?'} (views 0, ${every}, ${2 * every}, …), scored during training`
        : 'none: trains on all views', 'meta-held-out']);
    }
    clear(meta).append(...metaItems.flatMap(([k, v, mid]) => [h('dt', {}, k), h('dd', mid ? { id: mid } : {}, v)]));
    if (job.status === 'failed') {
      clear(errorBox).append(h('h2', { class: 'h3' }, 'This job failed'), h('p', { id: 'job-error-message' }, job.error || 'No error message was recorded.'));
      errorBox.hidden = false;
    } else errorBox.hidden = true;
    if (job.status === 'cancelled') {
      noteBox.textContent = 'This job was cancelled. Below are its partial results: the model as it was when training stopped.';
      noteBox.hidden = false;
    } else if (job.status === 'queued') {
      noteBox.textContent = 'Waiting for a worker.';
      noteBox.hidden = false;
    } else noteBox.hidden = true;

    renderDecisions(job.raw?.decisions);

    const active = !isFinal(job.status);
    const cancelling = !!job.raw?.cancel_requested && active;
    cancelBtn.disabled = !active || cancelling;
    cancelBtn.textContent = cancelling ? 'Cancelling…' : 'Cancel';
    deleteBtn.disabled = active;
    deleteBtn.title = active ? 'Cancel the job first' : '';
    if ((job.status === 'succeeded' || job.status === 'cancelled') && !viewerRequested) {
      viewerRequested = true;
      loadResults();
    } else if (job.status === 'failed' && !viewerRequested) {
      // whatever the run wrote before failing (metrics, report) can still be downloaded
      viewerRequested = true;
      viewerMsg.textContent = 'No asset: the job failed before its export.';
      api.artifacts(id).then((list) => !stopped && renderDownloads(list?.artifacts || [], !!list?.manifest))
        .catch(() => {});
    }
  }

  /** The core's adaptivity decisions (report.json, via the API): one row each. */
  function renderDecisions(decisions) {
    if (!Array.isArray(decisions) || !decisions.length) return;
    const key = JSON.stringify(decisions);
    if (key === decisionsKey) return;
    decisionsKey = key;
    const fmtValue = (v) => (v !== null && typeof v === 'object' ? JSON.stringify(v) : String(v));
    clear(decisionsHost).append(h('table', { class: 'decisions small', id: 'decisions-table' },
      h('thead', {}, h('tr', {}, h('th', { scope: 'col' }, 'Step'), h('th', { scope: 'col' }, 'Decision'),
        h('th', { scope: 'col' }, 'Value'), h('th', { scope: 'col' }, 'Reason'))),
      h('tbody', {}, ...decisions.map((d) => h('tr', { 'data-decision': String(d.decision) },
        h('td', {}, String(d.step ?? '')), h('td', {}, String(d.decision)),
        h('td', {}, fmtValue(d.value)), h('td', {}, String(d.reason ?? '')))))));
  }

  // ---------------------------------------------------------------- results
  async function loadResults() {
    let list = null;
    try {
      list = await api.artifacts(id);
    } catch (e) {
      viewerMsg.textContent = `Could not list the results: ${e.message}`;
      return;
    }
    if (stopped) return;
    const arts = list?.artifacts || [];
    renderDownloads(arts, !!list?.manifest);
    const has = (p) => arts.some((a) => a.path === p);
    if (!has('asset.glb')) {
      viewerMsg.textContent = job?.status === 'cancelled'
        ? 'This job was cancelled before an asset was exported.'
        : 'No asset.glb among the results.';
      return;
    }
    viewerMsg.textContent = 'Loading the asset…';
    try {
      const buf = await (await api.artifact(id, 'asset.glb')).arrayBuffer();
      if (stopped) return;
      viewer = new AssetViewer(viewerHost, { onChange: () => syncControls() });
      viewer.setFrame(list?.frame); // the manifest's frame: the GLB is +Y up, world records are rotated into it
      await viewer.loadGLB(buf);
      if (stopped) return;
      viewerMsg.hidden = true;
      const extras = [];
      if (has('lights.json')) {
        extras.push(api.artifactJson(id, 'lights.json').then((js) => viewer.setLightsFromJson(js)).catch((e) => console.warn('lights.json:', e.message)));
      }
      await Promise.all(extras);
      buildControls();
      if (has('previews/relit_canonical.json')) {
        loadRelitPreviews(relitStrip, id, { viewer, isStopped: () => stopped, onApplied: afterRelitApplied });
      }
      if (has('light_field.json')) {
        api.artifactJson(id, 'light_field.json').then((js) => {
          if (stopped) return;
          const n = viewer.setLightField(js);
          lightFieldReady(n);
        }).catch((e) => {
          console.warn('light_field.json:', e.message);
          lightFieldReady(0);
        });
      } else lightFieldReady(0);
    } catch (e) {
      console.warn('asset load failed', e);
      viewerMsg.textContent = `Could not display the asset: ${e.message}`;
      viewerMsg.hidden = false;
    }
  }

  function renderDownloads(arts, hasManifest) {
    clear(downloads);
    if (!arts.length) {
      downloads.append(h('p', { class: 'muted' }, 'No results yet.'));
      return;
    }
    if (!hasManifest) downloads.append(h('p', { class: 'note small' }, 'The export manifest is not written yet; these are the files so far.'));
    const groups = new Map();
    for (const a of arts) {
      const g = downloadGroup(a.kind, a.path);
      if (!groups.has(g)) groups.set(g, []);
      groups.get(g).push(a);
    }
    const metricsExtras = [
      { path: 'metrics.json', label: 'metrics.json (all records)', make: () => JSON.stringify(allRecords, null, 1), type: 'application/json' },
      { path: 'metrics.csv', label: 'metrics.csv', make: () => metricsToCsv(allRecords), type: 'text/csv' },
    ];
    if (!groups.has('Metrics')) groups.set('Metrics', []);
    const sorted = [...groups.entries()].sort((a, b) => GROUP_ORDER.indexOf(a[0]) - GROUP_ORDER.indexOf(b[0]));
    for (const [g, items] of sorted) {
      const ul = h('ul', { class: 'dl-list' });
      for (const a of items) {
        const name = a.path.split('/').pop();
        ul.append(h('li', {},
          h('button', {
            type: 'button', class: 'btn small link', dataset: { download: a.path },
            'aria-label': `Download ${a.path}`,
            onclick: async (e) => {
              e.target.disabled = true;
              try {
                await saveResponse(await api.artifact(id, a.path), name);
              } catch (err) {
                toast(`Download failed: ${err.message}`, 'error');
              } finally {
                e.target.disabled = false;
              }
            },
          }, a.path),
          h('span', { class: 'small muted' }, ` ${fmtBytes(a.bytes)}${a.sha256 ? ` · sha256 ${a.sha256.slice(0, 12)}…` : ''}`)));
      }
      if (g === 'Metrics') {
        for (const m of metricsExtras) {
          ul.append(h('li', {},
            h('button', {
              type: 'button', class: 'btn small link', dataset: { download: m.path },
              onclick: async () => {
                await fetchAllMetrics();
                await saveResponse(new Response(new Blob([m.make()], { type: m.type })), m.path);
              },
            }, m.label),
            h('span', { class: 'small muted' }, ' from the metrics API')));
        }
      }
      downloads.append(h('div', { class: 'dl-group' }, h('h3', {}, g), ul));
    }
  }

  async function fetchAllMetrics() {
    // the charts already hold every record streamed so far; re-read to be complete
    try {
      const res = await api.metrics(id, 0);
      const recs = res?.records || [];
      if (recs.length >= allRecords.length) allRecords.splice(0, allRecords.length, ...recs);
    } catch {
      /* keep what we have */
    }
  }

  // ---------------------------------------------------------------- viewer controls
  let ctl = {};
  let lfToggle = null;
  let lfLegend = null;
  let lfSlider = null;

  function buildControls() {
    const st = viewer.state;
    const chGroup = h('fieldset', { class: 'channels', id: 'channel-group' },
      h('legend', {}, 'Channel'),
      h('div', { class: 'seg' }, CHANNELS.map((c) => h('label', { class: 'seg-item' },
        h('input', {
          type: 'radio', name: 'channel', value: c.value, id: `channel-${c.value}`, checked: st.channel === c.value,
          onchange: () => viewer.set({ channel: c.value }),
        }), h('span', {}, c.label)))));
    const wire = h('label', { class: 'check' }, h('input', {
      type: 'checkbox', id: 'wireframe', checked: st.wireframe,
      onchange: (e) => viewer.set({ wireframe: e.target.checked }),
    }), ' Wireframe');
    const upSel = h('div', { class: 'field' }, h('label', { for: 'up-axis' }, 'Up axis'),
      h('select', {
        id: 'up-axis',
        onchange: (e) => {
          viewer.setUp(e.target.value);
          syncControls();
        },
      }, Object.entries(UP_AXES).map(([k, v]) => h('option', { value: k, selected: k === st.up }, v.label))));
    const resetView = h('button', { type: 'button', class: 'btn small', id: 'reset-view', onclick: () => viewer.frameCamera() }, 'Reset view');

    // light field
    lfToggle = h('input', {
      type: 'checkbox', id: 'lightfield-toggle', disabled: true,
      onchange: (e) => {
        viewer.set({ lightField: e.target.checked });
        lfLegend.hidden = !e.target.checked;
      },
    });
    lfSlider = slider({
      id: 'lightfield-density', label: 'Glyph density', min: 0.02, max: 1, step: 0.02, value: st.density,
      format: (v) => `${Math.round(v * 100)}%`,
      onInput: (v) => viewer.set({ density: v }),
    });
    lfSlider.input.disabled = true;
    lfLegend = h('div', { class: 'legend', id: 'lightfield-legend', hidden: true });
    const lfSet = h('fieldset', { id: 'lightfield-group' },
      h('legend', {}, 'Light field'),
      h('label', { class: 'check' }, lfToggle, ' Show light glyphs'),
      lfSlider.wrap, lfLegend,
      h('p', { class: 'small muted', id: 'lightfield-status' }, 'Loading light_field.json…'));

    // relighting
    const mk = (key, label, min, max, step, fmt) => (ctl[key] = slider({
      id: `light-${key}`, label, min, max, step, value: st[key], format: fmt,
      onInput: (v) => viewer.set({ [key]: v }),
    }));
    const env = h('select', {
      id: 'env-preset',
      onchange: (e) => viewer.set({ env: e.target.value }),
    }, ENVIRONMENTS.map((o) => h('option', { value: o.value, selected: o.value === st.env }, o.label)));
    const lightSet = h('fieldset', { id: 'light-group' },
      h('legend', {}, 'Relighting'),
      h('p', { class: 'small muted' }, viewer.lightsJson ? 'Initialised from lights.json. Drag the yellow sphere, or use the sliders.' : 'Drag the yellow sphere, or use the sliders.'),
      mk('lightAz', 'Light azimuth', -180, 180, 1, (v) => `${Math.round(v)}°`).wrap,
      mk('lightEl', 'Light elevation', -89, 89, 1, (v) => `${Math.round(v)}°`).wrap,
      mk('lightDist', 'Light distance', 1.2, 20, 0.1, (v) => `${Number(v).toFixed(1)} r`).wrap,
      mk('lightIntensity', 'Light intensity', 0, 5, 0.05, (v) => `${Number(v).toFixed(2)}×`).wrap,
      h('div', { class: 'field' }, h('label', { for: 'env-preset' }, 'Environment'), env),
      mk('envIntensity', 'Environment strength', 0, 2, 0.05, (v) => Number(v).toFixed(2)).wrap,
      mk('exposure', 'Exposure', 0.1, 4, 0.05, (v) => Number(v).toFixed(2)).wrap,
      h('button', {
        type: 'button', class: 'btn small', id: 'light-reset',
        onclick: () => {
          if (viewer.lightsJson) viewer.setLightsFromJson({ __parsed: viewer.lightsJson });
          viewer.set({ lightIntensity: 1 });
          syncControls();
        },
      }, 'Reset light'));

    // material editing
    const tint = h('input', {
      type: 'color', id: 'albedo-tint', value: st.tint,
      oninput: (e) => viewer.set({ tint: e.target.value }),
    });
    const matSet = h('fieldset', { id: 'material-group' },
      h('legend', {}, 'Material editing'),
      (ctl.roughnessScale = slider({
        id: 'roughness-scale', label: 'Roughness scale', min: 0, max: 2, step: 0.05, value: st.roughnessScale,
        format: (v) => `${Number(v).toFixed(2)}×`, onInput: (v) => viewer.set({ roughnessScale: v }),
      })).wrap,
      (ctl.metallicScale = slider({
        id: 'metallic-scale', label: 'Metallic scale', min: 0, max: 2, step: 0.05, value: st.metallicScale,
        format: (v) => `${Number(v).toFixed(2)}×`, onInput: (v) => viewer.set({ metallicScale: v }),
      })).wrap,
      h('div', { class: 'field' }, h('label', { for: 'albedo-tint' }, 'Albedo tint'), tint),
      h('button', {
        type: 'button', class: 'btn small', id: 'material-reset',
        onclick: () => {
          viewer.set({ roughnessScale: 1, metallicScale: 1, tint: '#ffffff' });
          tint.value = '#ffffff';
          syncControls();
        },
      }, 'Reset material'));

    clear(controls).append(
      h('fieldset', { id: 'view-group' }, h('legend', {}, 'View'), chGroup, h('div', { class: 'row wrap' }, wire, resetView), upSel),
      lightSet, lfSet, matSet);
    controls.hidden = false;
  }

  function lightFieldReady(n) {
    if (!lfToggle) return;
    const status = controls.querySelector('#lightfield-status');
    if (n > 0) {
      lfToggle.disabled = false;
      lfSlider.input.disabled = false;
      status.textContent = `${n} surface samples. Arrows point the way the light travels; the tip touches the surface.`;
      const lf = viewer.lf;
      clear(lfLegend).append(
        h('span', { class: 'small' }, 'Intensity'),
        h('div', { class: 'legend-bar', style: { background: COLORMAP_CSS }, role: 'img', 'aria-label': `Colour scale from ${lf.min.toPrecision(3)} to ${lf.max.toPrecision(3)}` }),
        h('div', { class: 'legend-ticks small' }, h('span', {}, lf.min.toPrecision(3)), h('span', {}, lf.max.toPrecision(3))));
    } else {
      status.textContent = 'No light field in the results.';
    }
  }

  /** After a relit preview was put on the viewer: the selects and sliders show its state. */
  function afterRelitApplied() {
    const env = controls.querySelector('#env-preset');
    if (env) env.value = viewer.state.env;
    const up = controls.querySelector('#up-axis');
    if (up) up.value = viewer.state.up;
    syncControls();
  }

  function syncControls() {
    if (!viewer) return;
    for (const [k, c] of Object.entries(ctl)) c.set(viewer.state[k]);
  }

  // ---------------------------------------------------------------- live
  // the page's data-live says how it follows the job: connecting | sse | polling | stopped
  page.dataset.live = 'connecting';
  const stop = followJob(id, {
    onMode: (mode) => {
      page.dataset.live = mode;
    },
    onJob: (j) => {
      if (stopped) return;
      job = { ...(job || {}), ...Object.fromEntries(Object.entries(j).filter(([, v]) => v !== null && v !== undefined)) };
      job.status = j.status;
      renderHeader();
    },
    onMetrics: (recs) => {
      if (stopped) return;
      allRecords.push(...recs);
      charts.add(recs);
      holdout.update(recs);
    },
  });

  return () => {
    stopped = true;
    stop();
    charts.destroy();
    holdout.dispose();
    viewer?.dispose();
  };
}
