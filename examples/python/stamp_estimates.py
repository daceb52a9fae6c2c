"""Stamp an estimates file with the simulation it was made from (pyarrow).

    python3 examples/python/stamp_estimates.py SIM estimates.parquet

`kfmc score` warns about, and `kfmc check` refuses, an estimates file without a stamp: the two
file-level metadata keys `kfmc.world_stamp` and `kfmc.master_seed`, whose values are the
`world_stamp` and `master_seed` of the simulation's manifest.toml. The five lines of `stamp`
are all a writer needs; the rest is the command line.
"""

import pathlib
import sys
import tomllib

import pyarrow.parquet as pq


def stamp(sim, path):
    m = tomllib.loads(pathlib.Path(sim, "manifest.toml").read_text())
    t = pq.read_table(path)
    keys = {"kfmc.world_stamp": m["world_stamp"], "kfmc.master_seed": str(m["master_seed"])}
    t = t.replace_schema_metadata({**(t.schema.metadata or {}), **keys})
    pq.write_table(t, path)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    stamp(sys.argv[1], sys.argv[2])
