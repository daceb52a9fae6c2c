"""Time and memory of `kfmc.score` by the route the estimates take, for the figures on the
book's Python page (docs/src/guide/python.md, "Measured") and performance page.

    python3 examples/python/bench_score_routes.py prepare DIR [RUNS]
    python3 examples/python/bench_score_routes.py file|memory|generator DIR

`prepare` simulates `experiments/external_filterpy_l1.toml` with RUNS runs (10,000 by
default) into DIR/sim and writes the estimates of its two outside filters into
DIR/own/estimates.parquet: kfmc's own KF under their labels (`kfmc run --export-estimates`
of the spec with them made `kind = "ekf"`), 201 rows per run and filter. The routes then
score them against DIR/sim into DIR/<route>: `file` gives the file's path, `memory` a polars
DataFrame read whole first (`pl.read_parquet`, one chunk per row group), `generator` pyarrow
Tables of 500 runs each, made one at a time (`ParquetFile.iter_batches`). Each prints the
call's wall and CPU time, the RSS before it (the DataFrame, for `memory`) and the peak RSS
during it (`/proc/self/clear_refs` resets the peak before the call; Linux only). Run the
routes in turn, several times: on a shared machine the ratios of neighbouring runs mean
more than the times.
"""

import os
import pathlib
import resource
import shutil
import subprocess
import sys
import time

import kfmc

ROOT = pathlib.Path(__file__).resolve().parents[2]
SPEC = ROOT / "experiments" / "external_filterpy_l1.toml"


def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


def prepare(folder, runs):
    kfmc.simulate(SPEC, out=folder / "sim", runs=runs, force=True, quiet=True)
    # The outside filters as kfmc's own KF, without kfmc's `kf` and the gate that names it.
    text = SPEC.read_text().split("[[check.assert]]")[0]
    text = text.replace('[[filters]]\nlabel = "kf"\nkind = "ekf"\n\n', "")
    own = folder / "own.toml"
    own.write_text(text.replace('kind = "external"', 'kind = "ekf"'))
    kfmc_cli = pathlib.Path(sys.executable).parent / "kfmc"
    subprocess.run(
        [str(kfmc_cli) if kfmc_cli.exists() else "kfmc", "run", str(own), "--runs", str(runs),
         "--out", str(folder / "own"), "--export-estimates", "--force", "-q"],
        check=True,
    )


def score(route, folder):
    est = folder / "own" / "estimates.parquet"
    out = folder / route
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    if route == "memory":
        import polars as pl

        estimates = pl.read_parquet(est)
    elif route == "generator":
        import pyarrow as pa
        import pyarrow.parquet as pq

        batches = pq.ParquetFile(est).iter_batches(batch_size=201 * 500)
        estimates = (pa.Table.from_batches([b]) for b in batches)
    elif route == "file":
        estimates = est
    else:
        sys.exit(f"unknown route {route!r}: file, memory or generator")
    t1 = time.perf_counter()
    held = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # the peak from here on
    c0 = resource.getrusage(resource.RUSAGE_SELF)
    kfmc.score(folder / "sim", estimates, out=out, quiet=True)
    t2 = time.perf_counter()
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime
    peak = status("VmHWM")
    print(
        f"{route}: read {t1 - t0:.2f} s, score {t2 - t1:.2f} s (CPU {cpu:.1f} s), "
        f"RSS before {held:.0f} MiB, peak during {peak:.0f} MiB (+{peak - held:.0f})"
    )


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    if sys.argv[1] == "prepare":
        prepare(pathlib.Path(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 10_000)
    else:
        score(sys.argv[1], pathlib.Path(sys.argv[2]))
