"""Evaluation harness (metrics, protocols, LPIPS), the `wtbench` CLI, run folders and speed scripts."""
