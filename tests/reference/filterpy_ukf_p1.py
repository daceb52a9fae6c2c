"""FilterPy reference for tests/it/cross_checks/filterpy_ukf.rs.

Reads tests/golden/filterpy_ukf_p1_input.csv (P1's parameters, Q, R, x0, P0, two sets of
unscented parameters and 1,000 steps of the roll scenario with controls, measurements and
the reporting components, written by the Rust test with KFMC_BLESS=1), runs FilterPy's
UnscentedKalmanFilter with MerweScaledSigmaPoints for each parameter set, and writes
tests/golden/filterpy_ukf_p1.csv with x̂_k, P_k and the NIS after every step (k = 0 is the
prior; the NIS is NaN on predict-only steps).

FilterPy does not wrap angles by default; it is given kfmc's angle handling, written here
from its definition: the state θ (index 4) and the θ measurement are averaged with the
circular mean anchored at the centre sigma point, a + atan2(Σ w sin(y − a), Σ w cos(y − a)),
and their residuals are wrapped to [−π, π) as MATLAB's mod(d + π, 2π) − π. A step on which
only some components report is an update with those rows of h and R.

    pip install filterpy numpy
    python3 tests/reference/filterpy_ukf_p1.py [OUTPUT]

OUTPUT defaults to the golden file; tests/it/cross_checks/filterpy_ukf.rs passes a scratch path to check that
the committed golden is still what FilterPy computes.
"""

import math
import os
import sys

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

HERE = os.path.dirname(os.path.abspath(__file__))
GOLDEN = os.path.join(HERE, "..", "golden")
THETA = 4
# Which positions of the current (reduced) measurement vector are angles.
Z_ANGLES = []


def wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def circular_mean(sigmas, wm, angles):
    m = np.dot(wm, sigmas)
    for i in angles:
        a = sigmas[0, i]
        d = sigmas[:, i] - a
        m[i] = a + math.atan2(np.dot(wm, np.sin(d)), np.dot(wm, np.cos(d)))
    return m


def residual(a, b, angles):
    d = np.subtract(a, b)
    for i in angles:
        d[i] = wrap(d[i])
    return d


def main():
    params, points, mats, steps = None, [], {}, []
    with open(os.path.join(GOLDEN, "filterpy_ukf_p1_input.csv")) as f:
        for line in f:
            c = line.strip().split(",")
            if c[0] == "params":
                params = [float(v) for v in c[1:]]
            elif c[0] == "points":
                points.append(tuple(float(v) for v in c[2:5]))
            elif c[0] == "z":
                v = [float(x) for x in c[3:]]
                steps.append((int(c[1]), int(c[2]), np.array(v[0:2]), np.array(v[2:5])))
            else:
                r, k = int(c[1]), int(c[2])
                mats[c[0]] = np.array([float(v) for v in c[3:]]).reshape(r, k)
    mass, arm, inertia, g, dt = params

    def fx(x, dt, u):
        thrust = u[0] + u[1]
        s, c = math.sin(x[4]), math.cos(x[4])
        xdd = -s * thrust / mass
        ydd = c * thrust / mass - g
        thdd = arm / inertia * u[0] - arm / inertia * u[1]
        return np.array(
            [
                x[0] + x[1] * dt,
                x[1] + xdd * dt,
                x[2] + x[3] * dt,
                x[3] + ydd * dt,
                x[4] + x[5] * dt,
                x[5] + thdd * dt,
            ]
        )

    rows = []
    for ci, (alpha, beta, kappa) in enumerate(points):
        pts = MerweScaledSigmaPoints(6, alpha=alpha, beta=beta, kappa=kappa)
        ukf = UnscentedKalmanFilter(
            dim_x=6,
            dim_z=3,
            dt=dt,
            hx=lambda x: np.array([x[2], x[4], x[5]]),
            fx=fx,
            points=pts,
            x_mean_fn=lambda s, w: circular_mean(s, w, [THETA]),
            z_mean_fn=lambda s, w: circular_mean(s, w, Z_ANGLES),
            residual_x=lambda a, b: residual(a, b, [THETA]),
            residual_z=lambda a, b: residual(a, b, Z_ANGLES),
        )
        ukf.x = mats["x0"].ravel().copy()
        ukf.P = mats["P0"].copy()
        ukf.Q = mats["Q"]
        r_full = mats["R"]

        def record(k, nis):
            rows.append([ci, k] + list(ukf.x.ravel()) + list(ukf.P.ravel()) + [nis])

        record(0, float("nan"))
        for k, mask, u, z in steps:
            ukf.predict(u=u)
            idx = [i for i in range(3) if mask & (1 << i)]
            nis = float("nan")
            if idx:
                Z_ANGLES[:] = [p for p, i in enumerate(idx) if i == 1]
                ukf.update(
                    z[idx],
                    R=r_full[np.ix_(idx, idx)],
                    hx=lambda x, idx=idx: np.array([x[2], x[4], x[5]])[idx],
                )
                y = ukf.y
                nis = float(y @ np.linalg.solve(ukf.S, y))
            record(k, nis)
    header = (
        ["config", "k"]
        + [f"x{i}" for i in range(6)]
        + [f"p{i}{j}" for i in range(6) for j in range(6)]
        + ["nis"]
    )
    out = sys.argv[1] if len(sys.argv) > 1 else os.path.join(GOLDEN, "filterpy_ukf_p1.csv")
    with open(out, "w") as f:
        f.write(",".join(header) + "\n")
        for r in rows:
            f.write(",".join([str(r[0]), str(r[1])] + [repr(float(v)) for v in r[2:]]) + "\n")


if __name__ == "__main__":
    main()
