"""Synthetic flights for tests, studies and benchmarks: trajectories, terrain, IMU, logs.

Not part of the estimator: nothing outside ``sim``, ``studies``, ``cli`` and ``plots``
imports it (``tests/project/test_layout.py``).

- :mod:`~cdtm_graph.sim.trajectory`: flight plans and their exact kinematics.
- :mod:`~cdtm_graph.sim.terrain`: fractal terrain, cloned cells, Fig. 6's sigma_h.
- :mod:`~cdtm_graph.sim.imu`: IMU samples along a plan, with noise and bias walks.
- :mod:`~cdtm_graph.sim.simulate`: whole flight logs (``cdtm simulate``).
- :mod:`~cdtm_graph.sim.scenario`: two-frame scenarios of the paper's studies.
"""
