// Parsers of the export's light records (pure, tested in Node): light_field.json and lights.json.
import { vec3 } from './frame.js';

/**
 * Parse light_field.json into {positions, directions, intensity, normals} (flat arrays).
 * Accepts column form (`points`/`positions`, `directions`/`light_dirs`, `intensity`, `normals`)
 * or a list of records (`p`/`position`/`point`, `l`/`direction`/`light_dir`, `intensity`/`I`).
 */
export function parseLightField(lf) {
  if (!lf) return null;
  const pick = (o, names) => {
    for (const n of names) if (o && o[n] !== undefined) return o[n];
    return undefined;
  };
  const P_NAMES = ['points', 'positions', 'position', 'p', 'x', 'xyz', 'point'];
  const L_NAMES = ['directions', 'light_dirs', 'light_dir', 'light_directions', 'dirs', 'direction', 'l', 'light_direction'];
  const I_NAMES = ['intensity', 'intensities', 'I', 'i', 'light_intensity'];
  const N_NAMES = ['normals', 'normal', 'n'];
  const src = Array.isArray(lf) ? lf : (lf.samples || lf.records || lf.items || lf.data || lf);
  const out = { positions: [], directions: [], intensity: [], normals: [] };
  if (Array.isArray(src)) {
    for (const r of src) {
      const p = vec3(pick(r, P_NAMES));
      const l = vec3(pick(r, L_NAMES));
      if (!p || !l) continue;
      out.positions.push(p);
      out.directions.push(l.normalize());
      out.intensity.push(Number(pick(r, I_NAMES) ?? 1));
      out.normals.push(vec3(pick(r, N_NAMES)));
    }
  } else if (src && typeof src === 'object') {
    const P = pick(src, P_NAMES);
    const L = pick(src, L_NAMES);
    const I = pick(src, I_NAMES);
    const N = pick(src, N_NAMES);
    if (!Array.isArray(P) || !Array.isArray(L)) return null;
    const flat = (A, i) => (Array.isArray(A[0]) || (A[0] && typeof A[0] === 'object') ? vec3(A[i]) : vec3(A.slice(3 * i, 3 * i + 3)));
    const n = Array.isArray(P[0]) || typeof P[0] === 'object' ? P.length : Math.floor(P.length / 3);
    for (let i = 0; i < n; i++) {
      const p = flat(P, i);
      const l = flat(L, i);
      if (!p || !l) continue;
      out.positions.push(p);
      out.directions.push(l.normalize());
      out.intensity.push(Array.isArray(I) ? Number(I[i]) : 1);
      out.normals.push(Array.isArray(N) ? flat(N, i) : null);
    }
  }
  return out.positions.length ? out : null;
}

/**
 * Parse lights.json (nepf_core/export/light_field.py) into
 * {position?: Vector3, direction?: Vector3, intensity?: number, atPoint?: number}.
 * `intensity` is a point light's radiant intensity (inverse-square, world units);
 * `atPoint` is the intensity arriving at the surface (directional fit: mean_intensity).
 * Also accepts `{lights:[...]}`, a list, or a bare `{position, intensity}` object.
 */
export function parseLights(js) {
  if (!js || typeof js !== 'object') return null;
  if (js.point_light !== undefined || js.dominant_direction !== undefined) {
    const pl = js.point_light && typeof js.point_light === 'object' ? js.point_light : null;
    const dir = vec3(js.dominant_direction);
    return {
      type: js.type || (pl ? 'point' : 'directional'),
      position: pl ? vec3(pl.position) : null,
      direction: dir ? dir.normalize() : null,
      intensity: pl && Number.isFinite(Number(pl.intensity)) ? Number(pl.intensity) : null,
      atPoint: Number.isFinite(Number(js.mean_intensity)) ? Number(js.mean_intensity) : null,
      center: vec3(js.object_center),
      radius: Number.isFinite(Number(js.object_radius)) ? Number(js.object_radius) : null,
    };
  }
  let l = js;
  if (Array.isArray(js.lights)) l = js.lights[0];
  else if (Array.isArray(js)) l = js[0];
  if (!l || typeof l !== 'object') return null;
  const position = vec3(l.position ?? l.pos);
  const direction = vec3(l.direction ?? l.dir);
  const intensity = Number.isFinite(Number(l.intensity)) ? Number(l.intensity) : null;
  return { type: position ? 'point' : 'directional', position, direction: direction ? direction.normalize() : null, intensity, atPoint: null };
}
