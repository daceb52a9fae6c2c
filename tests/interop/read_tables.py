#!/usr/bin/env python3
"""Reads every table of a kfmc result folder with pyarrow, pandas, DuckDB and polars and
checks they agree with manifest.toml and with each other.

Usage: python3 tests/interop/read_tables.py RESULTS_DIR
Exit 0 when every reader agrees; 1 with a message otherwise; 3 when a reader is missing.
"""
import pathlib
import sys
import tomllib

try:
    import duckdb
    import pandas
    import polars
    import pyarrow.parquet as pq
except ImportError as e:  # the Rust test decides whether a missing reader is fatal
    print(f"missing reader: {e}", file=sys.stderr)
    sys.exit(3)

d = pathlib.Path(sys.argv[1])
manifest = tomllib.loads((d / "manifest.toml").read_text())
failures = []
for t in manifest["tables"]:
    path = d / f"{t['name']}.parquet"
    rows = t["rows"]
    arrow = pq.read_table(path)
    pdf = pandas.read_parquet(path)
    ddb = duckdb.sql(f"SELECT COUNT(*) FROM read_parquet('{path}')").fetchall()[0][0]
    pl = polars.read_parquet(path)
    counts = {"pyarrow": arrow.num_rows, "pandas": len(pdf), "duckdb": ddb, "polars": pl.height}
    if any(c != rows for c in counts.values()):
        failures.append(f"{path.name}: manifest says {rows} rows, readers say {counts}")
    if list(pdf.columns) != arrow.column_names or pl.columns != arrow.column_names:
        failures.append(f"{path.name}: column names differ between readers")
    # Numeric agreement: the sum of every float column, per reader.
    for c in arrow.schema:
        if str(c.type) == "double":
            a = pdf[c.name].sum(skipna=True)
            b = duckdb.sql(f"SELECT COALESCE(SUM(\"{c.name}\"), 0) FROM read_parquet('{path}')").fetchall()[0][0]
            p = pl[c.name].sum()
            if not (abs(a - b) <= 1e-9 * max(1.0, abs(a)) and abs(a - p) <= 1e-9 * max(1.0, abs(a))):
                failures.append(f"{path.name}.{c.name}: sums differ pandas={a} duckdb={b} polars={p}")

runs = pandas.read_parquet(d / "runs.parquet")
expected = ["scenario", "noise_scale", "filter", "q_scale", "r_scale", "run", "seed", "status"]
if list(runs.columns[:8]) != expected:
    failures.append(f"runs.parquet key columns {list(runs.columns[:8])} != {expected}")
rm = runs[runs["filter"] == "running_mean"]
if len(rm) and rm["nees_mean"].notna().any():
    failures.append("running_mean rows must have null nees_mean")
if failures:
    print("\n".join(failures), file=sys.stderr)
    sys.exit(1)
print(f"{len(manifest['tables'])} tables agree across pyarrow, pandas, DuckDB and polars")
