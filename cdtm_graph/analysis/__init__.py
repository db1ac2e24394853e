"""A-priori accuracy analysis: what the geometry allows, before (or beside) any solve.

- :mod:`~cdtm_graph.analysis.closed_form`: the paper's closed-form covariance of a frame
  pair (eqs. 9-32) and the degeneracy checks of section V.B.
- :mod:`~cdtm_graph.analysis.two_frame`: the two-frame C-DTM solve with GTSAM's marginal
  beside the closed form (``cdtm analyze``).
- :mod:`~cdtm_graph.analysis.accuracy_map`: the predicted accuracy over a DTM
  (``cdtm accuracy-map``).

It uses the estimator's factors and solver; the estimator does not import it.
"""
