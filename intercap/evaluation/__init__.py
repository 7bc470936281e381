"""Judging results: metrics against ground truth (`evaluate`), the table and JSON that
`intercap eval` prints and writes. Reads results folders and sessions; imports no stage."""
from intercap.evaluation.evaluate import EvalResult, evaluate
from intercap.evaluation.table import format_table, write_json

__all__ = ["EvalResult", "evaluate", "format_table", "write_json"]
