"""What the suite measures against: its arms and the figures the open issues target."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: The arms each subject runs in.
ARMS = ("pipeline", "truth_labels")
#: Arms run on request (``bench/validate.py --arms``) to localise a miss: the truth label
#: map of the reference position alone (the mesh's source), the other positions segmented.
EXTRA_ARMS = ("reference_truth",)

#: The fitted parameter: one breast modulus for both breasts (the paper's single tissue).
FIT_PARAMETER = "materials.breast_left.E|materials.breast_right.E"


@dataclass(frozen=True)
class Target:
    """A figure an issue targets.

    figure : key of a subject's ``figures`` (``dice_breast_min``, ``tre_max_mm``, ...)
    bound : the bound, in the figure's unit
    kind : "max" (figure <= bound) or "min" (figure >= bound)
    arm : the arm whose figure is checked
    issue : the issue that targets it
    enforced : True once that issue has landed: a miss then fails the CI slice
    """

    figure: str
    bound: float
    kind: str
    arm: str
    issue: int
    enforced: bool = False

    def met(self, value: float | None) -> bool | None:
        if value is None or not np.isfinite(value):
            return None
        return bool(value <= self.bound) if self.kind == "max" else bool(value >= self.bound)


TARGETS: tuple[Target, ...] = (
    Target("completed", 1.0, "min", "pipeline", 14),
    Target("dice_breast_min", 0.95, "min", "pipeline", 14),
    Target("dice_muscle_min", 0.90, "min", "pipeline", 14),
    Target("tre_max_mm", 0.5, "max", "pipeline", 14),
    Target("rotation_error_max_deg", 0.3, "max", "pipeline", 14),
    Target("completed", 1.0, "min", "truth_labels", 15),
    Target("breast_E_rel_error", 0.10, "max", "truth_labels", 15),
    Target("mhd_calibrated_max_mm", 1.0, "max", "truth_labels", 15),
    Target("mhd_held_out_max_mm", 1.5, "max", "truth_labels", 15),
    Target("mhd_calibrated_overlap_max_mm", 1.0, "max", "truth_labels", 15),
    Target("breast_E_rel_error", 0.10, "max", "pipeline", 15),
    Target("mhd_calibrated_max_mm", 1.0, "max", "pipeline", 15),
    Target("mhd_held_out_max_mm", 1.5, "max", "pipeline", 15),
    Target("mhd_calibrated_overlap_max_mm", 1.0, "max", "pipeline", 15),
)


def check_targets(result: Mapping[str, Any],
                  targets: Sequence[Target] = TARGETS) -> list[dict[str, Any]]:
    """Each target's value and verdict on one subject's result (``met`` None: no figure)."""
    rows = []
    for t in targets:
        arm = (result.get("arms") or {}).get(t.arm)
        if arm is None:
            continue
        v = arm["figures"].get(t.figure)
        rows.append({"figure": t.figure, "arm": t.arm, "bound": t.bound, "kind": t.kind,
                     "issue": t.issue, "enforced": t.enforced, "value": v, "met": t.met(v)})
    return rows
