"""The exported mesh of a real-data run: connected pieces, the largest piece's share, bounds, and
shaded previews seen from the dataset's own cameras.

``python -m bench.mesh_report RUN/mesh.ply --dataset DIR --out PREFIX [--views 0,20,40]`` prints
one JSON line (``faces``, ``pieces``, ``largest_share``, ``bounds_world``, ``bounds_normalized``:
the mesh's extent in the unit-sphere frame, where 1 is the region of interest's radius) and writes
``PREFIX_view<k>.png``: the mesh in grey, lit from the camera, seen through view ``k``'s camera
(pinhole, its field of view), beside that view's photo. The mesh and the cameras are in the
input's world coordinates (``nepf mesh``, ``Scene.world_from_norm``).
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def pieces(mesh) -> tuple[int, float]:
    """``(number of face-connected pieces, faces in the largest / all faces)``."""
    parts = mesh.split(only_watertight=False)
    sizes = sorted((len(p.faces) for p in parts), reverse=True)
    return len(sizes), (sizes[0] / max(1, len(mesh.faces))) if sizes else 0.0


def render_view(mesh, scene, k: int, path: str, size: int = 320) -> None:
    import pyvista as pv
    from PIL import Image
    W, H = scene.width, scene.height
    K = scene.intrinsics[k]
    c2w = scene.world_from_norm @ scene.c2w[k].astype(np.float64)
    scale = np.cbrt(np.linalg.det(scene.world_from_norm[:3, :3]))
    R = c2w[:3, :3] / scale
    eye = c2w[:3, 3]
    h = size * H / max(W, H)
    w = size * W / max(W, H)
    faces = np.hstack([np.full((len(mesh.faces), 1), 3, np.int64), mesh.faces]).ravel()
    pl = pv.Plotter(off_screen=True, window_size=(int(w), int(h)))
    pl.set_background((0.12, 0.13, 0.15))
    pl.add_mesh(pv.PolyData(np.asarray(mesh.vertices, np.float64), faces), color=(0.8, 0.8, 0.8),
                smooth_shading=True)
    pl.camera_position = [tuple(eye), tuple(eye + R[:, 2]), tuple(-R[:, 1])]
    pl.camera.view_angle = float(np.degrees(2 * np.arctan(H / 2 / K[1, 1])))
    pl.render()
    img = pl.screenshot(return_img=True)[..., :3]
    pl.close()
    photo = np.clip(scene.images[k], 0, 1) ** (1 / 2.2)
    photo = np.asarray(Image.fromarray((photo * 255).astype(np.uint8)).resize((img.shape[1], img.shape[0])))
    Image.fromarray(np.concatenate([photo, img], 1)).save(path)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--max-side", type=int, default=400)
    ap.add_argument("--out", required=True, help="prefix of the preview images")
    ap.add_argument("--views", default="0")
    a = ap.parse_args(argv)
    import trimesh
    from nepf_core.data.detect import load_scene
    mesh = trimesh.load(a.mesh, process=False)
    scene = load_scene(a.dataset, max_side=a.max_side)
    n, share = pieces(mesh)
    inv = np.linalg.inv(scene.world_from_norm)
    vn = (np.asarray(mesh.vertices) @ inv[:3, :3].T) + inv[:3, 3]
    for k in (int(v) for v in a.views.split(",")):
        render_view(mesh, scene, k, f"{a.out}_view{k}.png")
    print(json.dumps({"faces": int(len(mesh.faces)), "pieces": n, "largest_share": round(share, 4),
                      "bounds_world": np.asarray(mesh.bounds).round(3).tolist(),
                      "bounds_normalized": [vn.min(0).round(3).tolist(), vn.max(0).round(3).tolist()]}))


if __name__ == "__main__":
    main()
