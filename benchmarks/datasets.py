"""Seconds to make 1M transitions of the built-in datasets, stated at the reference host's speed.

    python benchmarks/datasets.py                        # 20K transitions of each MuJoCo env, 10K AntMaze
    python benchmarks/datasets.py --size 50000 --names hopper-medium antmaze-umaze

Each dataset is made (one process) into a temporary folder with ``size`` transitions; the host's
probe (``eabc.timing.probe_gflops``) is taken right before and after. A figure at the reference
host's speed is the seconds here times probe here / the reference probe, which is what
``eabc.timing.DATASET_SECONDS_PER_1M`` holds (per family, the range over the names measured).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

NAMES = ("hopper-medium", "halfcheetah-medium", "walker2d-medium", "antmaze-umaze")


def measure(name: str, size: int, folder: Path) -> float:
    """Seconds to make ``size`` transitions of ``name``."""
    from eabc.data import generate

    start = time.perf_counter()
    generate.make(name, folder / f"{name}.hdf5", seed=0, size=size)
    return time.perf_counter() - start


def main() -> None:
    from eabc import timing

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=None, help="transitions per dataset")
    parser.add_argument("--names", nargs="+", default=list(NAMES))
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for name in args.names:
            size = args.size or (10_000 if name.startswith("antmaze") else 20_000)
            before = timing.probe_gflops()
            seconds = measure(name, size, Path(folder))
            probe = (before + timing.probe_gflops()) / 2
            here = seconds / size * 1e6
            reference = here * probe / timing.REFERENCE_PROBE_GFLOPS
            rows.append((name, size, seconds, probe, here, reference))
    print(f"{'dataset':20s} {'size':>7s} {'seconds':>8s} {'probe GFLOP/s':>13s} "
          f"{'s per 1M here':>13s} {'s per 1M at reference':>21s}")  # fmt: skip
    for name, size, seconds, probe, here, reference in rows:
        print(f"{name:20s} {size:7d} {seconds:8.1f} {probe:13.1f} {here:13.0f} {reference:21.0f}")
    print(f"stated now (eabc.timing.DATASET_SECONDS_PER_1M): {timing.DATASET_SECONDS_PER_1M}")


if __name__ == "__main__":
    main()
