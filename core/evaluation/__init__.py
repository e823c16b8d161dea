"""`dgs eval`: a run scored on its held-out views (`run.evaluate_run`, RUN/eval.json)."""

from core.evaluation.run import evaluate_run

__all__ = ["evaluate_run"]
