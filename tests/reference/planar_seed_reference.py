#!/usr/bin/env python3
"""Independent reference implementation of the planar-quadrotor seed (golden data).

This is a Python 3 + numpy reference implementation of the MATLAB code from the
planar-quadrotor EKF report (seed 000: ``Planar_Quadrotor.m`` and
``simulation_quadrotor.m``), together with the IMU measurement variant of seed 003
(measurement y = [y, thetadot, body x-accel, body y-accel]). Its CSV output is golden
data for the Rust test suite.

What it reproduces:

* Parameters m=0.5, r=0.15, I=0.005, g=9.81, dt=0.01, time = 0:dt:10 (1001 samples,
  k = 0..1000, t_k = k*0.01).
* The four control profiles (basic CU1/CU2, horizontal CU3/CU4, roll CU5/CU6, fall
  CU7/CU8) and initial states of ``Planar_Quadrotor.m``.
* The Euler truth simulation with additive process noise, the noisy measurement
  (z_0 is the noise-free output), the EKF (P0 = I, Q = q^2 I, R = diag(r^2), residual
  theta wrapped for the P1 sensor) and the running-mean filter (window 10, P1 only) of
  ``simulation_quadrotor.m``, plus the per-state RMSE over all 1001 samples.
* MATLAB ``randn`` is replaced by ``numpy.random.default_rng(seed).standard_normal``:
  for each k = 1..1000, w_k = 6 draws then v_k = p draws. Every standard normal is
  written to the CSV (w_0 = v_0 = 0) so another implementation can replay them.

Files written to ``tests/golden/``: ``planar_p1_{basic,horizontal,roll,fall}.csv``,
``planar_p1_roll_x20.csv``, ``planar_p2_{basic,roll}.csv`` and
``planar_golden_rmse.csv``.

Floating-point notes: the scalar formulas (controls, dynamics, h(x,u)) are evaluated
with Python floats and the C library ``math.sin``/``math.cos`` in the same operation
order as the MATLAB lines; running-mean window sums and RMSE sums are plain sequential
sums; 6x6 products use numpy ``@`` and the gain uses ``numpy.linalg.solve``
(K = P_pred H' S^-1 computed as solve(S', (P_pred H')')'), so consumers should compare
filter outputs with a small tolerance rather than bit-for-bit.

Regenerate (deterministic; from the repository root):

    python3 tests/reference/planar_seed_reference.py
"""

import math
import os

import numpy as np

# --------------------------------------------------------------------------- constants
M = 0.5
R_ARM = 0.15
INERTIA = 0.005
G = 9.81
DT = 0.01
N = 1001  # time = 0:0.01:10
U1_BASE = 5.0
U2_BASE = 5.0

SCENARIOS = ["basic", "horizontal", "roll", "fall"]
STATE_NAMES = ["x", "xdot", "y", "ydot", "theta", "thetadot"]

HERE = os.path.dirname(os.path.abspath(__file__))
GOLDEN_DIR = os.path.normpath(os.path.join(HERE, "..", "golden"))


# --------------------------------------------------------------------------- controls
def control_profile(name):
    """Return (u1, u2) lists of length N, Planar_Quadrotor.m lines 52-102."""
    u1, u2 = U1_BASE, U2_BASE
    cu1 = [0.0] * N
    cu2 = [0.0] * N
    if name in ("basic", "fall"):
        # CU1 = u1 * 0.6 * (1 + 0.001*cos(2*time)); time(k) taken as k*0.01
        fac = 0.6 if name == "basic" else 0.54
        for k in range(N):
            t = k * DT
            cu1[k] = u1 * fac * (1 + 0.001 * math.cos(2 * t))
            cu2[k] = u2 * fac * (1 + 0.001 * math.sin(2 * t))
    elif name == "horizontal":
        # MATLAB loops use the integer loop variable t (= 0-based index k).
        # The last loop runs to length(time) and writes one extra (unused) element.
        for k in range(N):
            if k <= 109:
                f1, f2 = 0.81, 0.8
            elif k <= 219:
                f1, f2 = 0.8, 0.81
            else:
                f1, f2 = 0.8, 0.8
            cu1[k] = u1 * f1 * (1 + 0.001 * math.cos(2 * 0.01 * k))
            cu2[k] = u2 * f2 * (1 + 0.001 * math.sin(2 * 0.01 * k))
    elif name == "roll":
        for k in range(N):
            c = 1 + 0.001 * math.cos(2 * 0.01 * k)
            s = 1 + 0.001 * math.sin(2 * 0.01 * k)
            if k <= 199:
                cu1[k] = u1 * 0.808 * c
                cu2[k] = u2 * 0.8 * s
            elif k <= 299:
                cu1[k] = u1 * 0 * c
                cu2[k] = u2 * 0 * s
            elif k <= 500:
                cu1[k] = u1 * 0 * c
                cu2[k] = u2 * 0.008 * s
            else:
                cu1[k] = u1 * c
                cu2[k] = u2 * s
    else:
        raise ValueError(name)
    return cu1, cu2


def initial_state(name):
    """Planar_Quadrotor.m lines 107-110."""
    return {
        "basic": [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "horizontal": [0.0, 3.0, 10.0, 0.0, -math.pi / 2, 0.0],
        "roll": [0.0, 0.0, 50.0, 5.0, 0.0, 0.0],
        "fall": [0.0, -1.0, 15.0, -3.0, -(math.pi / 2 - math.atan(3 / 1)), 0.0],
    }[name]


# --------------------------------------------------------------------------- model
def delta(prev, c1, c2):
    """State increment, simulation_quadrotor.m lines 81-92 (theta of prev, u of new k)."""
    th = prev[4]
    d = [0.0] * 6
    d[0] = prev[1] * DT
    d[2] = prev[3] * DT
    d[4] = prev[5] * DT
    d[5] = (R_ARM / INERTIA * c1 - R_ARM / INERTIA * c2) * DT
    d[1] = (-math.sin(th) * (c1 + c2) / M) * DT
    d[3] = (math.cos(th) * (c1 + c2) / M - G) * DT
    return d


def jacobian_f(th, c1, c2):
    """F = eye(6) + dt*A(theta, u), lines 125-130."""
    a = np.zeros((6, 6))
    a[0, 1] = 1.0
    a[1, 4] = -math.cos(th) * (c1 + c2) / M
    a[2, 3] = 1.0
    a[3, 4] = -math.sin(th) * (c1 + c2) / M
    a[4, 5] = 1.0
    return np.eye(6) + DT * a


# P1: z = C x with C selecting [y, theta, thetadot]
P1_IDX = [2, 4, 5]


def h_p1(x, c1, c2):
    return [x[2], x[4], x[5]]


def jac_h_p1(x, c1, c2):
    h = np.zeros((3, 6))
    h[0, 2] = 1.0
    h[1, 4] = 1.0
    h[2, 5] = 1.0
    return h


# P2 (seed 003, IMU): z = [y, thetadot, -(u1+u2) sin(th)/m, (u1+u2) cos(th)/m - g]
def h_p2(x, c1, c2):
    th = x[4]
    return [
        x[2],
        x[5],
        -(c1 + c2) * math.sin(th) / M,
        (c1 + c2) * math.cos(th) / M - G,
    ]


def jac_h_p2(x, c1, c2):
    th = x[4]
    h = np.zeros((4, 6))
    h[0, 2] = 1.0
    h[1, 5] = 1.0
    h[2, 4] = -math.cos(th) * (c1 + c2) / M
    h[3, 4] = -math.sin(th) * (c1 + c2) / M
    return h


def wrap_pi(a):
    """MATLAB mod(a + pi, 2*pi) - pi (floor-mod; numpy's mod has the same sign rule)."""
    return float(np.mod(a + np.pi, 2 * np.pi)) - np.pi


# --------------------------------------------------------------------------- run
def run_case(scenario, sensor, seed, proc_std, meas_std, q_std, r_std):
    """Simulate truth + EKF (+ running mean for P1). meas_std / r_std are per-channel lists."""
    u1, u2 = control_profile(scenario)
    x0 = initial_state(scenario)
    if sensor == "p1":
        h_fun, jac_h, p, wrap_idx = h_p1, jac_h_p1, 3, 1
    else:
        h_fun, jac_h, p, wrap_idx = h_p2, jac_h_p2, 4, None
    assert len(meas_std) == p and len(r_std) == p

    rng = np.random.default_rng(seed)

    w = [[0.0] * 6 for _ in range(N)]
    v = [[0.0] * p for _ in range(N)]
    truth = [None] * N
    z = [None] * N
    ekf = [None] * N
    ekf_var = [None] * N
    rm = [None] * N

    truth[0] = list(x0)
    z[0] = h_fun(x0, u1[0], u2[0])  # clean output, no noise (line 38)
    ekf[0] = list(x0)
    P = np.eye(6)
    ekf_var[0] = [float(P[i, i]) for i in range(6)]
    rm[0] = list(x0)

    Q = np.eye(6) * (q_std * q_std)
    R = np.diag([s * s for s in r_std])
    window_size = 10

    for k in range(1, N):
        c1, c2 = u1[k], u2[k]
        wk = [float(a) for a in rng.standard_normal(6)]
        vk = [float(a) for a in rng.standard_normal(p)]
        w[k], v[k] = wk, vk

        # ---- truth (lines 81-99)
        prev = truth[k - 1]
        d = delta(prev, c1, c2)
        xk = [(prev[i] + d[i]) + proc_std * wk[i] for i in range(6)]
        truth[k] = xk
        hk = h_fun(xk, c1, c2)
        z[k] = [hk[j] + meas_std[j] * vk[j] for j in range(p)]

        # ---- EKF prediction (lines 108-132)
        xe = ekf[k - 1]
        de = delta(xe, c1, c2)
        x_pred = np.array([xe[i] + de[i] for i in range(6)])
        F = jacobian_f(xe[4], c1, c2)
        P_pred = F @ P @ F.T + Q

        # ---- EKF correction (lines 137-149)
        res = np.array(z[k]) - np.array(h_fun(x_pred, c1, c2))
        if wrap_idx is not None:
            res[wrap_idx] = wrap_pi(res[wrap_idx])
        H = jac_h(x_pred, c1, c2)
        S = H @ P_pred @ H.T + R
        PHt = P_pred @ H.T
        K = np.linalg.solve(S.T, PHt.T).T  # MATLAB: P_pred*H' / S
        x_upd = x_pred + K @ res
        P = (np.eye(6) - K @ H) @ P_pred
        ekf[k] = [float(a) for a in x_upd]
        ekf_var[k] = [float(P[i, i]) for i in range(6)]

        # ---- running mean (lines 152-175), P1 only
        if sensor == "p1":
            lo = max(0, k - window_size)
            n = k - lo + 1
            sm = []
            for j in range(p):
                acc = z[lo][j]
                for i in range(lo + 1, k + 1):
                    acc = acc + z[i][j]
                sm.append(acc / n)
            pr = rm[k - 1]
            th_rm = sm[1]
            est = [0.0] * 6
            est[2] = sm[0]
            est[4] = sm[1]
            est[5] = sm[2]
            est[0] = pr[0] + pr[1] * DT
            est[1] = pr[1] + (-math.sin(th_rm) * (c1 + c2) / M) * DT
            est[3] = pr[3] + (math.cos(th_rm) * (c1 + c2) / M - G) * DT
            rm[k] = est

    return {
        "u1": u1, "u2": u2, "w": w, "v": v, "truth": truth, "z": z,
        "ekf": ekf, "ekf_var": ekf_var, "rm": rm if sensor == "p1" else None, "p": p,
    }


def rmse(truth, est):
    out = []
    for i in range(6):
        acc = 0.0
        for k in range(N):
            e = truth[k][i] - est[k][i]
            acc = acc + e * e
        out.append(math.sqrt(acc / N))
    return out


def fmt(x):
    return repr(float(x))


def write_case(fname, res):
    p = res["p"]
    header = ["step", "t", "u1", "u2"]
    header += [f"w{i}" for i in range(6)]
    header += [f"v{j}" for j in range(p)]
    header += [f"truth_{s}" for s in STATE_NAMES]
    header += [f"z{j}" for j in range(p)]
    header += [f"ekf_{s}" for s in STATE_NAMES]
    header += [f"ekf_var_{s}" for s in STATE_NAMES]
    if res["rm"] is not None:
        header += [f"rm_{s}" for s in STATE_NAMES]
    lines = [",".join(header)]
    for k in range(N):
        row = [str(k), fmt(k * DT), fmt(res["u1"][k]), fmt(res["u2"][k])]
        row += [fmt(a) for a in res["w"][k]]
        row += [fmt(a) for a in res["v"][k]]
        row += [fmt(a) for a in res["truth"][k]]
        row += [fmt(a) for a in res["z"][k]]
        row += [fmt(a) for a in res["ekf"][k]]
        row += [fmt(a) for a in res["ekf_var"][k]]
        if res["rm"] is not None:
            row += [fmt(a) for a in res["rm"][k]]
        lines.append(",".join(row))
    with open(os.path.join(GOLDEN_DIR, fname), "w", newline="\n") as f:
        f.write("\n".join(lines) + "\n")


def main():
    os.makedirs(GOLDEN_DIR, exist_ok=True)
    cases = []
    for idx, sc in enumerate(SCENARIOS):
        cases.append((f"planar_p1_{sc}.csv", sc, "p1", 47 + idx, 0.003, [0.01] * 3, 0.003, [0.01] * 3))
    # robustness "nominal filter" case: truth noise x20, filter keeps nominal Q, R
    cases.append(("planar_p1_roll_x20.csv", "roll", "p1", 147, 0.06, [0.2] * 3, 0.003, [0.01] * 3))
    for sc in ("basic", "roll"):
        idx = SCENARIOS.index(sc)
        ms = [0.01, 0.01, 0.1, 0.1]
        cases.append((f"planar_p2_{sc}.csv", sc, "p2", 247 + idx, 0.003, ms, 0.003, ms))

    rmse_rows = ["file,filter," + ",".join(f"rmse_{s}" for s in STATE_NAMES)]
    for fname, sc, sensor, seed, ps, ms, qs, rs in cases:
        res = run_case(sc, sensor, seed, ps, ms, qs, rs)
        write_case(fname, res)
        e = rmse(res["truth"], res["ekf"])
        rmse_rows.append(f"{fname},ekf," + ",".join(fmt(a) for a in e))
        print(f"{fname:28s} ekf          " + " ".join(f"{a:.4f}" for a in e))
        if res["rm"] is not None:
            e = rmse(res["truth"], res["rm"])
            rmse_rows.append(f"{fname},running_mean," + ",".join(fmt(a) for a in e))
            print(f"{fname:28s} running_mean " + " ".join(f"{a:.4f}" for a in e))
    with open(os.path.join(GOLDEN_DIR, "planar_golden_rmse.csv"), "w", newline="\n") as f:
        f.write("\n".join(rmse_rows) + "\n")


if __name__ == "__main__":
    main()
