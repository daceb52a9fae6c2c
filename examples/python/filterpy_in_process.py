"""Judge FilterPy filters with kfmc in one Python process: no subprocess, no estimates file,
and no transcription of the model — the filters use the simulated world's own.

    pip install kfmc filterpy numpy            # matplotlib too, for the figure
    python3 examples/python/filterpy_in_process.py            # L1: FilterPy's KalmanFilter
    python3 examples/python/filterpy_in_process.py --model p1 # P1: FilterPy's EKF

`kfmc.simulate` writes the runs' world (the same runs `kfmc run` gives kfmc's own filters)
and carries its model: for the linear quadrotor L1 the matrices `sim.F`, `sim.G`, `sim.H`,
`sim.Q`, `sim.R` at full precision, for the planar quadrotor `sim.f(x, u)`, `sim.h(x)`,
`sim.jacobians(x, u)` and `sim.residual(z, ẑ)` (θ's innovation wrapped), which run kfmc's
Rust model. The step convention (`sim.step_convention`): the input on row k drives the step
from k−1 to k, z_k updates it, and step 0 is the run's prior, with no measurement.
`Simulation.runs()` hands the runs over one at a time; the estimates (est_*, the lower
triangle P_*, the innovation nu_* with S_*, the error transition A_* = (I − K H) F) go to
`kfmc.score` as a polars DataFrame; the verdict is printed, and a figure of the average NEES
per step with its 95 % band is saved beside the tables (when matplotlib is installed).
"""

import argparse
import os

import numpy as np
import polars as pl
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

import kfmc

HERE = os.path.dirname(os.path.abspath(__file__))
SPECS = {
    "l1": os.path.join(HERE, "..", "..", "experiments", "external_filterpy_l1.toml"),
    "p1": os.path.join(HERE, "..", "..", "experiments", "external_filterpy_p1.toml"),
}
LABELS = {"l1": "filterpy_kf", "p1": "filterpy_ekf"}


class WorldEkf(ExtendedKalmanFilter):
    """FilterPy's EKF with the simulation's nonlinear f (FilterPy's own predict_x is F x)."""

    def __init__(self, sim, dim_x, dim_z):
        super().__init__(dim_x=dim_x, dim_z=dim_z)
        self.sim = sim

    def predict_x(self, u=0):
        self.x = self.sim.f(self.x.ravel(), u).reshape(-1, 1)


def make_filter(sim, x0, p0, q_scale):
    """A FilterPy filter on the simulation's own model: a KalmanFilter from F, G, H, Q, R when
    the model is linear, else an EKF calling f, h and the Jacobians."""
    m = sim.model
    nq, nz = len(m.states), len(m.measurements)
    if m.linear:
        kf = KalmanFilter(dim_x=nq, dim_z=nz, dim_u=len(m.inputs))
        kf.F, kf.B, kf.H, kf.R = sim.F, sim.G, sim.H, sim.R
    else:
        kf = WorldEkf(sim, nq, nz)
        kf.R = sim.R
    kf.Q = sim.Q * q_scale
    kf.x = x0.reshape(nq, 1)
    kf.P = p0
    return kf


def step(sim, kf, z, u):
    """Predict step k with u_k (the input on row k), then update with z_k: (ν, S, A)."""
    m = sim.model
    nq, nz = len(m.states), len(m.measurements)
    if m.linear:
        f = kf.F
        kf.predict(u=u.reshape(-1, 1))
    else:
        f, _ = sim.jacobians(kf.x.ravel(), u)
        kf.F = f
        kf.predict(u=u)
    if not np.all(np.isfinite(z)):
        return np.full(nz, np.nan), np.full((nz, nz), np.nan), f.copy()
    if m.linear:
        kf.update(z.reshape(nz, 1))
        h = kf.H
    else:
        _, h = sim.jacobians(kf.x.ravel(), u)
        kf.update(
            z.reshape(nz, 1),
            HJacobian=lambda x: h,
            Hx=lambda x: sim.h(x.ravel()).reshape(-1, 1),
            residual=lambda a, b: sim.residual(a.ravel(), b.ravel()).reshape(-1, 1),
        )
    return kf.y.ravel(), kf.S, (np.eye(nq) - kf.K @ h) @ f


def estimates_of(sim, label, q_scale):
    """One row per (run, step) of the FilterPy filter on every run of `sim`."""
    m = sim.model
    q_names, z_names = m.states, m.measurements
    nq, nz = len(q_names), len(z_names)
    tri = [(i, j) for i in range(nq) for j in range(i + 1)]
    ztri = [(i, j) for i in range(nz) for j in range(i + 1)]
    names = (
        [f"est_{n}" for n in q_names]
        + [f"P_{q_names[i]}_{q_names[j]}" for i, j in tri]
        + [f"nu_{n}" for n in z_names]
        + [f"S_{z_names[i]}_{z_names[j]}" for i, j in ztri]
        + [f"A_{qi}_{qj}" for qi in q_names for qj in q_names]
    )
    frames = []
    for (scenario, noise_scale, run), _truth, meas, init in sim.runs():
        row = init.row(0, named=True)
        x0 = np.array([row[f"est_{n}"] for n in q_names])
        p0 = np.zeros((nq, nq))
        for i, j in tri:
            p0[i, j] = p0[j, i] = row[f"P_{q_names[i]}_{q_names[j]}"]
        kf = make_filter(sim, x0, p0, q_scale)
        z = meas.select([f"z_{n}" for n in z_names]).to_numpy().astype(float)
        u = meas.select([f"u_{n}" for n in m.inputs]).to_numpy().astype(float)
        values = []
        for k in range(meas.height):
            nu, s, a = np.full(nz, np.nan), np.full((nz, nz), np.nan), np.full((nq, nq), np.nan)
            if k > 0:
                nu, s, a = step(sim, kf, z[k], u[k])
            values.append(
                list(kf.x.ravel())
                + [kf.P[i, j] for i, j in tri]
                + list(nu)
                + [s[i, j] for i, j in ztri]
                + list(a.ravel())
            )
        v = np.array(values)
        frames.append(
            pl.DataFrame(
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
        )
    return pl.concat(frames)


def save_figure(study, path):
    """The average NEES per step of every filter with its 95 % band (steps.parquet)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no figure (pip install matplotlib)")
        return
    steps = study.table("steps").filter(pl.col("step") > 0)
    scenarios = steps["scenario"].unique(maintain_order=True).to_list()
    fig, axes = plt.subplots(len(scenarios), 1, figsize=(8, 2.6 * len(scenarios)), squeeze=False)
    for ax, scenario in zip(axes[:, 0], scenarios):
        cell = steps.filter(pl.col("scenario") == scenario)
        for label in cell["filter"].unique(maintain_order=True).to_list():
            f = cell.filter(pl.col("filter") == label).sort("step")
            ax.plot(f["t"], f["anees"], lw=0.8, label=label)
        band = cell.filter(pl.col("filter") == cell["filter"][0]).sort("step")
        ax.fill_between(band["t"], band["anees_lo"], band["anees_hi"], color="0.85", label="95 % band")
        ax.set_title(f"{scenario}: average NEES per step")
        ax.set_xlabel("t [s]")
        ax.set_yscale("log")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"figure: {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", choices=["l1", "p1"], default="l1")
    ap.add_argument("--runs", type=int, default=None, help="runs per cell (default: the spec's)")
    ap.add_argument("--out", default="results/filterpy_in_process")
    args = ap.parse_args()

    spec = SPECS[args.model]
    sim = kfmc.simulate(spec, out=os.path.join(args.out, "sim"), runs=args.runs, force=True)
    print(sim.model)
    est = [estimates_of(sim, LABELS[args.model], 1.0)]
    if args.model == "l1":
        # The spec's negative control: the same filter assuming 4 Q.
        est.append(estimates_of(sim, "filterpy_kf_q4", 4.0))
    study = kfmc.score(sim, est, out=os.path.join(args.out, "score"), force=True)
    verdict = study.verdict().select("scenario", "filter", "statistic", "p_value", "pass")
    with pl.Config(tbl_rows=-1, tbl_cols=-1):
        print(verdict)
    print(f"tables in {study.folder}: {', '.join(study.tables())}")
    save_figure(study, os.path.join(args.out, "anees.png"))


if __name__ == "__main__":
    main()
