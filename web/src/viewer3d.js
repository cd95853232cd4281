// 3D view of the recovered asset: orbit/zoom/pan, wireframe, material channels,
// light-field glyphs, a movable point light with a sphere gizmo, environment presets,
// and live material edits (roughness / metallic scale, albedo tint).
//
// Renders on demand (no idle animation loop): SwiftShader and laptops stay cool. AssetViewer
// holds the scene and the state; each concern lives in its module under viewer/: frames and
// directions (frame.js), light records (parse.js), materials (materials.js), environments
// (environment.js), the light gizmo and its drag (gizmo.js), the default camera (framing.js),
// the light sliders (lighting.js), light-field glyphs (glyphs.js).
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { UP_AXES, anglesOf, directionOf, frameRotation, horizontalAxesOf, upFromExtras, upFromFrame, upVectorOf, vec3 } from './viewer/frame.js';
import { parseLightField, parseLights } from './viewer/parse.js';
import { applyMaterials, meshMaterials } from './viewer/materials.js';
import { Environments } from './viewer/environment.js';
import { LightGizmo, attachGizmoDrag } from './viewer/gizmo.js';
import { bestViewDirection, placeCamera, samplePoints } from './viewer/framing.js';
import { lightSliders } from './viewer/lighting.js';
import { LightFieldGlyphs } from './viewer/glyphs.js';

export { UP_AXES, frameRotation, upFromFrame } from './viewer/frame.js';
export { parseLightField, parseLights } from './viewer/parse.js';
export { ENVIRONMENTS } from './viewer/environment.js';
export { COLORMAP_CSS, colormap } from './viewer/glyphs.js';

export const CHANNELS = [
  { value: 'pbr', label: 'PBR (lit)' },
  { value: 'albedo', label: 'Albedo' },
  { value: 'roughness', label: 'Roughness' },
  { value: 'metallic', label: 'Metallic' },
  { value: 'normal', label: 'Normal' },
];

export const BACKGROUND = 0x15191e;

/** The viewer's state at start (the sliders, selects and toggles of the job page). */
export function initialState() {
  return {
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
}

/** Which parts of the scene a state patch touches (set() re-applies only those). */
export function patchTouches(patch) {
  const any = (...keys) => keys.some((k) => k in patch);
  return {
    materials: any('channel', 'wireframe', 'roughnessScale', 'metallicScale', 'tint'),
    env: any('env', 'envIntensity', 'exposure'),
    light: any('lightAz', 'lightEl', 'lightDist', 'lightIntensity'),
    lightField: any('lightField', 'density'),
  };
}

function makeRenderer() {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  renderer.toneMapping = THREE.NeutralToneMapping;
  renderer.toneMappingExposure = 1;
  const canvas = renderer.domElement;
  canvas.id = 'viewer-canvas';
  canvas.setAttribute('role', 'img');
  canvas.setAttribute('aria-label', '3D view of the recovered asset. Drag to orbit, scroll to zoom, right-drag to pan.');
  canvas.tabIndex = 0;
  return renderer;
}

export class AssetViewer {
  /**
   * @param {HTMLElement} host element that receives the canvas (sized by CSS)
   * @param {{onChange?: () => void}} opts
   */
  constructor(host, { onChange } = {}) {
    this.host = host;
    this.onChange = onChange;
    this.renderer = makeRenderer();
    this.canvas = this.renderer.domElement;
    host.append(this.canvas);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.controls.enableDamping = false;
    this.controls.screenSpacePanning = true;
    this.controls.listenToKeyEvents(this.canvas); // arrow keys pan when the canvas has focus
    this.controls.addEventListener('change', () => this.requestRender());
    this.environments = new Environments(this.renderer);
    this.root = new THREE.Group();
    this.scene.add(this.root);
    this.center = new THREE.Vector3();
    this.radius = 1;
    this.light = new THREE.PointLight(0xffffff, 10, 0, 2);
    this.scene.add(this.light);
    this.gizmo = new LightGizmo(this.scene);
    this.state = initialState();
    // x_view = viewFromWorld x_world: the GLB's frame (manifest frame.gltf_from_world); null = identity
    this.viewFromWorld = null;
    this.frameFromManifest = false;
    // Default when lights.json is absent: irradiance pi at the asset centre from 3 radii, so a
    // white Lambertian surface facing the light shows ~1. The intensity slider multiplies it.
    this.baseLightIntensity = Math.PI * 9;
    this.meshes = []; // [{mesh, materials: {pbr, albedo, roughness, metallic, normal}}]
    this.assetExtras = null; // asset.extras.nepf of the GLB
    this.glyphs = null; // LightFieldGlyphs
    this.lf = null;
    this.frame = 0;
    this.loaded = false;
    this.ro = new ResizeObserver(() => this.resize());
    this.ro.observe(host);
    this.resize();
    attachGizmoDrag(this);
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
      const materials = meshMaterials(o);
      if (!o.geometry.attributes.normal) o.geometry.computeVertexNormals();
      this.meshes.push({ mesh: o, materials });
    });
    const sphere = new THREE.Box3().setFromObject(obj).getBoundingSphere(new THREE.Sphere());
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
    const s = lightSliders(l, {
      center: this.center, radius: this.radius, up: this.state.up,
      current: { lightAz: this.state.lightAz, lightEl: this.state.lightEl, lightDist: this.state.lightDist, baseLightIntensity: this.baseLightIntensity },
    });
    this.baseLightIntensity = s.baseLightIntensity;
    delete s.baseLightIntensity;
    Object.assign(this.state, s);
    if (l.color) this.light.color.setRGB(l.color[0], l.color[1], l.color[2], THREE.LinearSRGBColorSpace);
    else this.light.color.setRGB(1, 1, 1);
  }

  /** Azimuth / elevation (degrees) of a unit direction in the current up frame. */
  anglesOf(dir) {
    return anglesOf(dir, this.state.up);
  }

  /** Attach light_field.json (see parseLightField; a `frame: "world"` file goes through worldToView). */
  setLightField(js) {
    this.lf = parseLightField(js);
    if (!this.lf) return 0;
    if (js?.frame === 'world' && this.viewFromWorld) {
      for (const k of ['positions', 'directions', 'normals']) this.lf[k] = this.lf[k].map((v) => this.worldToView(v));
    }
    this.glyphs = new LightFieldGlyphs(this.lf, this.radius);
    this.root.add(this.glyphs.mesh);
    this.applyLightField();
    return this.lf.positions.length;
  }

  // ---------------------------------------------------------------- state
  set(patch) {
    Object.assign(this.state, patch);
    const t = patchTouches(patch);
    if (t.materials) this.applyMaterials();
    if (t.env) this.applyEnv();
    if (t.light) this.applyLight();
    if (t.lightField) this.applyLightField();
    this.requestRender();
  }

  upVector() {
    return upVectorOf(this.state.up);
  }

  /** Two horizontal axes (x-like, y-like) for the azimuth around the up vector. */
  horizontalAxes() {
    return horizontalAxesOf(this.state.up);
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

  /** The default view (framing.js): the largest silhouette, the asset and the light handle in view. */
  frameCamera() {
    const up = this.upVector();
    const [ax, ay] = this.horizontalAxes();
    const dir = bestViewDirection(samplePoints(this.meshes), up, ax, ay);
    placeCamera(this.camera, this.controls, { center: this.center, radius: this.radius, up, dir });
  }

  lightDirection() {
    return directionOf(this.state.lightAz, this.state.lightEl, this.state.up);
  }

  applyLight() {
    const dir = this.lightDirection();
    this.light.position.copy(this.center).addScaledVector(dir, this.state.lightDist * this.radius);
    this.light.intensity = this.baseLightIntensity * this.state.lightIntensity;
    this.light.distance = 0; // no cut-off
    this.gizmo.place(this.center, dir, this.radius);
    this.gizmo.show(this.state.channel === 'pbr');
    this.requestRender();
  }

  applyMaterials() {
    applyMaterials(this.meshes, this.state);
    this.gizmo.show(this.state.channel === 'pbr');
  }

  applyEnv() {
    this.environments.apply(this.scene, this.state);
    this.requestRender();
  }

  applyLightField() {
    this.glyphs?.apply(this.state);
  }

  glyphCount() {
    return this.glyphs ? this.glyphs.visibleCount() : 0;
  }

  // ---------------------------------------------------------------- drawing
  /** Screen position (CSS px, relative to the canvas) of the light gizmo. */
  gizmoScreenPosition() {
    const p = this.gizmo.handle.position.clone().project(this.camera);
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
    this.environments.dispose();
    this.scene.traverse((o) => {
      o.geometry?.dispose?.();
    });
    for (const { materials } of this.meshes) for (const m of Object.values(materials)) m.dispose();
    this.renderer.dispose();
    this.renderer.forceContextLoss?.();
    this.canvas.remove();
  }
}
