// The light's handle: a yellow sphere on a sphere of GIZMO_RADIUS asset radii around the asset
// (always in view; the light itself may be farther), a dashed line to the centre, and its drag.
import * as THREE from 'three';
import { anglesOf } from './frame.js';

/** The light handle moves on a sphere of this many asset radii around the asset. */
export const GIZMO_RADIUS = 1.45;
const COLOR = 0xffd34d;

/**
 * Where a pointer ray grabs the handle's sphere (centre `center`, radius `R`): the near
 * intersection, or the far one when the drag started on the back (`back`); outside the
 * silhouette, the ray's closest point to the centre. Returns the unit direction from the centre.
 */
export function dragDirection(ray, center, R, back) {
  const o = ray.origin.clone().sub(center);
  const b = o.dot(ray.direction);
  const disc = b * b - (o.lengthSq() - R * R);
  const p = disc >= 0
    ? ray.at(back ? -b + Math.sqrt(disc) : -b - Math.sqrt(disc), new THREE.Vector3())
    : ray.closestPointToPoint(center, new THREE.Vector3());
  return p.sub(center).normalize();
}

export class LightGizmo {
  constructor(scene) {
    this.handle = new THREE.Mesh(new THREE.SphereGeometry(1, 20, 14),
      new THREE.MeshBasicMaterial({ color: COLOR, toneMapped: false }));
    this.handle.name = 'light-gizmo';
    this.line = new THREE.Line(
      new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 1, 0)]),
      new THREE.LineDashedMaterial({ color: COLOR, dashSize: 0.05, gapSize: 0.05, transparent: true, opacity: 0.6, toneMapped: false }),
    );
    scene.add(this.handle, this.line);
    this.enabled = true;
  }

  /** The handle in direction `dir` from `center`, sized for an asset of radius `radius`. */
  place(center, dir, radius) {
    const at = center.clone().addScaledVector(dir, GIZMO_RADIUS * radius);
    this.handle.position.copy(at);
    this.handle.scale.setScalar(radius * 0.07);
    this.line.geometry.setFromPoints([center, at]);
    this.line.computeLineDistances();
    this.line.material.dashSize = radius * 0.05;
    this.line.material.gapSize = radius * 0.05;
  }

  /** Shown only over the lit (PBR) channel. */
  show(visible) {
    this.handle.visible = this.enabled && visible;
    this.line.visible = this.handle.visible;
  }
}

/**
 * Let the pointer drag the handle of `viewer` (an AssetViewer) around the asset: the light's
 * azimuth / elevation follow, the orbit controls pause meanwhile.
 */
export function attachGizmoDrag(viewer) {
  const { canvas, camera, controls } = viewer;
  const handle = viewer.gizmo.handle;
  const ray = new THREE.Raycaster();
  const ndc = new THREE.Vector2();
  const drag = { on: false, back: false };
  const aim = (e) => {
    const r = canvas.getBoundingClientRect();
    ndc.set(((e.clientX - r.left) / r.width) * 2 - 1, -((e.clientY - r.top) / r.height) * 2 + 1);
    ray.setFromCamera(ndc, camera);
    return ray.intersectObject(handle, false).length > 0;
  };
  canvas.addEventListener('pointerdown', (e) => {
    if (!handle.visible || !aim(e)) return;
    drag.on = true;
    const toCam = camera.position.clone().sub(viewer.center);
    drag.back = handle.position.clone().sub(viewer.center).dot(toCam) < 0;
    controls.enabled = false;
    canvas.setPointerCapture(e.pointerId);
    canvas.style.cursor = 'grabbing';
    e.preventDefault();
    e.stopImmediatePropagation();
  }, { capture: true });
  canvas.addEventListener('pointermove', (e) => {
    if (!drag.on) {
      if (handle.visible && e.buttons === 0) canvas.style.cursor = aim(e) ? 'grab' : '';
      return;
    }
    aim(e);
    const d = dragDirection(ray.ray, viewer.center, GIZMO_RADIUS * viewer.radius, drag.back);
    const { az, el } = anglesOf(d, viewer.state.up);
    viewer.state.lightEl = el;
    viewer.state.lightAz = az;
    viewer.applyLight();
    viewer.onChange?.();
  });
  const end = (e) => {
    if (!drag.on) return;
    drag.on = false;
    controls.enabled = true;
    canvas.style.cursor = '';
    try {
      canvas.releasePointerCapture(e.pointerId);
    } catch {
      /* already released */
    }
  };
  canvas.addEventListener('pointerup', end);
  canvas.addEventListener('pointercancel', end);
}
