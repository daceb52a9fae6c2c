"""Judge FilterPy filters with kfmc in one Python process: no subprocess, no estimates file.

    pip install kfmc filterpy numpy
    python3 examples/python/filterpy_in_process.py            # L1: FilterPy's KalmanFilter
    python3 examples/python/filterpy_in_process.py --model p1 # P1: FilterPy's EKF

`kfmc.simulate` writes the runs' world (the same runs `kfmc run` gives kfmc's own filters);
`Simulation.runs()` hands them over one run at a time; the filter loop is the one of
examples/python/filterpy_estimates.py (the files route), reused from it; the estimates
(est_*, the lower triangle P_*, the innovation nu_* with S_*, the error transition A_*) go
to `kfmc.score` as a polars DataFrame, through the Arrow C stream interface; the verdict is
printed, and written with the other tables under --out.
"""

import argparse
import os
import sys

import numpy as np
import polars as pl

import kfmc

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import filterpy_estimates as files_route  # noqa: E402  (the files route's filter loop)

SPECS = {
    "l1": os.path.join(HERE, "..", "..", "experiments", "external_filterpy_l1.toml"),
    "p1": os.path.join(HERE, "..", "..", "experiments", "external_filterpy_p1.toml"),
}
LABELS = {"l1": "filterpy_kf", "p1": "filterpy_ekf"}


def estimates_of(sim, model, label, q_scale, l1_model):
    """One row per (run, step) of the FilterPy filter on every run of `sim`."""
    manifest = sim.manifest
    q_names = [q["name"] for q in manifest["quantities"]]
    z_names = manifest["measurements"]
    nq, nz = len(q_names), len(z_names)
    tri = [(i, j) for i in range(nq) for j in range(i + 1)]
    ztri = [(i, j) for i in range(nz) for j in range(i + 1)]
    args = argparse.Namespace(l1_model=l1_model, q_scale=q_scale)
    frames = []
    for (scenario, noise_scale, run), _truth, meas, init in sim.runs():
        row = init.row(0, named=True)
        x0 = np.array([row[f"est_{n}"] for n in q_names])
        p0 = np.zeros((nq, nq))
        for i, j in tri:
            p0[i, j] = p0[j, i] = row[f"P_{q_names[i]}_{q_names[j]}"]
        filt = files_route.Runner(model, args, x0, p0, nq, nz)
        z = meas.select([f"z_{n}" for n in z_names]).to_numpy().astype(float)
        u_cols = [c for c in meas.columns if c.startswith("u_")]
        u = meas.select(u_cols).to_numpy().astype(float) if u_cols else np.zeros((meas.height, 0))
        values = []
        for k in range(meas.height):
            nu, s, a = np.full(nz, np.nan), np.full((nz, nz), np.nan), np.full((nq, nq), np.nan)
            if k > 0:
                nu, s, a = filt.step(z[k], u[k])
            values.append(
                list(filt.kf.x.ravel())
                + [filt.kf.P[i, j] for i, j in tri]
                + list(nu)
                + [s[i, j] for i, j in ztri]
                + list(a.ravel())
            )
        names = (
            [f"est_{n}" for n in q_names]
            + [f"P_{q_names[i]}_{q_names[j]}" for i, j in tri]
            + [f"nu_{n}" for n in z_names]
            + [f"S_{z_names[i]}_{z_names[j]}" for i, j in ztri]
            + [f"A_{qi}_{qj}" for qi in q_names for qj in q_names]
        )
        v = np.array(values)
        frame = pl.DataFrame(
            {
                "scenario": [scenario] * meas.height,
                "noise_scale": [noise_scale] * meas.height,
                "run": [run] * meas.height,
                "step": list(range(meas.height)),
                "filter": [label] * meas.height,
                # NaN (no innovation at step 0, a sensor that did not report) is "not given".
                **{n: pl.Series(n, v[:, c]).fill_nan(None) for c, n in enumerate(names)},
            }
        )
        frames.append(frame)
    return pl.concat(frames)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", choices=["l1", "p1"], default="l1")
    ap.add_argument("--runs", type=int, default=None, help="runs per cell (default: the spec's)")
    ap.add_argument("--out", default="results/filterpy_in_process")
    ap.add_argument("--l1-model", default=files_route.DEFAULT_MODEL)
    args = ap.parse_args()

    spec = SPECS[args.model]
    sim = kfmc.simulate(spec, out=os.path.join(args.out, "sim"), runs=args.runs, force=True)
    label = LABELS[args.model]
    est = [estimates_of(sim, args.model, label, 1.0, args.l1_model)]
    if args.model == "l1":
        # The spec's negative control: the same filter assuming 4 Q.
        est.append(estimates_of(sim, "l1", "filterpy_kf_q4", 4.0, args.l1_model))
    study = kfmc.score(sim, est, out=os.path.join(args.out, "score"), force=True)
    verdict = study.verdict().select("scenario", "filter", "statistic", "p_value", "pass")
    with pl.Config(tbl_rows=-1, tbl_cols=-1):
        print(verdict)
    print(f"tables in {study.folder}: {', '.join(study.tables())}")


if __name__ == "__main__":
    main()
