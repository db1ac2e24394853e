"""Acquisition before smoothing, end to end, on the issue's far-fix flights.

For each flight: the first frames are dead-reckoned from the log's initial state and
searched (:func:`cdtm_graph.robust.acquisition.acquire`); when the fix is ACQUIRED, a copy of the
log gets the corrected initial position and attitude (the prior's sigmas unchanged, so
only the smoothers' linearization point moves) and is smoothed in every mode. Beside
it: the log as it is, smoothed with the smoothers' own search (the default: their first
frames' features wait for the fix) and without it (``acquisition=None``: what the search
prevents), and the same flight under a clean prior (the truth, 50 m and 1 deg), the
yardstick of "RMSE <= 1.5x clean".

Flights: ``far1000`` as in ``scripts/robustness_matrix.py`` (its terrain is the 3 km
fractal cell tiled, so the 1000 m prior's 3-sigma region holds copies of the truth) and
``far1000-12km``, the same with a 12 km cell (no copy within reach).

Run: ``python scripts/acquisition_demo.py [far1000 far1000-12km far300 ...] [--frames 90]
[--window 6] [--modes batch isam2 fixed_lag]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass

import numpy as np

from cdtm_graph.errors import CdtmError
from cdtm_graph.flightlog import FlightLog
from cdtm_graph.geometry import make_pose, quat_wxyz_to_rotation, rotation_to_quat_wxyz
from cdtm_graph.robust.acquisition import (
    AcquisitionResult,
    FixVerdict,
    acquire,
    dead_reckoned_window,
    needs_acquisition,
)
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode


def flight(name: str, frames: int) -> tuple[FlightLog, object]:
    """A robustness scenario by name; ``NAME-12km`` swaps in a 12 km terrain cell."""
    base = dataclasses.replace(BASE, frames=frames)
    if name.endswith("-12km"):
        base = dataclasses.replace(base, terrain_cell_m=12000.0)
        name = name.removesuffix("-12km")
    return SCENARIOS[name].flight(base)


def with_initial_pose(log: FlightLog, world_T_body: np.ndarray, sigma_m: float | None = None,
                      sigma_deg: float | None = None) -> FlightLog:
    """The log with its prior mean at this pose (and, if given, these sigmas)."""
    init = log.config.initial_state
    init = dataclasses.replace(
        init, position_m=world_T_body[:3, 3].copy(),
        quaternion_wxyz=rotation_to_quat_wxyz(world_T_body[:3, :3]),
        sigma_position_m=init.sigma_position_m if sigma_m is None else sigma_m,
        sigma_attitude_deg=init.sigma_attitude_deg if sigma_deg is None else sigma_deg)
    return dataclasses.replace(log, config=dataclasses.replace(log.config, initial_state=init))


def truth_pose(log: FlightLog) -> np.ndarray:
    """(4, 4) the true body pose at the first frame."""
    gt = log.groundtruth
    assert gt is not None
    i0 = int(np.searchsorted(gt.t_ns, log.frames.t_ns[0]))
    return make_pose(quat_wxyz_to_rotation(gt.quaternion_wxyz[i0]), gt.position_m[i0])


@dataclass(frozen=True)
class Row:
    """One smoothing run of the demo (NaN where it failed)."""

    label: str
    mode: Mode
    rmse_m: np.ndarray
    rmse_3d_m: float
    anees: float

    def __str__(self) -> str:
        x, y, z = self.rmse_m
        return (f"  {self.label:12} {self.mode.value:9} rmse {x:8.2f} {y:8.2f} {z:8.2f} m   "
                f"3d {self.rmse_3d_m:8.2f} m   anees {self.anees:12.2f}")


def smooth_row(label: str, log: FlightLog, dtm, mode: Mode,
               settings: SmootherSettings | None = None) -> Row:
    try:
        out = smooth_and_evaluate(log, dtm, mode.settings(settings or SmootherSettings()))
    except CdtmError:
        return Row(label, mode, np.full(3, np.nan), np.nan, np.nan)
    e = out.errors
    assert e is not None
    return Row(label, mode, e.rmse_position_m, float(e.rmse_position_3d_m),
               float(e.anees_position if e.anees_position is not None else np.nan))


def demo(name: str, frames: int = BASE.frames, window: int = 6,
         modes: list[Mode] | None = None) -> tuple[AcquisitionResult, list[Row]]:
    """Acquire on one flight, then smooth it without a search, as logged (the smoothers
    search), acquired up front (if so) and from a clean prior."""
    modes = modes or list(Mode)
    log, dtm = flight(name, frames)
    init = log.config.initial_state
    window_frames, prior = dead_reckoned_window(log, window)
    truth = truth_pose(log)
    error = window_frames[0].world_T_body[:3, 3] - truth[:3, 3]
    needed = needs_acquisition(prior.position_covariance_world, prior.heading_sigma_rad)
    print(f"{name}: initial error {np.linalg.norm(error[:2]):.0f} m horizontal, prior "
          f"{init.sigma_position_m:g} m / {init.sigma_attitude_deg:g} deg; needs "
          f"acquisition: {needed}", flush=True)
    result = acquire(window_frames, log.config.camera, dtm, prior)
    r = result.searched
    print(f"  acquisition {result.time_s:.2f} s over {r.n_offsets} offsets x "
          f"{len(r.search_headings_deg)} headings ({r.n_tracks} tracks, {r.n_features} "
          f"C-DTM features; terrain information {result.information_z:.1f} standard "
          f"errors): {result.verdict.value}: {result.reason}", flush=True)
    for h in result.hypotheses:
        fixed = h.correction.apply_to_state(window_frames[0].world_T_body, init.velocity_mps)[0]
        print(f"    fix {h.offset_world_m.round(0)} m, {h.correction.heading_deg:+.2f} deg, "
              f"z {h.separation_z:5.1f}, {h.prior_sigmas:.2f} prior sigmas, "
              f"{np.linalg.norm(fixed[:3, 3] - truth[:3, 3]):7.1f} m from the truth")
    no_search = SmootherSettings(acquisition=None)
    runs = [("no search", log, no_search), ("as logged", log, None),
            ("clean prior", with_initial_pose(log, truth, 50.0, 1.0), None)]
    if result.verdict is FixVerdict.ACQUIRED:
        assert result.correction is not None
        pose, _ = result.correction.apply_to_state(init.world_T_body, init.velocity_mps)
        runs.insert(2, ("acquired", with_initial_pose(log, pose), no_search))
    rows = []
    for label, run_log, settings in runs:
        for mode in modes:
            rows.append(smooth_row(label, run_log, dtm, mode, settings))
            print(rows[-1], flush=True)
    return result, rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flights", nargs="*", default=["far1000", "far1000-12km"])
    parser.add_argument("--frames", type=int, default=BASE.frames)
    parser.add_argument("--window", type=int, default=6, help="frames acquisition looks at")
    parser.add_argument("--modes", nargs="+", default=[m.value for m in Mode])
    args = parser.parse_args(argv)
    for name in args.flights:
        demo(name, args.frames, args.window, [Mode(m) for m in args.modes])


if __name__ == "__main__":
    main(sys.argv[1:])
