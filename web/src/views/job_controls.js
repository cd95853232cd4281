// The controls beside the 3D asset on the job page: view (channel, wireframe, up axis), relighting,
// light field, material editing. `buildControls(host, viewer)` fills `host` and returns the handle
// the page keeps: `sync()` (sliders follow the viewer's state), `lightFieldReady(n)`,
// `afterRelitApplied()`.
import { CHANNELS, ENVIRONMENTS, COLORMAP_CSS, UP_AXES } from '../viewer3d.js';
import { h, clear, slider } from '../util.js';

/** The "View" fieldset: channel radio group, wireframe, reset view, up axis. */
function viewGroup(viewer, sync) {
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
        sync();
      },
    }, Object.entries(UP_AXES).map(([k, v]) => h('option', { value: k, selected: k === st.up }, v.label))));
  const resetView = h('button', { type: 'button', class: 'btn small', id: 'reset-view', onclick: () => viewer.frameCamera() }, 'Reset view');
  return h('fieldset', { id: 'view-group' }, h('legend', {}, 'View'), chGroup, h('div', { class: 'row wrap' }, wire, resetView), upSel);
}

/** The "Relighting" fieldset; its sliders are registered in `ctl` by state key. */
function lightGroup(viewer, ctl, sync) {
  const st = viewer.state;
  const mk = (key, label, min, max, step, fmt) => (ctl[key] = slider({
    id: `light-${key}`, label, min, max, step, value: st[key], format: fmt,
    onInput: (v) => viewer.set({ [key]: v }),
  }));
  const env = h('select', {
    id: 'env-preset',
    onchange: (e) => viewer.set({ env: e.target.value }),
  }, ENVIRONMENTS.map((o) => h('option', { value: o.value, selected: o.value === st.env }, o.label)));
  return h('fieldset', { id: 'light-group' },
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
        sync();
      },
    }, 'Reset light'));
}

/** The "Light field" fieldset, disabled until `ready(n)` says how many samples there are. */
function lightFieldGroup(viewer) {
  const legend = h('div', { class: 'legend', id: 'lightfield-legend', hidden: true });
  const toggle = h('input', {
    type: 'checkbox', id: 'lightfield-toggle', disabled: true,
    onchange: (e) => {
      viewer.set({ lightField: e.target.checked });
      legend.hidden = !e.target.checked;
    },
  });
  const density = slider({
    id: 'lightfield-density', label: 'Glyph density', min: 0.02, max: 1, step: 0.02, value: viewer.state.density,
    format: (v) => `${Math.round(v * 100)}%`,
    onInput: (v) => viewer.set({ density: v }),
  });
  density.input.disabled = true;
  const status = h('p', { class: 'small muted', id: 'lightfield-status' }, 'Loading light_field.json…');
  const el = h('fieldset', { id: 'lightfield-group' },
    h('legend', {}, 'Light field'),
    h('label', { class: 'check' }, toggle, ' Show light glyphs'),
    density.wrap, legend, status);
  const ready = (n) => {
    if (!(n > 0)) {
      status.textContent = 'No light field in the results.';
      return;
    }
    toggle.disabled = false;
    density.input.disabled = false;
    status.textContent = `${n} surface samples. Arrows point the way the light travels; the tip touches the surface.`;
    const { min, max } = viewer.lf;
    clear(legend).append(
      h('span', { class: 'small' }, 'Intensity'),
      h('div', { class: 'legend-bar', style: { background: COLORMAP_CSS }, role: 'img', 'aria-label': `Colour scale from ${min.toPrecision(3)} to ${max.toPrecision(3)}` }),
      h('div', { class: 'legend-ticks small' }, h('span', {}, min.toPrecision(3)), h('span', {}, max.toPrecision(3))));
  };
  return { el, ready };
}

/** The "Material editing" fieldset (roughness / metallic scale, albedo tint). */
function materialGroup(viewer, ctl, sync) {
  const st = viewer.state;
  const scale = (key, id, label) => (ctl[key] = slider({
    id, label, min: 0, max: 2, step: 0.05, value: st[key],
    format: (v) => `${Number(v).toFixed(2)}×`, onInput: (v) => viewer.set({ [key]: v }),
  })).wrap;
  const tint = h('input', {
    type: 'color', id: 'albedo-tint', value: st.tint,
    oninput: (e) => viewer.set({ tint: e.target.value }),
  });
  return h('fieldset', { id: 'material-group' },
    h('legend', {}, 'Material editing'),
    scale('roughnessScale', 'roughness-scale', 'Roughness scale'),
    scale('metallicScale', 'metallic-scale', 'Metallic scale'),
    h('div', { class: 'field' }, h('label', { for: 'albedo-tint' }, 'Albedo tint'), tint),
    h('button', {
      type: 'button', class: 'btn small', id: 'material-reset',
      onclick: () => {
        viewer.set({ roughnessScale: 1, metallicScale: 1, tint: '#ffffff' });
        tint.value = '#ffffff';
        sync();
      },
    }, 'Reset material'));
}

/** Fill `host` with every control group of `viewer`; returns {sync, lightFieldReady, afterRelitApplied}. */
export function buildControls(host, viewer) {
  const ctl = {};
  const sync = () => {
    for (const [k, c] of Object.entries(ctl)) c.set(viewer.state[k]);
  };
  const lf = lightFieldGroup(viewer);
  clear(host).append(viewGroup(viewer, sync), lightGroup(viewer, ctl, sync), lf.el, materialGroup(viewer, ctl, sync));
  host.hidden = false;
  /** After a relit preview was put on the viewer: the selects and sliders show its state. */
  const afterRelitApplied = () => {
    const env = host.querySelector('#env-preset');
    if (env) env.value = viewer.state.env;
    const up = host.querySelector('#up-axis');
    if (up) up.value = viewer.state.up;
    sync();
  };
  return { sync, lightFieldReady: lf.ready, afterRelitApplied };
}
