"""Training of the embedded default depth network (torch; ``pip install -e "research/[train]"``).

Nothing in the runtime imports this package; it needs torch. See docs/training.md.
"""
