"""Albedo PSNR of an exported asset's **baked** base-colour texture at a scene's held-out views.

    python -m bench.baked_albedo RUN --scene /work/shared/scenes/spot_textured [--out FILE.json]
        [--save-images DIR] [--run-export [--texture-size 1024] [--max-faces 100000]] [--export-log LOG]

* Reads ``RUN/asset.glb`` (from ``nepf export RUN``): positions (input world coordinates),
  ``TEXCOORD_0`` (glTF top-left origin) and the ``baseColorTexture`` PNG (sRGB).
* Cameras: ``nepf_core.data.detect.load_scene(SCENE/gt/dtu_test)`` (K with pixel centres at
  +0.5, ``c2w`` in that loader's normalised frame, ``world_from_norm``); the mesh is moved
  world -> normalised with ``inv(world_from_norm)``.
* Rasterises the mesh per pixel centre (vectorised numpy, z-buffer, perspective-correct
  barycentrics), interpolates UVs, samples the texture bilinearly after sRGB -> linear.
* Compares with ``SCENE/gt/arrays_test.npz['albedo']`` (linear) on pixels where GT
  ``alpha > 0.5`` AND the mesh is hit, after the per-channel least-squares scale alignment
  (``nepf_core.evaluate.albedo_psnr_aligned``, sRGB PSNR).
* Reports the GLB size, the coverage of the GT foreground, and the export time when it can be
  found (``--run-export`` timing, ``--export-log``, ``summary.json``/``export*.json`` keys, or
  an ``export: ... total Xs`` line in a ``*.log``/``*.txt`` file of the run).

Prints one JSON object (and writes it to ``--out`` when given).
"""

from __future__ import annotations

import argparse
import io
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

# ----------------------------------------------------------------------------------------------
# GLB reading
# ----------------------------------------------------------------------------------------------

_NP_TYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _accessor(gltf, blob: bytes, idx: int) -> np.ndarray:
    acc = gltf.accessors[idx]
    bv = gltf.bufferViews[acc.bufferView]
    dt = np.dtype(_NP_TYPES[acc.componentType])
    n = _NCOMP[acc.type]
    start = (bv.byteOffset or 0) + (acc.byteOffset or 0)
    stride = bv.byteStride or dt.itemsize * n
    if stride == dt.itemsize * n:
        arr = np.frombuffer(blob, dtype=dt, count=acc.count * n, offset=start).reshape(acc.count, n)
    else:
        rows = [np.frombuffer(blob, dtype=dt, count=n, offset=start + i * stride) for i in range(acc.count)]
        arr = np.stack(rows)
    if acc.normalized and dt != np.float32:
        arr = arr.astype(np.float32) / np.iinfo(dt).max
    return arr


def read_glb(path) -> dict:
    """``{"vertices" [V,3], "uv" [V,2], "faces" [F,3], "base_color" [H,W,3|4] uint8, "extras"}``
    (all primitives of all meshes concatenated; node transforms applied)."""
    import pygltflib as g
    from PIL import Image

    gltf = g.GLTF2().load_binary(str(path))
    blob = gltf.binary_blob()
    verts, uvs, faces, tex_idx = [], [], [], set()
    node_mats = _node_matrices(gltf)
    off = 0
    for node_i, node in enumerate(gltf.nodes):
        if node.mesh is None:
            continue
        M = node_mats[node_i]
        for prim in gltf.meshes[node.mesh].primitives:
            if prim.mode not in (None, 4):
                continue
            v = _accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
            v = v @ M[:3, :3].T + M[:3, 3]
            if prim.attributes.TEXCOORD_0 is None:
                raise ValueError(f"{path}: primitive without TEXCOORD_0")
            t = _accessor(gltf, blob, prim.attributes.TEXCOORD_0).astype(np.float64)
            f = (_accessor(gltf, blob, prim.indices).reshape(-1, 3).astype(np.int64) if prim.indices is not None
                 else np.arange(len(v)).reshape(-1, 3))
            verts.append(v); uvs.append(t); faces.append(f + off)
            off += len(v)
            if prim.material is not None:
                pbr = gltf.materials[prim.material].pbrMetallicRoughness
                if pbr is not None and pbr.baseColorTexture is not None:
                    tex_idx.add(pbr.baseColorTexture.index)
    if not verts:
        raise ValueError(f"{path}: no triangle mesh")
    if len(tex_idx) != 1:
        raise ValueError(f"{path}: expected one baseColorTexture, found {sorted(tex_idx)}")
    img = gltf.images[gltf.textures[tex_idx.pop()].source]
    if img.bufferView is not None:
        bv = gltf.bufferViews[img.bufferView]
        data = blob[(bv.byteOffset or 0):(bv.byteOffset or 0) + bv.byteLength]
    else:
        data = (Path(path).parent / img.uri).read_bytes()
    base = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    extras = (gltf.asset.extras or {}) if gltf.asset is not None else {}
    return {"vertices": np.concatenate(verts), "uv": np.concatenate(uvs), "faces": np.concatenate(faces),
            "base_color": base, "extras": extras}


def _node_matrices(gltf) -> list[np.ndarray]:
    """World matrix of every node (identity for the NePF GLB, which has one untransformed node)."""
    local = []
    for n in gltf.nodes:
        if n.matrix:
            local.append(np.asarray(n.matrix, dtype=np.float64).reshape(4, 4).T)
            continue
        M = np.eye(4)
        if n.scale:
            M = M @ np.diag([*n.scale, 1.0])
        if n.rotation:
            x, y, z, w = n.rotation
            R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
            Rm = np.eye(4); Rm[:3, :3] = R
            M = Rm @ M
        if n.translation:
            T = np.eye(4); T[:3, 3] = n.translation
            M = T @ M
        local.append(M)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    out = []
    for i in range(len(gltf.nodes)):
        M, j = local[i], i
        while j in parent:
            j = parent[j]
            M = local[j] @ M
        out.append(M)
    return out


# ----------------------------------------------------------------------------------------------
# rasterisation
# ----------------------------------------------------------------------------------------------

def rasterize(x_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, H: int, W: int,
              near: float = 1e-4, max_pairs: int = 4_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffered triangle rasterisation at pixel centres ``(i + 0.5, j + 0.5)``.

    Args:
        x_cam: ``[V,3]`` camera-space vertices (OpenCV: z forward). faces: ``[F,3]``.
        K: ``[3,3]`` intrinsics (pixel centres at +0.5, as ``Scene.intrinsics``).
    Returns:
        ``face [H,W]`` int64 (-1: no hit) and perspective-correct barycentrics ``[H,W,3]``.
    """
    z = x_cam[:, 2]
    p = x_cam @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / p[:, 2:3]
    fz = z[faces]
    keep = (fz > near).all(1)  # faces crossing the near plane are dropped (objects are far from the cameras)
    fidx = np.nonzero(keep)[0]
    tri = uv[faces[fidx]]                                      # [F,3,2] pixel coords
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5)
    x0 = np.clip(np.ceil(tri[..., 0].min(1) - 0.5), 0, W).astype(np.int64)
    x1 = np.clip(np.floor(tri[..., 0].max(1) - 0.5), -1, W - 1).astype(np.int64)
    y0 = np.clip(np.ceil(tri[..., 1].min(1) - 0.5), 0, H).astype(np.int64)
    y1 = np.clip(np.floor(tri[..., 1].max(1) - 0.5), -1, H - 1).astype(np.int64)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    cnt = np.where((bw > 0) & (bh > 0), bw * bh, 0)
    best_d = np.full(H * W, np.inf)
    best_f = np.full(H * W, -1, dtype=np.int64)
    best_b = np.zeros((H * W, 3))
    order = np.nonzero(cnt)[0]
    csum = np.cumsum(cnt[order])
    start = 0
    while start < len(order):
        base = csum[start - 1] if start else 0
        end = int(np.searchsorted(csum, base + max_pairs, side="right"))
        end = max(end, start + 1)
        sel = order[start:end]
        c = cnt[sel]
        rep = np.repeat(np.arange(len(sel)), c)
        k = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        fi = sel[rep]
        px = x0[fi] + k % bw[fi]
        py = y0[fi] + k // bw[fi]
        t = tri[fi]
        cx, cy = px + 0.5, py + 0.5
        a, b, cc = t[:, 0], t[:, 1], t[:, 2]
        area = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cc[:, 0] - a[:, 0])
        w0 = (b[:, 0] - cx) * (cc[:, 1] - cy) - (b[:, 1] - cy) * (cc[:, 0] - cx)
        w1 = (cc[:, 0] - cx) * (a[:, 1] - cy) - (cc[:, 1] - cy) * (a[:, 0] - cx)
        w2 = (a[:, 0] - cx) * (b[:, 1] - cy) - (a[:, 1] - cy) * (b[:, 0] - cx)
        ok = np.abs(area) > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            bary = np.stack([w0, w1, w2], 1) / area[:, None]
        eps = 1e-7
        ok &= (bary >= -eps).all(1)
        bary, fi, px, py = bary[ok], fi[ok], px[ok], py[ok]
        zf = fz[fidx[fi]]                                       # [P,3]
        iz = (bary / zf).sum(1)
        depth = 1.0 / iz
        pbary = (bary / zf) / iz[:, None]
        pix = py * W + px
        srt = np.lexsort((depth, pix))
        pix_s = pix[srt]
        first = np.ones(len(srt), dtype=bool)
        first[1:] = pix_s[1:] != pix_s[:-1]
        s = srt[first]
        pp = pix[s]
        better = depth[s] < best_d[pp]
        pp, s = pp[better], s[better]
        best_d[pp] = depth[s]
        best_f[pp] = fidx[fi[s]]
        best_b[pp] = pbary[s]
        start = end
    return best_f.reshape(H, W), best_b.reshape(H, W, 3)


def sample_bilinear(tex: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``tex [Ht,Wt,C]`` at glTF UVs ``[N,2]`` (top-left origin, clamp to edge)."""
    Ht, Wt = tex.shape[:2]
    x = np.clip(uv[:, 0], 0.0, 1.0) * Wt - 0.5
    y = np.clip(uv[:, 1], 0.0, 1.0) * Ht - 0.5
    x0 = np.floor(x).astype(np.int64); y0 = np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xa, xb = np.clip(x0, 0, Wt - 1), np.clip(x0 + 1, 0, Wt - 1)
    ya, yb = np.clip(y0, 0, Ht - 1), np.clip(y0 + 1, 0, Ht - 1)
    return ((1 - fx) * (1 - fy) * tex[ya, xa] + fx * (1 - fy) * tex[ya, xb]
            + (1 - fx) * fy * tex[yb, xa] + fx * fy * tex[yb, xb])


def render_baked_albedo(asset: dict, scene) -> tuple[np.ndarray, np.ndarray]:
    """Linear albedo ``[N,H,W,3]`` of the baked texture at every view of ``scene`` and the hit mask ``[N,H,W]``."""
    from nepf_core.data.images import srgb_to_linear

    wfn = np.asarray(scene.world_from_norm, dtype=np.float64)
    vw = np.c_[asset["vertices"], np.ones(len(asset["vertices"]))]
    vn = (vw @ np.linalg.inv(wfn).T)[:, :3]
    tex = srgb_to_linear(asset["base_color"][..., :3].astype(np.float32) / 255.0).astype(np.float64)
    faces, uvv = asset["faces"], asset["uv"]
    N, H, W = scene.n_views, scene.height, scene.width
    out = np.zeros((N, H, W, 3), np.float32)
    hit = np.zeros((N, H, W), bool)
    for k in range(N):
        c2w = np.asarray(scene.c2w[k], dtype=np.float64)
        w2c = np.linalg.inv(c2w)
        x_cam = vn @ w2c[:3, :3].T + w2c[:3, 3]
        f, b = rasterize(x_cam, faces, scene.intrinsics[k], H, W)
        m = f >= 0
        fu = uvv[faces[f[m]]]                                  # [P,3,2]
        uv = (b[m][..., None] * fu).sum(1)
        out[k][m] = sample_bilinear(tex, uv)
        hit[k] = m
    return out, hit


# ----------------------------------------------------------------------------------------------
# export time
# ----------------------------------------------------------------------------------------------

_EXPORT_LINE = re.compile(r"export:.*?\btotal ([0-9.]+)s")


def find_export_time(run: Path, export_log: str | None = None) -> tuple[float | None, str | None]:
    """Export wall time from an export log or the run's JSON files (None when not recorded)."""
    logs = [Path(export_log)] if export_log else []
    logs += sorted(run.glob("*.log")) + sorted(run.glob("*.txt")) + sorted(run.glob("logs/*"))
    for p in logs:
        try:
            m = _EXPORT_LINE.findall(p.read_text(errors="replace"))
        except OSError:
            continue
        if m:
            return float(m[-1]), str(p)
    for name in ("summary.json", "export.json", "export_timings.json", "manifest.json"):
        p = run / name
        if not p.exists():
            continue
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        v = _search_export_time(d)
        if v is not None:
            return v, f"{p}"
    return None, None


def _search_export_time(d, in_export: bool = False):
    if isinstance(d, dict):
        for k, v in d.items():
            kl = str(k).lower()
            here = in_export or "export" in kl or "timing" in kl
            if here and kl in ("total", "total_s", "export_s", "export_wall_s", "export_time_s", "seconds", "wall_s") \
                    and isinstance(v, (int, float)):
                return float(v)
            if isinstance(v, (dict, list)) and ("export" in kl or "timing" in kl or in_export):
                r = _search_export_time(v, True)
                if r is not None:
                    return r
            if kl in ("export_s", "export_wall_s", "export_time_s") and isinstance(v, (int, float)):
                return float(v)
    return None


# ----------------------------------------------------------------------------------------------
# main
# ----------------------------------------------------------------------------------------------

def evaluate(run, scene_dir, *, export_log: str | None = None, save_images: str | None = None,
             export_s: float | None = None) -> dict:
    from nepf_core.data.detect import load_scene
    from nepf_core.evaluate import albedo_psnr_aligned

    run, scene_dir = Path(run), Path(scene_dir)
    glb = run / "asset.glb"
    if not glb.exists():
        raise SystemExit(f"{glb} not found: run `nepf export {run}` first (or pass --run-export)")
    t0 = time.perf_counter()
    asset = read_glb(glb)
    scene = load_scene(scene_dir / "gt" / "dtu_test")
    arrays = np.load(scene_dir / "gt" / "arrays_test.npz")
    gt = arrays["albedo"].astype(np.float32)
    alpha = arrays["alpha"].astype(np.float32) if "alpha" in arrays else None
    if gt.shape[:3] != (scene.n_views, scene.height, scene.width):
        raise SystemExit(f"GT albedo {gt.shape} does not match the test views "
                         f"({scene.n_views}, {scene.height}, {scene.width})")
    fg = alpha > 0.5 if alpha is not None else scene.masks
    t1 = time.perf_counter()
    pred, hit = render_baked_albedo(asset, scene)
    t_render = time.perf_counter() - t1
    m = fg & hit
    res = {"run": str(run), "scene": str(scene_dir), "glb": str(glb), "glb_bytes": glb.stat().st_size,
           "glb_mib": glb.stat().st_size / 2**20, "faces": int(len(asset["faces"])),
           "vertices": int(len(asset["vertices"])), "texture_size": list(asset["base_color"].shape[:2]),
           "views": scene.n_views, "resolution": [scene.width, scene.height],
           "gt_fg_pixels": int(fg.sum()), "hit_pixels": int(hit.sum()), "pixels_used": int(m.sum()),
           "coverage_of_gt_fg": float(m.sum() / max(fg.sum(), 1)),
           "hit_outside_gt_fg": float((hit & ~fg).sum() / max(hit.sum(), 1)),
           "metric": "albedo PSNR (sRGB) after per-channel LS scale in linear space, on GT alpha>0.5 AND mesh hit"}
    if m.sum():
        p, scale = albedo_psnr_aligned(pred, gt, m)
        res["albedo_psnr"], res["scale"] = p, [float(s) for s in scale]
        per_view = []
        for k in range(scene.n_views):
            if m[k].sum():
                per_view.append(albedo_psnr_aligned(pred[k:k + 1] * 1.0, gt[k:k + 1], m[k:k + 1])[0])
            else:
                per_view.append(None)
        res["albedo_psnr_per_view_own_scale"] = per_view
    else:
        res["albedo_psnr"] = None
        res["error"] = "the mesh covers no GT foreground pixel (frame mismatch?)"
    net = _network_albedo_psnr(run)
    if net is not None:
        res["network_albedo_psnr_last_eval"] = net
    if export_s is not None:
        res["export_s"], res["export_s_source"] = export_s, "timed here (--run-export)"
    else:
        res["export_s"], res["export_s_source"] = find_export_time(run, export_log)
    res["render_s"] = t_render
    res["total_s"] = time.perf_counter() - t0
    if save_images:
        _save_images(Path(save_images), pred, gt, m)
    return res


def _network_albedo_psnr(run: Path):
    p = run / "metrics.jsonl"
    if not p.exists():
        return None
    from nepf_core.plots import read_metrics
    vals = [r for r in read_metrics(p) if r.get("kind") == "test" and r.get("albedo_psnr") is not None]
    return vals[-1]["albedo_psnr"] if vals else None


def _save_images(d: Path, pred: np.ndarray, gt: np.ndarray, m: np.ndarray) -> None:
    from PIL import Image

    from nepf_core.data.images import linear_to_srgb
    d.mkdir(parents=True, exist_ok=True)
    for k in range(len(pred)):
        row = np.concatenate([linear_to_srgb(pred[k] * m[k][..., None]), linear_to_srgb(gt[k] * m[k][..., None])], 1)
        Image.fromarray((np.clip(row, 0, 1) * 255 + 0.5).astype(np.uint8)).save(d / f"{k:03d}.png")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.baked_albedo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="run folder with asset.glb")
    p.add_argument("--scene", required=True, help="scene folder with gt/dtu_test and gt/arrays_test.npz")
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.add_argument("--save-images", default=None, help="write baked | GT albedo (sRGB, masked) per view here")
    p.add_argument("--export-log", default=None, help="stdout of `nepf export RUN` (for the export time)")
    p.add_argument("--run-export", action="store_true", help="(re-)export RUN first (CPU) and time it")
    p.add_argument("--texture-size", type=int, default=1024)
    p.add_argument("--max-faces", type=int, default=100_000)
    p.add_argument("--mesh-resolution", type=int, default=256)
    a = p.parse_args(argv)
    export_s = None
    if a.run_export:
        from nepf_core.jobs import export_run
        t0 = time.perf_counter()
        export_run(a.run, device="cpu", texture_size=a.texture_size, max_faces=a.max_faces,
                   mesh_resolution=a.mesh_resolution, log=lambda *x: print(*x, file=sys.stderr))
        export_s = time.perf_counter() - t0
    res = evaluate(a.run, a.scene, export_log=a.export_log, save_images=a.save_images, export_s=export_s)
    txt = json.dumps(res, indent=1)
    if a.out:
        Path(a.out).write_text(txt + "\n")
    print(txt)
    return 0 if res.get("albedo_psnr") is not None else 1


if __name__ == "__main__":
    sys.exit(main())
