"""Metrics, benchmark runners, figures and reports."""
