"""Training of the embedded default depth network (optional ``[train]`` extra: torch).

Nothing in the runtime imports this package; it needs torch. See docs/training.md.
"""
