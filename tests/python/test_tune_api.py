"""`kfmc.tune` against the command it wraps: the same spec and seed give the same tables as
`kfmc tune` (both methods), its keywords are checked with errors naming Python's arguments,
and the temporary folder of a call without `out=` lives as long as the result.

The correctness of the ml estimate itself is tested against statsmodels in test_tune_ml.py.
"""

import gc
import subprocess

import pytest

kfmc = pytest.importorskip("kfmc")
pl = pytest.importorskip("polars")


def _cli(kfmc_bin, *args):
    out = subprocess.run([kfmc_bin, *args], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out


def _frames_equal(a, b):
    assert a.columns == b.columns
    assert a.equals(b), f"{a}\n!=\n{b}"


def test_ml_equals_the_command(tmp_path, kfmc_bin):
    spec = kfmc.examples()["tune_ml_cv"]
    _cli(kfmc_bin, "tune", str(spec), "--quiet", "--out", str(tmp_path / "cli"))
    result = kfmc.tune(spec, quiet=True, out=tmp_path / "py")
    assert result.method == "ml"
    cli_table = pl.read_parquet(tmp_path / "cli" / "tuned.parquet")
    _frames_equal(result.table, cli_table)
    _frames_equal(result.trace, pl.read_parquet(tmp_path / "cli" / "tune_trace.parquet"))
    assert result.tuned_toml == (tmp_path / "cli" / "tuned.toml").read_text()
    d = result.details
    assert d["runs"] == 4 and d["converged"] is True
    assert d["measurements"] > 0 and d["not_identified"] == []
    # −ln L at the optimum is at most its value at the search's start (the spec's values).
    trace = result.trace
    assert d["objective"] <= trace.filter(pl.col("iteration") == 0)["objective"].min() + 1e-9


def test_ml_elements_keyword_wins_over_the_spec(tmp_path, kfmc_bin):
    spec = kfmc.examples()["tune_ml_cv"]
    elements = ["q[vx,vx]", "r[zx,zx]"]
    _cli(kfmc_bin, "tune", str(spec), "--quiet", "--out", str(tmp_path / "cli"), "--elements", *elements)
    result = kfmc.tune(spec, elements=elements, quiet=True, out=tmp_path / "py")
    assert result.table.height == 2
    _frames_equal(result.table, pl.read_parquet(tmp_path / "cli" / "tuned.parquet"))


def test_consistency_equals_the_command(tmp_path, kfmc_bin):
    spec = kfmc.examples()["ci_consistency"]
    _cli(kfmc_bin, "tune", str(spec), "--method", "consistency", "--runs", "4", "--quiet", "--out", str(tmp_path / "cli"))
    result = kfmc.tune(spec, method="consistency", runs=4, quiet=True, out=tmp_path / "py")
    assert result.method == "consistency"
    cli_table = pl.read_parquet(tmp_path / "cli" / "tuning.parquet")
    _frames_equal(result.table, cli_table)
    d = result.details
    # The reported best is the candidate with the smallest mean objective over the cells.
    means = cli_table.group_by(["q_scale", "r_scale"]).agg(pl.col("objective").mean()).sort("objective")
    assert (d["q_scale"], d["r_scale"]) == (means["q_scale"][0], means["r_scale"][0])
    assert d["objective"] == pytest.approx(means["objective"][0], rel=1e-12)
    with pytest.raises(kfmc.StudyError, match="no iteration trace"):
        result.trace


def test_keywords_are_checked_and_named(tmp_path):
    spec = kfmc.examples()["tune_ml_cv"]
    with pytest.raises(kfmc.SpecError, match="method=\"truthy\""):
        kfmc.tune(spec, method="truthy", quiet=True)
    with pytest.raises(kfmc.SpecError, match="objective=\"fast\""):
        kfmc.tune(spec, objective="fast", quiet=True)
    with pytest.raises(kfmc.SpecError, match="elements= and measurements= belong to the ml method"):
        kfmc.tune(spec, method="consistency", elements=["q[vx,vx]"], quiet=True)
    with pytest.raises(kfmc.SpecError, match="tune_r= and filter= belong to the consistency method"):
        kfmc.tune(spec, tune_r=True, quiet=True)
    with pytest.raises(kfmc.SpecError) as bad:
        kfmc.tune(spec, elements=["q[vx,vx]", "q[nope,nope]"], quiet=True, out=tmp_path / "bad")
    message = str(bad.value)
    assert "elements[1]" in message and "--elements" not in message
    with pytest.raises(kfmc.SpecError, match="runs=-1"):
        kfmc.tune(spec, runs=-1, quiet=True)


def test_a_call_without_out_writes_a_temporary_folder_the_result_holds(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = kfmc.tune(kfmc.examples()["tune_ml_cv"], quiet=True)
    folder = result.folder
    assert (folder / "tuned.parquet").is_file()
    assert list(tmp_path.iterdir()) == [], "nothing is written in the working directory"
    del result
    gc.collect()
    assert not folder.exists()


def test_the_tuning_chapters_python_example_runs(root, tmp_path, monkeypatch, capsys):
    import re

    page = (root / "docs" / "src" / "statistics" / "tuning.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", page, flags=re.S) if "kfmc.tune(" in b)
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "tuning.md", "exec"), {})
    printed = capsys.readouterr().out
    assert "q[vx,vx]" in printed.lower() and "[model]" in printed
    assert list(tmp_path.iterdir()) == []


def test_truth_equals_the_command(tmp_path, kfmc_bin):
    spec = kfmc.examples()["tune_truth_cv"]
    _cli(kfmc_bin, "tune", str(spec), "--quiet", "--out", str(tmp_path / "cli"))
    result = kfmc.tune(spec, quiet=True, out=tmp_path / "py")
    assert result.method == "truth"
    _frames_equal(result.table, pl.read_parquet(tmp_path / "cli" / "tuned.parquet"))
    _frames_equal(result.trace, pl.read_parquet(tmp_path / "cli" / "tune_trace.parquet"))
    assert result.tuned_toml == (tmp_path / "cli" / "tuned.toml").read_text()
    d = result.details
    assert d["converged"] is True and d["not_identified"] == []
    # At the estimate every condition holds (one equation per element, solved to its root).
    assert set(d["conditions"]) == set(result.table["element"])
    assert max(abs(g) for g in d["conditions"].values()) < 1e-6
    with pytest.raises(kfmc.SpecError, match="truth method takes"):
        kfmc.tune(spec, objective="rmse", quiet=True)
    with pytest.raises(kfmc.SpecError, match="do not belong to the truth method"):
        kfmc.tune(spec, tune_r=True, quiet=True)
