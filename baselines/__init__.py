"""Methods other than WorldTree (static 3DGS, Base, ...), each registered by name with its config."""
