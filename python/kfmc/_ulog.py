"""``kfmc.ulog_nis``: calibrated NIS verdicts from PX4 flight logs (``kfmc ulog nis``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Union

import polars as pl

from kfmc import _kfmc

PathLike = Union[str, "os.PathLike[str]"]


def ulog_nis(
    path: PathLike,
    *,
    out: PathLike = "results/ulog",
    instance: Union[str, int] = "primary",
    sensors: Sequence[str] = (),
    alpha: float = 0.05,
    holdoff: Optional[float] = None,
    include_ground: bool = False,
    baseline: Optional[PathLike] = None,
    tolerance: Optional[float] = None,
    force: bool = False,
    quiet: bool = True,
) -> Dict[str, Any]:
    """Judges the NIS of every aid source and axis of a PX4 log, or of every ``.ulg`` under
    a folder, as ``kfmc ulog nis`` does, and returns a dict: ``samples`` and ``summary`` (the
    tables ulog_samples.parquet and ulog_summary.parquet as polars DataFrames), ``cases`` (a
    DataFrame of the check cases: name, kind, outcome ``pass``/``fail``/``incomplete``,
    detail), ``failed``, ``incomplete``, ``logs``, ``seconds`` and ``out``.

    ``instance`` is ``"primary"``, ``"all"`` or an instance number; ``baseline`` a stored
    ulog_summary.parquet for the regression gate. Nothing is raised for a failed or
    incomplete verdict: read ``failed`` and ``incomplete`` (the command's exit codes 3 and 4).
    A log that is not a ULog file raises :class:`kfmc.Error`; a folder of another kind,
    :class:`kfmc.StudyError`."""
    r = _kfmc.ulog_nis(
        os.fspath(path),
        out=os.fspath(out),
        instance=str(instance),
        sensors=list(sensors),
        alpha=alpha,
        holdoff=holdoff,
        include_ground=include_ground,
        baseline=None if baseline is None else os.fspath(baseline),
        tolerance=tolerance,
        force=force,
    )
    if not quiet:
        print(r["report"], end="")
    folder = Path(r["out"])
    r["samples"] = pl.read_parquet(folder / "ulog_samples.parquet")
    r["summary"] = pl.read_parquet(folder / "ulog_summary.parquet")
    r["cases"] = pl.DataFrame(
        r["cases"], schema=["name", "kind", "outcome", "detail"], orient="row"
    )
    return r
