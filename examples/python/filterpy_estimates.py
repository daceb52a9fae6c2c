"""Judge FilterPy filters with kfmc: the worked example of the estimates exchange.

    kfmc simulate experiments/external_filterpy_l1.toml --out SIM
    python3 examples/python/filterpy_estimates.py l1 SIM kf.parquet --label filterpy_kf
    python3 examples/python/filterpy_estimates.py l1 SIM q4.parquet --label filterpy_kf_q4 --q-scale 4
    kfmc score SIM --estimates kf.parquet q4.parquet
    kfmc check experiments/external_filterpy_l1.toml --estimates kf.parquet q4.parquet

    kfmc simulate experiments/external_filterpy_l1_variants.toml --out SIMV
    python3 examples/python/filterpy_estimates.py l1 SIMV tunings.parquet --label filterpy_kf
    kfmc score SIMV --estimates tunings.parquet

    kfmc simulate experiments/external_filterpy_p1.toml --out SIM1
    python3 examples/python/filterpy_estimates.py p1 SIM1 ekf.parquet --label filterpy_ekf
    kfmc score SIM1 --estimates ekf.parquet

It reads `kfmc simulate`'s measurements.parquet (z, null where a sensor did not report; the
inputs u) and initial.parquet (each run's prior x̂_0, P_0) with pyarrow, runs a FilterPy filter
and writes one row per (scenario, noise_scale, run, step): est_*, the lower triangle P_*, the
innovation nu_* with S_*, and the error transition A = (I − K H) F, which gives kfmc's
calibrated NEES verdict. The file's metadata carries the simulation's stamp (its world stamp
and master seed, from manifest.toml), so `kfmc score` and `kfmc check` refuse estimates of
another simulation.

A label whose spec entry declares `q_scale` variants (the manifest's
`[[exchange.external_filters]]`) gets one filter per declared value on every run (or per
`--q-scale` value given), and a `q_scale` column naming each row's variant: kfmc scores
each as its own series, as it does its own filters' variants.

Models:
* `l1` — FilterPy's KalmanFilter on the linear quadrotor L1 (position sensor, Δt = 0.1 s).
  F, H, Q and R are read from tests/golden/filterpy_l1_input.csv, where kfmc wrote them at
  full precision (`--l1-model`); a real user has them from their own model. The scenario
  hovers (u = 0), so the input term is absent; the script refuses inputs it does not model.
* `p1` — FilterPy's ExtendedKalmanFilter on the planar quadrotor with sensor P1 (y, θ, θ̇) of
  seed 000: f, F = I + A Δt and h written here from the seed's equations, Q = 0.003² I,
  R = 0.01² I (the seed study's), the θ residual wrapped as the seed's code wraps it.

    pip install filterpy numpy pyarrow
"""

import argparse
import math
import os
import re

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_MODEL = os.path.join(HERE, "..", "..", "tests", "golden", "filterpy_l1_input.csv")


def read_manifest(path):
    """manifest.toml with tomllib (Python ≥ 3.11); on older Pythons, the few keys used here."""
    try:
        import tomllib

        with open(path, "rb") as f:
            return tomllib.load(f)
    except ImportError:
        pass
    text = open(path, encoding="utf-8").read()
    # The top-level keys precede the spec text (which repeats some of them) in the file.
    head = text.split('spec = """', 1)[0]

    def scalar(key):
        return re.search(rf"^{key} = (.+)$", head, re.M).group(1).strip().strip('"')

    quantities = [{"name": n} for n in re.findall(r'\[\[quantities\]\]\s*name = "([^"]+)"', text)]
    meas = re.search(r'^measurements = \[(.*)\]$', head, re.M).group(1)
    return {
        "world_stamp": scalar("world_stamp"),
        "master_seed": int(scalar("master_seed")),
        "quantities": quantities,
        "measurements": re.findall(r'"([^"]+)"', meas),
    }


def read_model(path):
    mats = {}
    with open(path) as f:
        for line in f:
            c = line.strip().split(",")
            if c[0] in ("F", "H", "Q", "R"):
                r, k = int(c[1]), int(c[2])
                mats[c[0]] = np.array([float(v) for v in c[3:]]).reshape(r, k)
    return mats


# Planar quadrotor (seed 000): mass, arm, inertia, gravity, Δt.
M, R_ARM, INERTIA, G, DT_P1 = 0.5, 0.15, 0.005, 9.81, 0.01


def p1_f(x, u):
    """x_k = x_{k-1} + Δx(x_{k-1}, u_k), simulation_quadrotor.m lines 64-71."""
    th, thrust = x[4], u[0] + u[1]
    return np.array(
        [
            x[0] + x[1] * DT_P1,
            x[1] + (-math.sin(th) * thrust / M) * DT_P1,
            x[2] + x[3] * DT_P1,
            x[3] + (math.cos(th) * thrust / M - G) * DT_P1,
            x[4] + x[5] * DT_P1,
            x[5] + (R_ARM / INERTIA * u[0] - R_ARM / INERTIA * u[1]) * DT_P1,
        ]
    )


def p1_jacobian(x, u):
    """F = I + A Δt, eq. (15) of seed 000."""
    th, thrust = x[4], u[0] + u[1]
    f = np.eye(6)
    f[0, 1] = DT_P1
    f[1, 4] = -math.cos(th) * thrust / M * DT_P1
    f[2, 3] = DT_P1
    f[3, 4] = -math.sin(th) * thrust / M * DT_P1
    f[4, 5] = DT_P1
    return f


P1_H = np.zeros((3, 6))
P1_H[0, 2] = P1_H[1, 4] = P1_H[2, 5] = 1.0


def p1_residual(z, zp):
    """z − h with θ wrapped into [−π, π) as MATLAB's mod(a + pi, 2*pi) − pi."""
    r = z - zp
    r[1] = float(np.mod(r[1] + math.pi, 2 * math.pi)) - math.pi
    return r


class PlanarEkf(ExtendedKalmanFilter):
    """FilterPy's EKF with the nonlinear time update f(x, u) (its own predict_x is linear)."""

    def predict_x(self, u=0):
        self.x = p1_f(self.x.ravel(), u).reshape(-1, 1)


class Runner:
    """One filter per run: step(k, z, u) returns (x, P, nu, S, A) after step k."""

    def __init__(self, model, args, q_scale, x0, p0, nq, nz):
        self.model, self.nq, self.nz = model, nq, nz
        if model == "l1":
            m = read_model(args.l1_model)
            if m["F"].shape != (nq, nq) or m["H"].shape != (nz, nq):
                raise SystemExit(f"{args.l1_model}: the model is not {nq} states and {nz} measurements")
            kf = KalmanFilter(dim_x=nq, dim_z=nz)
            kf.F, kf.H, kf.R = m["F"], m["H"], m["R"]
            kf.Q = m["Q"] * q_scale
        else:
            if (nq, nz) != (6, 3):
                raise SystemExit("model p1 needs the planar quadrotor with sensor p1")
            kf = PlanarEkf(dim_x=6, dim_z=3)
            kf.Q = np.eye(6) * 0.003**2 * q_scale
            kf.R = np.eye(3) * 0.01**2
        kf.x = x0.reshape(nq, 1)
        kf.P = p0
        self.kf = kf

    def step(self, z, u):
        kf, nq, nz = self.kf, self.nq, self.nz
        if self.model == "l1":
            kf.predict()
            f = kf.F
        else:
            f = p1_jacobian(kf.x.ravel(), u)
            kf.F = f
            kf.predict(u=u)
        if not np.all(np.isfinite(z)):
            return np.full(nz, np.nan), np.full((nz, nz), np.nan), f.copy()
        if self.model == "l1":
            kf.update(z.reshape(nz, 1))
        else:
            kf.update(
                z.reshape(nz, 1),
                HJacobian=lambda x: P1_H,
                Hx=lambda x: P1_H @ x,
                residual=lambda a, b: p1_residual(a.ravel(), b.ravel()).reshape(-1, 1),
            )
        h = P1_H if self.model == "p1" else kf.H
        return kf.y.ravel(), kf.S, (np.eye(nq) - kf.K @ h) @ f


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", choices=["l1", "p1"], help="which FilterPy filter and model")
    ap.add_argument("sim", help="a folder written by kfmc simulate")
    ap.add_argument("out", help="the estimates file to write (Parquet)")
    ap.add_argument("--label", default="filterpy_kf", help="the external filter's label")
    ap.add_argument(
        "--q-scale", type=float, nargs="+", default=None,
        help="multiply the assumed Q (a mistuning); several values, or none for a label that "
        "declares q_scale variants (then every declared value), write one variant each",
    )
    ap.add_argument("--l1-model", default=DEFAULT_MODEL, help="CSV with L1's F, H, Q, R")
    args = ap.parse_args()

    manifest = read_manifest(os.path.join(args.sim, "manifest.toml"))
    q_names = [q["name"] for q in manifest["quantities"]]
    z_names = manifest["measurements"]
    nq, nz = len(q_names), len(z_names)
    # The variants the spec declares for this label, if any: each row names its own.
    entry = next(
        (e for e in manifest.get("exchange", {}).get("external_filters", []) if e["label"] == args.label),
        {},
    )
    declared = entry.get("q_scale")
    q_scales = args.q_scale or declared or [1.0]
    if len(q_scales) > 1 and declared is None:
        raise SystemExit(f"several --q-scale values, but `{args.label}` declares no q_scale variants in the spec")

    meas = pq.read_table(os.path.join(args.sim, "measurements.parquet"))
    init = pq.read_table(os.path.join(args.sim, "initial.parquet"))
    u_names = [c for c in meas.column_names if c.startswith("u_")]
    if args.model == "l1":
        for u in u_names:
            if pc.max(pc.abs(meas[u])).as_py() not in (0.0, None):
                raise SystemExit(f"column {u}: this example models no input, but u is not zero")
    u_all = np.column_stack([meas[u].to_numpy(zero_copy_only=False) for u in u_names])

    cols = {n: [] for n in ["scenario", "noise_scale", "run", "step", "filter"]}
    variant = []
    # The `failed` column: true from the step the filter failed at (an exception from its
    # linear algebra), where the row carries no estimate. kfmc counts such a run a
    # numerical failure there; a run left out of the file would be missing instead, which no
    # [check] max_failed_runs tolerates.
    failed = []
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
        x0 = np.array([row[f"est_{n}"] for n in q_names])
        p0 = np.zeros((nq, nq))
        for i, j in tri:
            p0[i, j] = p0[j, i] = row[f"P_{q_names[i]}_{q_names[j]}"]
        for q_scale in q_scales:
            filt = Runner(args.model, args, q_scale, x0, p0, nq, nz)
            k = 0
            failed_at = None
            while first + k < meas.num_rows and (
                meas_keys[0][first + k],
                meas_keys[1][first + k],
                meas_keys[2][first + k],
            ) == key:
                assert steps[first + k] == k
                nu = np.full(nz, np.nan)
                s = np.full((nz, nz), np.nan)
                a = np.full((nq, nq), np.nan)
                if k > 0 and failed_at is None:
                    try:
                        nu, s, a = filt.step(z_all[first + k], u_all[first + k])
                    except (np.linalg.LinAlgError, ValueError):
                        failed_at = k
                cols["scenario"].append(key[0])
                cols["noise_scale"].append(key[1])
                cols["run"].append(key[2])
                cols["step"].append(k)
                cols["filter"].append(args.label)
                variant.append(q_scale)
                failed.append(failed_at is not None)
                width = nq + len(tri) + nz + len(ztri) + nq * nq
                values.append(
                    [np.nan] * width
                    if failed_at is not None
                    else list(filt.kf.x.ravel())
                    + [filt.kf.P[i, j] for i, j in tri]
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
    ]
    keys = list(cols)
    if declared is not None:
        arrays.append(pa.array(variant, pa.float64()))
        keys.append("q_scale")
    arrays.append(pa.array(failed, pa.bool_()))
    keys.append("failed")
    arrays += [pa.array(v[:, c], pa.float64(), mask=~np.isfinite(v[:, c])) for c in range(len(names))]
    table = pa.table(arrays, names=keys + names)
    table = table.replace_schema_metadata(
        {
            "kfmc.world_stamp": manifest["world_stamp"],
            "kfmc.master_seed": str(manifest["master_seed"]),
        }
    )
    pq.write_table(table, args.out)


if __name__ == "__main__":
    main()
