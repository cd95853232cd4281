// The asset's materials: the GLB's own (PBR), and one per inspection channel (albedo, roughness,
// metallic, normal); the material edits (roughness / metallic scale, albedo tint) act on them.
import * as THREE from 'three';

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

/**
 * The channel materials of one mesh of the GLB (its PBR material made a MeshStandardMaterial
 * whose metalness is clamped to 1, with its base values kept for the edits).
 */
export function meshMaterials(o) {
  const pbr = Array.isArray(o.material) ? o.material[0] : o.material;
  if (!pbr.isMeshStandardMaterial) {
    o.material = new THREE.MeshStandardMaterial({ color: pbr.color || 0xcccccc, map: pbr.map || null });
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
  return {
    pbr: std,
    albedo: new THREE.MeshBasicMaterial({ map: std.map || null, color: std.color.clone(), vertexColors: hasVC, toneMapped: false }),
    roughness: channelMaterial(orm, 1, std.roughness),
    metallic: channelMaterial(std.metalnessMap || orm, 2, std.metalness),
    normal: new THREE.MeshNormalMaterial(),
  };
}

/** Put the state's channel, wireframe and material edits on every mesh ([{mesh, materials}]). */
export function applyMaterials(meshes, st) {
  const tint = new THREE.Color(st.tint);
  for (const { mesh, materials } of meshes) {
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
}
