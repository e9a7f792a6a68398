"""labctl.records — run records (``runs/<timestamp>/``), their event logs and reports."""

from .record import RecordError, RunData, RunRecord, load_run, read_events, to_jsonable
from .report import write_report

__all__ = ["RecordError", "RunData", "RunRecord", "load_run", "read_events", "to_jsonable", "write_report"]
