"""A running smoother's map error grown as the flight goes: :class:`~cdtm_graph.robust.
map_error.MapErrorWatch` reads the map at the track judge's rounds, :class:`MapGrowth`
makes the smoother go on with what it read (a live user cannot be smoothed again;
:func:`~cdtm_graph.smoother.smooth` makes the run again instead)."""

from __future__ import annotations

import logging
from dataclasses import replace

from cdtm_graph.dtm import Dtm
from cdtm_graph.graph import dtm_ray_caster
from cdtm_graph.robust.map_error import MapErrorSettings, MapErrorWatch, grown_map
from cdtm_graph.robust.stages import BuildFactors
from cdtm_graph.robust.track_judge import TrackJudge
from cdtm_graph.smoother.window import SolverWindow

logger = logging.getLogger(__name__)


class MapGrowth:
    """What a grown map error changes in a running smoother: the factors it builds (their
    noise, and their tangent planes' slopes regional), the track tests, and the factors
    already in the solver.

    Args:
        watch: reads the map and decides. dtm: the map as given (the grid).
        settings: what a grown map takes (its regional slopes: :func:`~cdtm_graph.
            robust.map_error.grown_map`).
        build: the stage that builds the factors. judge: the track tests.
        window: the solver's side.
    """

    def __init__(self, watch: MapErrorWatch, dtm: Dtm, settings: MapErrorSettings,
                 build: BuildFactors, judge: TrackJudge, window: SolverWindow):
        self.watch, self.dtm, self.settings = watch, dtm, settings
        self.build, self.judge, self.window = build, judge, window
        self.grown: list[tuple[int, float]] = []  # (frame, sigma_h from that frame on)

    def read(self, k: int) -> bool:
        """Frame k's reading of the map from the tracks its round judged (the left out
        ones too), the cameras taken as exact; grown if it shows (returns whether)."""
        heights = self.judge.last_round_heights()
        sigma_h_m = None if heights is None else self.watch.read(k, heights)
        if sigma_h_m is not None:
            self._grow(sigma_h_m, k)
        return sigma_h_m is not None

    def _grow(self, sigma_h_m: float, k: int) -> None:
        build = self.build
        if build.dtm is self.dtm:  # (the first growth: the grid smoothed once)
            build.dtm = grown_map(self.dtm, self.settings)
        build.noise = self.judge.noise = replace(build.noise, sigma_h_m=sigma_h_m)
        self.window.on_map(build.noise, dtm_ray_caster(build.dtm), k)
        self.grown.append((k, sigma_h_m))
        logger.info("frame %d: the map's height error grown to %.2f m (stated %.2f m)", k,
                    sigma_h_m, self.watch.stated_m)
