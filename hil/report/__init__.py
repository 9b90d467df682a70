"""Run results: summary.json, timeseries.npz and the self-contained report.html."""

from hil.report.html import render_report_html, write_report_html
from hil.report.summary import read_summary, write_summary
from hil.report.timeseries import read_timeseries, write_timeseries

__all__ = [
    "read_summary",
    "read_timeseries",
    "render_report_html",
    "write_report_html",
    "write_summary",
    "write_timeseries",
]
