"""The benchmark harness: evaluation (metrics, protocols, LPIPS), the runner (run folders, sweeps, overrides),
reporting (tables, plots, videos), speed scripts, and the `wtbench` CLI."""
