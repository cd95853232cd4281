// Environment lighting presets (studio room, sky gradient, dim room, none), prefiltered once
// each (PMREM) and rotated onto the asset's up axis.
import * as THREE from 'three';
import { RoomEnvironment } from 'three/examples/jsm/environments/RoomEnvironment.js';
import { UP_AXES } from './frame.js';

export const ENVIRONMENTS = [
  { value: 'room', label: 'Studio room' },
  { value: 'sky', label: 'Sky gradient' },
  { value: 'dim', label: 'Dim room' },
  { value: 'none', label: 'None (point light only)' },
];

/** The environment strength a preset is drawn at ('dim' is the room at a quarter). */
export function environmentIntensity(name, strength) {
  return name === 'dim' ? strength * 0.25 : strength;
}

function skyScene() {
  const s = new THREE.Scene();
  const mat = new THREE.ShaderMaterial({
    side: THREE.BackSide,
    vertexShader: 'varying vec3 vP; void main(){ vP = position; gl_Position = projectionMatrix*modelViewMatrix*vec4(position,1.0); }',
    fragmentShader: `varying vec3 vP; void main(){ float t = normalize(vP).y;
      vec3 sky = mix(vec3(0.9,0.85,0.75), vec3(0.25,0.45,0.85), smoothstep(0.0, 0.8, t));
      vec3 ground = vec3(0.18,0.16,0.14);
      gl_FragColor = vec4(t > 0.0 ? sky : mix(ground, vec3(0.5,0.45,0.4), smoothstep(-0.15, 0.0, t)), 1.0); }`,
  });
  s.add(new THREE.Mesh(new THREE.SphereGeometry(1, 32, 16), mat));
  return s;
}

export class Environments {
  constructor(renderer) {
    this.renderer = renderer;
    this.pmrem = new THREE.PMREMGenerator(renderer);
    this.cache = new Map();
  }

  /** The prefiltered texture of a preset (null for 'none'), made once. */
  texture(name) {
    if (this.cache.has(name)) return this.cache.get(name);
    let tex = null;
    if (name === 'room' || name === 'dim') {
      tex = this.cache.get('room') || this.pmrem.fromScene(new RoomEnvironment(), 0.04).texture;
      this.cache.set('room', tex);
    } else if (name === 'sky') {
      tex = this.pmrem.fromScene(skyScene(), 0).texture;
    }
    this.cache.set(name, tex);
    return tex;
  }

  /** Put the state's environment, strength and exposure on the scene and the renderer. */
  apply(scene, st) {
    scene.environment = st.env === 'none' ? null : this.texture(st.env);
    scene.environmentIntensity = environmentIntensity(st.env, st.envIntensity);
    // environments are authored Y-up: rotate them onto the asset's up axis
    scene.environmentRotation.copy(UP_AXES[st.up]?.envRotation || new THREE.Euler());
    this.renderer.toneMappingExposure = st.exposure;
  }

  dispose() {
    for (const t of this.cache.values()) t?.dispose();
    this.pmrem.dispose();
  }
}
