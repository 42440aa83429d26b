"""Early stop: a fit ends when its loss has stopped improving (or at its preset's maximum of steps).

Rule (:class:`PlateauRule`). Training draws frames in random epochs, so single-step losses are as noisy as the
frames differ; the rule compares *window means*. With ``W = window`` steps (by default one epoch of the
model's frames, at least ``min_window``), after every completed window ``k`` the mean loss ``m_k`` of its steps
is compared with the best earlier window mean ``b = min(m_1 .. m_{k-1})``; the window *improved* when
``m_k < b * (1 - rel_tol)``. The fit stops after ``patience`` consecutive windows without improvement, but
never before step ``min_steps`` (e.g. the end of density control, so the model's size is settled).
A non-finite loss never counts as an improvement.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass, field

__all__ = ["PlateauDetector", "PlateauRule"]


@dataclass(frozen=True)
class PlateauRule:
    """When a fit has plateaued (module docstring)."""

    enabled: bool | None = None
    """Stop fits at a plateau; None: only with WorldTree's ``--depth auto`` (off: every fit runs its preset's
    steps)."""
    rel_tol: float = 0.01
    """A window improves when its mean loss is below ``(1 - rel_tol)`` times the best earlier window mean."""
    patience: int = 2
    """Stop after this many windows in a row without improvement."""
    min_window: int = 25
    """Shortest window in steps (the window is ``max(min_window, frames)``)."""
    min_steps: int = 0
    """Never stop before this step."""

    def __post_init__(self) -> None:
        if not 0 <= self.rel_tol < 1 or self.patience < 1 or self.min_window < 1 or self.min_steps < 0:
            raise ValueError(
                "PlateauRule needs 0 <= rel_tol < 1, patience >= 1, min_window >= 1 and min_steps >= 0; got "
                f"{self.rel_tol}, {self.patience}, {self.min_window}, {self.min_steps}"
            )

    def detector(self, frames: int, min_steps: int = 0) -> PlateauDetector:
        """A fresh detector for a fit over ``frames`` frames that must not stop before ``min_steps`` (besides
        ``self.min_steps``; e.g. the end of its density control)."""
        rule = dataclasses.replace(self, min_steps=max(self.min_steps, int(min_steps)))
        return PlateauDetector(rule, self.window(frames))

    def window(self, frames: int) -> int:
        """Window length for a model of ``frames`` frames (one epoch, at least ``min_window``)."""
        return max(self.min_window, int(frames))


@dataclass
class PlateauDetector:
    """Running state of :class:`PlateauRule` for one fit; checkpoint it with :meth:`state_dict`."""

    rule: PlateauRule
    window: int
    sum: float = 0.0
    count: int = 0
    best: float = math.inf
    stale: int = 0
    means: list[float] = field(default_factory=list)
    """Every completed window's mean loss."""
    stopped_at: int | None = None
    """Step at which the rule fired (None: it has not)."""

    def update(self, step: int, loss: float) -> bool:
        """Add the loss of ``step`` (1-based); returns True when the fit should stop after this step."""
        if self.stopped_at is not None:
            return self.stopped_at is not None
        self.sum += float(loss) if math.isfinite(float(loss)) else math.inf
        self.count += 1
        if self.count < self.window:
            return False
        mean = self.sum / self.count
        self.sum, self.count = 0.0, 0
        self.means.append(mean)
        if math.isfinite(mean) and mean < self.best * (1.0 - self.rule.rel_tol):
            self.best, self.stale = mean, 0
        else:
            self.stale += 1
        if self.stale >= self.rule.patience and step >= self.rule.min_steps:
            self.stopped_at = int(step)
            return True
        return False

    def state_dict(self) -> dict:
        d = asdict(self)
        d.pop("rule")
        return d

    def load_state_dict(self, d: dict) -> None:
        for k, v in d.items():
            setattr(self, k, v)

    def report(self) -> dict:
        """JSON-able summary: the rule, the window, the window means and where it stopped."""
        return {"rule": asdict(self.rule), "window": self.window, "window_means": list(self.means),
                "stopped_at": self.stopped_at}  # fmt: skip
