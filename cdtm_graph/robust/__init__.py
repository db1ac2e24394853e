"""What keeps bad data out while solving: the defences the smoothers run as stages.

- :mod:`~cdtm_graph.robust.stages`: the ordered list of per-frame stages both smoothers
  run over a frame's sightings, and how to add one.
- :mod:`~cdtm_graph.robust.epipolar`: wrong matches out before the graph (two-point
  RANSAC against the IMU's rotation).
- :mod:`~cdtm_graph.robust.gating`: chi-square tests of features (the innovation gate, the
  outlier count).
- :mod:`~cdtm_graph.robust.mismatch`: terrain the DTM lacks, seen by tracks and their
  neighbours; :mod:`~cdtm_graph.robust.neighbours`: the spatial views' one search.
- :mod:`~cdtm_graph.robust.clutter`: clutter over a region (forest, town): a mixture fit.
- :mod:`~cdtm_graph.robust.track_judge`: the incremental smoother's judge of tracks;
  :mod:`~cdtm_graph.robust.track_tests`: the batch's rounds of the same tests.
- :mod:`~cdtm_graph.robust.fix_search` and :mod:`~cdtm_graph.robust.acquisition`: finding
  the fix when the prior is wider than the smoothers pull in.

The wing never imports the smoothers (``tests/project/test_layout.py``).
"""
