"""``cdtm analyze LOG --pair A B``: the closed-form analysis of one frame pair of a log."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from cdtm_graph.cli import COMMANDS

if TYPE_CHECKING:
    import numpy as np

    from cdtm_graph.analysis.two_frame import LogPairAnalysis


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze", help=COMMANDS["analyze"].summary,
        description="Linearize the C-DTM problem of frames A and B of a flight log at known "
                    "poses and print the paper's closed-form covariance (eq. 13, printed and "
                    "weighted), GTSAM's marginal mapped to the same parameters, Sigma_C2, the "
                    "condition number and the degeneracy verdict.")
    p.add_argument("log", help="flight log directory (cdtm-flightlog/1)")
    p.add_argument("--pair", nargs=2, type=int, required=True, metavar=("A", "B"),
                   help="frame indices (rows of frames.csv)")
    p.add_argument("--at", choices=("groundtruth", "nav"), default="groundtruth",
                   help="where the linearization poses come from (default: groundtruth)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def _json_matrix(a: np.ndarray) -> list:
    import numpy as np

    return [[float(x) if np.isfinite(x) else None for x in row] for row in np.atleast_2d(a)]


def to_json(result: LogPairAnalysis) -> dict:
    """The JSON report: metres and radians, theta order ``theta_names``."""
    import numpy as np

    from cdtm_graph.analysis.closed_form import C2_NAMES, THETA_NAMES

    unc = result.uncertainty
    a = unc.analysis
    cond = a.condition_number
    return {
        "frames": [result.frame_a, result.frame_b],
        "linearized_at": result.poses_from,
        "n_features": result.n_features,
        "n_missed_dtm": result.n_missed,
        "theta_names": list(THETA_NAMES),
        "c2_names": list(C2_NAMES),
        "units": "metres and radians",
        "theta": [float(x) for x in a.theta],
        "sigma_theta_weighted": _json_matrix(a.sigma_theta_weighted),
        "sigma_theta_unweighted": _json_matrix(a.sigma_theta_unweighted),
        "sigma_theta_gtsam": _json_matrix(unc.sigma_theta_gtsam),
        "sigma_c2_weighted": _json_matrix(a.sigma_c2_weighted),
        "sigma_c2_unweighted": _json_matrix(a.sigma_c2_unweighted),
        "condition_number": float(cond) if np.isfinite(cond) else None,
        "degenerate": {"flag": a.degeneracy.degenerate, "reasons": list(a.degeneracy.reasons),
                       "message": a.degeneracy.message()},
    }


def _sigmas(cov: np.ndarray) -> np.ndarray:
    import numpy as np

    with np.errstate(invalid="ignore"):
        return np.sqrt(np.diag(cov))


def to_table(result: LogPairAnalysis) -> str:
    """1-sigma values, metres and degrees."""
    import numpy as np

    from cdtm_graph.analysis.closed_form import C2_NAMES, THETA_NAMES

    unc = result.uncertainty
    a = unc.analysis
    cols = (("eq13 weighted", _sigmas(a.sigma_theta_weighted)),
            ("eq13 printed", _sigmas(a.sigma_theta_unweighted)),
            ("GTSAM", _sigmas(unc.sigma_theta_gtsam)))
    lines = [f"frames {result.frame_a} -> {result.frame_b}, linearized at {result.poses_from}: "
             f"{result.n_features} features ({result.n_missed} missed the DTM)",
             f"{'parameter':<10}{'unit':>6}" + "".join(f"{c:>16}" for c, _ in cols)]

    def rows(names, cols):
        for i, name in enumerate(names):
            angle = name.startswith(("phi", "theta", "psi"))
            unit, scale = ("deg", np.degrees(1.0)) if angle else ("m", 1.0)
            values = "".join(f"{v[i] * scale:>16.4g}" for _, v in cols)
            lines.append(f"{name:<10}{unit:>6}" + values)

    rows(THETA_NAMES, cols)
    lines.append("camera 2 pose (eqs. 27-31):")
    rows(C2_NAMES, (("eq13 weighted", _sigmas(a.sigma_c2_weighted)),
                    ("eq13 printed", _sigmas(a.sigma_c2_unweighted))))
    lines.append(f"condition number of J^T W J (scale-normalized): {a.condition_number:.3g}")
    verdict = a.degeneracy
    lines.append("degenerate: " + (verdict.message() if verdict.degenerate else "no"))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from cdtm_graph.analysis.two_frame import analyze_log_pair
    from cdtm_graph.run.prepare import load_log_and_dtm

    flight, dtm = load_log_and_dtm(args.log)
    result = analyze_log_pair(flight, dtm, args.pair[0], args.pair[1], args.at)
    print(json.dumps(to_json(result)) if args.json else to_table(result))
    return 0
