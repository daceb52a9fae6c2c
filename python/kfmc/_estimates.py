"""Estimates tables from arrays (:class:`Estimates`) and the error transition of a
sigma-point filter (:func:`sigma_point_transition`): the exchange format written for the
user, with its column names, its stamp and its checks."""

from __future__ import annotations

import importlib
import os
import secrets
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Set, Tuple, Union

import numpy as np
import polars as pl

from kfmc import _kfmc
from kfmc._kfmc import Error, EstimatesError

#: The covariance forms of the exchange format (``kfmc schema estimates``).
COVARIANCE_FORMS = ("lower", "cholesky", "correlation")

_KEYS = ("scenario", "noise_scale", "run", "step", "filter")

#: The column that marks a failed run: true from the step the filter failed at.
_FAILED = "failed"

#: The key columns naming the variant of a filter that declares ``q_scale``/``r_scale``.
_VARIANT_KEYS = ("q_scale", "r_scale")

#: A file or folder path.
_PathLike = Union[str, "os.PathLike[str]"]


def _layout_of_simulation(simulation: Any) -> Tuple[Path, Dict[str, Any]]:
    folder = Path(getattr(simulation, "folder", simulation))
    return folder, dict(_kfmc.estimates_layout(os.fspath(folder), simulation=True))


_DIMS = {
    "x": "steps 0..=K × quantities",
    "P": "steps × quantities × quantities",
    "nu": "steps × measurement components",
    "S": "steps × components × components",
    "A": "steps × quantities × quantities",
    "quat": "steps × 4, or steps × rotations × 4",
}


def _array(value: Any, name: str, shape: Tuple[int, ...], key: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape``, or EstimatesError naming ``name``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise EstimatesError(f"{name} of {key}: not an array of numbers ({e})") from None
    if a.shape != shape:
        raise EstimatesError(
            f"{name} of {key}: shape {a.shape}, expected {shape} ({_DIMS[name]})"
        )
    return a


def _where(a: np.ndarray, bad: np.ndarray) -> Tuple[int, Tuple[int, ...], float]:
    """The first (step, entry, value) where ``bad`` holds."""
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    return idx[0], idx[1:], float(a[idx])


class Estimates:
    """An estimates table built from arrays: the exchange format's columns (``kfmc schema
    estimates``), checked as runs are added, stamped with the simulation's world.

    ``simulation`` is a :class:`kfmc.Simulation` (or its folder) and ``label`` one of its
    spec's ``kind = "external"`` filters. ``covariance`` is the form the covariance is
    written in: ``"lower"`` (``P_<qi>_<qj>``, the lower triangle), ``"cholesky"``
    (``L_<i>_<j>``, a lower Cholesky factor) or ``"correlation"`` (``var_<q>`` and
    ``corr_<qi>_<qj>``). With ``float32=True`` the covariance, innovations, S and A are
    stored as float32 — about half the bytes — while the estimates stay float64: the error
    truth − estimate needs every digit of the estimate. kfmc reads float32 as float64.

    A label whose spec entry lists ``q_scale`` and/or ``r_scale`` has variants: each run
    names its variant with ``add_run(..., q_scale=…, r_scale=…)`` (the multipliers the
    filter applied to its assumed Q and R, one of the listed values), and the table carries a
    ``q_scale``/``r_scale`` column for each listed axis. :attr:`variants` lists them.

    Add each run with :meth:`add_run` (or a batch of one cell's runs with
    :meth:`add_runs`), then pass the object to :func:`kfmc.score` or :func:`kfmc.check`
    (the stamp is checked against what it is scored on), or :meth:`write` a Parquet file,
    or take :meth:`to_polars`. Every argument is checked as it is added: a wrong shape, an
    infinite value, a key outside the simulation, a run given twice raise
    :class:`kfmc.EstimatesError` naming the argument, the run and the step.
    """

    def __init__(
        self,
        simulation: Any,
        label: str,
        *,
        covariance: str = "lower",
        float32: bool = False,
        path: Optional[_PathLike] = None,
    ) -> None:
        # Set first: a constructor that raises leaves an object __del__ can look at.
        self._writer: Optional[_StreamWriter] = None
        folder, layout = _layout_of_simulation(simulation)
        if covariance not in COVARIANCE_FORMS:
            raise EstimatesError(
                f"covariance = {covariance!r}: one of {', '.join(map(repr, COVARIANCE_FORMS))}"
            )
        external = [lbl for lbl, ext in layout["filters"] if ext]
        if label not in external:
            raise EstimatesError(
                f"label {label!r} is not an external filter of the simulation's spec ({folder}); "
                + (
                    f"its external filters: {', '.join(external)}"
                    if external
                    else 'declare one with [[filters]] label = "…", kind = "external"'
                )
            )
        #: The filter label every row carries.
        self.label: str = label
        entry = next(
            (e for e in layout.get("external_filters", []) if e["label"] == label), {"label": label}
        )
        #: The multipliers the label's variants take, per declared axis:
        #: ``{"q_scale": [0.5, 1.0, 2.0]}``; empty for a filter without variants.
        self.variants: Dict[str, List[float]] = {
            axis: [float(v) for v in entry[axis]] for axis in _VARIANT_KEYS if axis in entry
        }
        #: The covariance form: ``"lower"``, ``"cholesky"`` or ``"correlation"``.
        self.covariance: str = covariance
        #: Whether the covariance, innovations, S and A are stored as float32.
        self.float32: bool = bool(float32)
        #: The simulation folder the estimates are made on.
        self.folder: Path = folder
        self._layout = layout
        self._q: List[str] = list(layout["quantities"])
        self._z: List[str] = list(layout["measurements"])
        self._steps: Dict[str, int] = {name: int(k) for name, k in layout["scenarios"]}
        self._scales: List[float] = [float(s) for s in layout["noise_scales"]]
        self._rotations: List[Dict[str, Any]] = list(layout["rotations"])
        # Fixed by the first run: whether innovations, A and quaternions are given.
        self._parts: Optional[Tuple[bool, bool, bool]] = None
        self._first: Optional[str] = None
        # The runs held in memory (all of them, or those not yet written to `path`), and the
        # keys of every run added.
        self._runs: Dict[_RunKey, Dict[str, np.ndarray]] = {}
        self._added: Set[_RunKey] = set()
        self._rows = 0
        #: The file the table streams to (``path=``), or None for a table held in memory.
        self.path: Optional[Path] = None if path is None else Path(path)
        if self.path is not None:
            self._writer = _StreamWriter(self.path)

    def __repr__(self) -> str:
        where = "" if self.path is None else f", path={os.fspath(self.path)!r}"
        return (
            f"kfmc.Estimates(label={self.label!r}, runs={len(self._added)}, rows={len(self)}, "
            f"covariance={self.covariance!r}, float32={self.float32}{where})"
        )

    def __len__(self) -> int:
        """The rows so far: steps 0..=K of every run added."""
        return self._rows

    @property
    def buffered_rows(self) -> int:
        """The rows held in memory: every row of a table held in memory; with ``path=``,
        those not yet written, fewer than :attr:`rows_per_group` plus one run's."""
        return sum(len(v["step"]) for v in self._runs.values()) + (
            0 if self._writer is None else self._writer.carried
        )

    @property
    def rows_per_group(self) -> int:
        """Rows per Parquet row group of the file :meth:`write` (or ``path=``) writes: 2²⁰
        values per group over the columns, as kfmc's own export groups its estimates."""
        return max(1, _GROUP_VALUES // len(self.columns))

    @property
    def metadata(self) -> Dict[str, str]:
        """The stamp a file of these estimates carries: ``kfmc.world_stamp`` and
        ``kfmc.master_seed`` of the simulation."""
        return dict(self._layout["metadata"])

    @property
    def world_stamp(self) -> str:
        """The simulation's world stamp (``kfmc.world_stamp``)."""
        return str(self._layout["world_stamp"])

    @property
    def master_seed(self) -> int:
        """The simulation's master seed (``kfmc.master_seed``)."""
        return int(self._layout["master_seed"])

    @property
    def columns(self) -> List[str]:
        """The table's columns, in order (those of ``kfmc schema estimates`` with this
        covariance form; ``nu_``/``S_``, ``A_`` and ``quat_`` as the first run gave them)."""
        innovations, transition, quaternions = self._parts or (False, False, False)
        q, z = self._q, self._z
        est = [f"est_{n}" for n in q]
        if quaternions:
            for r in reversed(self._rotations):
                est[r["first"] : r["first"] + 3] = list(r["quaternion"])
        cols = list(_KEYS) + [a for a in _VARIANT_KEYS if a in self.variants] + [_FAILED]
        cols += est + self._covariance_columns()
        if innovations:
            cols += [f"nu_{n}" for n in z]
            cols += [f"S_{z[i]}_{z[j]}" for i in range(len(z)) for j in range(i + 1)]
        if transition:
            cols += [f"A_{a}_{b}" for a in q for b in q]
        return cols

    def _covariance_columns(self) -> List[str]:
        q = self._q
        tri = [(i, j) for i in range(len(q)) for j in range(i + 1)]
        if self.covariance == "lower":
            return [f"P_{q[i]}_{q[j]}" for i, j in tri]
        if self.covariance == "cholesky":
            return [f"L_{i}_{j}" for i, j in tri]
        return [f"var_{q[i]}" if i == j else f"corr_{q[i]}_{q[j]}" for i, j in tri]

    def add_run(
        self,
        scenario: str,
        noise_scale: float,
        run: int,
        x: Any,
        P: Any,
        nu: Any = None,
        S: Any = None,
        A: Any = None,
        *,
        quat: Any = None,
        failed_at: Optional[int] = None,
        q_scale: Optional[float] = None,
        r_scale: Optional[float] = None,
    ) -> None:
        """Adds one run: its rows for steps 0..=K of the scenario (row 0 the prior).

        ``x`` is (K+1, n) — the estimate of every quantity, in the order of
        ``kfmc.schema("estimates", …)`` — and ``P`` (K+1, n, n) its covariance (its lower
        triangle is what is read). ``nu`` (K+1, m) and ``S`` (K+1, m, m) are the innovation
        (NaN where a component did not report) and its covariance; ``A`` (K+1, n, n) the
        error transition (a step's A all NaN: not given). Row 0 of ``nu``, ``S`` and ``A``
        is not written (the prior has none). ``quat`` replaces a rotation's Euler angles in
        ``x`` by the unit quaternion (K+1, 4) — (K+1, r, 4) for r rotations — with ``P``'s
        rows for it the rotation error's covariance. A key from ``Simulation.runs()`` fits
        as ``add_run(*key, x=…, P=…)``.

        A filter that failed at step k: ``failed_at=k`` marks its rows from k on
        ``failed = true`` and writes them without an estimate, and kfmc counts the run a
        numerical failure at k, as its own filters'; only such runs count against
        ``[check] max_failed_runs``. A run never added is missing, not failed: a ``kfmc
        check`` case is incomplete without it, whatever the tolerance.

        ``q_scale`` and ``r_scale`` name the run's variant when the label declares variants
        (:attr:`variants`): the multipliers the filter applied to its assumed Q and R, each
        one of the spec's values; leave out an axis the label does not declare.
        """
        variant = self._variant(q_scale, r_scale)
        key = (str(scenario), float(noise_scale), int(run)) + variant
        name = f"run (scenario={key[0]!r}, noise_scale={key[1]!r}, run={key[2]}"
        for axis, v in zip(_VARIANT_KEYS, variant):
            if v is not None:
                name += f", {axis}={v!r}"
        name += ")"
        if key[0] not in self._steps:
            raise EstimatesError(
                f"scenario {key[0]!r} is not one of the simulation's: {', '.join(self._steps)}"
            )
        if key[1] not in self._scales:
            raise EstimatesError(
                f"noise_scale {key[1]!r} is not one of the simulation's: "
                f"{', '.join(repr(s) for s in self._scales)} (the values exactly)"
            )
        if not 0 <= key[2] < int(self._layout["runs"]) or key[2] != run:
            raise EstimatesError(f"run {run!r} is outside 0..{self._layout['runs']}")
        if self._writer is not None and self._writer.closed:
            raise Error(f"the estimates were written to {self.path} and closed: add runs before close()")
        if key in self._added:
            raise EstimatesError(f"{name} was added already")
        k1 = self._steps[key[0]] + 1
        n, m = len(self._q), len(self._z)
        x = _array(x, "x", (k1, n), name)
        P = _array(P, "P", (k1, n, n), name)
        parts = (nu is not None or S is not None, A is not None, quat is not None)
        if (nu is None) != (S is None):
            raise EstimatesError(
                f"{'S' if S is None else 'nu'} of {name}: give the innovation nu with its covariance S, or neither"
            )
        if self._parts is not None and parts != self._parts:
            what = ("nu and S", "A", "quat")
            i = next(i for i in range(3) if parts[i] != self._parts[i])
            raise EstimatesError(
                f"{what[i]} of {name}: {'given' if parts[i] else 'not given'}, but the first run "
                f"{self._first} {'did not give' if parts[i] else 'gave'} it; every run of a "
                "filter has the same columns (a step without one: NaN rows)"
            )
        if quat is not None and not self._rotations:
            raise EstimatesError(f"quat of {name}: the simulation's quantities have no rotation")
        end = k1
        if failed_at is not None:
            if not 0 <= int(failed_at) < k1:
                raise EstimatesError(f"failed_at of {name}: {failed_at} is outside steps 0..={k1 - 1}")
            end = int(failed_at)
        cols: Dict[str, np.ndarray] = {"step": np.arange(k1, dtype=np.int64)}
        x = x.copy()
        if quat is not None:
            r = len(self._rotations)
            qa = _array(quat, "quat", (k1, 4) if r == 1 else (k1, r, 4), name).reshape(k1, r, 4)
            bad = ~np.isfinite(qa[:end])
            if bad.any():
                s, e, v = _where(qa, bad)
                raise EstimatesError(f"quat of {name}: {v} at step {s}, entry {e}{self._failed_hint(s)}")
            norm = np.linalg.norm(qa[:end], axis=2)
            if (norm == 0).any():
                s, e, _ = _where(norm, norm == 0)
                raise EstimatesError(f"quat of {name}: a zero quaternion at step {s}")
            for ri, rot in enumerate(self._rotations):
                x[:, rot["first"] : rot["first"] + 3] = 0.0  # not written
                for ci, col in enumerate(rot["quaternion"]):
                    cols[col] = qa[:, ri, ci].copy()
        for arr, label in ((x, "x"), (P, "P")):
            bad = ~np.isfinite(arr[:end])
            if bad.any():
                s, e, v = _where(arr, bad)
                raise EstimatesError(
                    f"{label} of {name}: {v} at step {s}, entry {e}{self._failed_hint(s)}"
                )
        scale = np.sqrt(np.abs(np.einsum("kii->ki", P[:end])))
        asym = np.abs(P[:end] - P[:end].transpose(0, 2, 1)) > 1e-6 * scale[:, :, None] * scale[:, None, :]
        if asym.any():
            s, (i, j), _ = _where(P, asym)
            raise EstimatesError(
                f"P of {name}: not symmetric at step {s}: P[{i}, {j}] = {P[s, i, j]!r}, "
                f"P[{j}, {i}] = {P[s, j, i]!r} (is it P, in the order steps × n × n?)"
            )
        for i, qn in enumerate(self._q):
            cols[f"est_{qn}"] = x[:, i]
        cov = self._covariance(P, end, name)
        for c, values in zip(self._covariance_columns(), cov):
            cols[c] = values
        if nu is not None:
            self._innovations(cols, _array(nu, "nu", (k1, m), name), _array(S, "S", (k1, m, m), name), end, name)
        if A is not None:
            self._transition(cols, _array(A, "A", (k1, n, n), name), end, name)
        # Rows from failed_at on carry no estimate: the run failed there. (Every column is a
        # copy of the arguments or made here: the caller's arrays are never written.)
        if end < k1:
            for c in cols:
                if c != "step":
                    cols[c] = cols[c].copy()
                    cols[c][end:] = np.nan
        cols[_FAILED] = np.arange(k1) >= end
        if self._parts is None:
            self._parts, self._first = parts, name
        self._runs[key] = cols
        self._added.add(key)
        self._rows += k1
        if self._writer is not None and self.buffered_rows >= self.rows_per_group:
            self._writer.write(self._frame(), self._arrow, self._options(), final=False)
            self._runs.clear()

    def _variant(
        self, q_scale: Optional[float], r_scale: Optional[float]
    ) -> Tuple[Optional[float], Optional[float]]:
        """The run's (q_scale, r_scale) key: a declared value on each declared axis, None on
        the others."""
        out: List[Optional[float]] = []
        for axis, value in zip(_VARIANT_KEYS, (q_scale, r_scale)):
            declared = self.variants.get(axis)
            if declared is None:
                if value is not None:
                    raise EstimatesError(
                        f"{axis}={value!r}: filter {self.label!r} declares no {axis} variants in "
                        f"the spec (list {axis} = [...] in its [[filters]] entry to score variants)"
                    )
                out.append(None)
                continue
            values = ", ".join(f"{v:g}" for v in declared)
            if value is None:
                raise EstimatesError(
                    f"{axis}: filter {self.label!r} declares {axis} = {values}; "
                    f"add_run(..., {axis}=…) names the run's variant"
                )
            v = float(value)
            if v not in declared:
                raise EstimatesError(
                    f"{axis}={value!r} is not a variant of filter {self.label!r}, which declares "
                    f"{axis} = {values} (the values exactly)"
                )
            out.append(v)
        return out[0], out[1]

    @staticmethod
    def _failed_hint(step: int) -> str:
        return (
            f"; a filter that failed at step {step}: add_run(..., failed_at={step}) records it "
            "as a numerical failure there"
        )

    def _covariance(self, P: np.ndarray, end: int, name: str) -> List[np.ndarray]:
        n = len(self._q)
        tri = [(i, j) for i in range(n) for j in range(i + 1)]
        if self.covariance == "lower":
            return [P[:, i, j].copy() for i, j in tri]
        if self.covariance == "cholesky":
            L = np.full_like(P, np.nan)
            # numpy's Cholesky reads the lower triangle, as kfmc does.
            sym = np.tril(P[:end]) + np.tril(P[:end], -1).transpose(0, 2, 1)
            for k in range(end):
                try:
                    L[k] = np.linalg.cholesky(sym[k])
                except np.linalg.LinAlgError:
                    raise EstimatesError(
                        f"P of {name}: not positive definite at step {k}, so it has no Cholesky "
                        f"factor; covariance='lower' writes it as it is (kfmc counts the run a "
                        f"numerical failure there){self._failed_hint(k)}"
                    ) from None
            return [L[:, i, j] for i, j in tri]
        var = np.einsum("kii->ki", P).copy()
        bad = var[:end] <= 0
        if bad.any():
            s, (i,), v = _where(var, bad)
            raise EstimatesError(
                f"P of {name}: the variance of {self._q[i]} is {v} at step {s}; the correlation "
                f"form needs positive variances (covariance='lower' writes it as it is)"
                f"{self._failed_hint(s)}"
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            sd = np.sqrt(var)
            out = []
            for i, j in tri:
                out.append(var[:, i] if i == j else P[:, i, j] / (sd[:, i] * sd[:, j]))
        return out

    def _innovations(
        self, cols: Dict[str, np.ndarray], nu: np.ndarray, S: np.ndarray, end: int, name: str
    ) -> None:
        m = len(self._z)
        nu, S = nu.copy(), S.copy()
        nu[0], S[0] = np.nan, np.nan  # the prior has no innovation
        inf = np.isinf(nu[:end])
        if inf.any():
            s, e, v = _where(nu, inf)
            raise EstimatesError(f"nu of {name}: {v} at step {s}, entry {e} (NaN means not reported)")
        reported = np.isfinite(nu)
        both = reported[:, :, None] & reported[:, None, :]
        bad = both[:end] & ~np.isfinite(S[:end])
        if bad.any():
            s, (i, j), v = _where(S, bad)
            raise EstimatesError(
                f"S of {name}: {v} at step {s}, entry ({i}, {j}), where nu reported "
                f"{self._z[i]} and {self._z[j]}"
            )
        for i, zn in enumerate(self._z):
            cols[f"nu_{zn}"] = nu[:, i]
        for i in range(m):
            for j in range(i + 1):
                cols[f"S_{self._z[i]}_{self._z[j]}"] = np.where(both[:, i, j], S[:, i, j], np.nan)

    def _transition(self, cols: Dict[str, np.ndarray], A: np.ndarray, end: int, name: str) -> None:
        A = A.copy()
        A[0] = np.nan  # the prior has none
        inf = np.isinf(A[:end])
        if inf.any():
            s, e, v = _where(A, inf)
            raise EstimatesError(f"A of {name}: {v} at step {s}, entry {e}")
        given = np.isfinite(A[:end]).reshape(end, -1)
        partial = given.any(axis=1) & ~given.all(axis=1)
        if partial.any():
            s = int(np.argmax(partial))
            entry = tuple(int(i) for i in np.unravel_index(int(np.argmin(given[s])), A.shape[1:]))
            raise EstimatesError(
                f"A of {name}: NaN at step {s}, entry {entry}, where the step "
                "gives other entries (give a step's whole error transition, or none: all NaN)"
            )
        for i, a in enumerate(self._q):
            for j, b in enumerate(self._q):
                cols[f"A_{a}_{b}"] = A[:, i, j]

    def add_runs(
        self,
        scenario: str,
        noise_scale: float,
        runs: Sequence[int],
        x: Any,
        P: Any,
        nu: Any = None,
        S: Any = None,
        A: Any = None,
        *,
        quat: Any = None,
        q_scale: Optional[float] = None,
        r_scale: Optional[float] = None,
    ) -> None:
        """Adds several runs of one cell at once: the arrays of :meth:`add_run` with a first
        axis for the runs (``x`` (R, K+1, n), ``P`` (R, K+1, n, n), …), e.g. from a filter
        vectorised over runs; ``q_scale``/``r_scale`` name the runs' variant, as for
        :meth:`add_run`."""
        runs = list(runs)
        arrays = {"x": x, "P": P, "nu": nu, "S": S, "A": A, "quat": quat}
        for arg, a in arrays.items():
            if a is not None and len(a) != len(runs):
                raise EstimatesError(
                    f"{arg}: {len(a)} runs along the first axis, but {len(runs)} run indices"
                )
        for i, r in enumerate(runs):
            self.add_run(
                scenario,
                noise_scale,
                r,
                x[i],
                P[i],
                None if nu is None else nu[i],
                None if S is None else S[i],
                None if A is None else A[i],
                quat=None if quat is None else quat[i],
                q_scale=q_scale,
                r_scale=r_scale,
            )

    def to_polars(self) -> pl.DataFrame:
        """The table: one row per run and step, in the order the runs were added, with the
        columns of :attr:`columns` (null where a value is not given). With ``path=`` the
        table is the file's, once closed."""
        if self._writer is not None:
            if not self._writer.closed:
                raise Error(
                    f"the estimates stream to {self.path}: close() them first (the rows written "
                    "are no longer in memory)"
                )
            return pl.read_parquet(self._writer.path)
        if not self._runs:
            raise EstimatesError("no runs added: an estimates table needs at least one run")
        return self._frame()

    def _frame(self) -> pl.DataFrame:
        """The runs held in memory as the table's rows."""
        variant_keys = [a for a in _VARIANT_KEYS if a in self.variants]
        values = [c for c in self.columns if c not in _KEYS and c not in variant_keys]
        f32 = pl.Float32 if self.float32 else pl.Float64
        keep64 = {c for c in values if c.startswith("est_") or c.startswith("quat_")}
        keys: Dict[str, List[Any]] = {"scenario": [], "noise_scale": [], "run": [], "q_scale": [], "r_scale": []}
        steps: List[np.ndarray] = []
        data: Dict[str, List[np.ndarray]] = {c: [] for c in values}
        for (scenario, scale, run, q, r), cols in self._runs.items():
            k1 = len(cols["step"])
            keys["q_scale"].append(np.full(k1, np.nan if q is None else q))
            keys["r_scale"].append(np.full(k1, np.nan if r is None else r))
            keys["scenario"].append(pl.repeat(scenario, k1, eager=True, dtype=pl.String))
            keys["noise_scale"].append(np.full(k1, scale))
            keys["run"].append(np.full(k1, run, dtype=np.int64))
            steps.append(cols["step"])
            for c in values:
                data[c].append(cols[c])
        series = [
            pl.concat(keys["scenario"]).alias("scenario"),
            pl.Series("noise_scale", np.concatenate(keys["noise_scale"]), dtype=pl.Float64),
            pl.Series("run", np.concatenate(keys["run"]), dtype=pl.Int64),
            pl.Series("step", np.concatenate(steps), dtype=pl.Int64),
            pl.repeat(self.label, sum(len(s) for s in steps), eager=True, dtype=pl.String).alias("filter"),
        ]
        for axis in variant_keys:
            series.append(pl.Series(axis, np.concatenate(keys[axis]), dtype=pl.Float64))
        for c in values:
            if c == _FAILED:
                series.append(pl.Series(c, np.concatenate(data[c]), dtype=pl.Boolean))
                continue
            dtype = pl.Float64 if c in keep64 else f32
            a = np.concatenate(data[c]).astype(np.float64 if dtype == pl.Float64 else np.float32)
            series.append(pl.Series(c, a, dtype=dtype, nan_to_null=True))
        return pl.DataFrame(series)

    def __arrow_c_stream__(self, requested_schema: Optional[object] = None) -> object:
        """The table through the Arrow C stream interface (what :meth:`to_polars` gives)."""
        return self.to_polars().__arrow_c_stream__(requested_schema)

    def _arrow(self, df: pl.DataFrame) -> Any:
        """The rows as the pyarrow Table :meth:`write` writes: the stamp in its schema."""
        table = df.to_arrow()
        return table.replace_schema_metadata({**(table.schema.metadata or {}), **self.metadata})

    def _options(self) -> Dict[str, Any]:
        """pyarrow's writer options: byte-stream-split floats, zstd, dictionaries for the
        two string keys only, row groups of :attr:`rows_per_group`."""
        floats = [c for c in self.columns if c not in _KEYS and c not in _VARIANT_KEYS and c != _FAILED]
        return dict(
            compression="zstd",
            use_dictionary=["scenario", "filter"],
            use_byte_stream_split=floats,
            row_group_size=self.rows_per_group,
        )

    def write(self, path: Optional[_PathLike] = None) -> Path:
        """Writes the table as Parquet carrying the simulation's stamp (:attr:`metadata`):
        what ``kfmc score SIM --estimates FILE`` and ``kfmc check`` read. With pyarrow
        installed the float columns are written byte-stream-split and zstd-compressed
        without dictionaries (the smallest files measured), in row groups of
        :attr:`rows_per_group`; else polars writes them. With ``path=`` given at the start,
        ``write()`` is :meth:`close`."""
        if self._writer is not None:
            if path is not None and Path(path) != self.path:
                raise Error(f"the estimates stream to {self.path}, not {path}")
            return self.close()
        if path is None:
            raise TypeError("write() needs the file's path (or Estimates(..., path=…) at the start)")
        path = Path(path)
        df = self.to_polars()
        try:
            pq: Any = importlib.import_module("pyarrow.parquet")
        except ImportError:
            pq = None
        if pq is not None:
            pq.write_table(self._arrow(df), path, **self._options())
        else:
            try:
                df.write_parquet(path, compression="zstd", metadata=self.metadata)
            except TypeError:
                raise Error(
                    "writing the stamp needs pyarrow or polars >= 1.26 (write_parquet's "
                    "metadata): pip install pyarrow"
                ) from None
        return path

    def close(self) -> Path:
        """Ends a table that streams to ``path=``: writes the rows still held and moves the
        file into place (until then it is written under a temporary name beside it, so the
        path never holds part of a table). Returns the path. Closing twice is harmless."""
        if self._writer is None:
            raise Error("close() ends estimates made with path=…; write(path) writes these")
        if not self._writer.closed:
            if not self._rows:
                self._writer.abort()
                raise EstimatesError("no runs added: an estimates table needs at least one run")
            frame = self._frame() if self._runs else None
            self._writer.write(frame, self._arrow, self._options(), final=True)
            self._runs.clear()
            self._writer.commit()
        assert self.path is not None
        return self.path

    def abort(self) -> None:
        """Drops a table that streams to ``path=``: its temporary file is removed, and
        nothing is written at the path. What leaving a ``with`` block by an exception does."""
        if self._writer is not None:
            self._writer.abort()

    def __enter__(self) -> "Estimates":
        return self

    def __exit__(self, kind: Any, value: Any, traceback: Any) -> None:
        if self._writer is None:
            return
        if kind is None:
            self.close()
        else:
            self.abort()

    def __del__(self) -> None:
        # A loop abandoned without close() leaves no temporary file behind.
        writer = getattr(self, "_writer", None)
        if writer is not None and not writer.closed:
            writer.abort()


_RunKey = Tuple[str, float, int, Optional[float], Optional[float]]

#: Values per row group (rows × columns), as kfmc's export (``ESTIMATES_GROUP_VALUES``).
_GROUP_VALUES = 1 << 20


class _StreamWriter:
    """A Parquet file written row group by row group under a temporary name beside
    ``path`` (``.kfmc-<token>-0.<name>.partial``, unique to it) and renamed to ``path`` on
    :meth:`commit`: the rows of
    every group but the last are exactly ``rows_per_group``, as ``pq.write_table`` cuts the
    whole table, so the file is the one :meth:`Estimates.write` writes."""

    def __init__(self, path: Path) -> None:
        try:
            self._pq: Any = importlib.import_module("pyarrow.parquet")
        except ImportError:
            raise Error(
                "Estimates(..., path=…) streams the rows through pyarrow's Parquet writer: "
                "pip install pyarrow (or leave out path= and write(path) at the end)"
            ) from None
        self.path = path
        # A name of kfmc's own, taken exclusively (never a user's ``.<name>.partial``, never
        # through a symbolic link), so that nothing else's file is written over or removed.
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
        while True:
            self.tmp = path.with_name(f".kfmc-{secrets.token_hex(8)}-0.{path.name}.partial")
            try:
                fd = os.open(self.tmp, flags, 0o666)
                break
            except FileExistsError:
                continue
        # The file created, by identity: pyarrow opens it by name, so each use checks that the
        # name still holds this file and not something put there since.
        st = os.fstat(fd)
        os.close(fd)
        self._identity = (st.st_dev, st.st_ino)
        self._writer: Any = None
        # Rows of the last flush beyond a whole group, written with the next.
        self._carry: Optional[pl.DataFrame] = None
        self.closed = False

    @property
    def carried(self) -> int:
        return 0 if self._carry is None else self._carry.height

    def write(
        self,
        frame: Optional[pl.DataFrame],
        arrow: Callable[[pl.DataFrame], Any],
        options: Dict[str, Any],
        *,
        final: bool,
    ) -> None:
        """Writes whole groups of the carried rows and ``frame`` (and with ``final`` the
        rest), carrying what is left."""
        parts = [p for p in (self._carry, frame) if p is not None]
        if not parts:
            return
        df = pl.concat(parts) if len(parts) > 1 else parts[0]
        rows = int(options["row_group_size"])
        at = 0
        while df.height - at >= rows or (final and at < df.height):
            group = arrow(df.slice(at, rows).rechunk())
            if self._writer is None:
                self._check_tmp()
                opts = {k: v for k, v in options.items() if k != "row_group_size"}
                self._writer = self._pq.ParquetWriter(self.tmp, group.schema, **opts)
            self._writer.write_table(group, row_group_size=rows)
            at += rows
        self._carry = df.slice(at) if at < df.height else None

    def _check_tmp(self) -> None:
        """Raises :class:`kfmc.Error` when the temporary file is no longer the one created."""
        try:
            st = os.lstat(self.tmp)
            same = (st.st_dev, st.st_ino) == self._identity
        except FileNotFoundError:
            same = False
        if not same:
            # Whatever is at the name now is not this stream's: it is neither written nor
            # removed, and the stream is over.
            self.closed = True
            raise Error(
                f"the estimates streamed to {self.tmp} are gone: something removed or replaced that "
                f"temporary file before close(), so nothing was written at {self.path}; add the runs again"
            )

    def commit(self) -> None:
        self._writer.close()
        self.closed = True
        self._check_tmp()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._carry = None
        try:
            if self._writer is not None:
                self._writer.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def _points(a: Any, name: str, rows: Optional[int] = None) -> np.ndarray:
    try:
        p = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise EstimatesError(f"{name}: not an array of numbers ({e})") from None
    if p.ndim == 1:
        p = p[:, None]
    if p.ndim != 2 or (rows is not None and p.shape[0] != rows):
        want = f"({rows}, …)" if rows is not None else "(points, dimension)"
        raise EstimatesError(f"{name}: shape {np.shape(a)}, expected {want}: one row per sigma point")
    if not np.isfinite(p).all():
        i = tuple(int(v) for v in np.argwhere(~np.isfinite(p))[0])
        raise EstimatesError(f"{name}: {p[i]} at point {i[0]}, entry {i[1]}")
    return p


def _deviations(p: np.ndarray, wm: np.ndarray, residual: Optional[Callable[[Any, Any], Any]]) -> np.ndarray:
    """The points' deviations from their weighted mean. With ``residual`` (a ⊖ b), taken
    from the first point and then centred, so an angle's mean never straddles its wrap."""
    if residual is None:
        return p - wm @ p
    d = np.array([np.asarray(residual(pi, p[0]), dtype=np.float64).reshape(-1) for pi in p])
    return d - wm @ d


def _regression(
    x: np.ndarray, g: np.ndarray, wm: np.ndarray, wc: np.ndarray,
    rx: Optional[Callable[[Any, Any], Any]], rg: Optional[Callable[[Any, Any], Any]], what: str,
) -> np.ndarray:
    """G̃ = C_gx C_xx⁻¹ over the weighted points (the statistical linearisation of g)."""
    dx, dg = _deviations(x, wm, rx), _deviations(g, wm, rg)
    cxx = (dx * wc[:, None]).T @ dx
    cgx = (dg * wc[:, None]).T @ dx
    try:
        np.linalg.cholesky(cxx)
    except np.linalg.LinAlgError:
        raise EstimatesError(
            f"{what}: their weighted covariance is not positive definite, so they do not span "
            "the state (are they the points, one per row, with their weights?)"
        ) from None
    return np.linalg.solve(cxx, cgx.T).T


def sigma_point_transition(
    sigmas: Any,
    sigmas_f: Any,
    Wm: Any,
    Wc: Any,
    *,
    K: Any = None,
    sigmas_update: Any = None,
    sigmas_h: Any = None,
    residual_x: Optional[Callable[[Any, Any], Any]] = None,
    residual_z: Optional[Callable[[Any, Any], Any]] = None,
) -> np.ndarray:
    """The error transition A_k of one step of a sigma-point filter (UKF, CKF), as the
    ``A_*`` columns of an estimates table want it: e_k ≈ A_k e_{k−1} + noise.

    Predict: ``sigmas`` (N, n) are the points drawn from (x̂_{k−1}, P_{k−1}) and
    ``sigmas_f`` (N, n) their images f(χ_i, u_k), with the weights ``Wm`` and ``Wc`` (N,).
    Their statistical linearisation is F̃ = C_fx C_xx⁻¹ with C_fx = Σ Wc_i (f(χ_i) − f̄)(χ_i
    − x̄)ᵀ and C_xx = Σ Wc_i (χ_i − x̄)(χ_i − x̄)ᵀ (= P_{k−1} for the usual symmetric points).
    Without an update A_k = F̃.

    Update: ``K`` (n, m) the gain, ``sigmas_update`` (N, n) the points the update drew
    (from x̂⁻_k, P⁻_k) and ``sigmas_h`` (N, m) their images h(χ_i); then H̃ = C_hx C_xx⁻¹
    over those points and A_k = (I − K H̃) F̃. For a component that did not report, leave
    its column out of ``K`` and ``sigmas_h`` alike. ``residual_x`` and ``residual_z`` (a,
    b) → a ⊖ b wrap angle components, as FilterPy's arguments of the same names.

    With FilterPy's ``UnscentedKalmanFilter`` the predict points must be kept before
    ``predict()`` replaces ``ukf.sigmas_f`` by points redrawn from (x̂⁻, P⁻) — those carry Q
    and are not f of anything, and F̃ formed from them is wrong (see the book's page
    "Judging estimators written in any language"). The points ``update()`` uses are then
    ``ukf.sigmas_f`` and their images ``ukf.sigmas_h``, with ``ukf.K``.
    """
    chi = _points(sigmas, "sigmas")
    npts, n = chi.shape
    chi_f = _points(sigmas_f, "sigmas_f", npts)
    if chi_f.shape[1] != n:
        raise EstimatesError(f"sigmas_f: {chi_f.shape[1]} columns, but sigmas has {n} (f maps the state to itself)")
    wm = _points(Wm, "Wm", npts)[:, 0]
    wc = _points(Wc, "Wc", npts)[:, 0]
    f = _regression(chi, chi_f, wm, wc, residual_x, residual_x, "sigmas")
    parts = (K is None, sigmas_update is None, sigmas_h is None)
    if all(parts):
        return f
    if any(parts):
        missing = [a for a, p in zip(("K", "sigmas_update", "sigmas_h"), parts) if p]
        raise EstimatesError(
            f"{', '.join(missing)}: the update needs K, sigmas_update and sigmas_h together"
        )
    chi_u = _points(sigmas_update, "sigmas_update", npts)
    if chi_u.shape[1] != n:
        raise EstimatesError(f"sigmas_update: {chi_u.shape[1]} columns, but the state has {n}")
    zeta = _points(sigmas_h, "sigmas_h", npts)
    m = zeta.shape[1]
    gain = np.asarray(K, dtype=np.float64)
    if gain.ndim == 1:
        gain = gain[:, None]
    if gain.shape != (n, m) or not np.isfinite(gain).all():
        raise EstimatesError(
            f"K: shape {np.shape(K)}, expected ({n}, {m}) (states × the components in sigmas_h), all finite"
        )
    h = _regression(chi_u, zeta, wm, wc, residual_x, residual_z, "sigmas_update")
    return (np.eye(n) - gain @ h) @ f


def _truth_input(truth: Any) -> Any:
    """A recorded truth for :func:`kfmc.score`: a Parquet file's path as a ``str``, or one
    table with ``__arrow_c_stream__`` (a polars DataFrame in one chunk, a pyarrow Table; a
    pandas DataFrame through polars). Its columns: ``scenario``, ``noise_scale``, ``run``,
    ``step``, ``t`` and ``truth_<q>`` for every state of the recorded spec."""
    if isinstance(truth, (str, os.PathLike)):
        return os.fspath(truth)
    if isinstance(truth, pl.DataFrame):
        return truth.rechunk()
    if type(truth).__module__.startswith("pandas"):
        return pl.from_pandas(truth)
    if hasattr(truth, "__arrow_c_stream__"):
        return truth
    raise TypeError(
        "truth must be a Parquet file's path, a polars or pandas DataFrame or a pyarrow "
        f"Table; got {type(truth).__name__}"
    )
