"""Binary glTF 2.0 (GLB) writer for the baked asset (pygltflib, one mesh, one PBR material).

Frame decision: glTF is +Y up and right-handed (specification §3.4), and Blender's importer,
three.js' ``GLTFLoader`` and every viewer assume it. The caller (``export_asset``) passes the
vertices and normals already rotated from the input's world into that frame,
``x_glb = R x_world`` with ``R`` the proper rotation of :mod:`nepf_core.up_axis` that takes the
world's up axis to +Y (world units and origin kept: no scale, no translation). The rotation is
baked into the vertex data and the node has **no transform**, so a loader that ignores node
transforms still gets the same frame; ``det R = +1``, so the triangle winding (counter-clockwise
seen from the side the normal points to) is unchanged. ``asset.extras.nepf`` records ``frame``,
``up`` (``[0, 1, 0]``), ``world_up`` (the input's axis), ``gltf_from_world`` (``R``) and
``world_from_norm``.

Contents:
* one node -> one mesh -> one triangle primitive with ``POSITION`` (float32, min/max),
  ``NORMAL`` (unit float32), ``TEXCOORD_0`` (float32, glTF top-left origin), ``uint32``
  indices;
* one material, ``pbrMetallicRoughness`` with ``baseColorTexture`` (sRGB PNG),
  ``metallicRoughnessTexture`` (linear ORM PNG: G = roughness, B = metallic) and
  ``occlusionTexture`` pointing at the same ORM image (R = occlusion = 1);
  ``baseColorFactor = 1``, ``metallicFactor = roughnessFactor = 1`` so the textures hold the
  values directly;
* PNG bytes embedded in the binary chunk (identical to ``textures/*.png``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib as g

__all__ = ["write_glb"]

_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT = 5126
_UINT32 = 5125
_LINEAR = 9729
_LINEAR_MIPMAP_LINEAR = 9987
_REPEAT = 10497


def write_glb(
    path: str | Path,
    vertices: np.ndarray,
    normals: np.ndarray,
    uv: np.ndarray,
    faces: np.ndarray,
    base_color_png: bytes,
    orm_png: bytes,
    name: str = "nepf_asset",
    extras: dict | None = None,
) -> Path:
    """Write a GLB.

    Args:
        vertices: ``[V,3]`` in the GLB frame (module docstring). normals: ``[V,3]`` (renormalised here).
        uv: ``[V,2]`` in [0,1], top-left origin. faces: ``[F,3]`` vertex indices.
        base_color_png, orm_png: encoded PNG files.
        extras: JSON-able dict stored under ``asset.extras.nepf``.
    Returns: the path written.
    """
    v, n, t, idx = _vertex_arrays(vertices, normals, uv, faces)
    chunk = _BinaryChunk()
    accessors = _mesh_accessors(chunk, v, n, t, idx)
    images = [g.Image(bufferView=chunk.add(bytes(base_color_png), None), mimeType="image/png", name="base_color"),
              g.Image(bufferView=chunk.add(bytes(orm_png), None), mimeType="image/png", name="orm")]
    chunk.pad()
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="nepf export",
                      extras={"nepf": {"frame": "glTF +Y up: x_glb = gltf_from_world @ x_world (input world units and origin)",
                                       **(extras or {})}}),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0, name=name)],
        meshes=[g.Mesh(name=name, primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2), indices=3,
            material=0, mode=4)])],
        accessors=accessors,
        bufferViews=chunk.views,
        buffers=[g.Buffer(byteLength=len(chunk.blob))],
        images=images,
        samplers=[g.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=_REPEAT,
                            wrapT=_REPEAT)],
        textures=[g.Texture(sampler=0, source=0), g.Texture(sampler=0, source=1)],
        materials=[_baked_material()],
    )
    gltf.set_binary_blob(bytes(chunk.blob))
    return _save_atomic(gltf, Path(path))


def _vertex_arrays(vertices, normals, uv, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(positions [V, 3], unit normals [V, 3], uv [V, 2] in [0, 1], indices [3F])`` as glTF
    stores them (float32, uint32); a normal that is not finite or shorter than 0.5 before
    normalising becomes +Z."""
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    bad = ~np.isfinite(n).all(axis=-1) | (np.linalg.norm(n, axis=-1) < 0.5)
    n[bad] = (0.0, 0.0, 1.0)
    n = np.ascontiguousarray(n, dtype=np.float32)
    t = np.ascontiguousarray(np.clip(uv, 0.0, 1.0), dtype=np.float32)
    idx = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1)
    if len(v) == 0 or len(idx) == 0:
        raise ValueError("write_glb: empty mesh")
    return v, n, t, idx


class _BinaryChunk:
    """The GLB's binary chunk and its buffer views, each view starting at a multiple of 4 bytes."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[g.BufferView] = []

    def pad(self) -> None:
        while len(self.blob) % 4:
            self.blob.append(0)

    def add(self, data: bytes, target: int | None) -> int:
        """Append ``data`` as a new buffer view; returns its index."""
        self.pad()
        self.views.append(g.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(data), target=target))
        self.blob.extend(data)
        return len(self.views) - 1


def _mesh_accessors(chunk: _BinaryChunk, v, n, t, idx) -> list[g.Accessor]:
    """Accessors 0-3: ``POSITION`` (with min/max), ``NORMAL``, ``TEXCOORD_0``, the indices."""
    return [
        g.Accessor(bufferView=chunk.add(v.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT,
                   count=len(v), type="VEC3", min=v.min(0).tolist(), max=v.max(0).tolist()),
        g.Accessor(bufferView=chunk.add(n.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT,
                   count=len(n), type="VEC3"),
        g.Accessor(bufferView=chunk.add(t.tobytes(), _ARRAY_BUFFER), componentType=_FLOAT,
                   count=len(t), type="VEC2"),
        g.Accessor(bufferView=chunk.add(idx.tobytes(), _ELEMENT_ARRAY_BUFFER), componentType=_UINT32,
                   count=len(idx), type="SCALAR"),
    ]


def _baked_material() -> g.Material:
    """Texture 0 the base colour, texture 1 the ORM image (metallic-roughness and occlusion);
    factors 1 so the textures hold the values."""
    return g.Material(
        name="baked",
        pbrMetallicRoughness=g.PbrMetallicRoughness(
            baseColorFactor=[1.0, 1.0, 1.0, 1.0],
            baseColorTexture=g.TextureInfo(index=0, texCoord=0),
            metallicFactor=1.0,
            roughnessFactor=1.0,
            metallicRoughnessTexture=g.TextureInfo(index=1, texCoord=0),
        ),
        occlusionTexture=g.OcclusionTextureInfo(index=1, texCoord=0, strength=1.0),
        doubleSided=False,
    )


def _save_atomic(gltf: g.GLTF2, path: Path) -> Path:
    """Write ``path`` through a temporary file beside it, so no reader sees half a GLB."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    gltf.save_binary(str(tmp))
    tmp.replace(path)
    return path
