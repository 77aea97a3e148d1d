"""Vehicle traces: SUMO runs (through libsumo, one subprocess each) recorded once into
cached, checksummed tensors per split (train, eval, test).

Three rooms: :mod:`~uabs_rl.traces.inputs` (the SUMO files a scenario names, the
network netgenerate builds), :mod:`~uabs_rl.traces.cache` (``TraceSet``, the cache key,
the checked files) and :mod:`~uabs_rl.traces.build` (the worker processes, SUMO's
errors, ``get_traces``: the cache or a build); :mod:`~uabs_rl.traces.sumo_sim` is one
simulation, in its worker.

Every public name is importable from here too. They load on first use: a SUMO worker
(``python -m uabs_rl.traces.sumo_sim``) imports this package and must start without
torch."""

from __future__ import annotations

import importlib

_HOMES = {
    "inputs": ("check_area_contains_network", "net_file", "netgenerate_path", "read_net",
               "scenario_inputs", "split_begin", "sumocfg_inputs"),
    "cache": ("FORMAT_VERSION", "CacheFolderError", "TraceCacheError", "TraceSet",
              "cache_dir", "cache_path", "check_cache_dir", "load_cached", "load_traceset",
              "save_traceset", "split_key"),
    "build": ("SPLITS", "WORK_PREFIX", "TracesInterrupted", "build_split",
              "check_has_vehicles", "check_names", "get_traces", "remove_stale_work_folders",
              "stack_cities", "thinning", "training_traces"),
}
_MODULE_OF = {name: module for module, names in _HOMES.items() for name in names}
__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
