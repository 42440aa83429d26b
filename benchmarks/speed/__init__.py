"""Speed and proof scripts (`python -m benchmarks.speed.<name>`); they print figures, tests never time."""
