"""flight.yaml's initial position held against the data (the verdict's ``initial_position``).

The statistic (:meth:`cdtm_graph.results.PositionPrior.conflict`) in the linear-Gaussian
model it is derived in, then smoothed flights: a prior 20 m off at a stated 2 m is named
without ground truth, an honest 2 m prior never is. The rule's notes (a prior the data do
not lean on, a conflict beside a fault of the data) are in ``test_verdict.py``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cdtm_graph.codes import Code
from cdtm_graph.constants import chi2_quantile
from cdtm_graph.geometry import make_pose
from cdtm_graph.results import PositionPrior
from cdtm_graph.run import smooth_and_evaluate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS, Mode
from cdtm_graph.verdict.rules import assess

#: Monte Carlo draws: the mean of that many chi-square(3) has a standard deviation of
#: sqrt(6 / N) = 0.045, so the band below (3.3 of them) rejects a covariance 1.5x off
#: (mean 2 or 4.5).
DRAWS = 3000
MEAN_BAND = 0.15


def _posterior(rng, sigma_prior_m, data_cov, offset_cov, R):
    """One linear-Gaussian first frame: the truth, a prior drawn within its sigma, the
    data's fix drawn within ``data_cov`` plus the map's offset, and the posterior of the
    two; the run's covariance holds the offset as :class:`~cdtm_graph.results.MapOffset`
    adds it (body frame: ``R``)."""
    truth = rng.normal(scale=1000.0, size=3)
    mu = truth + sigma_prior_m * rng.standard_normal(3)
    offset = rng.multivariate_normal(np.zeros(3), offset_cov)
    x_data = truth + rng.multivariate_normal(np.zeros(3), data_cov) + offset
    prior_info = np.eye(3) / sigma_prior_m**2
    data_info = np.linalg.inv(data_cov)
    P = np.linalg.inv(prior_info + data_info)
    x = P @ (prior_info @ mu + data_info @ x_data)
    pose_cov = np.eye(6) * 1e-6
    pose_cov[3:, 3:] = R.T @ (P + offset_cov) @ R
    return mu, x_data, x, make_pose(R, x), pose_cov


def test_the_conflict_is_chi_square_and_gives_back_the_datas_fix(rng, manifold):
    """A 2 m prior against data that tell one axis 1 m, one 2 m and one 6 m, beside a
    declared map offset (3 m horizontal, 1 m vertical): the statistic is chi-square(3)
    (its mean within 0.15 of 3 over 3000 draws; 99.9% exceedances near 0.1%), and the
    data's fix and the prior's pull come back exactly. Mutations (2026-11-28): the
    offset's term left out of the covariance (``S = D``) -> mean 5.5; the statistic's
    covariance taken as the prior's and the offset's, without ``- P`` (``S = I + V^T O
    V``) -> mean 1.24; as the prior's alone -> mean 3.14 but 0.97% beyond the 99.9%
    bound: each fails."""
    sigma = 2.0
    Q = manifold.random_rotation(rng, np.pi)
    data_cov = Q @ np.diag([1.0, 4.0, 36.0]) @ Q.T
    offset_cov = np.diag([9.0, 9.0, 1.0])
    nis = np.empty(DRAWS)
    for i in range(DRAWS):
        R = manifold.random_rotation(rng, np.pi)
        mu, x_data, x, world_T_body, pose_cov = _posterior(rng, sigma, data_cov, offset_cov, R)
        conflict = PositionPrior(mu, sigma).conflict(world_T_body, pose_cov, offset_cov)
        assert conflict is not None and conflict.dof == 3
        nis[i] = conflict.nis
        if i < 20:
            assert conflict.distance_m == pytest.approx(np.linalg.norm(x_data - mu), rel=1e-6)
            assert conflict.pull_m == pytest.approx(np.linalg.norm(x - x_data), rel=1e-6)
    assert abs(nis.mean() - 3.0) < MEAN_BAND, nis.mean()
    assert np.mean(nis > chi2_quantile(0.999, 3)) < 0.004


def test_a_direction_only_the_prior_tells_is_left_out(rng, manifold):
    """Data that say nothing of the height (its variance 1e12 m^2): the test keeps the two
    directions the data tell (2 dof) and does not divide by the height's nothing; a prior
    the data cannot tell at all is not tested (None)."""
    sigma, R = 2.0, manifold.random_rotation(rng, np.pi)
    none = np.zeros((3, 3))
    mu, _, _, world_T_body, pose_cov = _posterior(
        rng, sigma, np.diag([1.0, 1.0, 1e12]), none, R)
    conflict = PositionPrior(mu, sigma).conflict(world_T_body, pose_cov, none)
    assert conflict is not None and conflict.dof == 2 and np.isfinite(conflict.nis)
    mu, _, _, world_T_body, pose_cov = _posterior(rng, sigma, np.eye(3) * 1e12, none, R)
    assert PositionPrior(mu, sigma).conflict(world_T_body, pose_cov, none) is None
    assert PositionPrior(mu, 0.0).conflict(world_T_body, pose_cov, none) is None


def _flight_with_prior(seed: int, off_m: float, sigma_m: float):
    """The robustness study's 30-frame flight with flight.yaml's initial position moved
    ``off_m`` from the truth (a seeded direction; 0: drawn within ``sigma_m``) and its
    sigma stated as ``sigma_m``."""
    log, dtm = SCENARIOS["clean"].flight(dataclasses.replace(BASE, frames=30, seed=seed))
    gt = log.groundtruth
    assert gt is not None
    truth = gt.position_m[np.searchsorted(gt.t_ns, log.frames.t_ns[0])]
    rng = np.random.default_rng(seed)
    direction = rng.standard_normal(3)
    error = (off_m * direction / np.linalg.norm(direction) if off_m
             else sigma_m * rng.standard_normal(3))
    init = dataclasses.replace(log.config.initial_state, position_m=truth + error,
                               sigma_position_m=sigma_m)
    return dataclasses.replace(log, config=dataclasses.replace(log.config,
                                                               initial_state=init)), dtm


@pytest.mark.slow
def test_a_prior_far_beyond_its_sigma_is_named_without_ground_truth(seed):
    """20 m off at a stated 2 m, three seeds, batch: the first frame 14-15 m off at 1.5 m
    sigma (ANEES 28-36, and `trusted` without ground truth before); now
    ``initial_position`` in every seed (4.9-5.4 sigma against the 4.0 bound; iSAM2 reads
    the same within 0.1), and an honest 2 m prior on the same flights is never named
    (1.1-1.6 sigma), 2026-11-28. Mutations: the rule's reason
    switched off -> fails; the distance taken in the prior's sigma alone, ``Sp - P`` as
    ``Sp``, reads 2.7-3.3 sigma and names no seed -> fails."""
    settings = Mode.BATCH.settings(SmootherSettings())
    for s in (seed, seed + 1, seed + 2):
        far = smooth_and_evaluate(*_flight_with_prior(s, 20.0, 2.0), settings)
        codes = [r.code for r in assess(far.result).reasons]
        assert Code.INITIAL_POSITION in codes, (s, codes)
        honest = smooth_and_evaluate(*_flight_with_prior(s, 0.0, 2.0), settings)
        assert Code.INITIAL_POSITION not in [r.code for r in assess(honest.result).reasons]
        assert not any(n.startswith("initial_position") for n in honest.verdict.notes)


@pytest.mark.slow
def test_a_fixed_lag_holds_the_prior_against_the_whole_flights_first_frame(seed):
    """The same 20 m off at 2 m in the fixed lag: its own first frame is the window's it
    left, where the prior holds most of it (3.9 sigma on this flight, under the 4.0 bound;
    ANEES 26.5); the calibration check's side solve gives the whole flight's view of it
    (5.3 sigma): named (2026-11-28; 60 frames, seeds 0-2: 3 of 3, was 1 of 3). Mutation:
    the fixed lag's own first frame (``first_frame`` left unused) -> fails."""
    log, dtm = _flight_with_prior(seed, 20.0, 2.0)
    result = smooth_and_evaluate(log, dtm, Mode.FIXED_LAG.settings(SmootherSettings())).result
    assert result.calibration_check is not None
    assert result.calibration_check.first_frame is not None
    assert Code.INITIAL_POSITION in [r.code for r in assess(result).reasons]
