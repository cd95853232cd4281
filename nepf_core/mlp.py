"""The one MLP builder used by every network (ReLU / softplus / SIREN, geometric init).

    h_0 = x,   h_{k+1} = act(W_k [h_k (, x if k in skips)] + b_k),   y = W_L h_L + b_L

* ``relu``: plain ReLU.
* ``softplus``: ``softplus(beta * z) / beta`` (beta = 100 as in NeuS/IDR, a smooth ReLU
  whose second derivative exists, so a Hessian regulariser is meaningful).
* ``siren``: ``sin(w0 * z)`` with SIREN's initialisation (Sitzmann et al. 2020):
  first layer ``U(-1/d, 1/d)``, later layers ``U(-sqrt(6/d)/w0, sqrt(6/d)/w0)``.
* ``geometric_init`` (SAL / IDR, for SDF networks): weights ``N(0, sqrt(2)/sqrt(d_out))``,
  last layer ``N(sqrt(pi)/sqrt(d), 1e-4)`` with bias ``-radius``, so the network starts
  close to the SDF of a sphere of that radius. With ``n_freq_inputs`` the positional
  encoding columns of the first layer start at zero, as in IDR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn


@dataclass
class MLPConfig:
    """Configuration of one MLP."""

    in_dim: int
    """Input feature size."""
    out_dim: int
    """Output size."""
    width: int = 256
    """Hidden width."""
    depth: int = 8
    """Number of hidden layers (linear layers = depth + 1)."""
    activation: str = "relu"
    """``relu`` | ``softplus`` | ``siren``."""
    skips: tuple[int, ...] = ()
    """Hidden layer indices that re-read the input (concatenated)."""
    geometric_init: bool = False
    """SAL/IDR sphere initialisation (SDF networks)."""
    init_radius: float = 0.5
    """Sphere radius for ``geometric_init``."""
    n_raw_inputs: int = 3
    """With geometric init: the first ``n_raw_inputs`` columns are raw xyz; the rest
    (positional encoding, features) start with zero weights."""
    softplus_beta: float = 100.0
    """Beta of the softplus activation."""
    siren_w0: float = 30.0
    """SIREN frequency for the first layer (later layers use w0 too, as in SIREN)."""
    weight_norm: bool = False
    """Wrap linear layers in weight normalisation (NeuS does for the SDF)."""


class SineActivation(nn.Module):
    def __init__(self, w0: float) -> None:
        super().__init__()
        self.w0 = w0

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(self.w0 * x)


class MLP(nn.Module):
    """Fully connected network built from an :class:`MLPConfig`. ``[N, in] -> [N, out]``."""

    def __init__(self, cfg: MLPConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.skips = set(cfg.skips)
        dims = [cfg.in_dim] + [cfg.width] * cfg.depth + [cfg.out_dim]
        layers = []
        for k in range(len(dims) - 1):
            d_in = dims[k] + (cfg.in_dim if k in self.skips and k > 0 else 0)
            lin = nn.Linear(d_in, dims[k + 1])
            self._init_layer(lin, k, len(dims) - 1, d_in)
            if cfg.weight_norm:
                lin = nn.utils.parametrizations.weight_norm(lin)
            layers.append(lin)
        self.layers = nn.ModuleList(layers)
        if cfg.activation == "relu":
            self.act = nn.ReLU()
        elif cfg.activation == "softplus":
            self.act = nn.Softplus(beta=cfg.softplus_beta)
        elif cfg.activation == "siren":
            self.act = SineActivation(cfg.siren_w0)
        else:
            raise ValueError(f"unknown activation {cfg.activation!r} (relu|softplus|siren)")

    def _init_layer(self, lin: nn.Linear, k: int, n_lin: int, d_in: int) -> None:
        cfg = self.cfg
        last = k == n_lin - 1
        with torch.no_grad():
            if cfg.geometric_init:
                if last:
                    nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(d_in), std=1e-4)
                    nn.init.constant_(lin.bias, -cfg.init_radius)
                else:
                    nn.init.constant_(lin.bias, 0.0)
                    nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
                    if k == 0 and cfg.in_dim > cfg.n_raw_inputs:
                        lin.weight[:, cfg.n_raw_inputs:] = 0.0
                    if k in self.skips and k > 0 and cfg.in_dim > cfg.n_raw_inputs:
                        # the re-read encoding columns start at zero (IDR)
                        lin.weight[:, -(cfg.in_dim - cfg.n_raw_inputs):] = 0.0
            elif cfg.activation == "siren":
                bound = 1.0 / d_in if k == 0 else math.sqrt(6.0 / d_in) / cfg.siren_w0
                nn.init.uniform_(lin.weight, -bound, bound)
                nn.init.uniform_(lin.bias, -bound, bound)

    def forward(self, x: Tensor) -> Tensor:
        h = x
        n = len(self.layers)
        for k, lin in enumerate(self.layers):
            if k in self.skips and k > 0:
                h = torch.cat([h, x], dim=-1) / math.sqrt(2.0)
            h = lin(h)
            if k < n - 1:
                h = self.act(h)
        return h


def build_mlp(cfg: MLPConfig) -> MLP:
    """Build the MLP described by ``cfg`` (the only MLP constructor in the project)."""
    return MLP(cfg)


def positional_encoding(x: Tensor, n_freqs: int, include_input: bool = True) -> Tensor:
    """NeRF frequency encoding ``[x, sin(2^k x), cos(2^k x)]_{k<L}``: ``[N, d] -> [N, d(1+2L)]``."""
    if n_freqs <= 0:
        return x
    freqs = 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
    xb = x[..., None, :] * freqs[:, None]  # [N, L, d]
    enc = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1).flatten(-2)
    return torch.cat([x, enc], dim=-1) if include_input else enc


def encoding_dim(d: int, n_freqs: int, include_input: bool = True) -> int:
    """Output size of :func:`positional_encoding`."""
    if n_freqs <= 0:
        return d
    return d * (2 * n_freqs + (1 if include_input else 0))
