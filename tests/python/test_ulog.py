"""kfmc.ulog_nis: the tables of `kfmc ulog nis` as DataFrames, on the real PX4 logs the
repository ships (too short in the air for a verdict: every case is incomplete)."""

from pathlib import Path

import polars as pl
import pytest

import kfmc

LOGS = Path(__file__).resolve().parents[1] / "ulog"


def test_ulog_nis_returns_the_tables_as_dataframes(tmp_path):
    r = kfmc.ulog_nis(LOGS, out=tmp_path / "nis")
    assert r["logs"] == 5
    assert r["failed"] == 0 and r["incomplete"] > 0
    assert isinstance(r["summary"], pl.DataFrame) and isinstance(r["samples"], pl.DataFrame)
    s = r["summary"]
    assert {"log", "instance", "primary", "source", "axis", "test", "statistic", "verdict"} <= set(s.columns)
    # One verdict row per log; none of these short flights can be judged.
    verdicts = s.filter(pl.col("test") == "verdict")
    assert verdicts.height == 5
    assert set(verdicts["verdict"]) == {"incomplete"}
    assert set(r["cases"]["outcome"]) == {"incomplete"}
    # v1.14.3 logs three EKF instances; with instance="all" each is judged on its own.
    one = kfmc.ulog_nis(LOGS / "px4_v1.14.3_fmu-v5_3ekf.ulg", out=tmp_path / "all", instance="all", include_ground=True)
    inst = one["summary"].filter(pl.col("test") == "nis_mean")["instance"].unique().sort().to_list()
    assert inst == [0, 1, 2]
    # NIS = ν²/S in every sample row.
    smp = one["samples"]
    assert (smp["nis"] - smp["innovation"] ** 2 / smp["innovation_variance"]).abs().max() < 1e-9


def test_a_file_that_is_not_a_log_is_refused_naming_it(tmp_path):
    bad = tmp_path / "x.ulg"
    bad.write_bytes(b"not a log")
    with pytest.raises(kfmc.Error, match="x.ulg"):
        kfmc.ulog_nis(bad, out=tmp_path / "o")
