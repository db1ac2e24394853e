"""The two incremental solvers behind :class:`~cdtm_graph.smoother.IncrementalSmoother`.

Both hold an iSAM2 Bayes tree and take one update per frame; they differ in what they
keep. :class:`FullHistory` keeps every frame (GTSAM's ``ISAM2``); :class:`FixedLag`
marginalizes frames older than the lag (GTSAM's ``IncrementalFixedLagSmoother``), at
their linearization point, so it must relinearize well before a state leaves the window.
Every GTSAM error that means "this system is not solvable" becomes a ``SolverError``
naming the variable here, once.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any, Protocol

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.optimizer import explain_indeterminant


def frame_keys(k: int) -> tuple[int, int, int]:
    """The states of frame k: pose, velocity, bias."""
    return X(k), V(k), B(k)


def isam2_params() -> gtsam.ISAM2Params:
    """iSAM2: per-type relinearization thresholds, relinearize every 10th update, QR."""
    params = gtsam.ISAM2Params()
    thresholds = gtsam.ISAM2ThresholdMap()
    # Finer than DESIGN.md's first guess (0.01 rad, 1 m, 0.1 m/s, 1e-3): with metre-level
    # pose sigmas, a 1 m threshold left the final estimate ~0.3 sigma from the batch
    # optimum; these cost ~0.3 ms per frame more.
    thresholds.insert(("x", np.r_[[0.002] * 3, [0.1] * 3]))
    thresholds.insert(("v", np.full(3, 0.02)))
    thresholds.insert(("b", np.full(6, 1e-4)))
    params.setRelinearizeThreshold(thresholds)
    params.relinearizeSkip = 10
    # Cholesky declares the IMU + prior system indeterminant at frame 1 (information
    # spans ~1e-4..1e9 across pose, velocity and bias); QR is stable there.
    params.setFactorization("QR")
    params.cacheLinearizedFactors = True
    params.enablePartialRelinearizationCheck = True
    return params


@contextlib.contextmanager
def _solvable() -> Iterator[None]:
    """GTSAM's 'indeterminant system near ...' as one clear SolverError."""
    try:
        yield
    except RuntimeError as exc:
        raise explain_indeterminant(exc) from None


class Backend(Protocol):
    """What the incremental front needs of a solver."""

    #: Updates between relinearizations (a forced step relinearizes everything).
    relinearize_skip: int
    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               stamps: dict[int, float], relinearize: bool = False) -> list[int]:
        """Add factors and new states (with their times, s); return the factors' slots."""
        ...

    def step(self) -> None:
        """One relinearizing update with no new data."""
        ...

    def replace(self, graph: gtsam.NonlinearFactorGraph, slots: list[int]) -> list[int]:
        """Swap the factors in ``slots`` for ``graph``'s; return the new slots."""
        ...

    def pose(self, k: int) -> np.ndarray: ...

    def velocity(self, k: int) -> np.ndarray: ...

    def bias(self, k: int) -> gtsam.imuBias.ConstantBias: ...

    def estimate(self) -> gtsam.Values: ...

    def marginal(self, key: int) -> np.ndarray: ...

    def joint_marginal(self, keys: list[int]) -> np.ndarray:
        """Joint covariance of ``keys``, blocks in their order."""
        ...

    def error(self) -> float:
        """The total error of the factors held, at the current estimate."""
        ...


class _Isam2Estimates:
    """Estimates and marginals read from a solver with iSAM2's calculate* methods.

    Poses and marginals are kept until the solver changes (``_changed``, called by every
    update): a frame's update asks for the same window poses a dozen times (pairing, gate,
    track tests), each a back-substitution, and a round the same frames' marginals twice
    (the track tests, the map's shape).
    """

    _solver: Any  # gtsam.ISAM2 or gtsam.IncrementalFixedLagSmoother: the same calculate*
    _poses: dict[int, np.ndarray]
    _marginals: dict[int, np.ndarray]

    def _isam2(self) -> gtsam.ISAM2:
        raise NotImplementedError

    def _changed(self) -> None:
        self._poses = {}
        self._marginals = {}

    # (every read back-substitutes, and may meet the system indeterminant there: a
    # SolverError naming the variable, as an update does)
    def pose(self, k: int) -> np.ndarray:
        pose = self._poses.get(k)
        if pose is None:
            with _solvable():
                pose = self._poses[k] = self._solver.calculateEstimatePose3(X(k)).matrix()
            pose.flags.writeable = False  # shared: callers must not change it in place
        return pose

    def velocity(self, k: int) -> np.ndarray:
        with _solvable():
            return np.asarray(self._solver.calculateEstimateVector(V(k)))

    def bias(self, k: int) -> gtsam.imuBias.ConstantBias:
        with _solvable():
            return self._solver.calculateEstimateConstantBias(B(k))

    def estimate(self) -> gtsam.Values:
        with _solvable():
            return self._solver.calculateEstimate()

    def marginal(self, key: int) -> np.ndarray:
        # (kept until the next update: a track round and the shape watch ask for the same)
        cov = self._marginals.get(key)
        if cov is None:
            with _solvable():
                cov = self._marginals[key] = np.asarray(self._solver.marginalCovariance(key))
            cov.flags.writeable = False  # shared: callers must not change it in place
        return cov

    def joint_marginal(self, keys: list[int]) -> np.ndarray:
        with _solvable():
            return self._isam2().jointMarginalCovariance(keys).fullMatrix()


class FullHistory(_Isam2Estimates):
    """iSAM2 over every frame so far.

    Args:
        updates_per_frame: solver updates each frame makes (2 with an innovation gate):
            the relinearization interval is kept the same in frames.
    """

    def __init__(self, updates_per_frame: int = 1):
        params = isam2_params()
        params.relinearizeSkip *= updates_per_frame
        self.relinearize_skip = params.relinearizeSkip
        self._isam = self._solver = gtsam.ISAM2(params)
        self._poses = {}
        self._marginals = {}

    def _isam2(self) -> gtsam.ISAM2:
        return self._isam

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               stamps: dict[int, float], relinearize: bool = False) -> list[int]:
        self._changed()
        with _solvable():
            result = self._isam.update(graph, values, [], None, None, None, relinearize)
        return list(result.getNewFactorsIndices())

    def step(self) -> None:
        self.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, relinearize=True)

    def replace(self, graph: gtsam.NonlinearFactorGraph, slots: list[int]) -> list[int]:
        self._changed()
        with _solvable():
            result = self._isam.update(graph, gtsam.Values(), slots)
        return list(result.getNewFactorsIndices())

    def error(self) -> float:
        return float(self._isam.getFactorsUnsafe().error(self.estimate()))


class FixedLag(_Isam2Estimates):
    """GTSAM's incremental fixed-lag smoother: states older than ``lag_s`` are marginalized.

    States are marginalized at their linearization point and the smoother's update
    cannot force relinearization, so it relinearizes at least four times per window
    (every update when the frame interval is not known), and :meth:`step` runs as many
    updates as it skips.

    Args:
        lag_s: the window (s).
        frame_interval_s: expected time between frames, or None.
        updates_per_frame: solver updates each frame makes (2 with an innovation gate).
    """

    def __init__(self, lag_s: float, frame_interval_s: float | None = None,
                 updates_per_frame: int = 1):
        params = isam2_params()
        params.relinearizeSkip = 1
        if frame_interval_s is not None and frame_interval_s > 0:
            params.relinearizeSkip = int(np.clip(lag_s / frame_interval_s // 4, 1, 10))
        params.relinearizeSkip *= updates_per_frame
        self.relinearize_skip = params.relinearizeSkip
        self.lag_s = lag_s
        self._fls = self._solver = gtsam.IncrementalFixedLagSmoother(lag_s, params)
        self._poses = {}
        self._marginals = {}

    def _isam2(self) -> gtsam.ISAM2:
        return self._fls.getISAM2()  # by reference

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               stamps: dict[int, float], relinearize: bool = False,
               remove: list[int] | None = None) -> list[int]:
        timestamps = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t_s in stamps.items():
            timestamps.insert((key, t_s))
        # iSAM2 appends new factors (it does not reuse empty slots by default), and the
        # smoother marginalizes after adding them: their slots follow the current size.
        first = self._isam2().getFactorsUnsafe().size()
        self._changed()
        with _solvable():
            self._fls.update(graph, values, timestamps, remove or [])
        return list(range(first, first + graph.size()))

    def step(self) -> None:
        self._changed()
        with _solvable():
            for _ in range(self.relinearize_skip):  # its update cannot force relinearization
                self._fls.update()

    def replace(self, graph: gtsam.NonlinearFactorGraph, slots: list[int]) -> list[int]:
        return self.update(graph, gtsam.Values(), {}, remove=slots)

    def error(self) -> float:
        return float(self._fls.getFactors().error(self.estimate()))
