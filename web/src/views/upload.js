// Upload: pick a zip, or drag a folder in (zipped here, in the browser, with fflate);
// choose a preset and a time budget; show upload progress and per-file validation errors.
import { zip as fflateZip } from 'fflate';
import { createJob, validationErrors } from '../api.js';
import { h, clear, fmtBytes, toast } from '../util.js';

/** Job options and their bounds (the API checks them again: api/job_config.py). */
export const TEXTURE_SIZES = [256, 512, 1024, 2048];
export const MAX_FACES_RANGE = [1000, 2000000];
/** The input world's up axis, turned into glTF's +Y by the export ('' or 'auto': from the cameras). */
export const UP_AXES = ['auto', '+x', '-x', '+y', '-y', '+z', '-z'];

/**
 * The optional job options from the form's strings; empty means "the server's default".
 * Returns {options, problems}: problems name the field and the allowed values.
 */
export function jobOptions({ holdoutEvery = '', maxImageSide = '', textureSize = '', maxFaces = '', upAxis = '' }) {
  const options = {};
  const problems = [];
  const int = (label, text, ok, allowed, key) => {
    const t = String(text).trim();
    if (!t) return;
    const v = Number(t);
    if (!Number.isInteger(v) || !ok(v)) problems.push({ code: 'invalid_config', file: label, view: null, message: `must be ${allowed} (got ${t})` });
    else options[key] = v;
  };
  int('Held-out views', holdoutEvery, (v) => v === 0 || v >= 2, '0 (train on all views) or an integer ≥ 2', 'holdout_every');
  int('Working resolution', maxImageSide, (v) => v >= 8, 'an integer ≥ 8 pixels', 'max_image_side');
  int('Texture size', textureSize, (v) => TEXTURE_SIZES.includes(v), `one of ${TEXTURE_SIZES.join(', ')}`, 'texture_size');
  int('Mesh faces', maxFaces, (v) => v >= MAX_FACES_RANGE[0] && v <= MAX_FACES_RANGE[1],
    `an integer from ${MAX_FACES_RANGE[0]} to ${MAX_FACES_RANGE[1]}`, 'max_faces');
  const up = String(upAxis).trim().toLowerCase();
  if (up && up !== 'auto') {
    if (UP_AXES.includes(up)) options.up_axis = up;
    else problems.push({ code: 'invalid_config', file: 'Up axis', view: null, message: `must be one of ${UP_AXES.join(', ')} (got ${up})` });
  }
  return { options, problems };
}

const PRESETS = [
  { value: 'tiny', label: 'tiny — smoke test, a few minutes on a CPU' },
  { value: 'fast', label: 'fast — minutes on a GPU' },
  { value: 'paper', label: 'paper — the paper\'s settings (hours)' },
];

/** Read every file under a dropped directory entry: [{path, file}] */
async function walkEntry(entry, prefix = '') {
  if (entry.isFile) {
    const file = await new Promise((res, rej) => entry.file(res, rej));
    return [{ path: prefix + entry.name, file }];
  }
  if (entry.isDirectory) {
    const reader = entry.createReader();
    const all = [];
    // readEntries returns batches (100 in Chromium) until it returns an empty list
    for (;;) {
      const batch = await new Promise((res, rej) => reader.readEntries(res, rej));
      if (!batch.length) break;
      all.push(...batch);
    }
    const out = [];
    for (const e of all) out.push(...(await walkEntry(e, `${prefix}${entry.name}/`)));
    return out;
  }
  return [];
}

/** Drop a single shared top folder so the zip's root is the dataset root. Skip OS junk. */
function normalisePaths(items) {
  items = items.filter((it) => !/(^|\/)(\.DS_Store|Thumbs\.db|__MACOSX)(\/|$)/.test(it.path));
  const tops = new Set(items.map((it) => it.path.split('/')[0]));
  if (tops.size === 1 && items.every((it) => it.path.includes('/'))) {
    const top = [...tops][0];
    return { root: top, items: items.map((it) => ({ ...it, path: it.path.slice(top.length + 1) })) };
  }
  return { root: null, items };
}

/** Zip files in the browser (stored, not deflated: images are already compressed). */
export async function zipFiles(items, onStep) {
  const data = {};
  let i = 0;
  for (const it of items) {
    data[it.path] = [new Uint8Array(await it.file.arrayBuffer()), { level: /\.(png|jpe?g|exr|npz)$/i.test(it.path) ? 0 : 6 }];
    onStep?.(++i, items.length);
  }
  const bytes = await new Promise((res, rej) => fflateZip(data, { level: 0 }, (err, out) => (err ? rej(err) : res(out))));
  return new Blob([bytes], { type: 'application/zip' });
}

export function renderUpload(root) {
  let dataset = null; // {blob, name, nFiles?}
  let busy = false;

  const fileInput = h('input', {
    type: 'file', id: 'zip-input', accept: '.zip,application/zip', 'aria-describedby': 'drop-help',
    onchange: () => {
      const f = fileInput.files?.[0];
      if (f) setDataset({ blob: f, name: f.name });
    },
  });
  const dirInput = h('input', {
    type: 'file', id: 'dir-input', webkitdirectory: true, multiple: true,
    onchange: async () => {
      const files = [...(dirInput.files || [])];
      if (files.length) await zipFolder(files.map((f) => ({ path: f.webkitRelativePath || f.name, file: f })));
    },
  });
  const chosen = h('p', { id: 'dataset-chosen', class: 'small', 'aria-live': 'polite' }, 'No dataset chosen.');
  const drop = h('div', {
    class: 'dropzone', id: 'dropzone', tabindex: 0, role: 'button',
    'aria-label': 'Drop a dataset folder or zip here, or press Enter to pick a zip file',
    onkeydown: (e) => {
      if (e.key === 'Enter' || e.key === ' ') {
        e.preventDefault();
        fileInput.click();
      }
    },
    onclick: () => fileInput.click(),
    ondragover: (e) => {
      e.preventDefault();
      drop.classList.add('over');
    },
    ondragleave: () => drop.classList.remove('over'),
    ondrop: async (e) => {
      e.preventDefault();
      drop.classList.remove('over');
      const items = [...(e.dataTransfer?.items || [])];
      const entries = items.map((it) => it.webkitGetAsEntry?.()).filter(Boolean);
      if (entries.length === 1 && entries[0].isFile && /\.zip$/i.test(entries[0].name)) {
        const f = e.dataTransfer.files[0];
        setDataset({ blob: f, name: f.name });
        return;
      }
      if (entries.length) {
        const files = [];
        for (const en of entries) files.push(...(await walkEntry(en)));
        await zipFolder(files);
      } else if (e.dataTransfer?.files?.length) {
        const f = e.dataTransfer.files[0];
        setDataset({ blob: f, name: f.name });
      }
    },
  },
  h('p', { class: 'drop-title' }, 'Drop a dataset folder (or a .zip) here'),
  h('p', { id: 'drop-help', class: 'small muted' },
    'DTU (cameras.npz, image/, mask/), NeRF-synthetic / Blender (transforms_train.json), nerfstudio or instant-ngp (transforms.json), or COLMAP (sparse/0/ + images/). A folder is zipped in your browser.'));

  const preset = h('select', { id: 'preset', name: 'preset' },
    PRESETS.map((p) => h('option', { value: p.value, selected: p.value === 'fast' }, p.label)));
  const budget = h('input', {
    id: 'budget', name: 'budget', type: 'number', min: 0, max: 43200, step: 1, value: 0, inputmode: 'numeric',
    'aria-describedby': 'budget-help',
  });
  const nameInput = h('input', {
    id: 'job-name', name: 'name', type: 'text', maxlength: 200, placeholder: 'defaults to the dataset name',
    oninput: () => { nameInput.dataset.auto = '0'; },
  });
  const holdout = h('input', {
    id: 'holdout-every', name: 'holdout_every', type: 'number', min: 0, step: 1, inputmode: 'numeric',
    placeholder: '8 for 16+ views, else 0', 'aria-describedby': 'holdout-help',
  });
  const maxSide = h('input', {
    id: 'max-image-side', name: 'max_image_side', type: 'number', min: 8, step: 1, inputmode: 'numeric',
    placeholder: 'server default', 'aria-describedby': 'max-side-help',
  });
  const textureSize = h('select', { id: 'texture-size', name: 'texture_size' },
    h('option', { value: '', selected: true }, 'server default'),
    TEXTURE_SIZES.map((v) => h('option', { value: String(v) }, `${v} × ${v}`)));
  const maxFaces = h('input', {
    id: 'max-faces', name: 'max_faces', type: 'number', min: MAX_FACES_RANGE[0], max: MAX_FACES_RANGE[1], step: 1,
    inputmode: 'numeric', placeholder: 'server default', 'aria-describedby': 'faces-help',
  });
  const upAxis = h('select', { id: 'up-axis-input', name: 'up_axis', 'aria-describedby': 'up-axis-help' },
    UP_AXES.map((v) => h('option', { value: v, selected: v === 'auto' }, v === 'auto' ? 'auto (from the cameras)' : `${v} up`)));
  const progress = h('progress', { id: 'upload-progress', max: 100, value: 0, hidden: true, 'aria-label': 'Upload progress' });
  const progressText = h('span', { id: 'upload-progress-text', class: 'small muted', 'aria-live': 'polite' });
  const errorsEl = h('div', { id: 'upload-errors', role: 'alert', hidden: true, class: 'errors-box' });
  const submit = h('button', { type: 'submit', class: 'btn primary', id: 'upload-submit' }, 'Upload and start');

  async function zipFolder(items) {
    const { root: top, items: norm } = normalisePaths(items);
    if (!norm.length) {
      chosen.textContent = 'That folder is empty.';
      return;
    }
    chosen.textContent = `Zipping ${norm.length} files…`;
    try {
      const blob = await zipFiles(norm, (i, n) => {
        if (i % 20 === 0 || i === n) chosen.textContent = `Zipping ${i}/${n} files…`;
      });
      setDataset({ blob, name: `${top || 'dataset'}.zip`, nFiles: norm.length });
    } catch (e) {
      chosen.textContent = `Could not zip the folder: ${e.message}`;
    }
  }

  function setDataset(d) {
    dataset = d;
    if (!nameInput.value || nameInput.dataset.auto === '1') {
      nameInput.value = d.name.replace(/\.zip$/i, '');
      nameInput.dataset.auto = '1';
    }
    chosen.textContent = `Dataset: ${d.name} (${fmtBytes(d.blob.size)}${d.nFiles ? `, ${d.nFiles} files zipped here` : ''})`;
    errorsEl.hidden = true;
  }

  function showErrors(err) {
    const list = err.problems || validationErrors(err.body);
    const optionsRejected = !!err.problems || err.body?.code === 'invalid_config';
    clear(errorsEl);
    errorsEl.append(h('h2', { class: 'h3' }, optionsRejected ? 'The job options were rejected'
      : err.status === 422 || err.status === 400 || list.length ? 'The dataset was rejected' : 'Upload failed'));
    errorsEl.append(h('p', {}, list.length > 1 ? `${list.length} problems were found:` : (list.length ? 'Problem found:' : err.message)));
    if (list.length) {
      const byFile = new Map();
      for (const e of list) {
        const k = e.file || '(dataset)';
        if (!byFile.has(k)) byFile.set(k, []);
        byFile.get(k).push(e);
      }
      errorsEl.append(h('ul', { class: 'error-list' },
        [...byFile.entries()].map(([file, errs]) => h('li', { class: 'error-item', dataset: { file } },
          h('code', { class: 'error-file' }, file),
          h('ul', {}, errs.map((e) => h('li', {},
            e.message,
            e.view !== null && e.view !== undefined ? h('span', { class: 'muted' }, ` (view ${e.view})`) : null,
            e.code ? [' ', h('span', { class: 'chip small' }, e.code)] : null)))))));
    }
    errorsEl.hidden = false;
  }

  const form = h('form', {
    class: 'card', id: 'upload-form', 'aria-labelledby': 'upload-title',
    onsubmit: async (e) => {
      e.preventDefault();
      if (busy) return;
      const opts = jobOptions({
        holdoutEvery: holdout.value, maxImageSide: maxSide.value, textureSize: textureSize.value, maxFaces: maxFaces.value,
        upAxis: upAxis.value,
      });
      if (opts.problems.length) {
        showErrors({ problems: opts.problems, message: 'Check the job options.' });
        return;
      }
      if (!dataset) {
        chosen.textContent = 'Choose a zip or drop a folder first.';
        drop.focus();
        return;
      }
      busy = true;
      submit.disabled = true;
      errorsEl.hidden = true;
      progress.hidden = false;
      progress.value = 0;
      const minutes = Number(budget.value);
      const config = { preset: preset.value, ...opts.options };
      if (nameInput.value.trim()) config.name = nameInput.value.trim().slice(0, 200);
      if (minutes > 0) config.time_budget_s = Math.round(minutes * 60);
      try {
        const job = await createJob(dataset.blob, config, (loaded, total) => {
          progress.value = Math.round((100 * loaded) / total);
          progressText.textContent = `Uploading ${fmtBytes(loaded)} / ${fmtBytes(total)}`;
        }, dataset.name);
        progress.value = 100;
        progressText.textContent = 'Uploaded.';
        const id = job?.id ?? job?.job_id;
        toast(`Job ${id ?? ''} created`);
        sessionStorage.setItem('nepf.newJob', String(id ?? ''));
        location.hash = '#/jobs';
      } catch (err) {
        progress.hidden = true;
        progressText.textContent = '';
        showErrors(err);
      } finally {
        busy = false;
        submit.disabled = false;
      }
    },
  },
  h('h1', { id: 'upload-title' }, 'New job'),
  h('fieldset', {},
    h('legend', {}, 'Dataset'),
    drop,
    h('div', { class: 'row wrap' },
      h('div', { class: 'field' }, h('label', { for: 'zip-input' }, 'Zip file'), fileInput),
      h('div', { class: 'field' }, h('label', { for: 'dir-input' }, 'Or a folder'), dirInput)),
    chosen),
  h('fieldset', {},
    h('legend', {}, 'Training'),
    h('div', { class: 'row wrap' },
      h('div', { class: 'field' }, h('label', { for: 'job-name' }, 'Job name'), nameInput),
      h('div', { class: 'field' }, h('label', { for: 'preset' }, 'Preset'), preset),
      h('div', { class: 'field' }, h('label', { for: 'budget' }, 'Time budget (minutes)'), budget,
        h('span', { id: 'budget-help', class: 'small muted' }, '0 = no limit; the schedule is compressed to fit.')))),
  h('fieldset', {},
    h('legend', {}, 'Options (empty: the default)'),
    h('div', { class: 'row wrap' },
      h('div', { class: 'field' }, h('label', { for: 'holdout-every' }, 'Held-out views: every N-th'), holdout,
        h('span', { id: 'holdout-help', class: 'small muted' },
          'Views 0, N, 2N, … are kept out of training and scored as it runs (the error-against-time chart); '
          + 'they cost that many training views. 0 = train on all; at most half the view count.')),
      h('div', { class: 'field' }, h('label', { for: 'max-image-side' }, 'Working resolution (px, long side)'), maxSide,
        h('span', { id: 'max-side-help', class: 'small muted' },
          'Larger images are resampled down to this at load; up to the server\'s ceiling. Smaller trains faster.')),
      h('div', { class: 'field' }, h('label', { for: 'texture-size' }, 'Texture size'), textureSize),
      h('div', { class: 'field' }, h('label', { for: 'max-faces' }, 'Mesh faces (at most)'), maxFaces,
        h('span', { id: 'faces-help', class: 'small muted' }, `${MAX_FACES_RANGE[0]} to ${MAX_FACES_RANGE[1]}.`)),
      h('div', { class: 'field' }, h('label', { for: 'up-axis-input' }, 'Up axis of the input'), upAxis,
        h('span', { id: 'up-axis-help', class: 'small muted' },
          'The world axis that points up; the GLB turns it into glTF\'s +Y. Auto: the mean of the cameras\' up vectors.')))),
  h('div', { class: 'actions' }, submit, progress, progressText),
  errorsEl);

  root.append(h('section', { class: 'page' }, form));
  return () => {};
}
