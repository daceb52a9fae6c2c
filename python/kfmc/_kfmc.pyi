# The compiled module (py/src/lib.rs); the documented API is kfmc/__init__.py.
import os
from typing import Any, Dict, List, Optional, Sequence, Union

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
    "describe",
    "schema",
    "load_toml",
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
) -> Dict[str, Any]: ...
def score(
    simulation: _Path,
    paths: Sequence[_Path],
    streams: Sequence[Any],
    *,
    out: Optional[_Path] = None,
    threads: Optional[int] = None,
    quiet: bool = False,
    force: bool = False,
) -> Dict[str, Any]: ...
def check(
    spec: _Spec,
    paths: Sequence[_Path],
    streams: Sequence[Any],
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
) -> Dict[str, Any]: ...
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
    spending: str = "obrien-fleming",
    futility: Optional[float] = None,
) -> "os.PathLike[str]": ...
def describe(spec: _Spec) -> Dict[str, Any]: ...
def schema(kind: str, spec: _Spec) -> Dict[str, Any]: ...
def load_toml(path: _Path) -> Dict[str, Any]: ...
