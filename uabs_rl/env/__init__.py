"""The world the UABS fly in (docs/model.md §1-5): lattice geometry, the 3GPP channel
models behind a registry, links and beams, service and priorities, and ``UABSEnv``, the
batched TorchRL env that replays the traces."""
