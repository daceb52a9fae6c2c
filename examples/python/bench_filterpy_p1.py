"""Throughput of FilterPy's EKF on kfmc's P1 planar quadrotor, for the comparison on the book's performance page (docs/src/performance.md).

    pip install filterpy numpy
    python3 examples/python/bench_filterpy_p1.py [RUNS]

The same work as one run of kfmc's EKF-only study (`cargo run --release --example
bench_study -- --case p1_ekf`): simulate the truth and the measurements (1,001 samples of the
basic scenario, hover thrust, process noise 0.003 and measurement noise 0.01 on every
component), run FilterPy's ExtendedKalmanFilter with f, F = I + A Δt and h of seed 000 (as in
filterpy_estimates.py), and keep the per-step squared errors, NEES and NIS. Prints the CPU
time per filter step (one thread), to be set against kfmc's CPU time per step in the same
session.
"""

import math
import sys
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

M, R_ARM, INERTIA, G, DT = 0.5, 0.15, 0.005, 9.81, 0.01


def f(x, u):
    th, thrust = x[4], u[0] + u[1]
    return np.array(
        [
            x[0] + x[1] * DT,
            x[1] + (-math.sin(th) * thrust / M) * DT,
            x[2] + x[3] * DT,
            x[3] + (math.cos(th) * thrust / M - G) * DT,
            x[4] + x[5] * DT,
            x[5] + (R_ARM / INERTIA * u[0] - R_ARM / INERTIA * u[1]) * DT,
        ]
    )


def jacobian(x, u):
    th, thrust = x[4], u[0] + u[1]
    F = np.eye(6)
    F[0, 1] = DT
    F[1, 4] = -math.cos(th) * thrust / M * DT
    F[2, 3] = DT
    F[3, 4] = -math.sin(th) * thrust / M * DT
    F[4, 5] = DT
    return F


H = np.zeros((3, 6))
H[0, 2] = H[1, 4] = H[2, 5] = 1.0


def residual(a, b):
    r = (a - b).ravel()
    r[1] = float(np.mod(r[1] + math.pi, 2 * math.pi)) - math.pi
    return r.reshape(-1, 1)


class PlanarEkf(ExtendedKalmanFilter):
    def predict_x(self, u=0):
        self.x = f(self.x.ravel(), u).reshape(-1, 1)


def one_run(rng, steps=1000):
    u = np.array([M * G / 2, M * G / 2])
    x = np.array([0.0, 0.0, 10.0, 0.0, 0.0, 0.0])
    kf = PlanarEkf(dim_x=6, dim_z=3)
    kf.Q = np.eye(6) * 0.003**2
    kf.R = np.eye(3) * 0.01**2
    kf.x = x.reshape(6, 1).copy()
    kf.P = np.eye(6)
    sq = np.zeros((steps + 1, 6))
    nees = np.zeros(steps + 1)
    nis = np.zeros(steps + 1)
    for k in range(1, steps + 1):
        x = f(x, u) + 0.003 * rng.standard_normal(6)
        z = H @ x + 0.01 * rng.standard_normal(3)
        kf.F = jacobian(kf.x.ravel(), u)
        kf.predict(u=u)
        kf.update(z.reshape(3, 1), HJacobian=lambda s: H, Hx=lambda s: H @ s, residual=residual)
        e = x - kf.x.ravel()
        sq[k] = e * e
        nees[k] = e @ np.linalg.solve(kf.P, e)
        nis[k] = (kf.y.T @ kf.SI @ kf.y).item()
    return nees[1:].mean()


def main():
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    rng = np.random.default_rng(47)
    one_run(rng, 50)  # warm-up
    t0 = time.process_time()
    mean_nees = [one_run(rng) for _ in range(runs)]
    cpu = time.process_time() - t0
    print(
        f"filterpy EKF, {runs} runs x 1,000 steps: {cpu / runs:.3f} s CPU per run, "
        f"{cpu / runs / 1000 * 1e9:.0f} ns CPU per step (mean NEES {np.mean(mean_nees):.2f})"
    )


if __name__ == "__main__":
    main()
