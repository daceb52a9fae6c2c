"""Your own Monte Carlo, judged by kfmc: a pendulum simulated in numpy, FilterPy's
UnscentedKalmanFilter run on it, and truth and estimates handed to `kfmc.score` in memory.

    pip install kfmc filterpy numpy polars
    python3 examples/python/recorded_pendulum.py OUT_DIR                # Q as the truth's
    python3 examples/python/recorded_pendulum.py OUT_DIR --q-scale 0.1  # an over-confident UKF

kfmc never sees the pendulum: a spec of `model.kind = "recorded"` declares the states, the
measured component and the runs, and the truth table (`truth_theta`, `truth_omega`) stands in
for kfmc's simulator. The estimates carry no error transition A_k, so the NEES verdict is
the model-free run-average test (docs: "Real logs and your own runs").
"""

import argparse
import math
from pathlib import Path

import numpy as np
import polars as pl
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

import kfmc

RUNS, K, DT, G_OVER_L = 30, 200, 0.05, 9.81
Q = np.diag([1e-6, 4e-4])  # process noise on (θ, ω)
R = np.array([[0.01]])  # the angle sensor's variance (rad²)
P0 = np.diag([0.04, 0.04])

SPEC = f"""
name = "pendulum"
runs = {RUNS}
[model]
kind = "recorded"
states = ["theta", "omega"]
state_units = ["rad", "rad/s"]
angles = ["theta"]
measurements = ["theta"]
dt_s = {DT}
steps = {K}
[[filters]]
label = "ukf"
kind = "external"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.01
"""


def f(x, dt=DT):
    theta, omega = x
    return np.array([theta + omega * dt, omega - G_OVER_L * math.sin(theta) * dt])


def h(x):
    return x[:1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--q-scale", type=float, default=1.0)
    args = ap.parse_args()
    rng = np.random.default_rng(48)
    keys = {k: [] for k in ("scenario", "noise_scale", "run", "step")}
    truth_rows, est_rows = [], []
    for run in range(RUNS):
        x = np.array([0.6, 0.0]) + rng.multivariate_normal(np.zeros(2), P0)
        points = MerweScaledSigmaPoints(2, alpha=0.5, beta=2.0, kappa=1.0)
        ukf = UnscentedKalmanFilter(2, 1, DT, hx=h, fx=f, points=points)
        ukf.x, ukf.P = np.array([0.6, 0.0]), P0.copy()
        ukf.Q, ukf.R = Q * args.q_scale, R
        for k in range(K + 1):
            nu = s = None
            if k > 0:
                x = f(x) + rng.multivariate_normal(np.zeros(2), Q)
                z = h(x) + rng.normal(0.0, math.sqrt(R[0, 0]), 1)
                ukf.predict()
                ukf.update(z)
                nu, s = float(ukf.y[0]), float(ukf.S[0, 0])
            for key, v in zip(keys, ("recorded", 1.0, run, k)):
                keys[key].append(v)
            truth_rows.append((k * DT, x[0], x[1]))
            p = ukf.P
            est_rows.append((ukf.x[0], ukf.x[1], p[0, 0], p[1, 0], p[1, 1], nu, s))
    t = np.array(truth_rows)
    truth = pl.DataFrame(
        {**keys, "t": t[:, 0], "truth_theta": t[:, 1], "truth_omega": t[:, 2]}
    )
    e = list(zip(*est_rows))
    estimates = pl.DataFrame(
        {
            **keys,
            "filter": ["ukf"] * len(e[0]),
            "est_theta": e[0],
            "est_omega": e[1],
            "P_theta_theta": e[2],
            "P_omega_theta": e[3],
            "P_omega_omega": e[4],
            "nu_theta": pl.Series(e[5], dtype=pl.Float64),
            "S_theta_theta": pl.Series(e[6], dtype=pl.Float64),
        }
    )
    args.out.mkdir(parents=True, exist_ok=True)
    spec = args.out / "pendulum.toml"
    spec.write_text(SPEC)
    study = kfmc.score(spec, estimates, truth=truth, out=args.out / "score", quiet=True, force=True)
    v = study.table("consistency").filter(pl.col("test") == "verdict").row(0, named=True)
    print(f"UKF Q × {args.q_scale}: verdict {'pass' if v['pass'] else 'FAIL'}, p = {v['p_value']:.3g}")
    print(f"tables in {study.folder}; figures: kfmc plot {study.folder}")


if __name__ == "__main__":
    main()
