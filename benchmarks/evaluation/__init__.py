"""Evaluation: metrics, protocols, LPIPS and the `wtbench eval` harness over run folders."""
