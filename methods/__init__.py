"""The methods the benchmark runs (static 3DGS, Base, WorldTree), each registered by name with its config."""
