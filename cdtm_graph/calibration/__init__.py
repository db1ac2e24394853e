"""The camera calibration: estimated online, checked after a run, and the bias the
features' noise leaves in it.

- :mod:`~cdtm_graph.calibration.online`: the camera-IMU time offset, the mount rotation
  and a focal scale as one more variable of the batch graph (``C(0)``).
- :mod:`~cdtm_graph.calibration.check`: a run that held flight.yaml's calibration is
  checked by a side solve that estimates it (``calibration_suspect``).
- :mod:`~cdtm_graph.calibration.noise_bias`: the bias the features' noise leaves in the
  focal scale, taken out.
"""
