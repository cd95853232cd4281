"""The ``nepf`` command line: fit, mesh, render, eval, export, make-scene, serve, worker, token.

Service commands (serve, worker, token) are imported lazily from ``api``/``worker`` so the
library never depends on FastAPI or Celery: they come with ``pip install 'nepf[service]'``, and
without it these commands say so.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _device_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="where to run (default: auto)")


def cmd_fit(a) -> int:
    from nepf_core.cli_progress import progress_callbacks
    from nepf_core.jobs import run_job
    cb, bar = progress_callbacks()
    try:
        summary = run_job(a.data, a.out, preset=a.config, iters=a.iters, time_budget_s=a.time_budget,
                          device=a.device, callbacks=cb, resume=a.resume, export=not a.no_export,
                          texture_size=a.texture_size, max_faces=a.faces, test_dir=a.eval_test,
                          gt_mesh=a.gt_mesh, gt_albedo=a.gt_albedo, max_side=a.max_side,
                          max_total_pixels=a.max_total_pixels, holdout_every=a.holdout_every, up_axis=a.up,
                          log=bar.write)
    finally:
        bar.close()
    print(json.dumps({k: summary[k] for k in ("status", "step", "total", "wall_s", "manifest", "split")}, indent=2))
    return 0


def cmd_mesh(a) -> int:
    import trimesh  # noqa: F401

    from nepf_core.train import load_model
    from nepf_core.meshing import world_mesh
    from nepf_core.model import ModelFieldQuery
    model, cfg, state = load_model(a.run, a.device)
    m = world_mesh(ModelFieldQuery(model), state["extra"]["world_from_norm"], a.resolution,
                   device=next(model.parameters()).device)
    out = Path(a.run) / "mesh.ply"
    m.export(out)
    print(f"wrote {out} ({len(m.vertices)} vertices, {len(m.faces)} faces, input world coordinates)")
    return 0


def _encode_channel(name: str, arr):
    import numpy as np

    from nepf_core.color import linear_to_srgb
    if name in ("pbr", "radiance", "albedo"):
        img = linear_to_srgb(arr)
    elif name in ("normal", "light_dir"):
        img = (arr + 1.0) * 0.5
    elif name == "light_intensity":
        img = arr / max(float(arr.max()), 1e-6)
    elif name == "depth":
        img = arr / max(float(arr.max()), 1e-6)
    else:
        img = arr
    img = np.clip(img, 0, 1)
    if img.shape[-1] == 1:
        img = img[..., 0]
    return (img * 255 + 0.5).astype("uint8")


def render_run(run, cameras, out, device="auto", stride: int = 1, max_side: int = 0,
               max_total_pixels: int | None = None) -> dict:
    """Render every camera of the dataset ``cameras`` with the run's model, at the working
    resolution ``max_side`` (0: full size), refusing more than ``max_total_pixels`` decoded pixels
    (None/0: no cap); see ``nepf render``."""
    import numpy as np
    from PIL import Image

    from nepf_core.evaluate import CHANNELS, render_view
    from nepf_core.train import load_model
    from nepf_core.rays import PixelSampler
    from nepf_core.reframe import load_held_out
    model, cfg, state = load_model(run, device)
    W = np.asarray(state["extra"]["world_from_norm"])
    scene = load_held_out(cameras, W, max_side=max_side, max_total_pixels=max_total_pixels)
    dev = next(model.parameters()).device
    sampler = PixelSampler(scene, dev)
    rot = W[:3, :3] / float(np.cbrt(abs(np.linalg.det(W[:3, :3]))))
    out = Path(out)
    arrays = {c: [] for c in CHANNELS}
    for k in range(scene.n_views):
        r = render_view(model, sampler, k, cfg.render, stride=stride, rotation=rot, shading=state["run_state"].shading())
        for c in CHANNELS:
            arrays[c].append(r[c])
            if c == "depth":
                continue
            (out / c).mkdir(parents=True, exist_ok=True)
            Image.fromarray(_encode_channel(c, r[c])).save(out / c / f"{k:03d}.png")
    np.savez_compressed(out / "arrays.npz", **{c: np.stack(v) for c, v in arrays.items()})
    return {"views": scene.n_views, "out": str(out), "scene": scene}


def cmd_render(a) -> int:
    info = render_run(a.run, a.cameras, a.out, a.device, a.stride, max_side=a.max_side,
                      max_total_pixels=a.max_total_pixels)
    s = info["scene"]
    print(f"rendered {info['views']} views at {s.width}x{s.height} px ({_side_rule(a.max_side)}) into {info['out']}")
    return 0


def cmd_relight(a) -> int:
    from nepf_core.relight.run import relight_run
    info = relight_run(a.run, a.lights, a.cameras, a.out, a.device, max_side=a.max_side, bsdf_kind=a.bsdf,
                       max_total_pixels=a.max_total_pixels)
    w, h = info["working_size"]
    print(f"relit {info['views']} views at {w}x{h} px ({_side_rule(a.max_side)}) under {info['lights']} lights "
          f"({info['bsdf_kind']} BSDF) into {info['out']}")
    return 0


def cmd_eval(a) -> int:
    import numpy as np

    from nepf_core.data.detect import load_scene
    from nepf_core.color import linear_to_srgb
    from nepf_core.evaluate import psnr, ssim
    from nepf_core.train import load_model
    from nepf_core.model import ModelFieldQuery
    out_dir = Path(a.out) if a.out else Path(a.run) / "eval"
    info = render_run(a.run, a.test, out_dir / "renders", a.device, max_side=a.max_side,
                      max_total_pixels=a.max_total_pixels)
    scene = info["scene"]
    print(f"eval: {scene.n_views} views at {scene.width}x{scene.height} px ({_side_rule(a.max_side)})", file=sys.stderr)
    arr = np.load(out_dir / "renders" / "arrays.npz")
    pred, gt = linear_to_srgb(arr["pbr"]), linear_to_srgb(scene.images)
    rad = linear_to_srgb(arr["radiance"])   # the radiance network's colour: what a plain NeuS reports
    res = {"views": scene.n_views, "working_size": [scene.width, scene.height], "psnr_full": psnr(pred, gt),
           "ssim_full": float(np.mean([ssim(pred[i], gt[i]) for i in range(len(gt))])),
           "radiance_psnr_full": psnr(rad, gt)}
    if scene.masks is not None:
        m = scene.masks
        res["psnr_masked"] = psnr(pred, gt, m)
        res["radiance_psnr_masked"] = psnr(rad, gt, m)
        res["ssim_masked"] = float(np.nanmean([ssim(pred[i], gt[i], m[i]) for i in range(len(gt))]))
    if a.gt_mesh:
        from nepf_core.meshing import chamfer_against_gt
        model, cfg, state = load_model(a.run, a.device)
        cw, cu = chamfer_against_gt(ModelFieldQuery(model), state["extra"]["world_from_norm"], a.gt_mesh,
                                    resolution=a.resolution, device=next(model.parameters()).device)
        res["chamfer_world"], res["chamfer_unit_sphere"] = cw, cu
    if a.relight or a.gt_maps:  # relight PSNR and material scores (nepf_core/relight/metrics.py)
        from nepf_core.relight.evaluation import eval_section
        res.update(eval_section(a.run, a.test, arr, scene.images, scene.masks, out_dir, relight_dir=a.relight,
                                gt_maps=a.gt_maps, device=a.device, max_side=a.max_side))
    res["conventions"] = ("psnr_*/ssim_*: the surface PBR colour; radiance_psnr_*: the radiance network's "
                          "volume-rendered colour. PSNR/SSIM on sRGB values in [0,1]; masked = GT foreground pixels only (SSIM: "
                          "the mean of the SSIM map over them); Chamfer = point-to-mesh, mean of both directions, "
                          "100k samples per mesh")
    (out_dir).mkdir(parents=True, exist_ok=True)
    (out_dir / "eval.json").write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))
    return 0


def cmd_export(a) -> int:
    from nepf_core.jobs import export_run
    p = export_run(a.run, device=a.device, texture_size=a.texture_size, max_faces=a.faces,
                   mesh_resolution=a.resolution, previews=not a.no_previews, up_axis=a.up)
    print(f"wrote {p}")
    return 0


def _up_axis_type(value: str) -> str:
    from nepf_core.up_axis import parse_up_axis
    try:
        return parse_up_axis(value) or "auto"
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _join_up_values(argv: list[str]) -> list[str]:
    """``--up -z`` as ``--up=-z``: argparse reads a value starting with ``-`` as an option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] == "--up" and arg.lower() in ("-x", "-y", "-z"):
            out[-1] = f"--up={arg}"
        else:
            out.append(arg)
    return out


def _up_arg(p: argparse.ArgumentParser, default_help: str) -> None:
    from nepf_core.up_axis import UP_CHOICES
    p.add_argument("--up", default=None, type=_up_axis_type, metavar="AXIS",
                   help="the input world's up axis, one of " + ", ".join(UP_CHOICES) + "; the GLB, lights.json and "
                        "light_field.json are rotated so that it becomes glTF's +Y (" + default_help + ")")


def _max_side_arg(p: argparse.ArgumentParser) -> None:
    """``--max-side`` and ``--max-total-pixels``, with the service's defaults (``nepf_core.limits``)."""
    from nepf_core.limits import DEFAULT_IMAGE_SIDE, MAX_TOTAL_PIXELS
    p.add_argument("--max-side", type=int, default=DEFAULT_IMAGE_SIDE, metavar="PX",
                   help="working resolution: images whose long side exceeds PX are area-resampled to it at load, "
                        f"intrinsics scaled to match (default {DEFAULT_IMAGE_SIDE}, the service's "
                        "NEPF_DEFAULT_IMAGE_SIDE; 0: full resolution)")
    p.add_argument("--max-total-pixels", type=int, default=MAX_TOTAL_PIXELS, metavar="N",
                   help="refuse a dataset whose images hold more than N pixels in all, read from the headers "
                        f"before decoding (default {MAX_TOTAL_PIXELS:,}, the service's NEPF_MAX_TOTAL_PIXELS: "
                        "about 4.8 GB of float32 images at full size; 0: no cap)")


def _side_rule(max_side: int) -> str:
    return f"long side at most {max_side} px; --max-side 0: full size" if max_side else "full resolution"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="nepf", description="NePF: single-stage neural inverse rendering")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("fit", help="train NePF on a dataset folder (DTU, Blender, nerfstudio, instant-ngp or COLMAP)")
    p.add_argument("data", help="dataset folder")
    p.add_argument("--out", required=True, help="run folder to write")
    p.add_argument("--config", default="fast", choices=["paper", "fast", "tiny"], help="preset (default: fast)")
    p.add_argument("--iters", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--time-budget", type=float, default=None, help="stop after this many seconds of training")
    p.add_argument("--resume", action="store_true", help="continue from RUN/checkpoints/latest.pt")
    p.add_argument("--eval-test", default=None, help="held-out dataset folder evaluated on a wall-clock schedule")
    p.add_argument("--holdout-every", type=int, default=None, metavar="N",
                   help="hold views 0, N, 2N, ... out of training and evaluate them on the wall-clock schedule "
                        "(0: train on all; N in 2..views/2; default: 8 for 16 or more views, else 0, and 0 "
                        "with --eval-test)")
    p.add_argument("--gt-mesh", default=None, help="ground-truth mesh (world coordinates) for Chamfer")
    p.add_argument("--gt-albedo", default=None, help="npz with 'albedo' [N,H,W,3] of the held-out views")
    p.add_argument("--no-export", action="store_true", help="skip the GLB/texture export at the end")
    p.add_argument("--texture-size", type=int, default=None, choices=[256, 512, 1024, 2048],
                   help="baked texture size (default: 1024; 256 for tiny)")
    p.add_argument("--faces", type=int, default=None, help="face budget of the exported mesh (default 100k; 5k for tiny)")
    _up_arg(p, "default auto: the mean of the cameras' up vectors, snapped to the nearest axis")
    _max_side_arg(p)
    _device_arg(p)
    p.set_defaults(fn=cmd_fit)

    p = sub.add_parser("mesh", help="write RUN/mesh.ply (marching cubes at SDF=0, input world coordinates)")
    p.add_argument("run")
    p.add_argument("--resolution", type=int, default=256)
    _device_arg(p)
    p.set_defaults(fn=cmd_mesh)

    p = sub.add_parser("render", help="render every camera of another dataset folder, all channels")
    p.add_argument("run")
    p.add_argument("--cameras", required=True, help="dataset folder whose cameras to render")
    p.add_argument("--out", required=True)
    p.add_argument("--stride", type=int, default=1, help="render every N-th pixel")
    _max_side_arg(p)
    _device_arg(p)
    p.set_defaults(fn=cmd_render)

    p = sub.add_parser("relight", help="render the recovered asset under point lights (lights.json), with shadows")
    p.add_argument("run")
    p.add_argument("--lights", required=True, help='lights.json: {"lights": [{"type": "point", "position_world": '
                   '[x,y,z], "intensity_rgb": [r,g,b]}, ...]} in the input\'s world coordinates (radiant intensity)')
    p.add_argument("--cameras", required=True, help="dataset folder whose cameras to render")
    p.add_argument("--out", required=True, help="folder for light_K/NNN.png and arrays.npz")
    p.add_argument("--bsdf", default=None, choices=["paper", "gltf"], help="BSDF (default: the run's)")
    _max_side_arg(p)
    _device_arg(p)
    p.set_defaults(fn=cmd_relight)

    p = sub.add_parser("eval", help="PSNR/SSIM of the surface PBR on test views, Chamfer to a GT mesh")
    p.add_argument("run")
    p.add_argument("--test", required=True, help="held-out dataset folder")
    p.add_argument("--gt-mesh", default=None)
    p.add_argument("--resolution", type=int, default=256, help="marching-cubes resolution for Chamfer")
    p.add_argument("--out", default=None, help="folder for renders and eval.json (default RUN/eval)")
    p.add_argument("--relight", default=None, help="relight ground truth (gt/relight: lights.json, arrays.npz) "
                   "for the cameras of --test: adds relight_psnr")
    p.add_argument("--gt-maps", default=None, help="GT maps of the --test views (gt/arrays_test.npz): adds albedo "
                   "PSNR (all / lit), roughness and metallic MAE, normal MAE")
    _max_side_arg(p)
    _device_arg(p)
    p.set_defaults(fn=cmd_eval)

    p = sub.add_parser("export", help="GLB with baked PBR textures, light field, previews, manifest")
    p.add_argument("run")
    p.add_argument("--texture-size", type=int, default=1024, choices=[256, 512, 1024, 2048])
    p.add_argument("--faces", type=int, default=100_000)
    p.add_argument("--resolution", type=int, default=256, help="marching-cubes resolution")
    p.add_argument("--no-previews", action="store_true")
    _up_arg(p, "default: an earlier --up of this run (frame.json), else auto from the cameras")
    _device_arg(p)
    p.set_defaults(fn=cmd_export)

    p = sub.add_parser("make-scene", help="write a synthetic ground-truth scene (DTU + Blender + gt/)")
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(fn=lambda a: _delegate("nepf_core.data.synth", "main", a.rest))

    for name, mod, fn in (("serve", "api.commands", "serve_main"), ("worker", "worker.commands", "worker_main"),
                          ("token", "api.commands", "token_main")):
        p = sub.add_parser(name, help=f"service: {name} (see docs/SERVICE.md)", add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(fn=lambda a, mod=mod, fn=fn: _delegate(mod, fn, a.rest))
    return ap


#: top-level modules of the ``service`` extra (pyproject.toml): without them serve/worker/token
#: stop with an install hint instead of a traceback
SERVICE_MODULES = frozenset({"fastapi", "starlette", "uvicorn", "python_multipart", "pydantic",
                             "pydantic_settings", "sqlalchemy", "alembic", "psycopg", "celery",
                             "kombu", "redis"})


def _delegate(module: str, fn: str, argv: list[str]) -> int:
    import importlib
    try:
        return int(getattr(importlib.import_module(module), fn)(list(argv)) or 0)
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in SERVICE_MODULES:
            raise
        print(f"nepf: this command needs the NePF service, which is not installed (no module named "
              f"{missing!r}); install nepf[service]: pip install 'nepf[service]'", file=sys.stderr)
        return 2


SERVICE_COMMANDS = {"serve": ("api.commands", "serve_main"), "worker": ("worker.commands", "worker_main"),
                    "token": ("api.commands", "token_main"), "make-scene": ("nepf_core.data.synth", "main")}


def main(argv: list[str] | None = None) -> int:
    from nepf_core.data.errors import DatasetError
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in SERVICE_COMMANDS:  # forwarded unchanged (options included)
        mod, fn = SERVICE_COMMANDS[argv[0]]
        return _delegate(mod, fn, argv[1:])
    ap = build_parser()
    a = ap.parse_args(_join_up_values(argv))
    try:
        return int(a.fn(a) or 0)
    except DatasetError as e:
        print(f"nepf: invalid dataset: {e}", file=sys.stderr)
        if getattr(e, "code", None) == "too_many_pixels":
            cap = getattr(a, "max_total_pixels", None) or 0
            print(f"nepf: the cap is --max-total-pixels {cap:,} (default: the service's NEPF_MAX_TOTAL_PIXELS); it "
                  "counts the images' full-size pixels, whatever --max-side; give a larger value, or 0 for none, "
                  "if this machine has the memory (12 bytes per pixel at full size)", file=sys.stderr)
        return 2
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        print(f"nepf: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
