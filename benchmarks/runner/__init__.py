"""The runner: run folders (train + evaluate one method on one scene), sweeps, and `--set` config overrides."""
