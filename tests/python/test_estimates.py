"""`kfmc.Estimates` and `kfmc.sigma_point_transition`.

* An `Estimates` built from the arrays of kfmc's own exported KF is the exported table,
  value for value, and scores to the same tables, in memory and as a written file.
* The compact forms (Cholesky, correlations) and float32 score within the tolerances the
  book states (`docs/src/guide/external.md`): f64 forms to 1e-12, float32 to 1e-6 relative on
  NEES/NIS, p-values to 1e-5, the same verdicts, the RMSE bit for bit (the estimates stay
  f64); a float32 file is smaller.
* Bad arrays raise `EstimatesError` naming the argument, the run and the step.
* `sigma_point_transition` is F for a linear f whatever the points; a FilterPy UKF on L1
  given the predict points kept before `predict()` gives kfmc's KF's (I − KH)F, while the
  points `predict()` leaves in `ukf.sigmas_f` give a wrong one; a numpy UKF on P1 (θ through
  π) gives the A_k kfmc's own UKF exports.
"""

import contextlib
import importlib
import math
import subprocess

import numpy as np
import polars as pl
import pytest

import kfmc
from test_model import toml_text

L1 = {
    "name": "py_estimates_l1",
    "master_seed": 5,
    "runs": 8,
    "output": "unused",
    "model": {"kind": "linear_quadrotor", "sensor": "positions"},
    "scenarios": [
        {"name": "hover", "x0": [1.0, 0.0, 1.0, 0.0, 1.0, 0.0], "duration_s": 5.0},
        {"name": "drift", "x0": [0.0, 0.5, 0.0, -0.5, 2.0, 0.0], "duration_s": 3.0},
    ],
    "noise": {"scales": [1.0, 3.0]},
    "filters": [{"label": "kf", "kind": "ekf"}],
    "initial_estimate": {"mode": "sampled", "p0_std": 1.0},
    "consistency": {"alpha": 0.01},
}

KEYS = ["scenario", "noise_scale", "run"]


def with_external(spec, label="mine"):
    d = dict(spec)
    d["filters"] = list(spec["filters"]) + [{"label": label, "kind": "external"}]
    return d


def export(spec, base, script_kfmc):
    """kfmc's own filters' estimates on the spec's runs (`kfmc run --export-estimates`)."""
    path = base / f"{spec['name']}.toml"
    path.write_text(toml_text(dict(spec, output=str(base / "own"))))
    subprocess.run([script_kfmc, "run", str(path), "--export-estimates", "-q"], check=True)
    return pl.read_parquet(base / "own" / "estimates.parquet")


def arrays(run, q, z):
    """x, P, nu, S, A of one run's exported rows (the lower triangles mirrored)."""
    k1, n, m = run.height, len(q), len(z)
    x = run.select([f"est_{a}" for a in q]).to_numpy()
    P = np.zeros((k1, n, n))
    for i in range(n):
        for j in range(i + 1):
            P[:, i, j] = P[:, j, i] = run[f"P_{q[i]}_{q[j]}"].to_numpy()
    nu = run.select([f"nu_{a}" for a in z]).to_numpy().astype(float)
    S = np.full((k1, m, m), np.nan)
    for i in range(m):
        for j in range(i + 1):
            S[:, i, j] = S[:, j, i] = run[f"S_{z[i]}_{z[j]}"].to_numpy().astype(float)
    A = np.stack(
        [run[f"A_{a}_{b}"].to_numpy().astype(float) for a in q for b in q], axis=1
    ).reshape(k1, n, n)
    return x, P, nu, S, A


@pytest.fixture(scope="module")
def world(tmp_path_factory, script_kfmc):
    """An L1 simulation with the external filter `mine`, kfmc's KF's exported rows relabelled
    `mine`, and the per-run arrays of those rows."""
    base = tmp_path_factory.mktemp("est")
    sim = kfmc.simulate(with_external(L1), out=base / "sim", quiet=True)
    own = export(L1, base, script_kfmc).with_columns(pl.lit("mine").alias("filter"))
    q, z = sim.model.states, sim.model.measurements
    runs = [
        (key, arrays(g.sort("step"), q, z))
        for key, g in own.group_by(KEYS, maintain_order=True)
    ]
    return sim, own, runs, base


def build(sim, runs, **options):
    est = kfmc.Estimates(sim, "mine", **options)
    for key, (x, P, nu, S, A) in runs:
        est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
    return est


def same_tables(a, b):
    assert a.tables() == b.tables()
    for t in a.tables():
        assert a.table(t).equals(b.table(t)), t


def test_estimates_from_the_export_arrays_are_the_export_and_score_the_same(world, tmp_path, script_kfmc):
    sim, own, runs, _ = world
    est = build(sim, runs)
    assert len(est) == own.height and est.columns == own.columns
    assert est.to_polars().equals(own)
    assert est.metadata == sim.stamp == kfmc.schema("estimates", with_external(L1))["metadata"]
    study = kfmc.score(sim, est, out=tmp_path / "mem", quiet=True)
    same_tables(study, kfmc.score(sim, own, out=tmp_path / "df", quiet=True))
    # The file carries the stamp: `kfmc score` takes it without a warning, to the same tables.
    path = est.write(tmp_path / "mine.parquet")
    import pyarrow.parquet as pq

    meta = pq.ParquetFile(path).metadata.metadata
    assert meta[b"kfmc.world_stamp"].decode() == est.world_stamp
    assert meta[b"kfmc.master_seed"].decode() == str(est.master_seed)
    o = subprocess.run(
        [script_kfmc, "score", str(sim.folder), "--estimates", str(path), "--out", str(tmp_path / "cli"), "-q"],
        capture_output=True, text=True,
    )
    assert o.returncode == 0 and "warning" not in o.stderr, o.stderr
    same_tables(study, kfmc.Study(tmp_path / "cli"))
    # Runs added as one cell's batch give the same table.
    batch = kfmc.Estimates(sim, "mine")
    cells = {}
    for key, a in runs:
        cells.setdefault(key[:2], []).append((key[2], a))
    for (scenario, scale), items in cells.items():
        batch.add_runs(scenario, scale, [r for r, _ in items], *[np.stack(p) for p in zip(*[a for _, a in items])])
    key_order = est.to_polars().sort(KEYS + ["step"])
    assert batch.to_polars().sort(KEYS + ["step"]).equals(key_order)
    # kfmc.check takes it as well.
    gate = dict(with_external(L1), check={"assert": [{"kind": "consistent", "filter": "mine"}]})
    result = kfmc.check(gate, estimates=est, out=tmp_path / "check")
    assert result.exit_code in (0, 3), result.report
    assert result.study.table("runs").filter(pl.col("filter") == "mine").height == len(runs)


@pytest.mark.parametrize("covariance", ["lower", "cholesky", "correlation"])
@pytest.mark.parametrize("float32", [False, True])
def test_compact_forms_and_float32_score_within_the_stated_tolerance(world, tmp_path, covariance, float32):
    sim, own, runs, _ = world
    full = kfmc.score(sim, own, out=tmp_path / "full", quiet=True)
    est = build(sim, runs, covariance=covariance, float32=float32)
    df = est.to_polars()
    prefix = {"lower": "P_", "cholesky": "L_", "correlation": "var_"}[covariance]
    assert any(c.startswith(prefix) for c in df.columns)
    assert df["est_x"].dtype == pl.Float64
    assert df["nu_x"].dtype == (pl.Float32 if float32 else pl.Float64)
    study = kfmc.score(sim, est, out=tmp_path / "compact", quiet=True)
    a, b = full.table("runs").sort(KEYS + ["filter"]), study.table("runs").sort(KEYS + ["filter"])
    # The estimates are f64 in every form: the RMSE is the full file's, bit for bit.
    for c in [c for c in a.columns if c.startswith("rmse_")] + ["status"]:
        assert a[c].equals(b[c]), c
    tol = 1e-6 if float32 else 1e-12
    for c in ("nees_mean", "nis_mean"):
        x, y = a[c].to_numpy(), b[c].to_numpy()
        assert np.max(np.abs(x - y) / np.abs(x)) < tol, c
    ca, cb = full.table("consistency"), study.table("consistency")
    assert ca["test"].equals(cb["test"]) and ca["pass"].equals(cb["pass"])
    assert np.nanmax(np.abs(ca["p_value"].to_numpy() - cb["p_value"].to_numpy())) < (1e-5 if float32 else 1e-12)
    if float32:
        # float32 values take fewer bytes: the file is much smaller than the f64 one.
        small = est.write(tmp_path / "f32.parquet").stat().st_size
        big = build(sim, runs, covariance=covariance).write(tmp_path / "f64.parquet").stat().st_size
        assert small < 0.85 * big, (small, big)


def first(runs):
    key, (x, P, nu, S, A) = runs[0]
    return key, x.copy(), P.copy(), nu.copy(), S.copy(), A.copy()


def bad_cases(runs):
    key, x, P, nu, S, A = first(runs)
    cases = []

    def case(name, expect, **change):
        args = dict(x=x, P=P, nu=nu, S=S, A=A)
        args.update(change)
        cases.append((name, key, args, expect))

    name = f"run (scenario='{key[0]}', noise_scale={key[1]!r}, run={key[2]})"
    case("x_shape", f"x of {name}: shape (50, 6), expected (51, 6)", x=x[1:])
    case("P_shape", "P of", P=P[:, :5, :5])
    x_nan = x.copy()
    x_nan[7, 2] = np.nan
    case("x_nan", f"x of {name}: nan at step 7, entry (2,); a filter that failed at step 7: add_run(..., failed_at=7)", x=x_nan)
    p_inf = P.copy()
    p_inf[3, 1, 0] = np.inf
    case("P_inf", "P of", P=p_inf)
    p_asym = P.copy()
    p_asym[4, 0, 1] += 1.0
    case("P_asym", f"P of {name}: not symmetric at step 4: P[0, 1]", P=p_asym)
    case("nu_without_S", "S of", S=None)
    nu_inf = nu.copy()
    nu_inf[5, 1] = -np.inf
    case("nu_inf", f"nu of {name}: -inf at step 5, entry (1,)", nu=nu_inf)
    s_nan = S.copy()
    s_nan[6, 1, 1] = np.nan
    case("S_nan", f"S of {name}: nan at step 6, entry (1, 1), where nu reported y and y", S=s_nan)
    a_part = A.copy()
    a_part[9, 2, 3] = np.nan
    case("A_partial", f"A of {name}: NaN at step 9, entry (2, 3), where the step gives other entries", A=a_part)
    a_inf = A.copy()
    a_inf[2, 0, 0] = np.inf
    case("A_inf", f"A of {name}: inf at step 2, entry (0, 0)", A=a_inf)
    case("A_shape", "A of", A=A[:, :, :5])
    return cases


def test_bad_arrays_raise_estimates_error_naming_argument_run_and_step(world):
    sim, own, runs, _ = world
    for name, key, args, expect in bad_cases(runs):
        est = kfmc.Estimates(sim, "mine")
        with pytest.raises(kfmc.EstimatesError) as e:
            est.add_run(*key, **args)
        assert expect in str(e.value), (name, str(e.value))
        assert len(est) == 0, "a refused run is not kept"
    key, x, P, nu, S, A = first(runs)
    est = kfmc.Estimates(sim, "mine")
    for bad_key, expect in (
        (("nowhere", key[1], key[2]), "scenario 'nowhere' is not one of the simulation's: hover, drift"),
        ((key[0], 2.0, key[2]), "noise_scale 2.0 is not one of the simulation's: 1.0, 3.0"),
        ((key[0], key[1], 8), "run 8 is outside 0..8"),
    ):
        with pytest.raises(kfmc.EstimatesError, match=expect):
            est.add_run(*bad_key, x=x, P=P)
    est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
    with pytest.raises(kfmc.EstimatesError, match="was added already"):
        est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
    other, (x2, P2, nu2, S2, _) = runs[1]
    with pytest.raises(kfmc.EstimatesError, match="A of .*not given, but the first run .* gave it"):
        est.add_run(*other, x=x2, P=P2, nu=nu2, S=S2)
    with pytest.raises(kfmc.EstimatesError, match="'kf' is not an external filter .* its external filters: mine"):
        kfmc.Estimates(sim, "kf")
    with pytest.raises(kfmc.EstimatesError, match="covariance = 'diag'"):
        kfmc.Estimates(sim, "mine", covariance="diag")
    with pytest.raises(kfmc.EstimatesError, match="no runs added"):
        kfmc.Estimates(sim, "mine").to_polars()
    # Forms that cannot hold a covariance that is not positive definite say so.
    p_bad = P.copy()
    p_bad[3] = -p_bad[3]
    with pytest.raises(kfmc.EstimatesError, match="not positive definite at step 3"):
        kfmc.Estimates(sim, "mine", covariance="cholesky").add_run(*key, x=x, P=p_bad)
    with pytest.raises(kfmc.EstimatesError, match="the variance of x is .* at step 3"):
        kfmc.Estimates(sim, "mine", covariance="correlation").add_run(*key, x=x, P=p_bad)
    # … while the lower triangle takes it, and kfmc counts the run a failure there.
    kfmc.Estimates(sim, "mine").add_run(*key, x=x, P=p_bad)


def test_failed_at_records_the_run_as_a_numerical_failure(world, tmp_path):
    sim, own, runs, _ = world
    est = kfmc.Estimates(sim, "mine")
    for i, (key, (x, P, nu, S, A)) in enumerate(runs):
        if i == 2:
            x = x.copy()
            x[12:] = np.nan  # the filter blew up at step 12
            before = [a.copy() for a in (P, nu, S, A)]
            est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A, failed_at=12)
            # The caller's arrays are left as they were.
            assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(before, (P, nu, S, A)))
        else:
            est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
    runs_table = kfmc.score(sim, est, out=tmp_path / "s", quiet=True).table("runs")
    key = runs[2][0]
    row = runs_table.filter(
        (pl.col("filter") == "mine") & (pl.col("scenario") == key[0])
        & (pl.col("noise_scale") == key[1]) & (pl.col("run") == key[2])
    )
    assert row["status"].to_list() == ["numerical_failure"]
    assert row["status_step"].to_list() == [12]
    mine = runs_table.filter(pl.col("filter") == "mine")
    assert (mine["status"] == "numerical_failure").sum() == 1


def test_estimates_of_another_world_are_refused(world, tmp_path):
    sim, own, runs, base = world
    est = build(sim, runs)
    other = kfmc.simulate(with_external(L1), out=tmp_path / "other", seed=99, quiet=True)
    with pytest.raises(kfmc.EstimatesError, match=f"made on the simulation .* master seed 5.*master seed 99"):
        kfmc.score(other, est, out=tmp_path / "x", quiet=True)
    with pytest.raises(kfmc.EstimatesError, match="master seed 99"):
        gate = dict(with_external(L1), check={"assert": [{"kind": "consistent", "filter": "mine"}]})
        kfmc.check(gate, estimates=est, seed=99, out=tmp_path / "y")


def test_failed_at_marks_the_failed_column_and_only_marked_runs_count_as_failed(world, tmp_path):
    sim, own, runs, _ = world
    est = kfmc.Estimates(sim, "mine")
    for i, (key, (x, P, nu, S, A)) in enumerate(runs):
        if i == 1:
            continue  # left out: missing, not failed
        est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A, failed_at=7 if i == 2 else None)
    table = est.to_polars()
    assert table["failed"].dtype == pl.Boolean
    k2 = runs[2][0]
    marked = table.filter(pl.col("failed"))
    assert marked.select(KEYS).unique().rows() == [k2]
    assert marked["step"].min() == 7
    study = kfmc.score(sim, est, out=tmp_path / "s", quiet=True)
    assert study.report["runs_missing"] == {"mine": 1}
    mine = study.table("runs").filter(pl.col("filter") == "mine")
    assert (mine["status"] == "numerical_failure").sum() == 1
    assert (mine["status"] == "missing").sum() == 1
    missing = mine.filter(pl.col("status") == "missing")
    assert missing.select(KEYS).rows() == [runs[1][0]]
    # Missing runs are in neither count of the summary.
    summary = study.table("summary").filter(pl.col("filter") == "mine")
    k1 = runs[1][0]
    cell = summary.filter((pl.col("scenario") == k1[0]) & (pl.col("noise_scale") == k1[1]))
    assert set(cell["runs"]) == {L1["runs"] - 1 - (k2[:2] == k1[:2])}
    assert set(cell["runs_failed"]) == {int(k2[:2] == k1[:2])}
    # A gate that tolerates every failure is still incomplete on a missing run.
    gate = dict(
        with_external(L1),
        check={"max_failed_runs": 1.0, "assert": [{"kind": "consistent", "filter": "mine"}]},
    )
    r = kfmc.check(gate, estimates=est, out=tmp_path / "gate")
    name = f"consistent[{k1[0]} noise={k1[1]:g} mine]"
    (case,) = [c for c in r.cases if c["name"] == name]
    assert case["incomplete"] and "missing" in case["detail"], case
    assert "failed numerically" not in r.report, r.report


def test_the_gate_holds_tables_in_memory_to_the_world_stamp(world, tmp_path):
    """A pyarrow Table read from a file of another seed carries that seed in its schema
    metadata and is refused; a table without a stamp needs allow_unstamped=True; a
    kfmc.Estimates carries its simulation's stamp. With only a `white` assertion the gate
    passed on the wrong world."""
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    sim, own, runs, _ = world
    gate = dict(with_external(L1), check={"assert": [{"kind": "white", "filter": "mine"}]})
    other = kfmc.simulate(with_external(L1), out=tmp_path / "other", seed=99, quiet=True)
    theirs = build(other, runs).write(tmp_path / "theirs.parquet")
    table = pq.read_table(theirs)
    assert table.schema.metadata[b"kfmc.master_seed"] == b"99"
    with pytest.raises(kfmc.EstimatesError, match="another simulation.*master_seed = 99"):
        kfmc.check(gate, estimates=table, out=tmp_path / "a")
    with pytest.raises(kfmc.EstimatesError, match="another simulation"):
        kfmc.score(sim, table, out=tmp_path / "a2", quiet=True)
    # Unstamped: refused by the gate unless allowed, as the command refuses the file.
    bare = pq.read_table(theirs).replace_schema_metadata(None)
    for unstamped in (bare, pl.from_arrow(bare)):
        with pytest.raises(kfmc.EstimatesError, match="carries no world stamp.*allow_unstamped=True"):
            kfmc.check(gate, estimates=unstamped, out=tmp_path / "b")
    # Stamped with this world, or allowed: judged (passed or failed, never refused).
    ours = pq.read_table(build(sim, runs).write(tmp_path / "ours.parquet"))
    judged = [
        kfmc.check(gate, estimates=ours, out=tmp_path / "c"),
        kfmc.check(gate, estimates=own, out=tmp_path / "d", allow_unstamped=True),
        kfmc.check(gate, estimates=build(sim, runs), out=tmp_path / "e"),
    ]
    assert all(r.exit_code in (0, 3) for r in judged), [r.report for r in judged]
    assert len({r.report for r in judged}) == 1


def test_a_filter_without_innovations_is_not_judged_rather_than_left_out(world, tmp_path):
    sim, own, runs, _ = world
    est = kfmc.Estimates(sim, "mine")
    for key, (x, P, nu, S, A) in runs:
        est.add_run(*key, x=x, P=P, A=A)
    study = kfmc.score(sim, est, out=tmp_path / "s", quiet=True)
    v = study.verdict()
    mine = v.filter(pl.col("filter") == "mine")
    assert mine.height == len(L1["scenarios"]) * len(L1["noise"]["scales"])
    assert set(mine["note"]) == {"not judged: no innovations"}
    assert mine["pass"].null_count() == mine.height and mine["p_value"].null_count() == mine.height
    kf = v.filter(pl.col("filter") == "kf")
    assert kf["note"].null_count() == kf.height and kf["pass"].null_count() == 0
    gate = dict(with_external(L1), check={"assert": [{"kind": "consistent", "filter": "mine"}]})
    r = kfmc.check(gate, estimates=est, out=tmp_path / "gate")
    assert r.exit_code == 4 and "not judged: no innovations" in r.report, r.report


def merwe(n, alpha=1.0, beta=2.0, kappa=0.0):
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + 1 - alpha**2 + beta
    return wm, wc, math.sqrt(n + lam)


def points(x, P, c):
    L = np.linalg.cholesky(P)
    n = len(x)
    return np.vstack([x] + [x + c * L[:, j] for j in range(n)] + [x - c * L[:, j] for j in range(n)])


def test_sigma_point_transition_of_a_linear_f_is_f_whatever_the_points():
    rng = np.random.default_rng(4)
    n = 5
    F = rng.normal(size=(n, n))
    x = rng.normal(size=n)
    M = rng.normal(size=(n, n))
    P = M @ M.T + 0.1 * np.eye(n)
    for alpha, beta, kappa in ((1.0, 2.0, 0.0), (0.5, 2.0, 3.0 - n), (1e-3, 2.0, 0.0)):
        wm, wc, c = merwe(n, alpha, beta, kappa)
        chi = points(x, P, c)
        A = kfmc.sigma_point_transition(chi, chi @ F.T + 3.0, wm, wc)
        assert np.allclose(A, F, rtol=0, atol=1e-8 * np.abs(F).max() / alpha**2), (alpha, A - F)
    # The cubature points (no centre point, equal weights).
    L = np.linalg.cholesky(P)
    chi = np.vstack([x + math.sqrt(n) * s * L[:, j] for s in (1, -1) for j in range(n)])
    w = np.full(2 * n, 0.5 / n)
    assert np.allclose(kfmc.sigma_point_transition(chi, chi @ F.T, w, w), F, atol=1e-12)
    # With an update: (I − K H̃) F̃, H̃ = H for a linear h.
    H = rng.normal(size=(2, n))
    K = rng.normal(size=(n, 2))
    wm, wc, c = merwe(n)
    chi_u = points(x + 1.0, P + np.eye(n), c)
    A = kfmc.sigma_point_transition(
        points(x, P, c), points(x, P, c) @ F.T, wm, wc, K=K, sigmas_update=chi_u, sigmas_h=chi_u @ H.T
    )
    assert np.allclose(A, (np.eye(n) - K @ H) @ F, atol=1e-10)
    # Bad arguments name themselves.
    with pytest.raises(kfmc.EstimatesError, match="sigmas_f: shape"):
        kfmc.sigma_point_transition(chi_u, chi_u[:3], wm, wc)
    with pytest.raises(kfmc.EstimatesError, match="sigmas_update, sigmas_h: the update needs"):
        kfmc.sigma_point_transition(chi_u, chi_u, wm, wc, K=K)
    with pytest.raises(kfmc.EstimatesError, match=r"K: shape \(5, 2\), expected \(5, 3\)"):
        kfmc.sigma_point_transition(chi_u, chi_u, wm, wc, K=K, sigmas_update=chi_u, sigmas_h=chi_u[:, :3])
    with pytest.raises(kfmc.EstimatesError, match="not positive definite"):
        kfmc.sigma_point_transition(np.zeros((11, 5)), np.zeros((11, 5)), wm, wc)


def filterpy_ukf_rows(sim, key, meas, init, naive):
    """FilterPy's UnscentedKalmanFilter on one L1 run, with the points of each predict kept
    before predict() replaces them (naive=False) or read from ukf.sigmas_f after it."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    m = sim.model
    n, nz = len(m.states), len(m.measurements)
    F, G, H = sim.F, sim.G, sim.H
    pts = MerweScaledSigmaPoints(n, alpha=1.0, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(
        dim_x=n, dim_z=nz, dt=m.dt_s, fx=lambda x, dt, u: F @ x + G @ u, hx=lambda x: H @ x, points=pts
    )
    row = init.row(0, named=True)
    q = m.states
    ukf.x = np.array([row[f"est_{a}"] for a in q])
    ukf.P = np.array([[row[f"P_{q[max(i, j)]}_{q[min(i, j)]}"] for j in range(n)] for i in range(n)])
    ukf.Q, ukf.R = sim.Q, sim.R
    z = meas.select([f"z_{a}" for a in m.measurements]).to_numpy()
    u = meas.select([f"u_{a}" for a in m.inputs]).to_numpy()
    As = np.full((meas.height, n, n), np.nan)
    for k in range(1, meas.height):
        chi = pts.sigma_points(ukf.x, ukf.P)  # the points predict() draws
        chi_f = np.array([F @ s + G @ u[k] for s in chi])
        ukf.predict(u=u[k])
        if naive:
            # What predict() leaves in ukf.sigmas_f: points redrawn from (x̂⁻, P⁻), taken
            # for the images of chi.
            chi_f = ukf.sigmas_f.copy()
        ukf.update(z[k])
        As[k] = kfmc.sigma_point_transition(
            chi, chi_f, ukf.Wm, ukf.Wc, K=ukf.K, sigmas_update=ukf.sigmas_f, sigmas_h=ukf.sigmas_h
        )
    return As


def test_filterpy_ukf_transition_from_the_kept_points_is_the_kfs_and_from_sigmas_f_is_not(world):
    pytest.importorskip("filterpy")
    sim, own, runs, _ = world
    for key, truth, meas, init in sim.runs():
        if key[2] > 1:
            continue
        ref = dict(runs)[key][4]
        good = filterpy_ukf_rows(sim, key, meas, init, naive=False)
        bad = filterpy_ukf_rows(sim, key, meas, init, naive=True)
        scale = np.abs(ref[1:]).max()
        assert np.abs(good[1:] - ref[1:]).max() < 1e-12 * scale, np.abs(good[1:] - ref[1:]).max()
        assert np.abs(bad[1:] - ref[1:]).max() > 0.1 * scale


P1_UKF = {
    "name": "py_estimates_p1",
    "master_seed": 7,
    "runs": 2,
    "output": "unused",
    "model": {"kind": "planar_quadrotor", "sensor": "p1"},
    "scenarios": [{"name": "roll", "duration_s": 6.0}],
    "filters": [{"label": "ukf", "kind": "ukf"}],
    "initial_estimate": {"mode": "sampled", "p0_std": 0.1},
}


def test_a_numpy_ukf_on_p1_gives_kfmcs_ukf_transition(tmp_path, script_kfmc):
    sim = kfmc.simulate(P1_UKF, out=tmp_path / "sim", quiet=True)
    ref = export(P1_UKF, tmp_path, script_kfmc)
    m = sim.model
    q, zn = m.states, m.measurements
    n = len(q)
    wm, wc, c = merwe(n)
    theta = zn.index("theta")

    def cloud_mean(zeta):
        # kfmc's mean: circular in θ, anchored at the centre point.
        mean = wm @ zeta
        d = zeta[:, theta] - zeta[0, theta]
        mean[theta] = zeta[0, theta] + math.atan2(wm @ np.sin(d), wm @ np.cos(d))
        return mean

    resid = lambda a, b: sim.residual(a, b)
    worst = 0.0
    for key, truth, meas, init in sim.runs():
        row = init.row(0, named=True)
        x = np.array([row[f"est_{a}"] for a in q])
        P = np.array([[row[f"P_{q[max(i, j)]}_{q[min(i, j)]}"] for j in range(n)] for i in range(n)])
        z = meas.select([f"z_{a}" for a in zn]).to_numpy()
        u = meas.select([f"u_{a}" for a in m.inputs]).to_numpy()
        run = ref.filter(
            (pl.col("scenario") == key[0]) & (pl.col("noise_scale") == key[1]) & (pl.col("run") == key[2])
        ).sort("step")
        ref_a = arrays(run, q, zn)[4]
        for k in range(1, meas.height):
            chi = points(x, P, c)
            chi_f = np.array([sim.f(s, u[k]) for s in chi])
            x = wm @ chi_f
            d = chi_f - x
            P = (d * wc[:, None]).T @ d + sim.Q
            chi_u = points(x, P, c)
            zeta = np.array([sim.h(s) for s in chi_u])
            zhat = cloud_mean(zeta)
            e = np.array([resid(zi, zhat) for zi in zeta])
            S = (e * wc[:, None]).T @ e + sim.R
            Pxz = ((chi_u - x) * wc[:, None]).T @ e
            K = np.linalg.solve(S, Pxz.T).T
            x = x + K @ resid(z[k], zhat)
            P = P - K @ Pxz.T
            P = 0.5 * (P + P.T)
            A = kfmc.sigma_point_transition(
                chi, chi_f, wm, wc, K=K, sigmas_update=chi_u, sigmas_h=zeta, residual_z=resid
            )
            worst = max(worst, float(np.abs(A - ref_a[k]).max() / np.abs(ref_a[k]).max()))
    assert run["est_theta"].max() > math.pi, "the roll passes π"
    assert worst < 1e-9, worst


DRONE = {
    "name": "py_estimates_drone",
    "master_seed": 11,
    "runs": 3,
    "output": "unused",
    "model": {"kind": "drone"},
    "scenarios": [{"name": "maneuver", "duration_s": 2.0}],
    "filters": [{"label": "ekf9", "kind": "ekf9"}],
    "initial_estimate": {"mode": "sampled"},
    "consistency": {"alpha": 0.05},
}


def test_a_rotation_given_as_a_quaternion_round_trips_the_drones_export(tmp_path, script_kfmc):
    # The drone's filters export nu without S (they update sensor by sensor), which the
    # reader refuses where nu reports: the round trip leaves both out.
    own = export(DRONE, tmp_path, script_kfmc).with_columns(pl.lit("mine").alias("filter"))
    own = own.select([c for c in own.columns if not c.startswith(("nu_", "S_"))])
    sim = kfmc.simulate(with_external(DRONE), out=tmp_path / "sim", quiet=True)
    layout = [
        c for c in kfmc.schema("estimates", with_external(DRONE))["columns"]
        if not c.startswith(("nu_", "S_"))
    ]
    assert layout == own.columns
    quat = [c for c in layout if c.startswith("quat_")]
    assert quat == [f"quat_roll_pitch_yaw_{c}" for c in "wxyz"]
    # The quantities in order: the rotation's three where its quaternion stands.
    est_cols = [c for c in layout if c.startswith(("est_", "quat_"))]
    at = est_cols.index(quat[0])
    quantities = [c[4:] for c in est_cols[:at]] + ["roll", "pitch", "yaw"] + [c[4:] for c in est_cols[at + 4:]]
    n = len(quantities)
    p_cols = [c for c in layout if c.startswith("P_")]
    a_cols = [c for c in layout if c.startswith("A_")]
    tri = [(i, j) for i in range(n) for j in range(i + 1)]
    assert len(p_cols) == len(tri) and len(a_cols) == n * n
    est = kfmc.Estimates(sim, "mine")
    for key, g in own.group_by(KEYS, maintain_order=True):
        g = g.sort("step")
        k1 = g.height
        x = np.full((k1, n), np.nan)  # the rotation's Euler angles: not given
        for i, name in enumerate(quantities):
            if name not in ("roll", "pitch", "yaw"):
                x[:, i] = g[f"est_{name}"].to_numpy()
        P = np.zeros((k1, n, n))
        for (i, j), c in zip(tri, p_cols):
            P[:, i, j] = P[:, j, i] = g[c].to_numpy()
        A = np.stack([g[c].to_numpy().astype(float) for c in a_cols], axis=1).reshape(k1, n, n)
        est.add_run(*key, x=x, P=P, A=A, quat=g.select(quat).to_numpy())
    assert est.columns == own.columns
    assert est.to_polars().equals(own)
    same_tables(
        kfmc.score(sim, est, out=tmp_path / "mem", quiet=True),
        kfmc.score(sim, own, out=tmp_path / "df", quiet=True),
    )
    # Without a quaternion the Euler angles are the estimate: a NaN there is refused.
    with pytest.raises(kfmc.EstimatesError, match="x of run .* nan at step 0, entry"):
        kfmc.Estimates(sim, "mine").add_run(*key, x=x, P=P, A=A)


def test_the_ukf_example_gives_kfmcs_dof_with_the_kept_points_and_fewer_with_sigmas_f(root, tmp_path):
    pytest.importorskip("filterpy")
    import sys

    example = root / "examples" / "python" / "filterpy_ukf_transition.py"
    r = subprocess.run(
        [sys.executable, str(example), "--runs", "10", "--out", str(tmp_path)],
        capture_output=True, text=True,
    )
    assert r.returncode == 0, r.stderr
    assert "A_k from ukf.sigmas_f" in r.stdout
    dof = {}
    for folder in ("kept", "sigmas_f"):
        c = kfmc.Study(tmp_path / folder).table("consistency").filter(pl.col("test") == "nees_time_average")
        dof[folder] = {f: d for f, d in zip(c["filter"], c["dof"])}
    # The kept points give kfmc's KF's effective dof (the UKF is the KF on L1) …
    assert abs(dof["kept"]["filterpy_kf"] - dof["kept"]["kf"]) < 1e-9 * dof["kept"]["kf"]
    # … the redrawn ukf.sigmas_f far fewer: the band is wider than the test's.
    assert dof["sigmas_f"]["filterpy_kf"] < 0.5 * dof["kept"]["kf"]


def test_estimates_of_declared_variants_score_like_the_file_route(tmp_path, script_kfmc):
    """An external filter declaring q_scale = [0.5, 1, 2]: `Estimates.add_run(...,
    q_scale=…)` writes each run's variant, and scoring it in memory gives the tables of the
    same rows written as a file with a `q_scale` column and scored by the CLI."""
    tunings = {"kf_a": 0.5, "kf_b": 1.0, "kf_c": 2.0}
    own_spec = dict(L1, filters=[{"label": l, "kind": "ekf", "q_scale": q} for l, q in tunings.items()])
    own = export(own_spec, tmp_path, script_kfmc)
    spec = dict(L1, filters=[{"label": "kf", "kind": "ekf"},
                             {"label": "mine", "kind": "external", "q_scale": [0.5, 1, 2]}])
    sim = kfmc.simulate(spec, out=tmp_path / "sim", quiet=True)
    assert sim.external_filters == [{"label": "mine", "q_scale": [0.5, 1.0, 2.0]}]
    q, z = sim.model.states, sim.model.measurements
    est = kfmc.Estimates(sim, "mine")
    assert est.variants == {"q_scale": [0.5, 1.0, 2.0]}
    for (label, *key), g in own.group_by(["filter"] + KEYS, maintain_order=True):
        x, P, nu, S, A = arrays(g.sort("step"), q, z)
        est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A, q_scale=tunings[label])
    # The file route: the exported rows relabelled, each naming its variant.
    rows = own.with_columns(
        pl.col("filter").replace_strict(tunings, return_dtype=pl.Float64).alias("q_scale"),
        pl.lit("mine").alias("filter"),
    ).select(est.columns)
    assert est.columns[:6] == ["scenario", "noise_scale", "run", "step", "filter", "q_scale"]
    assert est.to_polars().equals(rows)
    import pyarrow.parquet as pq

    table = rows.to_arrow()
    path = tmp_path / "variants.parquet"
    pq.write_table(table.replace_schema_metadata(sim.stamp), path)
    o = subprocess.run(
        [script_kfmc, "score", str(sim.folder), "--estimates", str(path), "--out", str(tmp_path / "cli"), "-q"],
        capture_output=True, text=True,
    )
    assert o.returncode == 0 and "warning" not in o.stderr, o.stderr
    study = kfmc.score(sim, est, out=tmp_path / "mem", quiet=True)
    same_tables(study, kfmc.Study(tmp_path / "cli"))
    summary = study.table("summary").filter(pl.col("filter") == "mine")
    assert sorted(summary["q_scale"].unique().to_list()) == [0.5, 1.0, 2.0]
    assert summary["r_scale"].unique().to_list() == [1.0]
    # A written file is the same table, stamped.
    written = est.write(tmp_path / "written.parquet")
    assert pl.read_parquet(written).equals(rows)
    # A run must name a declared variant, and only on a declared axis.
    key = ("hover", 1.0, 0)
    x, P, nu, S, A = arrays(own.filter(pl.col("filter") == "kf_a").head(51), q, z)
    fresh = kfmc.Estimates(sim, "mine")
    with pytest.raises(kfmc.EstimatesError, match=r"q_scale: filter 'mine' declares q_scale = 0.5, 1, 2"):
        fresh.add_run(*key, x=x, P=P)
    with pytest.raises(kfmc.EstimatesError, match=r"q_scale=3 is not a variant of filter 'mine'"):
        fresh.add_run(*key, x=x, P=P, q_scale=3)
    with pytest.raises(kfmc.EstimatesError, match=r"r_scale=1.0: filter 'mine' declares no r_scale variants"):
        fresh.add_run(*key, x=x, P=P, q_scale=2, r_scale=1.0)
    fresh.add_run(*key, x=x, P=P, q_scale=2)
    fresh.add_run(*key, x=x, P=P, q_scale=0.5)
    with pytest.raises(kfmc.EstimatesError, match="was added already"):
        fresh.add_run(*key, x=x, P=P, q_scale=2)
    # Two of the three variants: the third is reported missing, as a missing filter is.
    with pytest.raises(kfmc.Error, match=r"no rows for the external filter `mine` \(q_scale = 1\)"):
        kfmc.score(sim, fresh, out=tmp_path / "partial", quiet=True)


@pytest.mark.parametrize("options", [{}, {"covariance": "cholesky", "float32": True}])
def test_estimates_streamed_to_a_path_are_the_file_write_writes(world, tmp_path, monkeypatch, options):
    """With path= the rows go to the file a row group at a time: the file is the one
    write() writes of the whole table, byte for byte; it appears at the path only when
    complete; no more than a row group and a run are held."""
    import filecmp

    import pyarrow.parquet as pq

    sim, own, runs, _ = world
    # Small groups, so that these 32 runs make several.
    monkeypatch.setattr(importlib.import_module("kfmc._estimates"), "_GROUP_VALUES", len(own.columns) * 100)
    whole = build(sim, runs, **options)
    assert whole.buffered_rows == len(whole) == own.height
    whole.write(tmp_path / "whole.parquet")
    target = tmp_path / "streamed.parquet"
    held = []
    with kfmc.Estimates(sim, "mine", path=target, **options) as est:
        for key, (x, P, nu, S, A) in runs:
            est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
            held.append(est.buffered_rows)
            assert not target.exists()
        assert est.rows_per_group == 100
        assert len(est) == own.height
    longest = max(len(a[0]) for _, a in runs)
    assert 0 < max(held) < est.rows_per_group + longest, held
    assert pq.ParquetFile(target).metadata.num_row_groups == math.ceil(own.height / 100)
    assert filecmp.cmp(tmp_path / "whole.parquet", target, shallow=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["streamed.parquet", "whole.parquet"]
    assert est.to_polars().equals(whole.to_polars())
    assert est.write() == target  # closing again is harmless
    with pytest.raises(kfmc.Error, match="closed"):
        est.add_run(*runs[0][0], x=runs[0][1][0], P=runs[0][1][1])


def test_a_stream_has_a_temporary_name_of_its_own_and_a_vanished_one_is_a_kfmc_error(world, tmp_path):
    sim, own, runs, _ = world
    target = tmp_path / "mine.parquet"
    # A user's file with the name an earlier kfmc streamed under is neither used nor removed.
    theirs = tmp_path / ".mine.parquet.partial"
    theirs.write_text("the user's\n")
    est = kfmc.Estimates(sim, "mine", path=target)
    for key, (x, P, nu, S, A) in runs:
        est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
    temporary = [p for p in tmp_path.iterdir() if p.name.endswith(".mine.parquet.partial") and p != theirs]
    assert len(temporary) == 1 and temporary[0].name.startswith(".kfmc-"), temporary
    temporary[0].unlink()
    with pytest.raises(kfmc.Error, match="are gone") as raised:
        est.close()
    assert not isinstance(raised.value, FileNotFoundError)
    assert not target.exists()
    assert theirs.read_text() == "the user's\n"
    est.close()  # closing again is harmless


def test_a_streamed_table_scores_and_an_abandoned_one_leaves_no_file(world, tmp_path, monkeypatch):
    import gc

    sim, own, runs, _ = world
    monkeypatch.setattr(importlib.import_module("kfmc._estimates"), "_GROUP_VALUES", len(own.columns) * 100)
    whole = build(sim, runs)
    # Scoring a streamed table closes it and reads its file.
    est = build(sim, runs, path=tmp_path / "s.parquet")
    same_tables(
        kfmc.score(sim, est, out=tmp_path / "streamed", quiet=True),
        kfmc.score(sim, whole, out=tmp_path / "memory", quiet=True),
    )
    assert (tmp_path / "s.parquet").exists()
    # A loop that fails leaves nothing at the path, nor its temporary file: in a with
    # block, and without one once the object is let go.
    for scoped in (True, False):
        target = tmp_path / f"failed_{scoped}.parquet"
        with pytest.raises(KeyError, match="the filter failed"):
            est = kfmc.Estimates(sim, "mine", path=target)
            with est if scoped else contextlib.nullcontext():
                for i, (key, (x, P, nu, S, A)) in enumerate(runs):
                    if i == len(runs) - 3:
                        assert [p for p in tmp_path.iterdir() if p.name.endswith(f".{target.name}.partial")]
                        raise KeyError("the filter failed")
                    est.add_run(*key, x=x, P=P, nu=nu, S=S, A=A)
        del est
        gc.collect()
        assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".parquet" or p.name.endswith(".partial")) == ["s.parquet"]
