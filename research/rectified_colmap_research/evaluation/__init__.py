"""Evaluation helpers of the research scripts (not used by the runtime CLI)."""
