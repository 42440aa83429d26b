"""NVIDIA-LS: build the long-sequence NVIDIA Dynamic Scene benchmark from raw multi-view captures."""
