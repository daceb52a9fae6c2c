"""The Python API against the command: same tables, same errors, same exit codes."""

import filecmp
import math
import os
import pathlib
import re
import signal
import subprocess
import sys
import textwrap
import time

import polars as pl
import pytest

import kfmc


def crate_version(root: pathlib.Path) -> str:
    text = (root / "Cargo.toml").read_text()
    section = text.split("[workspace.package]", 1)[1]
    return re.search(r'^version = "([^"]+)"', section, re.M).group(1)


def parquet_files(folder: pathlib.Path):
    return sorted(p.relative_to(folder) for p in folder.rglob("*.parquet"))


def assert_same_tables(a: pathlib.Path, b: pathlib.Path):
    """Every Parquet table of two folders, byte for byte (kfmc's tables are deterministic)."""
    fa, fb = parquet_files(a), parquet_files(b)
    assert fa and fa == fb
    for rel in fa:
        assert filecmp.cmp(a / rel, b / rel, shallow=False), f"{rel} differs"


def test_version_is_the_crates(root, kfmc_bin, script_kfmc):
    v = crate_version(root)
    assert kfmc.__version__ == v
    out = subprocess.run([script_kfmc, "--version"], capture_output=True, text=True)
    assert out.returncode == 0
    assert out.stdout == f"kfmc {v}\n"
    assert out.stdout == subprocess.run([kfmc_bin, "--version"], capture_output=True, text=True).stdout


def test_the_script_prints_help_and_usage_errors_as_the_binary(kfmc_bin, script_kfmc):
    for args in (["--help"], ["run", "--help"], ["no-such-command"], ["run"], ["run", "x.toml", "--runs", "many"]):
        a = subprocess.run([kfmc_bin, *args], capture_output=True, text=True)
        b = subprocess.run([script_kfmc, *args], capture_output=True, text=True)
        assert (b.returncode, b.stdout, b.stderr) == (a.returncode, a.stdout, a.stderr), args
    assert subprocess.run([script_kfmc, "no-such-command"], capture_output=True).returncode == 2


def test_the_script_returns_the_gates_exit_codes(root, kfmc_bin, script_kfmc, tmp_path):
    spec = root / "experiments" / "ci_consistency.toml"
    # Q × 8: the consistency assertion fails (exit 3), as the command's.
    text = spec.read_text().replace("q_scale = 1.0", "q_scale = 8.0")
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    codes = []
    for exe, out in ((kfmc_bin, "a"), (script_kfmc, "b")):
        r = subprocess.run(
            [exe, "check", str(bad), "--runs", "20", "--out", str(tmp_path / out), "-q"],
            capture_output=True,
            text=True,
        )
        codes.append((r.returncode, r.stdout))
    assert codes[0][0] == 3
    assert codes[0] == codes[1]


def test_run_writes_the_tables_the_command_writes(root, kfmc_bin, tmp_path):
    spec = root / "experiments" / "ci_consistency.toml"
    subprocess.run(
        [kfmc_bin, "run", str(spec), "--out", str(tmp_path / "cli"), "--runs", "12", "--seed", "7", "-q"],
        check=True,
    )
    study = kfmc.run(spec, out=tmp_path / "api", runs=12, seed=7, quiet=True)
    assert study.folder == tmp_path / "api"
    assert_same_tables(tmp_path / "cli", tmp_path / "api")
    assert set(study.tables()) >= {"summary", "runs", "steps", "consistency"}
    assert study.manifest["master_seed"] == 7
    assert study.manifest["runs_per_cell"] == 12
    summary = study.table("summary")
    assert summary.height > 0 and "filter" in summary.columns
    verdict = study.verdict()
    assert verdict.height == 2  # two scenarios × one filter
    assert set(verdict["test"]) == {"verdict"}
    # A spec given as TOML text or as a dict is the same study.
    text = spec.read_text()
    kfmc.run(text, out=tmp_path / "text", runs=12, seed=7, quiet=True)
    assert_same_tables(tmp_path / "cli", tmp_path / "text")


def test_power_with_a_sequential_gate_writes_what_the_command_writes(root, kfmc_bin, tmp_path):
    spec = root / "experiments" / "ci_consistency.toml"
    subprocess.run(
        [kfmc_bin, "power", str(spec), "--out", str(tmp_path / "cli"), "--runs", "20",
         "--seed", "3", "-q", "--replications", "4", "--sequential", "--looks", "5,10,20",
         "--futility", "0.2"],
        check=True,
    )
    table = kfmc.power(spec, 4, out=tmp_path / "api", runs=20, seed=3, quiet=True,
                       sequential=True, looks=[5, 10, 20], futility=0.2)
    assert filecmp.cmp(tmp_path / "cli" / "power.parquet", tmp_path / "api" / "power.parquet",
                       shallow=False)
    gate = table.filter(pl.col("sequential"))
    assert gate.height == 2  # two scenarios × one filter
    assert ((gate["runs_used_mean"] >= 5) & (gate["runs_used_mean"] <= 20)).all()
    with pytest.raises(ValueError, match="sequential=True"):
        kfmc.power(spec, 2, looks=3, quiet=True)
    with pytest.raises(ValueError, match="end at the study's 20 runs"):
        kfmc.power(spec, 2, runs=20, sequential=True, looks=[5, 10], quiet=True,
                   out=tmp_path / "bad")
    with pytest.raises(ValueError, match="spending"):
        kfmc.power(spec, 2, runs=20, sequential=True, spending="haybittle", quiet=True,
                   out=tmp_path / "bad")
    # The library checks the request before any replication, as the command does.
    with pytest.raises(kfmc.SpecError, match="replications: must be at least 1"):
        kfmc.power(spec, 0, runs=20, quiet=True, out=tmp_path / "none")
    assert not (tmp_path / "none").exists()


POWER_SPEC = """
name = "power_target"
master_seed = 5
runs = 20
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[[filters]]
label = "kf"
kind = "ekf"
q_scale = [1.0, 2.0]
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
"""


def test_power_with_a_target_prints_and_writes_what_the_command_does(kfmc_bin, tmp_path, capsys):
    spec = tmp_path / "spec.toml"
    spec.write_text(POWER_SPEC)
    cli = subprocess.run(
        [kfmc_bin, "power", str(spec), "--out", str(tmp_path / "cli"), "-q", "-R", "6",
         "--target-power", "0.8", "--against", "q_scale=2"],
        check=True, capture_output=True, text=True,
    )
    assert "smallest N with power" in cli.stdout or "is not reached" in cli.stdout
    capsys.readouterr()
    table = kfmc.power(spec, 6, out=tmp_path / "api", target_power=0.8, against="q_scale=2")
    assert capsys.readouterr().out == cli.stdout
    assert filecmp.cmp(tmp_path / "cli" / "power.parquet", tmp_path / "api" / "power.parquet",
                       shallow=False)
    assert sorted(set(table["runs"])) == [2, 4, 6, 8, 10, 12, 14, 16, 18, 20]
    # Unanswerable requests are refused before anything runs.
    for kwargs, message in [
        ({"target_power": 0.8}, "go together"),
        ({"target_power": 1.5, "against": "q_scale=2"}, "target_power: must lie in"),
        ({"target_power": 0.8, "against": "q=2"}, "unknown key `q`"),
        ({"target_power": 0.8, "against": "q_scale=3"}, "no filter variant has q_scale=3"),
    ]:
        with pytest.raises(kfmc.SpecError, match=message):
            kfmc.power(spec, 6, out=tmp_path / "bad", quiet=True, **kwargs)
        assert not (tmp_path / "bad").exists()


def test_validate_describe_schema(root):
    spec = root / "experiments" / "linear_nees.toml"
    v = kfmc.validate(spec)
    assert v["cells"] == 1 and v["runs_per_cell"] == 200 and v["runs"] == 200
    assert v["memory_bytes"] > 0 and v["disk_bytes"] > 0
    d = kfmc.describe(spec)
    assert isinstance(d, dict) and d
    s = kfmc.schema("estimates", spec)
    assert list(s["columns"])[:5] == ["scenario", "noise_scale", "run", "step", "filter"]
    assert "kfmc.world_stamp" in s["metadata"]
    with pytest.raises(ValueError):
        kfmc.schema("nope", spec)


L1 = {
    "name": "py_l1",
    "master_seed": 11,
    "runs": 6,
    "output": "unused",
    "model": {"kind": "linear_quadrotor", "sensor": "positions"},
    "scenarios": [{"name": "hover", "x0": [1.0, 0.0, 1.0, 0.0, 1.0, 0.0], "duration_s": 5.0}],
    "filters": [{"label": "kf", "kind": "ekf"}],
    "initial_estimate": {"mode": "sampled", "p0_std": 1.0},
    "consistency": {"alpha": 0.01},
}


def l1_with_external():
    spec = {k: v for k, v in L1.items()}
    spec["filters"] = [{"label": "kf", "kind": "ekf"}, {"label": "mine", "kind": "external"}]
    return spec


@pytest.fixture(scope="module")
def l1_world(tmp_path_factory, script_kfmc):
    """An L1 simulation and, as `mine`, the estimates kfmc's own KF makes on its runs
    (`kfmc run --export-estimates`, relabelled): an outside filter known to equal kfmc's."""
    base = tmp_path_factory.mktemp("l1")
    spec = l1_with_external()
    sim = kfmc.simulate(spec, out=base / "sim", quiet=True)
    own = base / "own.toml"
    own.write_text(dict_to_toml(L1))
    subprocess.run(
        [script_kfmc, "run", str(own), "--out", str(base / "own"), "--export-estimates", "-q"],
        check=True,
    )
    est = pl.read_parquet(base / "own" / "estimates.parquet").with_columns(
        pl.lit("mine").alias("filter")
    )
    return spec, sim, est, base


def dict_to_toml(d):
    """The few shapes the test specs use (flat tables, arrays of tables, scalars, lists)."""

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)

    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append((f"[{k}]", v))
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            tables.extend((f"[[{k}]]", x) for x in v)
        else:
            lines.append(f"{k} = {val(v)}")
    for head, t in tables:
        lines.append(head)
        lines.extend(f"{k} = {val(v)}" for k, v in t.items())
    return "\n".join(lines) + "\n"


def test_simulation_reads_and_iterates_runs(l1_world):
    spec, sim, est, base = l1_world
    assert sim.truth.height == 6 * 51 and sim.measurements.height == 6 * 51
    assert sim.initial.height == 6
    runs = list(sim.runs())
    assert len(runs) == 6
    (key, truth, meas, init) = runs[2]
    assert key == ("hover", 1.0, 2)
    assert truth.height == 51 and meas.height == 51 and init.height == 1
    assert truth["step"].to_list() == list(range(51))
    assert truth.equals(sim.truth.filter((pl.col("run") == 2)))


def test_score_from_memory_equals_score_from_a_file(l1_world, kfmc_bin, tmp_path):
    spec, sim, est, base = l1_world
    stamp = kfmc.schema("estimates", spec)["metadata"]
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = est.to_arrow().replace_schema_metadata(stamp)
    pq.write_table(table, tmp_path / "mine.parquet")
    subprocess.run(
        [kfmc_bin, "score", str(sim.folder), "--estimates", str(tmp_path / "mine.parquet"),
         "--out", str(tmp_path / "files"), "-q"],
        check=True,
    )
    for name, estimates in (
        ("polars", est),
        ("arrow", est.to_arrow()),
        ("pandas", est.to_pandas()),
        ("batches", [est.slice(0, 100), est.slice(100)]),
        ("path", tmp_path / "mine.parquet"),
    ):
        study = kfmc.score(sim, estimates, out=tmp_path / name, quiet=True)
        assert_same_tables(tmp_path / "files", study.folder)
    # The outside filter is kfmc's own KF: its RMSE equals kf's to 1e-12 relative.
    s = study.table("summary")
    mine = s.filter(pl.col("filter") == "mine").sort("state")["rmse_mean"].to_numpy()
    kf = s.filter(pl.col("filter") == "kf").sort("state")["rmse_mean"].to_numpy()
    assert len(mine) == len(kf) > 0
    assert (abs(mine - kf) <= 1e-12 * abs(kf)).all()


def test_a_generator_of_runs_is_read_one_run_at_a_time(l1_world, tmp_path):
    """A filter loop that yields each run's estimates is scored as the whole table is, and
    each yielded table is let go before the next is asked for (a list would hold them all:
    10,000 runs of estimates do not fit where one does)."""
    import gc
    import weakref

    spec, sim, est, base = l1_world
    whole = kfmc.score(sim, est, out=tmp_path / "whole", quiet=True)
    runs = est["run"].unique().sort().to_list()
    assert len(runs) > 2
    previous = []
    alive_when_asked = []

    def per_run():
        for r in runs:
            gc.collect()
            alive_when_asked.append(any(p() is not None for p in previous))
            part = est.filter(pl.col("run") == r)
            previous.append(weakref.ref(part))
            yield part
            del part

    study = kfmc.score(sim, per_run(), out=tmp_path / "lazy", quiet=True)
    assert_same_tables(whole.folder, study.folder)
    assert alive_when_asked == [False] * len(runs), alive_when_asked
    # An exception of the generator reaches the caller as it is.
    def broken():
        yield est.filter(pl.col("run") == runs[0])
        raise KeyError("the user's loop failed")

    with pytest.raises(KeyError, match="the user's loop failed"):
        kfmc.score(sim, broken(), out=tmp_path / "broken", quiet=True)


@pytest.mark.parametrize(
    "column",
    ["est_x", "step", "P_x_x"],
)
def test_bad_estimates_name_the_column(l1_world, tmp_path, column):
    spec, sim, est, base = l1_world
    names = [c for c in est.columns if c.startswith("est_")]
    column = {"est_x": names[0], "step": "step", "P_x_x": [c for c in est.columns if c.startswith("P_")][0]}[column]
    with pytest.raises(kfmc.EstimatesError, match=re.escape(f"`{column}`")) as e:
        kfmc.score(sim, est.drop(column), out=tmp_path / "o", quiet=True)
    # A table in memory is read as it is, with no file: the message names it by position.
    assert "<estimates 0>" in str(e.value), str(e.value)
    # A key of the wrong type is named too.
    with pytest.raises(kfmc.EstimatesError, match="`step`"):
        kfmc.score(sim, est.with_columns(pl.col("step").cast(pl.Float64)), out=tmp_path / "p", quiet=True)


def spec_with(path, value):
    """L1 with `value` set at the dotted key `path` (a list index as an integer)."""
    import copy

    d = copy.deepcopy(L1)
    keys = path.split(".")
    node = d
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value
    return d


BAD_SPECS = [
    # (what, spec, the key path the message must name)
    ("a wrong type", spec_with("runs", "many"), "runs"),
    ("an out-of-range run count", spec_with("runs", 0), "runs"),
    ("a negative seed", spec_with("master_seed", -1), "master_seed"),
    ("an unknown top-level key", spec_with("colour", "red"), "colour"),
    ("an unknown model", spec_with("model.kind", "submarine"), "model.kind"),
    ("an unknown sensor", spec_with("model.sensor", "sonar"), "model.sensor"),
    ("a negative duration", spec_with("scenarios.0.duration_s", -1.0), "scenarios[0].duration_s"),
    ("an unknown filter kind", spec_with("filters.0.kind", "magic"), "filters[0].kind"),
    ("a negative prior std", spec_with("initial_estimate.p0_std", -1.0), "initial_estimate.p0_std"),
    ("alpha outside (0, 1)", spec_with("consistency.alpha", 2.0), "consistency.alpha"),
    ("an unknown key in a table", spec_with("consistency.alhpa", 0.1), "consistency.alhpa"),
    ("x0 of the wrong length", spec_with("scenarios.0.x0", [1.0, 2.0]), "scenarios[0].x0"),
]


@pytest.mark.parametrize("what,spec,key", BAD_SPECS, ids=[b[0] for b in BAD_SPECS])
def test_bad_specs_raise_spec_error_naming_the_key_path(what, spec, key, tmp_path):
    with pytest.raises(kfmc.SpecError) as e:
        kfmc.run(spec, out=tmp_path / "o", quiet=True)
    assert key in str(e.value), str(e.value)
    assert isinstance(e.value, kfmc.Error) and isinstance(e.value, ValueError)
    # The same spec as a TOML file: the message names the file too, as the command's does.
    path = tmp_path / "bad.toml"
    path.write_text(dict_to_toml(spec))
    with pytest.raises(kfmc.SpecError) as e:
        kfmc.validate(path)
    assert str(path) in str(e.value) and key in str(e.value)


def test_a_missing_spec_file_and_bad_toml_are_spec_errors(tmp_path):
    with pytest.raises(kfmc.SpecError, match="nope.toml"):
        kfmc.validate(tmp_path / "nope.toml")
    with pytest.raises(kfmc.SpecError):
        kfmc.validate("name = \nruns = [\n")


def test_a_folder_of_another_kind_is_a_study_error(l1_world, tmp_path):
    spec, sim, est, base = l1_world
    with pytest.raises(kfmc.StudyError):
        kfmc.score(tmp_path, est, quiet=True)
    # run into a simulation's folder: another kind of result.
    with pytest.raises(kfmc.StudyError):
        kfmc.run(L1, out=sim.folder, quiet=True)


def test_check_returns_the_gates_result(root, kfmc_bin, tmp_path):
    spec = root / "experiments" / "ci_consistency.toml"
    r = kfmc.check(spec, runs=20, out=tmp_path / "ok")
    cli = subprocess.run(
        [kfmc_bin, "check", str(spec), "--runs", "20", "--out", str(tmp_path / "cli"),
         "--junit", str(tmp_path / "cli.xml"), "-q"],
        capture_output=True, text=True,
    )
    assert r.exit_code == cli.returncode
    assert r.report == cli.stdout
    assert r.ok == (cli.returncode == 0)
    # The JUnit XML differs from the command's only in the measured time.
    strip = lambda s: re.sub(r'time="[^"]*"', "", s)
    assert strip(r.junit) == strip((tmp_path / "cli.xml").read_text())
    bad = kfmc.check(spec.read_text().replace("q_scale = 1.0", "q_scale = 8.0"), runs=20, out=tmp_path / "bad")
    assert bad.exit_code == 3 and not bad.ok and bad.failures
    with pytest.raises(kfmc.CheckFailedError):
        bad.raise_for_status()


def test_check_with_a_sequential_gate_equals_the_command(root, kfmc_bin, tmp_path):
    """kfmc.check(..., sequential=True, looks=…, spending=…, futility=…, futility_rho=…)
    runs the gate `kfmc check --sequential --looks … --futility …` runs: the same exit code,
    report and sequential.parquet bytes, for a tuned filter and a mistuned one that the gate
    stops at its first look; a gate setting without the gate, or one that makes no gate for
    the study's runs, is the command's exit 2 as kfmc.SpecError."""
    tuned = (root / "experiments" / "ci_consistency.toml").read_text()
    mistuned = tuned.replace("q_scale = 1.0", "q_scale = 8.0")
    for name, text, flags, kwargs in [
        ("tuned", tuned,
         ["--looks", "10,20,40", "--futility", "0.2", "--futility-rho", "1"],
         dict(looks=[10, 20, 40], futility=0.2, futility_rho=1.0)),
        ("mistuned", mistuned, ["--looks", "4", "--spending", "pocock"],
         dict(looks=4, spending="pocock")),
    ]:
        spec = tmp_path / f"{name}.toml"
        spec.write_text(text)
        cli = subprocess.run(
            [kfmc_bin, "check", str(spec), "--runs", "40", "--seed", "3", "--out",
             str(tmp_path / f"{name}_cli"), "-q", "--sequential", *flags],
            capture_output=True, text=True,
        )
        r = kfmc.check(text, runs=40, seed=3, out=tmp_path / f"{name}_api", sequential=True, **kwargs)
        assert r.exit_code == cli.returncode, cli.stderr
        assert r.report == cli.stdout
        assert filecmp.cmp(tmp_path / f"{name}_cli" / "sequential.parquet",
                           tmp_path / f"{name}_api" / "sequential.parquet", shallow=False)
        looks = r.study.table("sequential")
        if name == "tuned":
            assert r.exit_code == 0 and looks["runs"].to_list() == [10, 20, 40] * 2
        else:
            assert r.exit_code == 3 and looks["runs"].to_list() == [10, 10]
            assert looks["decision"].to_list() == ["reject", "reject"]
    # Without the gate, none of its settings; settings the study cannot take name their key.
    spec = root / "experiments" / "ci_consistency.toml"
    for kwargs, flags, message in [
        (dict(looks=3), ["--looks", "3"], "looks is a setting of the sequential gate: pass sequential=True"),
        (dict(futility=0.2), ["--futility", "0.2"], "futility is a setting of the sequential gate"),
        (dict(sequential=True, futility=2.0), ["--sequential", "--futility", "2"],
         r"check.futility_beta: β must lie in \(0, 1\); got 2"),
        (dict(sequential=True, looks=[5, 30]), ["--sequential", "--looks", "5,30"],
         "check.looks: the run counts must be ≥ 2, increase and end at the study's 20 runs"),
    ]:
        cli = subprocess.run(
            [kfmc_bin, "check", str(spec), "--runs", "20", "--out", str(tmp_path / "bad_cli"), "-q", *flags],
            capture_output=True, text=True,
        )
        assert cli.returncode == 2, cli.stderr
        with pytest.raises(kfmc.SpecError, match=message):
            kfmc.check(spec, runs=20, out=tmp_path / "bad_api", **kwargs)
    with pytest.raises(kfmc.SpecError, match="futility_rho .* pass futility"):
        kfmc.check(spec, runs=20, out=tmp_path / "bad_api", sequential=True, futility_rho=1.0)
    with pytest.raises(kfmc.SpecError, match="spending: `haybittle`"):
        kfmc.check(spec, runs=20, out=tmp_path / "bad_api", sequential=True, spending="haybittle")


SIGINT_SCRIPT = textwrap.dedent(
    """
    import sys, kfmc
    spec = {spec!r}
    print("started", flush=True)
    kfmc.run(spec, out=sys.argv[1], quiet=True, checkpoint_every=0.0, threads=1)
    print("finished", flush=True)
    """
)


def test_sigint_during_run_leaves_a_resumable_folder(root, tmp_path):
    spec = str(root / "experiments" / "ci_consistency.toml")
    d = {"runs": 150}
    script = tmp_path / "run.py"
    # Many cells (noise scales), each checkpointed, so the interrupt lands between cells.
    text = pathlib.Path(spec).read_text().replace("scales = [1.0]", "scales = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0]")
    text = re.sub(r"^runs = \d+", f"runs = {d['runs']}", text, flags=re.M)
    script.write_text(SIGINT_SCRIPT.format(spec=text))
    out = tmp_path / "interrupted"
    p = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    index = out / ".checkpoint" / "index.toml"
    deadline = time.time() + 120
    while not index.exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, "the study ended before a checkpoint: make it longer"
    os.kill(p.pid, signal.SIGINT)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode != 0
    assert "KeyboardInterrupt" in stderr and "finished" not in stdout
    assert not (out / "summary.parquet").exists(), "nothing is committed"
    resumed = kfmc.run(text, out=out, quiet=True, resume=True)
    assert resumed.report["cells_resumed"] > 0
    whole = kfmc.run(text, out=tmp_path / "whole", quiet=True)
    assert_same_tables(tmp_path / "whole", out)


def test_the_wheel_installs_and_runs_without_a_compiler(tmp_path):
    wheel = os.environ.get("KFMC_WHEEL")
    if not wheel:
        pytest.skip("KFMC_WHEEL names the wheel to install (set by .ci/run)")
    venv = tmp_path / "venv"
    # The system's site packages give polars (the wheel's dependency) without a download.
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    path = os.pathsep.join(
        p for p in os.environ["PATH"].split(os.pathsep)
        if not (pathlib.Path(p) / "cargo").exists() and not (pathlib.Path(p) / "rustc").exists()
    )
    env = dict(os.environ, PATH=f"{venv / 'bin'}{os.pathsep}{path}")
    for tool in ("cargo", "rustc", "cc", "gcc"):
        env.pop(tool.upper(), None)
    check = subprocess.run(["sh", "-c", "command -v cargo || command -v rustc || true"], env=env, capture_output=True, text=True)
    assert check.stdout.strip() == "", "cargo or rustc still on PATH"
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--no-index", "--no-deps", "--quiet", wheel], env=env, check=True)
    r = subprocess.run(["kfmc", "--version"], env=env, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("kfmc ")
    r = subprocess.run([str(venv / "bin" / "python"), "-c", "import kfmc; print(kfmc.__version__)"], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def l1_long_world(tmp_path_factory, script_kfmc):
    """`l1_world` with 100 runs: 5,100 rows, more than the reader checks at once (4,096),
    so a table of one batch is read in several blocks."""
    base = tmp_path_factory.mktemp("l1_long")
    spec = dict(l1_with_external(), runs=100)
    sim = kfmc.simulate(spec, out=base / "sim", quiet=True)
    own = base / "own.toml"
    own.write_text(dict_to_toml(dict(L1, runs=100)))
    subprocess.run(
        [script_kfmc, "run", str(own), "--out", str(base / "own"), "--export-estimates", "-q"],
        check=True,
    )
    est = pl.read_parquet(base / "own" / "estimates.parquet").with_columns(
        pl.lit("mine").alias("filter")
    )
    table = est.to_arrow().replace_schema_metadata(kfmc.schema("estimates", spec)["metadata"])
    import pyarrow.parquet as pq

    pq.write_table(table, base / "mine.parquet")
    files = kfmc.score(sim, base / "mine.parquet", out=base / "files", quiet=True)
    return sim, pl.read_parquet(base / "mine.parquet").rechunk(), files.folder


def test_a_chunked_dataframe_is_read_chunk_by_chunk_and_left_as_it_is(l1_long_world, tmp_path):
    """A polars DataFrame of several chunks (what read_parquet gives, one per row group) is
    handed over chunk by chunk: polars' own export would first copy it into one chunk (a
    second copy of the caller's table, and the caller's frame rechunked in place)."""
    sim, est, files = l1_long_world
    assert est.height > 4096
    chunked = pl.concat([est.slice(0, 1000), est.slice(1000, 3500), est.slice(4500)], rechunk=False)
    assert chunked.n_chunks("all") == [3] * chunked.width
    study = kfmc.score(sim, chunked, out=tmp_path / "chunked", quiet=True)
    assert_same_tables(files, study.folder)
    assert chunked.n_chunks("all") == [3] * chunked.width
    # One batch of all the rows, read block by block, and a chunk of another layout.
    assert est.n_chunks() == 1
    assert_same_tables(files, kfmc.score(sim, est, out=tmp_path / "one", quiet=True).folder)
    unaligned = chunked.with_columns(chunked.get_column("step").rechunk(), pl.lit("mine").alias("filter"))
    assert unaligned.get_column("step").n_chunks() == 1
    assert_same_tables(files, kfmc.score(sim, unaligned, out=tmp_path / "unaligned", quiet=True).folder)
    assert unaligned.get_column("run").n_chunks() == 3


def test_trouble_past_the_first_block_is_named_at_its_row(l1_long_world, tmp_path):
    sim, est, files = l1_long_world
    at = 4500
    row = est.row(at, named=True)
    key = (
        f'scenario = "{row["scenario"]}", noise_scale = {row["noise_scale"]:g}, '
        f'run = {row["run"]}, step = {row["step"]}, filter = "mine"'
    )
    idx = pl.int_range(pl.len())
    cases = [
        (est.with_columns(pl.when(idx == at).then(None).otherwise(pl.col("filter")).alias("filter")),
         f"column `filter`: null at row {at}"),
        (est.with_columns(pl.when(idx == at).then(float("nan")).otherwise(pl.col("nu_x")).alias("nu_x")),
         f"column `nu_x`: NaN at {key} (null means not given"),
        (est.with_columns(pl.when(idx == at).then(None).otherwise(pl.col("A_x_y")).alias("A_x_y")),
         f"column `A_x_y`: null at {key} where the row gives 35 other A_ entries"),
        (pl.concat([est, est.slice(at, 1)]), f"duplicate row {key}"),
    ]
    for i, (bad, message) in enumerate(cases):
        with pytest.raises(kfmc.EstimatesError) as e:
            kfmc.score(sim, bad.rechunk(), out=tmp_path / f"bad{i}", quiet=True)
        assert message in str(e.value), str(e.value)


def test_a_stream_of_batches_is_read_one_batch_at_a_time(l1_long_world, tmp_path):
    """A producer that makes its batches as they are asked for (a pyarrow RecordBatchReader,
    as a dataset scanner or a database query gives) is read batch by batch, each let go before
    the next is made: the rows never all sit in memory at once."""
    import pyarrow as pa

    sim, est, files = l1_long_world
    table = est.to_arrow()
    size = 500
    held = []

    def batches():
        for at in range(0, table.num_rows, size):
            held.append(pa.total_allocated_bytes())
            # A fresh copy in pyarrow's memory pool, as a scanner makes each batch.
            part = table.slice(at, size)
            yield part.take(pa.array(range(part.num_rows))).combine_chunks().to_batches()[0]

    reader = pa.RecordBatchReader.from_batches(table.schema, batches())
    study = kfmc.score(sim, reader, out=tmp_path / "stream", quiet=True)
    assert_same_tables(files, study.folder)
    batch_bytes = table.slice(0, size).nbytes
    assert len(held) == math.ceil(table.num_rows / size) > 3
    assert max(held) - held[0] < 3 * batch_bytes, (held, batch_bytes)


def test_more_looks_than_the_limit_raise_spec_error_at_once(root, tmp_path):
    """A count of 10¹² looks is refused before it is expanded into 10¹² run counts, with the
    message of the command and the spec's key; so is a list of 101 looks."""
    spec = root / "experiments" / "ci_consistency.toml"
    message = re.escape("1000000000000 looks are more than a gate may take (at most 100)")
    started = time.time()
    with pytest.raises(kfmc.SpecError, match=message):
        kfmc.check(spec, runs=1000, out=tmp_path / "c", quiet=True, sequential=True, looks=10**12)
    with pytest.raises(kfmc.SpecError, match=message):
        kfmc.power(spec, 2, runs=1000, out=tmp_path / "p", quiet=True, sequential=True,
                   looks=10**12)
    with pytest.raises(kfmc.SpecError, match="101 looks are more than a gate may take"):
        kfmc.check(spec, runs=1010, out=tmp_path / "c", quiet=True, sequential=True,
                   looks=[10 * k for k in range(1, 102)])
    assert time.time() - started < 30
    assert not (tmp_path / "c").exists() and not (tmp_path / "p").exists()


DEEP_SCRIPT = textwrap.dedent(
    """
    import sys, kfmc
    spec = {spec!r}
    looped = dict(spec)
    looped["model"] = dict(spec["model"])
    looped["model"]["again"] = looped
    deep = dict(spec)
    cur = deep["nested"] = {{}}
    for _ in range(20000):
        cur["a"] = {{}}
        cur = cur["a"]
    listed = dict(spec)
    lst = []
    lst.append(lst)
    listed["items"] = lst
    for name, d in (("looped", looped), ("deep", deep), ("listed", listed)):
        try:
            kfmc.validate(d)
            print(name, "accepted")
        except kfmc.SpecError as e:
            print(name, "SpecError", str(e)[:60], "…", str(e)[-80:])
    """
)


def test_a_spec_dict_that_contains_itself_or_nests_deep_raises_spec_error(tmp_path):
    """In a child process, as an unbounded recursion would overflow the stack and kill it."""
    script = tmp_path / "deep.py"
    script.write_text(DEEP_SCRIPT.format(spec=L1))
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, (p.returncode, p.stderr[-2000:])
    lines = dict(line.split(" ", 1) for line in p.stdout.splitlines())
    depth = "nested more than 64 tables or arrays deep"
    assert lines["looped"].startswith("SpecError <dict>: model.again.model.again."), lines
    assert lines["deep"].startswith("SpecError <dict>: nested.a.a.a."), lines
    assert lines["listed"].startswith("SpecError <dict>: items[0][0][0]"), lines
    for line in lines.values():
        assert depth in line, line


def test_estimates_of_other_types_raise_estimates_error_naming_the_column(l1_world, tmp_path, capfd):
    """Decimal and map columns (which polars cannot hold) and bool, integer or string values
    (which a conversion would score) are refused naming the column, never a Rust panic."""
    import decimal

    import pyarrow as pa

    spec, sim, est, base = l1_world
    n = est.height
    table = est.to_arrow()

    def replaced(column, values):
        return table.set_column(table.schema.get_field_index(column), column, values)

    cases = [
        ("est_x", replaced("est_x", pa.array([decimal.Decimal("1.5")] * n, pa.decimal128(10, 3))),
         "decimal(10, 3)"),
        ("P_x_x", replaced("P_x_x", pa.array([[("a", 1.0)]] * n, pa.map_(pa.string(), pa.float64()))),
         "map"),
        ("noise_scale", replaced("noise_scale", pa.array([decimal.Decimal("1")] * n, pa.decimal128(5, 0))),
         "decimal(5, 0)"),
        ("est_y", est.with_columns(pl.lit(True).alias("est_y")), "bool"),
        ("est_z", est.with_columns(pl.lit(1, dtype=pl.Int64).alias("est_z")), "int64"),
        ("est_xdot", est.with_columns(pl.lit("0.5").alias("est_xdot")), "string"),
    ]
    for column, estimates, type_name in cases:
        with pytest.raises(kfmc.EstimatesError) as e:
            kfmc.score(sim, estimates, out=tmp_path / column, quiet=True)
        assert f"column `{column}` holds " in str(e.value) and type_name in str(e.value), str(e.value)
        assert not (tmp_path / column).exists()
    assert "panicked" not in capfd.readouterr().err


COMMITTED_SCRIPT = textwrap.dedent(
    """
    import os, pathlib, signal, sys, threading, time, kfmc
    spec = {spec!r}
    out = pathlib.Path(sys.argv[1])
    sent = []

    def interrupt_while_running():
        # The study runs in one window, which a stop request cannot cut short: a Ctrl-C
        # while it runs comes too late to stop it, and it commits.
        while not (out / ".kfmc.lock").exists():
            time.sleep(0.0002)
        os.kill(os.getpid(), signal.SIGINT)
        sent.append(time.time())

    threading.Thread(target=interrupt_while_running, daemon=True).start()
    try:
        r = kfmc.run(spec, out=out, quiet=True, threads=1, checkpoint_every=0.0)
    except KeyboardInterrupt:
        print("interrupted", bool(sent), flush=True)
        sys.exit(3)
    print("returned", bool(sent), r.report["runs"], flush=True)
    """
)


def test_a_ctrl_c_that_comes_too_late_to_stop_the_study_does_not_raise(root, tmp_path):
    text = (root / "experiments" / "ci_consistency.toml").read_text()
    text = re.sub(r"^runs = \d+", "runs = 32", text, flags=re.M).replace("duration_s = 5.0", "duration_s = 10.0")
    script = tmp_path / "late.py"
    script.write_text(COMMITTED_SCRIPT.format(spec=text))
    out = tmp_path / "committed"
    p = subprocess.run([sys.executable, str(script), str(out)], capture_output=True, text=True, timeout=300)
    committed = (out / "manifest.toml").exists()
    assert p.stdout.split()[:2] == ["returned", "True"], (p.stdout, p.stderr[-2000:])
    assert p.returncode == 0 and committed
    assert "KeyboardInterrupt" not in p.stderr


SIGTERM_SCRIPT = textwrap.dedent(
    """
    import sys, kfmc
    spec = {spec!r}
    print("started", flush=True)
    kfmc.run(spec, out=sys.argv[1], quiet=True, checkpoint_every=0.0, threads=1)
    print("finished", flush=True)
    """
)


def test_sigterm_stops_a_run_like_ctrl_c_then_ends_the_process(root, tmp_path):
    """SIGTERM during kfmc.run: the study stops at its next window with a final checkpoint
    and no partial file, then the process ends by SIGTERM; resume=True completes it."""
    spec = str(root / "experiments" / "ci_consistency.toml")
    text = pathlib.Path(spec).read_text().replace("scales = [1.0]", "scales = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0]")
    text = re.sub(r"^runs = \d+", "runs = 150", text, flags=re.M)
    script = tmp_path / "term.py"
    script.write_text(SIGTERM_SCRIPT.format(spec=text))
    out = tmp_path / "terminated"
    p = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    index = out / ".checkpoint" / "index.toml"
    deadline = time.time() + 120
    while not index.exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, "the study ended before a checkpoint: make it longer"
    os.kill(p.pid, signal.SIGTERM)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == -signal.SIGTERM, (p.returncode, stderr[-2000:])
    assert "finished" not in stdout
    left = [q.name for q in out.rglob("*") if q.name.endswith(".partial")]
    assert left == [], left
    assert not (out / "manifest.toml").exists(), "nothing is committed"
    assert index.exists(), "the final checkpoint is kept"
    resumed = kfmc.run(text, out=out, quiet=True, resume=True)
    assert resumed.report["cells_resumed"] > 0
    whole = kfmc.run(text, out=tmp_path / "whole", quiet=True)
    assert_same_tables(tmp_path / "whole", out)
