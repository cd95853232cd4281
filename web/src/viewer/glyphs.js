// Light-field glyphs: one arrow per surface sample of light_field.json, coloured by intensity,
// a density slider showing an even subset. Pure helpers first (tested in Node).
import * as THREE from 'three';
import { mergeGeometries } from 'three/examples/jsm/utils/BufferGeometryUtils.js';

// Perceptual colour map for the light intensity (inferno-like), t in [0, 1].
const CMAP = [
  [0.0, [0.001, 0.0, 0.014]],
  [0.25, [0.341, 0.062, 0.429]],
  [0.5, [0.735, 0.216, 0.330]],
  [0.75, [0.978, 0.557, 0.035]],
  [1.0, [0.988, 0.998, 0.645]],
];
export function colormap(t) {
  t = Math.min(1, Math.max(0, t));
  for (let i = 1; i < CMAP.length; i++) {
    if (t <= CMAP[i][0]) {
      const [t0, c0] = CMAP[i - 1];
      const [t1, c1] = CMAP[i];
      const u = (t - t0) / (t1 - t0);
      return c0.map((c, k) => c + (c1[k] - c) * u);
    }
  }
  return CMAP[CMAP.length - 1][1];
}
export const COLORMAP_CSS = `linear-gradient(to right, ${CMAP.map(([t, c]) => `rgb(${c.map((v) => Math.round(v * 255)).join(',')}) ${t * 100}%`).join(', ')})`;

/** Arrow glyph along +Y, base at y=0 and tip at y=1. */
function arrowGeometry() {
  const shaft = new THREE.CylinderGeometry(0.05, 0.05, 0.65, 6, 1);
  shaft.translate(0, 0.325, 0);
  const head = new THREE.ConeGeometry(0.16, 0.35, 8, 1);
  head.translate(0, 0.825, 0);
  const g = mergeGeometries([shaft.toNonIndexed(), head.toNonIndexed()]);
  g.computeVertexNormals();
  return g;
}

/** Deterministic shuffle (mulberry32) so a density slider shows an even subset. */
export function shuffledIndices(n, seed = 12345) {
  const idx = Array.from({ length: n }, (_, i) => i);
  let s = seed >>> 0;
  const rnd = () => {
    s = (s + 0x6d2b79f5) >>> 0;
    let t = s;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
  for (let i = n - 1; i > 0; i--) {
    const j = Math.floor(rnd() * (i + 1));
    [idx[i], idx[j]] = [idx[j], idx[i]];
  }
  return idx;
}

/** [min, max] of the finite values ([0, 1] when there is none). */
export function intensityRange(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (Number.isFinite(v)) {
      lo = Math.min(lo, v);
      hi = Math.max(hi, v);
    }
  }
  return Number.isFinite(lo) ? [lo, hi] : [0, 1];
}

/**
 * Arrow length for `count` glyphs on an asset of radius `radius`: 0.8 x the mean spacing of the
 * samples on a sphere of that radius, sqrt(4 pi r^2 / count), clamped to [0.025 r, 0.15 r], so a
 * denser field gets smaller arrows instead of a solid carpet.
 */
export function glyphLength(radius, count) {
  const spacing = radius * Math.sqrt((4 * Math.PI) / count);
  return Math.min(0.15 * radius, Math.max(0.025 * radius, 0.8 * spacing));
}

/** How many of `n` glyphs a density in (0, 1] shows (at least one). */
export function glyphCountFor(n, density) {
  return Math.max(1, Math.round(n * density));
}

/** The instanced arrows of a parsed light field ({positions, directions, intensity}). */
export class LightFieldGlyphs {
  constructor(lf, radius) {
    this.lf = lf;
    this.radius = radius;
    const n = lf.positions.length;
    [lf.min, lf.max] = intensityRange(lf.intensity);
    lf.order = shuffledIndices(n);
    this.mesh = new THREE.InstancedMesh(arrowGeometry(), new THREE.MeshBasicMaterial({ toneMapped: false }), n);
    this.mesh.name = 'light-field-glyphs';
    this.mesh.frustumCulled = false;
    const c = new THREE.Color();
    for (let k = 0; k < n; k++) {
      const i = lf.order[k];
      const t = lf.max > lf.min ? (lf.intensity[i] - lf.min) / (lf.max - lf.min) : 1;
      const [r, g, b] = colormap(t);
      c.setRGB(r, g, b, THREE.SRGBColorSpace);
      this.mesh.setColorAt(k, c);
    }
    this.mesh.instanceMatrix.needsUpdate = true;
    if (this.mesh.instanceColor) this.mesh.instanceColor.needsUpdate = true;
    this.laidOut = false;
  }

  /** Show or hide, and lay out the density's share of the glyphs. */
  apply({ lightField, density }) {
    this.mesh.visible = !!lightField;
    const count = glyphCountFor(this.lf.positions.length, density);
    if (count !== this.mesh.count || !this.laidOut) this.layout(count);
  }

  /** Place the first `count` glyphs (of the shuffled order), each arrow's tip on its sample. */
  layout(count) {
    const m = new THREE.Matrix4();
    const q = new THREE.Quaternion();
    const Y = new THREE.Vector3(0, 1, 0);
    const len = glyphLength(this.radius, count);
    const s = new THREE.Vector3(len, len, len);
    for (let k = 0; k < count; k++) {
      const i = this.lf.order[k];
      const p = this.lf.positions[i];
      const l = this.lf.directions[i];
      // the arrow shows light arriving: it points along -l and its tip touches the surface
      q.setFromUnitVectors(Y, l.clone().negate());
      m.compose(p.clone().addScaledVector(l, len), q, s);
      this.mesh.setMatrixAt(k, m);
    }
    this.mesh.count = count;
    this.mesh.instanceMatrix.needsUpdate = true;
    this.laidOut = true;
  }

  /** Glyphs drawn now. */
  visibleCount() {
    return this.mesh.visible ? this.mesh.count : 0;
  }
}
