"""The stop rule of a self-stopping run: a plateau of the validation PSNR, met once with an
annealing of the means learning rate and a second time with a stop.

    rule = PlateauRule(patience=3, min_gain=0.05, stop_after=1500, anneal=0.3)
    state = rule.initial()
    state, action = rule.update(state, step, psnr)   # action: "best", "wait", "anneal" or "stop"

The state is a plain dict of JSON values (saved in checkpoints, so a resumed run keeps it).
"""

from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class PlateauRule:
    """Args:
        patience: checks in a row without a gain of `min_gain` over the best before acting.
        min_gain: dB over the best validation PSNR that counts as progress.
        stop_after: no anneal and no stop before this step, and the checks up to it do not
            count towards a plateau (at reduced resolution the validation PSNR levels off at
            what the resolution allows: a rule that counted those checks annealed a real
            plant's run at the very step full resolution began).
        anneal: factor on the means learning rate at the first plateau (1: stop at the first).
        keep_from: the run's model comes from a check at or after this step: there the best
            and the wait start again (an anneal already made stays), and the run does not stop
            before it. A loss that starts late (the normal prior) then always shapes the model
            kept, instead of only in the runs that happen to plateau after it.
    """

    patience: int
    min_gain: float
    stop_after: int = 0
    anneal: float = 0.3
    keep_from: int = 0

    @classmethod
    def from_config(cls, c, full_resolution_from: int = 0) -> "PlateauRule":
        """The config's rule; it never acts before training reaches full resolution, and with
        `normal_settle` it keeps a model that has had the normal loss that many steps (or from the
        ceiling's step, where `steps` ends the run sooner)."""
        normal = c.normal_settle and c.lambda_normal > 0 and c.normal_from < c.steps
        return cls(c.stop_patience, c.stop_min_gain, max(c.stop_after, full_resolution_from), c.lr_anneal,
                   min(c.normal_from + c.normal_settle, c.steps) if normal else 0)

    @staticmethod
    def initial() -> dict:
        return {"best_psnr": None, "best_step": 0, "waited": 0, "lr_scale": 1.0, "annealed_at": None,
                "stopped_at": None, "reason": None, "kept_from": None}

    def update(self, state: dict, step: int, psnr: float) -> tuple[dict, str]:
        """The rule's state after a check at `step`, and what to do now."""
        state = dict(state)
        if self.keep_from and step >= self.keep_from and state.get("kept_from") is None:
            state.update(best_psnr=None, best_step=0, waited=0, kept_from=step)  # the checks before are not kept
        best = state["best_psnr"]
        if best is None or (math.isfinite(psnr) and psnr > best):
            gained = best is None or psnr >= best + self.min_gain
            state.update(best_psnr=psnr, best_step=step, waited=0 if gained else state["waited"] + 1)
            if gained:
                return state, "best"
            action = "best"  # a better model to keep, but not enough progress to reset the wait
        else:
            state["waited"] += 1
            action = "wait"
        if step <= self.stop_after:
            state["waited"] = 0
            return state, action
        if not self.patience or state["waited"] < self.patience:
            return state, action
        if state["annealed_at"] is None and self.anneal < 1:
            state.update(annealed_at=step, waited=0, lr_scale=state["lr_scale"] * self.anneal)
            return state, "anneal"
        if step < self.keep_from:
            return state, action
        state.update(stopped_at=step, reason=(
            f"validation PSNR gained less than {self.min_gain} dB over {self.patience} checks"
            + (f" after the learning-rate annealing at step {state['annealed_at']}" if state["annealed_at"] else "")))
        return state, "stop"

    @staticmethod
    def held(before: dict, after: dict) -> dict:
        """`after` (an update that annealed or stopped) with that action undone and the wait begun
        again: the best model it saw stays, the learning rate and the run go on as `before`."""
        return dict(after, waited=0, lr_scale=before["lr_scale"], annealed_at=before["annealed_at"],
                    stopped_at=None, reason=None)
