"""Where the clean flights' covariance is pessimistic, split by noise source (issue 21).

The batch's error linearized at the truth, one part per source, against the part of the
covariance the noise model gives that source (build 7; docs/verdict.md, "The pessimism
split by noise source").

Run: ``python scripts/map_error_split.py [--frames 30] [--seeds 1 16] [--robust]
[--scenario detail_waves|detail_ridges|detail_bumps]
[--exact-dtm] [--no-shared] [--track-whitening [--height-scale S]]``.

The graph of each clean flight is built at its true states (no robust kernel unless
``--robust``), linearized there, and one Gauss-Newton step taken from the truth: ``dx =
P g``, ``P = (A^T A)^-1``, ``g = sum_c g_c``; ``dx`` is the error the estimate would have
to first order, and each source c (the C-DTM residuals' DTM part, their second-observation
``q_b`` pixel part, their first-observation ``q_a`` part; the IMU factors; the priors)
gives its own ``dx_c = P g_c``. Per source, per frame, the position NEES of ``dx_c``
against ``P``'s position block ("realized", the mean over frames and seeds) is printed
beside the share of ``P`` the model gives the source ("model": ``trace(P_pp^-1 (P M_c
P)_pp)``, ``M_c`` the source's information, summing to 3 over the sources). The C-DTM
residual at the truth is split by evaluating it again on the true terrain (the DTM part
is the difference) and with the noise-free first ray (the ``q_b`` part is what is left).

For the DTM part two more models: the residuals of a track's pairs sharing one height
error (``dh`` common to the track, ``sigma_h`` as stated: "track-shared") and the same
with each track's realized ``dh`` in place of sigma_h's spread (the map as it is at the
features, "track-shared, realized dh^2"); the realized ``dh`` at the features (DTM less
the true terrain at the true ground point) and the DTM residual's regression on it (1:
the factor's linear model). And per IMU factor, the whitened residual at the truth per
row (1 each for an honest IMU model).

``--track-whitening`` solves the same linearized batch (no kernel) three ways instead
(:func:`track_whitening`): with the pair factors as they are; the same estimate against
its true first-order covariance (the sandwich); and each track's C-DTM rows whitened
jointly. Each row's first-order noise comes from the factor's response to one sigma of
each source (:meth:`factors.CdtmPairFactor.noise_moved`): the two pixel coordinates of
each sighting, shared by the pairs that hold it, and the track's DTM height, shared by all
its pairs (docs/verdict.md, "What it would gain").
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import defaultdict

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from cdtm_graph.graph.builders import dtm_ray_caster
from cdtm_graph.graph.log_graph import build_log_graph
from cdtm_graph.sim.simulate import simulate
from cdtm_graph.smoother import SmootherSettings
from cdtm_graph.studies.robustness import BASE, SCENARIOS
from factors import CdtmPairFactor, PlaneMode, RobustKernel

#: the sources, in the order printed
SOURCES = ("cdtm_dtm", "cdtm_qb", "cdtm_qa", "imu", "prior")
#: sources taken together (their errors are correlated: one observation is q_b of one pair
#: and q_a of the next)
GROUPS = {"cdtm_pixel": ("cdtm_qb", "cdtm_qa"), "cdtm": ("cdtm_dtm", "cdtm_qb", "cdtm_qa")}


def truth_values(sim) -> gtsam.Values:
    """Every frame's true pose, velocity and IMU bias."""
    flight = sim.log
    t = flight.frames.t_ns
    gt = flight.groundtruth.interpolate(t)
    values = gtsam.Values()
    for k in range(len(t)):
        j = int(np.clip(np.searchsorted(sim.imu.t_ns, t[k]), 0, sim.imu.t_ns.size - 1))
        values.insert(X(k), gtsam.Pose3(gt.world_T_body[k]))
        values.insert(V(k), gt.velocity_mps[k])
        values.insert(B(k), gtsam.imuBias.ConstantBias(sim.imu.accel_bias[j],
                                                       sim.imu.gyro_bias[j]))
    return values


def _columns(K: int) -> dict[int, int]:
    """Column of each key in the dense system: per frame X (6), V (3), B (6)."""
    col, out = 0, {}
    for k in range(K):
        for key, dim in ((X(k), 6), (V(k), 3), (B(k), 6)):
            out[key] = col
            col += dim
    return out


def _dense(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, cols: dict[int, int],
           n: int) -> tuple[np.ndarray, np.ndarray]:
    """Whitened (A, b) of a graph at ``values`` (GTSAM's ``A dx - b``), columns ``cols``."""
    rows_A, rows_b = [], []
    linear = graph.linearize(values)
    for i in range(linear.size()):
        f = linear.at(i)
        A_f, b_f = f.jacobian()
        A = np.zeros((A_f.shape[0], n))
        c = 0
        for key in f.keys():
            d = 6 if gtsam.Symbol(key).chr() in (ord("x"), ord("b")) else 3
            A[:, cols[key]:cols[key] + d] = A_f[:, c:c + d]
            c += d
        rows_A.append(A)
        rows_b.append(b_f)
    return np.vstack(rows_A), np.concatenate(rows_b)



def _pair_rows(Ha: np.ndarray, Hb: np.ndarray, a: int, b: int, cols: dict[int, int],
               n: int) -> np.ndarray:
    """(F, 2, n) a pair factor's features' rows in the dense system (its Jacobians (F, 2, 6)
    w.r.t. X(a) and X(b) in their columns)."""
    H = np.zeros((Ha.shape[0], 2, n))
    H[:, :, cols[X(a)]:cols[X(a)] + 6] = Ha
    H[:, :, cols[X(b)]:cols[X(b)] + 6] = Hb
    return H


def _position_blocks(values: gtsam.Values, cols: dict[int, int], K: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's body-to-world rotation (K, 3, 3) at ``values`` and its position's three
    columns in the dense system (K, 3)."""
    R = np.stack([values.atPose3(X(k)).rotation().matrix() for k in range(K)])
    return R, np.array([cols[X(k)] + 3 for k in range(K)])[:, None] + np.arange(3)[None]

def _true_rays(sim) -> dict[tuple[int, int], np.ndarray]:
    """(frame, track id) -> the noise-free normalized ray (z = 1) of that sighting."""
    tracks = sim.log.tracks
    rays = sim.log.config.camera.camera.pixels_to_rays(sim.uv_true_px)
    rays = rays / rays[:, 2:3]
    return {(int(f), int(t)): rays[i] for i, (f, t) in enumerate(zip(tracks.frame,
                                                                      tracks.track_id))}


def split_one(sim, robust: RobustKernel, shared_dtm_error: bool = True) -> dict:
    """One flight's per-frame position NEES of each source (realized and model)."""
    flight, dtm = sim.log, sim.dtm
    K = len(flight.frames)
    values = truth_values(sim)
    base = SmootherSettings().graph
    graph_settings = dataclasses.replace(base, robust=robust, shared_dtm_error=shared_dtm_error)
    lg = build_log_graph(flight, dtm, graph_settings, values)
    cols = _columns(K)
    n = 15 * K
    A_base, b_base = _dense(lg.base, values, cols, n)
    imu_rows = np.zeros(b_base.size, bool)
    chi2_imu = []
    linear = lg.base.linearize(values)
    r = 0
    for i in range(linear.size()):
        m = linear.at(i).jacobian()[1].size
        if m == 15:  # a CombinedImuFactor
            imu_rows[r:r + m] = True
            chi2_imu.append(linear.at(i).jacobian()[1] ** 2)
        r += m
    info = {c: np.zeros((n, n)) for c in SOURCES}
    grad = {c: np.zeros(n) for c in SOURCES}
    info["imu"] = A_base[imu_rows].T @ A_base[imu_rows]
    info["prior"] = A_base[~imu_rows].T @ A_base[~imu_rows]
    grad["imu"] = A_base[imu_rows].T @ b_base[imu_rows]
    grad["prior"] = A_base[~imu_rows].T @ b_base[~imu_rows]
    info_track_shared = np.zeros((n, n))
    info_track_realized = np.zeros((n, n))
    track_sum: dict[int, np.ndarray] = defaultdict(lambda: np.zeros(n))
    track_dh: dict[int, float] = {}
    per_dof: dict[str, list[np.ndarray]] = defaultdict(list)
    true_rays = _true_rays(sim)
    truth_cast = dtm_ray_caster(sim.terrain)
    sigma_h = None
    dh_true_all, dh_fit_all, rank_all = [], [], []
    for f, ids in zip(lg.cdtm, lg.track_ids):
        a, b = int(gtsam.Symbol(f.key_a).index()), int(gtsam.Symbol(f.key_b).index())
        Ta = values.atPose3(X(a)).matrix()
        Tb = values.atPose3(X(b)).matrix()
        feats = f.features
        sigma_h = float(feats.noise.sigma_h_m)
        scale = (feats.dtm_variance_scale if feats.dtm_variance_scale is not None
                 else np.ones(feats.n))
        e, Ha, Hb = f.innovations(Ta, Tb)  # whitened, no kernel
        if robust is not RobustKernel.NONE:  # the kernel's IRLS weights at the truth
            e_r = f.evaluate(Ta, Tb, True)[0]
            w = np.ones(feats.n)
            nz = np.einsum("ni,ni->n", e, e) > 0
            w[nz] = np.sqrt(np.einsum("ni,ni->n", e_r, e_r)[nz]
                            / np.einsum("ni,ni->n", e, e)[nz])
        else:
            w = np.ones(feats.n)
        # the same data on the true terrain: the pixel part
        on_truth = CdtmPairFactor(f.key_a, f.key_b, feats, f.body_T_cam, PlaneMode.REINTERSECT,
                                  truth_cast, RobustKernel.NONE)
        e_pix = on_truth.innovations(Ta, Tb)[0]
        qa_true = np.stack([true_rays[(a, int(t))] for t in ids])
        exact_a = CdtmPairFactor(f.key_a, f.key_b, dataclasses.replace(feats, q_a=qa_true),
                                 f.body_T_cam, PlaneMode.REINTERSECT, truth_cast,
                                 RobustKernel.NONE)
        e_qb = exact_a.innovations(Ta, Tb)[0]
        parts = {"cdtm_dtm": e - e_pix, "cdtm_qb": e_qb, "cdtm_qa": e_pix - e_qb}
        # the residual per metre of DTM height (the plane moved up 1 m, held)
        wTc_a = Ta @ f.body_T_cam
        G, Nrm = f.planes(wTc_a)
        up = CdtmPairFactor(f.key_a, f.key_b, feats, f.body_T_cam, PlaneMode.FIXED)
        shifted = CdtmPairFactor(f.key_a, f.key_b, dataclasses.replace(
            feats, G_E=G + np.array([0.0, 0.0, 1.0]), N=Nrm), f.body_T_cam, PlaneMode.FIXED)
        up.features = dataclasses.replace(feats, G_E=G, N=Nrm)
        v = shifted.innovations(Ta, Tb)[0] - up.innovations(Ta, Tb)[0]  # (n, 2) per metre
        # realized dh at the hit: the log's DTM less the true terrain there
        dh_true = dtm.height(G[:, 0], G[:, 1]) - sim.terrain.height(G[:, 0], G[:, 1])
        vv = np.einsum("ni,ni->n", v, v)
        dh_fit = np.einsum("ni,ni->n", parts["cdtm_dtm"], v) / vv
        dh_true_all.append(dh_true)
        dh_fit_all.append(dh_fit)
        rank_all.append(np.round((np.sqrt(8 * scale + 1) - 1) / 2))
        H = _pair_rows(Ha, Hb, a, b, cols, n) * w[:, None, None]
        # model: the DTM's part of the whitened residual's covariance, v v^T sigma_h^2 scale
        C_dtm = np.einsum("ni,nj->nij", v, v) * (sigma_h**2 * scale)[:, None, None]
        C_pix = np.eye(2)[None] - C_dtm
        HT = np.swapaxes(H, 1, 2)  # (n, N, 2)
        info["cdtm_dtm"] += np.einsum("nai,nij,nbj->ab", HT, C_dtm, HT)
        info["cdtm_qb"] += np.einsum("nai,nij,nbj->ab", HT, C_pix, HT)
        for c, part in parts.items():
            grad[c] += -np.einsum("nai,ni->a", HT, part * w[:, None])
            per_dof[c].append(np.einsum("ni,ni->n", part, part) / 2)
        per_dof["all"].append(np.einsum("ni,ni->n", e, e) / 2)
        per_dof["model_dtm"].append(np.trace(C_dtm, axis1=1, axis2=2) / 2)
        Hv = np.einsum("nai,ni->na", HT, v)  # per feature, its gradient per metre of dh
        for i, t in enumerate(ids.tolist()):
            track_sum[t] += Hv[i]
            track_dh.setdefault(t, float(dh_true[i]))
    for t, h in track_sum.items():
        info_track_shared += sigma_h**2 * np.outer(h, h)
        info_track_realized += track_dh[t] ** 2 * np.outer(h, h)
    A_cdtm_info = sum(info[c] for c in ("cdtm_dtm", "cdtm_qb"))
    Lambda = A_cdtm_info + info["imu"] + info["prior"]
    P = np.linalg.inv(Lambda)
    R, idx = _position_blocks(values, cols, K)

    def pos_world(dx):  # (K, 3) world-frame position errors
        return np.einsum("kij,kj->ki", R, dx[idx])

    def cov_world(M):  # (K, 3, 3)
        C = P @ M @ P if M is not None else P
        blocks = C[idx[:, :, None], idx[:, None, :]]
        return R @ blocks @ np.swapaxes(R, 1, 2)

    Ppp = cov_world(None)
    Pinv = np.linalg.inv(Ppp)

    def nees(dp):
        return np.einsum("ki,kij,kj->k", dp, Pinv, dp)

    def share(M):
        return np.einsum("kij,kji->k", Pinv, cov_world(M))

    out = {"realized": {}, "model": {}}
    total = np.zeros(n)
    for c in SOURCES:
        dx = P @ grad[c]
        total += dx
        out["realized"][c] = nees(pos_world(dx))
        out["model"][c] = share(info[c])
    out["realized"]["total"] = nees(pos_world(total))
    for name, group in GROUPS.items():
        out["realized"][name] = nees(pos_world(P @ sum(grad[c] for c in group)))
        out["model"][name] = share(sum(info[c] for c in group))
    out["model"]["total"] = np.full(K, 3.0)
    out["model"]["dtm_track_shared"] = share(info_track_shared)
    out["model"]["dtm_track_realized"] = share(info_track_realized)
    dh_t, dh_f = np.concatenate(dh_true_all), np.concatenate(dh_fit_all)
    out["dh_rms"] = float(np.sqrt(np.mean(dh_t**2)))
    out["dh_track_rms"] = float(np.sqrt(np.mean(np.array(list(track_dh.values())) ** 2)))
    out["dh_slope"] = float(np.dot(dh_t, dh_f) / max(np.dot(dh_t, dh_t), 1e-300))
    out["dh_fit_resid_rms"] = float(np.sqrt(np.mean((dh_f - dh_t) ** 2)))
    out["sigma_h"] = sigma_h
    out["per_dof"] = {c: float(np.concatenate(x).mean()) for c, x in per_dof.items()}
    out["n_tracks"] = len(track_sum)
    out["mean_rank"] = float(np.concatenate(rank_all).mean())
    imu = np.concatenate(chi2_imu) if chi2_imu else np.zeros(0)
    out["imu_chi2_per_row"] = imu.reshape(-1, 15).mean(axis=0)
    return out


def track_whitening(sim, height_scale: float = 1.0) -> dict[str, float]:
    """One flight's linearized batch solved with independent pairs, against its sandwich
    covariance, and with each track's rows whitened jointly (module docstring): per
    estimator its 3-D position RMSE (m), its rms 3-D position sigma (m) and ANEES. The
    joint rows take the track's height noise at ``height_scale`` times sigma_h (the pairs'
    estimate and its sandwich keep the stated one)."""
    flight = sim.log
    K = len(flight.frames)
    values = truth_values(sim)
    settings = dataclasses.replace(SmootherSettings().graph, robust=RobustKernel.NONE)
    lg = build_log_graph(flight, sim.dtm, settings, values)
    cols = _columns(K)
    n = 15 * K
    A_base, b_base = _dense(lg.base, values, cols, n)
    info_base, grad_base = A_base.T @ A_base, A_base.T @ b_base
    # per track: each row pair's Jacobian (2, n), whitened residual (2,) and its loadings
    # on the noise it shares: ("q", frame, axis) per sighting, ("h",) the track's height
    tracks: dict[int, list[tuple[np.ndarray, np.ndarray, dict]]] = defaultdict(list)
    for f, ids in zip(lg.cdtm, lg.track_ids):
        a, b = int(gtsam.Symbol(f.key_a).index()), int(gtsam.Symbol(f.key_b).index())
        Ta, Tb = values.atPose3(X(a)).matrix(), values.atPose3(X(b)).matrix()
        e, Ha, Hb = f.innovations(Ta, Tb)
        moved, _, _ = f.noise_moved(Ta, Tb)
        e_moved = moved.innovations(Ta, Tb)[0].reshape(5, 2, f.features.n, 2)
        load = 0.5 * (e_moved[:, 0] - e_moved[:, 1])  # (source, feature, 2): +1 sigma
        load_h = height_scale * load[4]
        H = _pair_rows(Ha, Hb, a, b, cols, n)
        for i, t in enumerate(ids.tolist()):
            tracks[t].append((H[i], e[i], {("q", a, 0): load[0, i], ("q", a, 1): load[1, i],
                                        ("q", b, 0): load[2, i], ("q", b, 1): load[3, i],
                                        ("h",): load_h[i]}))
    info_pairs, grad_pairs = info_base.copy(), grad_base.copy()
    info_joint, grad_joint = info_base.copy(), grad_base.copy()
    spread = info_base.copy()  # A^T C A of the pairs' estimate
    for rows in tracks.values():
        H = np.vstack([r[0] for r in rows])
        e = np.concatenate([r[1] for r in rows])
        noise = sorted({key for r in rows for key in r[2]}, key=str)
        column = {key: j for j, key in enumerate(noise)}
        L = np.zeros((H.shape[0], len(noise)))
        for p, (_, _, loads) in enumerate(rows):
            for key, v in loads.items():
                L[2 * p:2 * p + 2, column[key]] += v
        C = L @ L.T  # the track's rows' first-order covariance (whitened by the model)
        info_pairs += H.T @ H
        grad_pairs -= H.T @ e
        C_inv = np.linalg.inv(C)
        info_joint += H.T @ C_inv @ H
        grad_joint -= H.T @ C_inv @ e
        stated = L.copy()
        stated[:, column[("h",)]] /= height_scale
        spread += H.T @ stated @ stated.T @ H
    R, idx = _position_blocks(values, cols, K)

    def figures(P: np.ndarray, dx: np.ndarray) -> tuple[float, float, float]:
        d = np.einsum("kij,kj->ki", R, dx[idx])
        C = R @ P[idx[:, :, None], idx[:, None, :]] @ np.swapaxes(R, 1, 2)
        nees = np.einsum("ki,kij,kj->k", d, np.linalg.inv(C), d)
        return (float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
                float(np.sqrt(np.mean(np.trace(C, axis1=1, axis2=2)))), float(nees.mean()))

    P_pairs, P_joint = np.linalg.inv(info_pairs), np.linalg.inv(info_joint)
    dx_pairs = P_pairs @ grad_pairs
    out = {}
    for name, P, dx in (("pairs", P_pairs, dx_pairs),
                        ("sandwich", P_pairs @ spread @ P_pairs, dx_pairs),
                        ("joint", P_joint, P_joint @ grad_joint)):
        out[f"{name}_rmse"], out[f"{name}_sigma"], out[f"{name}_anees"] = figures(P, dx)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--seeds", type=int, nargs=2, default=(1, 16), metavar=("FIRST", "LAST"))
    parser.add_argument("--robust", action="store_true",
                        help="the default Cauchy kernel's weights at the truth (default: none)")
    parser.add_argument("--scenario", choices=[n for n in SCENARIOS if n.startswith("detail_")],
                        help="the robustness study's map-detail scenario, not the clean flight")
    parser.add_argument("--exact-dtm", action="store_true",
                        help="the simulator's exact DTM (no map error, sigma_h 0.1 m)")
    parser.add_argument("--no-shared", action="store_true",
                        help="shared_dtm_error=False: every pair's DTM variance as stated")
    parser.add_argument("--track-whitening", action="store_true",
                        help="the pairs against each track's rows whitened jointly instead")
    parser.add_argument("--height-scale", type=float, default=1.0,
                        help="with --track-whitening: the joint rows' track height noise "
                             "at this many times sigma_h")
    args = parser.parse_args(argv)
    if not args.height_scale > 0:
        parser.error(f"--height-scale {args.height_scale:g}: expected a positive factor")
    if args.track_whitening and (args.robust or args.no_shared):
        parser.error("--track-whitening solves without a kernel and with each track's "
                     "height shared: expected neither --robust nor --no-shared")
    robust = SmootherSettings().graph.robust if args.robust else RobustKernel.NONE
    changes = dict(SCENARIOS[args.scenario].simulation) if args.scenario else {}
    if args.exact_dtm:
        changes["exact_dtm"] = True
    if args.track_whitening:
        runs = []
        for seed in range(args.seeds[0], args.seeds[1] + 1):
            sim = simulate(dataclasses.replace(BASE, frames=args.frames, seed=seed, **changes))
            runs.append(track_whitening(sim, args.height_scale))
            print(f"seed {seed}: " + " ".join(f"{k} {v:.3f}" for k, v in runs[-1].items()),
                  flush=True)
        print(f"\nmean over seeds {args.seeds[0]}-{args.seeds[1]}, {args.frames} frames "
              "(RMSE 3-D m, rms 3-D sigma m, ANEES):")
        for name in ("pairs", "sandwich", "joint"):
            print(f"  {name:9s} " + " ".join(
                f"{np.mean([r[f'{name}_{c}'] for r in runs]):.3f}"
                for c in ("rmse", "sigma", "anees")))
        return
    rows = []
    for seed in range(args.seeds[0], args.seeds[1] + 1):
        sim = simulate(dataclasses.replace(BASE, frames=args.frames, seed=seed, **changes))
        rows.append(split_one(sim, robust, not args.no_shared))
        r = rows[-1]
        print(f"seed {seed}: linearized ANEES {r['realized']['total'].mean():.2f}; "
              f"dh rms {r['dh_rms']:.2f} m (tracks {r['dh_track_rms']:.2f}, stated "
              f"{r['sigma_h']:.2f}); DTM residual / dh {r['dh_slope']:.3f}; "
              + " ".join(f"{c} {r['realized'][c].mean():.3f}/{r['model'][c].mean():.3f}"
                         for c in SOURCES), flush=True)
    print(f"\nmean over seeds {args.seeds[0]}-{args.seeds[1]}, {args.frames} frames "
          f"(position NEES per frame: realized / model):")
    for c in (*SOURCES, *GROUPS, "total"):
        re = np.mean([r["realized"][c].mean() for r in rows])
        mo = np.mean([r["model"][c].mean() for r in rows])
        print(f"  {c:10s} realized {re:.3f}  model {mo:.3f}")
    for c in ("dtm_track_shared", "dtm_track_realized"):
        print(f"  {c:20s} model {np.mean([r['model'][c].mean() for r in rows]):.3f}")
    print(f"  dh at the features rms {np.mean([r['dh_rms'] for r in rows]):.2f} m, per track "
          f"{np.mean([r['dh_track_rms'] for r in rows]):.2f} m, stated "
          f"{rows[0]['sigma_h']:.2f} m; mean pair rank "
          f"{np.mean([r['mean_rank'] for r in rows]):.2f}")
    d = {c: np.mean([r["per_dof"][c] for r in rows]) for c in rows[0]["per_dof"]}
    print(f"  C-DTM whitened residual^2 per dof at the truth (no kernel): all {d['all']:.3f}; "
          f"q_b part {d['cdtm_qb']:.3f}, q_a part {d['cdtm_qa']:.3f}, DTM part "
          f"{d['cdtm_dtm']:.4f} (the model's DTM part {d['model_dtm']:.4f}, its q_b part "
          f"{1 - d['model_dtm']:.3f}, q_a none)")
    imu = np.mean([r["imu_chi2_per_row"] for r in rows], axis=0)
    print("  IMU whitened residual^2 per row at the truth: " + " ".join(f"{x:.2f}" for x in imu))


if __name__ == "__main__":
    main()
