"""A user's own Monte Carlo judged in memory: ``kfmc.score(spec, estimates, truth=df)``.

A scalar random walk x_k = x_{k-1} + w_k, z_k = x_k + v_k is simulated in numpy with a
fixed seed, and a Kalman filter written here runs on it. With the true Q the verdict
passes; with Q × 0.05 (an over-confident filter) it fails. The truth and estimates are
polars DataFrames, never files."""

import math

import numpy as np
import polars as pl
import pytest

import kfmc

RUNS, K, Q, R = 40, 60, 0.04, 0.25

SPEC = f"""
name = "walk"
runs = {RUNS}
[model]
kind = "recorded"
states = ["x"]
state_units = ["m"]
measurements = ["x"]
dt_s = 0.1
steps = {K}
[[filters]]
label = "kf"
kind = "external"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.01
"""


def simulate(seed: int = 4):
    rng = np.random.default_rng(seed)
    x = np.zeros((RUNS, K + 1))
    x[:, 0] = rng.normal(0.0, 1.0, RUNS)
    for k in range(1, K + 1):
        x[:, k] = x[:, k - 1] + rng.normal(0.0, math.sqrt(Q), RUNS)
    z = x + rng.normal(0.0, math.sqrt(R), x.shape)
    return x, z


def keys():
    run = np.repeat(np.arange(RUNS), K + 1)
    step = np.tile(np.arange(K + 1), RUNS)
    return {
        "scenario": ["recorded"] * len(run),
        "noise_scale": np.ones(len(run)),
        "run": run,
        "step": step,
    }


def kalman(z, q_assumed):
    est = np.zeros_like(z)
    var = np.zeros_like(z)
    nu = np.full_like(z, np.nan)
    s = np.full_like(z, np.nan)
    a = np.full_like(z, np.nan)
    for r in range(RUNS):
        xh, p = 0.0, 1.0  # the prior N(0, 1) the truth's x_0 is drawn from
        est[r, 0], var[r, 0] = xh, p
        for k in range(1, K + 1):
            p = p + q_assumed
            s_k = p + R
            gain = p / s_k
            nu[r, k] = z[r, k] - xh
            s[r, k] = s_k
            xh = xh + gain * nu[r, k]
            p = (1 - gain) * p
            a[r, k] = 1 - gain  # (I − K H) F
            est[r, k], var[r, k] = xh, p
    return est, var, nu, s, a


def frames(q_assumed):
    x, z = simulate()
    truth = pl.DataFrame({**keys(), "t": np.tile(np.arange(K + 1) * 0.1, RUNS), "truth_x": x.ravel()})
    est, var, nu, s, a = kalman(z, q_assumed)
    estimates = pl.DataFrame(
        {
            **keys(),
            "filter": ["kf"] * RUNS * (K + 1),
            "est_x": est.ravel(),
            "P_x_x": var.ravel(),
            "nu_x": nu.ravel(),
            "S_x_x": s.ravel(),
            "A_x_x": a.ravel(),
        }
    ).with_columns(
        pl.col("nu_x").fill_nan(None), pl.col("S_x_x").fill_nan(None), pl.col("A_x_x").fill_nan(None)
    )
    return truth, estimates


def verdict(study):
    c = pl.read_parquet(f"{study.folder}/consistency.parquet").filter(pl.col("test") == "verdict")
    assert c.height == 1
    return c.row(0, named=True)


def test_score_judges_a_users_own_runs_in_memory(tmp_path):
    spec = tmp_path / "walk.toml"
    spec.write_text(SPEC)
    truth, good = frames(Q)
    ok = verdict(kfmc.score(spec, good, truth=truth, out=tmp_path / "good", quiet=True))
    assert ok["pass"] and ok["p_value"] > 0.01
    _, bad = frames(0.05 * Q)
    rejected = verdict(kfmc.score(spec, bad, truth=truth, out=tmp_path / "bad", quiet=True))
    assert not rejected["pass"] and rejected["p_value"] < 1e-6
    # A truth column the spec does not declare is named.
    with pytest.raises(kfmc.Error, match="truth_y"):
        kfmc.score(
            spec,
            good,
            truth=truth.with_columns(truth_y=pl.col("truth_x")),
            out=tmp_path / "bad_truth",
            quiet=True,
        )


CHECKED = SPEC + """
[[check.assert]]
kind = "consistent"
filter = "kf"
"""


def test_check_judges_a_users_own_runs_and_wants_their_stamp(tmp_path, kfmc_bin):
    import subprocess

    import pyarrow as pa
    import pyarrow.parquet as pq

    spec = tmp_path / "walk.toml"
    spec.write_text(CHECKED)
    truth, good = frames(Q)
    _, bad = frames(0.05 * Q)
    # A DataFrame carries no stamp: refused unless allowed, as the command refuses a file.
    with pytest.raises(kfmc.Error, match="stamp"):
        kfmc.check(spec, estimates=good, truth=truth, out=tmp_path / "unstamped", quiet=True)
    allowed = kfmc.check(spec, estimates=good, truth=truth, allow_unstamped=True, out=tmp_path / "a", quiet=True)
    assert allowed.ok and allowed.exit_code == 0
    failing = kfmc.check(spec, estimates=bad, truth=truth, allow_unstamped=True, out=tmp_path / "b", quiet=True)
    assert not failing.ok and failing.exit_code == 3
    # kfmc.stamp gives the metadata a table made on this truth carries: accepted without
    # allow_unstamped, and equal to what `kfmc stamp` writes into a file.
    stamp = kfmc.stamp(spec, truth)
    table = good.to_arrow()
    stamped = table.replace_schema_metadata({**(table.schema.metadata or {}), **stamp})
    assert kfmc.check(spec, estimates=stamped, truth=truth, out=tmp_path / "c", quiet=True).ok
    truth_file, by_cli, by_py = tmp_path / "truth.parquet", tmp_path / "cli.parquet", tmp_path / "py.parquet"
    truth.write_parquet(truth_file)
    good.write_parquet(by_cli)
    good.write_parquet(by_py)
    out = subprocess.run(
        [kfmc_bin, "stamp", "--truth", str(truth_file), "--spec", str(spec), str(by_cli)],
        capture_output=True, text=True,
    )
    assert out.returncode == 0, out.stderr
    assert kfmc.stamp(spec, truth_file, files=[by_py]) == stamp
    meta = lambda p: {k.decode(): v.decode() for k, v in (pq.read_metadata(p).metadata or {}).items() if k.startswith(b"kfmc.")}
    assert meta(by_py) == meta(by_cli) == stamp
    assert kfmc.check(spec, estimates=by_py, truth=truth_file, out=tmp_path / "d", quiet=True).ok
    # Estimates stamped with another truth (one value changed) are foreign.
    other = truth.with_columns(pl.when(pl.int_range(pl.len()) == 5).then(pl.col("truth_x") + 1e-9).otherwise(pl.col("truth_x")).alias("truth_x"))
    assert kfmc.stamp(spec, other) != stamp
    with pytest.raises(kfmc.Error, match="stamp|world"):
        kfmc.check(spec, estimates=stamped, truth=other, out=tmp_path / "e", quiet=True)
    assert isinstance(stamped, pa.Table)


def test_score_with_truth_writes_nothing_in_the_working_directory(tmp_path, monkeypatch):
    import gc

    spec = tmp_path / "spec" / "walk.toml"
    spec.parent.mkdir()
    spec.write_text(SPEC)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    truth, good = frames(Q)
    study = kfmc.score(spec, good, truth=truth, quiet=True)
    folder = study.folder
    assert (folder / "consistency.parquet").is_file()
    assert list(work.iterdir()) == []
    del study
    gc.collect()
    assert not folder.exists()
