// "Relit by the server": the export's three canonical relit previews beside the 3D view
// (previews/relit_canonical_{0,1,2}.png and previews/relit_canonical.json, written by
// nepf_core/relight/previews.py: point lights at 3 object radii, elevation 45°, azimuths
// 0 / 120 / 240° about the up axis, one fixed camera, the run's BSDF with shadows traced
// through the SDF). Each image has a button that puts the viewer's light and camera where the
// server's were, with no environment light, so the server's render and three.js' render of
// the GLB can be compared side by side.
//
// DOM state (read by tests): the strip `#relit-previews` has data-state (none | loading |
// loaded | error) and data-applied (index of the preview last put on the viewer); each
// `figure.relit-preview` has data-index, data-azimuth, data-light-world ("x y z", the input's
// world frame, as the record gives it) and data-camera-world. The viewer maps both into the GLB's
// +Y-up frame with the manifest's rotation (AssetViewer.setFrame / worldToView).
import { api } from '../api.js';
import { clear, h } from '../util.js';

function previewLabel(azimuth, elevation) {
  const deg = (v) => (Number.isFinite(Number(v)) ? `${Math.round(Number(v))}°` : '?');
  return `azimuth ${deg(azimuth)}` + (elevation === undefined ? '' : `, elevation ${deg(elevation)}`);
}

/** Put one preview's light (and the record's camera) on the viewer, with no environment light. */
function applyPreview(viewer, light, camera) {
  viewer.setLightWorld(light.position_world, light.intensity_rgb);
  if (camera) viewer.setCameraWorld(camera);
  viewer.set({ env: 'none', exposure: 1 });
}

/**
 * Fill `strip` (a hidden <section>) with the relit previews of job `id`.
 * @param {{viewer: import('../viewer3d.js').AssetViewer, isStopped: () => boolean, onApplied?: (k: number) => void}} opts
 */
export async function loadRelitPreviews(strip, id, { viewer, isStopped, onApplied }) {
  strip.hidden = false;
  strip.dataset.state = 'loading';
  let rec;
  try {
    rec = await api.artifactJson(id, 'previews/relit_canonical.json');
  } catch (e) {
    console.warn('relit_canonical.json:', e.message);
    strip.dataset.state = 'error';
    clear(strip).append(h('p', { class: 'small muted' }, 'The relit previews could not be read.'));
    return;
  }
  if (isStopped()) return;
  const images = Array.isArray(rec?.images) ? rec.images : [];
  const lights = Array.isArray(rec?.lights) ? rec.lights : [];
  const azimuths = rec?.canonical?.azimuths_deg || [];
  const n = Math.min(images.length, lights.length);
  const figures = [];
  for (let k = 0; k < n; k++) {
    const light = lights[k];
    const label = previewLabel(azimuths[k], rec?.canonical?.elevation_deg);
    const img = h('img', { class: 'relit-img', alt: `Server relighting under light ${k + 1} (${label})`, width: 128, height: 128 });
    api.artifactBlob(id, `previews/${images[k]}`)
      .then((b) => {
        if (!isStopped()) img.src = URL.createObjectURL(b);
      })
      .catch((e) => console.warn(`previews/${images[k]}:`, e.message));
    const apply = h('button', {
      type: 'button', class: 'btn small', dataset: { relitApply: String(k) },
      'aria-label': `Put the 3D view's light and camera where the server's were for light ${k + 1} (${label})`,
      onclick: () => {
        applyPreview(viewer, light, rec.camera);
        strip.dataset.applied = String(k);
        onApplied?.(k);
      },
    }, 'Use this light');
    figures.push(h('figure', {
      class: 'relit-preview',
      dataset: {
        index: String(k), azimuth: String(azimuths[k] ?? ''),
        lightWorld: (light.position_world || []).join(' '),
        cameraWorld: (rec.camera?.position_world || []).join(' '),
      },
    }, img, h('figcaption', { class: 'small' }, label), apply));
  }
  clear(strip).append(
    h('h3', { id: 'relit-title' }, 'Relit by the server'),
    h('p', { class: 'small muted' }, `The exported asset rendered by NePF (BSDF "${rec?.bsdf ?? '?'}", shadows traced `
      + 'through the SDF) under three point lights. "Use this light" puts the 3D view\'s light and camera there, '
      + 'with no environment light, to compare with three.js.'),
    h('div', { class: 'relit-row' }, figures));
  strip.dataset.state = n ? 'loaded' : 'none';
}
