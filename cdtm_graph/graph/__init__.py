"""The factor graph: what each factor is built from, and the whole log's graph.

- :mod:`~cdtm_graph.graph.builders`: small functions that each return factors (priors,
  IMU, C-DTM) and :class:`GraphSettings`, how they are built.
- :mod:`~cdtm_graph.graph.log_graph`: the whole log's graph for the batch solver and the
  calibration check (:func:`~cdtm_graph.graph.log_graph.build_log_graph`).
"""

from cdtm_graph.graph.builders import (
    DEFAULT_CALIBRATION_SIGMAS,
    CdtmBuild,
    GraphSettings,
    cdtm_factors,
    cdtm_information,
    dtm_ray_caster,
    feature_noise,
    imu_factor,
    insert_state,
    prior_factors,
    track_observations,
    without_tracks,
)

__all__ = [
    "CdtmBuild", "DEFAULT_CALIBRATION_SIGMAS", "GraphSettings", "cdtm_factors",
    "cdtm_information", "dtm_ray_caster", "feature_noise", "imu_factor", "insert_state",
    "prior_factors", "track_observations", "without_tracks",
]
