"""`kfmc tune --method ml` against statsmodels' state-space maximum likelihood on the same
data: experiments/tune_ml_cv3d.toml (six unknown diagonal elements, one run of 10,002 scalar
measurements), the same model, prior and start (the spec's values).

    python3 examples/python/bench_tune_statsmodels.py target/release/kfmc [ROUNDS]

Both sides are timed in turn (kfmc, statsmodels, kfmc, ...), so a shared machine's load
falls on both; each round's ratio is statsmodels' time over kfmc's. kfmc is timed as a whole
process (reading the file, three starts, the observed information, the tables written);
statsmodels as its fit alone, in this process, which favours statsmodels. Before timing, both
must reach the same estimates to 1e-3 relative.
"""

import math
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib

import numpy as np
import polars as pl
import statsmodels.api as sm

ROOT = pathlib.Path(__file__).resolve().parents[2]
SPEC = ROOT / "experiments" / "tune_ml_cv3d.toml"
STATES = ["px", "vx", "py", "vy", "pz", "vz"]
# The tuned elements' places: Q[vx,vx], Q[vy,vy], Q[vz,vz], then R's diagonal.
Q_AT = [1, 3, 5]


def main():
    kfmc = sys.argv[1]
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    spec = tomllib.loads(SPEC.read_text())
    F, H = np.array(spec["model"]["f"]), np.array(spec["model"]["h"])
    Q, R = np.array(spec["model"]["q"]), np.array(spec["model"]["r"])
    with tempfile.TemporaryDirectory() as tmp:
        sim = pathlib.Path(tmp) / "sim"
        subprocess.run([kfmc, "simulate", str(SPEC), "--out", str(sim), "--quiet"], check=True)
        init = pl.read_parquet(sim / "initial.parquet")
        x0 = np.array([init[f"est_{s}"][0] for s in STATES])
        P0 = np.zeros((6, 6))
        for i, a in enumerate(STATES):
            for j, b in enumerate(STATES[: i + 1]):
                P0[i, j] = P0[j, i] = init[f"P_{a}_{b}"][0]
        meas = pl.read_parquet(sim / "measurements.parquet").sort("step")
        y = meas.select(["z_zx", "z_zy", "z_zz"]).to_numpy()[1:]

        class Cv3d(sm.tsa.statespace.MLEModel):
            def __init__(self, endog):
                super().__init__(endog, k_states=6, k_posdef=6)
                self["design"] = H
                self["transition"] = F
                self["selection"] = np.eye(6)

            def update(self, params, **kwargs):
                params = super().update(params, **kwargs)
                # Complex-step derivatives: keep the imaginary part.
                q, r = Q.astype(params.dtype), R.astype(params.dtype)
                theta = np.exp(params)
                for k, i in enumerate(Q_AT):
                    q[i, i] = theta[k]
                for k in range(3):
                    r[k, k] = theta[3 + k]
                self["state_cov"] = q
                self["obs_cov"] = r
                # kfmc's prior is x̂_0 at step 0; the first measurement is at step 1.
                self.ssm.initialize_known(F @ x0, F @ P0 @ F.T + q)

            @property
            def start_params(self):
                return np.log([Q[i, i] for i in Q_AT] + [R[k, k] for k in range(3)])

        def run_kfmc():
            out = pathlib.Path(tmp) / "tuned"
            subprocess.run(
                [kfmc, "tune", str(SPEC), "--method", "ml", "--quiet", "--force",
                 "--threads", "2", "--out", str(out),
                 "--measurements", str(sim / "measurements.parquet")],
                check=True, stdout=subprocess.DEVNULL,
            )
            return pl.read_parquet(out / "tuned.parquet")["estimate"].to_numpy()

        def run_statsmodels():
            m = Cv3d(y)
            fit = m.fit(start_params=m.start_params, method="bfgs", maxiter=1000,
                        gtol=1e-8, disp=False)
            return np.exp(fit.params)

        ours, theirs = run_kfmc(), run_statsmodels()
        for a, b in zip(ours, theirs):
            assert math.isclose(a, b, rel_tol=1e-3), (ours, theirs)
        print(f"estimates agree to 1e-3: kfmc {np.array2string(ours, precision=5)}")
        ratios, tk, ts = [], [], []
        for _ in range(rounds):
            t0 = time.perf_counter()
            run_kfmc()
            t1 = time.perf_counter()
            run_statsmodels()
            t2 = time.perf_counter()
            tk.append(t1 - t0)
            ts.append(t2 - t1)
            ratios.append((t2 - t1) / (t1 - t0))
        print(f"kfmc tune --method ml: median {statistics.median(tk):.2f} s "
              f"[{min(tk):.2f}, {max(tk):.2f}] wall, whole process")
        print(f"statsmodels MLEModel.fit (BFGS): median {statistics.median(ts):.2f} s "
              f"[{min(ts):.2f}, {max(ts):.2f}] wall")
        print(f"statsmodels / kfmc: median {statistics.median(ratios):.1f}x "
              f"[{min(ratios):.1f}, {max(ratios):.1f}] over {rounds} rounds")


if __name__ == "__main__":
    main()
