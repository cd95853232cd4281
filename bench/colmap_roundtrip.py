"""The COLMAP round trip (issue 34): a scene's DTU form against its COLMAP form, side by side.

``python -m bench.colmap_roundtrip SCENE_DIR --out DIR [--seeds 0,1] [--steps 1200] [--threads 1]``

For a shared scene (``SCENE_DIR/input/dtu``, ``SCENE_DIR/gt``; a generated one has ``SCENE_DIR/dtu``):

1. ``DIR/dtu``: the DTU folder without its ``mask/`` (COLMAP carries no masks, so both forms
   train as a capture without masks would);
2. ``DIR/colmap_txt``: the same cameras and images as a COLMAP text model
   (:func:`nepf_core.data.convert.write_colmap`; no points: the object region comes from the
   points triangulated from the images, as for a COLMAP model without ``points3D``);
   ``DIR/colmap_points_txt`` (form ``colmap_points``): the same model with ``points3D`` as
   COLMAP's structure from motion leaves them on a textured object, here
   :func:`surface_points`: points on the true mesh that face at least two training cameras (the
   DTU form's ``scale_mat`` is the information a COLMAP model does not carry; its points are the
   nearest thing it does);
3. ``fit()`` with ``fast`` for ``--steps`` steps on each form and seed (no held-out evaluation
   during training), then ``nepf eval --test gt/dtu_test --gt-mesh gt/mesh.ply``;

and prints one row per form and seed: held-out PBR (full / masked, dB), Chamfer (world units),
and NeuS's sharpness ``inv_s`` at the end and its minimum over the run (a collapse into fog shows
as an ``inv_s`` that falls instead of rising). Writes ``DIR/roundtrip.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np


def surface_points(mesh_ply: Path, camera_centres: np.ndarray, n: int = 4000, seed: int = 0) -> np.ndarray:
    """``[P, 3]`` world points, area-uniform on the mesh, kept where the outward normal faces at
    least two of ``camera_centres [N, 3]`` (``n . (o - p) > 0``; occlusion is not tested): where
    structure from motion can triangulate a feature."""
    import trimesh

    mesh = trimesh.load(mesh_ply, force="mesh")
    pts, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    normals = mesh.face_normals[faces]
    facing = np.einsum("pk,pck->pc", normals, camera_centres[None, :, :] - pts[:, None, :]) > 0.0
    return np.asarray(pts[facing.sum(1) >= 2], dtype=np.float64)


FORMS = ("dtu", "colmap", "colmap_points")


def prepare(scene_dir: Path, out: Path, forms: tuple[str, ...] = FORMS) -> dict[str, Path]:
    """The scene's training views in each of ``forms`` (module docstring, steps 1 and 2), written
    under ``out`` unless already there; the DTU copy is always made (the others derive from it)."""
    from nepf_core.data.convert import dtu_cameras, write_colmap

    unknown = set(forms) - set(FORMS)
    if unknown:
        raise SystemExit(f"unknown form(s) {', '.join(sorted(unknown))}: choose from {', '.join(FORMS)}")
    source = scene_dir / "input" / "dtu" if (scene_dir / "input").is_dir() else scene_dir / "dtu"
    dtu = out / "dtu"
    if not dtu.exists():
        shutil.copytree(source, dtu, ignore=shutil.ignore_patterns("mask"))
    paths = {"dtu": dtu, "colmap": out / "colmap_txt", "colmap_points": out / "colmap_points_txt"}
    if "colmap" in forms and not paths["colmap"].exists():
        write_colmap(dtu, paths["colmap"], binary=False)
    if "colmap_points" in forms and not paths["colmap_points"].exists():
        centres = dtu_cameras(dtu)["c2w"][:, :3, 3]
        write_colmap(dtu, paths["colmap_points"], binary=False,
                     points=surface_points(scene_dir / "gt" / "mesh.ply", centres))
    return {form: paths[form] for form in dict.fromkeys(("dtu",) + tuple(forms))}


def train_and_score(data: Path, run: Path, gt: Path, seed: int, steps: int, threads: int) -> dict:
    """One ``fit()`` in a child process (its own thread count), then ``nepf eval``; the row."""
    code = ("import torch,sys; torch.set_num_threads(%d)\n"
            "from nepf_core.data.detect import load_scene\n"
            "from nepf_core.jobs import build_config\n"
            "from nepf_core.train import fit\n"
            "cfg = build_config('fast', %d, {'train.seed': %d, 'train.eval_every_s': 0.0, 'train.sync_every': 0})\n"
            "fit(load_scene(sys.argv[1]), sys.argv[2], cfg, device='cpu')\n") % (threads, steps, seed)
    subprocess.run([sys.executable, "-c", code, str(data), str(run)], check=True)
    subprocess.run([sys.executable, "-m", "nepf_core.cli", "eval", str(run), "--test", str(gt / "dtu_test"),
                    "--gt-mesh", str(gt / "mesh.ply")], check=True, stdout=subprocess.DEVNULL)
    ev = json.loads((run / "eval" / "eval.json").read_text())
    train = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    inv_s = [r["inv_s"] for r in train if r.get("kind") == "train" and "inv_s" in r]
    return {"psnr_full": ev.get("psnr_full"), "psnr_masked": ev.get("psnr_masked"), "chamfer_world": ev.get("chamfer_world"),
            "inv_s_end": inv_s[-1] if inv_s else None, "inv_s_min": min(inv_s) if inv_s else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.colmap_roundtrip", description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--steps", type=int, default=1200)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--forms", default="dtu,colmap", help=f"comma-separated, of {', '.join(FORMS)}")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    forms = prepare(a.scene, a.out, tuple(a.forms.split(",")))
    rows = []
    print("| form | seed | PBR full | PBR masked | Chamfer (world) | inv_s end | inv_s min |\n|---|---|---|---|---|---|---|")
    for seed in [int(s) for s in a.seeds.split(",")]:
        for form in a.forms.split(","):
            row = {"form": form, "seed": seed, **train_and_score(forms[form], a.out / f"run_{form}_{seed}",
                                                               a.scene / "gt", seed, a.steps, a.threads)}
            rows.append(row)
            print("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()) + " |",
                  flush=True)
    (a.out / "roundtrip.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
