"""A Kalman filter with a one-step timing error, written outside kfmc, for the whiteness test.

    kfmc simulate experiments/whiteness_cv.toml --out SIM
    python3 examples/python/timing_error_estimates.py experiments/whiteness_cv.toml SIM on_time.parquet --shift 0
    python3 examples/python/timing_error_estimates.py experiments/whiteness_cv.toml SIM late.parquet --shift 1
    kfmc score SIM --estimates on_time.parquet late.parquet

The filter is the spec's own linear KF (F, G, H, Q, R read from the spec's `[model]`, the
discrete form) started from each run's prior in initial.parquet. With `--shift 0` it is the
correct filter (a control: its tests must keep their false-alarm rate). With `--shift 1` its
clock is one step late against the world's: at step k it predicts with the input u_(k−1)
where the world applied u_k, so after every change of the commanded acceleration its
prediction is off for one step and the innovations carry a deterministic, time-correlated
part. Q and R are right, so nothing but the timing is wrong.

Every run of the spec has the same prior covariance and the same sensor schedule, so the
covariance and gain sequences are the same for all runs and the runs are filtered together
(one matrix per step, the states of all runs as rows). Needs numpy and pyarrow; the file
carries the simulation's stamp (spec hash and master seed from manifest.toml).
"""

import argparse
import os
import re
import tomllib

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("spec", help="the spec (a linear model in the discrete form f, g, h, q, r)")
    ap.add_argument("sim", help="a folder written by kfmc simulate for this spec")
    ap.add_argument("out", help="the estimates file to write (Parquet)")
    ap.add_argument("--shift", type=int, default=1, help="steps the filter's input lags (0: none)")
    ap.add_argument("--label", default=None, help="filter label (default kf_late<shift>)")
    args = ap.parse_args()
    label = args.label or f"kf_late{args.shift}"

    with open(args.spec, "rb") as f:
        model = tomllib.load(f)["model"]
    F, G, H, Q, R = (np.array(model[k], dtype=float) for k in ("f", "g", "h", "q", "r"))
    states, zs = model["states"], model["measurements"]
    us = model.get("inputs", [])
    nq, nz = len(states), len(zs)

    head = open(os.path.join(args.sim, "manifest.toml"), encoding="utf-8").read()
    head = head.split('spec = """', 1)[0]
    stamp = {
        k: re.search(rf"^{k} = (.+)$", head, re.M).group(1).strip().strip('"')
        for k in ("spec_hash", "master_seed")
    }

    meas = pq.read_table(os.path.join(args.sim, "measurements.parquet"))
    init = pq.read_table(os.path.join(args.sim, "initial.parquet"))
    keys = ["scenario", "noise_scale", "run"]
    m = {c: meas[c].to_numpy(zero_copy_only=False) for c in meas.column_names}
    z = np.column_stack([m[f"z_{n}"] for n in zs]).astype(float)
    u = np.column_stack([m[f"u_{n}"] for n in us]).astype(float)
    step = m["step"].astype(int)
    # Rows of one run are contiguous and ordered by step in kfmc's tables; every run has
    # the same number of steps, so the table is a (runs, steps) grid in its row order.
    k_steps = int(step.max()) + 1
    n_runs = meas.num_rows // k_steps
    if n_runs * k_steps != meas.num_rows or np.any(step != np.tile(np.arange(k_steps), n_runs)):
        raise SystemExit("measurements.parquet: runs of unequal length or out of order")
    z = z.reshape(n_runs, k_steps, nz)
    u = u.reshape(n_runs, k_steps, len(us))
    if not np.all(np.isfinite(z[:, 1:])):
        raise SystemExit("this example filters a sensor that reports at every step")

    # Priors in the measurement table's run order.
    irow = {tuple(r[k] for k in keys): r for r in init.to_pylist()}
    run_keys = [tuple(m[k][i * k_steps] for k in keys) for i in range(n_runs)]
    x = np.array([[irow[key][f"est_{s}"] for s in states] for key in run_keys])
    tri = [(i, j) for i in range(nq) for j in range(i + 1)]
    ztri = [(i, j) for i in range(nz) for j in range(i + 1)]
    p0 = np.zeros((nq, nq))
    first = irow[run_keys[0]]
    for i, j in tri:
        p0[i, j] = p0[j, i] = first[f"P_{states[i]}_{states[j]}"]
    for key in run_keys:
        if any(irow[key][f"P_{states[i]}_{states[j]}"] != p0[i, j] for i, j in tri):
            raise SystemExit("this example needs the same P0 in every run")

    est = np.empty((n_runs, k_steps, nq))
    cov = np.empty((k_steps, nq, nq))
    nu = np.full((n_runs, k_steps, nz), np.nan)
    s_all = np.full((k_steps, nz, nz), np.nan)
    a_all = np.full((k_steps, nq, nq), np.nan)
    p = p0
    est[:, 0], cov[0] = x, p
    for k in range(1, k_steps):
        uk = u[:, max(k - args.shift, 0)]
        x = x @ F.T + uk @ G.T
        p = F @ p @ F.T + Q
        s = H @ p @ H.T + R
        gain = p @ H.T @ np.linalg.inv(s)
        innov = z[:, k] - x @ H.T
        x = x + innov @ gain.T
        i_kh = np.eye(nq) - gain @ H
        p = i_kh @ p @ i_kh.T + gain @ R @ gain.T
        est[:, k], cov[k], nu[:, k], s_all[k], a_all[k] = x, p, innov, s, i_kh @ F

    rows = n_runs * k_steps
    cols = {
        "scenario": pa.array(m["scenario"], pa.string()),
        "noise_scale": pa.array(m["noise_scale"], pa.float64()),
        "run": pa.array(m["run"], pa.int64()),
        "step": pa.array(m["step"], pa.int64()),
        "filter": pa.array([label] * rows, pa.string()),
    }

    def put(name, v):
        v = np.ascontiguousarray(v).reshape(rows)
        cols[name] = pa.array(v, pa.float64(), mask=~np.isfinite(v))

    def per_step(v):
        return np.broadcast_to(v, (n_runs, k_steps))

    for i, s in enumerate(states):
        put(f"est_{s}", est[:, :, i])
    for i, j in tri:
        put(f"P_{states[i]}_{states[j]}", per_step(cov[:, i, j]))
    for i, n in enumerate(zs):
        put(f"nu_{n}", nu[:, :, i])
    for i, j in ztri:
        put(f"S_{zs[i]}_{zs[j]}", per_step(s_all[:, i, j]))
    for i, qi in enumerate(states):
        for j, qj in enumerate(states):
            put(f"A_{qi}_{qj}", per_step(a_all[:, i, j]))
    table = pa.table(cols).replace_schema_metadata(
        {"kfmc.spec_hash": stamp["spec_hash"], "kfmc.master_seed": stamp["master_seed"]}
    )
    pq.write_table(table, args.out)


if __name__ == "__main__":
    main()
