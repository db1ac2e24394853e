"""cdtm-graph: factor-graph smoothing for aircraft navigation from camera, IMU and DTM.

Implements the C-DTM constraint of Kupervasser, Lerner, Rivlin and Rotstein ("Error
Analysis for a Navigation Algorithm based on Optical-Flow and a Digital Terrain Map")
as GTSAM factors, fuses it with IMU preintegration, and cross-checks GTSAM's marginal
covariances against the paper's closed form (eq. 13).
"""

__version__ = "0.1.0"
