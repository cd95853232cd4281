// 3D view of the recovered asset: orbit/zoom/pan, wireframe, material channels,
// light-field glyphs, a movable point light with a sphere gizmo, environment presets,
// and live material edits (roughness / metallic scale, albedo tint).
//
// Renders on demand (no idle animation loop): SwiftShader and laptops stay cool.
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { RoomEnvironment } from 'three/examples/jsm/environments/RoomEnvironment.js';
import { mergeGeometries } from 'three/examples/jsm/utils/BufferGeometryUtils.js';

export const CHANNELS = [
  { value: 'pbr', label: 'PBR (lit)' },
  { value: 'albedo', label: 'Albedo' },
  { value: 'roughness', label: 'Roughness' },
  { value: 'metallic', label: 'Metallic' },
  { value: 'normal', label: 'Normal' },
];

export const ENVIRONMENTS = [
  { value: 'room', label: 'Studio room' },
  { value: 'sky', label: 'Sky gradient' },
  { value: 'dim', label: 'Dim room' },
  { value: 'none', label: 'None (point light only)' },
];

export const BACKGROUND = 0x15191e;
/** The light handle moves on a sphere of this many asset radii around the asset. */
const GIZMO_RADIUS = 1.45;

/**
 * Up-axis choices. The GLB is glTF's +Y up (nepf_core/up_axis.py): the export rotates the input
 * world's up axis to +Y and the manifest's `frame` says so, so 'y' is the choice for every asset
 * exported since; 'z' and '-y' remain for assets written in their input's world frame before.
 */
export const UP_AXES = {
  y: { label: '+Y up (glTF, NePF exports)', up: new THREE.Vector3(0, 1, 0), ax: new THREE.Vector3(0, 0, 1), ay: new THREE.Vector3(1, 0, 0), envRotation: new THREE.Euler(0, 0, 0) },
  z: { label: '+Z up (assets exported before the glTF frame)', up: new THREE.Vector3(0, 0, 1), ax: new THREE.Vector3(1, 0, 0), ay: new THREE.Vector3(0, 1, 0), envRotation: new THREE.Euler(Math.PI / 2, 0, 0) },
  '-y': { label: '−Y up (older DTU assets)', up: new THREE.Vector3(0, -1, 0), ax: new THREE.Vector3(0, 0, 1), ay: new THREE.Vector3(-1, 0, 0), envRotation: new THREE.Euler(Math.PI, 0, 0) },
};

/**
 * The rotation `gltf_from_world` (3x3, rows) of the manifest's `frame` or the GLB's extras as a
 * THREE.Matrix3, or null when absent or malformed (an asset in its world frame: identity).
 */
export function frameRotation(frame) {
  const r = frame?.gltf_from_world;
  if (!Array.isArray(r) || r.length !== 3 || !r.every((row) => Array.isArray(row) && row.length === 3)) return null;
  const flat = r.flat().map(Number);
  if (!flat.every(Number.isFinite)) return null;
  return new THREE.Matrix3().set(...flat);
}

/** The viewer's up axis for the manifest's `frame` (`glb_up`, "+y" for every export since issue 34). */
export function upFromFrame(frame) {
  const u = typeof frame?.glb_up === 'string' ? frame.glb_up.toLowerCase().replace('+', '') : null;
  return u && UP_AXES[u] ? u : null;
}

/** An up axis named in the GLB's asset.extras.nepf (`up` as "z"/"+z"/"-y" or a vector). */
function upFromExtras(ex) {
  if (!ex) return null;
  let u = ex.up ?? ex.up_axis ?? ex.world_up;
  if (Array.isArray(u) && u.length === 3) {
    const [x, y, z] = u.map(Number);
    if (Math.abs(z) > 0.9 && z > 0) return 'z';
    if (Math.abs(y) > 0.9) return y > 0 ? 'y' : '-y';
    return null;
  }
  if (typeof u === 'string') {
    u = u.toLowerCase().replace('+', '');
    if (UP_AXES[u]) return u;
  }
  return null;
}

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

/** Shader showing one channel of a (linear) texture as grey, scaled, with a constant fallback. */
function channelMaterial(tex, channel, fallback) {
  return new THREE.ShaderMaterial({
    uniforms: {
      map: { value: tex },
      hasMap: { value: tex ? 1 : 0 },
      channel: { value: channel },
      scale: { value: 1 },
      fallback: { value: fallback },
    },
    vertexShader: /* glsl */`
      varying vec2 vUv;
      void main() {
        vUv = uv;
        gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
      }`,
    fragmentShader: /* glsl */`
      uniform sampler2D map;
      uniform int hasMap;
      uniform int channel;
      uniform float scale;
      uniform float fallback;
      varying vec2 vUv;
      void main() {
        float v = fallback;
        if (hasMap == 1) {
          vec4 t = texture2D(map, vUv);
          v = channel == 0 ? t.r : (channel == 1 ? t.g : t.b);
        }
        v = clamp(v * scale, 0.0, 1.0);
        gl_FragColor = vec4(vec3(v), 1.0);
      }`,
  });
}

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
function shuffledIndices(n, seed = 12345) {
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

function vec3(v) {
  if (Array.isArray(v) && v.length >= 3 && v.slice(0, 3).every((x) => Number.isFinite(Number(x)))) {
    return new THREE.Vector3(Number(v[0]), Number(v[1]), Number(v[2]));
  }
  if (v && typeof v === 'object' && ['x', 'y', 'z'].every((k) => Number.isFinite(Number(v[k])))) {
    return new THREE.Vector3(Number(v.x), Number(v.y), Number(v.z));
  }
  return null;
}

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

export class AssetViewer {
  /**
   * @param {HTMLElement} host element that receives the canvas (sized by CSS)
   * @param {{onChange?: () => void}} opts
   */
  constructor(host, { onChange } = {}) {
    this.host = host;
    this.onChange = onChange;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    this.renderer.toneMapping = THREE.NeutralToneMapping;
    this.renderer.toneMappingExposure = 1;
    this.canvas = this.renderer.domElement;
    this.canvas.id = 'viewer-canvas';
    this.canvas.setAttribute('role', 'img');
    this.canvas.setAttribute('aria-label', '3D view of the recovered asset. Drag to orbit, scroll to zoom, right-drag to pan.');
    this.canvas.tabIndex = 0;
    host.append(this.canvas);

    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.enableDamping = false;
    this.controls.screenSpacePanning = true;
    this.controls.listenToKeyEvents(this.canvas); // arrow keys pan when the canvas has focus
    this.controls.addEventListener('change', () => this.requestRender());

    this.pmrem = new THREE.PMREMGenerator(this.renderer);
    this.envCache = new Map();

    this.root = new THREE.Group();
    this.scene.add(this.root);
    this.center = new THREE.Vector3();
    this.radius = 1;

    // point light + gizmo
    this.light = new THREE.PointLight(0xffffff, 10, 0, 2);
    this.scene.add(this.light);
    this.gizmo = new THREE.Mesh(
      new THREE.SphereGeometry(1, 20, 14),
      new THREE.MeshBasicMaterial({ color: 0xffd34d, toneMapped: false }),
    );
    this.gizmo.name = 'light-gizmo';
    this.scene.add(this.gizmo);
    this.gizmoLine = new THREE.Line(
      new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 1, 0)]),
      new THREE.LineDashedMaterial({ color: 0xffd34d, dashSize: 0.05, gapSize: 0.05, transparent: true, opacity: 0.6, toneMapped: false }),
    );
    this.scene.add(this.gizmoLine);
    this.gizmoVisible = true;

    this.state = {
      channel: 'pbr',
      wireframe: false,
      env: 'room',
      envIntensity: 0.3,
      exposure: 1,
      lightAz: 45, // degrees around the up axis
      lightEl: 35, // degrees above the horizon
      lightDist: 3, // in units of the asset radius
      lightIntensity: 1, // multiplier of the base intensity
      roughnessScale: 1,
      metallicScale: 1,
      tint: '#ffffff',
      lightField: false,
      density: 0.25,
      up: 'y', // the GLB is +Y up (its manifest's frame); older assets say otherwise in their extras
    };
    // x_view = viewFromWorld x_world: the GLB's frame (manifest frame.gltf_from_world); null = identity
    this.viewFromWorld = null;
    this.frameFromManifest = false;
    // Default when lights.json is absent: irradiance pi at the asset centre from 3 radii, so a
    // white Lambertian surface facing the light shows ~1. The intensity slider multiplies it.
    this.baseLightIntensity = Math.PI * 9;
    this.meshes = []; // [{mesh, materials: {pbr, albedo, roughness, metallic, normal}}]
    this.assetExtras = null; // asset.extras.nepf of the GLB
    this.glyphs = null;
    this.lf = null;
    this.frame = 0;
    this.loaded = false;

    this.ro = new ResizeObserver(() => this.resize());
    this.ro.observe(host);
    this.resize();
    this.setupGizmoDrag();
    this.applyEnv();
  }

  // ---------------------------------------------------------------- loading
  /** Parse a GLB (ArrayBuffer) and frame it. */
  async loadGLB(buffer) {
    const gltf = await new Promise((res, rej) => new GLTFLoader().parse(buffer, '', res, rej));
    const obj = gltf.scene;
    this.assetExtras = gltf.parser?.json?.asset?.extras?.nepf || null;
    if (!this.frameFromManifest) { // an asset without a manifest frame: its own extras, else as it is
      this.viewFromWorld = frameRotation(this.assetExtras);
      const hinted = upFromExtras(this.assetExtras);
      if (hinted) this.state.up = hinted;
    }
    this.root.add(obj);
    obj.updateMatrixWorld(true);
    obj.traverse((o) => {
      if (!o.isMesh) return;
      const pbr = Array.isArray(o.material) ? o.material[0] : o.material;
      if (!pbr.isMeshStandardMaterial) {
        const m = new THREE.MeshStandardMaterial({ color: pbr.color || 0xcccccc, map: pbr.map || null });
        o.material = m;
      }
      const std = o.material;
      // a metallic scale > 1 must not push factor * texture.B past 1 (three.js clamps roughness
      // but not metalness)
      std.onBeforeCompile = (shader) => {
        shader.fragmentShader = shader.fragmentShader.replace('#include <metalnessmap_fragment>',
          '#include <metalnessmap_fragment>\nmetalnessFactor = clamp( metalnessFactor, 0.0, 1.0 );');
      };
      std.customProgramCacheKey = () => 'nepf-clamped-metalness';
      std.userData.baseColor = std.color.clone();
      std.userData.baseRoughness = std.roughness;
      std.userData.baseMetalness = std.metalness;
      const orm = std.roughnessMap || std.metalnessMap || null;
      const hasVC = !!o.geometry.attributes.color;
      const materials = {
        pbr: std,
        albedo: new THREE.MeshBasicMaterial({ map: std.map || null, color: std.color.clone(), vertexColors: hasVC, toneMapped: false }),
        roughness: channelMaterial(orm, 1, std.roughness),
        metallic: channelMaterial(std.metalnessMap || orm, 2, std.metalness),
        normal: new THREE.MeshNormalMaterial(),
      };
      if (!o.geometry.attributes.normal) o.geometry.computeVertexNormals();
      this.meshes.push({ mesh: o, materials });
    });
    const box = new THREE.Box3().setFromObject(obj);
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    this.center.copy(sphere.center);
    this.radius = sphere.radius > 0 ? sphere.radius : 1;
    this.loaded = true;
    this.frameCamera();
    this.applyMaterials();
    this.applyLight();
    this.requestRender();
    return { meshes: this.meshes.length, radius: this.radius };
  }

  /**
   * The GLB's frame from the export manifest's `frame` (GET /jobs/{id}/artifacts: `frame`): the
   * rotation `gltf_from_world` that world-frame records (relit_canonical.json, a world-frame
   * lights.json) go through, and the up axis (`glb_up`). Call before loadGLB.
   */
  setFrame(frame) {
    const r = frameRotation(frame);
    if (!r) return false;
    this.viewFromWorld = r;
    this.frameFromManifest = true;
    const up = upFromFrame(frame);
    if (up) this.state.up = up;
    return true;
  }

  /** A world-frame point or direction (Vector3) in the viewer's frame (the GLB's). */
  worldToView(v) {
    return v && this.viewFromWorld ? v.clone().applyMatrix3(this.viewFromWorld) : v;
  }

  /** A viewer-frame point (Vector3) in the input's world frame. */
  viewToWorld(v) {
    if (!v || !this.viewFromWorld) return v;
    return v.clone().applyMatrix3(this.viewFromWorld.clone().transpose()); // a rotation: inverse = transpose
  }

  /**
   * Initialise the light from lights.json (see parseLights). Its top level is in the GLB's frame
   * (`frame: "glb"`); one that says `frame: "world"` goes through the manifest's rotation.
   */
  setLightsFromJson(js) {
    let l = js && js.__parsed ? js.__parsed : parseLights(js);
    if (!l) return;
    if (js?.frame === 'world') {
      l = { ...l, position: this.worldToView(l.position), direction: this.worldToView(l.direction), center: this.worldToView(l.center) };
    }
    this.placeLight(l);
    this.lightsJson = l;
    this.applyLight();
    this.onChange?.();
  }

  /**
   * Put the interactive light at a world position with a radiant intensity: one entry of
   * `previews/relit_canonical.json` (`position_world`, `intensity_rgb`; nepf_core/relight/previews.py).
   * The position goes into the GLB's frame (worldToView) and converts to the sliders' azimuth /
   * elevation / distance about the asset's centre exactly as lights.json does (placeLight); the
   * light's colour is
   * `intensity_rgb / mean(intensity_rgb)` and its intensity the mean. Not the "Reset light" target.
   */
  setLightWorld(positionWorld, intensityRgb) {
    const position = this.worldToView(vec3(positionWorld));
    if (!position) return false;
    const rgb = (Array.isArray(intensityRgb) ? intensityRgb : [1, 1, 1]).slice(0, 3).map(Number);
    const mean = rgb.every(Number.isFinite) ? (rgb[0] + rgb[1] + rgb[2]) / 3 : 0;
    this.placeLight({ position, intensity: mean > 0 ? mean : null, color: mean > 0 ? rgb.map((c) => c / mean) : null });
    this.applyLight();
    this.onChange?.();
    return true;
  }

  /**
   * Look through a camera given in the world frame (`position_world`, `target_world`, `up`,
   * `fov_y_deg`: the `camera` of relit_canonical.json), mapped into the GLB's frame. A camera `up`
   * that is one of UP_AXES becomes the viewer's up axis first, so the orbit controls keep the same roll.
   */
  setCameraWorld(cam) {
    const pos = this.worldToView(vec3(cam?.position_world));
    const target = this.worldToView(vec3(cam?.target_world));
    if (!pos || !target) return false;
    const up = this.worldToView(vec3(cam.up));
    if (up) {
      up.normalize();
      const key = Object.keys(UP_AXES).find((k) => UP_AXES[k].up.distanceTo(up) < 1e-6);
      if (key && key !== this.state.up) this.setUp(key);
    }
    const fov = Number(cam.fov_y_deg);
    if (Number.isFinite(fov) && fov > 1 && fov < 179) this.camera.fov = fov;
    const dist = pos.distanceTo(target);
    this.camera.position.copy(pos);
    this.camera.near = Math.max(dist / 1000, 1e-4);
    this.camera.far = Math.max(dist * 100, this.camera.far);
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(target);
    this.controls.update();
    this.requestRender();
    return true;
  }

  /** Slider state and base intensity from a parsed light ({position?, direction?, intensity?, atPoint?, color?}). */
  placeLight(l) {
    let dir = null;
    let dist = null;
    if (l.position) {
      const d = l.position.clone().sub(this.center);
      dist = d.length() / this.radius;
      dir = d.normalize();
    } else if (l.direction) {
      dir = l.direction.clone();
    }
    if (dir) {
      const { az, el } = this.anglesOf(dir);
      this.state.lightAz = az;
      this.state.lightEl = el;
    }
    let rescale = 1;
    if (dist && Number.isFinite(dist)) {
      this.state.lightDist = Math.min(20, Math.max(1.2, dist));
      // a light moved onto the slider's range keeps the irradiance it gave the asset
      rescale = (this.state.lightDist / dist) ** 2;
    }
    // Radiant intensity of the point light (three.js: irradiance = I / d^2, Lambert = albedo/pi,
    // the same model as NePF's L = f * I * max(n.l, 0) with I falling off as 1/d^2).
    if (l.intensity && l.intensity > 0) this.baseLightIntensity = l.intensity * rescale;
    else if (l.atPoint && l.atPoint > 0) {
      const d = this.state.lightDist * this.radius;
      this.baseLightIntensity = l.atPoint * d * d;
    }
    this.state.lightIntensity = 1;
    if (l.color) this.light.color.setRGB(l.color[0], l.color[1], l.color[2], THREE.LinearSRGBColorSpace);
    else this.light.color.setRGB(1, 1, 1);
  }

  /** Azimuth / elevation (degrees) of a unit direction in the current up frame. */
  anglesOf(dir) {
    const up = this.upVector();
    const [ax, ay] = this.horizontalAxes();
    return {
      el: THREE.MathUtils.radToDeg(Math.asin(Math.max(-1, Math.min(1, dir.dot(up))))),
      az: THREE.MathUtils.radToDeg(Math.atan2(dir.dot(ay), dir.dot(ax))),
    };
  }

  /** Attach light_field.json (see parseLightField; a `frame: "world"` file goes through worldToView). */
  setLightField(js) {
    this.lf = parseLightField(js);
    if (!this.lf) return 0;
    if (js?.frame === 'world' && this.viewFromWorld) {
      for (const k of ['positions', 'directions', 'normals']) this.lf[k] = this.lf[k].map((v) => this.worldToView(v));
    }
    const n = this.lf.positions.length;
    let lo = Infinity;
    let hi = -Infinity;
    for (const v of this.lf.intensity) {
      if (Number.isFinite(v)) {
        lo = Math.min(lo, v);
        hi = Math.max(hi, v);
      }
    }
    if (!Number.isFinite(lo)) {
      lo = 0;
      hi = 1;
    }
    this.lf.min = lo;
    this.lf.max = hi;
    this.lf.order = shuffledIndices(n);
    const geo = arrowGeometry();
    const mat = new THREE.MeshBasicMaterial({ toneMapped: false });
    this.glyphs = new THREE.InstancedMesh(geo, mat, n);
    this.glyphs.name = 'light-field-glyphs';
    this.glyphs.frustumCulled = false;
    const c = new THREE.Color();
    for (let k = 0; k < n; k++) {
      const i = this.lf.order[k];
      const t = hi > lo ? (this.lf.intensity[i] - lo) / (hi - lo) : 1;
      const [r, g, b] = colormap(t);
      c.setRGB(r, g, b, THREE.SRGBColorSpace);
      this.glyphs.setColorAt(k, c);
    }
    this.glyphs.instanceMatrix.needsUpdate = true;
    if (this.glyphs.instanceColor) this.glyphs.instanceColor.needsUpdate = true;
    this.root.add(this.glyphs);
    this.applyLightField();
    return n;
  }

  // ---------------------------------------------------------------- state
  set(patch) {
    Object.assign(this.state, patch);
    if ('channel' in patch || 'wireframe' in patch || 'roughnessScale' in patch || 'metallicScale' in patch || 'tint' in patch) this.applyMaterials();
    if ('env' in patch || 'envIntensity' in patch || 'exposure' in patch) this.applyEnv();
    if ('lightAz' in patch || 'lightEl' in patch || 'lightDist' in patch || 'lightIntensity' in patch) this.applyLight();
    if ('lightField' in patch || 'density' in patch) this.applyLightField();
    this.requestRender();
  }

  upVector() {
    return UP_AXES[this.state.up]?.up.clone() || new THREE.Vector3(0, 1, 0);
  }

  /** Two horizontal axes (x-like, y-like) for the azimuth around the up vector. */
  horizontalAxes() {
    const u = UP_AXES[this.state.up] || UP_AXES.y;
    return [u.ax.clone(), u.ay.clone()];
  }

  /** Change the up axis, keeping the light where it is in the world. */
  setUp(up) {
    if (!UP_AXES[up] || up === this.state.up) return;
    const dir = this.lightDirection();
    this.state.up = up;
    const { az, el } = this.anglesOf(dir);
    this.state.lightAz = az;
    this.state.lightEl = el;
    this.frameCamera();
    this.applyEnv();
    this.applyLight();
    this.onChange?.();
  }

  /**
   * The default view: 20 degrees above the horizon, at the azimuth (of 12) where the asset's
   * silhouette is largest (area of the 2D bounding box of up to 2000 vertices projected on
   * the view plane). An elongated asset is then seen from the side, not end-on.
   */
  bestViewDirection(up, ax, ay) {
    const pts = [];
    for (const { mesh } of this.meshes) {
      const pos = mesh.geometry.attributes.position;
      const step = Math.max(1, Math.floor(pos.count / 2000));
      const v = new THREE.Vector3();
      for (let i = 0; i < pos.count; i += step) pts.push(v.fromBufferAttribute(pos, i).applyMatrix4(mesh.matrixWorld).clone());
    }
    const el = THREE.MathUtils.degToRad(20);
    let best = null;
    let bestArea = -1;
    for (let k = 0; k < 12; k++) {
      const az = (k / 12) * 2 * Math.PI + 0.6;
      const dir = ax.clone().multiplyScalar(Math.cos(az) * Math.cos(el))
        .addScaledVector(ay, Math.sin(az) * Math.cos(el)).addScaledVector(up, Math.sin(el)).normalize();
      const right = new THREE.Vector3().crossVectors(up, dir).normalize();
      const top = new THREE.Vector3().crossVectors(dir, right);
      let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
      for (const p of pts) {
        const x = p.dot(right);
        const y = p.dot(top);
        x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
      }
      const area = pts.length ? (x1 - x0) * (y1 - y0) : (k === 0 ? 1 : 0);
      if (area > bestArea * 1.02) {
        bestArea = area;
        best = dir;
      }
    }
    return best;
  }

  frameCamera() {
    const up = this.upVector();
    this.camera.up.copy(up);
    const [ax, ay] = this.horizontalAxes();
    const dir = this.bestViewDirection(up, ax, ay);
    // fit the asset and the light handle around it in the narrower of the two fields of view
    const vHalf = THREE.MathUtils.degToRad(this.camera.fov / 2);
    const hHalf = Math.atan(Math.tan(vHalf) * this.camera.aspect);
    const dist = (this.radius * (GIZMO_RADIUS + 0.12)) / Math.sin(Math.min(vHalf, hHalf));
    this.camera.position.copy(this.center).addScaledVector(dir, dist);
    this.camera.near = Math.max(dist / 1000, 1e-4);
    this.camera.far = dist * 100;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(this.center);
    this.controls.minDistance = this.radius * 0.2;
    this.controls.maxDistance = dist * 20;
    // OrbitControls caches the up vector at construction: rebuild its quaternion.
    this.controls._quat?.setFromUnitVectors(up, new THREE.Vector3(0, 1, 0));
    this.controls._quatInverse?.copy(this.controls._quat).invert();
    this.controls.update();
  }

  lightDirection() {
    const az = THREE.MathUtils.degToRad(this.state.lightAz);
    const el = THREE.MathUtils.degToRad(this.state.lightEl);
    const [ax, ay] = this.horizontalAxes();
    return ax.multiplyScalar(Math.cos(el) * Math.cos(az))
      .addScaledVector(ay, Math.cos(el) * Math.sin(az))
      .addScaledVector(this.upVector(), Math.sin(el))
      .normalize();
  }

  applyLight() {
    const dist = this.state.lightDist * this.radius;
    const pos = this.center.clone().addScaledVector(this.lightDirection(), dist);
    this.light.position.copy(pos);
    this.light.intensity = this.baseLightIntensity * this.state.lightIntensity;
    this.light.distance = 0; // no cut-off
    // The handle sits on a sphere of GIZMO_RADIUS asset radii in the light's direction (always
    // in view); the light itself may be farther away.
    const handle = this.center.clone().addScaledVector(this.lightDirection(), GIZMO_RADIUS * this.radius);
    this.gizmo.position.copy(handle);
    this.gizmo.scale.setScalar(this.radius * 0.07);
    const g = this.gizmoLine.geometry;
    g.setFromPoints([this.center, handle]);
    this.gizmoLine.computeLineDistances();
    this.gizmoLine.material.dashSize = this.radius * 0.05;
    this.gizmoLine.material.gapSize = this.radius * 0.05;
    const show = this.gizmoVisible && this.state.channel === 'pbr';
    this.gizmo.visible = show;
    this.gizmoLine.visible = show;
    this.requestRender();
  }

  applyMaterials() {
    const st = this.state;
    const tint = new THREE.Color(st.tint);
    for (const { mesh, materials } of this.meshes) {
      const pbr = materials.pbr;
      pbr.color.copy(pbr.userData.baseColor).multiply(tint);
      // glTF / three.js: roughness = factor * texture.G, metalness = factor * texture.B (the
      // shader clamps the product), so the scale is the factor times the file's own factor.
      pbr.roughness = pbr.userData.baseRoughness * st.roughnessScale;
      pbr.metalness = pbr.userData.baseMetalness * st.metallicScale;
      materials.albedo.color.copy(pbr.userData.baseColor).multiply(tint);
      materials.roughness.uniforms.scale.value = st.roughnessScale;
      materials.metallic.uniforms.scale.value = st.metallicScale;
      for (const m of Object.values(materials)) m.wireframe = st.wireframe;
      mesh.material = materials[st.channel] || pbr;
    }
    const show = this.gizmoVisible && st.channel === 'pbr';
    this.gizmo.visible = show;
    this.gizmoLine.visible = show;
  }

  envTexture(name) {
    if (this.envCache.has(name)) return this.envCache.get(name);
    let tex = null;
    if (name === 'room' || name === 'dim') {
      tex = this.envCache.get('room') || this.pmrem.fromScene(new RoomEnvironment(), 0.04).texture;
      this.envCache.set('room', tex);
    } else if (name === 'sky') {
      const s = new THREE.Scene();
      const geo = new THREE.SphereGeometry(1, 32, 16);
      const mat = new THREE.ShaderMaterial({
        side: THREE.BackSide,
        vertexShader: 'varying vec3 vP; void main(){ vP = position; gl_Position = projectionMatrix*modelViewMatrix*vec4(position,1.0); }',
        fragmentShader: `varying vec3 vP; void main(){ float t = normalize(vP).y;
          vec3 sky = mix(vec3(0.9,0.85,0.75), vec3(0.25,0.45,0.85), smoothstep(0.0, 0.8, t));
          vec3 ground = vec3(0.18,0.16,0.14);
          gl_FragColor = vec4(t > 0.0 ? sky : mix(ground, vec3(0.5,0.45,0.4), smoothstep(-0.15, 0.0, t)), 1.0); }`,
      });
      s.add(new THREE.Mesh(geo, mat));
      tex = this.pmrem.fromScene(s, 0).texture;
    }
    this.envCache.set(name, tex);
    return tex;
  }

  applyEnv() {
    const st = this.state;
    const name = st.env;
    this.scene.environment = name === 'none' ? null : this.envTexture(name);
    this.scene.environmentIntensity = name === 'dim' ? st.envIntensity * 0.25 : st.envIntensity;
    // environments are authored Y-up: rotate them onto the asset's up axis
    this.scene.environmentRotation.copy(UP_AXES[this.state.up]?.envRotation || new THREE.Euler());
    this.renderer.toneMappingExposure = st.exposure;
    this.requestRender();
  }

  applyLightField() {
    if (!this.glyphs) return;
    const n = this.lf.positions.length;
    this.glyphs.visible = !!this.state.lightField;
    const count = Math.max(1, Math.round(n * this.state.density));
    if (count !== this.glyphs.count || !this.glyphsLaidOut) this.layoutGlyphs(count);
  }

  /**
   * Place the first `count` glyphs (of the shuffled order). Arrow length follows the mean
   * spacing of the visible samples on a sphere of the asset's radius, sqrt(4 pi r^2 / count),
   * so a denser field gets smaller arrows instead of a solid carpet.
   */
  layoutGlyphs(count) {
    const m = new THREE.Matrix4();
    const q = new THREE.Quaternion();
    const s = new THREE.Vector3();
    const Y = new THREE.Vector3(0, 1, 0);
    const spacing = this.radius * Math.sqrt((4 * Math.PI) / count);
    const len = Math.min(0.15 * this.radius, Math.max(0.025 * this.radius, 0.8 * spacing));
    for (let k = 0; k < count; k++) {
      const i = this.lf.order[k];
      const p = this.lf.positions[i];
      const l = this.lf.directions[i];
      // the arrow shows light arriving: it points along -l and its tip touches the surface
      q.setFromUnitVectors(Y, l.clone().negate());
      s.set(len, len, len);
      m.compose(p.clone().addScaledVector(l, len), q, s);
      this.glyphs.setMatrixAt(k, m);
    }
    this.glyphs.count = count;
    this.glyphs.instanceMatrix.needsUpdate = true;
    this.glyphsLaidOut = true;
  }

  glyphCount() {
    return this.glyphs && this.glyphs.visible ? this.glyphs.count : 0;
  }

  // ---------------------------------------------------------------- interaction
  setupGizmoDrag() {
    const ray = new THREE.Raycaster();
    const ndc = new THREE.Vector2();
    let dragging = false;
    let dragBack = false;
    const toNdc = (e) => {
      const r = this.canvas.getBoundingClientRect();
      ndc.set(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1);
      ray.setFromCamera(ndc, this.camera);
    };
    this.canvas.addEventListener('pointerdown', (e) => {
      if (!this.gizmo.visible) return;
      toNdc(e);
      const hit = ray.intersectObject(this.gizmo, false);
      if (hit.length) {
        dragging = true;
        const toCam = this.camera.position.clone().sub(this.center);
        dragBack = this.gizmo.position.clone().sub(this.center).dot(toCam) < 0;
        this.controls.enabled = false;
        this.canvas.setPointerCapture(e.pointerId);
        this.canvas.style.cursor = 'grabbing';
        e.preventDefault();
        e.stopImmediatePropagation();
      }
    }, { capture: true });
    this.canvas.addEventListener('pointermove', (e) => {
      if (!dragging) {
        if (this.gizmo.visible && e.buttons === 0) {
          toNdc(e);
          this.canvas.style.cursor = ray.intersectObject(this.gizmo, false).length ? 'grab' : '';
        }
        return;
      }
      toNdc(e);
      // intersect the ray with the sphere the light lives on (centre: asset, radius: light distance)
      const R = GIZMO_RADIUS * this.radius;
      // ray-sphere: |o + t d - c|^2 = R^2; keep the handle on the side (front/back) it started on
      const o = ray.ray.origin.clone().sub(this.center);
      const b = o.dot(ray.ray.direction);
      const disc = b * b - (o.lengthSq() - R * R);
      let p;
      if (disc >= 0) {
        const t = dragBack ? -b + Math.sqrt(disc) : -b - Math.sqrt(disc);
        p = ray.ray.at(t, new THREE.Vector3());
      } else {
        // outside the silhouette: the closest point of the ray, pushed onto the sphere
        p = ray.ray.closestPointToPoint(this.center, new THREE.Vector3());
      }
      const d = p.sub(this.center).normalize();
      const up = this.upVector();
      const [ax, ay] = this.horizontalAxes();
      this.state.lightEl = THREE.MathUtils.radToDeg(Math.asin(Math.max(-1, Math.min(1, d.dot(up)))));
      this.state.lightAz = THREE.MathUtils.radToDeg(Math.atan2(d.dot(ay), d.dot(ax)));
      this.applyLight();
      this.onChange?.();
    });
    const end = (e) => {
      if (!dragging) return;
      dragging = false;
      this.controls.enabled = true;
      this.canvas.style.cursor = '';
      try {
        this.canvas.releasePointerCapture(e.pointerId);
      } catch {
        /* already released */
      }
    };
    this.canvas.addEventListener('pointerup', end);
    this.canvas.addEventListener('pointercancel', end);
  }

  /** Screen position (CSS px, relative to the canvas) of the light gizmo. */
  gizmoScreenPosition() {
    const p = this.gizmo.position.clone().project(this.camera);
    const r = this.canvas.getBoundingClientRect();
    return { x: (p.x + 1) / 2 * r.width, y: (1 - p.y) / 2 * r.height };
  }

  resize() {
    const w = Math.max(1, this.host.clientWidth);
    const hgt = Math.max(1, this.host.clientHeight);
    this.renderer.setSize(w, hgt, false);
    this.canvas.style.width = '100%';
    this.canvas.style.height = '100%';
    this.camera.aspect = w / hgt;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  requestRender() {
    if (this.pending || this.disposed) return;
    this.pending = requestAnimationFrame(() => {
      this.pending = null;
      this.render();
    });
  }

  render() {
    if (this.disposed) return;
    this.renderer.render(this.scene, this.camera);
    this.frame++;
    this.describeFrame();
  }

  /**
   * What the frame just drawn shows, as data-* attributes of the canvas (read by the browser
   * tests and by anyone inspecting the page): `data-state` (loading | loaded), `data-frame`
   * (frames drawn so far), `data-channel`, `data-wireframe`, `data-glyphs` (light-field arrows
   * drawn), `data-light-position` ("x y z", the viewer's frame = the GLB's), `data-light-position-world`
   * (the same in the input's world frame), `data-light-intensity` (three.js' radiant intensity),
   * `data-camera-position` / `data-camera-position-world` (likewise), `data-up` (the up axis),
   * `data-env`, `data-gizmo-x` / `data-gizmo-y` (the light gizmo's position in CSS px from the
   * canvas's top-left corner).
   */
  describeFrame() {
    const d = this.canvas.dataset;
    const p = this.light.position;
    const g = this.gizmoScreenPosition();
    d.state = this.loaded ? 'loaded' : 'loading';
    d.frame = String(this.frame);
    d.channel = this.state.channel;
    d.wireframe = String(this.state.wireframe);
    d.glyphs = String(this.glyphCount());
    d.lightPosition = [p.x, p.y, p.z].join(' ');
    d.lightIntensity = String(this.light.intensity);
    d.lightPositionWorld = this.viewToWorld(p.clone()).toArray().join(' ');
    d.cameraPosition = this.camera.position.toArray().join(' ');
    d.cameraPositionWorld = this.viewToWorld(this.camera.position.clone()).toArray().join(' ');
    d.up = this.state.up;
    d.env = this.state.env;
    d.gizmoX = g.x.toFixed(1);
    d.gizmoY = g.y.toFixed(1);
  }

  dispose() {
    this.disposed = true;
    cancelAnimationFrame(this.pending);
    this.ro.disconnect();
    this.controls.dispose();
    for (const t of this.envCache.values()) t?.dispose();
    this.pmrem.dispose();
    this.scene.traverse((o) => {
      o.geometry?.dispose?.();
    });
    for (const { materials } of this.meshes) for (const m of Object.values(materials)) m.dispose();
    this.renderer.dispose();
    this.renderer.forceContextLoss?.();
    this.canvas.remove();
  }
}
