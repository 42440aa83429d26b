"""Reporting: result records, tables, speed-vs-error plots, videos and the results site of finished runs."""
