"""FilterPy's UnscentedKalmanFilter judged with its error transition A_k, and what the wrong
A_k does.

    pip install kfmc filterpy numpy
    python3 examples/python/filterpy_ukf_transition.py                 # Q as the truth's
    python3 examples/python/filterpy_ukf_transition.py --q-scale 0.8   # a mistuned filter

The calibrated NEES test (`nees_time_average`) needs A_k, the error transition of each step,
for its effective degrees of freedom. A sigma-point filter's A_k is its statistical
linearisation, formed by `kfmc.sigma_point_transition` from the points of the predict, their
images f(χ), and the update's points, their images h(χ) and the gain. FilterPy's `predict()`
ends by redrawing `ukf.sigmas_f` from (x̂⁻, P⁻) for the update, so after it the images f(χ)
are gone and the points that made them were never kept: this script keeps them (the points
`predict()` draws are `ukf.points_fn.sigma_points(ukf.x, ukf.P)`), and, to show the mistake,
also forms A_k from the redrawn `ukf.sigmas_f` as if they were f(χ).

Both tables are made with `kfmc.Estimates` on the runs of experiments/external_filterpy_l1.toml
(the linear quadrotor L1, where the UKF equals kfmc's KF), scored with `kfmc.score`, and the
NEES test's effective dof, band and p-value printed for each: with the right A_k they are
kfmc's KF's; with the wrong one the dof drop about seven-fold and the band widens, so a
mistuned filter (--q-scale 0.8 or 1.25) passes. The spec's negative control (Q × 4) is the
same UKF with the right A_k.
"""

import argparse
import os

import numpy as np
import polars as pl
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

import kfmc

HERE = os.path.dirname(os.path.abspath(__file__))
SPEC = os.path.join(HERE, "..", "..", "experiments", "external_filterpy_l1.toml")


def ukf_run(sim, meas, init, q_scale):
    """FilterPy's UKF (α = 1, β = 2, κ = 0) on one run: x, P, ν, S and two A_k per step,
    from the kept predict points and from the redrawn ukf.sigmas_f."""
    m = sim.model
    q, n, nz = m.states, len(m.states), len(m.measurements)
    F, G, H = sim.F, sim.G, sim.H

    def fx(x, dt, u):
        return F @ x + G @ u

    points = MerweScaledSigmaPoints(n, alpha=1.0, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(
        dim_x=n, dim_z=nz, dt=m.dt_s, fx=fx, hx=lambda x: H @ x, points=points
    )
    row = init.row(0, named=True)
    ukf.x = np.array([row[f"est_{a}"] for a in q])
    ukf.P = np.array([[row[f"P_{q[max(i, j)]}_{q[min(i, j)]}"] for j in range(n)] for i in range(n)])
    ukf.Q, ukf.R = sim.Q * q_scale, sim.R
    z = meas.select([f"z_{a}" for a in m.measurements]).to_numpy()
    u = meas.select([f"u_{a}" for a in m.inputs]).to_numpy()
    k1 = meas.height
    x, P = np.zeros((k1, n)), np.zeros((k1, n, n))
    nu, S = np.full((k1, nz), np.nan), np.full((k1, nz, nz), np.nan)
    a_kept, a_redrawn = np.full((k1, n, n), np.nan), np.full((k1, n, n), np.nan)
    x[0], P[0] = ukf.x, ukf.P
    for k in range(1, k1):
        chi = ukf.points_fn.sigma_points(ukf.x, ukf.P)  # the points predict() draws
        chi_f = np.array([fx(s, m.dt_s, u[k]) for s in chi])  # their images f(χ)
        ukf.predict(u=u[k])
        redrawn = ukf.sigmas_f.copy()  # drawn from (x̂⁻, P⁻): not f of anything
        ukf.update(z[k])
        update = dict(K=ukf.K, sigmas_update=ukf.sigmas_f, sigmas_h=ukf.sigmas_h)
        a_kept[k] = kfmc.sigma_point_transition(chi, chi_f, ukf.Wm, ukf.Wc, **update)
        a_redrawn[k] = kfmc.sigma_point_transition(chi, redrawn, ukf.Wm, ukf.Wc, **update)
        x[k], P[k], nu[k], S[k] = ukf.x, ukf.P, ukf.y, ukf.S
    return x, P, nu, S, a_kept, a_redrawn


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=None, help="runs per cell (default: the spec's)")
    ap.add_argument("--q-scale", type=float, default=1.0, help="the UKF's Q as a multiple of the truth's")
    ap.add_argument("--out", default="results/filterpy_ukf_transition")
    args = ap.parse_args()

    sim = kfmc.simulate(SPEC, out=os.path.join(args.out, "sim"), runs=args.runs, force=True, quiet=True)
    kept = kfmc.Estimates(sim, "filterpy_kf")
    redrawn = kfmc.Estimates(sim, "filterpy_kf")
    control = kfmc.Estimates(sim, "filterpy_kf_q4")
    for key, _truth, meas, init in sim.runs():
        x, P, nu, S, a_kept, a_redrawn = ukf_run(sim, meas, init, args.q_scale)
        kept.add_run(*key, x=x, P=P, nu=nu, S=S, A=a_kept)
        redrawn.add_run(*key, x=x, P=P, nu=nu, S=S, A=a_redrawn)
        x, P, nu, S, a_kept, _ = ukf_run(sim, meas, init, 4.0)
        control.add_run(*key, x=x, P=P, nu=nu, S=S, A=a_kept)
    rows = []
    for name, folder, est in (
        ("A_k from the kept points", "kept", kept),
        ("A_k from ukf.sigmas_f", "sigmas_f", redrawn),
    ):
        study = kfmc.score(sim, [est, control], out=os.path.join(args.out, folder), force=True, quiet=True)
        c = study.table("consistency")
        for label in ("kf", "filterpy_kf"):
            nees = c.filter((pl.col("filter") == label) & (pl.col("test") == "nees_time_average")).row(0, named=True)
            verdict = c.filter((pl.col("filter") == label) & (pl.col("test") == "verdict")).row(0, named=True)
            rows.append(
                {
                    "scored": name,
                    "filter": label if label == "kf" else f"filterpy UKF, Q x {args.q_scale:g}",
                    "dof": round(nees["dof"], 1),
                    "band": f"[{nees['lower']:.3f}, {nees['upper']:.3f}]",
                    "ANEES": round(nees["statistic"], 3),
                    "p (NEES)": float(f"{nees['p_value']:.3g}"),
                    "verdict p": float(f"{verdict['p_value']:.3g}"),
                    "pass": verdict["pass"],
                }
            )
    with pl.Config(tbl_rows=-1, tbl_cols=-1, tbl_width_chars=160, fmt_str_lengths=40):
        print(pl.DataFrame(rows))


if __name__ == "__main__":
    main()
