"""The incremental smoother's settling: the newest frame's covariance honest from frame 1.

From a loose prior (an acquired fix, an IMU gap) the estimate is not yet where the C-DTM
factors put it, and their marginal at the linearization point the estimate is still
leaving is not its uncertainty: ``scripts/live_tracking.py`` put frame 1 114 m off at a
1-sigma of 2-3 m (iSAM2 relinearizes every 10 updates). While settling, each frame runs
relinearizing steps until one moves the newest frame by less than its 1-sigma; until one
does, it reports the last honest covariance carried to it by the IMU (at first the
prior's). :class:`Settling` is that state, for
:class:`~cdtm_graph.smoother.incremental.IncrementalSmoother`.
"""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from cdtm_graph.graph import insert_state
from cdtm_graph.imu import propagate_covariance
from cdtm_graph.smoother.backends import frame_keys
from cdtm_graph.smoother.window import SolverWindow


class Settling:
    """Whether the newest frame's marginal is honest yet, and what to report until it is.

    Args:
        window: the smoother's solver window (its backend is stepped while settling).
        iterations: at most this many relinearizing steps a frame (``final_iterations``;
            0: the estimate never settles, every frame reports the carried covariance).
    """

    #: The estimate has settled when one relinearizing step moves the newest frame's
    #: position by less than this NEES (3 dof) against its marginal: within its 1-sigma.
    SETTLED_STEP_NEES = 1.0

    def __init__(self, window: SolverWindow, iterations: int):
        self._window = window
        self._iterations = iterations
        self.active = True  # from the prior
        # the last honest covariance carried to the newest frame (15x15, [X, V, B]); None:
        # the newest frame's marginal is honest
        self._carried: np.ndarray | None = None

    def restart(self) -> None:
        """Settle again (an acquired fix), from the newest frame's covariance now (before
        the fix's sightings entered); a settling under way keeps what it carries."""
        if not self.active:
            self.active, self._carried = True, self._window.state_cov

    def carry(self, k: int, link: gtsam.CombinedImuFactor, values: gtsam.Values) -> None:
        """While settling: the last honest covariance (frame k-1's marginal, or what was
        carried to it) carried to frame k through the IMU factor (a Kalman prediction).
        ``values``: frame k's predicted state."""
        if not self.active:
            return
        w = self._window
        at = gtsam.Values(values)
        insert_state(at, k - 1, w.poses[k - 1], w.velocities[k - 1], w.biases[k - 1])
        earlier = w.state_cov if self._carried is None else self._carried
        self._carried, _ = propagate_covariance(link, at, earlier)

    def reported(self, k: int, has_cdtm: bool) -> tuple[bool, np.ndarray]:
        """Frame k's (converged, 15x15 covariance to report). Honest when no C-DTM factor
        has entered yet (the marginal is then the carried covariance) or the estimate has
        settled (:meth:`_settle`, which iterates); settled stays settled until
        :meth:`restart` or an IMU gap (``active = True``)."""
        w = self._window
        if self.active and has_cdtm and not self._settle(k):
            assert self._carried is not None
            return False, self._carried
        self.active = self.active and not has_cdtm
        self._carried = None
        return True, w.state_cov

    def _settle(self, k: int) -> bool:
        """Relinearizing steps until one moves frame k's position by less than its
        1-sigma (``SETTLED_STEP_NEES``): the linearization point is then the estimate, and
        the marginal there its covariance. Updates frame k's estimate and the window's
        ``state_cov``; returns whether it settled."""
        w = self._window
        settled = False
        for _ in range(self._iterations):
            before = w.poses[k][:3, 3].copy()
            w.backend.step()
            w.fetch(k)
            pose = w.poses[k]
            step_body_m = pose[:3, :3].T @ (pose[:3, 3] - before)
            position_cov = w.backend.marginal(X(k))[3:, 3:]
            if float(step_body_m @ np.linalg.solve(position_cov, step_body_m)) \
                    <= self.SETTLED_STEP_NEES:
                settled = True
                break
        w.state_cov = w.backend.joint_marginal(list(frame_keys(k)))
        return settled
