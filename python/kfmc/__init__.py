"""kfmc: judge state estimators (Kalman filters etc.) statistically.

The API, each function the ``kfmc`` command of the same name:

* :func:`run` a Monte Carlo study of kfmc's filters → :class:`Study` (its Parquet tables as
  polars DataFrames); :func:`summary`, :func:`plot`, :func:`report` of a study's folder;
* :func:`simulate` every run's world for a filter of yours → :class:`Simulation`
  (:meth:`Simulation.runs` yields each :class:`Run`: ``x0``, ``P0``, ``z``, ``u``,
  ``truth`` as numpy arrays), :class:`Estimates` to collect its output, :func:`score` it;
* :func:`check` a spec's ``[check]`` assertions → :class:`CheckResult`; :func:`power`;
* :func:`tune` a filter's noise covariances → :class:`TuneResult`;
* your own runs (a recorded truth): :func:`score` and :func:`check` with ``truth=``,
  :func:`stamp` their estimates;
* :func:`validate`, :func:`describe`, :func:`schema`, :func:`model`, :func:`list`,
  :func:`to_toml`; :func:`examples` the specs bundled with the wheel (name → path).

A *spec* is a path to a TOML file, a ``dict`` with the TOML's structure (numpy scalars and
arrays allowed), or TOML text (a ``str`` containing a newline). Without ``out=`` a call's
tables go to a temporary folder that lives as long as the object returned.

The functions release the GIL while the library works. Ctrl-C (and SIGTERM) stops a study at
its next window as SIGINT stops ``kfmc run``: the checkpoint kept, so
``run(..., out=..., resume=True)`` continues it. Errors are :class:`Error` (a
``ValueError``) and its subclasses.
"""

from __future__ import annotations

import builtins
import numbers
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import polars as pl

from kfmc import _kfmc
from kfmc._estimates import Estimates, sigma_point_transition
from kfmc._ulog import ulog_nis
from kfmc._kfmc import (
    CheckFailedError,
    Error,
    EstimatesError,
    IncompleteError,
    SpecError,
    StudyError,
)

__all__ = [
    "__version__",
    "CheckFailedError",
    "CheckResult",
    "Error",
    "Estimates",
    "EstimatesError",
    "IncompleteError",
    "Model",
    "Simulation",
    "SpecError",
    "Study",
    "StudyError",
    "TuneResult",
    "Run",
    "check",
    "describe",
    "examples",
    "list",
    "model",
    "plot",
    "power",
    "report",
    "run",
    "schema",
    "score",
    "sigma_point_transition",
    "simulate",
    "stamp",
    "summary",
    "to_toml",
    "tune",
    "ulog_nis",
    "validate",
]

#: The kfmc version (the crate's, the command's and the wheel's).
__version__: str = _kfmc.__version__

#: A spec: a TOML file's path, a dict, or TOML text (a str containing a newline).
Spec = Union[str, "os.PathLike[str]", Mapping[str, Any]]
#: A file or folder path.
PathLike = Union[str, "os.PathLike[str]"]

#: The consistency table's rows that carry the verdict of each cell.
_VERDICT = "verdict"


def _spec(spec: Spec) -> Any:
    if isinstance(spec, Mapping) and not isinstance(spec, dict):
        return dict(spec)
    return spec


def _path(p: Optional[PathLike]) -> Optional[str]:
    return None if p is None else os.fspath(p)


def _out(out: Optional[PathLike], resume: bool = False) -> Tuple[str, Optional["tempfile.TemporaryDirectory[str]"]]:
    """The folder a call writes: ``out``, or a new temporary folder (returned too, for the
    result to hold: it is removed when the result is let go)."""
    if out is not None:
        return os.fspath(out), None
    if resume:
        raise Error(
            "resume=True continues the checkpoint of an interrupted run in its folder: pass "
            "out= (the folder of that run); without out= a call writes a new temporary folder"
        )
    scratch = tempfile.TemporaryDirectory(prefix="kfmc-")
    return os.path.join(scratch.name, "study"), scratch


def _count(value: Any, name: str) -> Optional[int]:
    """An integer keyword (``runs``, ``seed``, …) checked here, so that a negative or
    non-integer value is a :class:`SpecError` naming it (not a bare ``OverflowError``)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise SpecError(f"{name}={value!r}: not an integer")
    if value < 0:
        raise SpecError(f"{name}={value!r}: not an integer ≥ 0")
    return int(value)


#: The command's flags as the Python arguments that do the same, for the library's messages.
_FLAGS = [
    ("`kfmc run SPEC --restart`", "`force=True`"),
    ("`kfmc run SPEC --resume`", "`resume=True` (with the same out=)"),
    ("`--restart`", "`force=True`"),
    ("`--resume`", "`resume=True`"),
    ("`--force`", "`force=True`"),
    ("`--allow-large`", "`allow_large=True`"),
    ("`--seed`", "`seed=`"),
    ("`--runs`", "`runs=`"),
    ("`--out`", "`out=`"),
    ("`--replications`", "`replications=`"),
    ("`--sequential`", "`sequential=True`"),
    ("`--looks`", "`looks=`"),
    ("`--against`", "`against=`"),
    ("--allow-large", "allow_large=True"),
    ("--method ml", 'method="ml"'),
    ("--elements[", "elements["),
    ("--elements", "elements="),
    ("--measurements", "measurements="),
]


def _pythonic(call: Callable[[], Any]) -> Any:
    """``call()``, with the library's messages naming Python's arguments where they name the
    command's flags."""
    try:
        return call()
    except Error as e:
        message = str(e)
        new = message
        for flag, keyword in _FLAGS:
            new = new.replace(flag, keyword)
        if new == message:
            raise
        raise type(e)(new) from None


class Study:
    """A result folder written by :func:`run`, :func:`score` or :func:`check`.

    Its tables are Parquet files; :meth:`table` reads one as a polars DataFrame with the
    columns the command writes (``kfmc schema`` and the book's table pages list them).
    """

    def __init__(
        self, folder: PathLike, report: Optional[Mapping[str, Any]] = None, *, _scratch: Any = None
    ) -> None:
        #: The folder.
        self.folder: Path = Path(folder)
        #: What the command reported: runs, wall_s, cells_resumed, tables (name, rows).
        self.report: Dict[str, Any] = dict(report or {})
        # The temporary folder of a call without out=, removed with this object.
        self._scratch = _scratch

    def summary(self, *, noise_scale: Optional[float] = None) -> str:
        """:func:`summary` of this folder: the RMSE table as ``kfmc summary`` prints it."""
        return summary(self, noise_scale=noise_scale)

    def __repr__(self) -> str:
        return f"kfmc.Study({str(self.folder)!r})"

    def tables(self) -> List[str]:
        """The names of the tables present (``"summary"``, ``"runs"``, ``"steps"``, …)."""
        return sorted(
            p.name[: -len(".parquet")]
            for p in self.folder.glob("*.parquet")
            if not p.name.startswith(".")
        )

    def table(self, name: str) -> pl.DataFrame:
        """The table ``name`` (``"summary"``, ``"runs"``, ``"steps"``, ``"consistency"``, …)."""
        path = self.folder / f"{name}.parquet"
        if not path.is_file():
            raise StudyError(
                f"{self.folder} has no table `{name}` (it has: {', '.join(self.tables()) or 'none'})"
            )
        return pl.read_parquet(path)

    @property
    def manifest(self) -> Dict[str, Any]:
        """``manifest.toml`` as a dict: the spec, seed, runs, versions and the tables' checksums."""
        return _kfmc.load_toml(self.folder / "manifest.toml")

    def verdict(self) -> pl.DataFrame:
        """The consistency verdict of every (cell, filter) and evaluation as a DataFrame: the
        ``consistency`` table's ``test == "verdict"`` rows, with a ``note`` column. A filter
        whose tests were evaluated but that has no verdict row is not left out: its row has
        a null statistic, p-value and pass, and the note says why — ``"not judged: no
        innovations"`` for a filter without a NIS test (estimates with ``x`` and ``P`` but
        no ``nu``/``S``), ``"not judged: the verdict could not be computed"`` otherwise."""
        t = self.table("consistency").with_row_index("_row")
        group = ["scenario", "noise_scale", "filter", "q_scale", "r_scale", "alpha", "runs"]
        tests = t.filter(pl.col("test") != "sequential")
        judged = tests.group_by(group).agg(
            (pl.col("test") == _VERDICT).any().alias("_has_verdict"),
            (pl.col("test") == "nis_time_average").any().alias("_has_nis"),
            pl.col("_row").max().alias("_last"),
        )
        missing = judged.filter(~pl.col("_has_verdict"))
        rows = t.filter(pl.col("test") == _VERDICT).with_columns(pl.lit(None, dtype=pl.String).alias("note"))
        if missing.height == 0:
            return rows.drop("_row")
        # One row per evaluation without a verdict, after that evaluation's last test.
        first = t.join(missing.select(group + ["_last", "_has_nis"]), left_on=group + ["_row"], right_on=group + ["_last"], how="inner", nulls_equal=True)
        blank = [c for c in t.columns if c not in group + ["_row", "test", "burn_in_steps"]]
        added = first.with_columns(
            pl.lit(_VERDICT).alias("test"),
            *[pl.lit(None, dtype=t.schema[c]).alias(c) for c in blank],
            pl.when(pl.col("_has_nis"))
            .then(pl.lit("not judged: the verdict could not be computed"))
            .otherwise(pl.lit("not judged: no innovations"))
            .alias("note"),
        ).select(rows.columns)
        return pl.concat([rows, added]).sort("_row").drop("_row")


Vector = Any
"""A vector: a 1-D numpy array or a sequence of floats."""

Sensor = Union[None, str, Sequence[str]]
"""Measurement components by name: ``None`` (all of them), one name, or a list of names."""


class Model:
    """The model kfmc's filters use — the world's own, for a filter written outside kfmc.

    Every call runs kfmc's Rust model (the f, h and Jacobians its truth simulator and filters
    call), so a filter built on it needs no transcription of the model. The step convention
    (:attr:`step_convention`): ``x_k = f(x_{k-1}, u_k) + w_k`` — the input on row ``k``
    drives the step from ``k-1`` to ``k`` — and ``z_k = h(x_k, u_k) + v_k``; step 0 has no
    measurement (its ``z`` is null) and starts from the run's prior (``initial``). Vectors
    and matrices are float64 numpy arrays, bit for bit the values Rust uses.

    Made by :attr:`Simulation.model` or :func:`model`; not constructed directly.
    """

    def __init__(self, raw: Any) -> None:
        self._raw = raw

    def __repr__(self) -> str:
        return (
            f"kfmc.Model(kind={self.kind!r}, states={self.states}, inputs={self.inputs}, "
            f"measurements={self.measurements}, linear={self.linear})"
        )

    @property
    def kind(self) -> str:
        """``model.kind`` of the spec."""
        return str(self._raw.kind)

    @property
    def states(self) -> List[str]:
        """The state names, in the order of every vector and matrix."""
        return builtins.list(self._raw.states)

    @property
    def inputs(self) -> List[str]:
        """The input names (the ``u_*`` columns of ``measurements``)."""
        return builtins.list(self._raw.inputs)

    @property
    def measurements(self) -> List[str]:
        """The measurement component names (the ``z_*`` columns)."""
        return builtins.list(self._raw.measurements)

    @property
    def dt_s(self) -> float:
        """The sample time Δt in seconds."""
        return float(self._raw.dt_s)

    @property
    def linear(self) -> bool:
        """Whether the model is linear, so that :attr:`F`, :attr:`G` and :attr:`H` exist."""
        return self._raw.linear() is not None

    def _linear(self, which: int) -> np.ndarray:
        parts = self._raw.linear()
        if parts is None:
            raise Error(
                f"model.kind = {self.kind!r} is not linear: it has no F, G, H; use f, h and "
                "jacobians (which run its model)"
            )
        n, nu, nz = len(self.states), len(self.inputs), len(self.measurements)
        rows, cols = ((n, n), (n, nu), (nz, n))[which]
        return _matrix(parts[which], rows, cols)

    @property
    def F(self) -> np.ndarray:
        """F of ``x_k = F x_{k-1} + G u_k + w_k`` (linear models; else :class:`Error`)."""
        return self._linear(0)

    @property
    def G(self) -> np.ndarray:
        """G of ``x_k = F x_{k-1} + G u_k + w_k`` (linear models; else :class:`Error`)."""
        return self._linear(1)

    @property
    def H(self) -> np.ndarray:
        """H of ``z_k = H x_k + v_k`` (linear models; else :class:`Error`)."""
        return self._linear(2)

    @property
    def Q(self) -> np.ndarray:
        """The truth's process-noise covariance at noise scale 1 (a cell with
        ``noise_scale`` s draws ``w_k ~ N(0, s² Q)``)."""
        n = len(self.states)
        return _matrix(self._raw.q, n, n)

    @property
    def R(self) -> np.ndarray:
        """The truth's measurement-noise covariance at noise scale 1 (``s² R`` at scale s)."""
        n = len(self.measurements)
        return _matrix(self._raw.r, n, n)

    @property
    def P0(self) -> np.ndarray:
        """``diag(p0_std²)``: the prior's covariance in the ``truth`` and ``sampled`` modes
        (each run's prior, also with ``batch_ls``, is its row of ``Simulation.initial``)."""
        n = len(self.states)
        return _matrix(self._raw.p0, n, n)

    @property
    def x0(self) -> Dict[str, np.ndarray]:
        """Each scenario's true initial state x_0, by scenario name."""
        return {name: np.array(x, dtype=np.float64) for name, x in self._raw.x0}

    @property
    def step_convention(self) -> Dict[str, Any]:
        """Which input drives a step, what row 0 is, and what wraps (as ``manifest.toml``'s
        ``[exchange.step_convention]`` and ``kfmc schema`` state it): ``transition``,
        ``measurement``, ``row_0`` (sentences), ``wrapped_errors`` (quantities whose error
        kfmc wraps), ``continuous_angles`` (angles kept continuous: truth, z and error not
        wrapped), ``wrapped_innovations`` (components whose innovation kfmc's filters wrap
        to [−π, π); :meth:`residual` does it), ``rotation_errors`` (quantities scored as a
        rotation: the rotation vector of the attitude error, not wrapped angles)."""
        return dict(self._raw.step_convention)

    def _rows(self, sensor: Sensor) -> List[int]:
        names = self.measurements
        if sensor is None:
            return builtins.list(range(len(names)))
        wanted = [sensor] if isinstance(sensor, str) else builtins.list(sensor)
        rows = []
        for s in wanted:
            if s not in names:
                raise Error(f"unknown sensor component {s!r}; the model measures: {', '.join(names)}")
            rows.append(names.index(s))
        return rows

    def _u_for_h(self, u: Optional[Vector]) -> List[float]:
        if u is None:
            if self._raw.measurement_uses_input:
                raise Error(
                    f"h of model.kind = {self.kind!r} reads the input: pass u (the input on the "
                    "same row as z)"
                )
            return []
        return _vector(u, len(self.inputs), "u")

    def f(self, x: Vector, u: Vector) -> np.ndarray:
        """``f(x_{k-1}, u_k)``: the noise-free transition into step k, with the input of
        step k (row k of ``measurements``). ``x`` may be a batch, m × n (one state a row:
        sigma points, particles), with one ``u`` for all or m × inputs; the result is then
        m × n, made in one call into the library."""
        n, nu = len(self.states), len(self.inputs)
        xs = _batch(x, n, "x")
        if xs is not None:
            got = self._raw.f_many(xs, _companion(u, len(xs), nu, "u"))
            return np.array(got, dtype=np.float64).reshape(len(xs), n)
        return np.array(
            self._raw.f(_vector(x, len(self.states), "x"), _vector(u, len(self.inputs), "u")),
            dtype=np.float64,
        )

    def h(self, x: Vector, sensor: Sensor = None, *, u: Optional[Vector] = None) -> np.ndarray:
        """``h(x_k, u_k)``: the noise-free measurement, all components or those named by
        ``sensor``. ``u`` is needed only when h reads the input (the planar IMU set). ``x``
        may be a batch, m × n, as for :meth:`f`: the result is m × components."""
        rows = self._rows(sensor)
        xs = _batch(x, len(self.states), "x")
        if xs is not None:
            if u is None:
                self._u_for_h(None)
                us: List[List[float]] = []
            else:
                us = _companion(u, len(xs), len(self.inputs), "u")
            got = np.array(self._raw.h_many(xs, us), dtype=np.float64)
            return got.reshape(len(xs), len(self.measurements))[:, rows]
        z = self._raw.h(_vector(x, len(self.states), "x"), self._u_for_h(u))
        return np.array([z[i] for i in rows], dtype=np.float64)

    def jacobians(
        self, x: Vector, u: Vector, sensor: Sensor = None
    ) -> Tuple[np.ndarray, np.ndarray]:
        """``(F, H)`` at ``(x, u)``: ``F = ∂f/∂x`` (an EKF takes it at the previous estimate
        ``x̂_{k-1}`` with ``u_k``) and ``H = ∂h/∂x`` (taken at the predicted ``x̂⁻_k``: call
        again there), H's rows those of ``sensor``."""
        xs = _vector(x, len(self.states), "x")
        us = _vector(u, len(self.inputs), "u")
        n = len(self.states)
        f = _matrix(self._raw.transition_jacobian(xs, us), n, n)
        rows = self._rows(sensor)
        h_u = us if self._raw.measurement_uses_input else []
        h = _matrix(self._raw.measurement_jacobian(xs, h_u), len(self.measurements), n)
        return f, h[rows, :]

    def residual(self, z: Vector, z_pred: Vector, sensor: Sensor = None) -> np.ndarray:
        """The innovation ``z - ẑ`` as kfmc's filters form it: the components in
        ``step_convention["wrapped_innovations"]`` wrapped to [−π, π). ``z`` may be a batch,
        m × components (with ``z_pred`` one row for all or m × components): the result is
        m × components, from one call into the library."""
        rows = self._rows(sensor)
        nz = len(self.measurements)
        zb = _batch(z, len(rows), "z")
        if zb is not None:
            full = np.zeros((len(zb), nz))
            full[:, rows] = zb
            preds = np.asarray(_companion(z_pred, len(zb), len(rows), "z_pred"), dtype=np.float64)
            full_pred = np.zeros((len(preds), nz))
            full_pred[:, rows] = preds
            got = np.array(self._raw.residual_many(full.tolist(), full_pred.tolist()), dtype=np.float64)
            return got.reshape(len(zb), nz)[:, rows]
        full_z, full_p = [0.0] * nz, [0.0] * nz
        zs = _vector(z, len(rows), "z")
        ps = _vector(z_pred, len(rows), "z_pred")
        for i, r in enumerate(rows):
            full_z[r], full_p[r] = zs[i], ps[i]
        d = self._raw.residual(full_z, full_p)
        return np.array([d[r] for r in rows], dtype=np.float64)

    def available(self, step: int) -> List[str]:
        """The measurement components that report at ``step`` (all of them at every step
        unless the model is multi-rate; none has a measurement at step 0)."""
        mask = self._raw.availability(step)
        return [n for n, a in zip(self.measurements, mask) if a]


def _vector(v: Vector, n: int, what: str) -> List[float]:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 1 or a.shape[0] != n:
        raise Error(f"{what} must be a vector of {n} numbers; got shape {a.shape}")
    return a.tolist()


def _batch(v: Vector, n: int, what: str) -> Optional[List[List[float]]]:
    """The rows of ``v`` when it is a batch (m × n), else None (a single vector)."""
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2:
        return None
    if a.shape[1] != n:
        raise Error(f"{what} must be a vector of {n} numbers or a batch m × {n} (one vector a row); got shape {a.shape}")
    return a.tolist()


def _companion(v: Vector, m: int, n: int, what: str) -> List[List[float]]:
    """The argument beside a batch of m rows: one vector for all of them, or m rows."""
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == n:
        return [a.tolist()]
    if a.ndim == 2 and a.shape == (m, n):
        return a.tolist()
    raise Error(f"{what} must be a vector of {n} numbers or {m} × {n} beside a batch of {m}; got shape {a.shape}")


def _matrix(rows: Sequence[Sequence[float]], r: int, c: int) -> np.ndarray:
    # Python floats are f64: the list round trip keeps every bit.
    return np.array(rows, dtype=np.float64).reshape(r, c)


def model(spec: Spec) -> Model:
    """The model kfmc's filters use for a spec (see :class:`Model`), without simulating.
    Raises :class:`Error` for a system whose world is not one model plus additive noise (the
    drone)."""
    return Model(_kfmc.filter_model(_spec(spec)))


class Simulation:
    """A folder written by :func:`simulate`: every run's world for a filter outside kfmc.

    ``truth``, ``measurements`` and ``initial`` are the whole tables (the columns ``kfmc
    simulate`` writes); :meth:`runs` yields one run at a time, so a loop over many runs never
    holds all of them. :attr:`model` is the world's model for the filter (F, G, H, Q, R,
    P0 of a linear system; f, h and their Jacobians of every system it exists for), and the
    same names are available on the simulation itself (``sim.F``, ``sim.f(x, u)``, …).
    """

    def __init__(
        self, folder: PathLike, report: Optional[Mapping[str, Any]] = None, *, _scratch: Any = None
    ) -> None:
        #: The folder.
        self.folder: Path = Path(folder)
        #: What the command reported: runs, wall_s, tables (name, rows).
        self.report: Dict[str, Any] = dict(report or {})
        self._model: Optional[Model] = None
        # The temporary folder of a call without out=, removed with this object.
        self._scratch = _scratch

    @property
    def model(self) -> Model:
        """The model kfmc's filters use in this simulation's world (the spec its manifest
        records); :class:`Error` for a system without one (the drone)."""
        if self._model is None:
            self._model = Model(_kfmc.simulation_model(os.fspath(self.folder)))
        return self._model

    @property
    def F(self) -> np.ndarray:
        """:attr:`Model.F` of :attr:`model`."""
        return self.model.F

    @property
    def G(self) -> np.ndarray:
        """:attr:`Model.G` of :attr:`model`."""
        return self.model.G

    @property
    def H(self) -> np.ndarray:
        """:attr:`Model.H` of :attr:`model`."""
        return self.model.H

    @property
    def Q(self) -> np.ndarray:
        """:attr:`Model.Q` of :attr:`model` (the truth's, at noise scale 1)."""
        return self.model.Q

    @property
    def R(self) -> np.ndarray:
        """:attr:`Model.R` of :attr:`model` (the truth's, at noise scale 1)."""
        return self.model.R

    @property
    def P0(self) -> np.ndarray:
        """:attr:`Model.P0` of :attr:`model`."""
        return self.model.P0

    @property
    def step_convention(self) -> Dict[str, Any]:
        """:attr:`Model.step_convention` of :attr:`model`."""
        return self.model.step_convention

    def f(self, x: Vector, u: Vector) -> np.ndarray:
        """:meth:`Model.f`: ``f(x_{k-1}, u_k)``, running kfmc's model."""
        return self.model.f(x, u)

    def h(self, x: Vector, sensor: Sensor = None, *, u: Optional[Vector] = None) -> np.ndarray:
        """:meth:`Model.h`: ``h(x_k)`` (all components, or those of ``sensor``)."""
        return self.model.h(x, sensor, u=u)

    def jacobians(
        self, x: Vector, u: Vector, sensor: Sensor = None
    ) -> Tuple[np.ndarray, np.ndarray]:
        """:meth:`Model.jacobians`: ``(∂f/∂x, ∂h/∂x)`` at ``(x, u)``."""
        return self.model.jacobians(x, u, sensor)

    def residual(self, z: Vector, z_pred: Vector, sensor: Sensor = None) -> np.ndarray:
        """:meth:`Model.residual`: the innovation, wrapped as kfmc's filters wrap it."""
        return self.model.residual(z, z_pred, sensor)

    def __repr__(self) -> str:
        return f"kfmc.Simulation({str(self.folder)!r})"

    def _read(self, name: str) -> pl.DataFrame:
        return pl.read_parquet(self.folder / f"{name}.parquet")

    @property
    def truth(self) -> pl.DataFrame:
        """``truth.parquet``: the true state (``truth_*``, ``world_*``) per run and step."""
        return self._read("truth")

    @property
    def measurements(self) -> pl.DataFrame:
        """``measurements.parquet``: ``z_*`` (null where a sensor did not report) and the
        inputs ``u_*`` per run and step."""
        return self._read("measurements")

    @property
    def initial(self) -> pl.DataFrame:
        """``initial.parquet``: each run's seed and prior (``est_*``, ``P_*``)."""
        return self._read("initial")

    @property
    def manifest(self) -> Dict[str, Any]:
        """``manifest.toml`` as a dict (what the tables mean: the exchange section)."""
        return _kfmc.load_toml(self.folder / "manifest.toml")

    @property
    def external_filters(self) -> List[Dict[str, Any]]:
        """The spec's external filters: the estimates to write for these runs (the manifest's
        ``[[exchange.external_filters]]``), dicts with ``label`` and, for a label that
        declares variants, ``q_scale`` and/or ``r_scale``: every pair of their values is a
        variant, whose rows name it in those columns (``Estimates.add_run(..., q_scale=…)``)."""
        return [dict(e) for e in self.manifest.get("exchange", {}).get("external_filters", [])]

    @property
    def stamp(self) -> Dict[str, str]:
        """The file metadata an estimates file made on these runs carries:
        ``{"kfmc.world_stamp": …, "kfmc.master_seed": …}`` (:class:`Estimates` writes it)."""
        m = self.manifest
        return {"kfmc.world_stamp": str(m["world_stamp"]), "kfmc.master_seed": str(m["master_seed"])}

    def runs(self) -> Iterator["Run"]:
        """Yields each run as a :class:`Run`, one at a time, in the tables' order: its
        ``x0``, ``P0``, ``z``, ``u`` and ``truth`` as numpy arrays, and its tables; it unpacks
        as ``(key, truth, measurements, initial)`` (the key ``(scenario, noise_scale, run)``,
        the tables polars DataFrames). Each table is scanned with a filter on the run's keys,
        so only that run's rows are read into memory."""
        keys = ["scenario", "noise_scale", "run"]
        files = {n: self.folder / f"{n}.parquet" for n in ("truth", "measurements", "initial")}
        order = (
            pl.scan_parquet(files["initial"])
            .select(keys)
            .collect()
        )
        for scenario, noise_scale, run in order.iter_rows():
            pred = (
                (pl.col("scenario") == scenario)
                & (pl.col("noise_scale") == noise_scale)
                & (pl.col("run") == run)
            )
            yield Run(
                (scenario, noise_scale, run),
                pl.scan_parquet(files["truth"]).filter(pred).collect(),
                pl.scan_parquet(files["measurements"]).filter(pred).collect(),
                pl.scan_parquet(files["initial"]).filter(pred).collect(),
            )




class Run(Tuple[Tuple[str, float, int], pl.DataFrame, pl.DataFrame, pl.DataFrame]):
    """One run of a :class:`Simulation` (what :meth:`Simulation.runs` yields): a tuple
    ``(key, truth, measurements, initial)`` of the key ``(scenario, noise_scale, run)`` and
    the run's rows of each table, with its arrays as attributes. Rows are steps (0 to K);
    columns follow the tables' order (the states of ``initial``'s ``est_*`` columns)."""

    __slots__ = ()

    def __new__(
        cls,
        key: Tuple[str, float, int],
        truth: pl.DataFrame,
        measurements: pl.DataFrame,
        initial: pl.DataFrame,
    ) -> "Run":
        return super().__new__(cls, (key, truth, measurements, initial))

    @property
    def key(self) -> Tuple[str, float, int]:
        """``(scenario, noise_scale, run)``."""
        return self[0]

    @property
    def states(self) -> List[str]:
        """The state names, in the order of :attr:`x0`, :attr:`P0` and :attr:`truth`."""
        return [c[len("est_"):] for c in self[3].columns if c.startswith("est_")]

    @property
    def x0(self) -> np.ndarray:
        """The prior x̂₀ kfmc's own filters start from (``initial``'s ``est_*``)."""
        return self[3].select([f"est_{q}" for q in self.states]).to_numpy()[0].astype(np.float64)

    @property
    def P0(self) -> np.ndarray:
        """The prior's covariance P₀ (``initial``'s ``P_*``, its lower triangle mirrored)."""
        names = self.states
        row = self[3]
        n = len(names)
        p = np.empty((n, n), dtype=np.float64)
        for i, qi in enumerate(names):
            for j, qj in enumerate(names[: i + 1]):
                p[i, j] = p[j, i] = float(row[f"P_{qi}_{qj}"][0])
        return p

    @property
    def z(self) -> np.ndarray:
        """The measurements, steps × components (``z_*``; NaN where a sensor did not report,
        and on row 0, which has none)."""
        m = self[2]
        return _floats(m.select([c for c in m.columns if c.startswith("z_")]))

    @property
    def u(self) -> np.ndarray:
        """The inputs, steps × inputs (``u_*``; row k drives the step from k−1 to k)."""
        m = self[2]
        return _floats(m.select([c for c in m.columns if c.startswith("u_")]))

    @property
    def truth(self) -> np.ndarray:
        """The true states, steps × states (``truth_*``, in the order of :attr:`states`)."""
        return _floats(self[1].select([f"truth_{q}" for q in self.states]))

    def __repr__(self) -> str:
        return f"kfmc.Run({self.key!r}, steps={self[2].height})"


def _floats(df: pl.DataFrame) -> np.ndarray:
    """A frame of float columns as a float64 array, nulls as NaN."""
    return df.cast(pl.Float64).fill_null(float("nan")).to_numpy().astype(np.float64, copy=False).reshape(df.height, df.width)


class CheckResult:
    """What :func:`check` found: the same cases, report and exit code as ``kfmc check``.

    * ``exit_code``: the command's exit code, 0 every assertion holds, 3 one failed, 4 a case
      could not be judged on the runs the spec declares (incomplete);
    * ``report``: the readable report ``kfmc check`` prints;
    * ``junit``: the JUnit XML ``kfmc check --junit`` writes (for a CI's test report);
    * ``cases``: every case, dicts with ``kind``, ``name``, ``passed``, ``incomplete``,
      ``detail``; :attr:`failures` those that failed or were incomplete;
    * ``study``: the :class:`Study` the assertions were judged on; :attr:`ok` is
      ``exit_code == 0`` and :meth:`raise_for_status` raises for 3 and 4.
    """

    def __init__(self, raw: Mapping[str, Any], _scratch: Any = None) -> None:
        #: The command's exit code: 0 all hold, 3 an assertion failed, 4 incomplete.
        self.exit_code: int = int(raw["exit_code"])
        #: The readable report ``kfmc check`` prints.
        self.report: str = raw["report"]
        #: The JUnit XML ``kfmc check --junit`` writes.
        self.junit: str = raw["junit"]
        #: Every case: dicts with kind, name, passed, incomplete, detail.
        self.cases: List[Dict[str, Any]] = builtins.list(raw["cases"])
        #: The study folder the assertions were judged on.
        self.study: Study = Study(raw["folder"], _scratch=_scratch)

    @property
    def ok(self) -> bool:
        """Whether every assertion holds on every run the spec declares (exit code 0)."""
        return self.exit_code == 0

    @property
    def failures(self) -> List[Dict[str, Any]]:
        """The cases that failed or could not be judged (incomplete)."""
        return [c for c in self.cases if not c["passed"]]

    def raise_for_status(self) -> None:
        """Raises :class:`CheckFailedError` (exit 3) or :class:`IncompleteError` (exit 4)."""
        if self.exit_code == 3:
            raise CheckFailedError(self.report)
        if self.exit_code == 4:
            raise IncompleteError(self.report)

    def __repr__(self) -> str:
        return f"kfmc.CheckResult(exit_code={self.exit_code}, cases={len(self.cases)}, failures={len(self.failures)})"


def validate(spec: Spec, *, allow_large: bool = False) -> Dict[str, Any]:
    """Checks a spec and returns the plan's summary (cells, runs, filter steps, estimated
    memory and disk) without running it; raises :class:`SpecError`."""
    return _pythonic(lambda: _kfmc.validate(_spec(spec), allow_large=allow_large))


def run(
    spec: Spec,
    *,
    out: Optional[PathLike] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    resume: bool = False,
    force: bool = False,
    allow_large: bool = False,
    checkpoint_every: float = 10.0,
    lanes: Optional[str] = None,
) -> Study:
    """Runs a Monte Carlo study (``kfmc run``) and returns its folder.

    The tables go to ``out``, or without it to a temporary folder that lives as long as the
    returned :class:`Study` (the spec's ``output`` is the command's). ``runs`` and ``seed``
    override the spec's ``runs`` and ``master_seed``; ``threads`` (default all cores) does
    not change any result. With ``resume=True`` (and the interrupted run's ``out``) its
    checkpoint is continued, and the tables come out identical to an uninterrupted run's;
    ``force=True`` discards a checkpoint instead, and writes into a non-empty folder that is
    not a kfmc study. A checkpoint follows a complete cell once ``checkpoint_every`` seconds
    have passed since the last (0: after every cell). ``allow_large`` lifts the size limits.
    ``lanes`` is ``"auto"`` (runs of a cell in groups) or ``"off"`` (one at a time); without
    it ``KFMC_LANES`` decides, else auto. It does not change any result (``kfmc run --lanes``).
    """
    folder, scratch = _out(out, resume)
    r = _pythonic(
        lambda: _kfmc.run(
            _spec(spec),
            out=folder,
            runs=_count(runs, "runs"),
            seed=_count(seed, "seed"),
            threads=_count(threads, "threads"),
            quiet=quiet,
            resume=resume,
            force=force,
            allow_large=allow_large,
            checkpoint_every=checkpoint_every,
            lanes=lanes,
        )
    )
    return Study(r["folder"], r, _scratch=scratch)


def simulate(
    spec: Spec,
    *,
    out: Optional[PathLike] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    allow_large: bool = False,
    lanes: Optional[str] = None,
) -> Simulation:
    """Writes every run's world (``kfmc simulate``): truth, measurements and priors for a
    filter outside kfmc, the same runs ``kfmc run`` gives its own filters. Without ``out``
    they go to a temporary folder that lives as long as the returned :class:`Simulation`.
    ``lanes`` is as in :func:`run`."""
    folder, scratch = _out(out)
    r = _pythonic(
        lambda: _kfmc.simulate(
            _spec(spec),
            out=folder,
            runs=_count(runs, "runs"),
            seed=_count(seed, "seed"),
            threads=_count(threads, "threads"),
            quiet=quiet,
            force=force,
            allow_large=allow_large,
            lanes=lanes,
        )
    )
    return Simulation(r["folder"], r, _scratch=scratch)


def _is_path(x: Any) -> bool:
    return isinstance(x, (str, os.PathLike))


def _plain_keys(x: Any) -> Any:
    """``x`` with categorical (dictionary-encoded) columns as their values, which the reader
    takes: pandas ``Categorical`` and polars ``Categorical``/``Enum`` key columns are ordinary
    choices for ``scenario`` and ``filter``."""
    if isinstance(x, pl.DataFrame):
        cats = [c for c, t in x.schema.items() if isinstance(t, (pl.Categorical, pl.Enum))]
        return x.with_columns(pl.col(c).cast(pl.String) for c in cats) if cats else x
    if type(x).__module__.startswith("pandas") and hasattr(x, "dtypes"):
        cats = [c for c, t in x.dtypes.items() if str(t) == "category"]
        if cats:
            x = x.copy(deep=False)
            for c in cats:
                x[c] = x[c].astype(x[c].cat.categories.dtype)
        return x
    return x


def _as_stream(x: Any) -> Any:
    x = _plain_keys(x)
    if isinstance(x, pl.DataFrame):
        return _chunks(x)
    if hasattr(x, "__arrow_c_stream__"):
        return x
    if type(x).__module__.startswith("pandas"):
        # An older pandas without the Arrow PyCapsule interface: polars converts it.
        return pl.from_pandas(x)
    raise TypeError(
        f"estimates must be a polars or pandas DataFrame, a pyarrow Table (anything with "
        f"__arrow_c_stream__), an iterable of them, or a path; got {type(x).__name__}"
    )


def _chunks(df: pl.DataFrame) -> Any:
    """A polars DataFrame as a list of zero-copy slices, one per stretch of rows that every
    column holds in one chunk, which the library reads as one table. polars'
    ``__arrow_c_stream__`` first copies a DataFrame of several chunks into one (a second
    copy of the whole table, made in place of the caller's chunks), while such a slice is
    exported as it is. A frame of one chunk is passed whole."""
    ends = set()
    for c in df.get_columns():
        at = 0
        for n in c.chunk_lengths():
            at += n
            ends.add(at)
    ends.discard(0)
    if len(ends) < 2:
        return df
    parts, at = [], 0
    for end in sorted(ends):
        parts.append(df.slice(at, end - at))
        at = end
    return parts


def _estimates(
    estimates: Any, stamp: Optional[Callable[[], Mapping[str, str]]] = None
) -> Tuple[List[str], Iterable[Any]]:
    """Paths and Arrow streams of ``estimates``; an :class:`Estimates` is checked against
    ``stamp()`` (the world it is scored on) first. A list or tuple is taken whole; any other
    iterable (a generator yielding each run's estimates) is passed on lazily, so the library
    reads each item and lets it go before asking for the next."""
    if estimates is None:
        return [], []
    if (
        _is_path(estimates)
        or isinstance(estimates, Estimates)
        or hasattr(estimates, "__arrow_c_stream__")
        or type(estimates).__module__.startswith("pandas")
    ):
        estimates = [estimates]
    ours: List[Optional[Dict[str, str]]] = []

    def stream_of(e: Any) -> Any:
        if _is_path(e):
            return os.fspath(e)
        if isinstance(e, Estimates):
            if not ours:
                ours.append(None if stamp is None else dict(stamp()))
            if ours[0] is not None and e.metadata != ours[0]:
                raise EstimatesError(
                    f"the estimates `{e.label}` were made on the simulation {e.folder} (world "
                    f"{e.world_stamp}, master seed {e.master_seed}); this study's runs are world "
                    f"{ours[0].get('kfmc.world_stamp')}, master seed {ours[0].get('kfmc.master_seed')}: "
                    "score them against the simulation they were made from"
                )
            if e.path is not None:
                # A table streamed to a file is read from it, once complete.
                return os.fspath(e.close())
            # A polars DataFrame has no metadata to carry the stamp: it goes beside it.
            return (_as_stream(e.to_polars()), e.metadata)
        return _as_stream(e)

    if not isinstance(estimates, (builtins.list, tuple)):

        def lazily(items: Iterable[Any]) -> Iterator[Any]:
            # Each reference is dropped before the next item is asked for (a generator
            # expression would keep the last one alive while its producer makes the next).
            for e in items:
                s = stream_of(e)
                del e
                yield s
                del s

        return [], lazily(estimates)
    paths: List[str] = []
    streams: List[Any] = []
    for e in estimates:
        if _is_path(e):
            paths.append(os.fspath(e))
        else:
            streams.append(stream_of(e))
    return paths, streams


EstimatesInput = Any
"""Estimates: a :class:`Estimates`, a polars or pandas DataFrame, a pyarrow Table (anything
with ``__arrow_c_stream__``), an iterable of them, a Parquet file's path, or a list of
paths."""


def score(
    simulation: Union[Simulation, PathLike],
    estimates: EstimatesInput,
    *,
    out: Optional[PathLike] = None,
    quiet: bool = False,
    threads: Optional[int] = None,
    force: bool = False,
    truth: Any = None,
) -> Study:
    """Scores estimates made outside kfmc against a simulation (``kfmc score``): writes the
    tables ``kfmc run`` writes, with kfmc's own filters of the spec run beside them.

    With ``truth`` (a Parquet file's path or a DataFrame: ``scenario``, ``noise_scale``,
    ``run``, ``step``, ``t``, ``truth_<q>``) the runs are the user's own: ``simulation`` is
    then the path of a spec of ``model.kind = "recorded"`` (``kfmc score --truth``);
    :func:`stamp` gives the stamp of estimates made on such runs.

    In-memory estimates (the columns ``schema("estimates", spec)`` lists) go to the library
    through the Arrow C stream interface. Their world stamp is checked as a file's: a
    :class:`Estimates` carries its simulation's, a pyarrow Table read from a stamped file
    keeps it in its schema metadata; one stamped with another world is refused, and one
    without a stamp (a polars or pandas DataFrame) is scored with a warning on stderr, as
    an unstamped file is. ``report["runs_missing"]`` counts, per outside filter, the runs
    its estimates leave out (a warning names them too): they are missing, not failures.
    """
    if truth is not None:
        from kfmc._estimates import _truth_input

        if isinstance(simulation, Simulation):
            raise TypeError(
                "with truth=…, the first argument is the path of a spec of "
                'model.kind = "recorded", not a Simulation'
            )
        paths, streams = _estimates(estimates)
        if not paths and not streams:
            raise EstimatesError("no estimates given")
        target, scratch = _out(out)
        truth_table = _truth_input(truth)
        r = _pythonic(
            lambda: _kfmc.score(
                os.fspath(simulation), paths, streams, out=target, threads=_count(threads, "threads"),
                quiet=quiet, force=force, truth=truth_table,
            )
        )
        return Study(r["folder"], r, _scratch=scratch)
    folder = simulation.folder if isinstance(simulation, Simulation) else Path(simulation)
    paths, streams = _estimates(estimates, lambda: Simulation(folder).stamp)
    if not paths and not streams:
        raise EstimatesError("no estimates given")
    target, scratch = _out(out)
    r = _pythonic(
        lambda: _kfmc.score(
            os.fspath(folder), paths, streams, out=target, threads=threads, quiet=quiet, force=force
        )
    )
    return Study(r["folder"], r, _scratch=scratch)


def check(
    spec: Spec,
    *,
    estimates: EstimatesInput = None,
    out: Optional[PathLike] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    replications: Optional[int] = None,
    allow_unstamped: bool = False,
    force: bool = False,
    allow_large: bool = False,
    sequential: bool = False,
    looks: Union[int, Sequence[int], None] = None,
    spending: Optional[str] = None,
    futility: Optional[float] = None,
    futility_rho: Optional[float] = None,
    futility_beta: Optional[float] = None,
    truth: Any = None,
    lanes: Optional[str] = None,
) -> CheckResult:
    """Runs the study and evaluates its ``[check]`` assertions (``kfmc check``). A failing
    or incomplete gate is a result (``.ok`` false, ``.exit_code`` 3 or 4), not an exception:
    :meth:`CheckResult.raise_for_status` raises it. Estimates, files or tables in memory,
    must carry the world stamp of the spec's runs unless ``allow_unstamped``, as the
    command refuses an unstamped file: a :class:`Estimates` made on the spec's world (and
    seed) carries it, and so does a pyarrow Table read from a stamped file (in its schema
    metadata); a polars or pandas DataFrame has none, so it needs ``allow_unstamped=True``.
    A table stamped with another world is refused either way.

    ``sequential=True`` judges the consistency verdicts with the group-sequential gate
    (``kfmc check --sequential``; the spec's ``[check] sequential = true`` does the same):
    each cell stops at the first look that settles its verdicts, and ``sequential.parquet``
    records every look. ``looks`` (a count of even looks, default 10, or the looks' run
    counts ending at the runs per cell), ``spending`` (``"obrien-fleming"``, the default, also
    spelled ``"obrien_fleming"`` as in the spec, or ``"pocock"``), ``futility`` (a β in
    (0, 1): non-binding futility bounds; ``futility_beta``, the spec's name, is the same) and
    ``futility_rho`` (their β-spending exponent, default 2) are ``--looks``, ``--spending``,
    ``--futility`` and ``--futility-rho``: each given one wins over the spec's key. A setting
    without the gate, or settings that make no gate for the study's runs, raise
    :class:`SpecError` (the command's exit 2). ``lanes`` is as in :func:`run`.

    With ``truth`` (a Parquet file's path or a DataFrame, as for :func:`score`) the spec is
    one of ``model.kind = "recorded"`` and the runs are the user's own (``kfmc check
    --truth``): the estimates are judged against that truth, and their stamp is the truth's
    (:func:`stamp`)."""

    truth_table = None
    if truth is not None:
        from kfmc._estimates import _truth_input

        truth_table = _truth_input(truth)

    def stamp() -> Dict[str, str]:
        if truth_table is not None:
            return dict(_kfmc.stamp(_spec(spec), truth_table, []))
        s = dict(_kfmc.schema("estimates", _spec(spec))["metadata"])
        if seed is not None:
            s["kfmc.master_seed"] = str(seed)
        return s

    beta = _futility(futility, futility_beta)
    paths, streams = _estimates(estimates, stamp)
    folder, scratch = _out(out)
    r = _pythonic(
        lambda: _kfmc.check(
            _spec(spec),
            paths,
            streams,
            out=folder,
            runs=_count(runs, "runs"),
            seed=_count(seed, "seed"),
            threads=_count(threads, "threads"),
            quiet=quiet,
            replications=_count(replications, "replications"),
            allow_unstamped=allow_unstamped,
            force=force,
            allow_large=allow_large,
            sequential=sequential,
            looks=looks,
            spending=spending,
            futility=beta,
            futility_rho=futility_rho,
            truth=truth_table,
            lanes=lanes,
        )
    )
    return CheckResult(r, scratch)


def _futility(futility: Optional[float], futility_beta: Optional[float]) -> Optional[float]:
    """``futility`` (the flag's name) or ``futility_beta`` (the spec's): one of them."""
    if futility is not None and futility_beta is not None:
        raise SpecError("futility and futility_beta are one setting (the β of the futility bounds): pass one")
    return futility if futility is not None else futility_beta


def power(
    spec: Spec,
    replications: int,
    *,
    out: Optional[PathLike] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    allow_large: bool = False,
    sequential: bool = False,
    looks: Union[int, Sequence[int], None] = None,
    spending: Optional[str] = None,
    futility: Optional[float] = None,
    futility_rho: Optional[float] = None,
    futility_beta: Optional[float] = None,
    target_power: Optional[float] = None,
    against: Optional[str] = None,
    lanes: Optional[str] = None,
) -> pl.DataFrame:
    """Runs the study ``replications`` times with independent seeds (``kfmc power``) and
    returns power.parquet: per (cell, filter variant, test) the rejection rate with its 95 %
    Clopper–Pearson interval.

    With ``sequential=True`` it also measures the group-sequential gate (``kfmc power
    --sequential``): rows with ``sequential`` true hold its rejection rate and the runs it used
    (``runs_used_mean``, ``runs_used_p05``, ``runs_used_p95``). ``looks`` is a count of even
    looks (default 10) or the looks' run counts ending at the study's runs per cell;
    ``spending`` is ``"obrien-fleming"`` (the default; ``"obrien_fleming"`` too) or
    ``"pocock"``; ``futility`` (or ``futility_beta``) a β in (0, 1) for non-binding futility
    stopping, ``futility_rho`` its β-spending exponent (default 2). Without ``out`` the
    study is written to a temporary folder, removed once the table is read. Invalid settings raise :class:`SpecError` (a ``ValueError``).

    With ``target_power=P, against="q_scale=X[,r_scale=Y]"`` (together, as ``kfmc power
    --target-power P --against …``) every test is also evaluated on the first N/10, 2N/10, …
    runs of each cell (rows with those ``runs``), and unless ``quiet`` the smallest N whose
    verdict reaches power P against that variant is printed, as the command prints it. A
    variant no filter of the spec has raises :class:`SpecError` before any run. ``lanes`` is
    as in :func:`run`."""
    beta = _futility(futility, futility_beta)
    target, scratch = _out(out)
    folder, answer = _pythonic(
        lambda: _kfmc.power(
            _spec(spec),
            _count(replications, "replications") or 0,
            out=target,
            runs=_count(runs, "runs"),
            seed=_count(seed, "seed"),
            threads=_count(threads, "threads"),
            quiet=quiet,
            force=force,
            allow_large=allow_large,
            sequential=sequential,
            looks=looks,
            spending=spending,
            futility=beta,
            futility_rho=futility_rho,
            target_power=target_power,
            against=against,
            lanes=lanes,
        )
    )
    if answer is not None and not quiet:
        print(answer, end="")
    table = pl.read_parquet(Path(folder) / "power.parquet", memory_map=False)
    if scratch is not None:
        scratch.cleanup()
    return table


class TuneResult:
    """What :func:`tune` found, and the folder holding its tables.

    ``method`` is ``"ml"``, ``"truth"`` or ``"consistency"``. For ``"ml"`` and ``"truth"``,
    :attr:`table` is
    ``tuned.parquet`` (one row per element: its estimate, standard error, 95 % interval
    ``ci_low``–``ci_high`` and whether it is identified),
    :attr:`trace` is ``tune_trace.parquet`` (every iteration of every start) and
    :attr:`tuned_toml` the tuned Q and R as TOML, ready to paste into a spec; ``details``
    holds −ln L (``objective``), ``converged``, ``runs``, ``measurements``, where the data
    came from (``data``) and ``not_identified``: one dict per direction the data do not
    identify (element name → component in ln units); for ``"truth"`` ``objective`` is the
    conditions' sum of squares and ``conditions`` their mean at the estimate (element name →
    value, 0 at an exact root), ``notes`` what the identifiability report adds (the scale
    ``objective="mse"`` cannot fix). For ``"consistency"``, :attr:`table` is
    ``tuning.parquet`` (every candidate in every cell) and ``details`` holds the tuned
    ``filter``, the best ``q_scale`` and ``r_scale``, their ``objective`` and their
    ``anees``/``anis``.
    """

    def __init__(self, details: Mapping[str, Any], *, _scratch: Any = None) -> None:
        #: The method that ran.
        self.method: str = str(details["method"])
        #: The folder holding the tables.
        self.folder: Path = Path(details["folder"])
        #: What the command prints, as a dict (see the class's description).
        self.details: Dict[str, Any] = {k: v for k, v in details.items() if k not in ("method", "folder")}
        # The temporary folder of a call without out=, removed with this object.
        self._scratch = _scratch

    def __repr__(self) -> str:
        return f"kfmc.TuneResult(method={self.method!r}, folder={str(self.folder)!r})"

    @property
    def table(self) -> pl.DataFrame:
        """``tuned.parquet`` (``ml``, ``truth``) or ``tuning.parquet`` (``consistency``)."""
        name = "tuning" if self.method == "consistency" else "tuned"
        return pl.read_parquet(self.folder / f"{name}.parquet", memory_map=False)

    @property
    def trace(self) -> pl.DataFrame:
        """``tune_trace.parquet``: every iteration of every start of the ``ml`` or ``truth``
        search."""
        if self.method == "consistency":
            raise StudyError("the consistency method keeps no iteration trace (method=\"ml\" and \"truth\" do)")
        return pl.read_parquet(self.folder / "tune_trace.parquet", memory_map=False)

    @property
    def tuned_toml(self) -> str:
        """The tuned model as TOML (``tuned.toml``; the ``ml`` and ``truth`` methods)."""
        if self.method == "consistency":
            raise StudyError("the consistency method writes no tuned.toml (method=\"ml\" and \"truth\" do)")
        return (self.folder / "tuned.toml").read_text()


def tune(
    spec: Spec,
    *,
    method: Optional[str] = None,
    elements: Optional[Sequence[str]] = None,
    measurements: Optional[PathLike] = None,
    objective: str = "consistency",
    tune_r: bool = False,
    filter: Optional[str] = None,  # noqa: A002 (the command's flag)
    out: Optional[PathLike] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    allow_large: bool = False,
    lanes: Optional[str] = None,
) -> TuneResult:
    """Tunes a filter's noise covariances (``kfmc tune``) → :class:`TuneResult`.

    ``method`` is ``"ml"``, ``"truth"`` or ``"consistency"`` (default: the spec's
    ``tune.method``, else ``"consistency"``).

    * ``"ml"``: the maximum-likelihood estimate of the ``elements`` of Q and R (e.g.
      ``["q[px,px]", "r[zx,zx]"]``; default the spec's ``tune.elements``) from the innovations
      alone, with 95 % intervals from the observed information, for linear systems. The data
      are the spec's simulation, or with ``measurements=`` a ``measurements.parquet`` in the
      layout :func:`simulate` writes (your own recorded measurements; an ``initial.parquet``
      beside it gives the priors).
    * ``"truth"``: the ``elements`` of Q and R from the spec's simulated runs and their truth,
      as the roots of one identifying condition each (``objective="consistency"``: per state
      E[e²/P] = 1, per measurement component E[ν²/S] = 1; ``objective="mse"``: the
      estimation error's minimum, which fixes ratios only), every candidate on the same runs,
      with 95 % intervals from the sandwich over runs; linear systems.
    * ``"consistency"``: the grid search of a Q multiplier (and with ``tune_r=True`` an R
      multiplier) of ``filter`` (default the first filter with a covariance) for
      ``objective="consistency"`` (ANEES closest to n and ANIS to p) or ``"rmse"``.

    Tables go to ``out``, or without it to a temporary folder that lives as long as the
    returned object. ``runs`` and ``seed`` override the spec's; ``force=True`` writes into a
    non-empty folder that is not a kfmc study; ``lanes`` is as in :func:`run`. Invalid settings
    raise :class:`SpecError`.
    """
    folder, scratch = _out(out)
    details = _pythonic(
        lambda: _kfmc.tune(
            _spec(spec),
            method=method,
            elements=None if elements is None else [str(e) for e in ([elements] if isinstance(elements, str) else elements)],
            measurements=_path(measurements),
            objective=objective,
            tune_r=tune_r,
            filter=filter,
            out=folder,
            runs=_count(runs, "runs"),
            seed=_count(seed, "seed"),
            threads=_count(threads, "threads"),
            quiet=quiet,
            force=force,
            allow_large=allow_large,
            lanes=lanes,
        )
    )
    return TuneResult(details, _scratch=scratch)


def stamp(spec: Spec, truth: Any, files: Sequence[PathLike] = ()) -> Dict[str, str]:
    """The world stamp of estimates made on a user's own runs (``kfmc stamp``): ``spec`` is a
    spec of ``model.kind = "recorded"``, ``truth`` its truth (a Parquet file's path or a
    DataFrame, as for :func:`score`). Returns the Parquet metadata keys and values (the
    truth's content hash among them) to set on an estimates table, e.g. a pyarrow Table's
    ``replace_schema_metadata``; each of ``files`` (Parquet estimates) is stamped in place,
    its rows and other metadata kept, as the command does."""
    from kfmc._estimates import _truth_input

    return dict(
        _pythonic(lambda: _kfmc.stamp(_spec(spec), _truth_input(truth), [os.fspath(f) for f in files]))
    )


def describe(spec: Spec) -> Dict[str, Any]:
    """The system's analysis for a spec (``kfmc describe``) as a dict: per scenario F, G, H,
    Q, R, the observability ranks, the steady-state gain, and per filter the tests'
    effective degrees of freedom."""
    return _pythonic(lambda: _kfmc.describe(_spec(spec)))


def schema(kind: str, spec: Spec) -> Dict[str, Any]:
    """The columns (name → type) of an exchange table for a spec (``kfmc schema``): ``kind``
    is ``"estimates"``, ``"truth"``, ``"measurements"`` or ``"initial"``. For the estimates
    also the stamp a writer puts in the file's metadata and the error convention."""
    return _kfmc.schema(kind, _spec(spec))




def _folder(study: Union[Study, Simulation, PathLike]) -> str:
    return os.fspath(study.folder if isinstance(study, (Study, Simulation)) else study)


def summary(study: Union[Study, PathLike], *, noise_scale: Optional[float] = None) -> str:
    """The RMSE table of a result folder (a :class:`Study` or its path) as ``kfmc summary``
    prints it; ``noise_scale`` keeps that truth-noise multiplier's rows only."""
    return _kfmc.summary(_folder(study), noise_scale=noise_scale)


def plot(study: Union[Study, PathLike], *, out: Optional[PathLike] = None, format: str = "png") -> List[Path]:  # noqa: A002
    """Draws every figure the folder's tables support (``kfmc plot``), as ``"png"`` or
    ``"svg"`` files in ``out`` (default: the folder's ``figures``); returns their paths."""
    return [Path(p) for p in _kfmc.plot(_folder(study), out=_path(out), format=format)]


def report(study: Union[Study, PathLike], *, out: Optional[PathLike] = None) -> Path:
    """Writes the self-contained HTML report of a folder (``kfmc report``; default
    ``report.html`` in it) and returns its path."""
    return Path(_kfmc.report(_folder(study), out=_path(out)))


def list() -> Dict[str, Any]:  # noqa: A001 (the command's name)
    """The registered systems (``kfmc list``): per ``model.kind`` its ``about`` line and its
    ``sections`` (scenarios, filter kinds, sensors, model keys, …) as name → description."""
    return _kfmc.list()


def to_toml(spec: Mapping[str, Any]) -> str:
    """A dict spec as TOML text, which ``kfmc validate`` and :func:`run` read as the dict
    (numpy scalars and arrays written as the numbers they hold)."""
    return _kfmc.to_toml_text(dict(spec))


def examples() -> Dict[str, Path]:
    """The example specs bundled with the wheel (the repository's ``experiments/``): name
    (the file's stem, e.g. ``"planar_seed_study"``) → path, sorted by name."""
    folder = Path(__file__).resolve().parent / "examples"
    return {p.stem: p for p in sorted(folder.glob("*.toml"))}
