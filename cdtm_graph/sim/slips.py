"""Tracker slips: what a real feature tracker does to tracks besides random wrong matches.

A wrong match to a random pixel is the easiest fault to catch: it breaks the epipolar
geometry. Real trackers also fail in ways the geometry of two frames cannot see, and
these are what this module does to a finished simulated log (its ground truth gives the
true cameras):

* :func:`with_track_jumps`: a track slips once, at a random sighting, to a ground point
  a few to a few tens of pixels away (a repeated texture, a shadow edge) and follows that
  point from then on. Each of its pairs is consistent with *some* ground point; only the
  pair that spans the jump is not.
* :func:`with_track_drift`: a track drifts from a random sighting on, a fixed rate
  (0.5-1.5 px a frame) in a fixed direction, accumulating (Lucas-Kanade on a smooth
  texture). Each pair is off by a pixel or so; the track as a whole is not.
* :func:`with_cluster_drift`: the tracks starting in one region of the image drift
  together, one rate and one direction for all (a cloud shadow, a moving object, a smear
  over part of the lens): the neighbours agree with each other.
* :func:`with_epipolar_wrong_matches`: a wrong match on the epipolar line: the pixel of
  a point on the earlier sighting's ray at another range (the wrong one of two similar
  patches along the line), which the epipolar check cannot reject.

Each returns a new log and which rows of tracks.csv it changed (rows a slip carried out
of the image are dropped, as a tracker loses them). The inputs are left alone.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cdtm_graph.dtm import Dtm
from cdtm_graph.flightlog import FlightLog, Tracks

#: A slipped track's new ground point lies this far from the old one, in the image (px).
JUMP_PX = (3.0, 40.0)
#: A drifting track moves this much a frame (px), in a fixed direction.
DRIFT_PX_PER_FRAME = (0.5, 1.5)
#: A wrong match on the epipolar line: the point on the earlier ray at the true range
#: times a factor between these, either way (nearer or farther).
RANGE_FACTOR = (1.3, 2.0)


def _truth_cameras(log: FlightLog) -> np.ndarray:
    """(K, 4, 4) the true ``world_T_cam`` at each frame."""
    if log.groundtruth is None:
        raise ValueError("the log has no ground truth: a slip needs the true cameras")
    world_T_body = log.groundtruth.interpolate(log.frames.t_ns).world_T_body
    return world_T_body @ log.config.camera.body_T_cam


def _tracks(log: FlightLog) -> Tracks:
    if log.tracks is None:
        raise ValueError("the log has no tracks")
    return log.tracks


def _sightings(tracks: Tracks) -> dict[int, np.ndarray]:
    """Track id -> its rows, in frame order."""
    order = np.lexsort((tracks.frame, tracks.track_id))
    ids = tracks.track_id[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    return {int(ids[s]): rows for s, rows in zip(starts, np.split(order, starts[1:]))}


def _project(log: FlightLog, world_T_cam: np.ndarray, point_m: np.ndarray) -> np.ndarray:
    """(n, 2) pixels of one world point (3,) in the cameras (n, 4, 4); NaN behind them."""
    R, t = world_T_cam[:, :3, :3], world_T_cam[:, :3, 3]
    in_cam = np.einsum("nji,nj->ni", R, point_m[None, :] - t)
    return log.config.camera.camera.rays_to_pixels(in_cam)


def _replaced(log: FlightLog, uv_px: np.ndarray, changed: np.ndarray
              ) -> tuple[FlightLog, np.ndarray]:
    """The log with these pixels; rows carried out of the image (or NaN) dropped.
    Returns the log and the changed rows among the kept ones."""
    tracks = _tracks(log)
    camera = log.config.camera.camera
    keep = ~changed | camera.in_image(uv_px)
    new = Tracks(tracks.frame[keep], tracks.track_id[keep], uv_px[keep])
    return dataclasses.replace(log, tracks=new), changed[keep]


def _chosen_tracks(tracks: Tracks, fraction: float, rng: np.random.Generator,
                   min_sightings: int) -> list[np.ndarray]:
    """The rows of a random ``fraction`` of the tracks seen at least ``min_sightings``
    times."""
    long = [rows for rows in _sightings(tracks).values() if rows.size >= min_sightings]
    picked = rng.random(len(long)) < fraction
    return [rows for rows, p in zip(long, picked) if p]


def _unit_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.column_stack([np.cos(angle), np.sin(angle)])


def with_track_jumps(log: FlightLog, dtm: Dtm, fraction: float, rng: np.random.Generator,
                     jump_px: tuple[float, float] = JUMP_PX) -> tuple[FlightLog, np.ndarray]:
    """A ``fraction`` of the tracks (of three sightings or more) each slip once, at a
    random sighting after their first, to the ground point ``jump_px`` away in the image
    (uniform, any direction) and follow that point from then on.

    The new point is where the slipped pixel's ray meets ``dtm`` (the log's map: within
    the map error of the true ground, a pixel or less). A jump whose pixel misses the map
    is not made.

    Returns:
        The log, and which of its tracks.csv rows slipped, (M,) bool.
    """
    tracks = _tracks(log)
    cameras = _truth_cameras(log)
    camera = log.config.camera.camera
    uv = tracks.uv_px.copy()
    changed = np.zeros(len(tracks), dtype=bool)
    for rows in _chosen_tracks(tracks, fraction, rng, 3):
        j = int(rng.integers(1, rows.size))
        at = rows[j]
        slipped = uv[at] + rng.uniform(*jump_px) * _unit_directions(rng, 1)[0]
        world_T_cam = cameras[tracks.frame[at]]
        ray = world_T_cam[:3, :3] @ camera.pixels_to_rays(slipped[None])[0]
        hit = dtm.raycast(world_T_cam[:3, 3], ray)
        if not np.isfinite(hit.point[0]).all():
            continue
        later = rows[j:]
        uv[later] = _project(log, cameras[tracks.frame[later]], hit.point[0])
        changed[later] = True
    return _replaced(log, uv, changed)


def _drifted(log: FlightLog, groups: list[tuple[np.ndarray, np.ndarray]]
             ) -> tuple[FlightLog, np.ndarray]:
    """Each group's rows (in frame order) moved by its velocity (2,) px a frame, counted
    from the group's first row."""
    tracks = _tracks(log)
    uv = tracks.uv_px.copy()
    changed = np.zeros(len(tracks), dtype=bool)
    for rows, velocity in groups:
        frames = tracks.frame[rows] - tracks.frame[rows[0]]
        uv[rows] += frames[:, None] * velocity[None, :]
        changed[rows[1:]] = True
    return _replaced(log, uv, changed)


def with_track_drift(log: FlightLog, fraction: float, rng: np.random.Generator,
                     px_per_frame: tuple[float, float] = DRIFT_PX_PER_FRAME
                     ) -> tuple[FlightLog, np.ndarray]:
    """A ``fraction`` of the tracks (of three sightings or more) drift from a random
    sighting on: ``px_per_frame`` (uniform) in a random direction, each frame, added up.

    Returns:
        The log, and which of its tracks.csv rows drifted, (M,) bool.
    """
    tracks = _tracks(log)
    groups = []
    for rows in _chosen_tracks(tracks, fraction, rng, 3):
        start = int(rng.integers(0, rows.size - 1))
        velocity = rng.uniform(*px_per_frame) * _unit_directions(rng, 1)[0]
        groups.append((rows[start:], velocity))
    return _drifted(log, groups)


def with_cluster_drift(log: FlightLog, rng: np.random.Generator, radius_px: float = 120.0,
                       px_per_frame: float = 1.0) -> tuple[FlightLog, np.ndarray]:
    """The tracks whose first sighting lies within ``radius_px`` of one random image
    point drift together from that sighting on: ``px_per_frame`` in one random direction
    for all of them, added up frame by frame.

    Returns:
        The log, and which of its tracks.csv rows drifted, (M,) bool.
    """
    tracks = _tracks(log)
    camera = log.config.camera.camera
    centre = rng.uniform([radius_px, radius_px],
                         [camera.width - radius_px, camera.height - radius_px])
    velocity = px_per_frame * _unit_directions(rng, 1)[0]
    groups = [(rows, velocity) for rows in _sightings(tracks).values()
              if rows.size >= 2 and np.hypot(*(tracks.uv_px[rows[0]] - centre)) <= radius_px]
    return _drifted(log, groups)


def with_epipolar_wrong_matches(log: FlightLog, fraction: float, rng: np.random.Generator,
                                range_factor: tuple[float, float] = RANGE_FACTOR
                                ) -> tuple[FlightLog, np.ndarray]:
    """A ``fraction`` of the sightings that have an earlier one moved along their
    epipolar line: to the pixel of the point on the earlier sighting's ray (the true
    camera there) at its true range times a factor in ``range_factor``, or divided by
    one. The true range is the earlier ray's to the true point, which this frame's
    true pixel gives (the two rays' closest approach).

    Returns:
        The log, and which of its tracks.csv rows were replaced, (M,) bool.
    """
    tracks = _tracks(log)
    cameras = _truth_cameras(log)
    camera = log.config.camera.camera
    uv = tracks.uv_px.copy()
    changed = np.zeros(len(tracks), dtype=bool)
    for rows in _sightings(tracks).values():
        for before, at in zip(rows[:-1], rows[1:]):
            if rng.random() >= fraction:
                continue
            a, b = cameras[tracks.frame[before]], cameras[tracks.frame[at]]
            ray_a = a[:3, :3] @ camera.pixels_to_rays(tracks.uv_px[before][None])[0]
            ray_b = b[:3, :3] @ camera.pixels_to_rays(tracks.uv_px[at][None])[0]
            range_a = _closest_approach(a[:3, 3], ray_a, b[:3, 3], ray_b)
            if not np.isfinite(range_a) or range_a <= 0.0:
                continue
            factor = rng.uniform(*range_factor)
            if rng.random() < 0.5:
                factor = 1.0 / factor
            wrong = a[:3, 3] + factor * range_a * ray_a
            uv[at] = _project(log, b[None], wrong)[0]
            changed[at] = True
    return _replaced(log, uv, changed)


def _closest_approach(origin_a: np.ndarray, ray_a: np.ndarray, origin_b: np.ndarray,
                      ray_b: np.ndarray) -> float:
    """The parameter ``s`` of ``origin_a + s ray_a`` closest to the line ``origin_b + u
    ray_b`` (NaN for parallel rays)."""
    w = origin_a - origin_b
    aa, bb, ab = ray_a @ ray_a, ray_b @ ray_b, ray_a @ ray_b
    denominator = aa * bb - ab * ab
    if denominator <= 1e-12 * aa * bb:
        return float("nan")
    return float((ab * (ray_b @ w) - bb * (ray_a @ w)) / denominator)
