"""Runs in groups (`lanes=`) from the wheel: a linear study, whose KF shares its covariance
recursion across a group, writes the same bytes with lanes on and off, and the same bytes as
the cargo-built command (the wheel and the command run one library)."""

import subprocess

import pytest

kfmc = pytest.importorskip("kfmc")

SPEC = "linear_nees"


def _parquet_bytes(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.parquet"))}


def test_lanes_on_and_off_and_the_command_write_the_same_tables(tmp_path, kfmc_bin):
    spec = kfmc.examples()[SPEC]
    # 13 runs per cell: one group of 8 and a tail of 5 where L = 8 (4 + 4 + 5 … elsewhere).
    on = kfmc.run(spec, runs=13, lanes="auto", quiet=True, out=tmp_path / "on")
    off = kfmc.run(spec, runs=13, lanes="off", quiet=True, out=tmp_path / "off")
    cli = tmp_path / "cli"
    out = subprocess.run(
        [kfmc_bin, "run", str(spec), "--runs", "13", "--quiet", "--out", str(cli)],
        capture_output=True, text=True,
    )
    assert out.returncode == 0, out.stderr
    tables = _parquet_bytes(on.folder)
    assert "steps.parquet" in tables and "consistency.parquet" in tables
    assert tables == _parquet_bytes(off.folder)
    assert tables == _parquet_bytes(cli)
    assert on.manifest["lanes"] >= 1 and off.manifest["lanes"] == 1
    assert off.manifest["isa"] == "scalar"
    with pytest.raises(ValueError, match="lanes"):
        kfmc.run(spec, runs=2, lanes="sideways", quiet=True, out=tmp_path / "bad")
