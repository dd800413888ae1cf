"""Evaluation of the RT-V3 prior (paper Sec. VI-A/B, Table I; NOTES.md "Metrics").

* :mod:`rtv3_maniskill.evaluation.prediction`: open-loop trajectory prediction on held-out
  dataset windows, ADE/FDE (x1000) in the Best-of-Mode and Most-Likely settings
  (``rtv3 evaluate prediction``).
* :mod:`rtv3_maniskill.evaluation.planning`: the closed-loop planning benchmark in
  ``GraspClutter-v1``: SR / CR / TOR (``rtv3 evaluate planning``).

Submodules are imported on demand (they load torch, LeRobot and ManiSkill).
"""

from __future__ import annotations

__all__ = ["planning", "prediction"]
