"""The paper's studies: sensitivity sweeps (Figs. 2-9) and navigation tables (Tables 1-2).

A harness around the estimator, not part of it (``tests/project/test_layout.py``).

- :mod:`~cdtm_graph.studies.sweeps`: ``cdtm study``, Monte Carlo against the closed form.
- :mod:`~cdtm_graph.studies.navsim`: ``cdtm navsim``, Free vs Compensated navigation.
"""
