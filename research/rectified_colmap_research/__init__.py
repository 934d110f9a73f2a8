"""Research side of rectified-colmap: what builds, trains and measures the runtime package
but is not installed with it (``pip install -e research/``).

- ``training``: the depth network (torch), its data (renders, real photos) and held-out
  measures; docs/training.md.
- ``evaluation``: evaluation helpers the runtime CLI does not use (method variants, plane
  pairs from SfM models, COLMAP-executable SfM runs, match-source accounting,
  LightGlue orientations).

The scripts that drive them are in research/scripts/ (docs/evaluation.md, docs/benchmarks.md).
"""
