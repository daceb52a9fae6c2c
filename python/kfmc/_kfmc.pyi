# The compiled module (py/src/lib.rs); the documented API is kfmc/__init__.py.
import os
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union, final

__all__ = [
    "__version__",
    "Error",
    "SpecError",
    "EstimatesError",
    "StudyError",
    "IncompleteError",
    "CheckFailedError",
    "cli_main",
    "validate",
    "run",
    "simulate",
    "score",
    "check",
    "power",
    "tune",
    "stamp",
    "describe",
    "schema",
    "load_toml",
    "to_toml_text",
    "summary",
    "plot",
    "report",
    "list",
    "FilterModel",
    "filter_model",
    "simulation_model",
    "estimates_layout",
    "ulog_nis",
]

__version__: str

class Error(ValueError): ...
class SpecError(Error): ...
class EstimatesError(Error): ...
class StudyError(Error): ...
class IncompleteError(Error): ...
class CheckFailedError(Error): ...

_Spec = Union[str, "os.PathLike[str]", Dict[str, Any]]
_Path = Union[str, "os.PathLike[str]"]

def cli_main(argv: Sequence[str]) -> int: ...
def validate(spec: _Spec, *, allow_large: bool = False) -> Dict[str, Any]: ...
def run(
    spec: _Spec,
    *,
    out: Optional[_Path] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    resume: bool = False,
    force: bool = False,
    allow_large: bool = False,
    checkpoint_every: float = 10.0,
    lanes: Optional[str] = None,
) -> Dict[str, Any]: ...
def simulate(
    spec: _Spec,
    *,
    out: Optional[_Path] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    allow_large: bool = False,
    lanes: Optional[str] = None,
) -> Dict[str, Any]: ...
def score(
    simulation: _Path,
    paths: Sequence[_Path],
    streams: Iterable[Any],
    *,
    out: Optional[_Path] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    truth: Any = None,
) -> Dict[str, Any]: ...
def check(
    spec: _Spec,
    paths: Sequence[_Path],
    streams: Iterable[Any],
    *,
    out: Optional[_Path] = None,
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
    truth: Any = None,
    lanes: Optional[str] = None,
) -> Dict[str, Any]: ...
def stamp(spec: _Spec, truth: Any, files: Sequence[_Path]) -> Dict[str, str]: ...
def power(
    spec: _Spec,
    replications: int,
    *,
    out: Optional[_Path] = None,
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
    target_power: Optional[float] = None,
    against: Optional[str] = None,
    lanes: Optional[str] = None,
) -> Tuple["os.PathLike[str]", Optional[str]]: ...
def tune(
    spec: _Spec,
    *,
    method: Optional[str] = None,
    elements: Optional[Sequence[str]] = None,
    measurements: Optional[Union[str, "os.PathLike[str]"]] = None,
    objective: str = "consistency",
    tune_r: bool = False,
    filter: Optional[str] = None,  # noqa: A002
    out: Optional[Union[str, "os.PathLike[str]"]] = None,
    runs: Optional[int] = None,
    seed: Optional[int] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
    allow_large: bool = False,
    lanes: Optional[str] = None,
) -> Dict[str, Any]: ...
def describe(spec: _Spec) -> Dict[str, Any]: ...
def schema(kind: str, spec: _Spec) -> Dict[str, Any]: ...
def load_toml(path: _Path) -> Dict[str, Any]: ...
def to_toml_text(spec: Dict[str, Any]) -> str: ...
def summary(folder: _Path, *, noise_scale: Optional[float] = None) -> str: ...
def plot(folder: _Path, *, out: Optional[_Path] = None, format: str = "png") -> List["os.PathLike[str]"]: ...
def report(folder: _Path, *, out: Optional[_Path] = None) -> "os.PathLike[str]": ...
def list() -> Dict[str, Any]: ...

_Rows = List[List[float]]

@final
class FilterModel:
    @property
    def kind(self) -> str: ...
    @property
    def states(self) -> List[str]: ...
    @property
    def inputs(self) -> List[str]: ...
    @property
    def measurements(self) -> List[str]: ...
    @property
    def dt_s(self) -> float: ...
    @property
    def measurement_uses_input(self) -> bool: ...
    @property
    def angle_states(self) -> List[int]: ...
    @property
    def angle_measurements(self) -> List[int]: ...
    @property
    def q(self) -> _Rows: ...
    @property
    def r(self) -> _Rows: ...
    @property
    def p0(self) -> _Rows: ...
    @property
    def x0(self) -> List[Tuple[str, List[float]]]: ...
    @property
    def step_convention(self) -> Dict[str, Any]: ...
    def f(self, x: Sequence[float], u: Sequence[float]) -> List[float]: ...
    def h(self, x: Sequence[float], u: Sequence[float]) -> List[float]: ...
    def transition_jacobian(self, x: Sequence[float], u: Sequence[float]) -> _Rows: ...
    def measurement_jacobian(self, x: Sequence[float], u: Sequence[float]) -> _Rows: ...
    def residual(self, z: Sequence[float], z_pred: Sequence[float]) -> List[float]: ...
    def f_many(self, xs: Sequence[Sequence[float]], us: Sequence[Sequence[float]]) -> _Rows: ...
    def h_many(self, xs: Sequence[Sequence[float]], us: Sequence[Sequence[float]]) -> _Rows: ...
    def residual_many(self, zs: Sequence[Sequence[float]], z_preds: Sequence[Sequence[float]]) -> _Rows: ...
    def availability(self, step: int) -> List[bool]: ...
    def linear(self) -> Optional[Tuple[_Rows, _Rows, _Rows]]: ...

def filter_model(spec: _Spec) -> FilterModel: ...
def simulation_model(folder: _Path) -> FilterModel: ...
def estimates_layout(source: Union[_Spec, _Path], *, simulation: bool) -> Dict[str, Any]: ...
def ulog_nis(
    path: str,
    *,
    out: str,
    instance: str = "primary",
    sensors: Sequence[str] = ...,
    alpha: float = 0.05,
    holdoff: Optional[float] = None,
    include_ground: bool = False,
    baseline: Optional[str] = None,
    tolerance: Optional[float] = None,
    force: bool = False,
) -> Dict[str, Any]: ...
