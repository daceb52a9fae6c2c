"""Judge a FilterPy Kalman filter with kfmc: the worked example of the estimates exchange.

    kfmc simulate experiments/external_filterpy_l1.toml --out SIM
    python3 examples/python/filterpy_l1.py SIM filterpy_kf.parquet --label filterpy_kf
    python3 examples/python/filterpy_l1.py SIM filterpy_q4.parquet --label filterpy_kf_q4 --q-scale 4
    kfmc score SIM --estimates filterpy_kf.parquet filterpy_q4.parquet
    kfmc check experiments/external_filterpy_l1.toml --estimates filterpy_kf.parquet filterpy_q4.parquet

It reads `kfmc simulate`'s measurements.parquet (z, null where a sensor did not report) and
initial.parquet (each run's prior x̂_0, P_0) with pyarrow, runs FilterPy's KalmanFilter on the
linear quadrotor L1 (position sensor, Δt = 0.1 s) and writes one row per (scenario,
noise_scale, run, step): est_*, the lower triangle P_*, the innovation nu_* with S_*, and the
error transition A = (I − K H) F, which gives kfmc's calibrated NEES verdict. The file's
metadata carries the simulation's spec hash and master seed, so `kfmc score` refuses estimates
of another study.

L1's F, H, Q and R are read from tests/golden/filterpy_l1_input.csv, where kfmc wrote them at
full precision (`--model`); a real user has them from their own model. The example's scenario
hovers (u = 0), so the input term is absent; the script refuses inputs it does not model.

    pip install filterpy numpy pyarrow
"""

import argparse
import os
import tomllib

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from filterpy.kalman import KalmanFilter

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_MODEL = os.path.join(HERE, "..", "..", "tests", "golden", "filterpy_l1_input.csv")


def read_model(path):
    mats = {}
    with open(path) as f:
        for line in f:
            c = line.strip().split(",")
            if c[0] in ("F", "H", "Q", "R"):
                r, k = int(c[1]), int(c[2])
                mats[c[0]] = np.array([float(v) for v in c[3:]]).reshape(r, k)
    return mats


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sim", help="a folder written by kfmc simulate")
    ap.add_argument("out", help="the estimates file to write (Parquet)")
    ap.add_argument("--label", default="filterpy_kf", help="the external filter's label")
    ap.add_argument("--q-scale", type=float, default=1.0, help="multiply the assumed Q (a mistuning)")
    ap.add_argument("--model", default=DEFAULT_MODEL, help="CSV with F, H, Q, R")
    args = ap.parse_args()

    with open(os.path.join(args.sim, "manifest.toml"), "rb") as f:
        manifest = tomllib.load(f)
    q_names = [q["name"] for q in manifest["quantities"]]
    z_names = manifest["measurements"]
    nq, nz = len(q_names), len(z_names)
    m = read_model(args.model)
    if m["F"].shape != (nq, nq) or m["H"].shape != (nz, nq):
        raise SystemExit(f"{args.model}: the model is not {nq} states and {nz} measurements")

    meas = pq.read_table(os.path.join(args.sim, "measurements.parquet"))
    init = pq.read_table(os.path.join(args.sim, "initial.parquet"))
    for u in [c for c in meas.column_names if c.startswith("u_")]:
        if pc.max(pc.abs(meas[u])).as_py() not in (0.0, None):
            raise SystemExit(f"column {u}: this example models no input, but u is not zero")

    cols = {n: [] for n in ["scenario", "noise_scale", "run", "step", "filter"]}
    values = []
    tri = [(i, j) for i in range(nq) for j in range(i + 1)]
    ztri = [(i, j) for i in range(nz) for j in range(i + 1)]
    keys = ["scenario", "noise_scale", "run"]
    init_rows = init.to_pylist()
    z_all = np.column_stack([meas[f"z_{n}"].to_numpy(zero_copy_only=False) for n in z_names])
    meas_keys = [meas[k].to_pylist() for k in keys]
    steps = meas["step"].to_numpy()
    # Rows of one run are contiguous and ordered by step in kfmc's tables.
    starts = {}
    for i in range(meas.num_rows):
        key = (meas_keys[0][i], meas_keys[1][i], meas_keys[2][i])
        starts.setdefault(key, i)

    for row in init_rows:
        key = tuple(row[k] for k in keys)
        first = starts[key]
        kf = KalmanFilter(dim_x=nq, dim_z=nz)
        kf.F, kf.H, kf.R = m["F"], m["H"], m["R"]
        kf.Q = m["Q"] * args.q_scale
        kf.x = np.array([row[f"est_{n}"] for n in q_names]).reshape(nq, 1)
        p0 = np.zeros((nq, nq))
        for i, j in tri:
            p0[i, j] = p0[j, i] = row[f"P_{q_names[i]}_{q_names[j]}"]
        kf.P = p0
        k = 0
        while first + k < meas.num_rows and (
            meas_keys[0][first + k],
            meas_keys[1][first + k],
            meas_keys[2][first + k],
        ) == key:
            assert steps[first + k] == k
            nu = np.full(nz, np.nan)
            s = np.full((nz, nz), np.nan)
            a = np.full((nq, nq), np.nan)
            if k > 0:
                kf.predict()
                z = z_all[first + k]
                if np.all(np.isfinite(z)):
                    kf.update(z.reshape(nz, 1))
                    nu, s = kf.y.ravel(), kf.S
                    a = (np.eye(nq) - kf.K @ kf.H) @ kf.F
                else:
                    a = kf.F.copy()
            cols["scenario"].append(key[0])
            cols["noise_scale"].append(key[1])
            cols["run"].append(key[2])
            cols["step"].append(k)
            cols["filter"].append(args.label)
            values.append(
                list(kf.x.ravel())
                + [kf.P[i, j] for i, j in tri]
                + list(nu)
                + [s[i, j] for i, j in ztri]
                + list(a.ravel())
            )
            k += 1

    names = (
        [f"est_{n}" for n in q_names]
        + [f"P_{q_names[i]}_{q_names[j]}" for i, j in tri]
        + [f"nu_{n}" for n in z_names]
        + [f"S_{z_names[i]}_{z_names[j]}" for i, j in ztri]
        + [f"A_{qi}_{qj}" for qi in q_names for qj in q_names]
    )
    v = np.array(values)
    arrays = [
        pa.array(cols["scenario"], pa.string()),
        pa.array(cols["noise_scale"], pa.float64()),
        pa.array(cols["run"], pa.int64()),
        pa.array(cols["step"], pa.int64()),
        pa.array(cols["filter"], pa.string()),
    ] + [pa.array(v[:, c], pa.float64(), mask=~np.isfinite(v[:, c])) for c in range(len(names))]
    table = pa.table(arrays, names=list(cols) + names)
    table = table.replace_schema_metadata(
        {
            "kfmc.spec_hash": manifest["spec_hash"],
            "kfmc.master_seed": str(manifest["master_seed"]),
        }
    )
    pq.write_table(table, args.out)


if __name__ == "__main__":
    main()
