"""Micro-benchmark of SDF grid encodings, regularisers and normal schemes (CPU or CUDA).

    python bench/encodings.py [--n 65536] [--reps 5] [--device cpu] [--clock wall|cpu]
                              [--only enc,tv,normals,step]

Times forward+backward (loss = sum(out * w) with a fixed random w) of each encoding on
N uniform points in [-1,1]^3, min of --reps after 2 warm-up runs, with
torch.get_num_threads() threads. Results feed docs/FAST.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from nepf_core.fields.fd_normals import sdf_gradient_fd  # noqa: E402
from nepf_core.fields.grid_encoding import GridConfig, MultiResGrid, SphereInitSDF  # noqa: E402


CLOCK = time.perf_counter  # --clock cpu: time.process_time (this process' CPU seconds, all threads)


def timeit(fn, reps: int, device: torch.device) -> float:
    for _ in range(2):
        fn()
    ts = []
    for _ in range(reps):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = CLOCK()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        ts.append(CLOCK() - t0)
    return min(ts)  # min: robust to other processes sharing the cores


# ---------------------------------------------------------------- bench-only variants
class GatherGrid(nn.Module):
    """Dense multi-res grid, all levels in one flat table, trilinear by one gather."""

    def __init__(self, resolutions, f):
        super().__init__()
        self.res = resolutions
        sizes = [r**3 for r in resolutions]
        self.offsets = [0]
        for s in sizes[:-1]:
            self.offsets.append(self.offsets[-1] + s)
        self.table = nn.Parameter(torch.randn(sum(sizes), f) * 1e-4)
        self.register_buffer("res_t", torch.tensor(resolutions, dtype=torch.float32))
        self.register_buffer("off_t", torch.tensor(self.offsets, dtype=torch.long))

    def forward(self, x):
        n = x.shape[0]
        u = (x.unsqueeze(1) + 1) * 0.5 * (self.res_t.view(1, -1, 1) - 1)  # [N,L,3]
        i0 = u.floor().clamp_max(self.res_t.view(1, -1, 1) - 2).clamp_min(0)
        w = u - i0
        i0 = i0.long()
        r = self.res_t.long().view(1, -1)
        corners = []
        weights = []
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    idx = (i0[..., 0] + dx) + r * ((i0[..., 1] + dy) + r * (i0[..., 2] + dz))
                    corners.append(idx + self.off_t.view(1, -1))
                    wx = w[..., 0] if dx else 1 - w[..., 0]
                    wy = w[..., 1] if dy else 1 - w[..., 1]
                    wz = w[..., 2] if dz else 1 - w[..., 2]
                    weights.append(wx * wy * wz)
        idx = torch.stack(corners, -1)  # [N,L,8]
        wts = torch.stack(weights, -1)
        v = self.table[idx.view(-1)].view(n, len(self.res), 8, -1)
        return (v * wts.unsqueeze(-1)).sum(2).reshape(n, -1)


class HashGrid(nn.Module):
    """Pure-torch instant-ngp hash grid (trilinear, 3-prime XOR hash)."""

    def __init__(self, n_levels=16, f=2, log2_t=19, base=16, max_res=2048):
        super().__init__()
        b = (max_res / base) ** (1 / (n_levels - 1))
        self.res = [int(base * b**level) for level in range(n_levels)]
        self.t = 2**log2_t
        self.table = nn.Parameter(torch.randn(n_levels, self.t, f) * 1e-4)
        self.register_buffer("res_t", torch.tensor(self.res, dtype=torch.float32))

    def forward(self, x):
        n, nl = x.shape[0], len(self.res)
        u = (x.unsqueeze(1) + 1) * 0.5 * self.res_t.view(1, -1, 1)
        i0 = u.floor()
        w = u - i0
        i0 = i0.long()
        lvl = torch.arange(nl, device=x.device).view(1, -1) * self.t
        out = 0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    h = ((i0[..., 0] + dx) ^ ((i0[..., 1] + dy) * 2654435761) ^ ((i0[..., 2] + dz) * 805459861)) % self.t
                    wx = w[..., 0] if dx else 1 - w[..., 0]
                    wy = w[..., 1] if dy else 1 - w[..., 1]
                    wz = w[..., 2] if dz else 1 - w[..., 2]
                    v = self.table.view(-1, self.table.shape[-1])[(h + lvl).view(-1)].view(n, nl, -1)
                    out = out + v * (wx * wy * wz).unsqueeze(-1)
        return out.reshape(n, -1)


class TriPlane(nn.Module):
    """Tri-plane [3, F, R, R]; features of the xy, yz, xz planes concatenated (or summed)."""

    def __init__(self, r=256, f=16, reduce="cat"):
        super().__init__()
        self.planes = nn.Parameter(torch.randn(3, f, r, r) * 1e-4)
        self.reduce = reduce

    def forward(self, x):
        n = x.shape[0]
        g = torch.stack([x[:, [0, 1]], x[:, [1, 2]], x[:, [0, 2]]], 0).view(3, 1, n, 2)
        v = F.grid_sample(self.planes, g, align_corners=True, padding_mode="border")  # [3,F,1,N]
        v = v.view(3, -1, n)
        if self.reduce == "sum":
            return v.sum(0).t()
        return v.permute(2, 0, 1).reshape(n, -1)


class SingleGrid(nn.Module):
    def __init__(self, r=128, f=8):
        super().__init__()
        self.v = nn.Parameter(torch.randn(1, f, r, r, r) * 1e-4)

    def forward(self, x):
        n = x.shape[0]
        return F.grid_sample(self.v, x.view(1, n, 1, 1, 3), align_corners=True, padding_mode="border").view(-1, n).t()


def mres(levels, base, mx, f):
    g = MultiResGrid(GridConfig(n_levels=levels, base_resolution=base, max_resolution=mx, features_per_level=f))
    g.set_active_levels(levels)
    return g


# ---------------------------------------------------------------- benches
def bench_encodings(n, reps, dev):
    x = torch.rand(n, 3, device=dev) * 2 - 1
    cases = [
        ("dense 1 lvl 128^3 x8 (grid_sample)", SingleGrid(128, 8)),
        ("dense 4 lvl 16..128 x4 (loop)", mres(4, 16, 128, 4)),
        ("dense 4 lvl 16..128 x2 (loop)", mres(4, 16, 128, 2)),
        ("dense 6 lvl 16..128 x2 (loop)", mres(6, 16, 128, 2)),
        ("dense 5 lvl 16..256 x2 (loop)", mres(5, 16, 256, 2)),
        ("dense 4 lvl 16..128 x4 (flat gather)", GatherGrid(mres(4, 16, 128, 4).resolutions, 4)),
        ("dense 4 lvl 16..128 x2 (flat gather)", GatherGrid(mres(4, 16, 128, 2).resolutions, 2)),
        ("tri-plane 3x256^2 x16 (concat)", TriPlane(256, 16)),
        ("tri-plane 3x256^2 x8 (concat)", TriPlane(256, 8)),
        ("hash 16 lvl x2, T=2^19", HashGrid(16, 2, 19)),
        ("hash 8 lvl x2, T=2^17", HashGrid(8, 2, 17, 16, 512)),
    ]
    rows = []
    for name, enc in cases:
        enc = enc.to(dev)
        with torch.no_grad():
            d = enc(x[:8]).shape[1]
        w = torch.randn(d, device=dev)

        def fb():
            enc.zero_grad(set_to_none=True)
            (enc(x) @ w).sum().backward()

        def fwd():
            with torch.no_grad():
                enc(x)

        n_par = sum(p.numel() for p in enc.parameters())
        rows.append((name, d, n_par, timeit(fwd, reps, dev), timeit(fb, reps, dev)))
        print(f"| {name} | {d} | {n_par/1e6:.2f} M | {rows[-1][3]*1e3:.0f} | {rows[-1][4]*1e3:.0f} |", flush=True)
    return rows


def bench_tv(reps, dev):
    g = mres(4, 16, 128, 4).to(dev)
    for n_cells in (None, 65536, 8192):
        def fb():
            g.zero_grad(set_to_none=True)
            g.tv_loss(n_cells).backward()

        print(f"| tv_loss 4 lvl 16..128 x4, n_cells={n_cells} | {timeit(fb, reps, dev)*1e3:.0f} |", flush=True)


def bench_normals(n, reps, dev):
    torch.manual_seed(0)
    g = mres(4, 16, 128, 4)
    sdf = SphereInitSDF(g, width=64, n_hidden=1, n_feat=15).to(dev)
    with torch.no_grad():
        for p in sdf.head.parameters():
            p.normal_(0, 0.05)
    x = torch.rand(n, 3, device=dev) * 2 - 1
    eps = 0.5 * g.active_cell_size()

    def plain():
        sdf.zero_grad(set_to_none=True)
        s = sdf.sdf_only(x)
        s.square().mean().backward()

    def autograd_dbl():
        sdf.zero_grad(set_to_none=True)
        xx = x.clone().requires_grad_(True)
        s = sdf.sdf_only(xx)
        (gr,) = torch.autograd.grad(s.sum(), xx, create_graph=True)
        (s.square().mean() + (gr.norm(dim=-1) - 1).square().mean()).backward()

    def fd(scheme, center):
        def run():
            sdf.zero_grad(set_to_none=True)
            gr, s = sdf_gradient_fd(sdf.sdf_only, x, eps, scheme, center)
            (s.square().mean() + (gr.norm(dim=-1) - 1).square().mean()).backward()

        return run

    for name, fn in [
        ("sdf only (no normals)", plain),
        ("autograd double backward", autograd_dbl),
        ("FD central, centre evaluated (7N)", fd("central", "eval")),
        ("FD central, centre = mean (6N)", fd("central", "mean")),
        ("FD tetra, centre evaluated (5N)", fd("tetra", "eval")),
        ("FD tetra, centre = mean (4N)", fd("tetra", "mean")),
    ]:
        print(f"| {name} | {timeit(fn, reps, dev)*1e3:.0f} |", flush=True)


def bench_step(reps, dev):
    """One simplified NeuS training step: sample -> SDF (+FD normals) -> colour MLP -> alpha
    from sample SDFs -> weights -> rgb + eikonal loss -> backward -> Adam step.
    Cases are timed interleaved (rep-major) so that load from other processes hits all
    cases alike; min over reps of both wall and process-CPU time is reported."""
    from nepf_core.render.occupancy import OccupancyConfig, OccupancyGrid

    def make(levels, base, mx, f, n_rays, n_samp, skip, scheme, center, width=64):
        torch.manual_seed(0)
        g = mres(levels, base, mx, f)
        sdf = SphereInitSDF(g, width=width, n_hidden=1, n_feat=15).to(dev)
        color = nn.Sequential(nn.Linear(15 + 3 + 3, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                              nn.Linear(width, 3), nn.Sigmoid()).to(dev)
        opt = torch.optim.Adam(list(sdf.parameters()) + list(color.parameters()), lr=1e-3)
        occ = OccupancyGrid(OccupancyConfig(resolution=64)).to(dev)
        inv_s = 200.0
        info = {}
        if skip:
            t0, c0 = time.perf_counter(), time.process_time()
            occ.update(sdf.sdf_only, inv_s)
            info["upd"] = (time.perf_counter() - t0, time.process_time() - c0)
        o = torch.randn(n_rays, 3, device=dev)
        o = o / o.norm(dim=1, keepdim=True) * 2.5
        d = torch.randn(n_rays, 3, device=dev) * 0.3 - o
        d = d / d.norm(dim=1, keepdim=True)
        b = (o * d).sum(1)
        disc = (b * b - (o * o).sum(1) + 1).clamp_min(0).sqrt()
        near, far = -b - disc, -b + disc
        target = torch.rand(n_rays, 3, device=dev)
        eps = 0.5 * g.active_cell_size()

        def step():
            if skip:
                rs = occ.sample_along_rays(o, d, near, far, n_samp, perturb=True)
                t = rs.t_vals
                info["skip"] = float(rs.skip_fraction.mean())
            else:
                u = (torch.arange(n_samp, device=dev) + torch.rand(n_rays, n_samp, device=dev)) / n_samp
                t = near[:, None] + (far - near)[:, None] * u
            x = (o[:, None] + d[:, None] * t[..., None]).reshape(-1, 3)
            holder = {}

            def f_sdf(p):
                s_, fe = sdf(p)
                holder["f"] = fe
                return s_

            grad, s = sdf_gradient_fd(f_sdf, x, eps, scheme, center)
            fe = holder["f"][-x.shape[0]:] if center == "eval" else holder["f"][: x.shape[0]]
            n = grad / grad.norm(dim=1, keepdim=True).clamp_min(1e-6)
            rgb = color(torch.cat([fe, n, d.repeat_interleave(n_samp, 0)], 1)).view(n_rays, n_samp, 3)
            s = s.view(n_rays, n_samp)
            cdf = torch.sigmoid(s * inv_s)
            alpha = ((cdf[:, :-1] - cdf[:, 1:] + 1e-5) / (cdf[:, :-1] + 1e-5)).clip(0, 1)
            trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha + 1e-7], 1), 1)[:, :-1]
            w = alpha * trans
            img = (w[..., None] * rgb[:, :-1]).sum(1)
            loss = (img - target).abs().mean() + 0.1 * (grad.norm(dim=1) - 1).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        return step, info

    cases = [
        ("baseline-like: 1 lvl 96^3 x8, uniform", (1, 96, 96, 8, 1024, 48, False, "central", "eval")),
        ("4 lvl 16..128 x2, uniform", (4, 16, 128, 2, 1024, 48, False, "tetra", "mean")),
        ("4 lvl 16..128 x2, occupancy", (4, 16, 128, 2, 1024, 24, True, "tetra", "mean")),
        ("4 lvl 16..128 x2, occupancy", (4, 16, 128, 2, 1024, 24, True, "central", "mean")),
        ("4 lvl 16..128 x4, occupancy", (4, 16, 128, 4, 1024, 24, True, "tetra", "mean")),
        ("4 lvl 16..128 x2, occupancy", (4, 16, 128, 2, 512, 32, True, "tetra", "mean")),
        ("4 lvl 16..128 x2, occupancy", (4, 16, 128, 2, 1024, 16, True, "tetra", "mean")),
    ]
    built = [(name, args, *make(*args)) for name, args in cases]
    for _, _, step, _ in built:
        step()  # warm-up
    wall = [float("inf")] * len(built)
    cpu = [float("inf")] * len(built)
    for _ in range(reps):
        for i, (_, _, step, _) in enumerate(built):
            t0, c0 = time.perf_counter(), time.process_time()
            step()
            wall[i] = min(wall[i], time.perf_counter() - t0)
            cpu[i] = min(cpu[i], time.process_time() - c0)
    for i, (name, args, _, info) in enumerate(built):
        extra = ""
        if "upd" in info:
            extra = f" {info['upd'][0]*1e3:.0f} / {info['upd'][1]*1e3:.0f} | {info['skip']:.2f}"
        else:
            extra = " - | 0"
        print(f"| {name} | {args[4]}x{args[5]} | {args[7]}/{args[8]} | {wall[i]*1e3:.0f} | {cpu[i]*1e3:.0f} |{extra} |", flush=True)


def bench_quality(iters, dev):
    """Fit a rotated torus SDF (R=0.45, r=0.12, tilted 30 deg about x) by regression with
    each encoding + the same head, ``iters`` Adam steps on 8192 points (half near the
    surface); report SDF MAE and normal angle error on held-out near-surface points."""
    import math

    c, s_ = math.cos(math.pi / 6), math.sin(math.pi / 6)
    rot = torch.tensor([[1, 0, 0], [0, c, -s_], [0, s_, c]], device=dev)

    def torus(x):
        q = x @ rot
        a = torch.stack([torch.linalg.vector_norm(q[:, :2], dim=1) - 0.45, q[:, 2]], 1)
        return torch.linalg.vector_norm(a, dim=1) - 0.12

    def near_surface(n, gen):
        x = torch.rand(n, 3, generator=gen, device=dev) * 2 - 1
        for _ in range(3):  # project towards the surface, then jitter
            x = x.requires_grad_(True)
            f = torus(x)
            (g,) = torch.autograd.grad(f.sum(), x)
            x = (x - f[:, None] * g).detach()
        return x + 0.02 * torch.randn(n, 3, generator=gen, device=dev)

    gen = torch.Generator(device=dev).manual_seed(0)
    xt = near_surface(20000, gen)
    ft = torus(xt)
    xg = xt.clone().requires_grad_(True)
    (nt,) = torch.autograd.grad(torus(xg).sum(), xg)

    def mk_dense():
        return mres(4, 16, 128, 2)

    def mk_tri():
        t = TriPlane(256, 8)
        t.n_output_dims = 24
        return t

    for name, mk in [("dense 4 lvl 16..128 x2", mk_dense), ("tri-plane 3x256^2 x8", mk_tri)]:
        torch.manual_seed(0)
        enc = mk()
        sdf = SphereInitSDF(enc, radius=0.5, width=64, n_hidden=1).to(dev)
        opt = torch.optim.Adam([{"params": enc.parameters(), "lr": 1e-2}, {"params": sdf.head.parameters(), "lr": 1e-3}])
        t0 = CLOCK()
        for _ in range(iters):
            x = torch.cat([near_surface(4096, gen), torch.rand(4096, 3, generator=gen, device=dev) * 2 - 1])
            loss = (sdf.sdf_only(x) - torus(x)).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        dt = CLOCK() - t0
        with torch.no_grad():
            mae = (sdf.sdf_only(xt) - ft).abs().mean().item()
        gfd, _ = sdf_gradient_fd(sdf.sdf_only, xt, 1e-3)
        cos = torch.nn.functional.cosine_similarity(gfd, nt, dim=1).clamp(-1, 1)
        ang = torch.rad2deg(torch.acos(cos)).mean().item()
        print(f"| {name} | {iters} | {dt / iters * 1e3:.0f} | {mae:.4f} | {ang:.1f} |", flush=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=65536)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--only", default="enc,tv,normals,step")
    ap.add_argument("--iters", type=int, default=300, help="iterations of the quality fit")
    ap.add_argument("--clock", default="wall", choices=["wall", "cpu"],
                    help="cpu: process CPU time summed over threads; stable when other jobs share the cores")
    a = ap.parse_args()
    global CLOCK
    if a.clock == "cpu":
        CLOCK = time.process_time
    dev = torch.device(a.device)
    only = a.only.split(",")
    print(f"device={dev} threads={torch.get_num_threads()} torch={torch.__version__} N={a.n} clock={a.clock}")
    if "enc" in only:
        print("\n| encoding | out dims | params | fwd ms (no grad) | fwd+bwd ms |\n|---|---|---|---|---|")
        bench_encodings(a.n, a.reps, dev)
    if "tv" in only:
        print("\n| regulariser | fwd+bwd ms |\n|---|---|")
        bench_tv(a.reps, dev)
    if "quality" in only:
        print("\n| encoding (+ head 1x64, sphere prior), rotated torus regression | iters | ms/iter | SDF MAE near surface | normal err deg |\n|---|---|---|---|---|")
        bench_quality(a.iters, dev)
    if "step" in only:
        print("\n| simplified NeuS step (SDF head 1x64, colour 2x64, Adam) | rays x samples | FD | wall ms | CPU ms | occ update 64^3 wall/CPU ms | skip |\n|---|---|---|---|---|---|---|")
        bench_step(a.reps, dev)
    if "normals" in only:
        print("\n| SDF grid(4 lvl x4)+MLP(1x64), loss sdf^2 + eikonal | fwd+bwd ms |\n|---|---|")
        bench_normals(a.n, a.reps, dev)


if __name__ == "__main__":
    main()
