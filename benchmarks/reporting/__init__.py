"""Reporting: result records, tables, speed-vs-error plots and videos of finished runs."""
