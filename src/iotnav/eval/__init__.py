"""Evaluation: error statistics against truth, studies, computational cost."""
