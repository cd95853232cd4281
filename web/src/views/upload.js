// Upload: pick a zip, or drag a folder in (zipped here, in the browser, with fflate);
// choose a preset and a time budget; show upload progress and per-file validation errors.
import { zip as fflateZip } from 'fflate';
import { api, createJob, validationErrors } from '../api.js';
import { h, clear, fmtBytes, toast } from '../util.js';

/**
 * The job options' limits, read from the server's JSON schema of its JobConfig model
 * (GET /schemas/job-config: the model the API validates with, this server's ceiling of
 * max_image_side filled in). A limit the schema does not give is not checked here (the API
 * checks every option again).
 */
export function limitsFromSchema(schema) {
  const props = schema?.properties || {};
  const field = (k) => {
    const p = props[k] || {};
    const branch = (p.anyOf || [p]).find((x) => x.type && x.type !== 'null') || {};
    return { ...p, ...branch };
  };
  const faces = field('max_faces');
  const side = field('max_image_side');
  return {
    presets: field('preset').enum || null,
    defaultPreset: props.preset?.default ?? null,
    maxNameLength: field('name').maxLength ?? null,
    maxBudgetS: field('time_budget_s').maximum ?? null,
    minImageSide: side.minimum ?? null,
    maxImageSide: side.maximum ?? null,
    textureSizes: field('texture_size').enum || null,
    maxFacesRange: faces.minimum !== undefined && faces.maximum !== undefined ? [faces.minimum, faces.maximum] : null,
    upAxes: (props.up_axis?.enum || []).filter((v) => typeof v === 'string'),
  };
}

function intOption(out, { label, text, ok, allowed, key }) {
  const t = String(text).trim();
  if (!t) return;
  const v = Number(t);
  if (!Number.isInteger(v) || !ok(v)) out.problems.push({ code: 'invalid_config', file: label, view: null, message: `must be ${allowed} (got ${t})` });
  else out.options[key] = v;
}

function sideRule(lo, hi) {
  if (lo === null) return [() => true, 'an integer'];
  if (hi === null) return [(v) => v >= lo, `an integer ≥ ${lo} pixels`];
  return [(v) => v >= lo && v <= hi, `an integer from ${lo} to ${hi} pixels`];
}

/**
 * The optional job options from the form's strings, checked against `limits`
 * (limitsFromSchema); empty means "the server's default".
 * Returns {options, problems}: problems name the field and the allowed values.
 */
export function jobOptions({ holdoutEvery = '', maxImageSide = '', textureSize = '', maxFaces = '', upAxis = '' }, limits = {}) {
  const out = { options: {}, problems: [] };
  intOption(out, { label: 'Held-out views', text: holdoutEvery, ok: (v) => v === 0 || v >= 2,
    allowed: '0 (train on all views) or an integer ≥ 2', key: 'holdout_every' });
  const [sideOk, sideText] = sideRule(limits.minImageSide ?? null, limits.maxImageSide ?? null);
  intOption(out, { label: 'Working resolution', text: maxImageSide, ok: sideOk, allowed: sideText, key: 'max_image_side' });
  const sizes = limits.textureSizes;
  intOption(out, { label: 'Texture size', text: textureSize, ok: (v) => !sizes || sizes.includes(v),
    allowed: sizes ? `one of ${sizes.join(', ')}` : 'an integer', key: 'texture_size' });
  const [lo, hi] = limits.maxFacesRange || [-Infinity, Infinity];
  intOption(out, { label: 'Mesh faces', text: maxFaces, ok: (v) => v >= lo && v <= hi,
    allowed: limits.maxFacesRange ? `an integer from ${lo} to ${hi}` : 'an integer', key: 'max_faces' });
  const up = String(upAxis).trim().toLowerCase();
  const axes = limits.upAxes?.length ? limits.upAxes : null;
  if (up && up !== 'auto') {
    if (!axes || axes.includes(up)) out.options.up_axis = up;
    else out.problems.push({ code: 'invalid_config', file: 'Up axis', view: null, message: `must be one of ${axes.join(', ')} (got ${up})` });
  }
  return out;
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

/** The dataset picker: a zip input, a folder input and a drop zone; `onPick({blob, name, nFiles?})`. */
function datasetPicker(onPick, chosen) {
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
      onPick({ blob, name: `${top || 'dataset'}.zip`, nFiles: norm.length });
    } catch (e) {
      chosen.textContent = `Could not zip the folder: ${e.message}`;
    }
  }
  const fileInput = h('input', {
    type: 'file', id: 'zip-input', accept: '.zip,application/zip', 'aria-describedby': 'drop-help',
    onchange: () => {
      const f = fileInput.files?.[0];
      if (f) onPick({ blob: f, name: f.name });
    },
  });
  const dirInput = h('input', {
    type: 'file', id: 'dir-input', webkitdirectory: true, multiple: true,
    onchange: async () => {
      const files = [...(dirInput.files || [])];
      if (files.length) await zipFolder(files.map((f) => ({ path: f.webkitRelativePath || f.name, file: f })));
    },
  });
  const drop = dropZone(fileInput, onPick, zipFolder);
  return { fileInput, dirInput, drop };
}

async function onDrop(e, onPick, zipFolder) {
  const items = [...(e.dataTransfer?.items || [])];
  const entries = items.map((it) => it.webkitGetAsEntry?.()).filter(Boolean);
  if (entries.length === 1 && entries[0].isFile && /\.zip$/i.test(entries[0].name)) {
    const f = e.dataTransfer.files[0];
    onPick({ blob: f, name: f.name });
    return;
  }
  if (entries.length) {
    const files = [];
    for (const en of entries) files.push(...(await walkEntry(en)));
    await zipFolder(files);
  } else if (e.dataTransfer?.files?.length) {
    const f = e.dataTransfer.files[0];
    onPick({ blob: f, name: f.name });
  }
}

function dropZone(fileInput, onPick, zipFolder) {
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
      await onDrop(e, onPick, zipFolder);
    },
  },
  h('p', { class: 'drop-title' }, 'Drop a dataset folder (or a .zip) here'),
  h('p', { id: 'drop-help', class: 'small muted' },
    'DTU (cameras.npz, image/, mask/), NeRF-synthetic / Blender (transforms_train.json), nerfstudio or instant-ngp (transforms.json), or COLMAP (sparse/0/ + images/). A folder is zipped in your browser.'));
  return drop;
}

/** The training and option inputs; `applyLimits(limits)` sets their bounds and choices from the schema. */
function optionInputs() {
  const f = {
    preset: h('select', { id: 'preset', name: 'preset' },
      PRESETS.map((p) => h('option', { value: p.value, selected: p.value === 'fast' }, p.label))),
    budget: h('input', {
      id: 'budget', name: 'budget', type: 'number', min: 0, step: 1, value: 0, inputmode: 'numeric',
      'aria-describedby': 'budget-help',
    }),
    name: h('input', { id: 'job-name', name: 'name', type: 'text', placeholder: 'defaults to the dataset name' }),
    holdout: h('input', {
      id: 'holdout-every', name: 'holdout_every', type: 'number', min: 0, step: 1, inputmode: 'numeric',
      placeholder: '8 for 16+ views, else 0', 'aria-describedby': 'holdout-help',
    }),
    maxSide: h('input', {
      id: 'max-image-side', name: 'max_image_side', type: 'number', step: 1, inputmode: 'numeric',
      placeholder: 'server default', 'aria-describedby': 'max-side-help',
    }),
    textureSize: h('select', { id: 'texture-size', name: 'texture_size' }, h('option', { value: '', selected: true }, 'server default')),
    maxFaces: h('input', {
      id: 'max-faces', name: 'max_faces', type: 'number', step: 1, inputmode: 'numeric', placeholder: 'server default',
      'aria-describedby': 'faces-help',
    }),
    facesHelp: h('span', { id: 'faces-help', class: 'small muted' }),
    upAxis: h('select', { id: 'up-axis-input', name: 'up_axis', 'aria-describedby': 'up-axis-help' },
      h('option', { value: 'auto', selected: true }, 'auto (from the cameras)')),
  };
  f.name.addEventListener('input', () => { f.name.dataset.auto = '0'; });
  f.applyLimits = (l) => {
    if (l.defaultPreset) f.preset.value = l.defaultPreset;
    if (l.maxBudgetS) f.budget.max = String(Math.floor(l.maxBudgetS / 60));
    if (l.maxNameLength) f.name.maxLength = l.maxNameLength;
    if (l.minImageSide !== null) f.maxSide.min = String(l.minImageSide);
    if (l.maxImageSide !== null) f.maxSide.max = String(l.maxImageSide);
    for (const v of l.textureSizes || []) f.textureSize.append(h('option', { value: String(v) }, `${v} × ${v}`));
    if (l.maxFacesRange) {
      [f.maxFaces.min, f.maxFaces.max] = l.maxFacesRange.map(String);
      f.facesHelp.textContent = `${l.maxFacesRange[0]} to ${l.maxFacesRange[1]}.`;
    }
    for (const v of l.upAxes.filter((a) => a !== 'auto')) f.upAxis.append(h('option', { value: v }, `${v} up`));
  };
  return f;
}

const field = (id, label, input, help) => h('div', { class: 'field' }, h('label', { for: id }, label), input, help || null);
const helpText = (id, text) => h('span', { id, class: 'small muted' }, text);

function optionFieldsets(f) {
  return [
    h('fieldset', {},
      h('legend', {}, 'Training'),
      h('div', { class: 'row wrap' },
        field('job-name', 'Job name', f.name),
        field('preset', 'Preset', f.preset),
        field('budget', 'Time budget (minutes)', f.budget, helpText('budget-help', '0 = no limit; the schedule is compressed to fit.')))),
    h('fieldset', {},
      h('legend', {}, 'Options (empty: the default)'),
      h('div', { class: 'row wrap' },
        field('holdout-every', 'Held-out views: every N-th', f.holdout, helpText('holdout-help',
          'Views 0, N, 2N, … are kept out of training and scored as it runs (the error-against-time chart); '
          + 'they cost that many training views. 0 = train on all; at most half the view count.')),
        field('max-image-side', 'Working resolution (px, long side)', f.maxSide, helpText('max-side-help',
          'Larger images are resampled down to this at load; up to the server\'s ceiling. Smaller trains faster.')),
        field('texture-size', 'Texture size', f.textureSize),
        field('max-faces', 'Mesh faces (at most)', f.maxFaces, f.facesHelp),
        field('up-axis-input', 'Up axis of the input', f.upAxis, helpText('up-axis-help',
          'The world axis that points up; the GLB turns it into glTF\'s +Y. Auto: the mean of the cameras\' up vectors.')))),
  ];
}

/** Fill `box` with a rejected upload's problems, grouped by file. */
function showErrors(box, err) {
  const list = err.problems || validationErrors(err.body);
  const optionsRejected = !!err.problems || err.body?.code === 'invalid_config';
  clear(box);
  box.append(h('h2', { class: 'h3' }, optionsRejected ? 'The job options were rejected'
    : err.status === 422 || err.status === 400 || list.length ? 'The dataset was rejected' : 'Upload failed'));
  box.append(h('p', {}, list.length > 1 ? `${list.length} problems were found:` : (list.length ? 'Problem found:' : err.message)));
  if (list.length) {
    const byFile = new Map();
    for (const e of list) {
      const k = e.file || '(dataset)';
      if (!byFile.has(k)) byFile.set(k, []);
      byFile.get(k).push(e);
    }
    box.append(h('ul', { class: 'error-list' },
      [...byFile.entries()].map(([file, errs]) => h('li', { class: 'error-item', dataset: { file } },
        h('code', { class: 'error-file' }, file),
        h('ul', {}, errs.map((e) => h('li', {},
          e.message,
          e.view !== null && e.view !== undefined ? h('span', { class: 'muted' }, ` (view ${e.view})`) : null,
          e.code ? [' ', h('span', { class: 'chip small' }, e.code)] : null)))))));
  }
  box.hidden = false;
}

/** The config JSON the form asks for (preset, name, budget and the checked options). */
function configFrom(f, options) {
  const config = { preset: f.preset.value, ...options };
  if (f.name.value.trim()) config.name = f.name.value.trim().slice(0, Number(f.name.maxLength) > 0 ? f.name.maxLength : undefined);
  const minutes = Number(f.budget.value);
  if (minutes > 0) config.time_budget_s = Math.round(minutes * 60);
  return config;
}

export function renderUpload(root) {
  const st = { dataset: null, busy: false };
  const f = optionInputs();
  const limits = api.jobConfigSchema().then((schema) => {
    const l = limitsFromSchema(schema);
    f.applyLimits(l);
    return l;
  }).catch(() => null); // the API checks the options anyway
  const chosen = h('p', { id: 'dataset-chosen', class: 'small', 'aria-live': 'polite' }, 'No dataset chosen.');
  const errorsEl = h('div', { id: 'upload-errors', role: 'alert', hidden: true, class: 'errors-box' });
  const picker = datasetPicker((d) => {
    st.dataset = d;
    if (!f.name.value || f.name.dataset.auto === '1') {
      f.name.value = d.name.replace(/\.zip$/i, '');
      f.name.dataset.auto = '1';
    }
    chosen.textContent = `Dataset: ${d.name} (${fmtBytes(d.blob.size)}${d.nFiles ? `, ${d.nFiles} files zipped here` : ''})`;
    errorsEl.hidden = true;
  }, chosen);
  const progress = h('progress', { id: 'upload-progress', max: 100, value: 0, hidden: true, 'aria-label': 'Upload progress' });
  const progressText = h('span', { id: 'upload-progress-text', class: 'small muted', 'aria-live': 'polite' });
  const submit = h('button', { type: 'submit', class: 'btn primary', id: 'upload-submit' }, 'Upload and start');
  const ui = { f, st, limits, chosen, errorsEl, picker, progress, progressText, submit };

  const form = h('form', { class: 'card', id: 'upload-form', 'aria-labelledby': 'upload-title', onsubmit: (e) => onSubmit(e, ui) },
    h('h1', { id: 'upload-title' }, 'New job'),
    h('fieldset', {},
      h('legend', {}, 'Dataset'),
      picker.drop,
      h('div', { class: 'row wrap' },
        field('zip-input', 'Zip file', picker.fileInput),
        field('dir-input', 'Or a folder', picker.dirInput)),
      chosen),
    ...optionFieldsets(f),
    h('div', { class: 'actions' }, submit, progress, progressText),
    errorsEl);
  root.append(h('section', { class: 'page' }, form));
  return () => {};
}

async function onSubmit(e, ui) {
  e.preventDefault();
  const { f, st } = ui;
  if (st.busy) return;
  const opts = jobOptions({
    holdoutEvery: f.holdout.value, maxImageSide: f.maxSide.value, textureSize: f.textureSize.value,
    maxFaces: f.maxFaces.value, upAxis: f.upAxis.value,
  }, (await ui.limits) || {});
  if (opts.problems.length) {
    showErrors(ui.errorsEl, { problems: opts.problems, message: 'Check the job options.' });
    return;
  }
  if (!st.dataset) {
    ui.chosen.textContent = 'Choose a zip or drop a folder first.';
    ui.picker.drop.focus();
    return;
  }
  st.busy = true;
  ui.submit.disabled = true;
  ui.errorsEl.hidden = true;
  ui.progress.hidden = false;
  ui.progress.value = 0;
  try {
    const job = await createJob(st.dataset.blob, configFrom(f, opts.options), (loaded, total) => {
      ui.progress.value = Math.round((100 * loaded) / total);
      ui.progressText.textContent = `Uploading ${fmtBytes(loaded)} / ${fmtBytes(total)}`;
    }, st.dataset.name);
    ui.progress.value = 100;
    ui.progressText.textContent = 'Uploaded.';
    const id = job?.id ?? job?.job_id;
    toast(`Job ${id ?? ''} created`);
    sessionStorage.setItem('nepf.newJob', String(id ?? ''));
    location.hash = '#/jobs';
  } catch (err) {
    ui.progress.hidden = true;
    ui.progressText.textContent = '';
    showErrors(ui.errorsEl, err);
  } finally {
    st.busy = false;
    ui.submit.disabled = false;
  }
}
