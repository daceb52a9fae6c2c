"""The Python API as a user of the wheel alone meets it: bundled specs, temporary folders,
one spelling of each setting, ordinary Python values, a run's arrays, the rest of the
command, and progress in a log."""

import gc
import inspect
import os
import pathlib
import pydoc
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import polars as pl
import pytest

import kfmc

from test_api import SIGINT_SCRIPT, assert_same_tables, l1_world  # noqa: F401 (fixture)


def small(name: str, runs: int = 4) -> dict:
    """A bundled spec as a dict, with few runs."""
    d = kfmc._kfmc.load_toml(kfmc.examples()[name])
    d["runs"] = runs
    return d


# 1. No clone needed -----------------------------------------------------------------------


def test_the_wheel_carries_every_bundled_spec(root):
    examples = kfmc.examples()
    repo = sorted(p.stem for p in (root / "experiments").glob("*.toml"))
    assert sorted(examples) == repo and len(repo) > 10
    package = pathlib.Path(kfmc.__file__).resolve().parent
    for name, path in examples.items():
        assert path.resolve().is_relative_to(package), path
        assert path.read_bytes() == (root / "experiments" / f"{name}.toml").read_bytes()
    # The guide's first example, from the wheel's copy.
    assert kfmc.validate(examples["ci_consistency"])["experiment"] == "ci_consistency"


def test_a_call_without_out_writes_a_temporary_folder_that_lives_with_its_result(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    study = kfmc.run(small("ci_consistency"), quiet=True)
    folder = study.folder
    assert (folder / "summary.parquet").is_file()
    assert not folder.resolve().is_relative_to(tmp_path.resolve())
    sim = kfmc.simulate(small("ci_consistency"), quiet=True)
    assert sum(1 for _ in sim.runs()) == 2 * 4
    result = kfmc.check(small("ci_consistency"), quiet=True)
    assert result.study.table("summary").height > 0
    table = kfmc.power(small("ci_consistency"), 2, quiet=True)
    assert table.height > 0
    assert list(tmp_path.iterdir()) == [], "nothing is written in the working directory"
    sim_folder, check_folder = sim.folder, result.study.folder
    del study, sim, result
    gc.collect()
    assert not folder.exists() and not sim_folder.exists() and not check_folder.exists()


def test_the_guides_first_example_runs_from_the_wheel_alone(root, tmp_path, monkeypatch, capsys):
    guide = (root / "docs" / "src" / "guide" / "python.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", guide, flags=re.S)
    first = next(b for b in blocks if 'kfmc.examples()["ci_consistency"]' in b)
    monkeypatch.chdir(tmp_path)
    exec(compile(first, "python.md", "exec"), {})
    assert "p_value" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []


def test_resume_without_out_is_a_clear_error():
    with pytest.raises(kfmc.Error, match=r"resume=True .* pass out="):
        kfmc.run(small("ci_consistency"), resume=True, quiet=True)


# 2. One spelling ---------------------------------------------------------------------------


def gate(spec: dict, **check) -> dict:
    spec = dict(spec, check=dict(spec["check"], **check))
    return spec


def test_either_spelling_of_the_gates_settings_is_the_same_gate(tmp_path):
    base = small("ci_consistency", runs=40)
    ref = kfmc.check(gate(base, sequential=True, spending="obrien_fleming", futility_beta=0.2),
                     out=tmp_path / "ref", quiet=True)
    variants = {
        "spec_flag_spelling": (gate(base, sequential=True, spending="obrien-fleming", futility=0.2), {}),
        "keywords_spec_spelling": (base, dict(sequential=True, spending="obrien_fleming", futility_beta=0.2)),
        "keywords_flag_spelling": (base, dict(sequential=True, spending="obrien-fleming", futility=0.2)),
    }
    for name, (spec, keywords) in variants.items():
        r = kfmc.check(spec, out=tmp_path / name, quiet=True, **keywords)
        assert r.exit_code == ref.exit_code, name
        assert_same_tables(ref.study.folder, r.study.folder)
    with pytest.raises(kfmc.SpecError, match="futility and futility_beta"):
        kfmc.check(base, sequential=True, futility=0.2, futility_beta=0.2, quiet=True)


def test_quiet_defaults_the_same_everywhere():
    defaults = {
        f.__name__: inspect.signature(f).parameters["quiet"].default
        for f in (kfmc.run, kfmc.simulate, kfmc.score, kfmc.check, kfmc.power)
    }
    assert set(defaults.values()) == {False}, defaults


def test_messages_name_python_arguments_not_flags(tmp_path):
    text = pathlib.Path(kfmc.examples()["ci_consistency"]).read_text()
    text = text.replace("scales = [1.0]", "scales = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0]")
    text = re.sub(r"^runs = \d+", "runs = 150", text, flags=re.M)
    script = tmp_path / "run.py"
    script.write_text(SIGINT_SCRIPT.format(spec=text))
    out = tmp_path / "interrupted"
    p = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    index = out / ".checkpoint" / "index.toml"
    deadline = time.time() + 120
    while not index.exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert p.poll() is None, "the study ended before a checkpoint: make it longer"
    os.kill(p.pid, signal.SIGINT)
    p.communicate(timeout=120)
    with pytest.raises(kfmc.StudyError) as e:
        kfmc.run(text, out=out, quiet=True)
    message = str(e.value)
    assert "resume=True" in message and "force=True" in message, message
    assert "--restart" not in message and "--resume" not in message, message
    # force=True is Python's word for starting over.
    study = kfmc.run(text, out=out, quiet=True, force=True)
    assert study.report["cells_resumed"] == 0
    with pytest.raises(kfmc.SpecError) as e:
        kfmc.validate(dict(small("ci_consistency"), runs=10**9))
    assert "allow_large=True" in str(e.value) and "--allow-large" not in str(e.value)


# 3. Ordinary Python values -----------------------------------------------------------------


def test_numpy_values_in_a_dict_spec_are_the_numbers_they_hold():
    plain = small("ci_consistency")
    plain["noise"]["scales"] = [0.5, 1.0]
    spec = small("ci_consistency")
    spec["runs"] = np.int64(4)
    spec["master_seed"] = np.uint32(2026)
    spec["noise"]["scales"] = np.array([0.5, 1.0])
    spec["model"]["measurement_noise_std"] = np.float64(0.01)
    spec["filters"][0]["q_scale"] = np.float64(1.0)
    assert kfmc.validate(spec) == kfmc.validate(plain)
    assert kfmc.to_toml(spec) == kfmc.to_toml(plain)


@pytest.mark.parametrize("keyword", ["runs", "seed", "threads"])
def test_a_negative_integer_keyword_is_a_spec_error(keyword):
    with pytest.raises(kfmc.SpecError, match=f"{keyword}=-1"):
        kfmc.run(small("ci_consistency"), quiet=True, **{keyword: -1})


def test_a_dict_specs_errors_name_the_key_path_without_toml_positions():
    spec = small("ci_consistency")
    spec["runs"] = -5
    spec["model"]["process_noise_std"] = "loud"
    for bad in ({**spec}, dict(small("ci_consistency"), runs=-5)):
        with pytest.raises(kfmc.SpecError) as e:
            kfmc.validate(bad)
        assert "runs" in str(e.value) and "<dict>" in str(e.value)
        assert "line " not in str(e.value) and "column" not in str(e.value), str(e.value)


def test_categorical_key_columns_are_accepted(l1_world, tmp_path):  # noqa: F811
    spec, sim, est, base = l1_world
    ref = kfmc.score(sim, est, out=tmp_path / "ref", quiet=True)
    frame = est.to_pandas()
    for c in ("scenario", "filter"):
        frame[c] = frame[c].astype("category")
    pandas = kfmc.score(sim, frame, out=tmp_path / "pandas", quiet=True)
    assert_same_tables(ref.folder, pandas.folder)
    polars = kfmc.score(sim, est.with_columns(pl.col("scenario", "filter").cast(pl.Categorical)),
                        out=tmp_path / "polars", quiet=True)
    assert_same_tables(ref.folder, polars.folder)


# 4. A run's arrays -------------------------------------------------------------------------


def test_a_run_gives_its_arrays_and_unpacks_as_before(l1_world):  # noqa: F811
    spec, sim, est, base = l1_world
    runs = list(sim.runs())
    run = runs[2]
    key, truth, meas, init = run
    assert key == run.key == ("hover", 1.0, 2)
    states = sim.model.states
    assert run.states == states
    n, nz, nu = len(states), len(sim.model.measurements), len(sim.model.inputs)
    assert run.x0.shape == (n,) and run.P0.shape == (n, n) and (run.P0 == run.P0.T).all()
    assert run.x0.tolist() == [init[f"est_{q}"][0] for q in states]
    assert run.P0[3, 1] == init[f"P_{states[3]}_{states[1]}"][0]
    assert run.z.shape == (meas.height, nz) and np.isnan(run.z[0]).all()
    assert run.z[5].tolist() == [meas[f"z_{m}"][5] for m in sim.model.measurements]
    assert run.u.shape == (meas.height, nu)
    assert run.truth.shape == (truth.height, n)
    assert run.truth[7].tolist() == [truth[f"truth_{q}"][7] for q in states]


# 5. The rest of the command ----------------------------------------------------------------


def test_summary_list_plot_report_and_to_toml(kfmc_bin, tmp_path):
    study = kfmc.run(small("ci_consistency"), out=tmp_path / "s", quiet=True)
    printed = subprocess.run([kfmc_bin, "summary", str(study.folder)], capture_output=True,
                             text=True, check=True).stdout
    assert kfmc.summary(study) == study.summary() and kfmc.summary(study).strip() == printed.strip()
    systems = kfmc.list()
    listed = subprocess.run([kfmc_bin, "list"], capture_output=True, text=True, check=True).stdout
    assert systems and all(f"\n{kind} — {s['about']}\n" in listed for kind, s in systems.items())
    assert all(s["sections"] for s in systems.values())
    html = kfmc.report(study)
    assert html == study.folder / "report.html" and html.read_text().startswith("<!DOCTYPE html")
    figures = kfmc.plot(study, out=tmp_path / "figures", format="svg")
    assert figures and all(f.suffix == ".svg" and f.is_file() for f in figures)
    spec = small("planar_ekf_vs_ukf")
    spec["noise"]["scales"] = np.array([1.0, 2.0])
    toml = tmp_path / "spec.toml"
    toml.write_text(kfmc.to_toml(spec))
    assert subprocess.run([kfmc_bin, "validate", str(toml)], capture_output=True).returncode == 0
    assert kfmc.validate(toml)["cells"] == kfmc.validate(spec)["cells"]


def test_help_leads_with_the_api():
    text = pydoc.render_doc(kfmc, renderer=pydoc.plaintext)
    head = text[: text.index("CLASSES")]
    for name in ("run", "simulate", "score", "check", "summary", "examples", "to_toml"):
        assert f":func:`{name}`" in head, name
    assert "exit_code" in pydoc.render_doc(kfmc.CheckResult, renderer=pydoc.plaintext)
    assert "junit" in (kfmc.CheckResult.__doc__ or "")


# 6. Progress in a log ----------------------------------------------------------------------


def test_progress_in_a_log_is_plain_lines(tmp_path):
    log = tmp_path / "stderr.log"
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent(
        """
        import sys, kfmc
        spec = kfmc._kfmc.load_toml(kfmc.examples()["planar_seed_study"])
        kfmc.run(spec, out=sys.argv[1], threads=1)
        """
    ))
    with open(log, "w") as err:
        subprocess.run([sys.executable, str(script), str(tmp_path / "out")], stderr=err, check=True)
    text = log.read_text()
    assert "\r" not in text, text[:500]
    assert re.search(r"^\d+/\d+ runs in [\d.]+ s$", text, flags=re.M), text


# 7. Batches through the model ----------------------------------------------------------------


def test_model_functions_take_a_batch_of_states_row_by_row():
    m = kfmc.model(small("planar_ekf_vs_ukf"))
    n, nu, nz = len(m.states), len(m.inputs), len(m.measurements)
    rng = np.random.default_rng(7)
    xs = rng.normal(size=(9, n))
    u = rng.normal(size=nu)
    us = rng.normal(size=(9, nu))
    assert (m.f(xs, u) == np.array([m.f(x, u) for x in xs])).all()
    assert (m.f(xs, us) == np.array([m.f(x, v) for x, v in zip(xs, us)])).all()
    assert (m.h(xs) == np.array([m.h(x) for x in xs])).all()
    sensor = m.measurements[-1]
    assert (m.h(xs, sensor) == np.array([m.h(x, sensor) for x in xs])).all()
    zs = rng.uniform(-4, 4, size=(9, nz))
    zp = rng.uniform(-4, 4, size=(9, nz))
    assert (m.residual(zs, zp) == np.array([m.residual(a, b) for a, b in zip(zs, zp)])).all()
    assert (m.residual(zs, zp[0]) == np.array([m.residual(a, zp[0]) for a in zs])).all()
    with pytest.raises(kfmc.Error, match=f"or a batch m × {n}"):
        m.f(xs[:, :-1], u)
    with pytest.raises(kfmc.Error, match="beside a batch of 9"):
        m.f(xs, us[:4])
