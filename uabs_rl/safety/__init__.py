"""Anti-collision (docs/model.md §6): the masking rules, the TorchRL transform and
action selector that apply them, and the factory that builds an env with its rule."""
