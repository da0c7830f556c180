"""How fast this machine runs right now, recorded with every benchmark so that runs can be compared.

The 2-core machines these benchmarks run on change speed by up to about three times from hour to hour (the
figures in docs/benchmarks.md), so a service figure alone does not say whether the service or the machine moved.
Each benchmark therefore times one fixed workload at its start and at its end: the served I2S assignment and
alignment files run alone by onnxruntime, one intra-op thread, in chunks of 8 windows as the service runs them,
no HTTP, nothing else of ours. ``per_core_windows_per_s`` is that rate; a service figure divided by it (times the
cores the service uses) is what the service makes of the machine, comparable across states.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np

from service.inference.registry import load_model, newest_version_dir

REFERENCE_MODELS = ("i2s_assignment", "i2s_alignment")
WINDOWS, CHUNK, RUNS = 256, 8, 3


def reference_rate(models_dir: Path) -> dict:
    """The newest I2S files under ``models_dir`` alone on one core: windows per second over ``WINDOWS`` windows (the
    best of ``RUNS`` runs, so a moment's interruption does not count), and which versions ran. Without them the
    rate is None and ``missing`` names them: a benchmark's own results are never lost to its reference."""
    dirs = {name: newest_version_dir(models_dir, name) for name in REFERENCE_MODELS}
    missing = [name for name, d in dirs.items() if d is None]
    if missing:
        return {"per_core_windows_per_s": None, "missing": missing}
    models = [load_model(d, threads=1) for d in dirs.values()]  # as the service loads them, one thread each
    rng = np.random.default_rng(0)
    x = rng.normal(size=(WINDOWS, 128, 6)).astype(np.float32)
    x[..., 2] += 9.81
    chunks = [x[i : i + CHUNK] for i in range(0, WINDOWS, CHUNK)]
    for m in models:  # warm-up
        m.run(chunks[0])
    best = float("inf")
    for _ in range(RUNS):
        start = time.perf_counter()
        for m in models:
            for chunk in chunks:
                m.run(chunk)
        best = min(best, time.perf_counter() - start)
    return {
        "per_core_windows_per_s": round(WINDOWS / best, 1),
        "models": {name: d.name for name, d in dirs.items()},
    }


def machine_state(models_dir: Path, when: str) -> dict:
    """What the machine is and how fast it runs now (``when``: "start" or "end" of the benchmark)."""
    return {
        "when": when,
        "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
        **reference_rate(models_dir),
    }
