"""Anti-collision (docs/model.md §6): the masking rules (:mod:`~uabs_rl.safety.rules`:
one rule class per mode, plain tensor math, and how reports name the modes), the TorchRL
transform and action selector that apply them (:mod:`~uabs_rl.safety.modules`), and the
factory that builds an env with its rule (:mod:`~uabs_rl.safety.make`).

The rules' registry and the report wording are importable from here without the
TorchRL modules."""

from uabs_rl.safety.rules import (
    PAPER_ORDER,
    RULES,
    MaskingRule,
    make_rule,
    masks_collisions,
    mode_phrase,
    register,
)

__all__ = ["PAPER_ORDER", "RULES", "MaskingRule", "make_rule", "masks_collisions",
           "mode_phrase", "register"]
