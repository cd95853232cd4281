"""Early stop at a held-out plateau, after a learning-rate cool-down.

Only when the user did not fix the iteration count. On each held-out evaluation the rule
takes the running mean of the last ``w = plateau_window`` PSNRs,
``m_k = mean(psnr_{k-w+1..k})`` (one evaluation is noisy late in a run; a lucky one must not
become the bar), and compares it with the best mean so far. The run has plateaued when
``plateau_patience`` evaluations in a row gained less than ``min_gain_db`` over the best
**and** they span ``t - t_best >= plateau_min_frac t`` of the training time ``t`` so far (so
frequent evaluations cannot stop a run that still improves slowly). The first full mean sets
the first bar. With a grid SDF no evaluation counts before the coarse-to-fine schedule has
activated every level (:attr:`PlateauRule.min_progress`): the model is still gaining resolution.

Then the learning-rate factor follows a cosine from its value ``f0`` at the plateau to the floor
``alpha`` over ``D = plateau_cooldown_frac t``,
``f = alpha + (f0 - alpha) (1 + cos(pi q)) / 2``, ``q = (wall - t_plateau) / D``, never above the
regular schedule, and the run stops at ``q >= 1`` (the regular schedule anneals only at the end
of the budget; a run stopped early would otherwise end at a high learning rate). The clock
restarts (:meth:`PlateauRule.restart`) when the shading model changes, because the held-out PBR
PSNR dips while the material adapts.
"""

from __future__ import annotations

import math

from nepf_core.train.decisions import Decision


class PlateauRule:
    def __init__(self, cfg, iters_fixed: bool = True) -> None:
        """``cfg``: the run's :class:`~nepf_core.config.NePFConfig`; ``iters_fixed``: the user fixed
        the iteration count (no plateau stop)."""
        self.cfg, self.rc, self.iters_fixed = cfg, cfg.rules, iters_fixed
        self.plateaued = False
        self.stop_requested = False
        self.best = -math.inf
        self.evals_since_best = 0
        self.best_wall: float | None = None
        self.recent: list[float] = []
        self.armed = False
        self.cool_start = self.cool_len = self.cool_f0 = None

    @property
    def min_progress(self) -> float:
        """No plateau counts before this training progress: a grid SDF's coarse-to-fine schedule
        (``train.coarse_to_fine_frac``) is still adding resolution."""
        return float(self.cfg.train.coarse_to_fine_frac) if self.cfg.model.sdf_kind == "grid" else 0.0

    def restart(self) -> None:
        """Forget the evaluations so far (the shading model changed). Not during the
        cool-down: a stop already decided stands."""
        if self.plateaued:
            return
        self.recent, self.best, self.best_wall, self.evals_since_best = [], -math.inf, None, 0

    def on_test_eval(self, step: int, rec: dict, progress: float | None = None) -> Decision | None:
        """Book one held-out evaluation (``rec["test_psnr"]``, ``rec["wall_s"]``); a decision when
        the run plateaus."""
        rc = self.rc
        v = rec.get("test_psnr")
        if v is None or not math.isfinite(v):
            return None
        window = max(int(rc.plateau_window), 1)
        self.recent = (self.recent + [float(v)])[-window:]
        v = sum(self.recent) / len(self.recent)
        wall = rec.get("wall_s")
        growing = progress is not None and progress < self.min_progress
        if len(self.recent) < window:   # a partial mean is noisier than the rule assumes: no bar yet
            self.best, self.best_wall, self.evals_since_best = -math.inf, wall, 0
            return None
        if growing or (progress is not None and not self.armed):
            # still adding capacity: track the best; the clock starts once every level is active
            self.best = max(self.best, v)
            self.evals_since_best = 0
            self.best_wall = wall
            self.armed = not growing
            return None
        if v > self.best + rc.min_gain_db:
            self.best, self.best_wall, self.evals_since_best = v, wall, 0
        else:
            self.evals_since_best += 1
        long_enough = True
        if wall is not None and self.best_wall is not None:
            long_enough = (wall - self.best_wall) >= rc.plateau_min_frac * wall
        if not (self.cfg.train.adaptive and not self.iters_fixed and self.evals_since_best >= rc.plateau_patience
                and long_enough and not self.plateaued):
            return None
        self.plateaued = True
        span = "" if wall is None or self.best_wall is None else \
            f" and {wall - self.best_wall:.0f} s of {wall:.0f} s of training"
        frac = rc.plateau_cooldown_frac
        if wall is None or frac <= 0:
            self.stop_requested = True
            then = "stop now"
        else:
            self.cool_start, self.cool_len = wall, frac * wall
            then = (f"anneal the learning rate to its floor over {self.cool_len:.0f} s "
                    f"({frac:.0%} of the training time so far), then stop")
        w = len(self.recent)
        what = "held-out PSNR" if w == 1 else f"mean held-out PSNR of the last {w} evaluations"
        return Decision("early_stop", True, f"{what} plateaued: no gain > {rc.min_gain_db} dB over "
                        f"{self.evals_since_best} evaluations{span} (best {self.best:.2f} dB): {then}", step)

    def lr_factor(self, wall: float, f_now: float) -> float:
        """The learning-rate factor at training time ``wall`` given the regular schedule's
        ``f_now`` (unchanged before a plateau); requests the stop at the end of the cool-down."""
        if self.cool_start is None:
            return f_now
        alpha = self.cfg.train.lr_alpha
        if self.cool_f0 is None:
            self.cool_f0 = f_now
        q = (wall - self.cool_start) / max(self.cool_len, 1e-9)
        if q >= 1.0:
            self.stop_requested = True
            return alpha
        return min(f_now, alpha + (self.cool_f0 - alpha) * 0.5 * (1.0 + math.cos(math.pi * max(q, 0.0))))

    def state(self) -> dict:
        return {"best": self.best if math.isfinite(self.best) else None, "since_best": self.evals_since_best,
                "best_wall": self.best_wall, "plateau_armed": self.armed, "plateaued": self.plateaued,
                "recent": list(self.recent), "cool": [self.cool_start, self.cool_len, self.cool_f0]}

    def load_state(self, s: dict) -> None:
        self.best = s.get("best") if s.get("best") is not None else -math.inf
        self.evals_since_best = s.get("since_best", 0)
        self.best_wall = s.get("best_wall")
        self.armed = s.get("plateau_armed", False)
        self.plateaued = s.get("plateaued", False)
        self.recent = list(s.get("recent", []))
        self.cool_start, self.cool_len, self.cool_f0 = s.get("cool", [None, None, None])
