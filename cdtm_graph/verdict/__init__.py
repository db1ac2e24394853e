"""Judging a run: before it (does the log constrain anything?) and after it (trusted,
degraded or failed, and why).

- :mod:`~cdtm_graph.verdict.preflight`: a log that gives the smoother no camera or DTM
  constraint is refused before any work.
- :mod:`~cdtm_graph.verdict.imu_faults`: IMU gaps, a wrong rate, stuck and saturated
  values, samples noisier than flight.yaml says.
- :mod:`~cdtm_graph.verdict.evaluation`: errors against ground truth, NEES;
  :mod:`~cdtm_graph.verdict.comparison`: many runs side by side (``cdtm evaluate``).
- :mod:`~cdtm_graph.verdict.fix_geometry`: what each frame's window of C-DTM information
  says about the fix (the paper's section V.B weak geometries).
- :mod:`~cdtm_graph.verdict.rules`: :func:`assess`, the rules that turn all of it into a
  :class:`Verdict` (:mod:`~cdtm_graph.verdict.outcome`: the verdict as data).

The wing judges results; it never imports the smoothers (``tests/project/test_layout.py``).
``from cdtm_graph.verdict import assess`` loads the rules on first use only, so that the
preflight check does not pay for them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from cdtm_graph.verdict.outcome import Reason, SelfChecks, Status, Verdict
    from cdtm_graph.verdict.rules import VerdictSettings, assess

_WHERE = {"Reason": "outcome", "SelfChecks": "outcome", "Status": "outcome", "Verdict": "outcome",
          "VerdictSettings": "rules", "assess": "rules"}
__all__ = ["Reason", "SelfChecks", "Status", "Verdict", "VerdictSettings", "assess"]


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib
        return getattr(importlib.import_module(f"cdtm_graph.verdict.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
