// The results of a job on its page: the downloads (grouped, from the export manifest, plus the
// metrics as JSON / CSV) and the 3D asset (the GLB, lights.json, the relit previews and the
// light field).
import { api } from '../api.js';
import { AssetViewer } from '../viewer3d.js';
import { h, clear, filenameFromDisposition, fmtBytes, metricsToCsv, toast } from '../util.js';
import { loadRelitPreviews } from './relit.js';
import { buildControls } from './job_controls.js';

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

/** The download group an artifact is listed under. */
export function downloadGroup(kind, path) {
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
export const GROUP_ORDER = ['Asset (GLB)', 'Material maps', 'Light field', 'Metrics', 'Mesh', 'Previews', 'Other'];

/** [[group, artifacts]] in GROUP_ORDER; 'Metrics' is always there (the metrics API's files). */
export function groupArtifacts(arts) {
  const groups = new Map([['Metrics', []]]);
  for (const a of arts) {
    const g = downloadGroup(a.kind, a.path);
    if (!groups.has(g)) groups.set(g, []);
    groups.get(g).push(a);
  }
  return [...groups.entries()].sort((a, b) => GROUP_ORDER.indexOf(a[0]) - GROUP_ORDER.indexOf(b[0]));
}

function artifactItem(id, a) {
  const name = a.path.split('/').pop();
  return h('li', {},
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
    h('span', { class: 'small muted' }, ` ${fmtBytes(a.bytes)}${a.sha256 ? ` · sha256 ${a.sha256.slice(0, 12)}…` : ''}`));
}

/** Every metric record so far (the charts' copy, re-read from the API to be complete). */
async function allMetrics(id, records) {
  try {
    const res = await api.metrics(id, 0);
    const recs = res?.records || [];
    if (recs.length >= records.length) records.splice(0, records.length, ...recs);
  } catch {
    /* keep what we have */
  }
  return records;
}

function metricsItems(id, records) {
  const extras = [
    { path: 'metrics.json', label: 'metrics.json (all records)', make: (r) => JSON.stringify(r, null, 1), type: 'application/json' },
    { path: 'metrics.csv', label: 'metrics.csv', make: metricsToCsv, type: 'text/csv' },
  ];
  return extras.map((m) => h('li', {},
    h('button', {
      type: 'button', class: 'btn small link', dataset: { download: m.path },
      onclick: async () => {
        const recs = await allMetrics(id, records);
        await saveResponse(new Response(new Blob([m.make(recs)], { type: m.type })), m.path);
      },
    }, m.label),
    h('span', { class: 'small muted' }, ' from the metrics API')));
}

/** Fill `host` with the job's downloads; `records` is the page's live list of metric records. */
export function renderDownloads(host, id, arts, hasManifest, records) {
  clear(host);
  if (!arts.length) {
    host.append(h('p', { class: 'muted' }, 'No results yet.'));
    return;
  }
  if (!hasManifest) host.append(h('p', { class: 'note small' }, 'The export manifest is not written yet; these are the files so far.'));
  for (const [g, items] of groupArtifacts(arts)) {
    const ul = h('ul', { class: 'dl-list' }, items.map((a) => artifactItem(id, a)));
    if (g === 'Metrics') ul.append(...metricsItems(id, records));
    host.append(h('div', { class: 'dl-group' }, h('h3', {}, g), ul));
  }
}

/** lights.json, the relit previews and the light field, once the GLB is shown. */
async function loadAssetExtras(ctx, viewer, has) {
  const { id, els, isStopped } = ctx;
  if (has('lights.json')) {
    await api.artifactJson(id, 'lights.json').then((js) => viewer.setLightsFromJson(js))
      .catch((e) => console.warn('lights.json:', e.message));
  }
  const controls = buildControls(els.controls, viewer);
  ctx.onControls(controls);
  if (has('previews/relit_canonical.json')) {
    loadRelitPreviews(els.relitStrip, id, { viewer, isStopped, onApplied: controls.afterRelitApplied });
  }
  if (!has('light_field.json')) {
    controls.lightFieldReady(0);
    return;
  }
  api.artifactJson(id, 'light_field.json').then((js) => {
    if (!isStopped()) controls.lightFieldReady(viewer.setLightField(js));
  }).catch((e) => {
    console.warn('light_field.json:', e.message);
    controls.lightFieldReady(0);
  });
}

/**
 * List the job's results, show its downloads and, when there is an asset.glb, the 3D viewer.
 * ctx: {id, els: {viewerHost, viewerMsg, controls, relitStrip, downloads}, records, status,
 * isStopped(), onViewer(viewer), onControls(controls)}.
 */
export async function loadResults(ctx) {
  const { id, els, isStopped } = ctx;
  let list = null;
  try {
    list = await api.artifacts(id);
  } catch (e) {
    els.viewerMsg.textContent = `Could not list the results: ${e.message}`;
    return;
  }
  if (isStopped()) return;
  const arts = list?.artifacts || [];
  renderDownloads(els.downloads, id, arts, !!list?.manifest, ctx.records);
  const has = (p) => arts.some((a) => a.path === p);
  if (!has('asset.glb')) {
    els.viewerMsg.textContent = ctx.status === 'cancelled'
      ? 'This job was cancelled before an asset was exported.'
      : 'No asset.glb among the results.';
    return;
  }
  els.viewerMsg.textContent = 'Loading the asset…';
  try {
    const buf = await (await api.artifact(id, 'asset.glb')).arrayBuffer();
    if (isStopped()) return;
    const viewer = new AssetViewer(els.viewerHost, { onChange: () => ctx.onChange() });
    ctx.onViewer(viewer);
    viewer.setFrame(list?.frame); // the manifest's frame: the GLB is +Y up, world records are rotated into it
    await viewer.loadGLB(buf);
    if (isStopped()) return;
    els.viewerMsg.hidden = true;
    await loadAssetExtras(ctx, viewer, has);
  } catch (e) {
    console.warn('asset load failed', e);
    els.viewerMsg.textContent = `Could not display the asset: ${e.message}`;
    els.viewerMsg.hidden = false;
  }
}
