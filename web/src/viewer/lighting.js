// The interactive point light: where a light record puts the sliders (pure, tested in Node).
import { anglesOf } from './frame.js';

/** The light distance slider's range, in asset radii. */
export const LIGHT_DIST_RANGE = [1.2, 20];

/**
 * The slider state and base radiant intensity for a parsed light ({position?, direction?,
 * intensity?, atPoint?}: parseLights, or a relit preview's record) about an asset at `center`
 * with radius `radius`, up axis `up`. `current` holds the state and base intensity kept where the
 * record says nothing. Returns {lightAz, lightEl, lightDist, lightIntensity, baseLightIntensity}.
 *
 * A light farther than the slider's range moves onto it and keeps the irradiance it gave the
 * asset (intensity x (d_slider / d)^2). three.js' point light: irradiance = I / d^2, Lambert =
 * albedo / pi, the same model as NePF's L = f * I * max(n.l, 0) with I falling off as 1/d^2. A
 * directional fit (`atPoint`: the intensity arriving at the surface) becomes I = atPoint * d^2.
 */
export function lightSliders(l, { center, radius, up, current }) {
  const out = { ...current, lightIntensity: 1 };
  let dir = null;
  let dist = null;
  if (l.position) {
    const d = l.position.clone().sub(center);
    dist = d.length() / radius;
    dir = d.normalize();
  } else if (l.direction) {
    dir = l.direction.clone();
  }
  if (dir) {
    const { az, el } = anglesOf(dir, up);
    out.lightAz = az;
    out.lightEl = el;
  }
  let rescale = 1;
  if (dist && Number.isFinite(dist)) {
    out.lightDist = Math.min(LIGHT_DIST_RANGE[1], Math.max(LIGHT_DIST_RANGE[0], dist));
    rescale = (out.lightDist / dist) ** 2;
  }
  if (l.intensity && l.intensity > 0) out.baseLightIntensity = l.intensity * rescale;
  else if (l.atPoint && l.atPoint > 0) {
    const d = out.lightDist * radius;
    out.baseLightIntensity = l.atPoint * d * d;
  }
  return out;
}
