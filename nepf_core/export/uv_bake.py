"""UV atlas (xatlas), texel rasterisation, material baking and seam padding.

UV convention (the glTF one): ``uv = (u, v)`` in [0, 1], origin at the **top-left** of the
image; texel ``(row, col)`` of an ``H x W`` texture has its centre at
``u = (col + 0.5) / W``, ``v = (row + 0.5) / H``. The UVs written to the GLB are exactly the
ones used here for rasterisation, so no flip happens anywhere.

Colour: the material field's albedo is linear RGB; the baseColor PNG is sRGB-encoded
(glTF baseColorTexture is sRGB). ORM is linear: R = occlusion (255, not computed),
G = roughness, B = metallic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import xatlas

from nepf_core.color import linear_to_srgb

from .mesh import evaluate_in_chunks

__all__ = [
    "UVMesh",
    "unwrap_uv",
    "rasterize_uv",
    "fill_push_pull",
    "BakedTextures",
    "bake_material_textures",
]


@dataclass
class UVMesh:
    """A mesh split along UV seams: ``vmapping[i]`` is the source vertex of vertex ``i``.

    Shapes: ``vmapping [V'] int64``, ``faces [F,3] int64`` (into the V' vertices),
    ``uv [V',2] float32`` in [0,1] (glTF convention, v down).
    """

    vmapping: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    width: int
    height: int
    utilization: float


def unwrap_uv(vertices: np.ndarray, faces: np.ndarray, texture_size: int = 1024,
              padding: int = 4, chart_iterations: int = 0) -> UVMesh:
    """UV-unwrap with xatlas (charts + packing), targeting a ``texture_size``² atlas.

    Cost grows quickly with face count (2 idle CPU cores, xatlas defaults: ~4 s for 20k
    faces, ~12-16 s for 50k), so decimate first. ``chart_iterations`` is xatlas'
    ``ChartOptions.max_iterations`` (re-seeding passes after the first chart growing):
    0 skips them, which halved the unwrap time of a 30k-face sphere with equal atlas
    utilisation (0.84 vs 0.71); raise it for fewer, rounder charts.
    """
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, dtype=np.float32),
                   np.ascontiguousarray(faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(texture_size)
    pack.padding = int(padding)
    pack.blockAlign = True
    charts = xatlas.ChartOptions()
    charts.max_iterations = int(chart_iterations)
    atlas.generate(charts, pack)
    if atlas.atlas_count != 1:  # uvs of several atlases would overlap in one texture
        raise RuntimeError(f"xatlas packed {atlas.atlas_count} atlases; expected 1")
    vmapping, indices, uv = atlas[0]
    uv = np.clip(np.asarray(uv, dtype=np.float32), 0.0, 1.0)
    return UVMesh(vmapping=np.asarray(vmapping, dtype=np.int64),
                  faces=np.asarray(indices, dtype=np.int64), uv=uv,
                  width=int(atlas.width), height=int(atlas.height),
                  utilization=float(atlas.utilization))


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, width: int, height: int,
                 margin_px: float = 0.75, max_candidates: int = 2_000_000
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Rasterise triangles in UV space to texel centres (vectorised numpy).

    Each triangle's pixel-space bounding box (grown by one texel) is enumerated at once for
    a batch of triangles (``np.repeat`` over box sizes, at most ``max_candidates`` texels per
    batch). With ``P_k = uv_k * (W, H) - 0.5`` (pixel-centre coordinates), the barycentrics of
    texel centre ``p`` are ``(b1, b2) = T^{-1} (p - P_0)``, ``T = [P_1 - P_0, P_2 - P_0]``,
    ``b0 = 1 - b1 - b2``. The distance outside edge ``k`` is ``-b_k * alt_k`` pixels
    (``alt_k`` the altitude onto that edge). Texels inside win; texels up to ``margin_px``
    outside every triangle (conservative rasterisation of chart borders) take the nearest
    triangle, with barycentrics clamped to >= 0 and renormalised.

    Returns:
        ``tri [H,W] int32`` (face index, -1 = empty) and ``bary [H,W,3] float32``.
    """
    W, H = int(width), int(height)
    tri_img = np.full(H * W, -1, dtype=np.int32)
    bary_img = np.zeros((H * W, 3), dtype=np.float32)
    best = np.full(H * W, np.inf, dtype=np.float32)

    p = uv[faces].astype(np.float64) * np.array([W, H], dtype=np.float64) - 0.5  # [F,3,2]
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    valid = np.abs(det) > 1e-10
    # inverse of T = [[e1x, e2x], [e1y, e2y]]
    inv = np.zeros((len(faces), 2, 2))
    d = np.where(valid, det, 1.0)
    inv[:, 0, 0] = e2[:, 1] / d
    inv[:, 0, 1] = -e2[:, 0] / d
    inv[:, 1, 0] = -e1[:, 1] / d
    inv[:, 1, 1] = e1[:, 0] / d
    # altitude onto edge k (opposite vertex k): 2*area / |edge k|
    edge_len = np.stack([np.linalg.norm(p[:, 2] - p[:, 1], axis=-1),
                         np.linalg.norm(p[:, 0] - p[:, 2], axis=-1),
                         np.linalg.norm(p[:, 1] - p[:, 0], axis=-1)], axis=-1)
    alt = np.abs(det)[:, None] / np.maximum(edge_len, 1e-12)

    lo = np.floor(p.min(axis=1) - margin_px).astype(np.int64)
    hi = np.ceil(p.max(axis=1) + margin_px).astype(np.int64)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array([W - 1, H - 1]))
    bw = np.clip(hi[:, 0] - lo[:, 0] + 1, 0, None)
    bh = np.clip(hi[:, 1] - lo[:, 1] + 1, 0, None)
    counts = np.where(valid, bw * bh, 0)
    ids = np.nonzero(counts)[0]
    csum = np.cumsum(counts[ids])
    start = 0
    while start < len(ids):
        base = csum[start - 1] if start > 0 else 0
        stop = int(np.searchsorted(csum, base + max_candidates, side="right"))
        stop = max(stop, start + 1)
        t = ids[start:stop]
        cnt = counts[t]
        start = stop
        tr = np.repeat(t, cnt)
        off = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        w_rep = bw[tr]
        col = lo[tr, 0] + off % w_rep
        row = lo[tr, 1] + off // w_rep
        dx = col - p[tr, 0, 0]
        dy = row - p[tr, 0, 1]
        b1 = inv[tr, 0, 0] * dx + inv[tr, 0, 1] * dy
        b2 = inv[tr, 1, 0] * dx + inv[tr, 1, 1] * dy
        b = np.stack([1.0 - b1 - b2, b1, b2], axis=-1)
        outside = np.max(-b * alt[tr], axis=-1)  # pixels outside the triangle (<= 0 inside)
        bad = np.maximum(outside, 0.0)
        keep = outside <= margin_px
        if not keep.any():
            continue
        tr, b, bad = tr[keep], b[keep], bad[keep]
        pix = row[keep] * W + col[keep]
        # best candidate per pixel within the batch, then against earlier batches
        order = np.lexsort((bad, pix))
        pix, tr, b, bad = pix[order], tr[order], b[order], bad[order]
        first = np.ones(len(pix), dtype=bool)
        first[1:] = pix[1:] != pix[:-1]
        pix, tr, b, bad = pix[first], tr[first], b[first], bad[first]
        better = bad < best[pix]
        pix, tr, b, bad = pix[better], tr[better], b[better], bad[better]
        b = np.clip(b, 0.0, None)
        b /= b.sum(axis=-1, keepdims=True)
        best[pix] = bad
        tri_img[pix] = tr
        bary_img[pix] = b
    return tri_img.reshape(H, W), bary_img.reshape(H, W, 3)


def fill_push_pull(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Fill texels where ``mask`` is False by push-pull (pyramid) interpolation.

    Push: 2x2 box-filter premultiplied colour and weight down to 1x1, with weights clipped
    to 1 (``c_{l+1} = sum(c_l w_l) / sum(w_l)``). Pull: from coarse to fine, empty texels
    take the (nearest-upsampled) coarser value. Covered texels are returned unchanged, so
    chart borders get padded with nearby colours and mip-maps / bilinear taps never bleed
    the background into a chart.

    Args:
        img: ``[H,W,C]`` float. mask: ``[H,W]`` bool (True = valid).
    Returns: ``[H,W,C]`` float32.
    """
    img = img.astype(np.float32)
    if mask.all() or not mask.any():
        return img
    colours = [img * mask[..., None]]
    weights = [mask.astype(np.float32)]
    while max(colours[-1].shape[:2]) > 1:
        c, w = colours[-1], weights[-1]
        h, wd = c.shape[:2]
        ph, pw = h % 2, wd % 2
        if ph or pw:
            c = np.pad(c, ((0, ph), (0, pw), (0, 0)))
            w = np.pad(w, ((0, ph), (0, pw)))
        cs = c.reshape(c.shape[0] // 2, 2, c.shape[1] // 2, 2, -1).sum(axis=(1, 3))
        ws = w.reshape(w.shape[0] // 2, 2, w.shape[1] // 2, 2).sum(axis=(1, 3))
        avg = cs / np.maximum(ws, 1e-12)[..., None]
        wc = np.minimum(ws, 1.0)
        colours.append(avg * wc[..., None])
        weights.append(wc)
    filled = colours[-1] / np.maximum(weights[-1], 1e-12)[..., None]
    for lvl in range(len(colours) - 2, -1, -1):
        c, w = colours[lvl], weights[lvl]
        h, wd = c.shape[:2]
        up = np.repeat(np.repeat(filled, 2, axis=0), 2, axis=1)[:h, :wd]
        cur = c / np.maximum(w, 1e-12)[..., None]
        filled = np.where((w > 0)[..., None], w[..., None] * cur + (1 - w[..., None]) * up, up)
    out = np.where(mask[..., None], img, filled)
    return out.astype(np.float32)


@dataclass
class BakedTextures:
    """``base_color [S,S,3] uint8`` (sRGB), ``orm [S,S,3] uint8`` (linear: R=AO, G=roughness,
    B=metallic), ``coverage [S,S] bool`` (texels covered by a triangle before padding)."""

    base_color: np.ndarray
    orm: np.ndarray
    coverage: np.ndarray


def bake_material_textures(
    material: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    positions: np.ndarray,
    normals: np.ndarray,
    uv: np.ndarray,
    faces: np.ndarray,
    texture_size: int = 1024,
    chunk: int = 65536,
    device: torch.device | str | None = None,
) -> BakedTextures:
    """Bake the material field into baseColor and ORM textures.

    Texel centres are rasterised to surface points ``x = sum_k b_k X_{f,k}`` (normalised
    frame) with interpolated unit normals ``n = normalize(sum_k b_k N_{f,k})``;
    ``material(x, n) -> (albedo [N,3] linear, roughness [N], metallic [N])`` is queried in
    chunks. Empty texels are filled by :func:`fill_push_pull`.

    Args:
        positions, normals: ``[V,3]`` per UV-split vertex (normalised frame).
        uv: ``[V,2]``; faces: ``[F,3]``.
    """
    s = int(texture_size)
    tri, bary = rasterize_uv(uv, faces, s, s)
    cov = tri >= 0
    rows, cols = np.nonzero(cov)
    t = tri[rows, cols]
    b = bary[rows, cols].astype(np.float64)
    fv = faces[t]  # [N,3]
    x = np.einsum("nk,nkd->nd", b, positions[fv].astype(np.float64))
    n = np.einsum("nk,nkd->nd", b, normals[fv].astype(np.float64))
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    albedo, rough, metal = evaluate_in_chunks(material, x.astype(np.float32), n.astype(np.float32),
                                              chunk=chunk, device=device)
    lin = np.zeros((s, s, 5), dtype=np.float32)
    lin[rows, cols, :3] = np.nan_to_num(albedo.reshape(-1, 3), nan=0.5)
    lin[rows, cols, 3] = np.nan_to_num(rough.reshape(-1), nan=0.5)
    lin[rows, cols, 4] = np.nan_to_num(metal.reshape(-1), nan=0.0)
    lin = np.clip(fill_push_pull(lin, cov), 0.0, 1.0)
    base = np.round(linear_to_srgb(lin[..., :3]) * 255.0).astype(np.uint8)
    orm = np.empty((s, s, 3), dtype=np.uint8)
    orm[..., 0] = 255
    orm[..., 1] = np.round(lin[..., 3] * 255.0).astype(np.uint8)
    orm[..., 2] = np.round(lin[..., 4] * 255.0).astype(np.uint8)
    return BakedTextures(base_color=base, orm=orm, coverage=cov)
