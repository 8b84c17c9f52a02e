"""What accuracy costs in time: SH inverse lighting over lmax x samples x dtype x device x solver.

Same as ``brdfcap bench`` (see :mod:`brdfcap.baselines` for the scene, the error measure and
the Adam-through-renderer baseline). Examples::

    python bench/accuracy_time.py                 # default grid, a few minutes on 2 cores
    python bench/accuracy_time.py --full          # adds 10^6 samples and the costly cells
    python bench/accuracy_time.py --out bench-out --lmax 2,8 --samples 1000,10000

Writes ``bench.json``, ``bench.csv``, ``bench.md`` (the tables), ``pareto.png`` and a
self-contained ``bench.html`` into ``--out``; prints the tables.
"""

from __future__ import annotations

import sys

from brdfcap.cli.bench import bench_cmd

if __name__ == "__main__":
    sys.argv[0] = "bench/accuracy_time.py"
    bench_cmd(prog_name="brdfcap bench")
