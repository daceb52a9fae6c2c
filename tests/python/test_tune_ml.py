"""`kfmc tune --method ml` against statsmodels' state-space likelihood (an independent
implementation): the −ln L kfmc reports at its optimum equals statsmodels' log-likelihood
of the same measurements, model, prior and tuned Q, R to 1e-10 relative, and statsmodels'
own maximum-likelihood fit from kfmc's start reaches the same elements to 1e-4 relative.

Skipped when statsmodels is not installed (CI installs it: pip install statsmodels).
"""

import math
import subprocess
import tomllib

import pytest

sm = pytest.importorskip("statsmodels.api")
np = pytest.importorskip("numpy")
pl = pytest.importorskip("polars")


def _run(kfmc_bin, *args):
    out = subprocess.run([kfmc_bin, *args], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out


def test_kfmc_ml_matches_statsmodels(tmp_path, kfmc_bin, root):
    spec = (root / "experiments" / "tune_ml_cv.toml").read_text()
    sim = tmp_path / "sim"
    spec_path = tmp_path / "cv.toml"
    spec_path.write_text(spec.replace('output = "results/tune_ml_cv"', f'output = "{sim}"'))
    _run(kfmc_bin, "simulate", str(spec_path), "--runs", "1", "--quiet")
    out = tmp_path / "tuned"
    _run(
        kfmc_bin, "tune", str(spec_path), "--method", "ml", "--quiet", "--out", str(out),
        "--measurements", str(sim / "measurements.parquet"),
    )
    model = tomllib.loads((out / "tuned.toml").read_text())["model"]
    F, H = np.array(model["f"]), np.array(model["h"])
    Q, R = np.array(model["q"]), np.array(model["r"])
    trace = pl.read_parquet(out / "tune_trace.parquet")
    tuned = pl.read_parquet(out / "tuned.parquet")
    meas = pl.read_parquet(sim / "measurements.parquet").sort("step")
    init = pl.read_parquet(sim / "initial.parquet")
    states = ["px", "vx", "py", "vy"]
    x0 = np.array([init[f"est_{s}"][0] for s in states])
    P0 = np.zeros((4, 4))
    for i, a in enumerate(states):
        for j, b in enumerate(states[: i + 1]):
            P0[i, j] = P0[j, i] = init[f"P_{a}_{b}"][0]
    y = meas.select(["z_zx", "z_zy"]).to_numpy()[1:]

    class Cv(sm.tsa.statespace.MLEModel):
        # params: ln of Q[vx,vx], Q[vy,vy], R[zx,zx], R[zy,zy].
        def __init__(self, endog):
            super().__init__(endog, k_states=4, k_posdef=4)
            self["design"] = H
            self["transition"] = F
            self["selection"] = np.eye(4)

        def update(self, params, **kwargs):
            params = super().update(params, **kwargs)
            # statsmodels differentiates by complex step: keep the imaginary part, or the
            # score is zero and the fit stops where it starts.
            q, r = Q.astype(params.dtype), R.astype(params.dtype)
            q[1, 1], q[3, 3], r[0, 0], r[1, 1] = np.exp(params)
            self["state_cov"] = q
            self["obs_cov"] = r
            # kfmc's prior is x̂_0 at step 0; the first measurement is at step 1.
            self.ssm.initialize_known(F @ x0, F @ P0 @ F.T + q)

        @property
        def start_params(self):
            return np.log([0.04, 0.09, 0.25, 1.0])

    m = Cv(y)
    theta = np.log(tuned["estimate"].to_numpy())
    ours = trace.filter(pl.col("objective") == trace["objective"].min())["objective"][0]
    theirs = -m.loglike(theta)
    assert abs(ours - theirs) <= 1e-10 * abs(theirs), (ours, theirs)
    fit = m.fit(start_params=m.start_params, method="bfgs", maxiter=1000, gtol=1e-10, disp=False)
    est = np.exp(fit.params)
    for a, b in zip(est, tuned["estimate"].to_numpy()):
        assert math.isclose(a, b, rel_tol=1e-4), (est, tuned["estimate"].to_numpy())
