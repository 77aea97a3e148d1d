"""The memory a run may use, and the refusal of what cannot fit in it: the machine's
(or a CUDA device's) free memory, read once per check, and the traces' size."""

from __future__ import annotations

import os

from uabs_rl.config.base import ConfigError
from uabs_rl.config.schema import ScenarioConfig, SplitConfig


def trace_bytes(scenario: ScenarioConfig, split: SplitConfig) -> int:
    """A lower bound on one split's traces (``uabs_rl.traces.cache.TraceSet``: float32 x, y
    and a bool per vehicle slot and step), counting the fleet's vehicles only."""
    steps = int(split.duration_s // scenario.dt)
    return split.n_sims * steps * scenario.sumo.fleet_size * (2 * 4 + 1)


def available_memory(device: str) -> tuple[int, str] | None:
    """``(bytes, where)``: the memory a run on ``device`` can use (a CUDA device's free
    memory, else the machine's MemAvailable from /proc/meminfo, else os.sysconf), or
    None where it cannot be read (then nothing is refused)."""
    if device != "cpu":
        import torch

        if torch.cuda.is_available():
            try:
                dev = torch.device("cuda" if device == "auto" else device)
                return torch.cuda.mem_get_info(dev)[0], f"{dev} has"
            except (RuntimeError, AssertionError, ValueError):
                return None  # no such device: refused where the device is resolved
        if device != "auto":
            return None  # cuda without CUDA: refused where the device is resolved
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "this machine has"
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "this machine has"
    except (ValueError, OSError, AttributeError):
        return None


def size_text(n: int) -> str:
    """``n`` bytes for a reader: 512 bytes, 1.5 GiB, ..."""
    x, unit = float(n), "bytes"
    for bigger in ("KiB", "MiB", "GiB", "TiB"):
        if x < 1024:
            break
        x, unit = x / 1024, bigger
    return f"{n} bytes" if unit == "bytes" else f"{x:.4g} {unit}"


def check_fits(setting: str, need: int, what: str, have: tuple[int, str] | None,
               fix: str) -> None:
    """Refuse ``setting`` when ``what`` needs more than ``have`` (``available_memory``)."""
    if have is not None and need > have[0]:
        raise ConfigError(f"{setting}: {what} would need at least {size_text(need)}, but "
                          f"{have[1]} {size_text(have[0])} available: {fix}.")


