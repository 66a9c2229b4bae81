"""The machine description every benchmark and report prints beside its figures."""
from __future__ import annotations

import os
import platform


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_info() -> dict:
    import torch

    try:
        load = list(os.getloadavg())
    except (OSError, AttributeError):
        load = None
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "usable_cores": usable, "torch": torch.__version__,
            "threads": torch.get_num_threads(), "load_average": load}


def machine_line() -> str:
    m = machine_info()
    load = "n/a" if m["load_average"] is None else "%.2f %.2f %.2f" % tuple(m["load_average"])
    return (f"machine: {m['cpu']}, {m['cores']} cores ({m['usable_cores']} usable), torch {m['torch']}, "
            f"{m['threads']} torch threads, load average {load}")
